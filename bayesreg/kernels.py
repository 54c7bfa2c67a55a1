"""Gradient kernels (MALA, HMC, NUTS) for the boundary displacements, in Gibbs with the
elastic parameters.

One transition (Metropolis-within-Gibbs, each part leaving the posterior invariant):

1. ``u_b | lam, mu``: one step of a BlackJAX gradient kernel on the boundary displacements,
   in preconditioned coordinates ``u_b = c + F w`` (``c`` the start's centre, ``F`` a fixed
   factor, by default ``R^-T`` of the Gauss-Newton precision ``R R^T`` at the start:
   a constant affine map, so the target is unchanged).  NUTS (:func:`blackjax.nuts`,
   multinomial, iterative), HMC (:func:`blackjax.hmc`; by default the number of leapfrog
   steps is drawn uniformly from ``1 .. 2L - 1`` each transition, mean ``L``, as
   :func:`blackjax.dynamic_hmc` does, which breaks the periodicity of a fixed trajectory
   length: Mackenzie 1989; Neal 2011, "MCMC using Hamiltonian dynamics", on the trajectory
   length) or
   MALA (HMC with one leapfrog step, which is MALA preconditioned by the inverse mass matrix).
   With ``condensed`` the interior comes from a cached dense map ``u_i = H(lam, mu) u_b``
   (no CG solve in the gradient), else from the CG solve with implicit differentiation.
2. ``lam, mu | u_b``: ``elastic_moves`` random-walk Metropolis steps on ``eta``, the logit of the free
   parameters on their prior support, with the log-Jacobian (:func:`bayesreg.posterior.
   from_unconstrained`) and, for ``prior_normaliser: exact``, the normaliser
   ``(1/2) log pdet S(lam, mu)`` (:func:`bayesreg.posterior.log_normaliser`).  If any move
   was accepted, the cache (``H`` and the normaliser) and the gradient state of part 1 are
   rebuilt once.

The elastic parameters move by a random walk rather than inside the gradient kernel because
they are few (1-6) and because the exact normaliser's gradient costs about eight dense
factorisations; the boundary displacements, about a thousand strongly correlated
coordinates, are where the gradient pays.

Warm-up (:func:`build_warmup_step`): Stan's windowed adaptation with BlackJAX's pieces
(:func:`blackjax.adaptation.step_size.dual_averaging_adaptation` for the step size,
:func:`blackjax.adaptation.mass_matrix.mass_matrix_adaptation` for a diagonal or dense inverse
mass matrix, :func:`blackjax.adaptation.window_adaptation.build_schedule` for the windows),
the elastic random walk's covariance from the same windows' covariance of ``eta``
(``2.38^2 / n_free`` times it, dense: Haario et al.'s adaptive Metropolis), and
Robbins-Monro on the log of a common multiplier toward acceptance 0.3.
Each chain adapts its own values; they are frozen after the warm-up.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from blackjax.adaptation.mass_matrix import mass_matrix_adaptation  # noqa: E402
from blackjax.adaptation.step_size import dual_averaging_adaptation  # noqa: E402
from blackjax.mcmc import hmc as bj_hmc  # noqa: E402
from blackjax.mcmc import nuts as bj_nuts  # noqa: E402
from blackjax.mcmc.proposal import static_binomial_sampling  # noqa: E402

__all__ = [
    "KINDS", "GibbsState", "GibbsInfo", "GibbsParams", "Cache", "Target", "make_target",
    "init", "build_kernel", "WarmupState", "build_warmup_step", "schedule", "default_target_acceptance",
]

KINDS = ("mala", "hmc", "nuts")
ELASTIC_TARGET_ACCEPTANCE = 0.3


def default_target_acceptance(kind: str) -> float:
    """Warm-up target of the u_b kernel's acceptance: 0.8 (HMC, NUTS), 0.57 (MALA), 0.25 (RW)."""
    return {"nuts": 0.8, "hmc": 0.8, "mala": 0.57, "rwmh": 0.25}[kind]


