"""Small problems shared by several test files.

Analytic images and grids, a box posterior, a quadratic posterior of known Gaussian form,
toy targets of the gradient kernels and the Monte Carlo moment check the sampler tests
use.  Fixtures live in ``conftest.py``; these are plain functions.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import numpy as np

import arviz as az
import jax.numpy as jnp
import scipy.ndimage as ndi
import scipy.sparse.linalg as spla

from bayesreg.fem import element as fem
from bayesreg.data import labels
from bayesreg.fem import stiffness
from bayesreg.data.images import Image
from bayesreg.sampling.kernels.target import Cache, Target
from bayesreg.model.parameters import ParamLayout
from bayesreg.model.posterior import Aux, build_posterior, log_density
from bayesreg.model.lncc import build_lncc
from bayesreg.model.similarity import build_ssd
from bayesreg.fem.solver import solve_interior
from conftest import box_mesh, centred_cube

# --- images and grids --------------------------------------------------------------------


def smooth_image(shape=(40, 40, 40), origin=-5.0) -> Image:
    """A smooth analytic image on 1 mm voxels from ``origin`` (world mm) on every axis."""
    affine = np.eye(4)
    affine[:3, 3] = origin
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1) + origin
    data = np.sin(ijk[..., 0] / 6.0) + np.cos(ijk[..., 1] / 5.0) * ijk[..., 2] / 30.0
    return Image(data, affine)


def grid_image(fn, shape=(40, 40, 40), spacing=1.0, origin=-5.0) -> Image:
    """``fn`` of the world coordinates ``(..., 3)`` of an isotropic grid's voxel centres."""
    affine = np.diag([spacing, spacing, spacing, 1.0])
    affine[:3, 3] = origin
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    x = ijk * spacing + origin
    return Image(fn(x), affine)


def world_grid(lo, hi, h):
    """Boolean grid (all False) with isotropic spacing ``h`` covering ``[lo, hi]^3`` mm, its
    affine, and the world coordinates of its voxel centres."""
    n = int(round((hi - lo) / h)) + 1
    aff = np.diag([h, h, h, 1.0])
    aff[:3, 3] = lo
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1)
    return np.zeros((n, n, n), bool), aff, ijk * h + lo


def ball_labels(affine=None, shape=(16, 16, 16)) -> Image:
    """A ball of grey matter (radius 5 voxels) in a 16^3 label map, 2 mm voxels."""
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    data = np.where(np.linalg.norm(ijk - 7.5, axis=-1) < 5, labels.GM, labels.BACKGROUND).astype(np.uint8)
    return Image(data, np.diag([2.0, 2.0, 2.0, 1.0]) if affine is None else affine)


# --- finite elements -----------------------------------------------------------------------


def direct_interior_solve(mesh, lam, mu, ub):
    """``u_i = -K_ii^-1 K_ib u_b`` by SciPy's sparse direct solver, ``(n_i, 3)``."""
    k = fem.stiffness_matrix(mesh.nodes, mesh.tets, lam, mu)
    idf = (3 * mesh.interior[:, None] + np.arange(3)).ravel()
    bd = (3 * mesh.boundary[:, None] + np.arange(3)).ravel()
    return spla.spsolve(k[idf][:, idf].tocsc(), -(k[idf][:, bd] @ ub.ravel())).reshape(-1, 3)


# --- a sampler result stand-in ----------------------------------------------------------------


def fake_run(seed=0, c=3, d=23):
    """A mesh, a problem stand-in (boundary first, interior after, ``perm`` to node order)
    and a sampler result with correlated draws."""
    rng = np.random.default_rng(seed)
    mesh = box_mesh(n=(2, 2, 2), size=(20.0, 20.0, 20.0))
    n = len(mesh.nodes)
    boundary = np.asarray(mesh.boundary)
    interior = np.setdiff1d(np.arange(n), boundary)
    order = np.concatenate([boundary, interior])  # [u_b, u_i][:, k] is node order[k]
    perm = np.argsort(order)  # full[:, j] = [u_b, u_i][:, perm[j]]
    nb = len(boundary)
    base = rng.normal(0.0, 2.0, (n, 3))
    draws = base + rng.normal(0.0, 0.3, (c, d, n, 3)) * rng.uniform(0.2, 1.0, (n, 1))
    n_par = 2
    positions = np.concatenate([draws[:, :, boundary].reshape(c, d, 3 * nb),
                                rng.uniform(1, 2, (c, d, n_par))], axis=-1)
    problem = SimpleNamespace(mesh=mesh, posterior=SimpleNamespace(n_boundary=nb, perm=perm, discrepancy=None))
    result = SimpleNamespace(positions=positions, interior=draws[:, :, interior])
    return mesh, problem, result, draws.reshape(c * d, n, 3)


