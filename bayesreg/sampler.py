"""Random-walk Metropolis-Hastings with parallel chains (paper Sec. 3.2, Algorithm 1).

Functional core in the BlackJAX style: :func:`init` and :func:`build_kernel` are pure; the
Normal jumping kernel (:func:`blackjax.mcmc.random_walk.normal`) and the Metropolis accept
step (:func:`blackjax.mcmc.proposal.static_binomial_sampling`) are BlackJAX's.  The state
also carries the chain's interior FE solution, the warm start of the next solve; a
:class:`KernelCache` (the condensation ``H``, the CG preconditioner ``K_ii^-1``) is built
from the state at every chunk start and carried through the chunk.

:func:`sample` is the driver: N chains inside one jitted ``lax.scan`` per chunk of thinned
draws (vmapped on an accelerator, in parallel host threads on a CPU, in pieces of chunks
where the chains do not split evenly over the cores: :func:`_over_chains`); coordinates
may be updated in blocks (Metropolis-within-Gibbs); a warm-up tunes each block's scale
toward a target acceptance rate (Robbins-Monro on the log scale) and its marginal scales
from the warm-up draws, then freezes them; sampling stops once the classic Gelman-Rubin
R-hat is below a threshold for every estimand, or at a maximum number of draws.  Proposals
are symmetric, so the acceptance probability is the posterior ratio of Eq. 13.
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Callable, NamedTuple

import numpy as np

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from blackjax.mcmc.proposal import static_binomial_sampling  # noqa: E402
from blackjax.mcmc.random_walk import normal as normal_jumping_kernel  # noqa: E402

from bayesreg.diagnostics import RunningGelmanRubin  # noqa: E402

__all__ = [
    "RWMHState", "RWMHInfo", "Condensation", "Preconditioner", "KernelCache", "init", "build_kernel",
    "SamplerResult", "SamplerCheckpoint", "sample", "sample_gradient",
]


#: :func:`jax.named_scope` names of the random walk's proposal and accept/reject (see
#: :data:`bayesreg.posterior.SCOPES`; ``benchmarks/profiling.py``).
PROPOSAL_SCOPE = "bayesreg_proposal"
ACCEPT_SCOPE = "bayesreg_accept"
#: ... and of the builds of a chain's :class:`KernelCache` (at each chunk start, and the
#: condensation's after an accepted elastic move)
CACHE_SCOPE = "bayesreg_cache"


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
    """Information about one transition (one MH update per block).

    Attributes
    ----------
    acceptance_rate : (B,)   ``min(1, p(theta*) / p(theta^n))`` (Eq. 13) per block
    is_accepted : (B,) bool
    cg_iterations : ()  CG iterations of the proposals' solves, summed over blocks
    solve_failed : ()  number of proposals whose solve did not converge (rejected)
    """

    acceptance_rate: jax.Array
    is_accepted: jax.Array
    cg_iterations: jax.Array
    solve_failed: jax.Array


def init(position, logdensity_fn: Callable, interior0) -> RWMHState:
    """Initial state; ``logdensity_fn(position, interior_guess) -> (logp, aux)``."""
    logp, aux = logdensity_fn(position, interior0)
    return RWMHState(position, logp, aux.interior)


class Condensation(NamedTuple):
    """A cache that makes moves of one coordinate block cheap (see :func:`build_kernel`).

    Attributes
    ----------
    logdensity_fn : callable
        ``(position, cache) -> (logp, aux)``, equal to the full log-density as long as the
        cache was built at a position that differs from ``position`` only inside ``block``.
    build : callable
        ``position -> cache``.
    block : int
        Index of the block whose moves use the cache; a move of any other block that is
        accepted rebuilds it.
    moves : int
        Updates of ``block`` per step (each a full Metropolis update).
    """

    logdensity_fn: Callable
    build: Callable
    block: int
    moves: int = 1


class Preconditioner(NamedTuple):
    """A CG preconditioner cached per chain (see :func:`build_kernel`).

    Attributes
    ----------
    logdensity_fn : callable
        ``(position, interior_guess, pre) -> (logp, aux)``: the log-density with its interior
        solve preconditioned by ``pre``.  For any ``pre`` it is the same function of the
        position as the kernel's own ``logdensity_fn`` (the CG meets the same tolerance; the
        preconditioner changes how many iterations that takes), so the target is unchanged.
    build : callable
        ``position -> pre`` at the position's elastic parameters
        (:func:`bayesreg.posterior.preconditioner`).
    """

    logdensity_fn: Callable
    build: Callable


class KernelCache(NamedTuple):
    """What a random-walk kernel carries from step to step besides the state: the
    condensation's cache and the preconditioner (``None`` where not used).  Rebuilt from the
    state at every chunk start (:func:`_build_chunk`), so a resumed run repeats the same
    arithmetic."""

    condensed: object = None
    precond: object = None


def build_kernel(logdensity_fn: Callable, blocks=None, condensation: Condensation | None = None,
                 preconditioner: Preconditioner | None = None) -> Callable:
    """RW-MH kernel ``(rng_key, state, sigmas) -> (state, info)`` for a fixed log-density.

    Parameters
    ----------
    logdensity_fn : callable
        ``(position, interior_guess) -> (logp, aux)``.
    blocks : sequence of int arrays, optional
        Coordinate blocks updated in turn, each by its own Metropolis step with a Normal
        jumping kernel (systematic-scan Metropolis-within-Gibbs; each update leaves the
        posterior invariant, so their composition does).  ``None``: one block with every
        coordinate, the paper's joint proposal (Eq. 14).
    condensation : Condensation, optional
        Moves of ``condensation.block`` evaluate ``condensation.logdensity_fn`` with the
        cache instead of ``logdensity_fn`` (for the boundary block: the interior from a
        cached ``u_i = H u_b``, no CG solve), ``condensation.moves`` times per step; after an
        accepted move of another block the cache is rebuilt (``lax.cond``).  Both
        log-densities are the same function of the position, so the target is unchanged.
    preconditioner : Preconditioner, optional
        The moves that solve (every move without a condensation) evaluate
        ``preconditioner.logdensity_fn`` with the chain's cached preconditioner, built at
        the chain's position when the chunk starts (:func:`_build_chunk`) and kept through
        the chunk: the random walk moves the parameters little per chunk, and the
        preconditioner only has to stay near ``K_ii^-1``.

    Notes
    -----
    ``sigmas[b]`` is block ``b``'s jumping-kernel scale: a vector (independent scales) or a
    matrix ``L`` (proposal covariance ``L L^T``), as in
    :func:`blackjax.mcmc.random_walk.normal`.

    With a condensation or a preconditioner the kernel is ``(rng_key, state, sigmas, cache)
    -> (state, info, cache)`` with ``cache`` a :class:`KernelCache`, and ``kernel.init_cache
    (state) -> KernelCache`` builds it.
    """

    def update(rng_key, state: RWMHState, idx, sigma, density):
        key_prop, key_acc = jax.random.split(rng_key)
        with jax.named_scope(PROPOSAL_SCOPE):
            sub = state.position[idx]
            move = normal_jumping_kernel(sigma)(key_prop, sub)
            proposal = state.position.at[idx].set(sub + move)
        logp, aux = density(proposal, state)
        with jax.named_scope(ACCEPT_SCOPE):
            log_ratio = logp - state.logdensity
            log_ratio = jnp.where(jnp.isnan(log_ratio), -jnp.inf, log_ratio)
            new = RWMHState(proposal, logp, aux.interior)
            state, (accepted, p_accept, _) = static_binomial_sampling(key_acc, log_ratio, state, new)
        return state, (p_accept, accepted, aux.solve.iterations, ~aux.solve.converged)

    def kernel(rng_key, state: RWMHState, sigmas, cache: KernelCache | None = None):
        idxs = blocks if blocks is not None else [jnp.arange(state.position.shape[0])]
        keys = jax.random.split(rng_key, len(idxs))

        def full(proposal, state):
            if preconditioner is None:
                return logdensity_fn(proposal, state.interior)
            return preconditioner.logdensity_fn(proposal, state.interior, cache.precond)

        out = []
        for b, idx in enumerate(idxs):
            idx = jnp.asarray(idx)
            if condensation is not None and b == condensation.block:
                def cached(proposal, _state, h=cache.condensed):
                    return condensation.logdensity_fn(proposal, h)

                def one(st, key, idx=idx, b=b, cached=cached):
                    st, o = update(key, st, idx, sigmas[b], cached)
                    return st, o

                state, os_ = jax.lax.scan(one, state, jax.random.split(keys[b], condensation.moves))
                out.append((jnp.mean(os_[0]), jnp.any(os_[1]), jnp.sum(os_[2]), jnp.any(os_[3])))
            else:
                state, o = update(keys[b], state, idx, sigmas[b], full)
                if condensation is not None:
                    with jax.named_scope(CACHE_SCOPE):
                        condensed = jax.lax.cond(o[1], lambda: condensation.build(state.position),
                                                 lambda: cache.condensed)
                    cache = cache._replace(condensed=condensed)
                out.append(o)
        info = RWMHInfo(
            jnp.stack([o[0] for o in out]),
            jnp.stack([o[1] for o in out]),
            sum(o[2] for o in out),
            sum(o[3].astype(jnp.int32) for o in out),
        )
        return (state, info) if cache is None else (state, info, cache)

    kernel.condensation = condensation
    kernel.preconditioner = preconditioner
    if condensation is not None or preconditioner is not None:
        def init_cache(state: RWMHState) -> KernelCache:
            with jax.named_scope(CACHE_SCOPE):
                return KernelCache(
                    None if condensation is None else condensation.build(state.position),
                    None if preconditioner is None else preconditioner.build(state.position))

        kernel.init_cache = init_cache
    return kernel


class SamplerResult(NamedTuple):
    """Output of :func:`sample` (host NumPy arrays).

    Attributes
    ----------
    positions : (C, D, dim)   thinned post-warm-up draws
    interior : (C, D, n_i, 3)   interior FE solution of each draw
    logdensity : (C, D)
    acceptance : (C, D, B)   mean acceptance probability per block over each thinning interval
    cg_iterations : (C, D)   mean CG iterations per step over each interval
    solve_failures : (C, D)   non-converged (rejected) solves per interval
    grad_evals : (C, D)   mean gradient evaluations per step over each interval (0: RW-MH)
    divergences : (C, D)   divergent transitions per interval (gradient kernels)
    rhat_history : list of (draws per chain, max monitored R-hat)
    sigma : tuple  the frozen tuned values: the proposal scale of each block (RW-MH), or
        ``(step_size (C,), inverse_mass (C, ...), eta_scale (C, n_free, n_free))`` (gradient kernels)
    warmup_acceptance : (B,) ndarray  acceptance per block in the last warm-up chunk
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
    grad_evals: np.ndarray
    divergences: np.ndarray
    rhat_history: list
    sigma: tuple
    warmup_acceptance: np.ndarray
    timings: dict
    converged: bool
    final_states: RWMHState


