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
   length: Mackenzie 1989; Neal 2011, "MCMC using Hamiltonian dynamics") or MALA (HMC with one leapfrog step, which is MALA preconditioned by the inverse mass matrix).
   With ``condensed`` the interior comes from a cached dense map ``u_i = H(lam, mu) u_b``
   (no CG solve in the gradient), else from the CG solve with implicit differentiation.
2. ``lam, mu | u_b``: ``elastic_moves`` random-walk Metropolis steps on ``eta``, the logit of the free
   parameters on their prior support, with the log-Jacobian (:func:`bayesreg.model.parameters.
   from_unconstrained`) and, for ``prior_normaliser: exact``, the normaliser
   ``(1/2) log pdet S(lam, mu)`` (:func:`bayesreg.model.posterior.log_normaliser`).  If any move
   was accepted, the cache (``H`` and the normaliser) and the gradient state of part 1 are
   rebuilt once.
3. Optionally (``collapsed_moves``), moves of ``(eta, u_b)`` together: ``eta`` by a random
   walk and ``u_b`` carried along by a Gaussian approximation of ``u_b`` given the
   parameters (:attr:`bayesreg.sampling.kernels.target.Target.conditional`), with the Jacobian of
   that map in the acceptance (exact whatever the approximation); they move parameters
   that ``u_b`` pins down given it but not in the marginal.  With a model discrepancy they
   carry ``[u_b, d]``, at the discrepancy's precision drawn from its conditional (the
   Student prior as a scale mixture: data augmentation, Tanner and Wong 1987), or
   (``carry="displacement"``) keep every node's displacement, the discrepancy taking up the
   FE interior's change (:func:`~bayesreg.sampling.kernels.collapsed.displacement_proposal`).

