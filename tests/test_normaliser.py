"""The exact normaliser of the elastic prior (bayesreg.fem.normaliser)."""

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.fem.element import stiffness_matrix
from bayesreg.sampling.kernels.target import make_target
from bayesreg.fem.normaliser import SAFE_RATIO
from bayesreg.model.parameters import ParamLayout
from bayesreg.model.posterior import (
    build_posterior, elastic_groups, log_normaliser, log_normaliser_dense, normaliser_surrogate,
    surrogate_normaliser)
from bayesreg.inference.targets import logdensity_fn
from helpers import box_posterior, sample_gibbs


def _dense_schur(mesh, post, phi):
    """Dense Schur complement ``S`` ``(3 n_b, 3 n_b)`` of ``K`` on the boundary DOFs (NumPy,
    boundary nodes in ``mesh.boundary`` order)."""
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, jnp.asarray(phi)))
    g = np.asarray(post.group)
    k = stiffness_matrix(mesh.nodes, mesh.tets, lam_g[g], mu_g[g]).toarray()
    b = np.asarray(mesh.boundary)
    i = np.setdiff1d(np.arange(len(mesh.nodes)), b)
    bd = (3 * b[:, None] + np.arange(3)).ravel()
    idf = (3 * i[:, None] + np.arange(3)).ravel()
    return k[np.ix_(bd, bd)] - k[np.ix_(bd, idf)] @ np.linalg.solve(k[np.ix_(idf, idf)], k[np.ix_(idf, bd)])


def _schur_pdet(mesh, post, phi):
    """(1/2) sum log of the non-zero eigenvalues of the dense Schur complement (NumPy)."""
    ev = np.linalg.eigvalsh(_dense_schur(mesh, post, phi))
    assert np.all(np.abs(ev[:6]) < 1e-8 * ev[-1])  # the six rigid-body modes
    return 0.5 * np.sum(np.log(ev[6:]))


def test_normaliser_equals_half_log_pseudo_determinant_of_the_schur_complement(small):
    mesh, post, theta = small
    phi = theta[-5:]
    for scale in (1.0, 0.3):
        p = phi * np.array([scale, 1, 1, scale, 1])
        assert float(log_normaliser(post, jnp.asarray(p))) == pytest.approx(_schur_pdet(mesh, post, p), rel=1e-10)


def test_normaliser_gradient_matches_finite_differences(small):
    _, post, theta = small
    phi = jnp.asarray(theta[-5:])
    f = jax.jit(lambda p: log_normaliser(post, p))
    g = np.asarray(jax.grad(f)(phi))
    for j in range(5):
        e = np.zeros(5)
        e[j] = 1e-5 * float(phi[j])
        fd = (float(f(phi + e)) - float(f(phi - e))) / (2 * e[j])
        assert g[j] == pytest.approx(fd, rel=1e-6)


def _element_posterior(small):
    """The box posterior of ``small`` with a Lamé pair per element (the per-element model)."""
    mesh, post, _ = small
    m = len(mesh.tets)
    layout = ParamLayout(tuple(f"e{k}" for k in range(m)),
                         free=tuple(("lam", k) for k in range(m)) + tuple(("mu", k) for k in range(m)),
                         fixed=())
    rng = np.random.default_rng(4)
    phi = np.r_[rng.uniform(1.0, 40.0, m), rng.uniform(0.5, 3.0, m)]
    el = build_posterior(mesh, post.similarity, _skull_image(), t_s=0.5, t_r=3.0, layout=layout,
                         element_group=np.arange(m), prior={"lam": (1, 1, 0, 100), "mu": (1, 1, 0, 10)},
                         phi_ref=phi)
    return el, phi


def _skull_image():
    """No skull, on the box posterior's grid."""
    from bayesreg.data.images import Image

    affine = np.eye(4)
    affine[:3, 3] = -9.0
    return Image(np.zeros((48, 48, 48), np.uint8), affine)