class SamplerCheckpoint(NamedTuple):
    """Everything :func:`sample` needs to continue after a chunk (host NumPy arrays).

    The stored draws are not part of it: they are handed to the ``on_chunk`` callback one
    chunk at a time and given back through ``resume_draws``.

    Attributes
    ----------
    states : state pytree (leaves ``(C, ...)``), or the list of its leaves (from a file)
        the chains after the last finished chunk
    sigma : tuple of arrays  the frozen tuned values (see ``SamplerResult.sigma``)
    warmup_acceptance : (B,) ndarray
    chunks_done : int  sampling chunks finished (0 right after the warm-up)
    rhat_history : list of (draws per chain, max monitored R-hat)
    timings : dict  seconds spent so far
    """

    states: RWMHState
    sigma: tuple
    warmup_acceptance: np.ndarray
    chunks_done: int
    rhat_history: list
    timings: dict


def _chain_threads(n_chains: int, n_cores: int | None = None) -> int:
    """Number of host threads that run ``n_chains`` whole chains on a CPU (equal groups).

    The smallest divisor of ``n_chains`` that is at least the number of cores available to
    this process (:func:`_cores`), or ``n_chains`` when there are more cores than chains:
    every thread runs the same number of chains, so one compiled shape serves all threads,
    and every core has a thread.  3 chains on 2 cores: 3 threads of one chain (when a chunk
    cannot be cut into pieces: :func:`_chain_pieces`).
    """
    if n_chains < 1:
        raise ValueError(f"n_chains must be >= 1, got {n_chains}")
    if n_cores is None:
        n_cores = _cores()
    return next((d for d in range(max(1, n_cores), n_chains + 1) if n_chains % d == 0), n_chains)


