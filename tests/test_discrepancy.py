"""The model discrepancy on the interior nodes (``model.discrepancy: interior``) and its
low-rank form (``modes``).

References: the solve model's log-density (the discrepancy at zero), SciPy's multivariate
Student t (its prior), finite differences (its gradient), JAX's Hessian at a zero residual
(the Gauss-Newton precision), a dense inverse (the trace behind its rate) and NumPy's
``eigh`` of SciPy's assembled ``K0_ii`` (the low-rank basis)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_t

from bayesreg import configure_jax
from bayesreg.data.images import Image
from bayesreg.fem.normaliser import trace_inverse_interior
from bayesreg.fem.element import stiffness_matrix
from bayesreg.inference.initialisation import gauss_newton_precision
from bayesreg.model.parameters import ParamLayout
from bayesreg.model.posterior import (
    _dense_k, build_posterior, discrepancy_log_prior, discrepancy_of, elastic_groups, log_density,
    nodal_displacement, smoothest_modes, split_position)
from bayesreg.fem.stiffness import ell_dense, ell_sparse
from bayesreg.model.similarity import build_ssd
from conftest import box_mesh
from helpers import box_skull, log_p

configure_jax()

PRIOR = {"lam": (2.0, 3.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
PHI = np.array([1.0, 10.0, 30.0, 0.5, 1.0])
LAYOUT = ParamLayout(("csf", "gm", "wm"), free=(("lam", 0), ("lam", 1), ("lam", 2), ("mu", 0), ("mu", 2)),
                     fixed=(("mu", 1, 1.0),))


MODES = 10  # of the box's 24 interior DOFs


def _k0(mesh):
    """``K0_ii`` at ``PHI`` (lam (1, 10, 30), mu (0.5, 1, 1) per tissue), by SciPy's assembly."""
    k = stiffness_matrix(mesh.nodes, mesh.tets, np.array([1.0, 10.0, 30.0])[mesh.tissue],
                         np.array([0.5, 1.0, 1.0])[mesh.tissue]).tocsc()
    dofs = (3 * mesh.interior[:, None] + np.arange(3)).ravel()
    return k[dofs][:, dofs].toarray()


def _posteriors(shift=1, discrepancy=(1.0, 0.05)):
    """The box posterior of ``tests/helpers.box_posterior`` (``m`` = ``f`` rolled by ``shift``
    voxels) without and with the discrepancy."""
    import scipy.ndimage as ndi

    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    rng = np.random.default_rng(0)
    affine = np.eye(4)
    affine[:3, 3] = -9.0
    f = Image(ndi.gaussian_filter(rng.random((48, 48, 48)), 2.0) * 4, affine)
    m = Image(np.roll(f.data, shift, axis=0), affine)
    kw = dict(t_s=0.5, t_r=3.0, layout=LAYOUT, element_group=mesh.tissue, prior=PRIOR, phi_ref=PHI)
    term = build_ssd(mesh.nodes, mesh.tets, f, m)
    return (mesh, build_posterior(mesh, term, box_skull(), **kw),
            build_posterior(mesh, term, box_skull(), discrepancy=discrepancy, **kw))


U_B_SENS = 0.5  # amplitude (mm) of the boundary displacement the sensitivities are taken at


def _orthogonal(post_d, mesh, seed=3):
    from bayesreg.model.posterior import orthogonal_discrepancy

    u_b = U_B_SENS * np.random.default_rng(seed).normal(size=(len(mesh.boundary), 3))
    return orthogonal_discrepancy(post_d, u_b), u_b


@pytest.fixture(scope="module")
def pair():
    return _posteriors()


def test_the_position_holds_the_discrepancy_between_u_b_and_the_parameters(pair):
    mesh, post, post_d = pair
    n_b, n_i = len(mesh.boundary), len(mesh.interior)
    assert post_d.n_discrepancy == 3 * n_i and post_d.n_displacement == 3 * (n_b + n_i)
    assert post_d.dim == post.dim + 3 * n_i
    theta = np.arange(post_d.dim, dtype=float)
    u_b, phi = split_position(post_d, jnp.asarray(theta))
    np.testing.assert_array_equal(u_b, theta[:3 * n_b].reshape(-1, 3))
    np.testing.assert_array_equal(phi, theta[3 * (n_b + n_i):])
    np.testing.assert_array_equal(discrepancy_of(post_d, theta), theta[3 * n_b:3 * (n_b + n_i)].reshape(-1, 3))
    assert discrepancy_of(post, theta[:post.dim]) is None
    with pytest.raises(ValueError, match="discrepancy DOFs"):
        log_p(post_d, theta[:post.dim])