@pytest.mark.parametrize("model", ["tissue", "uniform", "element", "every node"])
def test_sparse_normaliser_equals_the_dense_reference_in_value_and_gradient(small, model):
    """The sparse normaliser (two CHOLMOD factorisations with six grounded DOFs, gradient by
    selected inversion) equals the dense reference (one dense Cholesky factorisation of ``K``
    with the rigid modes lifted, differentiated by JAX) to 1e-10 in value and 1e-8 in
    gradient, for the tissue, uniform and per-element models and with every node sampled
    (no interior block)."""
    mesh, post, theta = small
    phi = jnp.asarray(theta[-5:]) * jnp.array([1.3, 0.7, 1.1, 2.0, 0.8])
    if model == "uniform":
        layout = ParamLayout(("all",), free=(("lam", 0), ("mu", 0)), fixed=())
        post = build_posterior(mesh, post.similarity, _skull_image(), t_s=0.5, t_r=3.0, layout=layout,
                               element_group=np.zeros(len(mesh.tets), np.int64),
                               prior={"lam": (1, 1, 0, 100), "mu": (1, 1, 0, 10)}, phi_ref=[12.0, 1.5])
        phi = jnp.array([17.0, 2.5])
    elif model == "element":
        post, phi = _element_posterior(small)
        phi = jnp.asarray(phi)
        assert post.normaliser.grounded.unit is None  # the element map, not unit matrices
    elif model == "every node":
        prior = {"lam": (2.0, 3.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
        _, post, theta = box_posterior(prior, 3.0, np.array([5.0, 10.0, 30.0, 2.0, 1.5]), every_node=True)
        phi = jnp.asarray(theta[-5:])
        assert post.normaliser.interior.n == 0
    sparse = jax.jit(lambda p: log_normaliser(post, p))
    dense = jax.jit(lambda p: log_normaliser_dense(post, p))
    assert float(sparse(phi)) == pytest.approx(float(dense(phi)), rel=1e-10)
    gs, gd = np.asarray(jax.grad(sparse)(phi)), np.asarray(jax.grad(dense)(phi))
    np.testing.assert_allclose(gs, gd, rtol=1e-8, atol=1e-8 * np.abs(gd).max())


def test_a_failed_factorisation_rejects_the_position(small):
    """Parameters the sparse factorisation must not see (non-positive, non-finite, or below
    ``SAFE_RATIO`` of the largest: a stiffness singular to round-off) give a NaN normaliser
    without reaching CHOLMOD (which would stop the program), and the posterior's log-density
    with the exact normaliser rejects the position (``-inf``); a valid position is finite."""
    mesh, post, theta = small
    f = jax.jit(lambda p: log_normaliser(post, p))
    phi = theta[-5:].copy()
    for bad in (-1.0, 0.0, np.nan, np.inf, 0.1 * SAFE_RATIO * 30.0):
        p = phi.copy()
        p[0] = bad
        assert np.isnan(float(f(jnp.asarray(p)))), bad
    lp = jax.jit(logdensity_fn(post, exact=True))
    interior = jnp.zeros((post.op.n_interior, 3))
    assert np.isfinite(float(lp(jnp.asarray(theta), interior)[0]))
    # inside the posterior's own support (mu_csf > 0) but singular to round-off: rejected
    t = theta.copy()
    t[-2] = 1e-17  # mu_csf
    assert float(lp(jnp.asarray(t), interior)[0]) == -np.inf


def test_the_surrogate_is_exact_at_its_centre_and_close_around_it(small):
    """The normaliser's surrogate (eigenvector part, axis interpolants, mixed derivatives)
    equals the exact value at its centre, its gradient there within 1e-3, and stays within
    0.1 of the exact value where the parameters move by 15% (a posterior's width) and along
    an axis across a factor of 30 (a parameter the images do not identify)."""
    _, post, theta = small
    phi0 = jnp.asarray(theta[-5:])
    s = normaliser_surrogate(post, phi0)
    exact = jax.jit(lambda p: log_normaliser(post, p))
    sur = jax.jit(lambda p: surrogate_normaliser(post, s, p))
    assert float(sur(phi0)) == pytest.approx(float(exact(phi0)), rel=1e-12)
    ge, gs = np.asarray(jax.grad(exact)(phi0)), np.asarray(jax.grad(sur)(phi0))
    np.testing.assert_allclose(gs, ge, rtol=1e-3, atol=1e-3 * np.abs(ge).max())
    rng = np.random.default_rng(2)
    for _ in range(10):
        p = phi0 * jnp.exp(rng.normal(0.0, 0.15, 5))
        assert abs(float(sur(p)) - float(exact(p))) < 0.1
    for factor in (1 / 30, 30.0):
        p = phi0.at[0].multiply(factor)  # lam_csf from 1/30 to 30
        assert abs(float(sur(p)) - float(exact(p))) < 0.1, factor
    assert np.all(np.isfinite(np.asarray(jax.grad(sur)(phi0.at[0].multiply(1e3)))))  # beyond its range


# the prior-recovery test: Beta(2, 3) on [1, 50] for lam, uniform on [0.5, 5] for mu (away
# from zero, where a void tissue would let the hard constraints truncate the prior of u_b)
PRIOR_RECOVERY = {"lam": (2.0, 3.0, 1.0, 50.0), "mu": (1.0, 1.0, 0.5, 5.0)}


def _prior_only_target(exact: bool, t_r=0.01, tau=0.05):
    """The box posterior with the image term off and the six rigid-body modes of ``u_b``
    anchored by ``-|R_b^T u_b|^2 / (2 tau^2)`` (``R_b`` orthonormal, ``S R_b = 0``).

    Then ``p(u_b | phi)`` is a proper Gaussian with precision ``S / T_r + R_b R_b^T / tau^2``,
    whose determinant is ``pdet(S / T_r) tau^-12``: under the exact normaliser the marginal of
    the elastic parameters is their prior, exactly; under the paper's it is the prior times
    ``pdet S(phi)^(-1/2)``, which favours soft tissue (Sec. 3.3)."""
    phi_ref = np.array([20.0, 20.0, 20.0, 2.0, 2.0])
    mesh, post, _ = box_posterior(PRIOR_RECOVERY, t_r, phi_ref)
    post = post._replace(inv_t_s=jnp.zeros_like(post.inv_t_s))
    nb3 = 3 * post.n_boundary
    rb = np.asarray(post.normaliser.rigid_b)
    prec = _dense_schur(mesh, post, phi_ref) / t_r + rb @ rb.T / tau**2
    factor = np.linalg.inv(np.linalg.cholesky(prec)).T  # u_b = F w, F F^T = prec^-1 at phi_ref
    tg = make_target(post, center_u=np.zeros(nb3), factor=factor, exact=exact, condensed=True)
    r = jnp.asarray(rb)

    def anchor(w, eta):
        return -0.5 * jnp.sum((r.T @ tg.position(w, eta)[:nb3]) ** 2) / tau**2

    def u_evaluate(w, eta, cache, interior):
        lp, *rest = tg.u_evaluate(w, eta, cache, interior)
        return (lp + anchor(w, eta), *rest)

    def evaluate(w, eta, interior, ln, precond=None):
        lz, lnat, *rest = tg.evaluate(w, eta, interior, ln, precond)
        a = anchor(w, eta)
        return (lz + a, lnat + a, *rest)

    target = tg._replace(u_logdensity=lambda w, eta, c, i: u_evaluate(w, eta, c, i)[0],
                         u_evaluate=u_evaluate, evaluate=evaluate)
    return post, target, factor


@pytest.mark.parametrize("exact", [True, pytest.param(False, marks=pytest.mark.heavy)])
def test_exact_normaliser_returns_the_prior_when_the_images_say_nothing(exact):
    """With ``T_s = infinity`` (no image term) the posterior of the elastic parameters is
    their prior if and only if the elastic prior on ``u_b`` is normalised: the NUTS-within-
    Gibbs sampler (condensed, logit parameters with their Jacobian) recovers the Beta(2, 3)
    and uniform marginals within 5 Monte Carlo standard errors under ``exact``, while the
    paper's unnormalised prior drags every parameter toward its lower bound, more than 10
    Monte Carlo standard errors below the prior mean."""
    post, target, factor = _prior_only_target(exact)
    nb3 = 3 * post.n_boundary
    rng = np.random.default_rng(5)
    n_chains = 4
    lam0 = 1.0 + 49.0 * rng.beta(2.0, 3.0, size=(n_chains, 3))
    mu0 = rng.uniform(0.5, 5.0, size=(n_chains, 2))
    u0 = (factor @ rng.normal(size=(nb3, n_chains))).T
    x0 = np.concatenate([u0, lam0, mu0], axis=1)
    # the paper's collapse is gross: a short run shows it
    warmup, draws, chunk = (250, 1000, 250) if exact else (50, 100, 50)
    res = sample_gibbs(jax.random.key(11), target, x0, jnp.zeros((post.op.n_interior, 3)), kind="nuts",
                          step_size=0.5, eta_scale=0.5, max_tree_depth=4, elastic_moves=8,
                          warmup_steps=warmup, max_draws=draws, min_draws=draws, chunk_draws=chunk,
                          progress=False)
    phi = res.positions[..., nb3:]  # (C, n, 5): lam csf, gm, wm; mu csf, wm
    mean_true = np.r_[np.full(3, 1.0 + 49.0 * 0.4), np.full(2, 2.75)]
    sd_true = np.r_[np.full(3, 49.0 * 0.2), np.full(2, 4.5 / np.sqrt(12.0))]
    ess = np.array([float(az.ess(phi[..., j], method="bulk")) for j in range(5)])
    z = (phi.reshape(-1, 5).mean(axis=0) - mean_true) / (sd_true / np.sqrt(ess))
    if exact:
        assert np.all(ess > 60), ess
        assert np.all(np.abs(z) < 5), (z, ess)
        sd = phi.reshape(-1, 5).std(axis=0)
        assert np.all(np.abs(sd / sd_true - 1) < 5 * np.sqrt(1.0 / ess)), (sd / sd_true, ess)
    else:
        assert np.all(z < -10), (z, ess)  # every parameter pushed down, far beyond Monte Carlo error


def test_the_host_route_of_the_sparse_factorisation_equals_the_direct_one(small):
    """On a backend without sparsax's handlers (a GPU) the factorisation runs on the host by
    ``jax.pure_callback`` with a ``custom_vjp`` (``sparse_logdet(host=True)``): here on the
    CPU it gives the direct call's value and selected-inverse gradient, inside ``jit`` and
    under ``vmap`` (chains mapped together), and an indefinite matrix still fails loudly."""
    _, post, theta = small
    from bayesreg.fem.normaliser import _flat, _values, sparse_logdet

    data, op = post.normaliser, post.op
    kl, km = _flat(op.klam), _flat(op.kmu)
    g = np.asarray(post.group)
    n_g = int(g.max()) + 1
    pattern = data.interior

    def values(theta_g):
        return _values(pattern, kl, km, theta_g[:n_g], theta_g[n_g:], post.group)

    rng = np.random.default_rng(0)
    thetas = jnp.asarray(rng.uniform(0.5, 20.0, (3, 2 * n_g)))
    direct = jax.jit(jax.vmap(jax.value_and_grad(lambda t: sparse_logdet(pattern, values(t), host=False))))
    hosted = jax.jit(jax.vmap(jax.value_and_grad(lambda t: sparse_logdet(pattern, values(t), host=True))))
    (vd, gd), (vh, gh) = direct(thetas), hosted(thetas)
    np.testing.assert_allclose(np.asarray(vh), np.asarray(vd), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(gh), np.asarray(gd), rtol=1e-10, atol=1e-12 * np.abs(gd).max())
    assert np.all(np.asarray(gd) > 0)  # d log det / d theta_t = tr(K^-1 K_t) > 0
    bad = values(thetas[0]).at[pattern.diag[0]].set(-1e6)
    with pytest.raises(jax.errors.JaxRuntimeError):
        float(jax.jit(lambda v: sparse_logdet(pattern, v, host=True))(bad))
