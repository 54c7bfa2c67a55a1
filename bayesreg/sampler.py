"""Random-walk Metropolis-Hastings with parallel chains (paper Sec. 3.2, Algorithm 1).

Functional core in the BlackJAX style: :func:`init` and :func:`build_kernel` are pure; the
Normal jumping kernel (:func:`blackjax.mcmc.random_walk.normal`) and the Metropolis accept
step (:func:`blackjax.mcmc.proposal.static_binomial_sampling`) are BlackJAX's.  The state
also carries the chain's interior FE solution, the warm start of the next solve.

:func:`sample` is the driver: N chains vmapped inside one jitted ``lax.scan`` per chunk
of thinned draws, a warm-up that tunes one global scale of the proposal toward a target
acceptance rate (Robbins-Monro on the log scale) together with the proposal scales of the
elastic parameters (from the warm-up draws), then frozen; sampling stops once the classic
Gelman-Rubin R-hat is below a threshold for every estimand, or at a maximum number of draws.
The proposal is symmetric, so the acceptance ratio is the posterior ratio of Eq. 13.
"""

from __future__ import annotations

import time
from typing import Callable, NamedTuple

import numpy as np

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from blackjax.mcmc.proposal import static_binomial_sampling  # noqa: E402
from blackjax.mcmc.random_walk import normal as normal_jumping_kernel  # noqa: E402

from bayesreg.diagnostics import gelman_rubin  # noqa: E402

__all__ = ["RWMHState", "RWMHInfo", "init", "build_kernel", "SamplerResult", "sample"]


class RWMHState(NamedTuple):
    """State of one chain.

    Attributes
    ----------
    position : (dim,)
    logdensity : ()
    interior : (n_i, 3)
        Interior FE solution at ``position`` (warm start of the next solve).
    """

    position: jax.Array
    logdensity: jax.Array
    interior: jax.Array


class RWMHInfo(NamedTuple):
    """Information about one transition.

    Attributes
    ----------
    acceptance_rate : ()   ``min(1, p(theta*) / p(theta^n))`` (Eq. 13)
    is_accepted : () bool
    cg_iterations : ()  CG iterations of the proposal's solve
    solve_failed : () bool  the proposal's solve did not converge (it was rejected)
    """

    acceptance_rate: jax.Array
    is_accepted: jax.Array
    cg_iterations: jax.Array
    solve_failed: jax.Array


def init(position, logdensity_fn: Callable, interior0) -> RWMHState:
    """Initial state; ``logdensity_fn(position, interior_guess) -> (logp, aux)``."""
    logp, aux = logdensity_fn(position, interior0)
    return RWMHState(position, logp, aux.interior)


def build_kernel(logdensity_fn: Callable) -> Callable:
    """Kernel ``(rng_key, state, sigma) -> (state, info)`` for a fixed log-density.

    ``sigma`` is the Normal jumping kernel's scale: a vector (independent scales) or a
    matrix ``L`` (proposal covariance ``L L^T``).
    """

    def kernel(rng_key, state: RWMHState, sigma):
        key_prop, key_acc = jax.random.split(rng_key)
        move = normal_jumping_kernel(sigma)(key_prop, state.position)
        proposal = state.position + move
        logp, aux = logdensity_fn(proposal, state.interior)
        log_ratio = logp - state.logdensity
        log_ratio = jnp.where(jnp.isnan(log_ratio), -jnp.inf, log_ratio)
        new = RWMHState(proposal, logp, aux.interior)
        state, (accepted, p_accept, _) = static_binomial_sampling(key_acc, log_ratio, state, new)
        return state, RWMHInfo(
            p_accept, accepted, aux.solve.iterations, ~aux.solve.converged
        )

    return kernel


class SamplerResult(NamedTuple):
    """Output of :func:`sample` (host NumPy arrays).

    Attributes
    ----------
    positions : (C, D, dim)   thinned post-warm-up draws
    interior : (C, D, n_i, 3)   interior FE solution of each draw
    logdensity : (C, D)
    acceptance : (C, D)   mean acceptance probability over each thinning interval
    cg_iterations : (C, D)   mean CG iterations per step over each interval
    solve_failures : (C, D)   non-converged (rejected) solves per interval
    rhat_history : list of (draws per chain, max classic R-hat)
    sigma : the frozen proposal scale
    warmup_acceptance : float
    timings : dict  seconds for compile, warm-up, sampling
    converged : bool   max R-hat < threshold at the end
    final_states : RWMHState  (to continue a run)
    """

    positions: np.ndarray
    interior: np.ndarray
    logdensity: np.ndarray
    acceptance: np.ndarray
    cg_iterations: np.ndarray
    solve_failures: np.ndarray
    rhat_history: list
    sigma: np.ndarray
    warmup_acceptance: float
    timings: dict
    converged: bool
    final_states: RWMHState