# --- posteriors ----------------------------------------------------------------------------


def box_skull() -> Image:
    """The skull of :func:`box_posterior`: everything with world x > 36 mm, on its 48^3
    grid of 1 mm voxels from -9 mm."""
    shape = (48, 48, 48)
    affine = np.diag([1.0, 1.0, 1.0, 1.0])
    affine[:3, 3] = -9.0
    x = np.arange(shape[0]) - 9.0
    return Image(np.broadcast_to((x > 36.0)[:, None, None], shape).astype(np.uint8), affine)


def box_posterior(prior, t_r, phi, *, quadrature_level=0, every_node=False, similarity="ssd"):
    """The posterior of a 30 mm box mesh (3 tissues by x thirds; ``mu_gm`` fixed at 1) on a
    smooth random image shifted by one voxel, with a skull at world x > 36 mm; with
    ``every_node`` every node sampled (``model.interior: sample``); ``similarity`` ``"lncc"``:
    the LNCC term (10 mm windows) instead of SSD.

    Returns ``(mesh, post, theta)``, ``theta`` a start near the rest state at ``phi``.
    """
    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    if every_node:
        mesh = mesh._replace(boundary=np.arange(len(mesh.nodes)))
    rng = np.random.default_rng(0)
    shape = (48, 48, 48)
    affine = np.diag([1.0, 1.0, 1.0, 1.0])
    affine[:3, 3] = -9.0
    f = Image(ndi.gaussian_filter(rng.random(shape), 2.0) * 4, affine)
    m = Image(np.roll(f.data, 1, axis=0), affine)
    forbidden = box_skull()
    layout = ParamLayout(("csf", "gm", "wm"),
                         free=(("lam", 0), ("lam", 1), ("lam", 2), ("mu", 0), ("mu", 2)),
                         fixed=(("mu", 1, 1.0),))
    term = (build_ssd(mesh.nodes, mesh.tets, f, m, quadrature_level=quadrature_level)
            if similarity == "ssd" else
            build_lncc(mesh.nodes, mesh.tets, f, m, window_mm=10.0, quadrature_level=quadrature_level))
    post = build_posterior(mesh, term, forbidden, t_s=0.5,
                           t_r=t_r, layout=layout, element_group=mesh.tissue, prior=prior,
                           phi_ref=phi)
    theta = np.concatenate([0.3 * rng.normal(size=3 * len(mesh.boundary)), phi])
    return mesh, post, theta


def log_p(post, theta):
    """``log_density`` at ``theta`` from a zero warm start, CG tolerance 1e-12: ``(logp, aux)``."""
    return log_density(post, jnp.asarray(theta), jnp.zeros((post.op.n_interior, 3)), rtol=1e-12)


def quadratic_problem():
    """Boundary displacements of a cube with an elastic prior and a Gaussian stand-in likelihood.

    Returns ``(logdensity, mean, cov, n_interior)``: the posterior is Gaussian with the
    given mean and covariance (precision ``A + S / T_r``, ``S`` the Schur complement of K).
    """
    mesh = centred_cube()
    lam, mu, t_r = 10.0, 1.0, 50.0
    op, _ = stiffness.build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    grads, vol = fem.shape_gradients(mesh.nodes, mesh.tets)
    perm = np.empty(len(mesh.nodes), int)
    perm[mesh.boundary] = np.arange(len(mesh.boundary))
    perm[mesh.interior] = len(mesh.boundary) + np.arange(len(mesh.interior))
    d = 3 * len(mesh.boundary)
    rng = np.random.default_rng(42)
    q = rng.normal(size=(d, d))
    a_prec = q @ q.T / d * 4.0 + np.eye(d) * 2.0  # likelihood precision (1/mm^2)
    a_mean = rng.normal(size=d)
    lam_e = jnp.full(len(mesh.tets), lam)
    mu_e = jnp.full(len(mesh.tets), mu)

    def logdensity(theta, u_i0):
        u_b = theta.reshape(-1, 3)
        u_i, info = solve_interior(op, lam_e, mu_e, u_b, u_i0, rtol=1e-12)
        u = jnp.concatenate([u_b, u_i])[perm]
        e_r = fem.element_strain_energy(jnp.asarray(grads), jnp.asarray(np.abs(vol)), u[mesh.tets],
                                        lam_e, mu_e)
        r = theta - a_mean
        e_s = 0.5 * r @ (a_prec @ r)
        lp = -e_s - e_r / t_r
        return jnp.where(info.converged, lp, -jnp.inf), Aux(u_i, info, e_s, e_r)

    # exact posterior: precision A + S / T_r, S the Schur complement of K
    k = fem.stiffness_matrix(mesh.nodes, mesh.tets, lam, mu).toarray()
    bd = (3 * mesh.boundary[:, None] + np.arange(3)).ravel()
    idf = (3 * mesh.interior[:, None] + np.arange(3)).ravel()
    s = k[np.ix_(bd, bd)] - k[np.ix_(bd, idf)] @ np.linalg.solve(k[np.ix_(idf, idf)], k[np.ix_(idf, bd)])
    prec = a_prec + s / t_r
    cov = np.linalg.inv(prec)
    mean = cov @ (a_prec @ a_mean)
    return logdensity, mean, cov, len(mesh.interior)