class Cache(NamedTuple):
    """What depends on the elastic parameters only, rebuilt when they move.

    Attributes
    ----------
    h : (3 n_i, 3 n_b) or (0,)
        Dense interior map (condensed targets), else an empty placeholder.
    log_norm : ()
        ``(1/2) log pdet S`` (exact normaliser) or 0 (the paper's prior).
    precond : DensePreconditioner or None
        The CG preconditioner of the solves (targets made with ``precondition=True``):
        built at the chain's parameters when a chunk starts (:meth:`Target.build_precond`)
        and kept when the rest of the cache is rebuilt (it only has to stay near
        ``K_ii^-1``; the solves meet the same tolerance).
    """

    h: jax.Array
    log_norm: jax.Array
    precond: object = None


class Target(NamedTuple):
    """The posterior seen by the Gibbs kernel (pure functions; see :func:`make_target`).

    Attributes
    ----------
    u_logdensity : callable
        ``(w, eta, cache, interior) -> logp``: log-density of ``w`` given ``eta``, up to
        terms that do not depend on ``w``; differentiable in ``w``.
    u_evaluate : callable
        ``(w, eta, cache, interior) -> (logp, interior, cg_iterations, solve_ok)``, the same
        value with the interior solution at ``w``.
    evaluate : callable
        ``(w, eta, interior, log_norm, precond=None) -> (logp_eta, logp_natural, interior,
        cg_iterations, solve_ok)``: the joint log-density over ``(w, eta)`` (with the
        log-Jacobian and the normaliser ``log_norm``) and over the natural parameters
        ``(u_b, lam, mu)`` (with the normaliser, without the Jacobian), from a solve that
        does not use the map ``H`` (preconditioned by ``precond`` if given).  The kernel passes
        ``precond`` only to targets with a ``build_precond``: a target without one may take
        the first four arguments alone.
    log_norm : callable
        ``eta -> ()`` the normaliser term (0 for the paper's prior).
    build_cache : callable
        ``(eta, log_norm) -> Cache`` (without a preconditioner).
    build_precond : callable or None
        ``eta -> DensePreconditioner`` at those parameters, or ``None`` (block Jacobi).
    position : callable
        ``(w, eta) -> theta``, the stored position ``[u_b.ravel(), phi]``.
    coordinates : callable
        ``theta -> (w, eta)``, the inverse of ``position``.
    n_free : int
    """

    u_logdensity: Callable
    u_evaluate: Callable
    evaluate: Callable
    log_norm: Callable
    build_cache: Callable
    position: Callable
    coordinates: Callable
    n_free: int
    build_precond: Callable | None = None


def make_target(post, *, center_u, factor, exact: bool, condensed: bool, rtol=1e-8, maxiter=1000,
                precondition: bool = False) -> Target:
    """:class:`Target` of a :class:`bayesreg.posterior.Posterior`.

    Parameters
    ----------
    post : Posterior
    center_u : (3 n_b,) array
        ``c`` of ``u_b = c + F w`` (mm).
    factor : (3 n_b,) or (3 n_b, 3 n_b) array
        ``F`` (mm per unit of ``w``): a vector of scales or a dense matrix.
    exact : bool
        Include the exact normaliser of the elastic prior (``prior_normaliser: exact``).
    condensed : bool
        Gradient moves take the interior from the cached dense map ``H`` instead of a CG solve.
    rtol, maxiter
        CG tolerance and cap (see :func:`bayesreg.posterior.log_density`).
    precondition : bool
        Precondition the CG solves (the elastic moves', and the gradient moves' without
        ``condensed``) by the dense ``K_ii^-1`` at the chain's parameters when the chunk
        started (:func:`bayesreg.posterior.preconditioner`): 2-3 iterations instead of
        40-180, the same tolerance.
    """
    from bayesreg.posterior import (
        add_normaliser, condensation, from_unconstrained, log_density, log_density_condensed, log_normaliser,
        preconditioner, to_unconstrained,
    )

    c = jnp.asarray(center_u)
    f = jnp.asarray(factor)
    nb3 = c.shape[0]
    dense = f.ndim == 2
    f_inv = jnp.linalg.inv(f) if dense else 1.0 / f

    def u_of(w):
        return c + (f @ w if dense else f * w)

    def theta_of(w, eta):
        phi, _ = from_unconstrained(post, eta)
        return jnp.concatenate([u_of(w), phi])

    def u_evaluate(w, eta, cache, interior):
        theta = theta_of(w, eta)
        if condensed:
            lp, aux = log_density_condensed(post, theta, cache.h)
        else:
            lp, aux = log_density(post, theta, interior, rtol=rtol, maxiter=maxiter, precond=cache.precond)
        return lp, aux.interior, aux.solve.iterations, aux.solve.converged

    def u_logdensity(w, eta, cache, interior):
        return u_evaluate(w, eta, cache, interior)[0]

    def log_norm(eta):
        if not exact:
            return jnp.zeros(())
        return log_normaliser(post, from_unconstrained(post, eta)[0])

    def evaluate(w, eta, interior, log_norm_value, precond=None):
        _, log_jac = from_unconstrained(post, eta)
        lp, aux = log_density(post, theta_of(w, eta), interior, rtol=rtol, maxiter=maxiter, precond=precond)
        lp_nat = add_normaliser(lp, log_norm_value)
        return lp_nat + log_jac, lp_nat, aux.interior, aux.solve.iterations, aux.solve.converged

    def build_cache(eta, log_norm_value):
        h = condensation(post, theta_of(jnp.zeros(nb3), eta)) if condensed else jnp.zeros((0,))
        return Cache(h, jnp.asarray(log_norm_value, jnp.float64))

    def coordinates(theta):
        d = theta[:nb3] - c
        w = f_inv @ d if dense else f_inv * d
        return w, to_unconstrained(post, theta[nb3:])

    def build_precond(eta):
        return preconditioner(post, theta_of(jnp.zeros(nb3), eta))

    return Target(u_logdensity, u_evaluate, evaluate, log_norm, build_cache, theta_of, coordinates,
                  int(post.n_free), build_precond if precondition else None)


