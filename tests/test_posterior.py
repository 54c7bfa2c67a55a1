"""The log-density: hard constraints give -inf; gradients match finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi

from bayesreg.fem import element as fem
from bayesreg.data.images import Image
from bayesreg.sampling.kernels.rwmh import (ACCEPT_SCOPE, CACHE_SCOPE, PROPOSAL_SCOPE, Preconditioner, build_kernel,
                                   init)
from bayesreg.model.parameters import ParamLayout, from_unconstrained, to_unconstrained
from bayesreg.model.posterior import (SCOPES, build_posterior, condensation, elastic_groups, full_displacement,
                                log_density, log_density_condensed, preconditioner, split_position)
from bayesreg.model.similarity import build_ssd
from bayesreg.fem.solver import interior_map
from conftest import box_mesh
from helpers import box_posterior, log_p


def test_finite_at_valid_point_and_matches_energies(small):
    mesh, post, theta = small
    lp, aux = log_p(post, theta)
    assert np.isfinite(float(lp)) and bool(aux.solve.converged)
    # prior: Beta(2,3) on [0,100] for lam, uniform on [0,10] for mu
    from scipy import stats

    lam = theta[-5:-2]
    assert np.all((theta[-2:] > 0) & (theta[-2:] < 10))  # mu: the uniform density is constant there
    lprior = stats.beta(2, 3).logpdf(lam / 100).sum() - 3 * np.log(100) - 2 * np.log(10)
    expected = -float(aux.e_s) / 0.5 - float(aux.e_r) / 3.0 + lprior
    assert float(lp) == pytest.approx(expected, rel=1e-10)
    assert float(aux.e_r) > 0 and float(aux.e_s) > 0


def test_constraint_violations_give_minus_inf(small):
    mesh, post, theta = small
    nb3 = 3 * len(mesh.boundary)
    # a non-positive parameter
    t = theta.copy()
    t[nb3 + 3] = -0.1
    assert float(log_p(post, t)[0]) == -np.inf
    # outside the prior range [r1, r2]
    t = theta.copy()
    t[nb3] = 150.0
    assert float(log_p(post, t)[0]) == -np.inf
    # a boundary node moved into the skull (x > 36 mm)
    t = theta.copy()
    k = int(np.argmax(mesh.nodes[mesh.boundary, 0]))
    t[3 * k] = 8.0
    assert float(log_p(post, t)[0]) == -np.inf
    # an inverted element: push one corner through the opposite face
    t = theta.copy()
    corner = int(np.flatnonzero(np.all(mesh.nodes[mesh.boundary] == 0.0, axis=1))[0])
    t[3 * corner: 3 * corner + 3] = [25.0, 25.0, 25.0]
    assert float(log_p(post, t)[0]) == -np.inf


def test_parameters_outside_the_support_are_rejected_without_a_solve(small):
    """No CG iterations for a proposal whose parameters leave the prior support, alone or
    under vmap (where both branches of the cond run), and no solve failure counted."""
    mesh, post, theta = small
    nb3 = 3 * len(mesh.boundary)
    bad = theta.copy()
    bad[nb3 + 3] = -0.1
    warm = log_p(post, theta)[1].interior
    lp, aux = log_density(post, jnp.asarray(bad), warm)
    assert float(lp) == -np.inf and int(aux.solve.iterations) == 0 and bool(aux.solve.converged)
    np.testing.assert_array_equal(np.asarray(aux.interior), np.asarray(warm))
    lps, auxs = jax.jit(jax.vmap(lambda t: log_density(post, t, jnp.zeros_like(warm))))(jnp.asarray(np.stack([theta, bad])))
    assert np.isfinite(float(lps[0])) and float(lps[1]) == -np.inf
    assert int(auxs.solve.iterations[0]) > 0 and int(auxs.solve.iterations[1]) == 0
    assert np.all(np.asarray(auxs.solve.converged))


def test_dense_preconditioner_leaves_the_log_density_unchanged(small):
    """The preconditioner (built at other parameters) changes the CG's iterations, not the
    log-density nor the interior solution (same tolerance), nor its -inf cases."""
    mesh, post, theta = small
    nb3 = 3 * len(mesh.boundary)
    other = theta.copy()
    other[nb3:] *= np.array([1.3, 0.8, 1.2, 1.1, 0.7])
    pre = preconditioner(post, jnp.asarray(other))
    assert not bool(pre.fallback)
    rng = np.random.default_rng(11)
    zero = jnp.zeros((post.op.n_interior, 3))
    for _ in range(3):
        t = theta.copy()
        t[:nb3] += 0.05 * rng.normal(size=nb3)
        t[nb3:] *= np.exp(0.1 * rng.normal(size=t.size - nb3))
        lp, aux = log_density(post, jnp.asarray(t), zero, rtol=1e-12)
        lpp, auxp = log_density(post, jnp.asarray(t), zero, rtol=1e-12, precond=pre)
        assert float(lpp) == pytest.approx(float(lp), rel=1e-12, abs=1e-9)
        np.testing.assert_allclose(np.asarray(auxp.interior), np.asarray(aux.interior), atol=1e-10)
        assert int(auxp.solve.iterations) < int(aux.solve.iterations)
    t = theta.copy()
    t[3 * int(np.argmax(mesh.nodes[mesh.boundary, 0]))] = 8.0  # into the skull
    assert float(log_density(post, jnp.asarray(t), zero, precond=pre)[0]) == -np.inf
    # outside the support the preconditioner is built at phi_ref (K_ii stays definite)
    t = theta.copy()
    t[nb3] = -1.0
    np.testing.assert_array_equal(np.asarray(preconditioner(post, jnp.asarray(t)).inverse),
                                  np.asarray(preconditioner(post, jnp.concatenate(
                                      [jnp.asarray(t[:nb3]), post.phi_ref])).inverse))


def test_nonconverged_solve_gives_minus_inf(small):
    _, post, theta = small
    lp, aux = log_density(post, jnp.asarray(theta), jnp.zeros((post.op.n_interior, 3)), maxiter=2)
    assert not bool(aux.solve.converged) and float(lp) == -np.inf


def test_gradient_finite_and_equal_to_finite_differences(small):
    _, post, theta = small
    f = jax.jit(lambda th: log_p(post, th)[0])
    g = np.asarray(jax.grad(f)(jnp.asarray(theta)))
    assert np.all(np.isfinite(g))
    rng = np.random.default_rng(5)
    for _ in range(3):
        d = rng.normal(size=theta.shape)
        d[-5:] *= 0.1
        h = 1e-6
        fd = (float(f(theta + h * d)) - float(f(theta - h * d))) / (2 * h)
        assert float(g @ d) == pytest.approx(fd, rel=1e-4, abs=1e-6)
    # derivative with respect to one elastic parameter alone (through K_ii in the solve)
    e = np.zeros_like(theta)
    e[-4] = 1.0
    h = 1e-5
    fd = (float(f(theta + h * e)) - float(f(theta - h * e))) / (2 * h)
    assert g[-4] == pytest.approx(fd, rel=1e-4)


def test_split_position_is_node_major(small):
    mesh, post, theta = small
    u_b, phi = split_position(post, jnp.asarray(theta))
    assert u_b.shape == (len(mesh.boundary), 3)
    assert float(u_b[1, 2]) == theta[3 * 1 + 2]
    assert phi.shape == (5,)


def test_position_shapes_are_checked_statically(small):
    """A position, warm start, map or parameter vector of the wrong shape is refused with its
    expected shape named (a theta 4 entries short is not broadcast).  The checks look at
    shapes only: under vmap they see one chain's theta, and out-of-support values still
    give -inf."""
    mesh, post, theta = small
    zero = jnp.zeros((post.op.n_interior, 3))
    dim = post.dim
    for bad in (theta[:-4], theta[:-1], np.r_[theta, 1.0]):
        with pytest.raises(ValueError, match=rf"theta must have shape \({dim},\) .*got \({len(bad)},\)"):
            log_density(post, jnp.asarray(bad), zero)
        with pytest.raises(ValueError, match=rf"theta must have shape \({dim},\)"):
            split_position(post, jnp.asarray(bad))
    with pytest.raises(ValueError, match=rf"theta must have shape \({dim},\) .*got \(2, {dim}\)"):
        log_density(post, jnp.asarray(np.stack([theta, theta])), zero)  # a batch needs vmap
    with pytest.raises(ValueError, match=rf"u_i0 must have shape \({post.op.n_interior}, 3\)"):
        log_density(post, jnp.asarray(theta), zero[:-1])
    with pytest.raises(ValueError, match=rf"theta must have shape \({dim},\)"):
        condensation(post, jnp.asarray(theta[:-4]))
    h = jax.eval_shape(condensation, post, jnp.asarray(theta))
    assert h.shape == (3 * post.op.n_interior, 3 * post.n_boundary)
    with pytest.raises(ValueError, match=r"h must have shape"):
        log_density_condensed(post, jnp.asarray(theta), jnp.zeros((h.shape[0], h.shape[1] - 3)))
    with pytest.raises(ValueError, match=r"phi must have shape \(\.\.\., 5\) .*got \(3, 1\)"):
        elastic_groups(post, jnp.ones((3, 1)))
    with pytest.raises(ValueError, match=r"eta must have shape \(\.\.\., 5\) .*got \(4,\)"):
        from_unconstrained(post.prior, jnp.zeros(4))
    with pytest.raises(ValueError, match=r"phi must have shape \(\.\.\., 5\)"):
        to_unconstrained(post.prior, jnp.ones(1))
    with pytest.raises(ValueError, match=rf"u_i must have shape \({post.op.n_interior}, 3\)"):
        full_displacement(post, jnp.zeros((post.n_boundary, 3)), zero[:-1])
    # vmapped over chains (traced, not compiled): one chain's shapes pass, a bad one raises
    thetas = jnp.asarray(np.stack([theta, theta]))
    lp = jax.eval_shape(jax.vmap(lambda th: log_density(post, th, zero)[0]), thetas)
    assert lp.shape == (2,)
    with pytest.raises(ValueError, match=rf"theta must have shape \({dim},\) .*got \({dim - 1},\)"):
        jax.eval_shape(jax.vmap(lambda th: log_density(post, th, zero)[0]), thetas[:, :-1])
    # values are not checked: a parameter outside the support still gives -inf under jit
    out = theta.copy()
    out[-1] = -1.0
    assert float(jax.jit(lambda th: log_density(post, th, zero)[0])(jnp.asarray(out))) == -np.inf


def test_bad_temperatures_and_priors_raise(small):
    mesh, post, _ = small
    from bayesreg.model.similarity import SSDTerm  # noqa: F401

    kw = dict(layout=ParamLayout(("all",), (("lam", 0),), (("mu", 0, 1.0),)),
              element_group=np.zeros(len(mesh.tets), int), prior={"lam": (1, 1, 0, 10), "mu": (1, 1, 0, 1)},
              phi_ref=[5.0])
    forb = Image(np.zeros((4, 4, 4), np.uint8), np.eye(4))
    with pytest.raises(ValueError, match="temperatures"):
        build_posterior(mesh, post.similarity, forb, t_s=0.0, t_r=1.0, **kw)
    with pytest.raises(ValueError, match="outside the prior support"):
        build_posterior(mesh, post.similarity, forb, t_s=1.0, t_r=1.0, **{**kw, "phi_ref": [50.0]})


def test_condensed_log_density_equals_the_solved_one(small):
    """u_i = H u_b from the dense condensation gives the CG log-density (and its -inf cases)."""
    mesh, post, theta = small
    h = condensation(post, jnp.asarray(theta))
    assert h.shape == (3 * len(mesh.interior), 3 * len(mesh.boundary))
    # H against the SciPy direct solve of K_ii H = -K_ib

    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, jnp.asarray(theta[-5:])))
    k = fem.stiffness_matrix(mesh.nodes, mesh.tets, lam_g[mesh.tissue], mu_g[mesh.tissue]).toarray()
    idf = (3 * mesh.interior[:, None] + np.arange(3)).ravel()
    bd = (3 * mesh.boundary[:, None] + np.arange(3)).ravel()
    ref = -np.linalg.solve(k[np.ix_(idf, idf)], k[np.ix_(idf, bd)])
    np.testing.assert_allclose(np.asarray(h), ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
    rng = np.random.default_rng(7)
    nb3 = 3 * len(mesh.boundary)
    for _ in range(3):  # moves of u_b only: the same parameters, the same map
        t = theta.copy()
        t[:nb3] += 0.2 * rng.normal(size=nb3)
        lp, aux = log_p(post, t)
        lpc, auxc = log_density_condensed(post, jnp.asarray(t), h)
        assert float(lpc) == pytest.approx(float(lp), rel=1e-10)
        np.testing.assert_allclose(np.asarray(auxc.interior), np.asarray(aux.interior), atol=1e-9)
    t = theta.copy()
    k_ = int(np.argmax(mesh.nodes[mesh.boundary, 0]))
    t[3 * k_] = 8.0  # into the skull
    assert float(log_density_condensed(post, jnp.asarray(t), h)[0]) == -np.inf
    # a failed factorisation (indefinite K_ii) is a rejection, not a number
    bad = interior_map(post.op, -jnp.ones(len(mesh.tets)), -jnp.ones(len(mesh.tets)), len(mesh.boundary))
    assert float(log_density_condensed(post, jnp.asarray(theta), bad)[0]) == -np.inf


def test_grouped_stiffness_blocks_give_the_element_assembled_log_density(small):
    """The per-group blocks (tissue model) and the per-element assembly are the same K."""
    _, post, theta = small
    assert post.unit_blocks is not None and post.unit_blocks.lam_ii[0].shape[0] == 3
    lp, aux = log_p(post, theta)
    lp_e, aux_e = log_p(post._replace(unit_blocks=None), theta)
    assert float(lp) == pytest.approx(float(lp_e), rel=1e-12)
    np.testing.assert_allclose(np.asarray(aux.interior), np.asarray(aux_e.interior), rtol=0, atol=1e-10)
    g = jax.grad(lambda th: log_p(post, th)[0])(jnp.asarray(theta))
    g_e = jax.grad(lambda th: log_p(post._replace(unit_blocks=None), th)[0])(jnp.asarray(theta))
    np.testing.assert_allclose(np.asarray(g), np.asarray(g_e), rtol=1e-8, atol=1e-8 * float(jnp.max(jnp.abs(g_e))))


def test_spectral_preconditioner_of_a_uniform_model_leaves_the_log_density_unchanged():
    """One parameter group: ``build_posterior(spectral=True)`` keeps the exact spectral
    preconditioner, which ``log_density`` uses by default: the same log-density and interior
    as block Jacobi at several ``lam``, in at most 2 CG iterations from zeros."""
    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    rng = np.random.default_rng(2)
    affine = np.diag([1.0, 1.0, 1.0, 1.0])
    affine[:3, 3] = -9.0
    f = Image(ndi.gaussian_filter(rng.random((48, 48, 48)), 2.0) * 4, affine)
    m = Image(np.roll(f.data, 1, axis=0), affine)
    forbidden = Image(np.zeros((48, 48, 48), np.uint8), affine)
    layout = ParamLayout(("all",), free=(("lam", 0),), fixed=(("mu", 0, 1.0),))
    kw = dict(t_s=0.5, t_r=3.0, layout=layout, element_group=np.zeros(len(mesh.tets), int),
              prior={"lam": (1.0, 1.0, 0.0, 1000.0), "mu": (1.0, 1.0, 0.0, 10.0)}, phi_ref=[5.0])
    ssd_term = build_ssd(mesh.nodes, mesh.tets, f, m)
    plain = build_posterior(mesh, ssd_term, forbidden, **kw)
    spec = build_posterior(mesh, ssd_term, forbidden, spectral=True, **kw)
    assert plain.spectral is None and spec.spectral is not None
    zero = jnp.zeros((plain.op.n_interior, 3))
    for lam in (0.5, 15.0, 900.0):
        t = jnp.asarray(np.concatenate([0.3 * rng.normal(size=3 * len(mesh.boundary)), [lam]]))
        lp, aux = log_density(plain, t, zero, rtol=1e-12)
        lps, auxs = log_density(spec, t, zero, rtol=1e-12)
        assert float(lps) == pytest.approx(float(lp), rel=1e-12)
        np.testing.assert_allclose(np.asarray(auxs.interior), np.asarray(aux.interior), atol=1e-10)
        assert int(auxs.solve.iterations) <= 2 < int(aux.solve.iterations)


def test_a_boundary_node_in_the_skull_is_rejected_without_a_solve(small):
    """The hard constraint on the boundary nodes is checked before the solve: no CG
    iteration and no energy for such a proposal (the paper's joint walk proposes many while
    nodes slide along the skull)."""
    mesh, post, theta = small
    warm = log_p(post, theta)[1].interior
    t = theta.copy()
    t[3 * int(np.argmax(mesh.nodes[mesh.boundary, 0]))] = 8.0  # into the skull (x > 36 mm)
    lp, aux = log_density(post, jnp.asarray(t), warm)
    assert float(lp) == -np.inf and int(aux.solve.iterations) == 0 and bool(aux.solve.converged)
    assert float(aux.e_s) == 0.0 and float(aux.e_r) == 0.0


def _tiny_posterior_args():
    """A one-cube mesh, its SSD term and valid keyword arguments of build_posterior (every
    check below raises before the FE assembly)."""
    mesh = box_mesh((1, 1, 1), size=(10.0, 10.0, 10.0))
    affine = np.eye(4)
    affine[:3, 3] = -2.0
    img = Image(np.full((14, 14, 14), 0.5), affine)
    kw = dict(t_s=1.0, t_r=1.0, layout=ParamLayout(("all",), (("lam", 0), ("mu", 0)), ()),
              element_group=np.zeros(len(mesh.tets), int),
              prior={"lam": (1.0, 1.0, 0.0, 10.0), "mu": (1.0, 1.0, 0.0, 5.0)}, phi_ref=[5.0, 1.0])
    return mesh, build_ssd(mesh.nodes, mesh.tets, img, img), Image(np.zeros((14, 14, 14), np.uint8), affine), kw


@pytest.mark.parametrize("change, match", [
    ({"prior": {"lam": (1.0, 1.0, 0.0, np.inf), "mu": (1.0, 1.0, 0.0, 5.0)}},
     r"invalid Beta prior of lam_all: need finite .* got \(A, B, r1, r2\) = \(1, 1, 0, inf\)"),
    ({"prior": {"lam": (np.nan, 1.0, 0.0, 10.0), "mu": (1.0, 1.0, 0.0, 5.0)}}, "invalid Beta prior of lam_all"),
    ({"prior": {"lam": (1.0, 1.0, 0.0, 10.0), "mu": (1.0, np.nan, 0.0, 5.0)}}, "invalid Beta prior of mu_all"),
    ({"prior": {"lam": (1.0, 1.0, 10.0), "mu": (1.0, 1.0, 0.0, 5.0)}},
     r"prior\['lam'\] must be \(A, B, r1, r2\) or one such tuple per group, shape \(1, 4\); got shape \(3,\)"),
    ({"prior": {"lam": [(1.0, 1.0, 0.0, 10.0)] * 3, "mu": (1.0, 1.0, 0.0, 5.0)}},
     r"prior\['lam'\] .* got shape \(3, 4\)"),
    ({"prior": {"lam": (1.0, 1.0, 0.0, 10.0)}}, "prior has no 'mu' entry .*mu_all"),
    ({"prior": [(1.0, 1.0, 0.0, 10.0)]}, "prior must be a dict"),
    ({"phi_ref": [np.nan, 1.0]}, r"phi_ref lie outside the prior support: lam_all=nan not in \(0, 10\)"),
    ({"phi_ref": [5.0]}, r"phi_ref must have shape \(2,\) .*got \(1,\)"),
    ({"forbidden": Image(np.zeros((14, 14), np.uint8), np.eye(4))}, r"forbidden must be 3D, got shape \(14, 14\)"),
    ({"forbidden": Image(np.zeros((14, 14, 14), np.uint8), np.zeros((4, 4)))}, "forbidden affine is singular"),
], ids=["r2-inf", "a-nan", "b-nan", "prior-length", "prior-groups", "prior-missing-mu", "prior-not-dict",
        "phi-nan", "phi-shape", "forbidden-2d", "forbidden-singular"])
def test_build_posterior_rejects_bad_priors_references_and_forbidden_images(change, match):
    mesh, ssd_term, forbidden, kw = _tiny_posterior_args()
    kw = {**kw, **change}
    forbidden = kw.pop("forbidden", forbidden)
    with pytest.raises(ValueError, match=match):
        build_posterior(mesh, ssd_term, forbidden, **kw)


def test_compiled_log_density_names_its_parts_for_the_profiler(small):
    """Every part of :data:`bayesreg.model.posterior.SCOPES` (and the kernel's proposal, accept
    and cache-build scopes) reaches the optimised program's metadata, where
    ``benchmarks/profile_step.py`` reads it to split a step's time."""
    mesh, post, theta = small
    zeros = jnp.zeros((post.op.n_interior, 3))

    def logdensity(x, guess):
        return log_density(post, x, guess, rtol=1e-8)

    kernel = build_kernel(logdensity)
    state = init(jnp.asarray(theta), logdensity, zeros)
    sigma = (jnp.full(theta.shape, 1e-3),)
    cache = kernel.init_cache(state)
    text = jax.jit(kernel.step).lower(jax.random.key(0), state, sigma, cache).compile().as_text()
    for scope in (*SCOPES.values(), PROPOSAL_SCOPE, ACCEPT_SCOPE):
        assert f"/{scope}/" in text, scope
    assert f"/{CACHE_SCOPE}/" not in text  # no cache: nothing built
    pre = Preconditioner(lambda x, guess, p: log_density(post, x, guess, rtol=1e-8, precond=p),
                         lambda x: preconditioner(post, x))
    cached = build_kernel(logdensity, preconditioner=pre)
    text = jax.jit(cached.init_cache).lower(state).compile().as_text()
    assert f"/{CACHE_SCOPE}/" in text  # each chain's K_ii^-1, built at every chunk start