# --- toy targets of the gradient kernels ---------------------------------------------------

D = 4
S = np.array([0.5, 1.0, 2.0, 0.2])  # conditional scales of u given eta = 0
A = 1.5  # E[u | eta] = A * eta
M_ETA, SD_ETA = 0.3, 0.15


def toy_target() -> Target:
    """``eta ~ N(0.3, 0.15^2)``, ``u | eta ~ N(A eta, exp(eta)^2 diag S^2)``.

    Written as the posterior is: an unnormalised conditional of ``u`` (the "elastic prior")
    plus a normaliser ``log_norm(eta) = -D eta`` that depends on the "elastic parameter"
    only, and a preconditioner ``u = F w``.  Moments: :func:`toy_moments`.
    """
    f = jnp.asarray(S)

    def u_of(w):
        return f * w

    def u_lp(w, eta, cache, interior):
        u = u_of(w)
        return -0.5 * jnp.sum(((u - A * eta[0]) / (f * jnp.exp(eta[0]))) ** 2) - 0.5 * ((eta[0] - M_ETA) / SD_ETA) ** 2

    def u_evaluate(w, eta, cache, interior):
        return u_lp(w, eta, cache, interior), interior, jnp.asarray(0), jnp.asarray(True)

    def log_norm(eta):
        return -D * eta[0]

    def evaluate(w, eta, interior, ln):
        lp = u_lp(w, eta, None, interior) + ln
        return lp, lp, interior, jnp.asarray(0), jnp.asarray(True)

    def build_cache(eta, ln):
        return Cache(jnp.zeros((0,)), jnp.asarray(ln, jnp.float64))

    def position(w, eta):
        return jnp.concatenate([u_of(w), eta])

    def coordinates(theta):
        return theta[:D] / f, theta[D:]

    return Target(u_lp, u_evaluate, evaluate, log_norm, build_cache, position, coordinates, 1)


def toy_moments():
    """Mean, variance and fourth central moment of each coordinate ``(u_1..u_D, eta)`` of
    :func:`toy_target`.

    With ``d = eta - M``, ``eta ~ N(M, s^2)`` and ``z ~ N(0, 1)``: ``u_j - A M = A d +
    S_j e^M e^d z``, so ``Var u_j = A^2 s^2 + S_j^2 e^(2M + 2s^2)`` and
    ``E (u_j - A M)^4 = 3 A^4 s^4 + 6 A^2 S_j^2 e^(2M) (s^2 + 4 s^4) e^(2 s^2)
    + 3 S_j^4 e^(4M + 8 s^2)`` (from ``E e^(t d) = e^(t^2 s^2 / 2)`` and its second derivative
    in ``t``); ``eta`` is Gaussian: ``3 s^4``.
    """
    m, s = M_ETA, SD_ETA
    mean = np.r_[np.full(D, A * m), m]
    var = np.r_[A**2 * s**2 + S**2 * np.exp(2 * m + 2 * s**2), s**2]
    fourth = np.r_[3 * A**4 * s**4 + 6 * A**2 * S**2 * np.exp(2 * m) * (s**2 + 4 * s**4) * np.exp(2 * s**2)
                   + 3 * S**4 * np.exp(4 * m + 8 * s**2), 3 * s**4]
    return mean, var, fourth


ETA_COV = np.array([[0.04, 0.0392], [0.0392, 0.04]])  # sd 0.2, correlation 0.98