class GibbsState(NamedTuple):
    """State of one chain.

    Attributes
    ----------
    position : (dim,)  ``[u_b.ravel() (mm), phi]`` (natural parameters, what is stored)
    logdensity : ()  log posterior at ``position`` in the natural parameters
    interior : (n_i, 3)  interior FE solution at ``position`` (mm)
    u : blackjax HMCState  ``w`` (``(3 n_b,)``), its conditional log-density and gradient
    eta : (n_free,)  unconstrained elastic parameters
    """

    position: jax.Array
    logdensity: jax.Array
    interior: jax.Array
    u: bj_hmc.HMCState
    eta: jax.Array


class GibbsInfo(NamedTuple):
    """One transition.

    Attributes
    ----------
    acceptance_rate : (B,)  u_b kernel's (NUTS: mean over the trajectory), elastic move's
    is_accepted : (B,) bool  (NUTS: whether the chain moved)
    cg_iterations : ()  CG iterations of the transition's solves
    solve_failed : ()  solves that did not converge (their moves are rejected)
    grad_evals : ()  gradient evaluations (leapfrog steps, plus one after an accepted
        elastic move)
    divergent : () bool
    tree_depth : ()  NUTS trajectory doublings (0 for MALA, HMC)
    """

    acceptance_rate: jax.Array
    is_accepted: jax.Array
    cg_iterations: jax.Array
    solve_failed: jax.Array
    grad_evals: jax.Array
    divergent: jax.Array
    tree_depth: jax.Array


class GibbsParams(NamedTuple):
    """Tuned values of one chain: ``step_size`` ``()``, ``inverse_mass`` ``(3 n_b,)`` or
    ``(3 n_b, 3 n_b)``, ``eta_scale`` ``(n_free, n_free)``: the lower-triangular factor ``L``
    of the elastic random walk (proposal ``eta + L z``, covariance ``L L^T``); a vector
    ``(n_free,)`` is accepted as independent scales."""

    step_size: jax.Array
    inverse_mass: jax.Array
    eta_scale: jax.Array


def init(target: Target, theta, interior0) -> tuple[GibbsState, Cache]:
    """State and cache at the natural position ``theta`` ``(dim,)``."""
    w, eta = target.coordinates(jnp.asarray(theta))
    cache = target.build_cache(eta, target.log_norm(eta))
    lp, interior, _, _ = target.u_evaluate(w, eta, cache, interior0)
    grad = jax.grad(target.u_logdensity)(w, eta, cache, interior)
    _, lp_nat, interior, _, _ = target.evaluate(w, eta, interior, cache.log_norm)
    return GibbsState(target.position(w, eta), lp_nat, interior, bj_hmc.HMCState(w, lp, grad), eta), cache