def test_at_zero_discrepancy_the_log_density_is_the_paper_models(pair):
    """``d = 0``: the same ``log p``, energies and interior as the model without it (the
    Student prior is 0 at ``q = 0``)."""
    mesh, post, post_d = pair
    rng = np.random.default_rng(3)
    n_b3, n_i3 = 3 * len(mesh.boundary), 3 * len(mesh.interior)
    theta = np.r_[0.3 * rng.normal(size=n_b3), PHI]
    theta_d = np.r_[theta[:n_b3], np.zeros(n_i3), PHI]
    (lp, aux), (lp_d, aux_d) = log_p(post, theta), log_p(post_d, theta_d)
    assert np.isfinite(lp)
    np.testing.assert_allclose(float(lp_d), float(lp), rtol=1e-12)
    np.testing.assert_allclose(aux_d.interior, aux.interior, atol=1e-12)
    np.testing.assert_allclose([aux_d.e_s, aux_d.e_r], [aux.e_s, aux.e_r], rtol=1e-12)


def test_the_discrepancy_moves_the_images_not_the_strain_energy(pair):
    """With ``d != 0``: ``E_r`` is the FE field's (unchanged), ``E_s`` and the nodal
    displacement are those of the FE interior plus ``d``, and ``log p`` changes by the
    similarity and the Student prior alone."""
    mesh, post, post_d = pair
    rng = np.random.default_rng(4)
    n_b3, n_i = 3 * len(mesh.boundary), len(mesh.interior)
    d = 0.2 * rng.normal(size=(n_i, 3))
    theta = np.r_[0.3 * rng.normal(size=n_b3), PHI]
    lp0, aux0 = log_p(post, theta)
    theta_d = np.r_[theta[:n_b3], d.ravel(), PHI]
    lp, aux = log_p(post_d, theta_d)
    np.testing.assert_allclose(aux.interior, aux0.interior, atol=1e-12)  # the FE solve's
    np.testing.assert_allclose(float(aux.e_r), float(aux0.e_r), rtol=1e-12)
    u = np.asarray(nodal_displacement(post_d, jnp.asarray(theta_d), aux.interior))
    np.testing.assert_allclose(u[mesh.interior], np.asarray(aux0.interior) + d, atol=1e-12)
    np.testing.assert_allclose(u[mesh.boundary], theta[:n_b3].reshape(-1, 3), atol=1e-12)
    e_s = float(post.similarity.energy(jnp.asarray(u)[post.tets]))
    np.testing.assert_allclose(float(aux.e_s), e_s, rtol=1e-12)
    log_d = float(discrepancy_log_prior(post_d, jnp.asarray(d))[0])
    expected = float(lp0) + (float(aux0.e_s) - e_s) / 0.5 + log_d
    np.testing.assert_allclose(float(lp), expected, rtol=1e-10)


def test_the_discrepancy_prior_is_a_multivariate_student_t(pair):
    """``-(a + 3 n_i / 2) log(1 + d^T K0 d / (2 b))`` is the log-density of SciPy's
    multivariate t with ``df = 2a`` and shape ``(b / a) K0^-1``, up to a constant: their
    differences between positions agree."""
    mesh, _, post_d = pair
    n_i = len(mesh.interior)
    a, b = float(post_d.discrepancy.shape) - 1.5 * n_i, float(post_d.discrepancy.rate)
    k0 = _k0(mesh)  # by SciPy's assembly at phi_ref
    ref = multivariate_t(loc=np.zeros(3 * n_i), shape=(b / a) * np.linalg.inv(k0), df=2 * a)
    rng = np.random.default_rng(5)
    ds = [s * rng.normal(size=(n_i, 3)) for s in (0.01, 0.1, 0.5, 2.0)]
    ours = np.array([float(discrepancy_log_prior(post_d, jnp.asarray(d))[0]) for d in ds])
    theirs = np.array([ref.logpdf(d.ravel()) for d in ds])
    np.testing.assert_allclose(ours - ours[0], theirs - theirs[0], rtol=1e-10, atol=1e-9)
    q = float(discrepancy_log_prior(post_d, jnp.asarray(ds[1]))[1])
    np.testing.assert_allclose(q, 0.5 * ds[1].ravel() @ k0 @ ds[1].ravel(), rtol=1e-12)


def test_the_rate_puts_the_floor_of_the_amplitude_where_it_is_asked(pair):
    """``b = (a + 3 n_i / 2) floor^2 n_i / tr(K0^-1)``: at ``T_d = b / (a + 3 n_i / 2)`` the
    rms per node of ``N(0, T_d K0^-1)`` is ``floor_mm``; the trace (CHOLMOD's selected
    inversion) against a dense inverse."""
    mesh, post, post_d = pair
    lam, mu = elastic_groups(post, post.phi_ref)
    trace = trace_inverse_interior(post.normaliser, post.op.klam, post.op.kmu, lam, mu, post.group)
    n_i3 = 3 * len(mesh.interior)
    k = np.asarray(_dense_k(post, post.phi_ref))[:n_i3, :n_i3]
    np.testing.assert_allclose(trace, np.trace(np.linalg.inv(k)), rtol=1e-10)
    disc = post_d.discrepancy
    t_floor = float(disc.rate) / float(disc.shape)
    np.testing.assert_allclose(np.sqrt(t_floor * trace / len(mesh.interior)), 0.05, rtol=1e-12)


