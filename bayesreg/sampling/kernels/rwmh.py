"""Random-walk Metropolis-Hastings on the posterior's position (paper Sec. 3.2, Algorithm 1).

The Normal jumping kernel (:func:`blackjax.mcmc.random_walk.normal`) and the Metropolis
accept step (:func:`blackjax.mcmc.proposal.static_binomial_sampling`) are BlackJAX's.  The
position may be updated in coordinate blocks (systematic-scan Metropolis-within-Gibbs); one
block with every coordinate is the paper's joint proposal (Eq. 14).  Proposals are
symmetric, so the acceptance probability is the posterior ratio of Eq. 13.

The state also carries the chain's interior FE solution, the warm start of the next solve.
A :class:`KernelCache` (the condensation ``H``, the CG preconditioner ``K_ii^-1``) is built
from the state at every chunk start (:attr:`bayesreg.sampling.kernels.base.Kernel.init_cache`) and
carried from step to step.  :func:`as_algorithm` adds the warm-up (Robbins-Monro on each
block's scale, Haario-style windows) and hands the kernel to the driver,
:func:`bayesreg.sampling.driver.sample` (chunks, stopping, checkpoints).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesreg.sampling.chains import build_chunk
from bayesreg.sampling.kernels.base import Kernel, Program, SamplingAlgorithm, Warmup, marginal_sd

__all__ = ["RWMHState", "RWMHInfo", "Condensation", "Preconditioner", "KernelCache", "init",
           "build_kernel", "as_algorithm", "DENSE_MAX"]

DENSE_MAX = 16  # blocks up to this size (the elastic parameters) adapt a dense proposal


#: :func:`jax.named_scope` names of the random walk's proposal and accept/reject (see
#: :data:`bayesreg.model.posterior.SCOPES`).
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
    acceptance_rate : (B,)
        ``min(1, p(theta*) / p(theta^n))`` (Eq. 13) per block
    is_accepted : (B,) bool
    cg_iterations : ()
        CG iterations of the proposals' solves, summed over blocks
    solve_failed : ()
        number of proposals whose solve did not converge (rejected)
    """

    acceptance_rate: jax.Array
    is_accepted: jax.Array
    cg_iterations: jax.Array
    solve_failed: jax.Array