def _cores() -> int:
    """Cores available to this process (``os.sched_getaffinity`` where it exists)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _chain_pieces(n_chains: int, n_draws: int | None, n_cores: int | None = None) -> int:
    """Pieces per chain of a chunk when the chains do not split evenly over the cores.

    With more chains than cores and a number of chains that is not a multiple of the
    number of cores (3 chains on 2 cores), whole chains cannot be shared out evenly: three
    threads on two cores ran 107 steps/s per chain against 226 for two chains on two
    threads (paper-size mesh; the oversubscribed threads preempt each other).  Cutting
    each chain's chunk into pieces of equal length, a multiple of ``P = cores /
    gcd(chains, cores)``, gives ``chains * P`` tasks or a multiple, a multiple of the
    number of cores, which one worker per core can run without idling (a chain's pieces
    in order: :func:`_over_chains`).  ``2 P`` pieces where ``n_draws`` allows (shorter
    tasks leave less idle time at the end of a chunk when chains run at different
    speeds), else ``P``; 1 when the chains already split evenly, when there are no more
    chains than cores, or when ``n_draws`` is not a multiple of ``P`` (then
    :func:`_chain_threads` applies).  Measured (``benchmarks/schedule.py``, 3 chains on 2
    cores, paper-size mesh, three runs each): 4 pieces 1.25-1.43x and 1.23-1.29x the
    steps/s of three threads (paper joint, blocked Laplace kernels), 2 pieces 1.20-1.44x
    and 1.21-1.24x: the finer cut costs nothing measurable.
    """
    n_cores = _cores() if n_cores is None else n_cores
    if n_draws is None or n_chains <= n_cores or n_chains % n_cores == 0:
        return 1
    pieces = n_cores // math.gcd(n_chains, n_cores)
    return next((k for k in (2 * pieces, pieces) if n_draws % k == 0), 1)


def _over_chains(one_chain, n_chains: int, params_per_chain: bool, *, piece=None, start=None,
                 n_draws: int | None = None):
    """Run ``one_chain(key, state, params)`` for every chain (leading axis); returns a callable.

    On an accelerator the chains are vmapped inside one jitted call, which is what it is
    built for.  On a CPU vmap is slow here: each chain's CG solve and NUTS trajectory is a
    ``while_loop``, and vmapped loops make every chain wait for the slowest (at paper size 3
    vmapped chains ran 24 steps/s each against 46 one after the other).  XLA:CPU runs one
    chain's small kernels on one core (the ELL mat-vec of a paper-size solve takes 32 us on
    one core or two), so the chains are split into :func:`_chain_threads` equal groups, each
    a jitted ``lax.map`` over its chains, dispatched from host threads that run at once
    (JAX releases the GIL while a computation runs): on 2 cores two threads of CG
    mat-vecs ran 1.8x the throughput of one.  Each chain's arithmetic does not depend on
    the others, so neither choice changes the draws beyond round-off.

    Where the chains do not split evenly over the cores and the chunk can be cut
    (``piece`` and ``n_draws`` given, :func:`_chain_pieces` > 1), one worker thread per core
    runs pieces of single chains instead, each chain's pieces in order, a chain's next
    piece queued as soon as its previous one ends.  ``start(state) -> carry`` begins a
    chain's chunk (``None``: the carry is the state), ``piece(draw_keys (m,), carry,
    params) -> (carry, out)`` continues it over the draws of ``draw_keys``, with ``out``
    stacked over them, and ``carry[0]`` is the state, such that ``one_chain(key, ...)``
    equals ``start`` and then the pieces run in turn on ``jax.random.split(key, n_draws)``
    (the carry, with any cache of the kernel, passes from one piece to the next).
    """
    in_axes = (0, 0, 0 if params_per_chain else None)
    if jax.default_backend() != "cpu":
        return jax.jit(jax.vmap(one_chain, in_axes=in_axes))

    def map_over(fn):
        @jax.jit
        def mapped(keys, states, params):
            if params_per_chain:
                return jax.lax.map(lambda a: fn(*a), (keys, states, params))
            return jax.lax.map(lambda a: fn(a[0], a[1], params), (keys, states))

        return mapped

    n_pieces = _chain_pieces(n_chains, n_draws) if piece is not None else 1
    if n_pieces > 1:
        begin = None if start is None else jax.jit(lambda states: jax.lax.map(start, states))
        return _pieces_runner(map_over(piece), begin, n_chains, n_draws, n_pieces, params_per_chain)
    mapped = map_over(one_chain)
    n_threads = _chain_threads(n_chains)
    if n_threads == 1:
        return mapped
    size = n_chains // n_threads
    # the groups' slices and the concatenation of their outputs each in one jitted program
    # (sliced and joined leaf by leaf, op by op, they compiled about 20 small programs)
    split = jax.jit(lambda tree: [jax.tree.map(lambda a, j=j: a[j * size:(j + 1) * size], tree)
                                  for j in range(n_threads)])
    join = jax.jit(lambda outs: jax.tree.map(lambda *xs: jnp.concatenate(xs), *outs))

    def threaded(keys, states, params):
        parts = split((keys, states, params) if params_per_chain else (keys, states))

        def group(j):
            return mapped(*parts[j][:2], parts[j][2] if params_per_chain else params)

        # the first call compiles in this thread alone (no concurrent traces of one shape)
        nonlocal compiled
        first = [] if compiled else [group(0)]
        compiled = True
        with ThreadPoolExecutor(n_threads) as pool:
            outs = first + list(pool.map(group, range(len(first), n_threads)))
        return join(outs)

    compiled = False
    return threaded


def _pieces_runner(mapped_piece, begin, n_chains: int, n_draws: int, n_pieces: int,
                   params_per_chain: bool):
    """The piecewise schedule of :func:`_over_chains`: ``_cores()`` workers, tasks of one
    chain and ``n_draws / n_pieces`` draws, each chain's next piece queued when its last
    one ends (first in, first out: with ``chains * pieces`` a multiple of the workers no
    worker idles while another has work).  ``begin(states) -> carries`` (jitted, one chain
    at a time) runs in the task of a chain's first piece; ``None``: the carry is the state."""
    m = n_draws // n_pieces
    # the keys, states and parameters cut per chain and piece, and the outputs joined, each
    # in one jitted program (op by op, leaf by leaf, they compiled dozens of small programs)

    @jax.jit
    def split(keys, states, params):
        draw_keys = jax.vmap(lambda k: jax.random.split(k, n_draws))(keys)  # one_chain's keys
        one = lambda tree, c: jax.tree.map(lambda a: a[c:c + 1], tree)  # noqa: E731
        return ([[draw_keys[c:c + 1, p * m:(p + 1) * m] for p in range(n_pieces)] for c in range(n_chains)],
                [one(states, c) for c in range(n_chains)],
                [one(params, c) for c in range(n_chains)] if params_per_chain else None)

    @jax.jit
    def join(finals, outs):
        per_chain = [jax.tree.map(lambda *xs: jnp.concatenate(xs, axis=1), *o) for o in outs]
        return (jax.tree.map(lambda *xs: jnp.concatenate(xs), *finals),
                jax.tree.map(lambda *xs: jnp.concatenate(xs), *per_chain))

    compiled = False

    def run(keys, states, params):
        nonlocal compiled
        draw_keys, first, chain_params = split(keys, states, params if params_per_chain else None)

        def task(c, p, carry):
            if p == 0 and begin is not None:
                carry = begin(carry)
            # blocking: the worker holds its core until the piece is done (async dispatch
            # from worker threads that return at once ran no faster than three threads)
            return jax.block_until_ready(mapped_piece(
                draw_keys[c][p], carry, chain_params[c] if params_per_chain else params))

        outs = [[None] * n_pieces for _ in range(n_chains)]
        finals = [None] * n_chains
        with ThreadPoolExecutor(_cores()) as pool:
            pending = {}
            for c in range(n_chains):
                if not compiled:  # the first call compiles in this thread alone
                    carry, out = task(c, 0, first[c])
                    compiled = True
                    outs[c][0] = out
                    pending[pool.submit(task, c, 1, carry)] = (c, 1)
                else:
                    pending[pool.submit(task, c, 0, first[c])] = (c, 0)
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    c, p = pending.pop(fut)
                    carry, outs[c][p] = fut.result()  # a worker's exception is raised here
                    if p + 1 < n_pieces:
                        pending[pool.submit(task, c, p + 1, carry)] = (c, p + 1)
                    else:
                        finals[c] = carry if begin is None else carry[0]
        return join(finals, outs)

    return run


