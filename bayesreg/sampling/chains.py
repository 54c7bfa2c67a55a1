"""The chain scheduler: how parallel chains of a kernel run on the hardware.

Like NumPyro's ``chain_method``, the way the chains are mapped is a choice
(:data:`CHAIN_METHODS`), which never changes the draws beyond round-off (each chain's
arithmetic does not depend on the others):

``"vectorized"``
    The chains ``vmap``-ed inside one jitted call: what an accelerator is built for, the
    default there.  On a CPU vmapped ``while_loop``\\ s (each chain's CG solves and NUTS
    trajectories) make every chain wait for the slowest.
``"sequential"``
    One jitted ``lax.map`` over the chains, in one thread.
``"threads"``
    The chains cut into :func:`chain_threads` equal groups, each a jitted ``lax.map``,
    dispatched from host threads that run at once (JAX releases the GIL while a computation
    runs).  XLA:CPU runs one chain's small kernels on one core, so this uses the cores.
``"pieces"``
    Where the chains do not split evenly over the cores (3 chains on 2 cores), one worker
    thread per core runs pieces of single chains, each chain's pieces in order
    (:func:`chain_pieces`), so no core idles while another oversubscribes; elsewhere as
    ``"threads"``.  Needs a kernel whose chunk can be cut (the random walks').
``"auto"``
    ``"vectorized"`` on an accelerator; on a CPU ``"pieces"`` where it applies, else
    ``"threads"`` (``"sequential"`` with one group).

:func:`build_chunk` and :func:`build_adaptive_chunk` run a :class:`~bayesreg.sampling.kernels.base.Kernel`
for a chunk of thinned draws on every chain, through :func:`map_chains`.
"""

from __future__ import annotations

import contextlib
import math
import os
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from bayesreg.sampling.kernels.base import Kernel

__all__ = ["CHAIN_METHODS", "ChainMap", "available_cores", "chain_threads", "chain_pieces",
           "resolve_method", "map_chains", "build_chunk", "build_adaptive_chunk"]

CHAIN_METHODS = ("auto", "vectorized", "sequential", "threads", "pieces")


class ChainMap(NamedTuple):
    """A function of all chains and how it maps them.

    Attributes
    ----------
    run : callable
        ``(keys (C, ...), states (C, ...), params) -> (states, out)``.
    method : str
        The method in use (one of :data:`CHAIN_METHODS` other than ``"auto"``).
    """

    run: Callable
    method: str