def init(position, logdensity_fn: Callable, interior0) -> RWMHState:
    """Initial state of a chain.

    ``position`` is ``(dim,)``; ``logdensity_fn(position, interior_guess) -> (logp, aux)``;
    ``interior0`` ``(n_i, 3)`` is the warm start of the first solve.
    """
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
        (:func:`bayesreg.model.posterior.preconditioner`).
    """

    logdensity_fn: Callable
    build: Callable


class KernelCache(NamedTuple):
    """What a random-walk kernel carries from step to step besides the state: the
    condensation's cache and the preconditioner (``None`` where not used).  Rebuilt from the
    state at every chunk start (:attr:`Kernel.init_cache`), so a resumed run repeats the
    same arithmetic."""

    condensed: object = None
    precond: object = None


def build_kernel(logdensity_fn: Callable, blocks=None, condensation: Condensation | None = None,
                 preconditioner: Preconditioner | None = None) -> Kernel:
    """RW-MH kernel for a fixed log-density.

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
        the chain's position when the chunk starts (:attr:`Kernel.init_cache`) and kept
        through the chunk: the random walk moves the parameters little per chunk, and the
        preconditioner only has to stay near ``K_ii^-1``.

    Returns
    -------
    Kernel
        ``step(rng_key, state, sigmas, cache) -> (state, RWMHInfo, cache)`` with ``cache`` a
        :class:`KernelCache` (empty without condensation and preconditioner), built by
        ``init_cache(state)``.  ``sigmas[b]`` is block ``b``'s jumping-kernel scale: a
        vector (independent scales) or a matrix ``L`` (proposal covariance ``L L^T``), as in
        :func:`blackjax.mcmc.random_walk.normal`.

    Examples
    --------
    Two chains' worth of steps on a standard normal (``aux`` carries the interior solution
    and the solve's figures, here placeholders):

    >>> import jax, jax.numpy as jnp
    >>> import bayesreg
    >>> from bayesreg.sampling.kernels import rwmh
    >>> from bayesreg.model.posterior import Aux
    >>> from bayesreg.fem.solver import SolveInfo
    >>> bayesreg.configure_jax()
    >>> def logdensity(x, interior):
    ...     solve = SolveInfo(jnp.asarray(0), jnp.asarray(0.0), jnp.asarray(True))
    ...     return -0.5 * jnp.sum(x ** 2), Aux(interior, solve, jnp.zeros(()), jnp.zeros(()))
    >>> kernel = rwmh.build_kernel(logdensity)
    >>> state = rwmh.init(jnp.zeros(3), logdensity, jnp.zeros((0, 3)))
    >>> cache = kernel.init_cache(state)
    >>> state, info, cache = jax.jit(kernel.step)(jax.random.key(0), state, (jnp.ones(3),), cache)
    >>> info.acceptance_rate.shape  # one Metropolis update per block
    (1,)
    """

    # BlackJAX is imported where a kernel is built, not with this module: importing it starts
    # JAX's backend, which must wait for bayesreg.configure_jax (the XLA flags)
    from blackjax.mcmc.proposal import static_binomial_sampling
    from blackjax.mcmc.random_walk import normal as normal_jumping_kernel

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

    def step(rng_key, state: RWMHState, sigmas, cache: KernelCache):
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
        return state, info, cache

    def init_cache(state: RWMHState) -> KernelCache:
        with jax.named_scope(CACHE_SCOPE):
            return KernelCache(
                None if condensation is None else condensation.build(state.position),
                None if preconditioner is None else preconditioner.build(state.position))

    return Kernel(step, init_cache, per_chain_params=False)


def as_algorithm(logdensity_fn: Callable, interior0, sigma, *, blocks=None, adapt_diagonal=None,
                 target_acceptance: float = 0.25, condensation: Condensation | None = None,
                 preconditioner: Preconditioner | None = None, block_names=None,
                 cg_preconditioner: str | None = None) -> SamplingAlgorithm:
    """The random walk with its warm-up, for :func:`bayesreg.sampling.driver.sample`.

    Warm-up (run chunk by chunk on the host): Robbins-Monro on each block's log-scale toward
    ``target_acceptance``; the scales re-estimated from the draws of two windows
    (``[n/4, n/2)`` and ``[n/2, 3n/4)`` of the ``n`` warm-up chunks) for the blocks that
    ``adapt_diagonal`` marks: a dense factor ``2.38 / sqrt(d_b) chol(C)`` of the window's
    within-chain covariance ``C`` (Haario et al.) for blocks of at most :data:`DENSE_MAX`
    coordinates (the elastic parameters; their ``sigma`` is taken as a diagonal factor from
    the start when there is a warm-up, so the kernel is traced once), ``2.38 / sqrt(d_b)``
    times the within-chain standard deviations for larger ones (a matrix factor keeps its
    correlations and has its rows rescaled).  The scale adaptation restarts after each
    window.  The tuned scales are frozen after the warm-up.

    Parameters
    ----------
    logdensity_fn : callable
        ``(position (dim,), interior_guess (n_i, 3)) -> (logp, aux)``; ``aux.interior``
        and ``aux.solve`` as in :class:`bayesreg.model.posterior.Aux`.
    interior0 : (n_i, 3) array
        Initial interior warm start.
    sigma : array or tuple of arrays
        Initial jumping-kernel scale per block: ``(d_b,)`` vector or ``(d_b, d_b)`` factor.
    blocks : sequence of int arrays, optional
        Coordinate blocks (:func:`build_kernel`); ``None``: one joint block.  They must
        partition ``range(dim)`` (checked by :func:`bayesreg.sampling.driver.sample`).
    adapt_diagonal : sequence of bool, optional
        Per block: re-estimate its scales from the warm-up windows (above).
    target_acceptance : float
        Warm-up target of the mean acceptance probability (paper: about 0.25).
    condensation, preconditioner
        As :func:`build_kernel` (``condensation`` needs ``blocks``).
    block_names : sequence of str, optional
        Names of the blocks (default ``("joint",)`` for one block, else ``("block0", ...)``).
    cg_preconditioner : str, optional
        Name of the CG preconditioner of ``logdensity_fn``'s solves when no
        ``preconditioner`` is given (recorded in ``run.json``).

    Returns
    -------
    SamplingAlgorithm
        ``kind="rwmh"``; its params are the tuple of the blocks' scales.

    Raises
    ------
    ValueError
        A ``sigma`` of the wrong shape, non-finite, or, as a vector of scales, not ``> 0``;
        ``target_acceptance`` outside ``(0, 1)``; ``condensation`` without ``blocks``;
        names and blocks of different counts.
    """
    sigmas = tuple(np.asarray(s_, np.float64) for s_ in (sigma if isinstance(sigma, tuple) else (sigma,)))
    sizes = None if blocks is None else [len(np.asarray(b)) for b in blocks]
    n_blocks = 1 if blocks is None else len(sizes)
    if len(sigmas) != n_blocks:
        raise ValueError(f"{n_blocks} blocks but {len(sigmas)} sigmas")
    for k, s_ in enumerate(sigmas):
        if s_.ndim not in (1, 2):
            raise ValueError(f"sigma of block {k} has shape {s_.shape}: a vector of scales or a "
                             "square factor is needed")
        d_b = s_.shape[0] if sizes is None else sizes[k]
        if s_.shape not in ((d_b,), (d_b, d_b)):
            raise ValueError(f"sigma of block {k} has shape {s_.shape}, block size {d_b}")
        if not np.all(np.isfinite(s_)):
            raise ValueError(f"sigma of block {k} must be finite, got non-finite values")
        if s_.ndim == 1 and not np.all(s_ > 0):
            raise ValueError(f"sigma of block {k} (a vector of scales) must be > 0, got minimum "
                             f"{s_.min()}")
    if not 0 < target_acceptance < 1:
        raise ValueError(f"target_acceptance must lie in (0, 1), got {target_acceptance}")
    if condensation is not None and blocks is None:
        raise ValueError("condensation needs coordinate blocks")
    names = tuple(block_names) if block_names is not None else (
        ("joint",) if n_blocks == 1 else tuple(f"block{k}" for k in range(n_blocks)))
    if len(names) != n_blocks:
        raise ValueError(f"{n_blocks} blocks but {len(names)} block_names")
    adapt = list(adapt_diagonal) if adapt_diagonal is not None else [False] * n_blocks
    kernel = build_kernel(logdensity_fn,
                          None if blocks is None else [np.asarray(b, np.int64) for b in blocks],
                          condensation, preconditioner)

    def build(n_chains, dim, chunk_draws, thinning, n_warm, chain_method):
        idxs = [np.arange(dim)] if blocks is None else _check_blocks(blocks, dim)
        if blocks is None and sigmas[0].shape[0] != dim:
            raise ValueError(f"sigma of block 0 has shape {sigmas[0].shape}, block size {dim}")
        # blocks adapted to a dense factor start as one (the kernel is traced once)
        start = tuple(np.diag(np.broadcast_to(s_, (len(ix),))) if a_ and n_warm and s_.ndim < 2
                      and len(ix) <= DENSE_MAX else s_ for s_, ix, a_ in zip(sigmas, idxs, adapt))
        chunk = build_chunk(kernel, chunk_draws, thinning, n_chains, method=chain_method)
        warmup = _robbins_monro(chunk.run, start, idxs, adapt, n_warm, target_acceptance)
        return Program(chunk.run, warmup, chunk.method)

    return SamplingAlgorithm(
        kind="rwmh", blocks=names, init=lambda x: init(x, logdensity_fn, interior0), build=build,
        params=lambda *a: tuple(a), describe=_describe,
        solves_per_step=float(n_blocks - (condensation is not None)),
        preconditioner="dense" if preconditioner is not None else (cg_preconditioner or "unknown"),
        condensed=condensation is not None)


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


class _WarmupState(NamedTuple):
    """The random walk's adaptation (host arrays: a checkpoint stores its leaves): the
    blocks' scales, their Robbins-Monro log-multipliers, the current window's draws
    ``(C, n, dim)`` and the gain's step count."""

    sigmas: tuple
    log_scales: np.ndarray
    window: np.ndarray
    k_gain: np.ndarray


