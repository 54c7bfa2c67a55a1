"""The exact normaliser of the elastic prior (bayesreg.normaliser)."""

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.fem import stiffness_matrix
from bayesreg.kernels.target import make_target
from bayesreg.posterior import elastic_groups, log_normaliser
from bayesreg.sampler import sample_gradient
from helpers import box_posterior


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


@pytest.mark.parametrize("exact", [True, False])
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
    res = sample_gradient(jax.random.key(11), target, x0, jnp.zeros((post.op.n_interior, 3)), kind="nuts",
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