def available_cores() -> int:
    """Cores available to this process (``os.sched_getaffinity`` where it exists)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def chain_threads(n_chains: int, n_cores: int | None = None) -> int:
    """Number of host threads that run ``n_chains`` whole chains (``"threads"``, equal groups).

    The smallest divisor of ``n_chains`` that is at least the number of cores
    (:func:`available_cores`), or ``n_chains`` when there are more cores than chains: every
    thread runs the same number of chains, so one compiled shape serves all threads, and
    every core has a thread.  3 chains on 2 cores: 3 threads of one chain.

    Raises
    ------
    ValueError
        ``n_chains < 1``.
    """
    if n_chains < 1:
        raise ValueError(f"n_chains must be >= 1, got {n_chains}")
    if n_cores is None:
        n_cores = available_cores()
    return next((d for d in range(max(1, n_cores), n_chains + 1) if n_chains % d == 0), n_chains)


def chain_pieces(n_chains: int, n_draws: int | None, n_cores: int | None = None) -> int:
    """Pieces per chain of a chunk of ``n_draws`` draws (``"pieces"``).

    With more chains than cores and a number of chains that is not a multiple of the
    number of cores (3 chains on 2 cores), whole chains cannot be shared out evenly, and
    oversubscribed threads preempt each other.  Cutting each chain's chunk into pieces of
    equal length, a multiple of ``P = cores / gcd(chains, cores)``, gives ``chains * P``
    tasks or a multiple, a multiple of the number of cores, which one worker per core can
    run without idling.  ``2 P`` pieces where ``n_draws`` allows (shorter tasks leave less
    idle time at the end of a chunk when chains run at different speeds), else ``P``; 1
    when the chains already split evenly, when there are no more chains than cores, or when
    ``n_draws`` is not a multiple of ``P`` (then :func:`chain_threads` applies).
    """
    n_cores = available_cores() if n_cores is None else n_cores
    if n_draws is None or n_chains <= n_cores or n_chains % n_cores == 0:
        return 1
    pieces = n_cores // math.gcd(n_chains, n_cores)
    return next((k for k in (2 * pieces, pieces) if n_draws % k == 0), 1)


def resolve_method(method: str, n_chains: int, n_draws: int | None = None, *,
                   can_piece: bool = False) -> str:
    """The concrete method that ``method`` means here (see the module docstring).

    Parameters
    ----------
    method : str
        One of :data:`CHAIN_METHODS`.
    n_chains : int
    n_draws : int, optional
        Draws per chunk (``"pieces"`` cuts them).
    can_piece : bool
        The chunk can be cut into pieces (a ``piece`` function exists).

    Raises
    ------
    ValueError
        An unknown method, or ``"pieces"`` for a chunk that cannot be cut.
    """
    if method not in CHAIN_METHODS:
        raise ValueError(f"unknown chain method {method!r}; expected one of {CHAIN_METHODS}")
    if method == "pieces" and not can_piece:
        raise ValueError("chain method 'pieces' needs a kernel whose chunk can be cut into "
                         "pieces (the random walks'); use 'threads' for the gradient kernels")
    if method == "auto":
        if jax.default_backend() != "cpu":
            return "vectorized"
        method = "pieces" if can_piece else "threads"
    if method == "pieces" and chain_pieces(n_chains, n_draws) == 1:
        method = "threads"
    if method == "threads" and chain_threads(n_chains) == 1:
        method = "sequential"
    return method


def map_chains(one_chain: Callable, n_chains: int, params_per_chain: bool, *,
               method: str = "auto", piece: Callable | None = None, start: Callable | None = None,
               n_draws: int | None = None) -> ChainMap:
    """Run ``one_chain(key, state, params) -> (state, out)`` for every chain (leading axis).

    Parameters
    ----------
    one_chain : callable
        One chain's function.
    n_chains : int
    params_per_chain : bool
        ``params`` has a leading chain axis (else it is shared).
    method : str
        One of :data:`CHAIN_METHODS`.
    piece, start : callable, optional
        For ``"pieces"``: ``start(state) -> carry`` begins a chain's chunk (``None``: the
        carry is the state), ``piece(draw_keys (m,), carry, params) -> (carry, out)``
        continues it over the draws of ``draw_keys``, with ``out`` stacked over them, and
        ``carry[0]`` is the state, such that ``one_chain(key, ...)`` equals ``start`` and then
        the pieces in turn on ``jax.random.split(key, n_draws)``.
    n_draws : int, optional
        Draws per chunk (for ``"pieces"``).

    Returns
    -------
    ChainMap

    Raises
    ------
    ValueError
        As :func:`resolve_method`.
    """
    method = resolve_method(method, n_chains, n_draws, can_piece=piece is not None)
    in_axes = (0, 0, 0 if params_per_chain else None)
    if method == "vectorized":
        return ChainMap(jax.jit(jax.vmap(one_chain, in_axes=in_axes)), method)

    def map_over(fn):
        @jax.jit
        def mapped(keys, states, params):
            if params_per_chain:
                return jax.lax.map(lambda a: fn(*a), (keys, states, params))
            return jax.lax.map(lambda a: fn(a[0], a[1], params), (keys, states))

        return mapped

    if method == "pieces":
        begin = None if start is None else jax.jit(lambda states: jax.lax.map(start, states))
        n_pieces = chain_pieces(n_chains, n_draws)
        return ChainMap(_pieces_runner(map_over(piece), begin, n_chains, n_draws, n_pieces,
                                       params_per_chain), method)
    mapped = map_over(one_chain)
    if method == "sequential":
        return ChainMap(mapped, method)
    n_threads = chain_threads(n_chains)
    size = n_chains // n_threads
    # the groups' slices and the concatenation of their outputs each in one jitted program
    # (sliced and joined leaf by leaf, op by op, they compile many small programs)
    split = jax.jit(lambda tree: [jax.tree.map(lambda a, j=j: a[j * size:(j + 1) * size], tree)
                                  for j in range(n_threads)])
    join = jax.jit(lambda outs: jax.tree.map(lambda *xs: jnp.concatenate(xs), *outs))
    compiled = False

    def threaded(keys, states, params):
        nonlocal compiled
        parts = split((keys, states, params) if params_per_chain else (keys, states))

        def group(j):
            return mapped(*parts[j][:2], parts[j][2] if params_per_chain else params)

        # the first call compiles in this thread alone (no concurrent traces of one shape)
        first = [] if compiled else [group(0)]
        compiled = True
        with _workers(n_threads) as pool:
            outs = first + list(pool.map(group, range(len(first), n_threads)))
        return join(outs)

    return ChainMap(threaded, method)


@contextlib.contextmanager
def _workers(n: int):
    """A pool of ``n`` threads that an exception (Ctrl-C while a chunk runs) leaves at once:
    queued tasks are cancelled and running ones not waited for (a chunk inside XLA cannot be
    stopped; its thread ends with it), so the interrupt reaches the caller now, not after
    the chunk.  Without an exception the pool is shut down after its tasks, as ``with
    ThreadPoolExecutor(n)`` would."""
    pool = ThreadPoolExecutor(n)
    try:
        yield pool
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def _pieces_runner(mapped_piece, begin, n_chains: int, n_draws: int, n_pieces: int,
                   params_per_chain: bool):
    """The ``"pieces"`` schedule: :func:`available_cores` workers, tasks of one chain and
    ``n_draws / n_pieces`` draws, each chain's next piece queued when its last one ends
    (first in, first out: with ``chains * pieces`` a multiple of the workers no worker idles
    while another has work).  ``begin(states) -> carries`` (jitted, one chain at a time) runs
    in the task of a chain's first piece; ``None``: the carry is the state."""
    m = n_draws // n_pieces
    # the keys, states and parameters cut per chain and piece, and the outputs joined, each
    # in one jitted program (op by op, leaf by leaf, they compile dozens of small programs)

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
            # blocking: the worker holds its core until the piece is done
            return jax.block_until_ready(mapped_piece(
                draw_keys[c][p], carry, chain_params[c] if params_per_chain else params))

        outs = [[None] * n_pieces for _ in range(n_chains)]
        finals = [None] * n_chains
        with _workers(available_cores()) as pool:
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
    """``(gradient evaluations, divergent, tree depth, energy)`` of the transitions of
    ``info`` (zero, or NaN for the energy, for random walks)."""
    shape = jnp.shape(info.cg_iterations)
    grads = getattr(info, "grad_evals", jnp.zeros(shape, jnp.int32))
    div = getattr(info, "divergent", jnp.zeros(shape, bool))
    depth = getattr(info, "tree_depth", jnp.zeros(shape, jnp.int32))
    energy = getattr(info, "energy", jnp.full(shape, jnp.nan))
    return grads, div, depth, energy


