"""Where the chains start and with which proposal scales (:func:`initialise`).

The central start (:func:`start_center`) is a fraction of the synthetic truth (paper
Sec. 4.2) or a fast optical-flow registration of ``f`` to ``m``
(:mod:`bayesreg.data.registration`); with ``init.method: mode`` the posterior mode is searched
from it (:func:`bayesreg.inference.mode.find_mode`).  The chains start dispersed around it
(:func:`initial_positions`), over-dispersed by draws of the Laplace approximation
(:func:`laplace_precision`) after a mode search.  The proposal scales
(:func:`proposal_scale`) whiten the random walk, or the gradient kernels' coordinates, by
the same Gauss-Newton precision.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla
import scipy.ndimage as ndi

from bayesreg.data import labels as L
from bayesreg.config import Config
from bayesreg.mesh.constraints import skull_distance
from bayesreg.fem.element import interior_solver, node_dofs, stiffness_matrix
from bayesreg.data.images import Image
from bayesreg.inference.mode import find_mode
from bayesreg.mesh.tetmesh import Mesh
from bayesreg.model.posterior import (
    Posterior, discrepancy_log_prior, discrepancy_map, discrepancy_of, discrepancy_stiffness,
    elastic_groups, energies, similarity_weight)
from bayesreg.model.problem import Problem, at_start
from bayesreg.data.registration import displacement_at, optical_flow_displacement
from bayesreg.inference.targets import make_logdensity

__all__ = ["Initialisation", "initialise", "start_center", "start_check", "registration_field",
           "initial_positions",
           "laplace_precision", "gauss_newton_precision", "schur_complement", "proposal_scale"]


def start_center(problem: Problem, cfg: Config, *, check=None, flow=None) -> tuple[np.ndarray, dict]:
    """Central start ``(dim,)`` of the chains and how it was made.

    ``u_b``: ``init.fraction * truth`` (``init.start: between``, paper Sec. 4.2; identity
    without a truth) or the displacement of a fast registration of ``f`` to ``m``
    (``init.start: registration``: scikit-image optical flow, see
    :func:`bayesreg.data.registration.optical_flow_displacement`) at the boundary nodes.  Nodes
    that the start would put into the skull (or an element it would invert) are pulled back
    toward zero by halving until the start is valid and no node is nearer the skull than half
    the barrier's width (:func:`bayesreg.mesh.constraints.skull_distance`, the one smooth skull of
    every stage).  Parameters: ``model.initial_*``.

    Parameters
    ----------
    check : callable, optional
        The jitted start check of :func:`start_check` (built here if not given; pass the
        one :func:`initial_positions` uses so that one program serves both).
    flow : Image, optional
        ``init.start: registration``: the :func:`registration_field` if already computed
        (made here, and its time recorded, otherwise).

    Returns
    -------
    theta : (dim,) ndarray
        (a model discrepancy, if any, at zero)
    info : dict
        ``{"start", "shrink"}`` (and the time of a registration made here)

    Raises
    ------
    ValueError
        If 30 halvings of the start's displacements find no valid start.
    """
    post, mesh = problem.posterior, problem.mesh
    nb = post.n_boundary
    info: dict = {"start": cfg.init.start}
    base_u = np.zeros((nb, 3))
    if cfg.init.start == "registration":
        if flow is None:
            t = time.perf_counter()
            flow = registration_field(problem, cfg.init.registration, outside=cfg.synthetic.outside)
            info["registration_s"] = time.perf_counter() - t
        base_u = displacement_at(flow, mesh.nodes[mesh.boundary])
    elif problem.truth is not None:
        base_u = cfg.init.fraction * problem.truth.u[mesh.boundary]
    # a model discrepancy (if any) starts at zero: the interior at the FE solve
    theta = np.concatenate([base_u.ravel(), np.zeros(post.n_discrepancy), problem.phi_init])
    check = start_check(problem, cfg) if check is None else check
    shrink = 1.0
    # a node nearer the skull than half the barrier's width counts as offending: its barrier
    # term (and gradient) would dwarf the rest of log p at the start of the mode search; one
    # nearer than that at rest may close half its rest clearance (halving reaches it)
    rest = np.asarray(skull_distance(post.skull, jnp.asarray(mesh.nodes[mesh.boundary])))
    limit = np.maximum(-0.5 * float(post.barrier_width), 0.5 * rest)  # d < limit <= 0
    for _ in range(30):
        moved = mesh.nodes[mesh.boundary] + theta[: 3 * nb].reshape(nb, 3)
        bad = np.asarray(skull_distance(post.skull, jnp.asarray(moved))) >= limit
        # the one start, as each of the chains' rows: the program of the dispersed starts
        if (not bad.any() and
                np.isfinite(np.asarray(check(jnp.tile(jnp.asarray(theta), (cfg.sampler.chains, 1))))[0])):
            info["shrink"] = shrink
            return theta, info
        # pull back only the offending nodes (in or near the skull, out of the image) first
        u = theta[: 3 * nb].reshape(nb, 3)
        u[bad if bad.any() else slice(None)] *= 0.5
        theta[: 3 * nb] = u.ravel()
        shrink *= 0.5
    raise ValueError("could not find a valid central start (skull, inverted element or solve)")


def registration_field(problem: Problem, method: str = "tvl1", *, outside: str = "extend") -> Image:
    """A dense registration of ``f`` to ``m`` on the brain, kept within 3 voxels of the
    intracranial tissues and zero beyond: scikit-image optical flow (``method`` ``"tvl1"``
    or ``"ilk"``, :func:`bayesreg.data.registration.optical_flow_displacement`) or ANTs SyN
    (``"syn"``, :func:`bayesreg.interop.syn.syn_displacement`).

    Both images as they are, except for a synthetic FE truth whose ``m`` holds the warped
    brain alone (``outside="background"``, ``synthetic.outside``: 0 where no deformed
    element reaches): then ``f``'s brain alone, so that neither image has tissue the other
    lacks.  With ``m`` continued outside the brain (``"extend"``, the default), real data
    and dense truths, masking ``f`` alone would pull the brain's surface toward the skull
    and scalp that only ``m`` shows.

    Returns
    -------
    Image
        ``(I, J, K, 3)`` displacement, world mm, ``m(x + u(x)) ~= f(x)``.

    Raises
    ------
    ValueError
        ``outside`` neither ``"extend"`` nor ``"background"``.
    ImportError
        ``"syn"`` without ANTsPy installed.
    RuntimeError
        ANTs failed (``"syn"``).
    """
    brain = np.isin(problem.labels.data, L.TISSUE_LABELS)
    if outside not in ("extend", "background"):
        raise ValueError(f"outside must be 'extend' or 'background' (synthetic.outside), got {outside!r}")
    f_reg = problem.f
    if problem.truth is not None and problem.truth.field is None and outside == "background":
        f_reg = Image(np.where(brain, problem.f.data, 0.0), problem.f.affine)
    mask = ndi.binary_dilation(brain, iterations=3)
    if method == "syn":
        from bayesreg.interop.syn import syn_displacement

        return syn_displacement(f_reg, problem.m, mask=mask)
    return optical_flow_displacement(f_reg, problem.m, method=method, mask=mask)


def start_check(problem: Problem, cfg: Config):
    """The jitted check of chain starts: ``(chains, dim) -> (chains,)`` log posterior.

    Each row is evaluated from a cold interior (zeros); ``-inf`` marks a start that violates
    a hard constraint (skull, inverted element, prior support) or whose solve did not
    converge.  :func:`start_center` and :func:`initial_positions` share it, so a run
    compiles one program for both.
    """
    logdensity = make_logdensity(problem, cfg)
    zeros = jnp.zeros((problem.posterior.op.n_interior, 3))

    def start_logdensity(theta):
        return logdensity(theta, zeros)[0]

    return jax.jit(jax.vmap(start_logdensity))


def initial_positions(problem: Problem, cfg: Config, center, rng, prec=None, *,
                      check=None) -> np.ndarray:
    """Dispersed starts ``(chains, dim)`` around ``center``.

    ``u_b`` (and a model discrepancy, if any): Gaussian jitter of ``init.perturb_mm`` (method ``between``), or
    ``init.overdispersion`` times a draw from the Laplace approximation ``N(0, prec^-1)``
    (method ``mode``).  Parameters: log-normal jitter ``init.param_jitter``, clipped into
    the prior support.  Starts that violate a hard constraint are redrawn closer to the
    centre (halving the jitter, at most 20 times).  ``check``: as in :func:`start_center`.

    Raises
    ------
    ValueError
        If some chain has no valid start after 20 halvings.
    """
    post = problem.posterior
    nb3 = post.n_displacement
    c = cfg.sampler.chains
    lo = np.asarray(post.prior.r1)
    hi = np.asarray(post.prior.r2)
    chol = None
    if cfg.init.method == "mode":
        chol = sla.cholesky(prec, lower=True)
    check = start_check(problem, cfg) if check is None else check
    out = np.tile(np.asarray(center, np.float64), (c, 1))
    todo = np.arange(c)
    shrink = 1.0
    for _ in range(20):
        z = rng.standard_normal((len(todo), nb3))
        if chol is None:
            du = cfg.init.perturb_mm * z
        else:
            du = cfg.init.overdispersion * sla.solve_triangular(chol, z.T, lower=True, trans="T").T
        phi = center[nb3:] * np.exp(cfg.init.param_jitter * rng.standard_normal((len(todo), post.n_free)))
        out[todo, :nb3] = center[:nb3] + shrink * du
        out[todo, nb3:] = np.clip(phi, lo + 1e-3 * (hi - lo), hi - 1e-3 * (hi - lo))
        ok = np.isfinite(np.asarray(check(jnp.asarray(out))))
        todo = np.flatnonzero(~ok)
        if todo.size == 0:
            return out
        shrink *= 0.5
    raise ValueError(f"could not find valid starts for chains {todo.tolist()}")


def laplace_precision(problem: Problem, theta) -> np.ndarray:
    """Gauss-Newton precision of ``u_b`` (and a model discrepancy, if any) at ``theta`` with the
    parameters held fixed (:func:`gauss_newton_precision` of the problem's posterior)."""
    return gauss_newton_precision(problem.posterior, problem.mesh, problem.element_group, theta)


def schur_complement(post: Posterior, mesh: Mesh, element_group, phi):
    """The interior map and the Schur complement of ``K`` at the parameters ``phi``
    ``(n_free,)``, by SciPy (sparse LU of ``K_ii``).

    Returns
    -------
    h : (3 n_i, 3 n_b) array
        ``u_i = h u_b`` solves ``K_ii u_i = -K_ib u_b`` (DOFs node-major, interior nodes in
        ``mesh.interior`` order, boundary nodes in ``mesh.boundary`` order).
    schur : (3 n_b, 3 n_b) array
        ``S = K_bb - K_bi K_ii^-1 K_ib``, so that ``E_r = u_b^T S u_b / 2``.
    """
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, jnp.asarray(phi)))
    g = np.asarray(element_group)
    k = stiffness_matrix(mesh.nodes, mesh.tets, lam_g[g], mu_g[g]).tocsr()
    solver = interior_solver(k, mesh.boundary, mesh.interior)
    bd = solver.boundary_dofs
    h = -solver.lu.solve(solver.k_ib.toarray())
    return h, k[bd][:, bd].toarray() + solver.k_ib.T @ h