def build_kernel(target: Target, kind: str, *, num_integration_steps: int = 16,
                 jitter_integration_steps: bool = True, max_num_doublings: int = 10,
                 divergence_threshold: float = 1000.0, elastic_moves: int = 1) -> Callable:
    """Gibbs kernel ``(rng_key, state, params, cache) -> (state, info, cache)``.

    Parameters
    ----------
    target : Target
    kind : {"mala", "hmc", "nuts"}
    num_integration_steps : int
        HMC's leapfrog steps per transition (the mean number if jittered).
    jitter_integration_steps : bool
        HMC: draw the number of leapfrog steps of each transition uniformly from
        ``1 .. 2 num_integration_steps - 1`` (independently of the state, so each transition
        is a mixture of reversible kernels and the target is unchanged).  A fixed length
        can make the trajectory nearly periodic for some directions (antithetic or stuck
        draws: bulk ESS above the number of draws next to a high tail R-hat).
    max_num_doublings : int
        NUTS' maximum tree depth.
    divergence_threshold : float
        Energy error above which a trajectory is divergent (BlackJAX's default 1000).
    elastic_moves : int
        Random-walk updates of the elastic parameters per transition (each a full
        Metropolis step given ``u_b``; the cache is rebuilt once after them if any was
        accepted).  Their acceptance is reported as the mean over the moves.

    Raises
    ------
    ValueError
        For an unknown ``kind`` or fewer than one leapfrog step.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown gradient kernel {kind!r}; expected one of {KINDS}")
    if kind == "nuts":
        inner = bj_nuts.build_kernel(divergence_threshold=divergence_threshold)
    else:
        inner = bj_hmc.build_kernel(divergence_threshold=divergence_threshold)
    n_leap = 1 if kind == "mala" else int(num_integration_steps)
    if n_leap < 1:
        raise ValueError(f"num_integration_steps must be >= 1, got {num_integration_steps}")
    jitter = kind == "hmc" and bool(jitter_integration_steps) and n_leap > 1

    def u_step(key, ustate, logdensity_fn, params):
        if kind == "nuts":
            new, info = inner(key, ustate, logdensity_fn, params.step_size, params.inverse_mass,
                              max_num_doublings=max_num_doublings)
            moved = jnp.any(new.position != ustate.position)
            return new, (info.acceptance_rate, moved, info.num_integration_steps, info.is_divergent,
                         info.num_trajectory_expansions)
        if jitter:
            key, k_n = jax.random.split(key)
            n = jax.random.randint(k_n, (), 1, 2 * n_leap)  # 1 .. 2L - 1, mean L
        else:
            n = jnp.asarray(n_leap)
        new, info = inner(key, ustate, logdensity_fn, params.step_size, params.inverse_mass, n)
        return new, (info.acceptance_rate, info.is_accepted, n, info.is_divergent, jnp.asarray(0))

    def kernel(rng_key, state: GibbsState, params: GibbsParams, cache: Cache):
        k_u, k_e = jax.random.split(rng_key)
        eta = state.eta

        def evaluate(w_, eta_, interior_, log_norm_):
            if target.build_precond is None:  # (a target of one's own may take 4 arguments)
                return target.evaluate(w_, eta_, interior_, log_norm_)
            return target.evaluate(w_, eta_, interior_, log_norm_, cache.precond)

        def cond_fn(w):
            return target.u_logdensity(w, eta, cache, state.interior)

        ustate, (acc_u, moved_u, n_grad, divergent, depth) = u_step(k_u, state.u, cond_fn, params)
        _, interior, its, ok_u = target.u_evaluate(ustate.position, eta, cache, state.interior)
        # a rejected trajectory keeps the old interior (the cached map gives the same)
        interior = jnp.where(moved_u, interior, state.interior)
        its = jnp.where(moved_u, its, 0)
        w = ustate.position
        acc = [acc_u]
        accepted = [moved_u]
        failed = (~ok_u & moved_u).astype(jnp.int32)
        grads = n_grad
        if target.n_free:
            # the chain's own parameters at its new u_b: a failed solve there (never seen)
            # leaves the elastic parameters where they are and is counted, rather than let
            # -inf accept whatever is proposed
            lz_c, lnat_c, int_c, its_c, ok_c = evaluate(w, eta, interior, cache.log_norm)

            def elastic_move(carry, key):
                eta_c, lz, lnat, int_, ln, n_its, n_fail = carry
                k_prop, k_a = jax.random.split(key)
                z = jax.random.normal(k_prop, eta_c.shape)
                scale = params.eta_scale
                eta_p = eta_c + (scale @ z if scale.ndim == 2 else scale * z)
                norm_p = target.log_norm(eta_p)
                lz_p, lnat_p, int_p, its_p, ok_p = evaluate(w, eta_p, int_, norm_p)
                log_ratio = jnp.where(jnp.isnan(lz_p - lz) | ~ok_c, -jnp.inf, lz_p - lz)
                _, (do, p_acc, _) = static_binomial_sampling(k_a, log_ratio, jnp.zeros(()), jnp.ones(()))
                carry = (jnp.where(do, eta_p, eta_c), jnp.where(do, lz_p, lz), jnp.where(do, lnat_p, lnat),
                         jnp.where(do, int_p, int_), jnp.where(do, norm_p, ln), n_its + its_p,
                         n_fail + (~ok_p).astype(jnp.int32))
                return carry, (p_acc, do)

            carry0 = (eta, lz_c, lnat_c, int_c, cache.log_norm, its_c, (~ok_c).astype(jnp.int32))
            (eta_new, _, lp_nat, interior, norm_new, its_e, fail_e), (p_acc, dos) = jax.lax.scan(
                elastic_move, carry0, jax.random.split(k_e, elastic_moves))
            do = jnp.any(dos)

            def rebuild(_):
                new_cache = target.build_cache(eta_new, norm_new)._replace(precond=cache.precond)
                lp, g = jax.value_and_grad(target.u_logdensity)(w, eta_new, new_cache, interior)
                return new_cache, bj_hmc.HMCState(w, lp, g)

            cache, ustate = jax.lax.cond(do, rebuild, lambda _: (cache, ustate), None)
            eta = eta_new
            its = its + its_e
            failed = failed + fail_e
            grads = grads + do.astype(grads.dtype)
            acc.append(jnp.mean(p_acc))
            accepted.append(do)
        else:
            lp_nat = ustate.logdensity + cache.log_norm
        state = GibbsState(target.position(w, eta), lp_nat, interior, ustate, eta)
        info = GibbsInfo(jnp.stack(acc), jnp.stack(accepted), its, failed, grads, divergent, depth)
        return state, info, cache

    def init_cache(state: GibbsState) -> Cache:
        cache = target.build_cache(state.eta, target.log_norm(state.eta))
        if target.build_precond is None:
            return cache
        return cache._replace(precond=target.build_precond(state.eta))

    kernel.init_cache = init_cache
    kernel.per_chain_params = True
    return kernel


class WarmupState(NamedTuple):
    """Adaptation state of one chain: BlackJAX's dual averaging and mass-matrix (Welford)
    states for the u_b kernel, a dense Welford state of ``eta`` whose window covariance
    ``C`` sets the elastic random walk's factor ``2.38 / sqrt(n_free) chol(C)`` (Haario et
    al.'s adaptive Metropolis; the posterior of the parameters is strongly correlated along
    the overall stiffness scale under the exact normaliser), and the Robbins-Monro
    log-multiplier of that factor."""

    da: tuple
    mm: tuple
    step_size: jax.Array
    inverse_mass: jax.Array
    mm_eta: tuple
    eta_base: jax.Array
    log_eta_scale: jax.Array
    count: jax.Array


def schedule(num_steps: int) -> np.ndarray:
    """Stan's warm-up windows ``(num_steps, 2)``: ``(slow?, window ends?)`` per step
    (:func:`blackjax.adaptation.window_adaptation.build_schedule`)."""
    from blackjax.adaptation.window_adaptation import build_schedule

    return np.array(build_schedule(num_steps), dtype=np.int32).reshape(-1, 2)


def build_warmup_step(kernel: Callable, *, target_acceptance: float, dense_mass: bool = False,
                      adapt_mass: bool = True):
    """``(init, step, final)`` of the windowed warm-up of :func:`build_kernel`'s kernel.

    ``adapt_mass=False`` keeps the identity inverse mass matrix (the preconditioned
    coordinates ``w`` already have about unit scale) and adapts the step size alone, by
    dual averaging over the whole warm-up (no restarts at the window ends).

    ``init(dim_u, initial_step_size, eta_scale) -> WarmupState``;
    ``step(key, state, ws, cache, stage) -> (state, ws, cache, info)`` with ``stage`` the
    ``(slow?, window ends?)`` row of :func:`schedule`; ``final(ws) -> GibbsParams``.
    """
    mm_init, mm_update, mm_final = mass_matrix_adaptation(not dense_mass)
    da_init, da_update, da_final = dual_averaging_adaptation(target_acceptance)

    mm_eta_init, mm_eta_update, mm_eta_final = mass_matrix_adaptation(False)

    def init_ws(dim_u: int, initial_step_size, eta_scale) -> WarmupState:
        mm = mm_init(dim_u)
        da = da_init(jnp.asarray(initial_step_size, jnp.float64))
        eta_scale = jnp.asarray(eta_scale, jnp.float64)
        if eta_scale.ndim == 1:
            eta_scale = jnp.diag(eta_scale)
        return WarmupState(da, mm, jnp.asarray(initial_step_size, jnp.float64), mm.inverse_mass_matrix,
                           mm_eta_init(max(eta_scale.shape[0], 1)), eta_scale, jnp.zeros(()), jnp.asarray(0))

    def step(key, state, ws: WarmupState, cache, stage):
        params = GibbsParams(ws.step_size, ws.inverse_mass, ws.eta_base * jnp.exp(ws.log_eta_scale))
        state, info, cache = kernel(key, state, params, cache)
        slow, window_end = stage[0] == 1, stage[1] == 1
        acc_u = jnp.nan_to_num(info.acceptance_rate[0])
        da = da_update(ws.da, acc_u)
        eta_pad = state.eta if state.eta.shape[0] else jnp.zeros(1)
        mm, mm_eta = jax.lax.cond(
            slow, lambda m: (mm_update(m[0], state.u.position) if adapt_mass else m[0],
                             mm_eta_update(m[1], eta_pad)),
            lambda m: m, (ws.mm, ws.mm_eta))
        n_free = state.eta.shape[0]

        def end_window(args):
            da_, mm_, mm_eta_, base, log_eta = args
            if adapt_mass:
                mm_ = mm_final(mm_)
                da_ = da_init(da_final(da_))
            mm_eta_ = mm_eta_final(mm_eta_)
            if n_free:  # factor from the window's (regularised) covariance, multiplier reset
                base = 2.38 / jnp.sqrt(n_free) * jnp.linalg.cholesky(mm_eta_.inverse_mass_matrix)
                log_eta = jnp.zeros(())
            return da_, mm_, mm_eta_, base, log_eta

        count = jnp.where(window_end, 0, ws.count + 1)
        da, mm, mm_eta, base, log_eta = jax.lax.cond(
            window_end, end_window, lambda a: a, (da, mm, mm_eta, ws.eta_base, ws.log_eta_scale))
        if info.acceptance_rate.shape[0] > 1:
            gain = 1.0 / ((count + 1).astype(jnp.float64) ** 0.6)
            log_eta = log_eta + gain * (jnp.nan_to_num(info.acceptance_rate[1]) - ELASTIC_TARGET_ACCEPTANCE)
        ws = WarmupState(da, mm, jnp.exp(da.log_step_size), mm.inverse_mass_matrix, mm_eta, base,
                         log_eta, count)
        return state, ws, cache, info

    def final(ws: WarmupState) -> GibbsParams:
        # the dual average, once it has averaged anything: BlackJAX's initial state holds
        # log_step_size_avg = 0, so with no warm-up step (or none since a window's restart)
        # the step in use is kept (before: step size 1 for warmup_steps = 0)
        step_size = jnp.where(ws.da.step > 1, jnp.exp(ws.da.log_step_size_avg), ws.step_size)
        return GibbsParams(step_size, ws.inverse_mass, ws.eta_base * jnp.exp(ws.log_eta_scale))

    return init_ws, step, final