def _scaled(sigmas, log_scales):
    return tuple(jnp.asarray(s_) * np.exp(ls) for s_, ls in zip(sigmas, log_scales))


def _robbins_monro(chunk, sigmas, idxs, adapt, n_warm, target_acceptance) -> Warmup:
    """The random walk's warm-up (:func:`as_algorithm`) as the driver runs it."""
    window_ends = {n_warm // 2, (3 * n_warm) // 4} - {0}

    def init_ws(states):
        c, dim = np.shape(states.position)
        return _WarmupState(tuple(np.asarray(s_) for s_ in sigmas), np.zeros(len(idxs)),
                            np.zeros((c, 0, dim)), np.asarray(0))

    def one_chunk(k, keys, states, ws):
        sig, log_scales, window, k_gain = ws
        sig = tuple(np.asarray(s_) for s_ in sig)
        log_scales, window = np.array(log_scales), np.asarray(window)
        states, out = chunk(keys, states, _scaled(sig, log_scales))
        acc = np.asarray(out[3]).reshape(-1, len(idxs)).mean(axis=0)
        k_gain = int(k_gain) + 1
        log_scales = log_scales + 2.0 / np.sqrt(k_gain) * (acc - target_acceptance)
        if k >= n_warm // 4:
            window = np.concatenate([window, np.asarray(out[0])], axis=1)  # (C, draws, dim)
        if k + 1 in window_ends and window.shape[1]:
            pos = window
            window = window[:, :0]
            new = list(sig)
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
                elif sig[b].ndim == 1:
                    new[b] = 2.38 / np.sqrt(len(ix)) * sd
                else:  # keep the correlations of the factor, match its marginal scales
                    implied = np.sqrt(np.sum(sig[b] ** 2, axis=1))
                    new[b] = (2.38 / np.sqrt(len(ix)) * sd / implied)[:, None] * sig[b]
                log_scales[b] = 0.0
            sig = tuple(new)
            k_gain = 0
        postfix = {"acc": np.array2string(acc, precision=2),
                   "scale": np.array2string(np.exp(log_scales), precision=2)}
        return states, _WarmupState(sig, log_scales, window, np.asarray(k_gain)), acc, postfix

    def final(ws, states):
        return tuple(np.asarray(s_) for s_ in _scaled(ws.sigmas, ws.log_scales)), states

    return Warmup(init_ws, one_chunk, final)


def _describe(sigma: tuple) -> dict:
    """The frozen proposal scales, for ``run.json``."""
    sds = [marginal_sd(np.asarray(s_), np.ndim(s_) == 2) for s_ in sigma]
    return {"proposal_sd_rms_per_block": [float(np.sqrt(np.mean(sd ** 2))) for sd in sds],
            "elastic_proposal_sd": sds[-1].tolist() if len(sds) > 1 else None}
