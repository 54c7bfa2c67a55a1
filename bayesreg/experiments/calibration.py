"""Simulation-based calibration (SBC) of the posterior on a small problem.

A posterior is calibrated when, for truths drawn from its prior and data drawn from its
likelihood, the rank of each truth among the posterior draws is uniform (Talts, Betancourt,
Simpson, Vehtari, Gelman 2018, *Validating Bayesian inference algorithms with
simulation-based calibration*; Modrák et al. 2023).  Then every central interval holds its
truth at its nominal rate.  This module runs that check on a box-shaped problem small enough
that many replicas fit in one program:

1. **Problem** (:func:`calibration_problem`): a structured box mesh
   (:func:`bayesreg.mesh.tetmesh.box_mesh`) in two tissues (``a``: the half at low x, ``b``: the
   other), a smooth analytic moving image ``m`` (a sum of plane waves), no skull, and the
   posterior of paper Eqs. 8-12 with ``mu_a`` fixed at 1 (the scale, as ``mu_GM`` in the
   paper) and ``lam_a``, ``lam_b``, ``mu_b`` free under scaled Beta priors.  The prior of
   ``u_b`` is made proper along the six rigid-body modes
   (:func:`bayesreg.model.posterior.build_posterior` ``rigid_sd``): without it no truth can be
   drawn from it.
2. **Truths and data** (:func:`simulate`): ``phi`` from its Beta priors, ``u_b`` from the
   Gaussian elastic prior given ``phi`` (precision ``S / T_r`` plus the rigid part), the
   interior from the FE solve; a draw that inverts an element or leaves the image is
   redrawn whole (the posterior's hard constraints).  The likelihood ``exp(-E_s / T_s)``
   (Eqs. 1, 9) sees ``f`` only through its values ``f_q`` at the fixed quadrature points
   ``x_q``, as independent ``f_q ~ N(m(x_q + u(x_q)), T_s / (2 w_q))`` (``w_q`` the point's
   weight, mm^3): ``f_q`` is drawn from exactly that, at ``T_s`` (or, with ``t_s_prior``,
   at a ``T_s`` drawn from it; with ``data_t_s``, at that one: a mismatch).
3. **Posterior draws** (:func:`run_replicas`): NUTS on ``u_b`` in Gibbs with random-walk moves
   of the parameters and, with ``sampler.collapsed_moves``, collapsed moves (the likelihood
   linearised at each chain's start, again where its warm-up ended)
   (:mod:`bayesreg.sampling.kernels.gibbs`), Stan's windowed warm-up
   (:mod:`bayesreg.sampling.kernels.adaptation`), chains started from the prior, not from the truth;
   run by the driver of every run (:func:`bayesreg.sampling.driver.sample`), every chain of
   every replica one of its chains with its replica's data as the chain's own (one
   compiled program).
4. **Ranks and coverage** (:func:`summarise`): the rank of each truth among ``L`` draws
   thinned evenly from all chains, their histogram and its chi-square test of uniformity
   (SciPy), and the coverage of the central 50/90/95% intervals; per free parameter, per
   ratio ``lam/mu``, for the rms boundary displacement and pooled over the boundary
   coordinates.

``prior_normaliser: paper`` keeps the paper's unnormalised elastic prior in the posterior
while the truths still come from the normalised one: the size of its bias is what the check
then shows.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla

from bayesreg.config.calibration import CalibrationSpec
from bayesreg.config.loading import load_model_file
from bayesreg.mesh.constraints import points_forbidden
from bayesreg.data.images import Image
from bayesreg.inference.initialisation import gauss_newton_precision, schur_complement
from bayesreg.jaxconfig import require_x64
from bayesreg.mesh.tetmesh import Mesh, box_mesh, signed_volumes
from bayesreg.model.parameters import ParamLayout
from bayesreg.model.posterior import Posterior, build_posterior, elastic_groups
from bayesreg.model.similarity import build_ssd, moving_values

__all__ = ["CalibrationSpec", "CalibrationProblem", "Replicas", "calibration_problem", "simulate",
           "run_replicas", "ranks_of", "summarise", "LEVELS", "GROUPS"]

#: Central interval levels whose coverage is reported.
LEVELS = (0.5, 0.9, 0.95)

#: Tissue groups of the calibration problem: ``a`` (x below the box's middle), ``b``.
GROUPS = ("a", "b")


class CalibrationProblem(NamedTuple):
    """The small problem of :func:`calibration_problem`.

    Attributes
    ----------
    mesh : Mesh
    posterior : Posterior
        With the data ``f_q`` of a replica still to be put in (:func:`simulate`).
    layout : ParamLayout
        Groups ``("a", "b")``; free ``lam_a, lam_b, mu_b``; ``mu_a = 1`` fixed.
    element_group : (M,) int
    exact : bool
        The posterior carries the exact normaliser.
    t_s_prior : (shape, rate) or None
        The Gamma prior the truths' ``1 / T_s`` come from (``model.t_s_prior``).
    data_t_s : float or None
        The temperature of the simulated noise where it differs from the model's.
    """

    mesh: Mesh
    posterior: Posterior
    layout: ParamLayout
    element_group: np.ndarray
    exact: bool
    t_s_prior: tuple | None = None
    data_t_s: float | None = None


def _plane_waves(x, wavelength):
    """``0.5 + 0.12 sum_j sin(2 pi d_j . x / wavelength + j)`` over four directions ``d_j``."""
    d = np.array([[1, 0.3, 0.1], [-0.2, 1, 0.4], [0.3, -0.1, 1], [1, 1, -1]], float)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    phase = 2 * np.pi * (x @ d.T) / wavelength + np.arange(4)
    return 0.5 + 0.12 * np.sin(phase).sum(-1)


def calibration_problem(spec: CalibrationSpec) -> CalibrationProblem:
    """The box problem of ``spec`` (module docstring, step 1).

    Raises
    ------
    RuntimeError
        JAX runs in float32 (call :func:`bayesreg.configure_jax` first).
    """
    require_x64("calibration_problem")
    p, mdl = spec.problem, spec.model
    size = float(p.size_mm)
    mesh = box_mesh((p.cells,) * 3, size=(size,) * 3)
    group = (mesh.nodes[mesh.tets].mean(1)[:, 0] > size / 2).astype(np.int64)
    mesh = mesh._replace(tissue=group)
    margin = 0.4 * size
    n_vox = int(np.ceil((size + 2 * margin) / p.voxel_mm)) + 1
    affine = np.diag([p.voxel_mm] * 3 + [1.0])
    affine[:3, 3] = -margin
    ijk = np.stack(np.meshgrid(*[np.arange(n_vox)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = ijk * p.voxel_mm - margin
    m = Image(_plane_waves(x, p.wavelength_mm).reshape((n_vox,) * 3), affine)
    skull = Image(np.zeros((n_vox,) * 3, np.uint8), affine)
    layout = ParamLayout(GROUPS, (("lam", 0), ("lam", 1), ("mu", 1)), (("mu", 0, 1.0),))
    pl, pm = mdl.prior_lam, mdl.prior_mu
    prior = {"lam": (pl.a, pl.b, pl.r1, pl.r2), "mu": (pm.a, pm.b, pm.r1, pm.r2)}
    phi_ref = [pl.r1 + (pl.r2 - pl.r1) * pl.a / (pl.a + pl.b)] * 2 + \
        [pm.r1 + (pm.r2 - pm.r1) * pm.a / (pm.a + pm.b)]
    gamma = None if mdl.t_s_prior is None else (mdl.t_s_prior.shape, mdl.t_s_prior.rate)
    post = build_posterior(mesh, build_ssd(mesh.nodes, mesh.tets, m, m,
                                           quadrature_level=p.quadrature_level),
                           skull, t_s=mdl.t_s, t_r=mdl.t_r, layout=layout, element_group=group,
                           prior=prior, phi_ref=phi_ref, rigid_sd=mdl.rigid_sd_mm, t_s_prior=gamma)
    return CalibrationProblem(mesh, post, layout, group, mdl.prior_normaliser == "exact", gamma,
                              mdl.data_t_s)


def _prior_draw(cp: CalibrationProblem, rng, phi):
    """``u`` ``(N, 3)`` from the elastic prior given ``phi`` (boundary Gaussian, interior FE)."""
    post, mesh = cp.posterior, cp.mesh
    h, schur = schur_complement(post, mesh, cp.element_group, phi)
    rigid = np.asarray(post.normaliser.rigid_b)
    prec = schur * float(post.inv_t_r) + float(post.inv_rigid_var) * rigid @ rigid.T
    chol = np.linalg.cholesky(0.5 * (prec + prec.T))
    u_b = sla.solve_triangular(chol.T, rng.standard_normal(len(prec)), lower=False)
    u = np.zeros_like(mesh.nodes)
    u[mesh.boundary], u[mesh.interior] = u_b.reshape(-1, 3), (h @ u_b).reshape(-1, 3)
    return u


def _prior_phi(cp: CalibrationProblem, rng, size=None):
    """Free parameters drawn from their scaled Beta priors, ``(*size, n_free)``."""
    pr = cp.posterior.prior
    a, b, r1, r2 = (np.asarray(v) for v in (pr.a, pr.b, pr.r1, pr.r2))
    shape = None if size is None else tuple(size) + (len(a),)
    return r1 + (r2 - r1) * rng.beta(a, b, size=shape)


class Truths(NamedTuple):
    """Truths and data of the replicas: ``theta`` ``(R, dim)`` (``[u_b.ravel(), phi]``), ``f_q``
    ``(R, M, Q)`` the simulated data, ``redraws`` ``(R,)`` prior draws refused by the hard
    constraints before each replica's truth, ``t_s`` ``(R,)`` the temperature each replica's
    noise was drawn with."""

    theta: np.ndarray
    f_q: np.ndarray
    redraws: np.ndarray
    t_s: np.ndarray


def _valid(cp: CalibrationProblem, u) -> bool:
    mesh, post = cp.mesh, cp.posterior
    x = mesh.nodes + u
    if np.any(signed_volumes(x, mesh.tets) <= 0):
        return False
    return not bool(np.any(np.asarray(points_forbidden(post.skull, jnp.asarray(x)))))


def simulate(cp: CalibrationProblem, n: int, rng, *, max_redraws: int = 1000) -> Truths:
    """``n`` truths from the prior and their data from the likelihood (module docstring, step 2).

    Raises
    ------
    RuntimeError
        More than ``max_redraws`` prior draws in a row broke the hard constraints (the prior
        is too wide for the mesh: lower ``t_r`` or ``rigid_sd_mm``).
    """
    post, mesh = cp.posterior, cp.mesh
    term = post.similarity
    m_at = jax.jit(lambda u: moving_values(term, u[jnp.asarray(mesh.tets)]))
    w_q = np.asarray(term.sqrt_w) ** 2
    gamma = cp.t_s_prior
    thetas, fqs, redraws, temps = [], [], [], []
    for _ in range(n):
        for tries in range(max_redraws + 1):
            phi = _prior_phi(cp, rng)
            u = _prior_draw(cp, rng, phi)
            if _valid(cp, u):
                break
        else:
            raise RuntimeError(f"calibration, truths: {max_redraws} prior draws in a row inverted "
                               "an element or left the image; lower model.t_r or "
                               "model.rigid_sd_mm")
        if cp.data_t_s is not None:
            t_s = cp.data_t_s
        elif gamma is not None:
            t_s = 1.0 / rng.gamma(gamma[0], 1.0 / gamma[1])
        else:
            t_s = float(1.0 / post.inv_t_s)
        redraws.append(tries)
        temps.append(t_s)
        thetas.append(np.r_[u[mesh.boundary].ravel(), phi])
        sd = np.sqrt(t_s / (2.0 * w_q))
        fqs.append(np.asarray(m_at(jnp.asarray(u))) + sd * rng.standard_normal(sd.shape))
    return Truths(np.array(thetas), np.array(fqs), np.array(redraws), np.array(temps))


def _starts(cp: CalibrationProblem, n: int, chains: int, rng) -> np.ndarray:
    """Chain starts ``(n, chains, dim)``: parameters from their priors, ``u_b`` at rest plus
    0.1 mm noise (never the truth)."""
    phi = _prior_phi(cp, rng, (n, chains))
    u = 0.1 * rng.standard_normal((n, chains, 3 * cp.posterior.n_boundary))
    return np.concatenate([u, phi], axis=-1)


class Replicas(NamedTuple):
    """Posterior draws of the replicas.

    Attributes
    ----------
    draws : (R, C, D, dim)
        Natural positions ``[u_b.ravel() (mm), phi]``.
    acceptance : (R, C, B)
        Mean acceptance of the ``u_b`` kernel, of the elastic random-walk moves and (with
        ``collapsed_moves``) of the collapsed moves over the draws.
    divergences : (R, C)
        Divergent NUTS transitions while drawing.
    gradients : (R, C)
        Mean gradient evaluations per transition while drawing.
    seconds : float
        Wall time of the program (compilation included).
    """

    draws: np.ndarray
    acceptance: np.ndarray
    divergences: np.ndarray
    gradients: np.ndarray
    seconds: float


def run_replicas(cp: CalibrationProblem, spec: CalibrationSpec, f_q, starts, key, *,
                 progress: bool = False) -> Replicas:
    """Posterior draws of every replica (module docstring, step 3).

    Every chain of every replica is one chain of the driver
    (:func:`bayesreg.sampling.driver.sample`) running the Gibbs kernel with Stan's warm-up
    (:func:`bayesreg.sampling.kernels.gibbs.as_algorithm`); each chain carries its replica's
    data ``f_q`` (and, with collapsed moves, its linearised likelihood) as its own data, so
    one compiled program serves them all.  ``sampler.draws`` draws per chain, no stop rule.

    Parameters
    ----------
    cp : CalibrationProblem
    spec : CalibrationSpec
    f_q : (R, M, Q) array
        Each replica's data.
    starts : (R, C, dim) array
        Natural chain starts.
    key : PRNGKey
    progress : bool
        Show the driver's progress bars.

    Returns
    -------
    Replicas
    """
    import math

    from bayesreg.model.posterior import condensation, full_displacement, similarity_weight
    from bayesreg.model.similarity import ssd_residuals
    from bayesreg.sampling.driver import sample
    from bayesreg.sampling.kernels import gibbs
    from bayesreg.sampling.kernels.target import laplace_likelihood, make_target

    s = spec.sampler
    post = cp.posterior
    nb3 = 3 * post.n_boundary
    theta_ref = np.r_[np.zeros(nb3), np.asarray(post.phi_ref)]
    chol = np.linalg.cholesky(gauss_newton_precision(post, cp.mesh, cp.element_group, theta_ref))
    # u_b = F w with F = R^-T, R R^T the Gauss-Newton precision at rest: F^-1 = R^T
    factor = jnp.asarray(sla.solve_triangular(chol.T, np.eye(nb3), lower=False))
    factor_inv = jnp.asarray(chol.T)
    interior0 = jnp.zeros((post.op.n_interior, 3))

    def posterior_of(f_q):
        return post._replace(similarity=post.similarity._replace(f_q=f_q))

    def curvature(p, theta):
        # Gauss-Newton curvature 2 J^T J / T_s of the similarity in u_b (interior by the map at
        # theta's parameters): dense, the problem is small
        h = condensation(p, theta)

        def residuals(u):
            u_i = (h @ u).reshape(-1, 3)
            u_n = full_displacement(p, u.reshape(-1, 3), u_i)
            return ssd_residuals(p.similarity, u_n[p.tets]).ravel()

        jac = jax.jacfwd(residuals)(theta[:nb3])
        r = residuals(theta[:nb3])
        return 2.0 * similarity_weight(p, r @ r) * jac.T @ jac

    def linearised(f_q, theta):
        p = posterior_of(f_q)
        return laplace_likelihood(p, theta, curvature(p, theta))

    def target_of(data):
        # data: the replica's f_q, and with collapsed moves the likelihood (A, b) linearised
        # at the chain's start, then where its warm-up ended
        return make_target(posterior_of(data[0]), center_u=jnp.zeros(nb3), factor=factor,
                           factor_inv=factor_inv, exact=cp.exact, condensed=True,
                           likelihood=tuple(data[1:]) if s.collapsed_moves else None)

    def relinearise(state):
        return state._replace(data=(state.data[0], *linearised(state.data[0], state.position)))

    n, c, dim = np.shape(starts)
    x0 = jnp.asarray(np.reshape(starts, (n * c, dim)))
    data = (jnp.repeat(jnp.asarray(f_q), c, axis=0),)
    if s.collapsed_moves:
        data = data + tuple(jax.jit(jax.vmap(linearised))(data[0], x0))
    algorithm = gibbs.as_algorithm(
        target_of, interior0, kind="nuts", max_tree_depth=s.max_tree_depth,
        elastic_moves=s.elastic_moves, collapsed_moves=s.collapsed_moves, chain_data=data,
        refresh=relinearise if s.collapsed_moves else None)
    # draws in chunks that also cut the warm-up exactly (its windows are the spec's)
    chunk = math.gcd(s.draws, -(-s.warmup_steps // s.thinning))
    res = sample(key, algorithm, x0, thinning=s.thinning, warmup_steps=s.warmup_steps,
                 max_draws=s.draws, min_draws=s.draws, chunk_draws=chunk, stop="paper",
                 progress=progress, chain_method=s.chain_method)

    def per_replica(a):
        return np.asarray(a).reshape((n, c) + np.shape(a)[1:])

    return Replicas(per_replica(res.positions), per_replica(res.acceptance.mean(axis=1)),
                    per_replica(res.divergences.sum(axis=1)), per_replica(res.grad_evals.mean(axis=1)),
                    float(res.timings["warmup_s"] + res.timings["sampling_s"]))


def ranks_of(truth, draws) -> np.ndarray:
    """Rank of each truth among its draws: the number of draws below it.

    Parameters
    ----------
    truth : (R, K) array
    draws : (R, L, K) array

    Returns
    -------
    (R, K) int array in ``0..L`` (uniform over it for a calibrated posterior; ties, which
    continuous posteriors do not make, count half).
    """
    truth = np.asarray(truth)[:, None, :]
    draws = np.asarray(draws)
    below = np.sum(draws < truth, axis=1)
    ties = np.sum(draws == truth, axis=1)
    return (below + ties // 2).astype(np.int64)


def _quantities(cp: CalibrationProblem, theta):
    """Scalar quantities ``(..., K)`` of positions ``(..., dim)`` and their names: the free
    parameters, ``lam/mu`` of each group, the rms boundary displacement (mm)."""
    theta = np.asarray(theta)
    nb3 = 3 * cp.posterior.n_boundary
    phi = theta[..., nb3:]
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(cp.posterior, jnp.asarray(phi)))
    u_rms = np.sqrt(np.mean(theta[..., :nb3] ** 2, axis=-1))
    names = list(cp.layout.free_names) + [f"lam/mu_{g}" for g in GROUPS] + ["u_rms"]
    return np.concatenate([phi, lam_g / mu_g, u_rms[..., None]], axis=-1), names


def _thin(draws, n: int):
    """``n`` draws ``(R, n, ...)`` evenly spaced over the chains' pooled draws ``(R, C, D, ...)``
    (chain after chain)."""
    r, c, d = draws.shape[:3]
    pooled = draws.reshape(r, c * d, *draws.shape[3:])
    return pooled[:, np.round(np.linspace(0, c * d - 1, n)).astype(int)]


def _covered(truth, draws, level: float):
    """Whether each truth ``(R, K)`` lies in the central ``level`` interval of its draws
    ``(R, S, K)``."""
    lo, hi = np.quantile(draws, [(1 - level) / 2, (1 + level) / 2], axis=1)
    return (truth >= lo) & (truth <= hi)


def _test(ranks, n_ranks: int, bins: int) -> dict:
    from scipy.stats import chisquare

    counts = np.bincount(np.asarray(ranks).ravel() * bins // (n_ranks + 1), minlength=bins)
    stat, p = chisquare(counts)
    return {"histogram": counts.tolist(), "chi2": float(stat), "p": float(p)}


def summarise(cp: CalibrationProblem, spec: CalibrationSpec, truths: Truths,
              reps: Replicas) -> dict:
    """Ranks, their chi-square tests and the interval coverage (module docstring, step 4).

    Returns
    -------
    dict
        ``quantities``: per free parameter, ratio and ``u_rms``: ``ranks`` (one per replica),
        ``histogram``, ``chi2``, ``p`` (SciPy's chi-square test against uniform bins),
        ``coverage`` per level of :data:`LEVELS`, ``bias`` (median over replicas of the
        posterior median minus the truth, relative to the truth); ``u_b``: the same pooled
        over all boundary coordinates of all replicas (``p`` then treats correlated
        coordinates as independent: indicative only); ``convergence``: per replica, the worst
        rank-normalised R-hat and the smallest bulk ESS of the quantities (ArviZ);
        ``verdict``: ``calibrated`` and the reasons it is not.
    """
    from bayesreg.sampling.convergence import rank_figures

    s = spec.sampler
    n_rank = s.ranks
    q_truth, names = _quantities(cp, truths.theta)
    q_draws, _ = _quantities(cp, reps.draws)  # (R, C, D, K)
    r = len(q_truth)
    pooled = q_draws.reshape(r, -1, q_draws.shape[-1])
    ranks = ranks_of(q_truth, _thin(q_draws, n_rank))
    out = {"replicas": r, "ranks_out_of": n_rank, "levels": list(LEVELS), "quantities": {}}
    median = np.median(pooled, axis=1)
    for k, name in enumerate(names):
        row = _test(ranks[:, k], n_rank, s.bins)
        row["ranks"] = ranks[:, k].tolist()
        row["coverage"] = {str(lv): float(np.mean(_covered(q_truth[:, [k]], pooled[:, :, [k]], lv)))
                           for lv in LEVELS}
        row["bias"] = float(np.median((median[:, k] - q_truth[:, k]) / np.abs(q_truth[:, k])))
        out["quantities"][name] = row
    nb3 = 3 * cp.posterior.n_boundary
    u_truth, u_draws = truths.theta[:, :nb3], reps.draws[..., :nb3]
    u_ranks = ranks_of(u_truth, _thin(u_draws, n_rank))
    u_pooled = u_draws.reshape(r, -1, nb3)
    row = _test(u_ranks, n_rank, s.bins)
    row["coverage"] = {str(lv): float(np.mean(_covered(u_truth, u_pooled, lv))) for lv in LEVELS}
    out["u_b"] = row
    conv = [rank_figures(q_draws[i][..., :-1]) for i in range(r)]
    out["convergence"] = {"rhat_rank_max": [c[0] for c in conv], "ess_bulk_min": [c[1] for c in conv]}
    out["sampler"] = {"acceptance_u": float(np.mean(reps.acceptance[..., 0])),
                      "acceptance_elastic": float(np.mean(reps.acceptance[..., 1])),
                      "acceptance_collapsed": (float(np.mean(reps.acceptance[..., 2]))
                                               if reps.acceptance.shape[-1] > 2 else None),
                      "divergences": int(np.sum(reps.divergences)),
                      "gradients_per_transition": float(np.mean(reps.gradients)),
                      "seconds": reps.seconds}
    out["verdict"] = verdict(out)
    return out


#: The issue's acceptance band of the 90% intervals' coverage and the smallest chi-square p.
COVERAGE_90 = (0.85, 0.95)
P_MIN = 0.01


def verdict(summary: dict) -> dict:
    """``{"calibrated": bool, "problems": [...]}``: every quantity's rank histogram uniform
    (chi-square ``p > P_MIN``) and every 90% coverage (the quantities' and the pooled
    boundary coordinates') within :data:`COVERAGE_90`."""
    problems = []
    lo, hi = COVERAGE_90
    rows = dict(summary["quantities"], u_b=summary["u_b"])
    for name, row in rows.items():
        if name != "u_b" and row["p"] <= P_MIN:
            problems.append(f"{name}: ranks not uniform (chi-square p {row['p']:.2g})")
        cov = row["coverage"]["0.9"]
        if not lo <= cov <= hi:
            problems.append(f"{name}: 90% intervals hold {cov:.0%} of the truths")
    return {"calibrated": not problems, "problems": problems}


def load_spec(path=None, overrides: list[str] | None = None) -> CalibrationSpec:
    """A calibration file (YAML; ``None``: every default) with ``key=value`` overrides.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ConfigError
        Bad YAML, an unknown key or a bad value (the message names it).
    """
    return load_model_file(path, CalibrationSpec, what="calibration file", overrides=overrides)


def table(summary: dict) -> str:
    """The summary as a Markdown table: coverage per level, rank test, bias per quantity."""
    levels = summary["levels"]
    head = ("| quantity | " + " | ".join(f"{lv:.0%} coverage" for lv in levels)
            + " | rank chi-square p | median bias |")
    lines = [head, "|" + "---|" * (len(levels) + 3)]
    rows = dict(summary["quantities"], u_b=summary["u_b"])
    for name, row in rows.items():
        cov = " | ".join(f"{row['coverage'][str(lv)]:.2f}" for lv in levels)
        p = f"{row['p']:.3f}" + (" (pooled)" if name == "u_b" else "")
        bias = f"{row['bias']:+.1%}" if "bias" in row else "-"
        lines.append(f"| {name} | {cov} | {p} | {bias} |")
    return "\n".join(lines)


def calibrate(spec: CalibrationSpec, out=None, *, progress: bool = True) -> dict:
    """Run the check of ``spec`` and write its folder; returns the summary (:func:`summarise`).

    Writes ``calibration.json`` (the spec, the summary, every rank), ``calibration.md`` (the
    table and the verdict), ``ranks.csv`` (one row per replica: the truths and their ranks)
    and ``rank_histograms.png``.

    Examples
    --------
    ``bayesreg calibrate configs/calibration.yaml`` on the command line; in Python:

    >>> import bayesreg
    >>> from bayesreg.experiments.calibration import calibrate, load_spec
    >>> bayesreg.configure_jax()
    >>> spec = load_spec(overrides=["replicas=2", "sampler.chains=2", "sampler.warmup_steps=20",
    ...                             "sampler.draws=10", "sampler.ranks=9"])
    >>> summary = calibrate(spec, "/tmp/bayesreg-calibration-doctest", progress=False)  # doctest: +SKIP
    """
    import csv
    import json
    import time
    from pathlib import Path

    from bayesreg.outputs.plots import rank_histograms

    def say(msg):
        if progress:
            print(f"bayesreg calibrate: {msg}", flush=True)

    out = Path(out or spec.dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    cp = calibration_problem(spec)
    rng = np.random.default_rng(spec.seed)
    truths = simulate(cp, spec.replicas, rng)
    say(f"{spec.replicas} truths drawn from the prior ({len(cp.mesh.nodes)} nodes, "
        f"{cp.posterior.n_boundary} on the boundary, {int(truths.redraws.sum())} prior draws "
        f"refused by the constraints), data from the likelihood ({time.perf_counter() - t0:.1f} s)")
    starts = _starts(cp, spec.replicas, spec.sampler.chains, rng)
    s = spec.sampler
    say(f"sampling {spec.replicas} x {s.chains} chains of {s.warmup_steps} warm-up and "
        f"{s.draws} x {s.thinning} transitions in one program ...")
    reps = run_replicas(cp, spec, truths.f_q, starts, jax.random.key(spec.seed), progress=progress)
    say(f"sampled in {reps.seconds:.1f} s")
    summary = summarise(cp, spec, truths, reps)
    q_truth, names = _quantities(cp, truths.theta)
    with open(out / "ranks.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["replica"] + [f"truth_{n}" for n in names] + [f"rank_{n}" for n in names]
                   + ["rhat_rank_max", "ess_bulk_min"])
        for i in range(spec.replicas):
            w.writerow([i] + [f"{v:.6g}" for v in q_truth[i]]
                       + [summary["quantities"][n]["ranks"][i] for n in names]
                       + [f"{summary['convergence']['rhat_rank_max'][i]:.4f}",
                          f"{summary['convergence']['ess_bulk_min'][i]:.1f}"])
    (out / "calibration.json").write_text(json.dumps(
        {"spec": spec.model_dump(mode="json"), "summary": summary}, indent=1))
    v = summary["verdict"]
    line = ("calibrated: every rank histogram uniform (chi-square p > 0.01) and every 90% "
            "coverage within 0.85-0.95" if v["calibrated"]
            else "NOT calibrated: " + "; ".join(v["problems"]))
    conv = summary["convergence"]
    mdl = spec.model
    temp = (f"T_s {mdl.t_s:g}" if mdl.t_s_prior is None else
            f"1 / T_s ~ Gamma({mdl.t_s_prior.shape:g}, {mdl.t_s_prior.rate:g}) integrated out")
    data = "" if mdl.data_t_s is None else f" (data simulated at T_s {mdl.data_t_s:g})"
    md = [f"# Calibration {spec.name}", "",
          f"{spec.replicas} replicas, prior normaliser {mdl.prior_normaliser}, {temp}{data}, "
          f"{s.collapsed_moves} collapsed moves; ranks among {s.ranks} draws; worst rank R-hat "
          f"{max(conv['rhat_rank_max']):.3f}, smallest bulk ESS "
          f"{min(conv['ess_bulk_min']):.0f} (of {s.chains * s.draws} draws).", "",
          table(summary), "", line, ""]
    (out / "calibration.md").write_text("\n".join(md))
    fig = rank_histograms(summary, s.bins)
    fig.savefig(out / "rank_histograms.png", dpi=110)
    say(f"outputs in {out}")
    return summary