def _draw_out(state, info):
    """A draw's stored outputs from the state after its ``thin`` transitions and their infos
    (stacked): ``(position, interior, logdensity, acceptance (B,), CG iterations per step,
    failed solves, gradient evaluations per step, divergences, tree depth, energy)``: the
    last two of the interval's last transition (the one that made the stored draw)."""
    grads, div, depth, energy = _info_extras(info)
    return (state.position, state.interior, state.logdensity, jnp.mean(info.acceptance_rate, axis=0),
            jnp.mean(info.cg_iterations.astype(jnp.float64)), jnp.sum(info.solve_failed),
            jnp.mean(grads.astype(jnp.float64)), jnp.sum(div.astype(jnp.int32)),
            jnp.asarray(depth)[-1].astype(jnp.int32), jnp.asarray(energy)[-1].astype(jnp.float64))


def build_chunk(kernel: Kernel, n_draws: int, thin: int, n_chains: int, *,
                method: str = "auto") -> ChainMap:
    """``(keys (C,), states, params) -> (states, out)`` running ``n_draws`` thinned draws.

    The kernel's cache (:attr:`~bayesreg.sampling.kernels.base.Kernel.init_cache`) is built from the
    state at every chunk start, so a resumed run repeats the same arithmetic, and carried
    through the chunk; with ``"pieces"`` it passes from one piece to the next, so the
    pieces repeat the arithmetic of the whole chunk.  ``out`` is ``(positions, interior,
    logdensity, acceptance (B,), CG iterations per step, failed solves, gradient
    evaluations per step, divergences, tree depth, energy)`` per draw, each with leading
    axes ``(C, n_draws)``.

    Raises
    ------
    ValueError
        As :func:`resolve_method`.
    """

    def start(state):
        return state, kernel.init_cache(state)

    def piece(draw_keys, carry, params):
        def draw(carry, key):
            def step(carry, key):
                st, info, cache = kernel.step(key, carry[0], params, carry[1])
                return (st, cache), info

            carry, info = jax.lax.scan(step, carry, jax.random.split(key, thin))
            return carry, _draw_out(carry[0], info)

        return jax.lax.scan(draw, carry, draw_keys)

    def one_chain(key, state, params):
        carry, out = piece(jax.random.split(key, n_draws), start(state), params)
        return carry[0], out

    return map_chains(one_chain, n_chains, kernel.per_chain_params, method=method, piece=piece,
                      start=start, n_draws=n_draws)