With a joint target (:func:`bayesreg.sampling.kernels.target.joint_target`) part 1 moves ``u_b`` and
the elastic parameters together along one trajectory, through the CG solve with implicit
differentiation; parts 2 and 3 are empty (Gibbs alternation mixes slowly where ``u_b`` pins
the parameters down).  Under the exact normaliser the trajectory sees a smooth surrogate of
it (:mod:`bayesreg.fem.normaliser`), and (4.) the surrogate transition's Metropolis step
(:func:`bayesreg.sampling.kernels.surrogate.correct`; block ``normaliser``, the cache holding
the :attr:`~bayesreg.sampling.kernels.target.Target.correction` at the chain's position)
makes the chain exact.

:func:`as_algorithm` adds the windowed warm-up (:mod:`bayesreg.sampling.kernels.adaptation`)
and hands the kernel to the driver, :func:`bayesreg.sampling.driver.sample`.  Chains of one
program may sample different posteriors: the target is then a function of each chain's own
data, which its state carries (``chain_data``; the replicas of
:mod:`bayesreg.experiments.calibration`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from bayesreg.sampling.chains import build_adaptive_chunk
from bayesreg.sampling.kernels import adaptation
from bayesreg.sampling.kernels.base import Kernel, Program, SamplingAlgorithm, Warmup, marginal_sd
from bayesreg.sampling.kernels.collapsed import CARRIES, collapsed_proposal, displacement_proposal
from bayesreg.sampling.kernels.surrogate import Rebuilds, SurrogateRebuild, correct
from bayesreg.sampling.kernels.target import Cache, Target

__all__ = ["KINDS", "GibbsState", "GibbsInfo", "GibbsParams", "init", "build_kernel",
           "as_algorithm", "default_target_acceptance", "rebuilt_center"]


KINDS = ("mala", "hmc", "nuts")


def default_target_acceptance(kind: str) -> float:
    """Warm-up target of the u_b kernel's acceptance: 0.8 (HMC, NUTS), 0.57 (MALA), 0.25 (RW)."""
    return {"nuts": 0.8, "hmc": 0.8, "mala": 0.57, "rwmh": 0.25}[kind]


class GibbsState(NamedTuple):
    """State of one chain.

    Attributes
    ----------
    position : (dim,)
        ``[u_b.ravel() (mm), phi]`` (natural parameters, what is stored)
    logdensity : ()
        log posterior at ``position`` in the natural parameters
    interior : (n_i, 3)
        interior FE solution at ``position`` (mm)
    u : blackjax HMCState
        ``w`` (``(3 n_b,)``), its conditional log-density and gradient
    eta : (n_free,)
        unconstrained elastic parameters
    data : pytree or None
        the chain's own data where chains differ by more than their starts (a kernel built
        on a function ``data -> Target``: :func:`build_kernel`); carried unchanged by the
        kernel.  ``None`` (no leaves) otherwise.
    """

    position: jax.Array
    logdensity: jax.Array
    interior: jax.Array
    u: object
    eta: jax.Array
    data: object = None


class GibbsInfo(NamedTuple):
    """One transition.

    Attributes
    ----------
    acceptance_rate : (B,)
        u_b kernel's (NUTS: mean over the trajectory), elastic move's
    is_accepted : (B,) bool
        (NUTS: whether the chain moved)
    cg_iterations : ()
        CG iterations of the transition's solves
    solve_failed : ()
        solves that did not converge (their moves are rejected)
    grad_evals : ()
        gradient evaluations (leapfrog steps, plus one after an accepted
        elastic move)
    divergent : () bool
    tree_depth : ()
        NUTS trajectory doublings (0 for MALA, HMC)
    energy : ()
        Hamiltonian (negative conditional log-density plus kinetic energy) at the end of
        the u_b trajectory (ArviZ's ``energy``: BFMI, energy plot)
    """

    acceptance_rate: jax.Array
    is_accepted: jax.Array
    cg_iterations: jax.Array
    solve_failed: jax.Array
    grad_evals: jax.Array
    divergent: jax.Array
    tree_depth: jax.Array
    energy: jax.Array


class GibbsParams(NamedTuple):
    """Tuned values of one chain: ``step_size`` ``()``, ``inverse_mass`` ``(3 n_b,)`` or
    ``(3 n_b, 3 n_b)``, ``eta_scale`` ``(n_free, n_free)``: the lower-triangular factor ``L``
    of the elastic random walk (proposal ``eta + L z``, covariance ``L L^T``); a vector
    ``(n_free,)`` is accepted as independent scales; ``collapsed_scale``, the same for the
    collapsed moves (``None``: ``eta_scale``); ``surrogate_center`` ``(n_params,)``, where the
    target's surrogate was rebuilt after the warm-up (:class:`SurrogateRebuild`; empty: not)."""

    step_size: jax.Array
    inverse_mass: jax.Array
    eta_scale: jax.Array
    collapsed_scale: jax.Array | None = None
    surrogate_center: jax.Array | None = None


def init(target: Target, theta, interior0, data=None) -> tuple[GibbsState, Cache]:
    """State and cache at the natural position ``theta`` ``(dim,)``.

    With ``data`` (a chain's own data, a pytree), ``target`` is a function ``data -> Target``
    and the state carries ``data`` (:class:`GibbsState`)."""
    from blackjax.mcmc import hmc as bj_hmc

    if data is not None:
        state, cache = init(target(data), theta, interior0)
        return state._replace(data=data), cache
    w, eta = target.coordinates(jnp.asarray(theta))
    cache = target.build_cache(eta, target.log_norm(eta))
    lp, interior, _, _ = target.u_evaluate(w, eta, cache, interior0)
    grad = jax.grad(target.u_logdensity)(w, eta, cache, interior)
    _, lp_nat, interior, _, _ = target.evaluate(w, eta, interior, cache.log_norm)
    if target.correction is not None:  # the trajectories' surrogate normaliser, corrected
        delta = jnp.asarray(target.correction(w), jnp.float64)
        cache = cache._replace(log_norm=delta)
        lp_nat = lp_nat + delta
    return GibbsState(target.position(w, eta), lp_nat, interior, bj_hmc.HMCState(w, lp, grad), eta), cache


def build_kernel(target: Target, kind: str, *, num_integration_steps: int = 16,
                 jitter_integration_steps: bool = True, max_num_doublings: int = 10,
                 divergence_threshold: float = 1000.0, elastic_moves: int = 1,
                 collapsed_moves: int = 0, carry: str = "conditional") -> Kernel:
    """The Gibbs kernel over a :class:`~bayesreg.sampling.kernels.target.Target`.

    Parameters
    ----------
    target : Target, or callable
        The target, or a function ``data -> Target`` of the chain's own data, which the
        state carries (:attr:`GibbsState.data`): chains of one program that sample different
        posteriors (the replicas of :mod:`bayesreg.experiments.calibration`), each data set
        a traced argument, not a compiled-in constant.
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
    collapsed_moves : int
        Collapsed moves of the parameters per transition, after the random-walk ones (a
        third acceptance column): ``eta' = eta + L z`` with ``u_b`` carried along by the
        target's Gaussian approximation of ``u_b`` given the parameters
        (:attr:`~bayesreg.sampling.kernels.target.Target.conditional`), ``u_b' = m' + C'^-T C^T
        (u_b - m)``, accepted with the joint density ratio times the Jacobian ``det C /
        det C'``.  Where that approximation is exact the move samples the parameters'
        marginal (``u_b`` integrated out) however strongly ``u_b`` and the parameters are
        coupled; elsewhere it stays exact and accepts less.  Needs a target with
        ``conditional``.  With a :attr:`~bayesreg.sampling.kernels.target.Target.mixture` (a
        model discrepancy) the moves of one transition are made at a precision ``tau`` of the
        discrepancy drawn from its conditional first, against the log-density at that
        ``tau`` (a Gibbs step of the scale mixture, then moves that leave its conditional
        invariant): the Gaussian they transport ``[u_b, d]`` by is then exact in both priors.
    carry : {"conditional", "displacement"}
        How the collapsed moves carry the displacement block along.  ``"conditional"``: by
        the target's Gaussian, as above (one dense factorisation of the block's order per
        move).  ``"displacement"`` (a target with
        :attr:`~bayesreg.sampling.kernels.target.Target.shift`: a model discrepancy): ``u_b``
        stays and the discrepancy takes up the FE interior's change, ``d' = d + H(phi) u_b -
        H(phi') u_b``, so every node's displacement, and with it the likelihood, stays where
        it was (:func:`~bayesreg.sampling.kernels.collapsed.displacement_proposal`; one more
        interior solve per move, no factorisation).  The moves then sample the parameters
        given ``u`` rather than given ``[u_b, d]``: the sufficient parametrisation beside the
        Gibbs step's ancillary one (Yu and Meng 2011, "To center or not to center", *JCGS*
        20(3)).  The map is a shear (Jacobian 1) that the reverse move undoes, so the
        acceptance is the log-density's ratio alone.

    Returns
    -------
    Kernel
        ``step(rng_key, state, params, cache) -> (state, GibbsInfo, cache)`` with ``params``
        a :class:`GibbsParams` and ``cache`` a :class:`~bayesreg.sampling.kernels.target.Cache`
        (``init_cache(state)``); parameters are per chain.

    Raises
    ------
    ValueError
        For an unknown ``kind``, fewer than one leapfrog step, or collapsed moves on a
        target without ``conditional`` or without free parameters.
    """
    per_chain = callable(target)  # a function data -> Target (a Target is a tuple)

    if carry not in CARRIES:
        raise ValueError(f"unknown carry {carry!r} of the collapsed moves; expected one of {CARRIES}")
    by_displacement = carry == "displacement"

    def check(target):
        if not collapsed_moves:
            return target
        if not target.n_free:
            raise ValueError("collapsed moves need free elastic parameters")
        if by_displacement and target.shift is None:
            raise ValueError("collapsed moves that carry the displacement need a target with a "
                             "model discrepancy (Target.shift)")
        if not by_displacement and target.conditional is None:
            raise ValueError("collapsed moves need a target with a Gaussian conditional of u_b "
                             "(make_target(likelihood=...))")
        return target

    if not per_chain:
        check(target)
    if kind not in KINDS:
        raise ValueError(f"unknown gradient kernel {kind!r}; expected one of {KINDS}")
    # BlackJAX is imported where a kernel is built, not with this module: importing it starts
    # JAX's backend, which must wait for bayesreg.configure_jax (the XLA flags)
    from blackjax.mcmc import hmc as bj_hmc
    from blackjax.mcmc import nuts as bj_nuts
    from blackjax.mcmc.proposal import static_binomial_sampling

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
                         info.num_trajectory_expansions, info.energy)
        if jitter:
            key, k_n = jax.random.split(key)
            n = jax.random.randint(k_n, (), 1, 2 * n_leap)  # 1 .. 2L - 1, mean L
        else:
            n = jnp.asarray(n_leap)
        new, info = inner(key, ustate, logdensity_fn, params.step_size, params.inverse_mass, n)
        return new, (info.acceptance_rate, info.is_accepted, n, info.is_divergent, jnp.asarray(0),
                     info.energy)

    def target_of(state):
        return check(target(state.data)) if per_chain else target

    def step(rng_key, state: GibbsState, params: GibbsParams, cache: Cache):
        return transition(target_of(state), rng_key, state, params, cache)

    def transition(target, rng_key, state, params, cache):
        k_u, k_e = jax.random.split(rng_key)
        eta = state.eta

        def evaluate(w_, eta_, interior_, log_norm_):
            if target.build_precond is None:  # (a target of one's own may take 4 arguments)
                return target.evaluate(w_, eta_, interior_, log_norm_)
            return target.evaluate(w_, eta_, interior_, log_norm_, cache.precond)

        def cond_fn(w):
            return target.u_logdensity(w, eta, cache, state.interior)

        ustate, (acc_u, moved_u, n_grad, divergent, depth, energy) = u_step(k_u, state.u, cond_fn, params)
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
            if collapsed_moves:  # (without them the random stream is the one it always was)
                k_e, k_c = jax.random.split(k_e)
            (eta_new, lz, lp_nat, interior, norm_new, its_e, fail_e), (p_acc, dos) = jax.lax.scan(
                elastic_move, carry0, jax.random.split(k_e, elastic_moves))
            do = jnp.any(dos)
            acc.append(jnp.mean(p_acc))
            accepted.append(do)
            if collapsed_moves:
                if target.mixture is not None and not by_displacement:
                    # the discrepancy's precision, given d, for these moves
                    k_c, k_t = jax.random.split(k_c)
                    tau = target.mixture.draw(k_t, target.position(w, eta_new)[:-target.n_free])
                else:
                    tau = jnp.zeros(())

                def collapsed_move(carry, key):
                    w_c, eta_c, lz, lnat, int_, ln, mean_c, chol_c, n_its, n_fail = carry
                    k_prop, k_a = jax.random.split(key)
                    z = jax.random.normal(k_prop, eta_c.shape)
                    scale = params.eta_scale if params.collapsed_scale is None else params.collapsed_scale
                    eta_p = eta_c + (scale @ z if scale.ndim == 2 else scale * z)
                    norm_p = target.log_norm(eta_p)
                    if by_displacement:  # the FE interior at eta_p, which d' takes up the change of
                        _, _, int_fe, its_0, ok_0 = evaluate(w_c, eta_p, int_, norm_p)
                        w_p = displacement_proposal(target, w_c, eta_c, eta_p, int_, int_fe)
                        mean_p, chol_p, log_corr = mean_c, chol_c, jnp.zeros(())
                    else:
                        w_p, mean_p, chol_p, log_corr = collapsed_proposal(target, w_c, eta_c, eta_p,
                                                                           tau, mean_c, chol_c)
                        int_fe, its_0, ok_0 = int_, 0, True
                    lz_p, lnat_p, int_p, its_p, ok_p = evaluate(w_p, eta_p, int_fe, norm_p)
                    its_p, ok_p = its_p + its_0, ok_p & ok_0
                    log_ratio = lz_p - lz + log_corr
                    # (a failed solve at eta_p rejects: the shifted d of a wrong interior would
                    # not be the reverse move's)
                    log_ratio = jnp.where(jnp.isnan(log_ratio) | ~ok_c | ~ok_p, -jnp.inf, log_ratio)
                    _, (do_, p_acc_, _) = static_binomial_sampling(k_a, log_ratio, jnp.zeros(()),
                                                                  jnp.ones(()))
                    keep = (w_p, eta_p, lz_p, lnat_p, int_p, norm_p, mean_p, chol_p)
                    old = (w_c, eta_c, lz, lnat, int_, ln, mean_c, chol_c)
                    new = tuple(jnp.where(do_, a, b) for a, b in zip(keep, old))
                    return new + (n_its + its_p, n_fail + (~ok_p).astype(jnp.int32)), (p_acc_, do_)

                if by_displacement:  # (no Gaussian: placeholders in the carry)
                    mean0, chol0 = jnp.zeros((0,)), jnp.zeros((0, 0))
                else:
                    mean0, chol0 = target.conditional(eta_new, tau)
                carry0 = (w, eta_new, lz, lp_nat, interior, norm_new, mean0, chol0, its_e, fail_e)
                (w, eta_new, _, lp_nat, interior, norm_new, _, _, its_e, fail_e), (p_c, dos_c) = \
                    jax.lax.scan(collapsed_move, carry0, jax.random.split(k_c, collapsed_moves))
                do = do | jnp.any(dos_c)
                acc.append(jnp.mean(p_c))
                accepted.append(jnp.any(dos_c))

            def rebuild(_):
                new_cache = target.build_cache(eta_new, norm_new)._replace(precond=cache.precond)
                lp, g = jax.value_and_grad(target.u_logdensity)(w, eta_new, new_cache, interior)
                return new_cache, bj_hmc.HMCState(w, lp, g)

            cache, ustate = jax.lax.cond(do, rebuild, lambda _: (cache, ustate), None)
            eta = eta_new
            its = its + its_e
            failed = failed + fail_e
            grads = grads + do.astype(grads.dtype)
        else:
            if target.correction is not None:  # the surrogate transition's Metropolis step
                ustate, interior, delta, p_c, kept = correct(target, k_e, moved_u, ustate, state.u,
                                                             interior, state.interior, cache.log_norm)
                w = ustate.position
                cache = cache._replace(log_norm=delta)
                acc.append(p_c)
                accepted.append(kept)
            lp_nat = ustate.logdensity + cache.log_norm
            if target.log_jacobian is not None:  # a joint target: its w holds the logits
                lp_nat = lp_nat - target.log_jacobian(w)
        state = GibbsState(target.position(w, eta), lp_nat, interior, ustate, eta, state.data)
        info = GibbsInfo(jnp.stack(acc), jnp.stack(accepted), its, failed, grads, divergent, depth,
                         energy)
        return state, info, cache

    def init_cache(state: GibbsState) -> Cache:
        target = target_of(state)
        cache = target.build_cache(state.eta, target.log_norm(state.eta))
        if target.correction is not None:
            cache = cache._replace(log_norm=jnp.asarray(target.correction(state.u.position),
                                                        jnp.float64))
        if target.build_precond is None:
            return cache
        return cache._replace(precond=target.build_precond(state.eta))

    return Kernel(step, init_cache, per_chain_params=True)


def as_algorithm(target: Target, interior0, *, kind: str = "nuts", step_size: float = 0.2,
                 eta_scale=0.1, dense_mass: bool = False, adapt_mass: bool = True,
                 num_integration_steps: int = 16, jitter_integration_steps: bool = True,
                 max_tree_depth: int = 10, elastic_moves: int = 1, collapsed_moves: int = 0,
                 carry: str = "conditional", target_acceptance: float | None = None, chain_data=None,
                 refresh=None, surrogate: SurrogateRebuild | None = None) -> SamplingAlgorithm:
    """The gradient Gibbs kernel with its windowed warm-up, for
    :func:`bayesreg.sampling.driver.sample`.

    The warm-up is Stan's windowed adaptation (:mod:`bayesreg.sampling.kernels.adaptation`:
    step size by dual averaging toward ``target_acceptance``, a diagonal or dense inverse
    mass matrix from the slow windows) on each chain, plus the scale of the elastic random
    walk; the tuned values are frozen after it as :class:`GibbsParams` with a leading chain
    axis (``step_size (C,), inverse_mass (C, ...), eta_scale (C, n_free, n_free),
    collapsed_scale (C, n_free, n_free)``).  Warm-up and sampling run one compiled chunk
    program (:func:`bayesreg.sampling.chains.build_adaptive_chunk`).

    Parameters
    ----------
    target : bayesreg.sampling.kernels.target.Target, or callable
        The target; with ``chain_data``, a function ``data -> Target`` (:func:`build_kernel`)
    interior0 : (n_i, 3) array
        warm start of the first solve
    kind : {"mala", "hmc", "nuts"}
    step_size : float
        initial leapfrog step (in the preconditioned coordinates ``w``)
    eta_scale : float, (n_free,) or (n_free, n_free) array
        initial scale(s), or lower-triangular factor, of the elastic random walk
    dense_mass : bool
        adapt a dense inverse mass matrix instead of a diagonal one
    adapt_mass : bool
        adapt the inverse mass matrix at all (else identity in ``w``)
    num_integration_steps : int
        HMC's leapfrog steps (their mean if jittered)
    jitter_integration_steps : bool
        HMC: draw the number of leapfrog steps uniformly from
        ``1 .. 2 num_integration_steps - 1`` each transition (:func:`build_kernel`)
    max_tree_depth : int
        NUTS' maximum number of trajectory doublings
    elastic_moves : int
        elastic random-walk updates per transition
    collapsed_moves : int
        collapsed moves of the elastic parameters per transition (a target with
        ``conditional``; :func:`build_kernel`)
    carry : {"conditional", "displacement"}
        how they carry the displacement along (:func:`build_kernel`)
    target_acceptance : float, optional
        Default :func:`default_target_acceptance` of ``kind``.
    chain_data : pytree, optional
        Each chain's own data, leaves with a leading chain axis ``(C, ...)``: chain ``c``
        samples ``target(data_c)``, all chains in one compiled program (the driver must be
        given ``C`` starts).  Static attributes (free parameters, blocks) come from the
        first chain's target and are the same for all.
    refresh : callable, optional
        ``state -> state`` for one chain, applied to every chain after the warm-up's last
        chunk, before the tuned values are frozen: per-chain data that depend on where the
        chain is (the collapsed moves' linearisation of the likelihood, made again where
        the warm-up ended).  It may change ``data`` only, and only what the log-density
        does not depend on (the kernel's proposals), so the stored state stays exact.  Warm-up
        draws are discarded, so the sampling kernel, fixed from then on, stays exact.
    surrogate : bayesreg.sampling.kernels.surrogate.SurrogateRebuild, optional
        Rebuild a joint target's normaliser surrogate where the chains are when the warm-up
        ends (ignored for a target without a correction).

    Returns
    -------
    SamplingAlgorithm

    Raises
    ------
    ValueError
        ``step_size`` not finite and ``> 0``, ``eta_scale`` non-finite or, as scales, not
        ``> 0``, ``target_acceptance`` outside ``(0, 1)``, an unknown ``kind``; at
        :attr:`~bayesreg.sampling.kernels.base.SamplingAlgorithm.build`, chains cut into
        ``"pieces"``.
    """
    target_acceptance = target_acceptance or default_target_acceptance(kind)
    if not 0 < target_acceptance < 1:
        raise ValueError(f"target_acceptance must lie in (0, 1), got {target_acceptance}")
    if not (np.ndim(step_size) == 0 and np.isfinite(step_size) and step_size > 0):
        raise ValueError(f"step_size must be a finite scalar > 0, got {step_size}")
    eta0 = np.asarray(eta_scale, np.float64)
    if not np.all(np.isfinite(eta0)) or (eta0.ndim < 2 and not np.all(eta0 > 0)):
        raise ValueError(f"eta_scale must be finite and, as scales, > 0, got {eta_scale}")
    if (chain_data is None) == callable(target):
        raise ValueError("chain_data goes with a target that is a function data -> Target, "
                         "and only with one")
    if surrogate is not None and chain_data is not None:
        raise ValueError("a rebuilt surrogate needs one target for every chain (no chain_data)")

    def kernel_of(tg):
        kn = build_kernel(tg, kind, num_integration_steps=num_integration_steps,
                          jitter_integration_steps=jitter_integration_steps,
                          max_num_doublings=max_tree_depth, elastic_moves=elastic_moves,
                          collapsed_moves=collapsed_moves, carry=carry)
        return (kn,) + adaptation.build_warmup_step(
            kn, GibbsParams, target_acceptance=target_acceptance, dense_mass=dense_mass,
            adapt_mass=adapt_mass)

    kernel, ws_init, ws_step, ws_final = kernel_of(target)
    target_of, target = target, (target if chain_data is None else
                                 target(jax.tree.map(lambda a: jnp.asarray(a)[0], chain_data)))
    n_blocks = 1 + (target.n_free > 0) + (collapsed_moves > 0) + (target.correction is not None)
    rebuilds = Rebuilds(surrogate if target.correction is not None else None, kernel_of,
                        lambda tg, x, i: init(tg, x, i)[0])
    # scales become a diagonal factor in ws_init
    eta0 = eta0 if eta0.ndim == 2 else np.broadcast_to(eta0, (target.n_free,))

    def build(n_chains, dim, chunk_draws, thinning, n_warm, chain_method):
        dim_u = dim - target.n_free  # the preconditioned u_b coordinates w
        mapped = build_adaptive_chunk(kernel, ws_step, chunk_draws, thinning, n_chains,
                                      method=chain_method)

        @jax.jit
        def ws_start():
            return jax.vmap(lambda _: ws_init(dim_u, step_size, eta0))(jnp.arange(n_chains))

        @jax.jit
        def ws_frozen(frozen):
            # a warm-up state whose kernel parameters are exactly ``frozen`` (eta_scale * exp(0))
            ws = ws_start()
            # the collapsed moves' factor is the same base times its own multiplier (trace
            # ratio); a checkpoint from before them has none
            log_col = jnp.zeros_like(ws.log_eta_scale)
            if frozen.collapsed_scale is not None and frozen.eta_scale.shape[-1]:
                log_col = jnp.log(jnp.trace(frozen.collapsed_scale, axis1=-2, axis2=-1)
                                  / jnp.trace(frozen.eta_scale, axis1=-2, axis2=-1))
            return ws._replace(step_size=frozen.step_size, inverse_mass=frozen.inverse_mass,
                               eta_base=frozen.eta_scale, log_eta_scale=jnp.zeros_like(ws.log_eta_scale),
                               log_collapsed_scale=log_col)

        # the draws' keys as a chunk of :func:`bayesreg.sampling.chains.build_chunk` takes them
        samp_keys = jax.jit(jax.vmap(lambda k: jax.vmap(lambda kd: jax.random.split(kd, thinning))(
            jax.random.split(k, chunk_draws))))
        warm_keys = jax.jit(jax.vmap(lambda k: jax.random.split(k, chunk_draws * thinning).reshape(
            chunk_draws, thinning)))
        no_stage = np.zeros((n_chains, chunk_draws, thinning, 2), np.int32)
        no_adapt = np.zeros(n_chains, bool)
        per_chunk = chunk_draws * thinning
        stages = adaptation.schedule(n_warm * per_chunk) if n_warm else np.zeros((0, 2), np.int32)
        adapt = np.ones(n_chains, bool)

        def chunk_program(kn, step_):  # the sampling chunk of a rebuilt target
            return build_adaptive_chunk(kn, step_, chunk_draws, thinning, n_chains, method=chain_method)

        def chunk(keys, states, frozen):
            program = rebuilds.program(frozen.surrogate_center, mapped, chunk_program)
            (states, _, _), out = program.run(samp_keys(keys), states, (ws_frozen(frozen), no_stage, no_adapt))
            return states, out

        def warm_chunk(k, keys, states, ws):
            stage = stages[k * per_chunk:(k + 1) * per_chunk].reshape(chunk_draws, thinning, 2)
            (states, ws, (acc, div, grads)), _ = mapped.run(
                warm_keys(keys), states, (ws, np.broadcast_to(stage, (n_chains,) + stage.shape), adapt))
            if refresh is not None and k + 1 == n_warm:
                states = refreshed(states)
            acc = np.asarray(acc).mean(axis=0)
            step = np.asarray(ws.step_size)
            postfix = {"acc": np.array2string(acc, precision=2),
                       "step": (np.array2string(step, precision=3) if n_chains <= 8 else
                                f"{step.min():.3f}-{step.max():.3f}"),
                       "grads": f"{float(np.mean(grads)):.0f}", "div": int(np.sum(div))}
            return states, ws, acc, postfix

        refreshed = None if refresh is None else jax.jit(jax.vmap(refresh))
        frozen_of = jax.jit(jax.vmap(ws_final))
        warmup = Warmup(lambda states: ws_start(), warm_chunk,
                        lambda ws, states: rebuilds.freeze(target, frozen_of(ws), states))
        return Program(chunk, warmup, mapped.method)

    init_chain = ((lambda x: init(target, x, interior0)[0]) if chain_data is None
                  else (lambda x, data: init(target_of, x, interior0, data)[0]))

    return SamplingAlgorithm(
        kind=kind,
        blocks=(("joint", "normaliser")[:n_blocks] if target.log_jacobian is not None
                else ("u_b", "elastic", "collapsed")[:n_blocks]),
        init=init_chain, build=build, chain_data=chain_data,
        params=lambda *a: GibbsParams(*a), describe=_describe,
        # the solves counted: with the cached map the trajectory needs none, and the elastic
        # block makes elastic_moves solves plus one evaluation before them; without it every
        # gradient solves (uncounted) and the count per step varies
        solves_per_step=(float(elastic_moves + 1) if target.condensed and target.n_free else None),
        preconditioner=target.preconditioner, condensed=target.condensed,
        sample_stats=("n_steps", "step_size", "energy")
        + (("tree_depth",) if kind == "nuts" else ()))


def rebuilt_center(sigma: tuple) -> np.ndarray | None:
    """The surrogate's centre ``(C, n_params)`` in the tuned values ``sigma`` (the :class:`GibbsParams`
    fields, as checkpoints hold them); ``None`` where it was not rebuilt after the warm-up."""
    center = GibbsParams(*sigma).surrogate_center
    return None if center is None or not np.size(center) else np.asarray(center)


def _describe(sigma: tuple) -> dict:
    """The frozen tuned values (step sizes, mass matrices, factors, surrogate), for ``run.json``."""
    step, inv_mass, eta_scale = (np.asarray(a) for a in sigma[:3])
    extra = {} if len(sigma) < 4 or sigma[3] is None else {
        "collapsed_proposal_sd_per_chain": marginal_sd(np.asarray(sigma[3]), np.ndim(sigma[3]) == 3).tolist()}
    center = rebuilt_center(sigma)
    extra |= {} if center is None else {"normaliser_surrogate_center": center[0].tolist()}
    return {**extra, "step_size_per_chain": step.tolist(),
            "inverse_mass_diag_quantiles_0_50_100": np.quantile(
                inv_mass if inv_mass.ndim == 2 else np.diagonal(inv_mass, axis1=1, axis2=2),
                [0, 0.5, 1]).tolist(),
            "elastic_proposal_sd_per_chain": marginal_sd(eta_scale, eta_scale.ndim == 3).tolist(),
            "elastic_factor_per_chain": eta_scale.tolist()}