@pytest.mark.parametrize("orthogonal", [False, True])
def test_the_gradient_in_u_b_d_and_the_parameters_matches_finite_differences(pair, orthogonal):
    mesh, _, post_d = pair
    if orthogonal:  # the interior moves by P d
        post_d, _ = _orthogonal(post_d, mesh)
    rng = np.random.default_rng(6)
    n_b3, n_i3 = 3 * len(mesh.boundary), 3 * len(mesh.interior)
    theta = np.r_[0.3 * rng.normal(size=n_b3), 0.1 * rng.normal(size=n_i3), PHI]
    zeros = jnp.zeros((len(mesh.interior), 3))
    grad = np.asarray(jax.grad(lambda t: log_density(post_d, t, zeros, rtol=1e-12)[0])(jnp.asarray(theta)))
    for k in (1, n_b3 + 2, n_b3 + n_i3 - 1, post_d.dim - 1):
        e = np.zeros_like(theta)
        e[k] = 1e-5
        fd = (float(log_p(post_d, theta + e)[0]) - float(log_p(post_d, theta - e)[0])) / 2e-5
        np.testing.assert_allclose(grad[k], fd, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("orthogonal", [False, True])
def test_the_gauss_newton_precision_over_u_b_and_d_is_the_hessian_at_a_zero_residual(orthogonal):
    """Identical images and ``u = 0``: the SSD's residuals vanish, so its Hessian is exactly
    ``2 J^T J``; the Student prior's at ``d = 0`` is ``tau K0`` with ``tau = (a + 3 n_i / 2) /
    b``.  The Gauss-Newton precision over ``[u_b, d]`` is then ``-`` the Hessian of ``log p``
    (JAX, through the CG solve), to its ridge.  Orthogonal: ``J`` through ``P``, the prior's
    block on the sampled ``d``."""
    mesh, _, post_d = _posteriors(shift=0)
    if orthogonal:
        post_d, _ = _orthogonal(post_d, mesh)
    n_s3 = post_d.n_displacement
    theta = np.r_[np.zeros(n_s3), PHI]
    zeros = jnp.zeros((len(mesh.interior), 3))

    def logp_x(x):
        return log_density(post_d, jnp.concatenate([x, jnp.asarray(PHI)]), zeros, rtol=1e-13)[0]

    # column by column (forward over reverse; the solve's cond does not batch under vmap)
    column = jax.jit(lambda e: jax.jvp(jax.grad(logp_x), (jnp.zeros(n_s3),), (e,))[1])
    hess = -np.stack([np.asarray(column(jnp.asarray(e))) for e in np.eye(n_s3)], axis=1)
    prec = gauss_newton_precision(post_d, mesh, mesh.tissue, theta)
    assert prec.shape == (n_s3, n_s3)
    ridge = 1e-6 * np.trace(hess) / n_s3
    np.testing.assert_allclose(prec - ridge * np.eye(n_s3), hess, rtol=1e-6,
                               atol=1e-7 * np.abs(hess).max())


@pytest.fixture(scope="module")
def low_rank():
    mesh, post, post_m = _posteriors(discrepancy=(1.0, 0.05, MODES))
    return mesh, post, post_m


def test_the_low_rank_basis_is_the_smoothest_eigenmodes_of_k0(low_rank):
    """``V``, ``Lambda``: the ``r`` smallest eigenpairs of SciPy's ``K0_ii`` (NumPy's ``eigh``),
    dense and by ARPACK's shift-invert alike; the sparse copy of the ELL blocks equals the
    dense one."""
    import bayesreg.model.posterior as P

    mesh, post, post_m = low_rank
    disc = post_m.discrepancy
    k0 = _k0(mesh)
    vals, vecs = np.linalg.eigh(k0)
    np.testing.assert_allclose(disc.eigenvalues, vals[:MODES], rtol=1e-10)
    v = np.asarray(disc.basis)
    np.testing.assert_allclose(v.T @ v, np.eye(MODES), atol=1e-10)
    np.testing.assert_allclose(k0 @ v, v * vals[:MODES], atol=1e-8 * vals.max())
    op = post.op
    np.testing.assert_allclose(ell_sparse(disc.k_ii, op.cols_ii, op.row_ii, op.n_interior).toarray(),
                               np.asarray(ell_dense(disc.k_ii, op.cols_ii, op.row_ii, op.n_interior)),
                               atol=0)
    dense_max = P.DENSE_MAX_DOFS
    try:  # the sparse path on the same matrix
        P.DENSE_MAX_DOFS = 0
        vals_s, vecs_s = smoothest_modes(disc.k_ii, op, 4)
    finally:
        P.DENSE_MAX_DOFS = dense_max
    np.testing.assert_allclose(vals_s, vals[:4], rtol=1e-8)
    np.testing.assert_allclose(np.abs(vecs_s.T @ v[:, :4]), np.eye(4), atol=1e-6)


def test_the_low_rank_position_and_prior(low_rank):
    """``theta = [u_b, c, phi]`` with ``d = V c``; the prior is SciPy's multivariate t of ``c``
    (``df = 2a``, shape ``(b / a) Lambda^-1``); the rate puts the floor at ``floor_mm`` rms per
    node under the truncated prior; ``d = 0`` gives the paper model's ``log p``."""
    mesh, post, post_m = low_rank
    disc = post_m.discrepancy
    n_b, n_i = len(mesh.boundary), len(mesh.interior)
    assert post_m.n_discrepancy == MODES and post_m.dim == post.dim + MODES
    rng = np.random.default_rng(7)
    c = rng.normal(size=MODES)
    theta = np.r_[0.3 * rng.normal(size=3 * n_b), c, PHI]
    np.testing.assert_allclose(discrepancy_of(post_m, jnp.asarray(theta)),
                               (np.asarray(disc.basis) @ c).reshape(n_i, 3), atol=1e-12)
    with pytest.raises(ValueError, match="10 discrepancy coordinates"):
        log_p(post_m, theta[:-1])
    lam = np.asarray(disc.eigenvalues)
    a, b = float(disc.shape) - 0.5 * MODES, float(disc.rate)
    ref = multivariate_t(loc=np.zeros(MODES), shape=(b / a) * np.diag(1.0 / lam), df=2 * a)
    cs = [s * rng.normal(size=MODES) for s in (0.01, 0.1, 1.0, 5.0)]
    ours = np.array([float(discrepancy_log_prior(post_m, discrepancy_of(post_m, jnp.asarray(
        np.r_[np.zeros(3 * n_b), ci, PHI])))[0]) for ci in cs])
    theirs = np.array([ref.logpdf(ci) for ci in cs])
    np.testing.assert_allclose(ours - ours[0], theirs - theirs[0], rtol=1e-10, atol=1e-9)
    t_floor = b / float(disc.shape)
    np.testing.assert_allclose(np.sqrt(t_floor * np.sum(1.0 / lam) / n_i), 0.05, rtol=1e-12)
    theta0 = np.r_[theta[:3 * n_b], np.zeros(MODES), PHI]
    np.testing.assert_allclose(float(log_p(post_m, theta0)[0]),
                               float(log_p(post, np.r_[theta[:3 * n_b], PHI])[0]), rtol=1e-12)


def test_the_low_rank_gradient_and_gauss_newton_precision():
    """The gradient in ``c`` against finite differences; at a zero residual the Gauss-Newton
    precision over ``[u_b, c]`` is ``-`` JAX's Hessian (its ``c`` block ``tau Lambda``)."""
    mesh, _, post_m = _posteriors(discrepancy=(1.0, 0.05, MODES))
    rng = np.random.default_rng(8)
    n_b3 = 3 * len(mesh.boundary)
    theta = np.r_[0.3 * rng.normal(size=n_b3), 0.3 * rng.normal(size=MODES), PHI]
    zeros = jnp.zeros((len(mesh.interior), 3))
    grad = np.asarray(jax.grad(lambda t: log_density(post_m, t, zeros, rtol=1e-12)[0])(jnp.asarray(theta)))
    for k in (n_b3, n_b3 + MODES - 1):
        e = np.zeros_like(theta)
        e[k] = 1e-5
        fd = (float(log_p(post_m, theta + e)[0]) - float(log_p(post_m, theta - e)[0])) / 2e-5
        np.testing.assert_allclose(grad[k], fd, rtol=1e-5, atol=1e-6)
    mesh, _, post_m = _posteriors(shift=0, discrepancy=(1.0, 0.05, MODES))
    n = post_m.n_displacement

    def logp_x(x):
        return log_density(post_m, jnp.concatenate([x, jnp.asarray(PHI)]), zeros, rtol=1e-13)[0]

    column = jax.jit(lambda e: jax.jvp(jax.grad(logp_x), (jnp.zeros(n),), (e,))[1])
    hess = -np.stack([np.asarray(column(jnp.asarray(e))) for e in np.eye(n)], axis=1)
    prec = gauss_newton_precision(post_m, mesh, mesh.tissue, np.r_[np.zeros(n), PHI])
    assert prec.shape == (n, n)
    ridge = 1e-6 * np.trace(hess) / n
    np.testing.assert_allclose(prec - ridge * np.eye(n), hess, rtol=1e-6, atol=1e-7 * np.abs(hess).max())


def test_a_model_discrepancy_needs_interior_nodes_and_a_valid_prior(pair):
    mesh, post, _ = pair
    kw = dict(t_s=0.5, t_r=3.0, layout=LAYOUT, element_group=mesh.tissue, prior=PRIOR, phi_ref=PHI)
    with pytest.raises(ValueError, match="discrepancy must be"):
        build_posterior(mesh, post.similarity, box_skull(), discrepancy=(1.0, -0.1), **kw)
    with pytest.raises(ValueError, match="modes must be an integer"):
        build_posterior(mesh, post.similarity, box_skull(), discrepancy=(1.0, 0.1, 0), **kw)
    every = mesh._replace(boundary=np.arange(len(mesh.nodes)))
    with pytest.raises(ValueError, match="needs interior nodes"):
        build_posterior(every, build_ssd(every.nodes, every.tets, *_images()), box_skull(),
                        discrepancy=(1.0, 0.05), **kw)


def _images():
    rng = np.random.default_rng(0)
    affine = np.eye(4)
    affine[:3, 3] = -9.0
    f = Image(rng.random((48, 48, 48)), affine)
    return f, f


@pytest.mark.slow
@pytest.mark.parametrize("orthogonal", [False, True])
def test_a_run_with_a_discrepancy_writes_its_draws_map_and_amplitude(tmp_path, capsys, tiny_mesh,
                                                                      orthogonal):
    """``model.discrepancy: interior`` end to end on the tiny quickstart: ``d`` and its rms in
    ``posterior.nc``, the amplitude map and figure, ``run.json["discrepancy"]``, the printed
    line; the draws that ``export`` and ``apply`` rebuild (the FE solve by SciPy, plus each
    draw's ``d``) average to ``mesh.vtu``'s nodal mean.  Orthogonal: the written ``d`` is
    the part that displaces the interior, ``K0_ii``-orthogonal to the sensitivities at the
    saved central start."""
    import arviz as az
    import meshio

    from bayesreg.cli import main
    from test_cli import TINY

    out = tmp_path / "run"
    sets = TINY + [f"mesh.file={tiny_mesh}", "model.discrepancy=interior", "sampler.max_draws=10",
                   "sampler.min_draws=10", "sampler.warmup_steps=20",
                   f"model.discrepancy_prior.orthogonal={str(orthogonal).lower()}"]
    assert main(["run", "configs/quickstart.yaml", "--out", str(out)]
                + sum((["--set", s] for s in sets), [])) == 0
    printed = capsys.readouterr().out
    assert "model discrepancy: rms |d| per interior node" in printed
    info = json.loads((out / "run.json").read_text())
    disc = info["discrepancy"]
    assert disc["floor_mm"] == 0.05 and 0 < disc["rms_mm"]["q05"] <= disc["rms_mm"]["q95"]
    for name in ("discrepancy_amplitude.nii.gz", "discrepancy.png"):
        assert (out / name).is_file()
    tree = az.from_netcdf(out / "posterior.nc")
    d = tree.posterior["d"].transpose("chain", "draw", "interior_node", "axis").values
    mesh = meshio.read(out / "mesh.vtu")
    interior = tree.posterior["interior_node"].values
    assert d.shape[:2] == (3, 10) and d.shape[2] == len(interior)
    np.testing.assert_allclose(mesh.point_data["d_mean"][interior], d.mean(axis=(0, 1)), atol=1e-10)
    rms = np.sqrt(np.mean(np.sum(d**2, axis=-1), axis=-1))
    np.testing.assert_allclose(tree.posterior["discrepancy_rms"].values, rms, rtol=1e-10)
    assert np.abs(mesh.point_data["d_mean"][np.setdiff1d(np.arange(len(mesh.points)), interior)]).max() == 0
    from bayesreg.apply import load_posterior, nodal_field_draws

    rp = load_posterior(out)
    assert rp.d.shape == (30, len(interior), 3)
    u = nodal_field_draws(rp, np.arange(rp.n_draws))
    np.testing.assert_allclose(u.mean(axis=0), mesh.point_data["u_mean"], atol=1e-5)
    np.testing.assert_allclose(u[:, interior] - nodal_field_draws(rp._replace(d=None), np.arange(30))[:, interior],
                               rp.d, atol=1e-12)
    if orthogonal:
        from bayesreg.checkpoint import Checkpoint
        from bayesreg.model.problem import assemble, at_start

        ckpt = Checkpoint(out)
        init = ckpt.load_init()
        assert "orthogonal_search" in info["init"]  # the search went on under the model
        problem = at_start(assemble(ckpt.load_config(), ckpt.load_problem()), ckpt.load_config(), init)
        assert init.anchor.shape == (problem.posterior.n_boundary, 3)
        dual = np.asarray(problem.posterior.discrepancy.dual)
        # every draw's d is K0-orthogonal to S: G^-1 S^T K0 d = dual^T d = 0
        flat = d.reshape(-1, d.shape[2] * 3)
        assert np.all(np.abs(flat @ dual) <= 1e-9 * (np.abs(flat) @ np.abs(dual)))


@pytest.mark.parametrize("modes, orthogonal", [(None, False), (MODES, False), (None, True)])
def test_the_collapsed_moves_gaussian_of_u_b_and_d_is_the_gauss_newton_step(modes, orthogonal):
    """The collapsed moves' Gaussian of ``x = [u_b, d]`` (``[u_b, c]`` low rank) given the
    parameters and ``tau``, from the likelihood linearised in the nodal displacement at
    ``x0`` (:func:`nodal_laplace_likelihood` of :func:`similarity_curvature`, as a run makes
    it), at ``x0``'s own parameters: its precision is
    :func:`gauss_newton_precision` (SciPy's interior map; ``tau`` its posterior mean of
    ``1 / T_d``), to that one's ridge, and its mean one Gauss-Newton step from ``x0``,
    ``x0 + P^-1 grad log p(x0 | tau)`` (JAX's gradient through the CG solve)."""
    from bayesreg.model.parameters import to_unconstrained
    from bayesreg.model.posterior import discrepancy_mixture_log_ratio, similarity_curvature
    from bayesreg.sampling.kernels.target import make_target, nodal_laplace_likelihood

    disc_arg = (1.0, 0.05) if modes is None else (1.0, 0.05, modes)
    mesh, _, post_d = _posteriors(shift=1, discrepancy=disc_arg)
    if orthogonal:  # the interior moves by P d
        post_d, _ = _orthogonal(post_d, mesh)
    n = post_d.n_displacement
    rng = np.random.default_rng(11)
    x0 = np.r_[0.3 * rng.normal(size=3 * len(mesh.boundary)), 0.2 * rng.normal(size=n - 3 * len(mesh.boundary))]
    theta = np.r_[x0, PHI]
    lik = nodal_laplace_likelihood(post_d, *similarity_curvature(post_d, theta))
    target = make_target(post_d, center_u=np.zeros(n), factor=np.ones(n), exact=False,
                         condensed=False, likelihood=lik)
    assert target.mixture is not None
    disc = post_d.discrepancy
    d0 = discrepancy_of(post_d, jnp.asarray(theta), projected=False)  # the prior's d
    tau = float(disc.shape) / (float(disc.rate) + float(discrepancy_log_prior(post_d, d0)[1]))
    mean, chol = target.conditional(to_unconstrained(post_d.prior, jnp.asarray(PHI)), tau)
    prec = np.asarray(chol @ chol.T)
    gn = gauss_newton_precision(post_d, mesh, mesh.tissue, theta)
    ridge = 1e-6 * np.trace(gn) / n / (1 + 1e-6)  # gn = P + r I with r = 1e-6 tr(P) / n
    np.testing.assert_allclose(prec, gn - ridge * np.eye(n), rtol=1e-8, atol=1e-9 * np.abs(gn).max())
    zeros = jnp.zeros((len(mesh.interior), 3))

    def logp_tau(x):
        th = jnp.concatenate([x, jnp.asarray(PHI)])
        return (log_density(post_d, th, zeros, rtol=1e-13)[0]
                + discrepancy_mixture_log_ratio(post_d, discrepancy_of(post_d, th, projected=False), tau))

    grad = np.asarray(jax.grad(logp_tau)(jnp.asarray(x0)))
    np.testing.assert_allclose(np.asarray(mean), x0 + np.linalg.solve(prec, grad), rtol=1e-7,
                               atol=1e-9 * np.abs(x0).max())


def test_the_discrepancys_precision_given_d_is_its_gamma_conditional(pair):
    """``tau | d ~ Gamma(a + 3 n_i / 2, b + q)`` (the Student prior as a scale mixture): the
    draws' mean and variance within 5 Monte Carlo standard errors of SciPy's Gamma; the
    mixture's log-ratio is ``-tau q`` less the Student log prior, and the Student prior is
    the Gaussian at ``tau`` integrated over that Gamma prior (SciPy's quadrature)."""
    from scipy import integrate, stats

    from bayesreg.model.posterior import discrepancy_mixture_log_ratio, discrepancy_precision_draw

    mesh, post, post_d = pair
    disc = post_d.discrepancy
    rng = np.random.default_rng(5)
    d = jnp.asarray(0.05 * rng.normal(size=(len(mesh.interior), 3)))
    log_p, q = (float(v) for v in discrepancy_log_prior(post_d, d))
    shape, rate = float(disc.shape), float(disc.rate) + q
    taus = np.asarray(jax.vmap(lambda k: discrepancy_precision_draw(post_d, k, d))(
        jax.random.split(jax.random.key(0), 4000)))
    ref = stats.gamma(shape, scale=1.0 / rate)
    assert abs(taus.mean() - ref.mean()) < 5 * ref.std() / np.sqrt(len(taus))
    assert abs(taus.var() - ref.var()) < 5 * np.sqrt((ref.moment(4) - 4 * ref.mean() * ref.moment(3)
                                                       + 6 * ref.mean()**2 * ref.moment(2)
                                                       - 3 * ref.mean()**4 - ref.var()**2) / len(taus))
    tau = 0.7 * ref.mean()
    np.testing.assert_allclose(float(discrepancy_mixture_log_ratio(post_d, d, tau)), -tau * q - log_p,
                               rtol=1e-12)
    # log p(d) = log of the integral over tau ~ Gamma(a, b) of tau^(n/2) exp(-tau q), up to a
    # constant: compare two values of d
    n = 3 * len(mesh.interior)
    a, b = shape - n / 2, float(disc.rate)

    def log_marginal(qv):
        f = lambda t: np.exp((a + n / 2 - 1) * np.log(t) - (b + qv) * t - (a + n / 2 - 1) * np.log(ref.mean()))
        return np.log(integrate.quad(f, 0, np.inf, limit=200)[0])

    d2 = 2.0 * d
    log_p2, q2 = (float(v) for v in discrepancy_log_prior(post_d, d2))
    np.testing.assert_allclose(log_p2 - log_p, log_marginal(q2) - log_marginal(q), rtol=1e-6)


def _fe_interior(mesh, post, phi, u_b):
    """``u_i`` ``(n_i, 3)`` solving ``K_ii u_i = -K_ib u_b`` at ``phi``, by SciPy's assembly and
    sparse LU (the reference of the solver's interior)."""
    import scipy.sparse.linalg as spla

    lam_g, mu_g = (np.asarray(v) for v in elastic_groups(post, jnp.asarray(phi)))
    group = np.asarray(post.group)
    k = stiffness_matrix(mesh.nodes, mesh.tets, lam_g[group], mu_g[group]).tocsc()
    di = (3 * mesh.interior[:, None] + np.arange(3)).ravel()
    db = (3 * mesh.boundary[:, None] + np.arange(3)).ravel()
    return spla.spsolve(k[di][:, di], -(k[di][:, db] @ u_b.ravel())).reshape(-1, 3)


@pytest.mark.parametrize("modes", [None, MODES])
def test_a_move_that_carries_the_displacement_keeps_every_node_where_it_was(modes):
    """:func:`~bayesreg.sampling.kernels.collapsed.displacement_proposal`: from ``phi`` to ``phi'``
    with ``u_b`` kept and ``d' = d + H(phi) u_b - H(phi') u_b`` (the interiors by SciPy), every
    node's displacement is unchanged, so is the data term, and ``log p`` is not (the
    priors see the new parameters and ``d'``); low rank, the change lies outside the modes'
    span.  The move back from ``phi'``
    returns the start (a shear: Jacobian 1, its own reverse)."""
    from bayesreg.model.parameters import to_unconstrained
    from bayesreg.model.posterior import data_log_likelihood
    from bayesreg.sampling.kernels.collapsed import displacement_proposal
    from bayesreg.sampling.kernels.target import make_target

    mesh, _, post_d = _posteriors(discrepancy=(1.0, 0.05) if modes is None else (1.0, 0.05, modes))
    rng = np.random.default_rng(11)
    n_d = post_d.n_displacement
    x = np.r_[0.4 * rng.normal(size=3 * len(mesh.boundary)), 0.1 * rng.normal(size=n_d - 3 * len(mesh.boundary))]
    phi, phi_p = PHI, PHI * np.exp(0.4 * rng.normal(size=PHI.size))
    target = make_target(post_d, center_u=np.zeros(n_d), factor=np.full(n_d, 0.5), exact=True,
                         condensed=False)
    eta, eta_p = (to_unconstrained(post_d.prior, jnp.asarray(p)) for p in (phi, phi_p))
    w, _ = target.coordinates(jnp.asarray(np.r_[x, phi]))
    u_b = x[:3 * len(mesh.boundary)].reshape(-1, 3)
    fe, fe_p = _fe_interior(mesh, post_d, phi, u_b), _fe_interior(mesh, post_d, phi_p, u_b)
    assert np.abs(fe - fe_p).max() > 1e-2  # the parameters move the FE interior
    w_p = displacement_proposal(target, w, eta, eta_p, jnp.asarray(fe), jnp.asarray(fe_p))
    theta, theta_p = target.position(w, eta), target.position(w_p, eta_p)
    np.testing.assert_allclose(np.asarray(theta_p[-PHI.size:]), phi_p, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(theta_p[:u_b.size]), u_b.ravel(), atol=1e-12)
    u = np.asarray(nodal_displacement(post_d, theta, jnp.asarray(fe)))
    u_p = np.asarray(nodal_displacement(post_d, theta_p, jnp.asarray(fe_p)))
    if modes is None:
        np.testing.assert_allclose(u_p, u, atol=1e-10)
        np.testing.assert_allclose(float(data_log_likelihood(post_d, jnp.asarray(u_p))),
                                   float(data_log_likelihood(post_d, jnp.asarray(u))), rtol=1e-10)
    else:
        change = (u_p - u)[mesh.interior].ravel()
        assert np.abs(change).max() > 1e-3  # what the modes cannot take up
        np.testing.assert_allclose(np.asarray(post_d.discrepancy.basis).T @ change, 0.0, atol=1e-10)
    np.testing.assert_allclose(u_p[mesh.boundary], u[mesh.boundary], atol=1e-12)
    assert abs(float(log_p(post_d, np.asarray(theta_p))[0]) - float(log_p(post_d, np.asarray(theta))[0])) > 1e-3
    w_back = displacement_proposal(target, w_p, eta_p, eta, jnp.asarray(fe_p), jnp.asarray(fe))
    np.testing.assert_allclose(np.asarray(w_back), np.asarray(w), atol=1e-10)
    with pytest.raises(ValueError, match="one row per interior node"):
        target.shift(theta[:n_d], jnp.zeros((len(mesh.interior) + 1, 3)))


def test_the_orthogonal_discrepancys_sensitivities_are_the_fe_interiors_derivatives(pair):
    """``S[:, k] = d(H(phi) u_b) / d log phi_k`` at ``phi_ref``: central differences of SciPy's
    interior solve (:func:`_fe_interior`) in each free parameter's log."""
    mesh, _, post_d = pair
    post_o, u_b = _orthogonal(post_d, mesh)
    s_mat = np.asarray(post_o.discrepancy.sensitivities)
    assert s_mat.shape == (3 * len(mesh.interior), PHI.size)
    h = 1e-5
    for k in range(PHI.size):
        up, down = PHI.copy(), PHI.copy()
        up[k] *= np.exp(h)
        down[k] *= np.exp(-h)
        fd = (_fe_interior(mesh, post_o, up, u_b) - _fe_interior(mesh, post_o, down, u_b)).ravel() / (2 * h)
        np.testing.assert_allclose(s_mat[:, k], fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def test_an_orthogonal_discrepancy_displaces_the_interior_only_k0_orthogonally_to_s(pair):
    """The map ``M = P`` is a projector with ``P S = 0`` and ``S^T K0 P = 0`` (``K0`` by
    SciPy's assembly), the interior moves by the FE solve plus ``P d``, the prior's ``q``
    splits over ``P d`` and ``(I - P) d``, and ``log p`` is the plain discrepancy model's at
    ``P d`` with the prior of the sampled ``d`` in place of ``P d``'s."""
    from bayesreg.model.posterior import discrepancy_map

    mesh, _, post_d = pair
    post_o, _ = _orthogonal(post_d, mesh)
    s_mat = np.asarray(post_o.discrepancy.sensitivities)
    k0 = _k0(mesh)
    proj = discrepancy_map(post_o)
    scale = np.abs(k0).max() * np.abs(s_mat).max()
    np.testing.assert_allclose(proj @ proj, proj, atol=1e-10)
    np.testing.assert_allclose(proj @ s_mat, 0.0, atol=1e-10 * np.abs(s_mat).max())
    np.testing.assert_allclose(s_mat.T @ k0 @ proj, 0.0, atol=1e-10 * scale)
    rng = np.random.default_rng(4)
    n_b3, n_i3 = 3 * len(mesh.boundary), 3 * len(mesh.interior)
    theta = np.r_[0.3 * rng.normal(size=n_b3), 0.1 * rng.normal(size=n_i3), PHI]
    d = theta[n_b3:n_b3 + n_i3]
    pd = proj @ d
    np.testing.assert_allclose(np.asarray(discrepancy_of(post_o, jnp.asarray(theta))).ravel(), pd, rtol=1e-12)
    raw = discrepancy_of(post_o, jnp.asarray(theta), projected=False)
    np.testing.assert_allclose(np.asarray(raw).ravel(), d, rtol=0)
    q = lambda v: 0.5 * v @ k0 @ v  # noqa: E731
    np.testing.assert_allclose(q(d), q(pd) + q(d - pd), rtol=1e-10)
    zeros = jnp.zeros((len(mesh.interior), 3))
    lp_o, aux = log_density(post_o, jnp.asarray(theta), zeros, rtol=1e-12)
    u_b = theta[:n_b3].reshape(-1, 3)
    u = np.asarray(nodal_displacement(post_o, jnp.asarray(theta), aux.interior))
    np.testing.assert_allclose(u[mesh.interior], _fe_interior(mesh, post_o, PHI, u_b) + pd.reshape(-1, 3),
                               rtol=1e-8, atol=1e-10)
    theta_p = theta.copy()
    theta_p[n_b3:n_b3 + n_i3] = pd
    lp_d = log_density(post_d, jnp.asarray(theta_p), zeros, rtol=1e-12)[0]
    prior = lambda v: float(discrepancy_log_prior(post_d, jnp.asarray(v.reshape(-1, 3)))[0])  # noqa: E731
    np.testing.assert_allclose(float(lp_o), float(lp_d) - prior(pd) + prior(d), rtol=1e-10)


def test_an_orthogonal_discrepancy_needs_a_start_that_moves_the_tissue(pair, tmp_path):
    """No sensitivities at ``u_b = 0`` (the paper's start): refused by name, at the posterior
    and through :func:`~bayesreg.model.problem.at_start`; the config refuses it without a
    discrepancy and with a parameter per element."""
    from bayesreg.config import Config
    from bayesreg.model.posterior import orthogonal_discrepancy

    mesh, post, post_d = pair
    with pytest.raises(ValueError, match="does not move with every free parameter"):
        orthogonal_discrepancy(post_d, np.zeros((len(mesh.boundary), 3)))
    with pytest.raises(ValueError, match="needs a posterior with a model discrepancy"):
        orthogonal_discrepancy(post, np.ones((len(mesh.boundary), 3)))
    with pytest.raises(ValueError, match="one row per boundary node"):
        orthogonal_discrepancy(post_d, np.ones((3, 3)))
    with pytest.raises(ValueError, match="needs a model discrepancy"):
        Config.model_validate({"model": {"discrepancy_prior": {"orthogonal": True}}})
    with pytest.raises(ValueError, match="not one per element"):
        Config.model_validate({"model": {"discrepancy": "interior", "elastic": "element",
                                         "discrepancy_prior": {"orthogonal": True}},
                               "sampler": {"kind": "nuts"}})