def _build_chunk(kernel, n_draws: int, thin: int):
    def one_chain(key, state, sigma):
        def draw(state, key):
            def step(state, key):
                return kernel(key, state, sigma)

            state, info = jax.lax.scan(step, state, jax.random.split(key, thin))
            return state, (
                state.position,
                state.interior,
                state.logdensity,
                jnp.mean(info.acceptance_rate),
                jnp.mean(info.cg_iterations.astype(jnp.float64)),
                jnp.sum(info.solve_failed),
            )

        return jax.lax.scan(draw, state, jax.random.split(key, n_draws))

    return jax.jit(jax.vmap(one_chain, in_axes=(0, 0, None)))


def sample(
    rng_key,
    logdensity_fn: Callable,
    initial_positions,
    interior0,
    sigma,
    *,
    adapt_mask=None,
    thinning: int = 10,
    warmup_steps: int = 2000,
    max_draws: int = 2000,
    min_draws: int = 100,
    chunk_draws: int = 50,
    target_acceptance: float = 0.25,
    rhat_threshold: float = 1.2,
    estimands: Callable | None = None,
    progress: bool = True,
) -> SamplerResult:
    """Run parallel RW-MH chains with warm-up, thinning and R-hat stopping.

    Parameters
    ----------
    rng_key : PRNGKey
    logdensity_fn : callable
        ``(position (dim,), interior_guess (n_i, 3)) -> (logp, aux)``; ``aux.interior``
        and ``aux.solve`` as in :class:`bayesreg.posterior.Aux`.
    initial_positions : (C, dim) array
        One start per chain (dispersed starts make R-hat meaningful).
    interior0 : (n_i, 3) array
        Initial interior warm start.
    sigma : (dim,) or (dim, dim) array
        Initial proposal scale (vector) or Cholesky-type factor (matrix).
    adapt_mask : (dim,) bool array, optional
        Coordinates whose scale is re-estimated in the second half of the warm-up (the
        elastic parameters): their diagonal entries of ``sigma`` become ``2.38 / sqrt(dim)``
        times the pooled standard deviation of the last warm-up chunk.  With a matrix
        ``sigma`` the masked rows and columns must be zero off the diagonal.
    thinning : int
        Steps per stored draw (paper: 10).
    warmup_steps : int
        Steps per chain spent tuning (discarded); rounded up to whole chunks.
    max_draws, min_draws : int
        Bounds on stored draws per chain after warm-up.
    chunk_draws : int
        Draws per jitted call (the R-hat check and progress-bar interval).
    target_acceptance : float
        Warm-up target of the mean acceptance probability (paper: about 0.25).
    rhat_threshold : float
        Stop when the classic Gelman-Rubin R-hat of every estimand is below it.
    estimands : callable, optional
        ``(draws (C, D, dim) ndarray) -> (C, D, K) ndarray`` of the scalars to monitor;
        default: the position coordinates.
    progress : bool
        Show a tqdm progress bar with acceptance and the worst R-hat.

    Returns
    -------
    SamplerResult

    Raises
    ------
    ValueError
        On bad arguments or if any chain starts at a point of zero posterior density.
    """
    from tqdm.auto import tqdm

    x0 = jnp.asarray(initial_positions, dtype=jnp.float64)
    if x0.ndim != 2:
        raise ValueError(f"initial_positions must be (chains, dim), got {x0.shape}")
    n_chains, dim = x0.shape
    if n_chains < 2:
        raise ValueError("at least 2 chains are needed for R-hat")
    if thinning < 1 or chunk_draws < 1 or max_draws < 1:
        raise ValueError("thinning, chunk_draws and max_draws must be >= 1")
    if not 0 < target_acceptance < 1:
        raise ValueError(f"target_acceptance must lie in (0, 1), got {target_acceptance}")
    sigma = jnp.asarray(sigma, dtype=jnp.float64)
    estimands = estimands or (lambda d: d)

    kernel = build_kernel(logdensity_fn)
    t0 = time.perf_counter()
    init_fn = jax.jit(jax.vmap(lambda x: init(x, logdensity_fn, interior0)))
    states = init_fn(x0)
    bad = ~np.isfinite(np.asarray(states.logdensity))
    if bad.any():
        raise ValueError(
            f"chains {np.flatnonzero(bad).tolist()} start at zero posterior density "
            "(constraint violated or CG solve not converged at the initial position)"
        )
    chunk = _build_chunk(kernel, chunk_draws, thinning)
    key_warm, key_samp = jax.random.split(rng_key)
    timings = {}

    # ---- warm-up: Robbins-Monro on a global log-scale, parameter scales from draws ----
    n_warm_chunks = int(np.ceil(warmup_steps / (chunk_draws * thinning))) if warmup_steps else 0
    log_scale = 0.0
    base_sigma = sigma
    warm_acc = float("nan")
    bar = tqdm(total=n_warm_chunks + int(np.ceil(max_draws / chunk_draws)), disable=not progress,
               desc="warm-up", unit="chunk")
    for k in range(n_warm_chunks):
        cur = base_sigma * np.exp(log_scale)
        states, out = chunk(jax.random.split(jax.random.fold_in(key_warm, k), n_chains), states, cur)
        if k == 0:
            timings["first_chunk_incl_compile_s"] = time.perf_counter() - t0
        warm_acc = float(np.mean(np.asarray(out[3])))
        gain = 1.0 / np.sqrt(k + 1.0)
        log_scale += 2.0 * gain * (warm_acc - target_acceptance)
        if adapt_mask is not None and k >= n_warm_chunks // 2 and k < n_warm_chunks - 1:
            pos = np.asarray(out[0]).reshape(-1, dim)
            sd = pos.std(axis=0)
            mask = np.asarray(adapt_mask)
            new = np.asarray(base_sigma).copy()
            scale_new = 2.38 / np.sqrt(dim) * np.maximum(sd, 1e-6 * np.abs(pos.mean(0)) + 1e-12)
            if new.ndim == 1:
                new[mask] = np.where(sd[mask] > 0, scale_new[mask], new[mask])
            else:
                idx = np.flatnonzero(mask)
                new[idx, idx] = np.where(sd[idx] > 0, scale_new[idx], new[idx, idx])
            base_sigma = jnp.asarray(new)
        bar.set_postfix(acc=f"{warm_acc:.2f}", scale=f"{np.exp(log_scale):.3g}")
        bar.update(1)
    timings["warmup_s"] = time.perf_counter() - t0
    sigma_frozen = base_sigma * np.exp(log_scale)

    # ---- sampling ----
    bar.set_description("sampling")
    t1 = time.perf_counter()
    pos_chunks, int_chunks, lp_chunks, acc_chunks, cg_chunks, fail_chunks = [], [], [], [], [], []
    history = []
    n_draws = 0
    rhat = np.inf
    k = 0
    while n_draws < max_draws:
        states, out = chunk(jax.random.split(jax.random.fold_in(key_samp, k), n_chains), states,
                            sigma_frozen)
        k += 1
        pos_chunks.append(np.asarray(out[0]))
        int_chunks.append(np.asarray(out[1]))
        lp_chunks.append(np.asarray(out[2]))
        acc_chunks.append(np.asarray(out[3]))
        cg_chunks.append(np.asarray(out[4]))
        fail_chunks.append(np.asarray(out[5]))
        n_draws += chunk_draws
        draws = np.concatenate(pos_chunks, axis=1)
        rhat = float(np.nanmax(gelman_rubin(estimands(draws))))
        history.append((n_draws, rhat))
        acc = float(np.mean(np.concatenate(acc_chunks, axis=1)))
        bar.set_postfix(acc=f"{acc:.2f}", rhat=f"{rhat:.3f}", draws=n_draws)
        bar.update(1)
        if n_draws >= min_draws and rhat < rhat_threshold:
            break
    bar.close()
    timings["sampling_s"] = time.perf_counter() - t1
    return SamplerResult(
        positions=np.concatenate(pos_chunks, axis=1),
        interior=np.concatenate(int_chunks, axis=1),
        logdensity=np.concatenate(lp_chunks, axis=1),
        acceptance=np.concatenate(acc_chunks, axis=1),
        cg_iterations=np.concatenate(cg_chunks, axis=1),
        solve_failures=np.concatenate(fail_chunks, axis=1),
        rhat_history=history,
        sigma=np.asarray(sigma_frozen),
        warmup_acceptance=warm_acc,
        timings=timings,
        converged=bool(rhat < rhat_threshold),
        final_states=states,
    )
