"""What the samplers run for a problem under a config: log-densities, kernels' ingredients.

:func:`logdensity_fn` closes the posterior's log-density (:func:`bayesreg.model.posterior.log_density`)
over the solver's tolerance and the prior normaliser; :func:`make_logdensity` does so from a
config.  :func:`dense_preconditioning` decides whether the chains' CG solves use a dense
``K_ii^-1`` per chain (``solver.preconditioner``), :func:`rw_preconditioner` and
:func:`rw_condensation` build the random walk's cached preconditioner and interior map, and
:func:`gradient_target` the gradient kernels' :class:`~bayesreg.sampling.kernels.target.Target` (a
joint one where :func:`use_joint` says so).  :func:`sampling_algorithm` puts them together
into the :class:`~bayesreg.sampling.kernels.base.SamplingAlgorithm` that ``sampler.kind``
names, for the driver (:func:`bayesreg.sampling.driver.sample`).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from bayesreg.config import Config
from bayesreg.sampling.kernels import gibbs, rwmh
from bayesreg.sampling.kernels.base import SamplingAlgorithm
from bayesreg.sampling.kernels.rwmh import Condensation, Preconditioner
from bayesreg.sampling.kernels.surrogate import SurrogateRebuild
from bayesreg.sampling.kernels.target import (
    Target, joint_target, laplace_likelihood, make_target, nodal_laplace_likelihood)
from bayesreg.fem.normaliser import add_normaliser
from bayesreg.model.parameters import from_unconstrained, to_unconstrained
from bayesreg.model.posterior import (
    Posterior, condensation, log_density, log_density_condensed, log_normaliser,
    normaliser_surrogate, preconditioner, prior_precision, similarity_curvature, split_position,
    surrogate_normaliser)
from bayesreg.fem.preconditioners import DENSE_MAX_DOFS
from bayesreg.model.problem import Problem

__all__ = ["logdensity_fn", "make_logdensity", "dense_budget_bytes", "dense_preconditioning",
           "cg_preconditioner", "rw_preconditioner", "rw_condensation", "gradient_target",
           "use_joint", "sampling_algorithm", "DENSE_HOST_BUDGET", "SURROGATE_TOLERANCE"]


def logdensity_fn(post: Posterior, *, exact: bool = False, rtol: float = 1e-8, maxiter: int = 1000,
                  preconditioned: bool = False):
    """``(theta, interior_guess) -> (logp, aux)`` closed over the posterior (for the samplers).

    Parameters
    ----------
    post : Posterior
    exact : bool
        Add the exact normaliser ``(1/2) log pdet S(lam, mu)``
        (:func:`bayesreg.model.posterior.log_normaliser`, one dense factorisation).
    rtol, maxiter
        The CG solve's tolerance and cap (:func:`bayesreg.model.posterior.log_density`).
    preconditioned : bool
        Return ``(theta, interior_guess, precond) -> (logp, aux)`` instead, the interior
        solve preconditioned by ``precond`` (:func:`bayesreg.model.posterior.preconditioner`).
    """
    base = partial(log_density, post, rtol=rtol, maxiter=maxiter)

    def logdensity(theta, interior, precond=None):
        lp, aux = base(theta, interior, precond=precond)
        if not exact:
            return lp, aux
        ln = log_normaliser(post, split_position(post, theta)[1])
        return add_normaliser(lp, ln), aux

    if preconditioned:
        return logdensity
    return lambda theta, interior: logdensity(theta, interior)


def make_logdensity(problem: Problem, cfg: Config, *, preconditioned: bool = False):
    """:func:`logdensity_fn` of ``problem`` with ``model.prior_normaliser`` and ``solver.*``."""
    return logdensity_fn(problem.posterior, exact=cfg.model.prior_normaliser == "exact",
                         rtol=cfg.solver.rtol, maxiter=cfg.solver.maxiter,
                         preconditioned=preconditioned)


SURROGATE_TOLERANCE = 1.0
"""Nats: ``sampler.normaliser_surrogate: auto`` rebuilds the surrogate after the warm-up
where its correction spans more than this over the chains
(:class:`bayesreg.sampling.kernels.surrogate.SurrogateRebuild`)."""

DENSE_HOST_BUDGET = 2 * 2**30  # bytes of the chains' float32 K_ii^-1 together, on a CPU


def dense_budget_bytes() -> int:
    """Bytes that the chains' dense preconditioners (float32 ``K_ii^-1``) may take together.

    On a CPU :data:`DENSE_HOST_BUDGET` (2 GiB).  On an accelerator that reports its memory
    (``memory_stats()['bytes_limit']`` of the default device), a sixteenth of it and at
    least 2 GiB: building the inverses peaks at about 4 times their float32 size (float64
    ``K_ii`` and its factor), so the build stays within a quarter of the device.
    """
    if jax.default_backend() == "cpu":
        return DENSE_HOST_BUDGET
    try:
        limit = int((jax.devices()[0].memory_stats() or {})["bytes_limit"])
    except (KeyError, TypeError, ValueError, RuntimeError, NotImplementedError):
        return DENSE_HOST_BUDGET  # a backend that does not report its memory
    return max(DENSE_HOST_BUDGET, limit // 16)


def dense_preconditioning(problem: Problem, cfg: Config, *, n_chains: int | None = None) -> bool:
    """Whether the samplers' CG solves use the dense preconditioner (``solver.preconditioner``).

    Never without interior nodes (``model.interior: sample``).  ``auto``: not where the
    posterior has the spectral one (one parameter group, see
    :func:`cg_preconditioner`); else where ``3 n_i <= DENSE_MAX_DOFS`` (4096) and the
    chains' float32 inverses, ``4 (3 n_i)^2`` bytes each, fit :func:`dense_budget_bytes`
    together (2 GiB on a CPU; the paper's size: about 8 MB a chain).  ``n_chains`` defaults
    to ``sampler.chains``.
    """
    if problem.posterior.op.n_interior == 0:  # every node sampled: nothing to solve
        return False
    choice = cfg.solver.preconditioner
    if choice != "auto":
        return choice == "dense"
    if problem.posterior.spectral is not None:
        return False
    n = 3 * problem.posterior.op.n_interior
    chains = cfg.sampler.chains if n_chains is None else n_chains
    return n <= DENSE_MAX_DOFS and chains * 4 * n * n <= dense_budget_bytes()


def cg_preconditioner(problem: Problem, cfg: Config, *, n_chains: int | None = None) -> str:
    """Name of the samplers' CG preconditioner: ``spectral``, ``dense`` or ``block-jacobi``."""
    if dense_preconditioning(problem, cfg, n_chains=n_chains):
        return "dense"
    return "spectral" if problem.posterior.spectral is not None else "block-jacobi"


def rw_preconditioner(problem: Problem, cfg: Config) -> Preconditioner:
    """The random walk's :class:`~bayesreg.sampling.kernels.rwmh.Preconditioner` (dense ``K_ii^-1``)."""
    post = problem.posterior
    return Preconditioner(make_logdensity(problem, cfg, preconditioned=True),
                          lambda theta: preconditioner(post, theta))


def rw_condensation(problem: Problem, cfg: Config) -> Condensation:
    """The random walk's :class:`~bayesreg.sampling.kernels.rwmh.Condensation` of the ``u_b`` block
    (cache ``(H, log_norm)``, ``sampler.u_moves`` moves per step)."""
    post = problem.posterior
    exact = cfg.model.prior_normaliser == "exact"

    def build(theta):
        ln = log_normaliser(post, split_position(post, theta)[1]) if exact else jnp.zeros(())
        return condensation(post, theta), ln

    def logdensity(theta, cache):
        lp, aux = log_density_condensed(post, theta, cache[0])
        return add_normaliser(lp, cache[1]), aux

    return Condensation(logdensity, build, 0, cfg.sampler.u_moves)


def gradient_target(problem: Problem, cfg: Config, center, factor, *, surrogate_at=None) -> Target:
    """The gradient kernels' target of ``problem`` in the coordinates ``u_b = center + factor w``
    (:func:`bayesreg.sampling.kernels.target.make_target`; ``center`` ``(dim,)``, of which the
    first ``3 n_b`` entries are used, ``3 (n_b + n_i)`` with a model discrepancy: ``[u_b, d]``),
    wrapped by :func:`bayesreg.sampling.kernels.target.joint_target` (the parameters' logits
    centred on ``center``'s) where :func:`use_joint` says so.  Under the exact normaliser the
    joint trajectories see its surrogate built at ``surrogate_at`` ``(n_free,)`` (natural
    parameters; default ``center``'s)."""
    post = problem.posterior
    nb3 = post.n_displacement  # u_b (and a model discrepancy, if any)
    joint = use_joint(problem, cfg)
    base = make_target(post, center_u=center[:nb3], factor=factor,
                       exact=cfg.model.prior_normaliser == "exact",
                       condensed=cfg.sampler.use_condensed and not joint, rtol=cfg.solver.rtol,
                       maxiter=cfg.solver.maxiter, precondition=dense_preconditioning(problem, cfg),
                       likelihood=(_likelihood(problem, center, factor) if cfg.sampler.collapsed_moves
                                   and cfg.collapsed_carry == "conditional" else None))
    if not joint:
        return base
    surrogate = None
    if cfg.model.prior_normaliser == "exact" and post.normaliser.grounded.unit is not None:
        # the trajectories see a smooth surrogate built at the starts' centre (or at
        # surrogate_at); one exact normaliser per transition corrects it (kernels.surrogate)
        s_data = normaliser_surrogate(post, np.asarray(center[nb3:] if surrogate_at is None
                                                       else surrogate_at))

        def surrogate(eta):
            return surrogate_normaliser(post, s_data, from_unconstrained(post.prior, eta)[0])
    return joint_target(base, center_eta=to_unconstrained(post.prior, jnp.asarray(center[nb3:])),
                        eta_scale=cfg.sampler.sigma_eta,
                        log_jacobian=lambda eta: from_unconstrained(post.prior, eta)[1],
                        surrogate=surrogate)


def use_joint(problem: Problem, cfg: Config) -> bool:
    """Whether the gradient kernel moves the elastic parameters with ``u_b``
    (``sampler.joint``; default: without collapsed moves, and under the exact normaliser
    where it has a surrogate: not the per-element model) rather than by Gibbs random-walk
    moves; only where the problem has free parameters."""
    s = cfg.sampler
    post = problem.posterior
    grouped = post.normaliser.grounded.unit is not None
    default = not s.collapsed_moves and (cfg.model.prior_normaliser == "paper" or grouped)
    joint = s.joint if s.joint is not None else default
    return bool(s.gradient and joint and post.n_free)


def _likelihood(problem: Problem, center, factor):
    """The collapsed moves' Gaussian likelihood, linearised at the central start ``center``.

    Of ``u_b``, with the Gauss-Newton curvature that ``factor`` holds (``F F^T = P^-1``,
    ``P`` the Gauss-Newton precision at ``center``,
    :func:`bayesreg.inference.initialisation.laplace_precision`): ``A = P - Q(phi_center)``
    (:func:`bayesreg.sampling.kernels.target.laplace_likelihood`).  With a model discrepancy,
    of the nodal displacement at ``center``, with the similarity's Gauss-Newton curvature
    ``2 J^T J / T_s`` over every node
    (:func:`bayesreg.sampling.kernels.target.nodal_laplace_likelihood`)."""
    post = problem.posterior
    nb3 = 3 * post.n_boundary
    if post.discrepancy is not None:
        return nodal_laplace_likelihood(post, *similarity_curvature(post, center))
    f_inv = np.linalg.inv(np.asarray(factor))
    a_lik = f_inv.T @ f_inv - np.asarray(prior_precision(post, jnp.asarray(center[nb3:])))
    return laplace_likelihood(post, jnp.asarray(center), 0.5 * (a_lik + a_lik.T))


def sampling_algorithm(problem: Problem, cfg: Config, init) -> SamplingAlgorithm:
    """The kernel ``cfg.sampler.kind`` names, with its warm-up, at the run's starts.

    Parameters
    ----------
    problem : Problem
    cfg : Config
    init : bayesreg.inference.initialisation.Initialisation
        Its centre and proposal scales (``init.sigma``: the random walk's per block, or the
        gradient kernels' ``u_b`` factor and elastic scales) and whether the random walk
        moves ``u_b`` and the parameters in blocks.

    Returns
    -------
    SamplingAlgorithm
        :func:`bayesreg.sampling.kernels.gibbs.as_algorithm` on :func:`gradient_target` for
        ``mala``, ``hmc`` and ``nuts``; :func:`bayesreg.sampling.kernels.rwmh.as_algorithm` on
        :func:`make_logdensity` (with the cached interior map and dense CG preconditioner
        where the config asks for them) for ``rwmh``.
    """
    s = cfg.sampler
    post = problem.posterior
    nb3 = post.n_displacement
    interior0 = jnp.zeros((post.op.n_interior, 3))
    if s.gradient:
        target = gradient_target(problem, cfg, init.center, init.sigma[0])
        rebuild = None
        if target.correction is not None and s.normaliser_surrogate != "start":
            rebuild = SurrogateRebuild(post.n_free, lambda phi: gradient_target(
                problem, cfg, init.center, init.sigma[0], surrogate_at=phi),
                tolerance=0.0 if s.normaliser_surrogate == "warmup" else SURROGATE_TOLERANCE)
        return gibbs.as_algorithm(
            target, interior0, kind=s.kind, step_size=s.step_size,
            eta_scale=init.sigma[1] if target.n_free else np.zeros(0), dense_mass=s.dense_mass,
            adapt_mass=s.adapt_mass, elastic_moves=s.elastic_moves,
            collapsed_moves=s.collapsed_moves, carry=cfg.collapsed_carry, num_integration_steps=s.hmc_steps,
            jitter_integration_steps=s.hmc_jitter, max_tree_depth=s.max_tree_depth,
            target_acceptance=s.target_acceptance, surrogate=rebuild)
    if init.blocked:
        blocks, adapt, names = (np.arange(nb3), np.arange(nb3, post.dim)), (True, True), ("u_b", "elastic")
    else:
        blocks, adapt, names = None, None, ("joint",)
    return rwmh.as_algorithm(
        make_logdensity(problem, cfg), interior0, tuple(init.sigma), blocks=blocks,
        adapt_diagonal=adapt, target_acceptance=s.target_acceptance or 0.25,
        condensation=rw_condensation(problem, cfg) if init.blocked and s.use_condensed else None,
        preconditioner=rw_preconditioner(problem, cfg) if dense_preconditioning(problem, cfg) else None,
        block_names=names, cg_preconditioner=cg_preconditioner(problem, cfg))