def _info_extras(info):
    """``(gradient evaluations, divergent)`` of a transition (zero for random walks)."""
    grads = getattr(info, "grad_evals", jnp.zeros((), jnp.int32))
    div = getattr(info, "divergent", jnp.zeros((), bool))
    return grads, div


def _draw_out(state, info):
    """A draw's stored outputs from the state after its ``thin`` transitions and their infos
    (stacked): ``(position, interior, logdensity, acceptance (B,), CG iterations per step,
    failed solves, gradient evaluations per step, divergences)``."""
    grads, div = _info_extras(info)
    return (state.position, state.interior, state.logdensity, jnp.mean(info.acceptance_rate, axis=0),
            jnp.mean(info.cg_iterations.astype(jnp.float64)), jnp.sum(info.solve_failed),
            jnp.mean(grads.astype(jnp.float64)), jnp.sum(div.astype(jnp.int32)))


def _build_chunk(kernel, n_draws: int, thin: int, n_chains: int, *, pieces: bool = True):
    """Jitted ``(keys (C,), states, params) -> (states, out)`` running ``n_draws`` thinned draws.

    ``kernel`` is ``(key, state, params) -> (state, info)``, or with a cache
    ``(key, state, params, cache) -> (state, info, cache)`` when it has
    ``kernel.init_cache(state) -> cache`` (the random walks' condensation and
    preconditioner, the gradient kernels' condensation and normaliser; :func:`sample_gradient`
    runs those through :func:`_build_adaptive_chunk`, the same draws).  The cache is
    built from the state at every chunk start, so a resumed run repeats the same
    arithmetic, and carried through the chunk; where a CPU runs the chunk in pieces
    (:func:`_chain_pieces`) it passes from one piece to the next, so the pieces repeat the
    arithmetic of the whole chunk.
    ``kernel.per_chain_params``: ``params`` has a leading chain axis.  ``pieces``: allow
    the piecewise CPU schedule (:func:`_chain_pieces`; the random walks use it, the
    gradient kernels do not: NUTS on the quickstart problem ran 0.97x (0.82-0.99) the
    transitions/s of three threads in pieces, ``benchmarks/schedule.py --kernel nuts``,
    identical draws).
    ``out`` is ``(positions, interior, logdensity, acceptance (B,), CG iterations per step,
    failed solves, gradient evaluations per step, divergences)`` per draw.
    """
    init_cache = getattr(kernel, "init_cache", None)
    per_chain = getattr(kernel, "per_chain_params", False)

    def start(state):
        return state, init_cache(state)

    def piece(draw_keys, carry, params):
        def draw(carry, key):
            def step(carry, key):
                if init_cache is None:
                    return kernel(key, carry, params)
                st, info, cache = kernel(key, carry[0], params, carry[1])
                return (st, cache), info

            carry, info = jax.lax.scan(step, carry, jax.random.split(key, thin))
            return carry, _draw_out(carry if init_cache is None else carry[0], info)

        return jax.lax.scan(draw, carry, draw_keys)

    def one_chain(key, state, params):
        carry = state if init_cache is None else start(state)
        carry, out = piece(jax.random.split(key, n_draws), carry, params)
        return (carry if init_cache is None else carry[0]), out

    return _over_chains(one_chain, n_chains, per_chain, piece=piece if pieces else None,
                        start=None if init_cache is None else start, n_draws=n_draws)


def _build_adaptive_chunk(kernel, ws_step, n_draws: int, thin: int, n_chains: int):
    """One chunk program for the gradient kernels' warm-up and sampling (one compilation).

    ``mapped(keys (C, n_draws, thin), states, (ws, stages (C, n_draws, thin, 2), adapt (C,)))
    -> ((states, ws, (acceptance (C, B), divergences (C,), gradients (C,))), out)``: each
    transition is ``ws_step`` (:func:`bayesreg.kernels.build_warmup_step`: the kernel at the
    parameters the warm-up state ``ws`` holds, then the adaptation of ``ws`` at the
    ``stages`` row), whose new ``ws`` is kept where ``adapt`` and discarded elsewhere; ``out``
    is :func:`_build_chunk`'s.  The warm-up runs it with ``adapt`` and Stan's windows, the
    sampling without, from a ``ws`` holding the frozen parameters: the same kernel
    arithmetic as a chunk of :func:`_build_chunk` at those parameters (the draws are equal),
    and one program where the two had compiled one each (7-10 s each at the quickstart's
    size; the discarded adaptation costs next to nothing beside a NUTS trajectory).
    """

    def one_chain(keys, state, params):
        ws, stages, adapt = params

        def step(carry, xs):
            st, w_, cache = carry
            st, w_new, cache, info = ws_step(xs[0], st, w_, cache, xs[1])
            w_ = jax.tree.map(lambda a, b: jnp.where(adapt, a, b), w_new, w_)
            return (st, w_, cache), info

        def draw(carry, xs):
            carry, info = jax.lax.scan(step, carry, xs)
            grads, div = _info_extras(info)
            return carry, (_draw_out(carry[0], info), (info.acceptance_rate, div, grads))

        carry = (state, ws, kernel.init_cache(state))
        (state, ws, _), (out, (acc, div, grads)) = jax.lax.scan(draw, carry, (keys, stages))
        stats = (jnp.mean(acc.reshape(-1, acc.shape[-1]), axis=0), jnp.sum(div),
                 jnp.mean(grads.astype(jnp.float64)))
        return (state, ws, stats), out

    return _over_chains(one_chain, n_chains, True)


def _scaled(sigmas, log_scales):
    return tuple(jnp.asarray(s_) * np.exp(ls) for s_, ls in zip(sigmas, log_scales))


DENSE_MAX = 16  # blocks up to this size (the elastic parameters) adapt a dense proposal