def gauss_newton_precision(post: Posterior, mesh: Mesh, element_group, theta) -> np.ndarray:
    """Gauss-Newton precision of ``u_b`` at ``theta`` with the parameters held fixed.

    ``P = 2 J^T J / T_s + S / T_r + R_b R_b^T / (n_b sigma^2)`` (``1 / T_s`` the posterior's
    :func:`~bayesreg.model.posterior.similarity_weight` at ``theta``): ``J`` is the Jacobian of the
    similarity term's residuals with respect to ``u_b`` through the interior map ``u_i = -K_ii^{-1} K_ib
    u_b``, ``S`` the Schur complement of ``K`` on the boundary DOFs (so ``E_r = u_b^T S u_b
    / 2``), the last term the posterior's prior along the rigid-body modes (0 if flat).
    With a model discrepancy ``d`` (:class:`~bayesreg.model.posterior.Discrepancy`,
    ``u_i = H u_b + d``) the precision is of ``[u_b, d]``: ``J`` over both, and the block of
    ``d`` adds ``tau K0_ii`` with ``tau = (a + 3 n_i / 2) / (b + q)`` the posterior mean of
    ``1 / T_d`` given ``theta``'s ``d`` (the positive part of the Student prior's curvature);
    low rank (``d = V c``) it is of ``[u_b, c]``, ``J`` through ``V`` and ``c``'s block
    ``tau Lambda``.

    Parameters
    ----------
    post : Posterior
    mesh : Mesh
        The posterior's mesh.
    element_group : (M,) int array
        Parameter group of each element.
    theta : (dim,) array
        ``[u_b.ravel() (mm), phi]`` (``[u_b.ravel(), d.ravel(), phi]`` with a discrepancy).

    Returns
    -------
    (n, n) array
        ``n`` = :attr:`~bayesreg.model.posterior.Posterior.n_displacement` (``3 n_b``, plus
        the discrepancy's ``3 n_i`` or ``r``); dense, symmetric, with a ridge of ``1e-6``
        times its mean diagonal.
    """
    nb = len(mesh.boundary)
    theta = np.asarray(theta)
    phi = theta[post.n_displacement:]
    h, schur = schur_complement(post, mesh, element_group, phi)
    bd, idf = node_dofs(mesh.boundary), node_dofs(mesh.interior)
    # residual Jacobian w.r.t. nodal displacements, through the interior map
    u_b = theta[: 3 * nb]
    disc = post.discrepancy
    basis = (None if disc is None or (disc.basis is None and disc.sensitivities is None)
             else discrepancy_map(post))  # the interior moves by basis @ theta's d entries
    d = (np.asarray(discrepancy_of(post, jnp.asarray(theta))).ravel() if disc is not None
         else np.zeros(0))
    u = np.zeros(3 * len(mesh.nodes))
    u[bd] = u_b
    u[idf] = h @ u_b + (d if d.size else 0.0)
    u = u.reshape(-1, 3)
    gram = post.similarity.gram(u, mesh.tets, len(mesh.nodes))
    g_ib, g_ii = gram[idf][:, bd], gram[idf][:, idf]
    g_ii_h = g_ii @ h
    jtj = gram[bd][:, bd].toarray() + g_ib.T @ h + h.T @ g_ib + h.T @ g_ii_h
    if d.size:  # J over [u_b, d] (or [u_b, c], d = V c): d moves the interior nodes directly
        cross = g_ib.T.toarray() + g_ii_h.T  # (3 n_b, 3 n_i)
        g_dd = g_ii.toarray()
        if basis is not None:
            cross, g_dd = cross @ basis, basis.T @ g_dd @ basis
        jtj = np.block([[jtj, cross], [cross.T, g_dd]])
    # E_s matters only where the temperature is integrated out (similarity_weight)
    e_s = energies(post, jnp.asarray(u), jnp.asarray(phi))[0] if float(post.t_s_shape) > 0 else 0.0
    prec = 2.0 * float(similarity_weight(post, e_s)) * jtj
    prior = float(post.inv_t_r) * schur
    rigid = np.asarray(post.normaliser.rigid_b)
    prior = prior + float(post.inv_rigid_var) * rigid @ rigid.T
    prec[: 3 * nb, : 3 * nb] += prior
    if d.size:
        disc = post.discrepancy
        _, q = discrepancy_log_prior(post, discrepancy_of(post, jnp.asarray(theta), projected=False))
        tau = float(disc.shape) / (float(disc.rate) + float(q))
        prec[3 * nb:, 3 * nb:] += tau * np.asarray(discrepancy_stiffness(post))
    prec = 0.5 * (prec + prec.T)
    ridge = 1e-6 * np.trace(prec) / len(prec)
    return prec + ridge * np.eye(len(prec))