def test_marginal_similarity_temperature_is_the_integral_over_its_gamma_prior():
    """With ``t_s_prior = (a, b)`` the similarity term is ``log int tau^(n/2) exp(-tau E_s)
    Gamma(tau; a, b) d tau`` up to a constant (SciPy quadrature over tau at two positions);
    the rest of ``log p`` is unchanged; and the Gauss-Newton weight is E[tau | E_s]."""
    from scipy.integrate import quad
    from scipy.special import gammaln

    from bayesreg.model.posterior import similarity_weight

    prior = {"lam": (1.0, 1.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
    phi = np.array([5.0, 5.0, 5.0, 1.0, 1.0])
    mesh, post, theta = box_posterior(prior, 3.0, phi)
    a, b = 2.0, 0.3
    marg = post._replace(t_s_shape=jnp.asarray(a + 0.5 * post.similarity.sqrt_w.size),
                         t_s_rate=jnp.asarray(b))
    n = post.similarity.sqrt_w.size

    def log_integral(e_s):
        shape = a + n / 2
        mode = (shape - 1) / (b + e_s)  # integrate exp(.) scaled at its mode

        def f(t):
            return np.exp((shape - 1) * np.log(t / mode) - (t - mode) * (b + e_s))

        val, _ = quad(f, 0, 50 * mode, points=[mode], limit=400)
        return np.log(val) + (shape - 1) * np.log(mode) - mode * (b + e_s)

    thetas = [theta, theta * 1.5]
    lps, ess = [], []
    for th in thetas:
        lp_f, aux_f = log_p(post, th)
        lp_m, aux_m = log_p(marg, th)
        e_s = float(aux_m.e_s)
        # same everything but the similarity term
        assert float(lp_m) - (-(a + n / 2) * np.log1p(e_s / b)) == pytest.approx(
            float(lp_f) + e_s * float(post.inv_t_s), rel=1e-10, abs=1e-8)
        lps.append(float(lp_m) - float(lp_f) - e_s * float(post.inv_t_s))  # the similarity term
        ess.append(e_s)
    assert lps[0] - lps[1] == pytest.approx(log_integral(ess[0]) - log_integral(ess[1]), rel=1e-7)
    assert log_integral(ess[0]) == pytest.approx(gammaln(a + n / 2) - (a + n / 2) * np.log(b + ess[0]),
                                                 rel=1e-9)
    assert float(similarity_weight(marg, ess[0])) == pytest.approx((a + n / 2) / (b + ess[0]))
    assert float(similarity_weight(post, ess[0])) == float(post.inv_t_s)


def test_every_node_sampled_keeps_the_elastic_prior_whose_conditional_mean_is_the_fe_solve():
    """``model.interior: sample`` (every node sampled, no solve): ``log p`` carries the whole
    ``-u^T K u / (2 T_r)``, its exact normaliser is ``(1/2) log pdet K`` (NumPy's
    eigenvalues but the six rigid modes'), and without the images the interior's gradient
    vanishes at the FE solve of the boundary: the paper's interior is this prior's
    conditional mean."""
    from bayesreg.model.posterior import log_normaliser
    from bayesreg.truth.synthetic import solve_dirichlet

    prior = {"lam": (2.0, 3.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
    phi = np.array([5.0, 10.0, 30.0, 2.0, 1.5])
    mesh, post, theta = box_posterior(prior, 3.0, phi, every_node=True)
    assert post.op.n_interior == 0 and post.n_boundary == len(mesh.nodes)
    lam_e = np.array([5.0, 10.0, 30.0])[mesh.tissue]
    mu_e = np.array([2.0, 1.0, 1.5])[mesh.tissue]
    k = fem.stiffness_matrix(mesh.nodes, mesh.tets, lam_e, mu_e).toarray()
    eig = np.linalg.eigvalsh(k)
    assert np.all(np.abs(eig[:6]) < 1e-9 * eig[-1]) and eig[6] > 1e-6 * eig[-1]
    assert float(log_normaliser(post, jnp.asarray(phi))) == pytest.approx(0.5 * np.sum(np.log(eig[6:])),
                                                                          rel=1e-9)
    u = theta[:-5].reshape(-1, 3)
    lp, aux = log_p(post, theta)
    assert float(aux.e_r) == pytest.approx(0.5 * u.ravel() @ k @ u.ravel(), rel=1e-10)
    # without the images: d log p / d u_i = 0 at the FE solve of the boundary nodes
    geo = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    u_fe = solve_dirichlet(geo, lam_e, mu_e, geo.boundary, 0.3 * u[geo.boundary])
    no_images = post._replace(inv_t_s=jnp.zeros_like(post.inv_t_s))
    grad = np.asarray(jax.grad(lambda t: log_p(no_images, t)[0])(jnp.asarray(
        np.concatenate([u_fe.ravel(), phi])))).reshape(-1)[:-5].reshape(-1, 3)
    inner = geo.interior
    assert np.abs(grad[inner]).max() < 1e-8 * np.abs(grad[geo.boundary]).max()