def correlated_target() -> Target:
    """``eta ~ N(0, ETA_COV)`` (two strongly correlated "elastic parameters", like the overall
    stiffness scale under the exact normaliser), ``u | eta ~ N((eta_0 - eta_1) 1, I)``."""
    prec = jnp.asarray(np.linalg.inv(ETA_COV))

    def u_lp(w, eta, cache, interior):
        return -0.5 * jnp.sum((w - (eta[0] - eta[1])) ** 2) - 0.5 * eta @ prec @ eta

    def evaluate(w, eta, interior, ln):
        lp = u_lp(w, eta, None, interior) + ln
        return lp, lp, interior, jnp.asarray(0), jnp.asarray(True)

    return Target(u_lp, lambda w, eta, c, i: (u_lp(w, eta, c, i), i, jnp.asarray(0), jnp.asarray(True)),
                  evaluate, lambda eta: jnp.zeros(()),
                  lambda eta, ln: Cache(jnp.zeros((0,)), jnp.asarray(ln, jnp.float64)),
                  lambda w, eta: jnp.concatenate([w, eta]), lambda theta: (theta[:2], theta[2:]), 2)


def gaussian_target(dim: int) -> Target:
    """``u ~ N(0, I)``, no elastic parameters (``n_free = 0``)."""

    def u_lp(w, eta, cache, interior):
        return -0.5 * jnp.sum(w**2)

    return Target(u_lp, lambda w, eta, c, i: (u_lp(w, eta, c, i), i, jnp.asarray(0), jnp.asarray(True)),
                  lambda w, eta, i, ln: (u_lp(w, eta, None, i), u_lp(w, eta, None, i), i, jnp.asarray(0),
                                         jnp.asarray(True)),
                  lambda eta: jnp.zeros(()),
                  lambda eta, ln: Cache(jnp.zeros((0,)), jnp.asarray(ln, jnp.float64)),
                  lambda w, eta: w, lambda theta: (theta, jnp.zeros((0,))), 0)


# --- Monte Carlo checks --------------------------------------------------------------------


def assert_moments(x, mean, var, fourth, *, n_se=5.0, what=None):
    """The sample mean and variance of draws ``x`` ``(chains, draws)`` equal the true ``mean``
    and ``var`` within ``n_se`` Monte Carlo standard errors, each from ArviZ's ESS of the
    quantity averaged.

    ``sd(mean_hat) = sqrt(var / ESS(x))`` and ``sd(var_hat) = sqrt((fourth - var^2) /
    ESS((x - mean)^2))``, ``fourth`` the true fourth central moment (``3 var^2`` for a
    Gaussian, where the second is ``var sqrt(2 / ESS)``).  Returns the two ESS.
    """
    x = np.asarray(x, dtype=np.float64)
    ess_x = float(az.ess(x, method="mean"))
    ess_sq = float(az.ess((x - mean) ** 2, method="mean"))
    se_mean = np.sqrt(var / ess_x)
    se_var = np.sqrt((fourth - var**2) / ess_sq)
    assert abs(x.mean() - mean) < n_se * se_mean, (what, x.mean(), mean, se_mean)
    assert abs(x.var() - var) < n_se * se_var, (what, x.var(), var, se_var)
    return ess_x, ess_sq


def _split_keywords(as_algorithm, kw: dict) -> tuple[dict, dict]:
    """``kw`` split into the keywords of ``as_algorithm`` and the rest (the driver's)."""
    import inspect

    own = inspect.signature(as_algorithm).parameters
    return {k: v for k, v in kw.items() if k in own}, {k: v for k, v in kw.items() if k not in own}


def sample_rwmh(rng_key, logdensity_fn, x0, interior0, sigma, **kw):
    """The driver (:func:`bayesreg.sampling.driver.sample`) on the random walk: the keywords of
    :func:`bayesreg.sampling.kernels.rwmh.as_algorithm` to it, the rest to the driver."""
    from bayesreg.sampling.driver import sample
    from bayesreg.sampling.kernels import rwmh

    alg, run = _split_keywords(rwmh.as_algorithm, kw)
    return sample(rng_key, rwmh.as_algorithm(logdensity_fn, interior0, sigma, **alg), x0, **run)


def sample_gibbs(rng_key, target, x0, interior0, **kw):
    """The driver on the gradient Gibbs kernel (:func:`bayesreg.sampling.kernels.gibbs.as_algorithm`)."""
    from bayesreg.sampling.driver import sample
    from bayesreg.sampling.kernels import gibbs

    alg, run = _split_keywords(gibbs.as_algorithm, kw)
    return sample(rng_key, gibbs.as_algorithm(target, interior0, **alg), x0, **run)


def load_benchmark(name: str):
    """The script ``benchmarks/<name>.py`` as a module (the benchmarks are not a package)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"bayesreg_bench_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