def proposal_scale(problem: Problem, cfg: Config, prec=None):
    """Initial jumping-kernel scales ``(sigma_u, sigma_phi)`` of the two coordinate blocks.

    ``sigma_u``: for ``proposal: laplace`` the ``(3 n_b, 3 n_b)`` factor ``2.38 / sqrt(3 n_b)
    R^-T`` with ``prec = R R^T`` the Gauss-Newton precision of ``u_b``
    (:func:`laplace_precision`), i.e. proposal covariance ``2.38^2 / d prec^-1``; for
    ``isotropic`` the paper's ``sigma_u`` (Eq. 14) as a ``(3 n_b,)`` vector.
    ``sigma_phi``: ``sigma_lam`` / ``sigma_mu`` per free parameter, ``(n_free,)``.
    """
    post = problem.posterior
    s = cfg.sampler
    sig_p = np.array([s.sigma_lam if p == "lam" else s.sigma_mu for p, _ in problem.layout.free])
    nb3 = post.n_displacement
    if s.proposal == "isotropic":
        return np.full(nb3, s.sigma_u), sig_p
    chol = sla.cholesky(prec, lower=True)
    factor = sla.solve_triangular(chol, np.eye(nb3), lower=True, trans="T")  # R^-T
    return 2.38 / np.sqrt(nb3) * factor, sig_p