def _warmup(chunk, states, key_warm, sigmas, idxs, adapt, n_chains, warmup_steps, chunk_draws,
            thinning, target_acceptance, progress):
    """Robbins-Monro on each block's log-scale; scales re-estimated from the draws of two
    windows: a dense factor ``2.38 / sqrt(d) chol(C)`` for blocks of at most ``DENSE_MAX``
    coordinates (the elastic parameters), per-coordinate scales for larger ones.

    Returns ``(states, frozen sigmas, last acceptance per block, timings)``.
    """
    from tqdm.auto import tqdm

    t0 = time.perf_counter()
    timings = {}
    n_warm = int(np.ceil(warmup_steps / (chunk_draws * thinning))) if warmup_steps else 0
    log_scales = np.zeros(len(idxs))
    warm_acc = np.full(len(idxs), np.nan)
    bar = tqdm(total=n_warm, disable=not progress or n_warm == 0, desc="warm-up", unit="chunk")
    # windows: scales re-estimated from the draws of [n/4, n/2) and [n/2, 3n/4)
    window_ends = {n_warm // 2, (3 * n_warm) // 4} - {0}
    window: list[np.ndarray] = []
    k_gain = 0
    for k in range(n_warm):
        states, out = chunk(jax.random.split(jax.random.fold_in(key_warm, k), n_chains), states,
                            _scaled(sigmas, log_scales))
        if k == 0:
            timings["first_chunk_incl_compile_s"] = time.perf_counter() - t0
        warm_acc = np.asarray(out[3]).reshape(-1, len(idxs)).mean(axis=0)
        k_gain += 1
        log_scales += 2.0 / np.sqrt(k_gain) * (warm_acc - target_acceptance)
        if k >= n_warm // 4:
            window.append(np.asarray(out[0]))  # (C, chunk, dim)
        if k + 1 in window_ends and window:
            pos = np.concatenate(window, axis=1)
            window = []
            new = list(sigmas)
            for b, ix in enumerate(idxs):
                sd = np.sqrt(pos[:, :, ix].var(axis=1).mean(axis=0))
                if not adapt[b] or not np.all(sd > 0):
                    continue
                if len(ix) <= DENSE_MAX:  # small block: the window's covariance (Haario et al.)
                    cov = np.mean([np.atleast_2d(np.cov(p_[:, ix], rowvar=False)) for p_ in pos], axis=0)
                    try:
                        new[b] = 2.38 / np.sqrt(len(ix)) * np.linalg.cholesky(cov)
                    except np.linalg.LinAlgError:
                        new[b] = 2.38 / np.sqrt(len(ix)) * np.diag(sd)
                elif sigmas[b].ndim == 1:
                    new[b] = 2.38 / np.sqrt(len(ix)) * sd
                else:  # keep the correlations of the factor, match its marginal scales
                    implied = np.sqrt(np.sum(sigmas[b] ** 2, axis=1))
                    new[b] = (2.38 / np.sqrt(len(ix)) * sd / implied)[:, None] * sigmas[b]
                log_scales[b] = 0.0
            sigmas = tuple(new)
            k_gain = 0
        bar.set_postfix(acc=np.array2string(warm_acc, precision=2),
                        scale=np.array2string(np.exp(log_scales), precision=2))
        bar.update(1)
    bar.close()
    frozen = tuple(np.asarray(s_) for s_ in _scaled(sigmas, log_scales))
    return states, frozen, warm_acc, timings


def sample(
    rng_key,
    logdensity_fn: Callable,
    initial_positions,
    interior0,
    sigma,
    *,
    blocks=None,
    adapt_diagonal=None,
    thinning: int = 10,
    warmup_steps: int = 2000,
    max_draws: int = 2000,
    min_draws: int = 100,
    chunk_draws: int = 50,
    target_acceptance: float = 0.25,
    rhat_threshold: float = 1.2,
    rhat_split: bool = False,
    estimands: Callable | None = None,
    progress: bool = True,
    on_chunk: Callable | None = None,
    resume: SamplerCheckpoint | None = None,
    resume_draws: tuple | None = None,
    condensation: Condensation | None = None,
    preconditioner: Preconditioner | None = None,
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
    sigma : array or tuple of arrays
        Initial jumping-kernel scale per block: ``(d_b,)`` vector or ``(d_b, d_b)`` factor.
    blocks : sequence of int arrays, optional
        Coordinate blocks (see :func:`build_kernel`); ``None``: one joint block.
    adapt_diagonal : sequence of bool, optional
        Per block: at 1/2 and 3/4 of the warm-up, set the proposal's marginal scales to
        ``2.38 / sqrt(d_b)`` times the within-chain standard deviation of the chains' draws
        since the previous window (Haario-style diagonal adaptation): a vector ``sigma`` is
        replaced, the rows of a matrix factor are rescaled (its correlations are kept).
        Blocks of at most ``DENSE_MAX`` coordinates (the elastic parameters) get the dense
        factor ``2.38 / sqrt(d_b) chol(C)`` of the window's within-chain covariance ``C``
        instead (their ``sigma`` is taken as a diagonal factor from the start, so the kernel
        is traced once).  The scale adaptation then restarts.
    thinning : int
        Steps per stored draw (paper: 10).
    warmup_steps : int
        Steps per chain spent tuning (discarded); rounded up to whole chunks.  Each block's
        scale follows Robbins-Monro on its log toward ``target_acceptance``; frozen after.
    max_draws, min_draws : int
        Bounds on stored draws per chain after warm-up, counted in whole chunks: sampling
        stops at the first chunk that reaches ``max_draws``, so a ``max_draws`` that is not
        a multiple of ``chunk_draws`` is rounded up to one.
    chunk_draws : int
        Draws per jitted call (the R-hat check and progress-bar interval).
    target_acceptance : float
        Warm-up target of the mean acceptance probability (paper: about 0.25).
    rhat_threshold : float
        Stop when the classic Gelman-Rubin R-hat of every estimand is below it.
    rhat_split : bool
        Monitor the split-chain version (see :func:`bayesreg.diagnostics.gelman_rubin`).
    estimands : callable, optional
        ``(draws (C, D, dim) ndarray) -> (C, D, K) ndarray`` of the scalars to monitor,
        acting draw by draw (it is applied to each chunk as it arrives:
        :class:`bayesreg.diagnostics.RunningGelmanRubin`); default: the position coordinates.
    progress : bool
        Show a tqdm progress bar with acceptance and the worst R-hat.
    on_chunk : callable, optional
        ``on_chunk(checkpoint, out)`` after the warm-up (``out=None``) and after every
        sampling chunk; ``out`` is the chunk's ``(positions (C, n, dim), interior
        (C, n, n_i, 3), logdensity (C, n), acceptance (C, n, B), cg_iterations (C, n),
        solve_failures (C, n), grad_evals (C, n), divergences (C, n))`` with
        ``n = chunk_draws``.  Persisting both lets a killed
        run continue (``resume``).
    resume : SamplerCheckpoint, optional
        Continue from a checkpoint (warm-up skipped).  Chunk ``k`` always uses the key
        ``fold_in(split(rng_key)[1], k)``, so a resumed run gives the same draws as an
        uninterrupted one with the same ``rng_key``.
    resume_draws : tuple of 8 arrays, optional
        The draws of the finished chunks (as ``out``, concatenated along axis 1); required
        with ``resume``.
    condensation : Condensation, optional
        Cached moves of one block (see :func:`build_kernel`); needs ``blocks``.
    preconditioner : Preconditioner, optional
        A per-chain CG preconditioner, rebuilt at every chunk start (see
        :func:`build_kernel`); the draws equal those without it to the CG tolerance.

    Returns
    -------
    SamplerResult

    Raises
    ------
    ValueError
        On bad arguments (among them: ``blocks`` that do not partition ``range(dim)``, a
        ``sigma`` of the wrong shape, non-finite, or, as a vector of scales, not ``> 0``;
        ``min_draws > max_draws`` or ``chunk_draws > max_draws``) or if any chain starts at
        a point of zero posterior density.
    """
    x0, n_chains = _check_starts(initial_positions, thinning, chunk_draws, max_draws, min_draws,
                                 target_acceptance)
    dim = x0.shape[1]
    idxs = [np.arange(dim)] if blocks is None else _check_blocks(blocks, dim)
    sigmas = tuple(np.asarray(s_, np.float64) for s_ in (sigma if isinstance(sigma, tuple) else (sigma,)))
    if len(sigmas) != len(idxs):
        raise ValueError(f"{len(idxs)} blocks but {len(sigmas)} sigmas")
    for k, (s_, ix) in enumerate(zip(sigmas, idxs)):
        if s_.shape not in ((len(ix),), (len(ix), len(ix))):
            raise ValueError(f"sigma of block {k} has shape {s_.shape}, block size {len(ix)}")
        if not np.all(np.isfinite(s_)):
            raise ValueError(f"sigma of block {k} must be finite, got non-finite values")
        if s_.ndim == 1 and not np.all(s_ > 0):
            raise ValueError(f"sigma of block {k} (a vector of scales) must be > 0, got minimum "
                             f"{s_.min()}")
    adapt = list(adapt_diagonal) if adapt_diagonal is not None else [False] * len(idxs)
    sigmas = tuple(np.diag(np.broadcast_to(s_, (len(ix),))) if a_ and warmup_steps and s_.ndim < 2
                   and len(ix) <= DENSE_MAX else s_ for s_, ix, a_ in zip(sigmas, idxs, adapt))
    if condensation is not None and blocks is None:
        raise ValueError("condensation needs coordinate blocks")
    kernel = build_kernel(logdensity_fn, None if blocks is None else idxs, condensation, preconditioner)
    chunk = _build_chunk(kernel, chunk_draws, thinning, n_chains)
    key_warm, key_samp = jax.random.split(rng_key)

    def init_states():
        return jax.vmap(lambda x: init(x, logdensity_fn, interior0))(x0)

    def warm_up():
        states = jax.jit(init_states)()
        _check_finite(states)
        return _warmup(chunk, states, key_warm, sigmas, idxs, adapt, n_chains, warmup_steps,
                       chunk_draws, thinning, target_acceptance, progress)

    return _drive(chunk, init_states, warm_up, key_samp, n_chains=n_chains, n_blocks=len(idxs),
                  max_draws=max_draws, min_draws=min_draws, chunk_draws=chunk_draws,
                  rhat_threshold=rhat_threshold, rhat_split=rhat_split, estimands=estimands,
                  progress=progress, on_chunk=on_chunk, resume=resume, resume_draws=resume_draws,
                  params_type=lambda *a: tuple(a))


def _check_starts(initial_positions, thinning, chunk_draws, max_draws, min_draws, target_acceptance):
    x0 = jnp.asarray(initial_positions, dtype=jnp.float64)
    if x0.ndim != 2:
        raise ValueError(f"initial_positions must be (chains, dim), got {x0.shape}")
    if x0.shape[0] < 2:
        raise ValueError("at least 2 chains are needed for R-hat")
    if thinning < 1 or chunk_draws < 1 or max_draws < 1:
        raise ValueError("thinning, chunk_draws and max_draws must be >= 1")
    if min_draws > max_draws:
        raise ValueError(f"min_draws must be <= max_draws, got min_draws={min_draws}, "
                         f"max_draws={max_draws}")
    if chunk_draws > max_draws:
        raise ValueError(f"chunk_draws must be <= max_draws (draws come in whole chunks), got "
                         f"chunk_draws={chunk_draws}, max_draws={max_draws}")
    if not 0 < target_acceptance < 1:
        raise ValueError(f"target_acceptance must lie in (0, 1), got {target_acceptance}")
    return x0, x0.shape[0]


def _check_blocks(blocks, dim: int) -> list:
    """The coordinate blocks as int arrays; they must partition ``range(dim)``."""
    idxs = []
    for k, b in enumerate(blocks):
        ix = np.asarray(b)
        if ix.ndim != 1 or not (np.issubdtype(ix.dtype, np.integer) or ix.size == 0):
            raise ValueError(f"block {k} must be a 1-D array of integer coordinate indices, got "
                             f"shape {ix.shape} and dtype {ix.dtype}")
        idxs.append(ix.astype(np.int64))
    flat = np.concatenate(idxs) if idxs else np.zeros(0, np.int64)
    counts = np.bincount(flat[(flat >= 0) & (flat < dim)], minlength=dim)
    outside = flat[(flat < 0) | (flat >= dim)]
    if outside.size or np.any(counts != 1):
        detail = []
        if outside.size:
            detail.append(f"indices outside [0, {dim}): {outside[:10].tolist()}")
        if np.any(counts == 0):
            detail.append(f"missing: {np.flatnonzero(counts == 0)[:10].tolist()}")
        if np.any(counts > 1):
            detail.append(f"repeated: {np.flatnonzero(counts > 1)[:10].tolist()}")
        raise ValueError(f"blocks must partition range({dim}) (each coordinate in exactly one "
                         f"block), got {'; '.join(detail)}")
    return idxs


def _check_finite(states):
    bad = ~np.isfinite(np.asarray(states.logdensity))
    if bad.any():
        raise ValueError(
            f"chains {np.flatnonzero(bad).tolist()} start at zero posterior density "
            "(constraint violated or CG solve not converged at the initial position)"
        )


N_OUT = 8  # positions, interior, logdensity, acceptance, CG, failed solves, gradients, divergences


def _drive(chunk, init_states, warm_up, key_samp, *, n_chains, n_blocks, max_draws, min_draws,
           chunk_draws, rhat_threshold, rhat_split, estimands, progress, on_chunk, resume,
           resume_draws, params_type) -> SamplerResult:
    """The sampling loop shared by every kernel: chunks, R-hat stopping, checkpoints, resume.

    ``warm_up() -> (states, frozen params, warm-up acceptance per block, timings)``;
    ``init_states()`` gives the structure of the states (to rebuild a checkpoint's leaves);
    ``params_type`` rebuilds the frozen parameters from their tuple of arrays.
    """
    estimands = estimands or (lambda d: d)
    n_samp = int(np.ceil(max_draws / chunk_draws))
    t0 = time.perf_counter()
    if resume is None:
        states, frozen, warm_acc, timings = warm_up()
        timings["warmup_s"] = time.perf_counter() - t0 + timings.get("warmup_s", 0.0)
        history: list = []
        parts: list[list[np.ndarray]] = [[] for _ in range(N_OUT)]
        k = 0
        if on_chunk is not None:
            on_chunk(SamplerCheckpoint(jax.tree.map(np.asarray, states), _as_arrays(frozen), warm_acc,
                                       0, [], dict(timings)), None)
    else:
        if resume_draws is None and resume.chunks_done:
            raise ValueError("resume needs resume_draws (the draws of the finished chunks)")
        treedef = jax.tree.structure(jax.eval_shape(init_states))
        leaves = resume.states if isinstance(resume.states, list) else jax.tree.leaves(resume.states)
        states = jax.tree.unflatten(treedef, [jnp.asarray(a) for a in leaves])
        frozen = params_type(*(np.asarray(f_) for f_ in resume.sigma))
        warm_acc = np.asarray(resume.warmup_acceptance)
        timings = dict(resume.timings)
        history = [tuple(h) for h in resume.rhat_history]
        k = int(resume.chunks_done)
        parts = [[np.asarray(a)] for a in resume_draws] if k else [[] for _ in range(N_OUT)]
        if k and parts[0][0].shape[1] != k * chunk_draws:
            raise ValueError(f"resume_draws hold {parts[0][0].shape[1]} draws per chain, "
                             f"the checkpoint {k} chunks of {chunk_draws}")
        if len(parts) != N_OUT:
            raise ValueError(f"resume_draws must hold {N_OUT} arrays, got {len(parts)}")
    frozen = params_type(*(jnp.asarray(f_) for f_ in frozen))

    from tqdm.auto import tqdm

    bar = tqdm(total=n_samp, initial=k, disable=not progress, desc="sampling", unit="chunk")
    t1 = time.perf_counter()
    spent = timings.get("sampling_s", 0.0)
    rhat = history[-1][1] if history else np.inf
    n_draws = k * chunk_draws
    # R-hat from per-chunk moments (constant work per chunk), fed chunk by chunk as the run
    # that wrote the checkpoint fed them, so a resumed run stops where it would have
    monitor = RunningGelmanRubin(estimands)
    acc_sum = np.zeros(n_blocks)
    for j in range(k):
        monitor.add(parts[0][0][:, j * chunk_draws:(j + 1) * chunk_draws])
        acc_sum += parts[3][0][:, j * chunk_draws:(j + 1) * chunk_draws].reshape(-1, n_blocks).sum(axis=0)

    def done():
        return n_draws >= max_draws or (n_draws >= min_draws and rhat < rhat_threshold)

    while not done():
        states, out = chunk(jax.random.split(jax.random.fold_in(key_samp, k), n_chains), states, frozen)
        out = tuple(np.asarray(o) for o in out)
        k += 1
        for lst, o in zip(parts, out):
            lst.append(o)
        n_draws += chunk_draws
        monitor.add(out[0])
        if n_draws >= (4 if rhat_split else 2):  # split halves need 2 draws each
            rhat = float(np.nanmax(monitor.rhat(split=rhat_split)))
        history.append((n_draws, rhat))
        acc_sum += out[3].reshape(-1, n_blocks).sum(axis=0)
        acc = acc_sum / (n_chains * n_draws)
        bar.set_postfix(acc=np.array2string(acc, precision=2), rhat=f"{rhat:.3f}", draws=n_draws)
        bar.update(1)
        timings["sampling_s"] = spent + time.perf_counter() - t1
        if on_chunk is not None:
            on_chunk(SamplerCheckpoint(jax.tree.map(np.asarray, states), _as_arrays(frozen), warm_acc, k,
                                       list(history), dict(timings)), out)
    bar.close()
    timings["sampling_s"] = spent + time.perf_counter() - t1
    pos, interior, lp, acc, cg, fail, grads, div = (np.concatenate(p_, axis=1) for p_ in parts)
    return SamplerResult(
        positions=pos,
        interior=interior,
        logdensity=lp,
        acceptance=acc,
        cg_iterations=cg,
        solve_failures=fail,
        grad_evals=grads,
        divergences=div,
        rhat_history=history,
        sigma=_as_arrays(frozen),
        warmup_acceptance=warm_acc,
        timings=timings,
        converged=bool(rhat < rhat_threshold),
        final_states=states,
    )


def _as_arrays(frozen) -> tuple:
    return tuple(np.asarray(f_) for f_ in frozen)


def sample_gradient(
    rng_key,
    target,
    initial_positions,
    interior0,
    *,
    kind: str = "nuts",
    step_size: float = 0.2,
    eta_scale=0.1,
    dense_mass: bool = False,
    adapt_mass: bool = True,
    num_integration_steps: int = 16,
    jitter_integration_steps: bool = True,
    max_tree_depth: int = 10,
    elastic_moves: int = 1,
    thinning: int = 1,
    warmup_steps: int = 1000,
    max_draws: int = 1000,
    min_draws: int = 100,
    chunk_draws: int = 50,
    target_acceptance: float | None = None,
    rhat_threshold: float = 1.2,
    rhat_split: bool = False,
    estimands: Callable | None = None,
    progress: bool = True,
    on_chunk: Callable | None = None,
    resume: SamplerCheckpoint | None = None,
    resume_draws: tuple | None = None,
) -> SamplerResult:
    """Parallel chains of a gradient kernel (:mod:`bayesreg.kernels`) with windowed warm-up.

    Same chains, thinning, R-hat stopping, checkpoints and result as :func:`sample`; the
    warm-up is Stan's windowed adaptation (step size by dual averaging toward
    ``target_acceptance``, a diagonal or dense inverse mass matrix from the slow windows) on
    each chain, plus the scale of the elastic random walk; the tuned values are frozen
    after it and returned in ``SamplerResult.sigma`` as ``(step_size (C,), inverse_mass
    (C, ...), eta_scale (C, n_free, n_free))`` (the elastic random walk's factor).

    Parameters
    ----------
    rng_key : PRNGKey
    target : bayesreg.kernels.Target
    initial_positions : (C, dim) array  natural positions ``[u_b.ravel(), phi]``
    interior0 : (n_i, 3) array  warm start of the first solve
    kind : {"mala", "hmc", "nuts"}
    step_size : float  initial leapfrog step (in the preconditioned coordinates ``w``)
    eta_scale : float, (n_free,) or (n_free, n_free) array
        initial scale(s), or lower-triangular factor, of the elastic random walk
    dense_mass : bool  adapt a dense inverse mass matrix instead of a diagonal one
    adapt_mass : bool  adapt the inverse mass matrix at all (else identity in ``w``)
    num_integration_steps : int  HMC's leapfrog steps (their mean if jittered)
    jitter_integration_steps : bool  HMC: draw the number of leapfrog steps uniformly from
        ``1 .. 2 num_integration_steps - 1`` each transition (:func:`bayesreg.kernels.build_kernel`)
    max_tree_depth : int  NUTS' maximum number of trajectory doublings
    elastic_moves : int  elastic random-walk updates per transition
    thinning, warmup_steps, max_draws, min_draws, chunk_draws, rhat_threshold, rhat_split,
    estimands, progress, on_chunk, resume, resume_draws
        As :func:`sample` (``warmup_steps`` rounded up to whole chunks).
    target_acceptance : float, optional
        Default :func:`bayesreg.kernels.default_target_acceptance` of ``kind``.

    Returns
    -------
    SamplerResult

    Raises
    ------
    ValueError
        On bad arguments (among them: ``step_size`` not finite and ``> 0``, ``eta_scale``
        non-finite or, as scales, not ``> 0``; ``min_draws > max_draws`` or ``chunk_draws >
        max_draws``) or if any chain starts at a point of zero posterior density.
    """
    from bayesreg import kernels as gk

    target_acceptance = target_acceptance or gk.default_target_acceptance(kind)
    x0, n_chains = _check_starts(initial_positions, thinning, chunk_draws, max_draws, min_draws,
                                 target_acceptance)
    if not (np.ndim(step_size) == 0 and np.isfinite(step_size) and step_size > 0):
        raise ValueError(f"step_size must be a finite scalar > 0, got {step_size}")
    eta_check = np.asarray(eta_scale, np.float64)
    if not np.all(np.isfinite(eta_check)) or (eta_check.ndim < 2 and not np.all(eta_check > 0)):
        raise ValueError(f"eta_scale must be finite and, as scales, > 0, got {eta_scale}")
    kernel = gk.build_kernel(target, kind, num_integration_steps=num_integration_steps,
                             jitter_integration_steps=jitter_integration_steps,
                             max_num_doublings=max_tree_depth, elastic_moves=elastic_moves)
    ws_init, ws_step, ws_final = gk.build_warmup_step(
        kernel, target_acceptance=target_acceptance, dense_mass=dense_mass, adapt_mass=adapt_mass)
    key_warm, key_samp = jax.random.split(rng_key)
    n_blocks = 1 + (target.n_free > 0)
    eta0 = np.asarray(eta_scale, np.float64)  # scales become a diagonal factor in ws_init
    eta0 = eta0 if eta0.ndim == 2 else np.broadcast_to(eta0, (target.n_free,))
    dim_u = x0.shape[1] - target.n_free  # the preconditioned u_b coordinates w
    mapped = _build_adaptive_chunk(kernel, ws_step, chunk_draws, thinning, n_chains)

    @jax.jit
    def ws_start():
        ws = jax.vmap(lambda _: ws_init(dim_u, step_size, eta0))(jnp.arange(n_chains))
        # BlackJAX's initial adaptation states hold weakly typed floats (python 0.0) that
        # the warm-up step returns strongly typed: made strong here, so that the chunk
        # program compiles once, not twice (9-10 s a compilation at the quickstart's size);
        # the integer counters stay weak in and out
        return jax.tree.map(lambda a: jnp.asarray(a, a.dtype) if jnp.issubdtype(a.dtype, jnp.floating)
                            else a, ws)

    @jax.jit
    def ws_frozen(frozen):
        # a warm-up state whose kernel parameters are exactly ``frozen`` (eta_scale * exp(0))
        ws = ws_start()
        return ws._replace(step_size=frozen.step_size, inverse_mass=frozen.inverse_mass,
                           eta_base=frozen.eta_scale, log_eta_scale=jnp.zeros_like(ws.log_eta_scale))

    # the draws' keys as the chunks of :func:`_build_chunk` and the former warm-up took them
    samp_keys = jax.jit(jax.vmap(lambda k: jax.vmap(lambda kd: jax.random.split(kd, thinning))(
        jax.random.split(k, chunk_draws))))
    warm_keys = jax.jit(jax.vmap(lambda k: jax.random.split(k, chunk_draws * thinning).reshape(
        chunk_draws, thinning)))
    no_stage, no_adapt = np.zeros((n_chains, chunk_draws, thinning, 2), np.int32), np.zeros(n_chains, bool)

    def chunk(keys, states, frozen):
        (states, _, _), out = mapped(samp_keys(keys), states, (ws_frozen(frozen), no_stage, no_adapt))
        return states, out

    def init_states():
        return jax.vmap(lambda x: gk.init(target, x, interior0)[0])(x0)

    def warm_up():
        t0 = time.perf_counter()
        states = jax.jit(init_states)()
        _check_finite(states)
        ws = ws_start()
        per_chunk = chunk_draws * thinning
        n_warm = int(np.ceil(warmup_steps / per_chunk)) if warmup_steps else 0
        stages = gk.schedule(n_warm * per_chunk) if n_warm else np.zeros((0, 2), np.int32)
        adapt = np.ones(n_chains, bool)

        from tqdm.auto import tqdm

        timings = {}
        warm_acc = np.full(n_blocks, np.nan)
        bar = tqdm(total=n_warm, disable=not progress or n_warm == 0, desc="warm-up", unit="chunk")
        for k in range(n_warm):
            keys = jax.random.split(jax.random.fold_in(key_warm, k), n_chains)
            stage = stages[k * per_chunk:(k + 1) * per_chunk].reshape(chunk_draws, thinning, 2)
            (states, ws, (acc, div, grads)), _ = mapped(
                warm_keys(keys), states, (ws, np.broadcast_to(stage, (n_chains,) + stage.shape), adapt))
            if k == 0:
                timings["first_chunk_incl_compile_s"] = time.perf_counter() - t0
            warm_acc = np.asarray(acc).mean(axis=0)
            bar.set_postfix(acc=np.array2string(warm_acc, precision=2),
                            step=np.array2string(np.asarray(ws.step_size), precision=3),
                            grads=f"{float(np.mean(grads)):.0f}", div=int(np.sum(div)))
            bar.update(1)
        bar.close()
        frozen = jax.jit(jax.vmap(ws_final))(ws)
        return states, tuple(np.asarray(f_) for f_ in frozen), warm_acc, timings

    return _drive(chunk, init_states, warm_up, key_samp, n_chains=n_chains, n_blocks=n_blocks,
                  max_draws=max_draws, min_draws=min_draws, chunk_draws=chunk_draws,
                  rhat_threshold=rhat_threshold, rhat_split=rhat_split, estimands=estimands,
                  progress=progress, on_chunk=on_chunk, resume=resume, resume_draws=resume_draws,
                  params_type=lambda *a: gk.GibbsParams(*a))