def build_adaptive_chunk(kernel: Kernel, ws_step: Callable, n_draws: int, thin: int, n_chains: int,
                         *, method: str = "auto") -> ChainMap:
    """One chunk program for the gradient kernels' warm-up and sampling (one compilation).

    ``run(keys (C, n_draws, thin), states, (ws, stages (C, n_draws, thin, 2), adapt (C,)))
    -> ((states, ws, (acceptance (C, B), divergences (C,), gradients (C,))), out)``: each
    transition is ``ws_step`` (:func:`bayesreg.sampling.kernels.adaptation.build_warmup_step`: the
    kernel at the parameters the warm-up state ``ws`` holds, then the adaptation of ``ws`` at
    the ``stages`` row), whose new ``ws`` is kept where ``adapt`` and discarded elsewhere;
    ``out`` is :func:`build_chunk`'s.  The warm-up runs it with ``adapt`` and Stan's windows,
    the sampling without, from a ``ws`` holding the frozen parameters: the same kernel
    arithmetic as a chunk of :func:`build_chunk` at those parameters, and one program where
    the two would compile one each (the discarded adaptation costs next to nothing beside
    a NUTS trajectory).  The chunk cannot be cut into pieces.

    Raises
    ------
    ValueError
        As :func:`resolve_method` (``"pieces"`` included).
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
            grads, div, _, _ = _info_extras(info)
            return carry, (_draw_out(carry[0], info), (info.acceptance_rate, div, grads))

        carry = (state, ws, kernel.init_cache(state))
        (state, ws, _), (out, (acc, div, grads)) = jax.lax.scan(draw, carry, (keys, stages))
        stats = (jnp.mean(acc.reshape(-1, acc.shape[-1]), axis=0), jnp.sum(div),
                 jnp.mean(grads.astype(jnp.float64)))
        return (state, ws, stats), out

    return map_chains(one_chain, n_chains, True, method=method)