class Initialisation(NamedTuple):
    """Starts and jumping kernels of a run (saved with it, so a resumed run reuses them).

    Attributes
    ----------
    x0 : (C, dim)
        chain starts
    center : (dim,)
        central start (after the mode search, if any)
    sigma : tuple of arrays
        initial jumping-kernel scale per block
    blocked : bool
        u_b and the elastic parameters in separate blocks
    info : dict
        how the starts were made (mode search figures, timings)
    anchor : (n_b, 3) or None
        With an orthogonal discrepancy (``model.discrepancy_prior.orthogonal``): the ``u_b``
        (mm) its sensitivities were taken at (:func:`bayesreg.model.problem.at_start`).
    """

    x0: np.ndarray
    center: np.ndarray
    sigma: tuple
    blocked: bool
    info: dict
    anchor: np.ndarray | None = None


def initialise(problem: Problem, cfg: Config, *, flow=None) -> Initialisation:
    """Central start (:func:`start_center`, given ``flow``), optional mode search, dispersed
    starts, kernels."""
    rng = np.random.default_rng(cfg.seed)
    t = time.perf_counter()
    check = start_check(problem, cfg)
    center, info = start_center(problem, cfg, check=check, flow=flow)
    info["method"] = cfg.init.method
    info["proposal"] = cfg.sampler.proposal

    def search(posterior, theta):
        return find_mode(posterior, theta, iterations=cfg.init.optimizer_iterations,
                         optimize_parameters=cfg.init.optimize_parameters,
                         exact=cfg.model.prior_normaliser == "exact", rtol=cfg.solver.rtol,
                         maxiter=cfg.solver.maxiter)

    if cfg.init.method == "mode":
        mode = search(problem.posterior, center)
        center = mode.theta
        info.update({k: v for k, v in mode._asdict().items()
                     if k != "theta" and not (k == "parameter_iterations_exact" and v is None)})
    anchor = None
    if cfg.model.discrepancy_prior.orthogonal:
        # the sensitivities at the central start's u_b; the start's deviation along them no
        # longer displaces the interior, so the search goes on under the orthogonal model
        anchor = center[:3 * problem.posterior.n_boundary].reshape(-1, 3).copy()
        problem = at_start(problem, cfg, anchor)
        if cfg.init.method == "mode":
            mode = search(problem.posterior, center)
            center = mode.theta
            info["orthogonal_search"] = {k: mode._asdict()[k] for k in
                                         ("logp_start", "logp_mode", "iterations", "message")}
    prec = None
    if cfg.init.method == "mode" or cfg.sampler.proposal == "laplace":
        prec = laplace_precision(problem, center)
    x0 = initial_positions(problem, cfg, center, rng, prec, check=check)
    post = problem.posterior
    nb3 = post.n_displacement
    if cfg.sampler.gradient:
        # u_b = c + F w: F = R^-T with prec = R R^T (laplace), or 1 mm (isotropic)
        if cfg.sampler.proposal == "laplace":
            chol = sla.cholesky(prec, lower=True)
            factor = sla.solve_triangular(chol, np.eye(nb3), lower=True, trans="T")
        else:
            factor = np.ones(nb3)
        info["init_s"] = time.perf_counter() - t
        return Initialisation(x0, center, (factor, np.full(post.n_free, cfg.sampler.sigma_eta)), True,
                              info, anchor)
    sigma_u, sigma_p = proposal_scale(problem, cfg, prec)
    info["init_s"] = time.perf_counter() - t
    if cfg.sampler.blocked:
        sigma = (sigma_u, sigma_p)
    elif sigma_u.ndim == 1:  # the paper's joint proposal (Eq. 14)
        sigma = (np.concatenate([sigma_u, sigma_p]),)
    else:
        joint = np.zeros((post.dim, post.dim))
        joint[:nb3, :nb3] = sigma_u * np.sqrt(nb3 / post.dim)
        joint[np.arange(nb3, post.dim), np.arange(nb3, post.dim)] = sigma_p
        sigma = (joint,)
    return Initialisation(x0, center, sigma, cfg.sampler.blocked, info, anchor)
