"""The chains' driver: warm-up, chunks of draws, the R-hat stopping rule, checkpoints.

:func:`sample` runs parallel chains of the random-walk kernel
(:mod:`bayesreg.sampling.kernels.rwmh`, paper Sec. 3.2); :func:`sample_gradient` those of the gradient
Gibbs kernel (:mod:`bayesreg.sampling.kernels.gibbs`).  Both run the chains in chunks of thinned draws
(one jitted program per chunk, mapped over the chains by :mod:`bayesreg.sampling.chains`), tune the
kernel during a warm-up and freeze it, and stop once the classic Gelman-Rubin R-hat of
every estimand is below a threshold (:class:`bayesreg.sampling.convergence.RunningGelmanRubin`), or at
a maximum number of draws.  After the warm-up and after every chunk an ``on_chunk`` callback
receives a :class:`SamplerCheckpoint` and the chunk's draws; a run given them back
(``resume``) continues to the same draws as one never interrupted: the key of chunk ``k``
is ``fold_in(key, k)``.  The result (:class:`SamplerResult`) describes its own run
(:class:`SamplerInfo`).
"""

from __future__ import annotations

import time
import warnings
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesreg.sampling.chains import build_adaptive_chunk, build_chunk
from bayesreg.sampling.convergence import RunningGelmanRubin, StopRule, rank_figures
from bayesreg.jaxconfig import require_x64
from bayesreg.sampling.kernels import adaptation as gw
from bayesreg.sampling.kernels import gibbs
from bayesreg.sampling.kernels.rwmh import Condensation, Preconditioner, build_kernel, init
from bayesreg.sampling.kernels.target import Target

__all__ = ["SamplerInfo", "SamplerResult", "SamplerCheckpoint", "sample", "sample_gradient"]


class SamplerInfo(NamedTuple):
    """How a run was sampled (recorded in ``run.json``).

    Attributes
    ----------
    kind : str
        ``"rwmh"``, ``"mala"``, ``"hmc"`` or ``"nuts"``.
    blocks : tuple of str
        Names of the coordinate blocks, in the order of the acceptance columns.
    solves_per_step : float or None
        CG solves counted in ``cg_iterations`` per step (``None`` where the number varies:
        gradient kernels without the cached interior map).
    preconditioner : str
        The CG preconditioner of the counted solves (``"dense"``, ``"spectral"``,
        ``"block-jacobi"``; ``"unknown"`` where the caller did not say).
    condensed : bool
        Moves of ``u_b`` take the interior from a cached dense map (no CG solve).
    chain_method : str
        How the chains ran (:data:`bayesreg.sampling.chains.CHAIN_METHODS`).
    thinning : int
        Steps per stored draw.
    warmup_steps : int
        Steps per chain of warm-up (whole chunks).
    rhat_threshold : float
    rhat_split : bool
        The monitored R-hat is the split-chain one.
    adapted : dict
        The tuned values frozen after the warm-up, JSON-ready.
    stuck_chains : tuple of int
        Chains whose stored draws are all one position (no move accepted while sampling):
        their draws say nothing about the posterior (a :class:`RuntimeWarning` names them).
    stop_rule : StopRule
        The rule the run stopped by (or tried to).
    """

    kind: str
    blocks: tuple
    solves_per_step: float | None
    preconditioner: str
    condensed: bool
    chain_method: str
    thinning: int
    warmup_steps: int
    rhat_threshold: float
    rhat_split: bool
    adapted: dict
    stuck_chains: tuple = ()
    stop_rule: StopRule = StopRule("paper")


class SamplerResult(NamedTuple):
    """Output of :func:`sample` and :func:`sample_gradient` (host NumPy arrays).

    Attributes
    ----------
    positions : (C, D, dim)
        thinned post-warm-up draws
    interior : (C, D, n_i, 3)
        interior FE solution of each draw
    logdensity : (C, D)
    acceptance : (C, D, B)
        mean acceptance probability per block over each thinning interval
    cg_iterations : (C, D)
        mean CG iterations per step over each interval
    solve_failures : (C, D)
        non-converged (rejected) solves per interval
    grad_evals : (C, D)
        mean gradient evaluations per step over each interval (0: RW-MH)
    divergences : (C, D)
        divergent transitions per interval (gradient kernels)
    tree_depth : (C, D)
        NUTS doublings of the transition that made each draw (0 otherwise)
    energy : (C, D)
        Hamiltonian at the end of that transition's u_b trajectory (NaN for random walks)
    rhat_history : list of tuples
        After each chunk: draws per chain, the max classic R-hat, the max rank-normalised
        R-hat, the min bulk and tail ESS (the rank figures NaN where not computed: before
        ``min_draws``, or with the paper's rule)
    sigma : tuple
        the frozen tuned values: the proposal scale of each block (RW-MH), or
        ``(step_size (C,), inverse_mass (C, ...), eta_scale (C, n_free, n_free),
        collapsed_scale (C, n_free, n_free))`` (gradient kernels; the last the collapsed
        moves' factor, :class:`bayesreg.sampling.kernels.gibbs.GibbsParams`)
    warmup_acceptance : (B,) ndarray
        acceptance per block in the last warm-up chunk
    timings : dict
        seconds for compile, warm-up, sampling
    converged : bool
        the stop rule met at the end
    final_states : state pytree
        the chains' states at the end (leaves ``(C, ...)``)
    info : SamplerInfo
        how the run was sampled
    """

    positions: np.ndarray
    interior: np.ndarray
    logdensity: np.ndarray
    acceptance: np.ndarray
    cg_iterations: np.ndarray
    solve_failures: np.ndarray
    grad_evals: np.ndarray
    divergences: np.ndarray
    tree_depth: np.ndarray
    energy: np.ndarray
    rhat_history: list
    sigma: tuple
    warmup_acceptance: np.ndarray
    timings: dict
    converged: bool
    final_states: object
    info: SamplerInfo


class SamplerCheckpoint(NamedTuple):
    """Everything :func:`sample` needs to continue after a chunk (host NumPy arrays).

    The stored draws are not part of it: they are handed to the ``on_chunk`` callback one
    chunk at a time and given back through ``resume_draws``.

    Attributes
    ----------
    states : state pytree (leaves ``(C, ...)``), or the list of its leaves (from a file)
        the chains after the last finished chunk
    sigma : tuple of arrays
        the frozen tuned values (see ``SamplerResult.sigma``)
    warmup_acceptance : (B,) ndarray
    chunks_done : int
        sampling chunks finished (0 right after the warm-up)
    rhat_history : list of tuples
        After each chunk: draws per chain, the max classic R-hat, the max rank-normalised
        R-hat, the min bulk and tail ESS (the rank figures NaN where not computed: before
        ``min_draws``, or with the paper's rule)
    timings : dict
        seconds spent so far
    """

    states: object
    sigma: tuple
    warmup_acceptance: np.ndarray
    chunks_done: int
    rhat_history: list
    timings: dict


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
    stop: str = "rank",
    rhat_rank_max: float = 1.01,
    ess_min: float = 400.0,
    estimands: Callable | None = None,
    progress: bool = True,
    on_chunk: Callable | None = None,
    resume: SamplerCheckpoint | None = None,
    resume_draws: tuple | None = None,
    condensation: Condensation | None = None,
    preconditioner: Preconditioner | None = None,
    block_names=None,
    cg_preconditioner: str | None = None,
    chain_method: str = "auto",
) -> SamplerResult:
    """Run parallel RW-MH chains (:mod:`bayesreg.sampling.kernels.rwmh`) with warm-up, thinning and
    R-hat stopping.

    Parameters
    ----------
    rng_key : PRNGKey
    logdensity_fn : callable
        ``(position (dim,), interior_guess (n_i, 3)) -> (logp, aux)``; ``aux.interior``
        and ``aux.solve`` as in :class:`bayesreg.model.posterior.Aux`.
    initial_positions : (C, dim) array
        One start per chain (dispersed starts make R-hat meaningful).
    interior0 : (n_i, 3) array
        Initial interior warm start.
    sigma : array or tuple of arrays
        Initial jumping-kernel scale per block: ``(d_b,)`` vector or ``(d_b, d_b)`` factor.
    blocks : sequence of int arrays, optional
        Coordinate blocks (see :func:`bayesreg.sampling.kernels.rwmh.build_kernel`); ``None``: one
        joint block.
    adapt_diagonal : sequence of bool, optional
        Per block: at 1/2 and 3/4 of the warm-up, set the proposal's marginal scales to
        ``2.38 / sqrt(d_b)`` times the within-chain standard deviation of the chains' draws
        since the previous window (Haario-style diagonal adaptation): a vector ``sigma`` is
        replaced, the rows of a matrix factor are rescaled (its correlations are kept).
        Blocks of at most ``DENSE_MAX`` (16) coordinates (the elastic parameters) get the dense
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
        ``stop="paper"``: stop when the classic Gelman-Rubin R-hat of every estimand is below it.
    rhat_split : bool
        ``stop="paper"``: monitor the split-chain version (see
        :func:`bayesreg.sampling.convergence.gelman_rubin`).
    stop : {"rank", "paper"}
        The stop rule (:class:`bayesreg.sampling.convergence.StopRule`): ``"rank"``, every estimand's
        rank-normalised split R-hat ``<= rhat_rank_max`` and bulk and tail ESS ``>= ess_min``
        (checked on all the draws so far after each chunk from ``min_draws`` on); ``"paper"``,
        the classic R-hat below ``rhat_threshold``.  The classic R-hat is recorded either way.
    rhat_rank_max, ess_min : float
        ``stop="rank"``: its thresholds (Vehtari et al. 2021: 1.01 and 400).
    estimands : callable, optional
        ``(draws (C, D, dim) ndarray) -> (C, D, K) ndarray`` of the scalars to monitor,
        acting draw by draw (it is applied to each chunk as it arrives:
        :class:`bayesreg.sampling.convergence.RunningGelmanRubin`); default: the position coordinates.
    progress : bool
        Show a tqdm progress bar with acceptance and the worst R-hat.
    on_chunk : callable, optional
        ``on_chunk(checkpoint, out)`` after the warm-up (``out=None``) and after every
        sampling chunk; ``out`` is the chunk's ``(positions (C, n, dim), interior
        (C, n, n_i, 3), logdensity (C, n), acceptance (C, n, B), cg_iterations (C, n),
        solve_failures (C, n), grad_evals (C, n), divergences (C, n), tree_depth (C, n),
        energy (C, n))`` with
        ``n = chunk_draws``.  Persisting both lets a killed
        run continue (``resume``).
    resume : SamplerCheckpoint, optional
        Continue from a checkpoint (warm-up skipped).  Chunk ``k`` always uses the key
        ``fold_in(split(rng_key)[1], k)``, so a resumed run gives the same draws as an
        uninterrupted one with the same ``rng_key``.
    resume_draws : tuple of 10 arrays, optional
        The draws of the finished chunks (as ``out``, concatenated along axis 1); required
        with ``resume``.
    condensation : Condensation, optional
        Cached moves of one block (see :func:`bayesreg.sampling.kernels.rwmh.build_kernel`); needs
        ``blocks``.
    preconditioner : Preconditioner, optional
        A per-chain CG preconditioner, rebuilt at every chunk start (see
        :func:`bayesreg.sampling.kernels.rwmh.build_kernel`); the draws equal those without it to the
        CG tolerance.
    block_names : sequence of str, optional
        Names of the blocks in :attr:`SamplerInfo.blocks` (default ``("joint",)`` for one
        block, else ``("block0", ...)``).
    cg_preconditioner : str, optional
        Name of the CG preconditioner that ``logdensity_fn``'s solves use when no
        ``preconditioner`` is given (recorded in :attr:`SamplerInfo.preconditioner`).
    chain_method : str
        How the chains run (:data:`bayesreg.sampling.chains.CHAIN_METHODS`; the draws do not depend
        on it).

    Returns
    -------
    SamplerResult

    Raises
    ------
    ValueError
        On bad arguments (among them: ``blocks`` that do not partition ``range(dim)``, a
        ``sigma`` of the wrong shape, non-finite, or, as a vector of scales, not ``> 0``;
        ``min_draws > max_draws`` or ``chunk_draws > max_draws``; an unknown
        ``chain_method``) or if any chain starts at a point of zero posterior density.
    RuntimeError
        JAX runs in float32 (call :func:`bayesreg.configure_jax` first).

    Examples
    --------
    Three chains on a 2-D standard normal (``aux`` carries the interior solution and the
    solve's figures, here placeholders):

    >>> import jax, jax.numpy as jnp, numpy as np
    >>> import bayesreg
    >>> from bayesreg.model.posterior import Aux
    >>> from bayesreg.sampling.driver import sample
    >>> from bayesreg.fem.solver import SolveInfo
    >>> bayesreg.configure_jax()
    >>> def logdensity(x, interior):
    ...     solve = SolveInfo(jnp.asarray(0), jnp.asarray(0.0), jnp.asarray(True))
    ...     return -0.5 * jnp.sum(x ** 2), Aux(interior, solve, jnp.zeros(()), jnp.zeros(()))
    >>> result = sample(jax.random.key(0), logdensity, np.zeros((3, 2)), jnp.zeros((0, 3)),
    ...                 np.ones(2), thinning=1, warmup_steps=200, max_draws=400,
    ...                 min_draws=400, progress=False)
    >>> result.positions.shape  # (chains, draws, dim)
    (3, 400, 2)
    >>> bool(abs(result.positions.std() - 1.0) < 0.2)
    True
    """
    require_x64("sample")
    rule = StopRule(stop, float(rhat_threshold), bool(rhat_split), float(rhat_rank_max),
                    float(ess_min)).check()
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
                   and len(ix) <= gw.DENSE_MAX else s_ for s_, ix, a_ in zip(sigmas, idxs, adapt))
    if condensation is not None and blocks is None:
        raise ValueError("condensation needs coordinate blocks")
    names = tuple(block_names) if block_names is not None else (
        ("joint",) if len(idxs) == 1 else tuple(f"block{k}" for k in range(len(idxs))))
    if len(names) != len(idxs):
        raise ValueError(f"{len(idxs)} blocks but {len(names)} block_names")
    kernel = build_kernel(logdensity_fn, None if blocks is None else idxs, condensation, preconditioner)
    chunk = build_chunk(kernel, chunk_draws, thinning, n_chains, method=chain_method)
    key_warm, key_samp = jax.random.split(rng_key)
    n_warm = int(np.ceil(warmup_steps / (chunk_draws * thinning))) if warmup_steps else 0
    info = SamplerInfo(
        kind="rwmh", blocks=names,
        solves_per_step=float(len(idxs) - (condensation is not None)),
        preconditioner="dense" if preconditioner is not None else (cg_preconditioner or "unknown"),
        condensed=condensation is not None, chain_method=chunk.method, thinning=int(thinning),
        warmup_steps=n_warm * chunk_draws * thinning, rhat_threshold=float(rhat_threshold),
        rhat_split=bool(rhat_split), adapted={}, stop_rule=rule)

    def init_states():
        return jax.vmap(lambda x: init(x, logdensity_fn, interior0))(x0)

    def warm_up():
        states = jax.jit(init_states)()
        _check_finite(states)
        return gw.rwmh_warmup(chunk.run, states, key_warm, sigmas, idxs, adapt, n_chains, warmup_steps,
                              chunk_draws, thinning, target_acceptance, progress)

    return _drive(chunk.run, init_states, warm_up, key_samp, n_chains=n_chains, n_blocks=len(idxs),
                  max_draws=max_draws, min_draws=min_draws, chunk_draws=chunk_draws,
                  rule=rule, estimands=estimands,
                  progress=progress, on_chunk=on_chunk, resume=resume, resume_draws=resume_draws,
                  params_type=lambda *a: tuple(a), info=info, adapted=_adapted_rwmh)


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


N_OUT = 10  # positions, interior, logdensity, acceptance, CG, failed solves, gradients,
# divergences, tree depth, energy


def _drive(chunk, init_states, warm_up, key_samp, *, n_chains, n_blocks, max_draws, min_draws,
           chunk_draws, rule: StopRule, estimands, progress, on_chunk, resume,
           resume_draws, params_type, info: SamplerInfo, adapted: Callable) -> SamplerResult:
    """The sampling loop shared by every kernel: chunks, the stop rule, checkpoints, resume.

    ``warm_up() -> (states, frozen params, warm-up acceptance per block, timings)``;
    ``init_states()`` gives the structure of the states (to rebuild a checkpoint's leaves);
    ``params_type`` rebuilds the frozen parameters from their tuple of arrays;
    ``adapted(frozen arrays) -> dict`` describes them for :attr:`SamplerInfo.adapted`.
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
        history = [tuple(h) + (np.nan,) * (5 - len(h)) for h in resume.rhat_history]
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
    figures = history[-1][1:] if history else (np.inf, np.nan, np.nan, np.nan)
    n_draws = k * chunk_draws
    rhat_split = rule.rhat_split
    # R-hat from per-chunk moments (constant work per chunk), fed chunk by chunk as the run
    # that wrote the checkpoint fed them, so a resumed run stops where it would have
    monitor = RunningGelmanRubin(estimands)
    acc_sum = np.zeros(n_blocks)
    for j in range(k):
        monitor.add(parts[0][0][:, j * chunk_draws:(j + 1) * chunk_draws])
        acc_sum += parts[3][0][:, j * chunk_draws:(j + 1) * chunk_draws].reshape(-1, n_blocks).sum(axis=0)

    def done():
        return n_draws >= max_draws or (n_draws >= min_draws and rule.met(*figures))

    while not done():
        states, out = chunk(jax.random.split(jax.random.fold_in(key_samp, k), n_chains), states, frozen)
        out = tuple(np.asarray(o) for o in out)
        k += 1
        for lst, o in zip(parts, out):
            lst.append(o)
        n_draws += chunk_draws
        monitor.add(out[0])
        rhat = figures[0]
        if n_draws >= (4 if rhat_split else 2):  # split halves need 2 draws each
            rhat = float(np.nanmax(monitor.rhat(split=rhat_split)))
        rank = (np.nan,) * 3
        if rule.kind == "rank" and n_draws >= max(min_draws, 4):  # on every draw so far
            rank = rank_figures(estimands(np.concatenate(parts[0], axis=1)))
        figures = (rhat, *rank)
        history.append((n_draws, *figures))
        acc_sum += out[3].reshape(-1, n_blocks).sum(axis=0)
        acc = acc_sum / (n_chains * n_draws)
        shown = {"rhat": f"{rhat:.3f}"} if rule.kind == "paper" or np.isnan(rank[0]) else {
            "rank_rhat": f"{rank[0]:.3f}", "ess": f"{rank[1]:.0f}/{rank[2]:.0f}"}
        bar.set_postfix(acc=np.array2string(acc, precision=2), draws=n_draws, **shown)
        bar.update(1)
        timings["sampling_s"] = spent + time.perf_counter() - t1
        if on_chunk is not None:
            on_chunk(SamplerCheckpoint(jax.tree.map(np.asarray, states), _as_arrays(frozen), warm_acc, k,
                                       list(history), dict(timings)), out)
    bar.close()
    timings["sampling_s"] = spent + time.perf_counter() - t1
    pos, interior, lp, acc, cg, fail, grads, div, depth, energy = (np.concatenate(p_, axis=1)
                                                                   for p_ in parts)
    return SamplerResult(
        positions=pos,
        interior=interior,
        logdensity=lp,
        acceptance=acc,
        cg_iterations=cg,
        solve_failures=fail,
        grad_evals=grads,
        divergences=div,
        tree_depth=depth,
        energy=energy,
        rhat_history=history,
        sigma=_as_arrays(frozen),
        warmup_acceptance=warm_acc,
        timings=timings,
        converged=rule.met(*figures),
        final_states=states,
        info=info._replace(adapted=adapted(_as_arrays(frozen)), stuck_chains=_stuck(pos)),
    )


def _stuck(positions) -> tuple:
    """Chains whose draws ``(C, D, dim)`` never leave their first position, warned about."""
    stuck = tuple(int(c) for c in np.flatnonzero(np.all(positions == positions[:, :1], axis=(1, 2))))
    if stuck:
        warnings.warn(
            f"chains {list(stuck)} never moved while sampling (every proposal rejected): their "
            "draws are their start repeated and the summaries of this run do not describe the "
            "posterior; check the proposal scales (sampler.sigma_*, sampler.step_size), the "
            "starts and the model", RuntimeWarning, stacklevel=3)
    return stuck


def _as_arrays(frozen) -> tuple:
    return tuple(np.asarray(f_) for f_ in frozen)


def sample_gradient(
    rng_key,
    target: Target,
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
    collapsed_moves: int = 0,
    thinning: int = 1,
    warmup_steps: int = 1000,
    max_draws: int = 1000,
    min_draws: int = 100,
    chunk_draws: int = 50,
    target_acceptance: float | None = None,
    rhat_threshold: float = 1.2,
    rhat_split: bool = False,
    stop: str = "rank",
    rhat_rank_max: float = 1.01,
    ess_min: float = 400.0,
    estimands: Callable | None = None,
    progress: bool = True,
    on_chunk: Callable | None = None,
    resume: SamplerCheckpoint | None = None,
    resume_draws: tuple | None = None,
    chain_method: str = "auto",
) -> SamplerResult:
    """Parallel chains of the gradient Gibbs kernel (:mod:`bayesreg.sampling.kernels.gibbs`) with
    windowed warm-up (:mod:`bayesreg.sampling.kernels.adaptation`).

    Same chains, thinning, R-hat stopping, checkpoints and result as :func:`sample`; the
    warm-up is Stan's windowed adaptation (step size by dual averaging toward
    ``target_acceptance``, a diagonal or dense inverse mass matrix from the slow windows) on
    each chain, plus the scale of the elastic random walk; the tuned values are frozen
    after it and returned in ``SamplerResult.sigma`` as ``(step_size (C,), inverse_mass
    (C, ...), eta_scale (C, n_free, n_free), collapsed_scale (C, n_free, n_free))`` (the
    elastic random walk's factor and the collapsed moves').

    Parameters
    ----------
    rng_key : PRNGKey
    target : bayesreg.sampling.kernels.target.Target
    initial_positions : (C, dim) array
        natural positions ``[u_b.ravel(), phi]``
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
        ``1 .. 2 num_integration_steps - 1`` each transition
        (:func:`bayesreg.sampling.kernels.gibbs.build_kernel`)
    max_tree_depth : int
        NUTS' maximum number of trajectory doublings
    elastic_moves : int
        elastic random-walk updates per transition
    collapsed_moves : int
        collapsed moves of the elastic parameters per transition (a target with
        ``conditional``; :func:`bayesreg.sampling.kernels.gibbs.build_kernel`)
    thinning, warmup_steps, max_draws, min_draws, chunk_draws, rhat_threshold, rhat_split,
    stop, rhat_rank_max, ess_min, estimands, progress, on_chunk, resume, resume_draws
        As :func:`sample` (``warmup_steps`` rounded up to whole chunks).
    target_acceptance : float, optional
        Default :func:`bayesreg.sampling.kernels.gibbs.default_target_acceptance` of ``kind``.
    chain_method : str
        How the chains run (:data:`bayesreg.sampling.chains.CHAIN_METHODS`, ``"pieces"`` excepted).

    Returns
    -------
    SamplerResult

    Raises
    ------
    ValueError
        On bad arguments (among them: ``step_size`` not finite and ``> 0``, ``eta_scale``
        non-finite or, as scales, not ``> 0``; ``min_draws > max_draws`` or ``chunk_draws >
        max_draws``; an unknown ``chain_method``) or if any chain starts at a point of zero
        posterior density.
    RuntimeError
        JAX runs in float32 (call :func:`bayesreg.configure_jax` first).
    """
    require_x64("sample_gradient")
    rule = StopRule(stop, float(rhat_threshold), bool(rhat_split), float(rhat_rank_max),
                    float(ess_min)).check()
    target_acceptance = target_acceptance or gibbs.default_target_acceptance(kind)
    x0, n_chains = _check_starts(initial_positions, thinning, chunk_draws, max_draws, min_draws,
                                 target_acceptance)
    if not (np.ndim(step_size) == 0 and np.isfinite(step_size) and step_size > 0):
        raise ValueError(f"step_size must be a finite scalar > 0, got {step_size}")
    eta_check = np.asarray(eta_scale, np.float64)
    if not np.all(np.isfinite(eta_check)) or (eta_check.ndim < 2 and not np.all(eta_check > 0)):
        raise ValueError(f"eta_scale must be finite and, as scales, > 0, got {eta_scale}")
    kernel = gibbs.build_kernel(target, kind, num_integration_steps=num_integration_steps,
                             jitter_integration_steps=jitter_integration_steps,
                             max_num_doublings=max_tree_depth, elastic_moves=elastic_moves,
                             collapsed_moves=collapsed_moves)
    ws_init, ws_step, ws_final = gw.build_warmup_step(
        kernel, target_acceptance=target_acceptance, dense_mass=dense_mass, adapt_mass=adapt_mass)
    key_warm, key_samp = jax.random.split(rng_key)
    n_blocks = 1 + (target.n_free > 0) + (collapsed_moves > 0) + (target.correction is not None)
    eta0 = np.asarray(eta_scale, np.float64)  # scales become a diagonal factor in ws_init
    eta0 = eta0 if eta0.ndim == 2 else np.broadcast_to(eta0, (target.n_free,))
    dim_u = x0.shape[1] - target.n_free  # the preconditioned u_b coordinates w
    mapped = build_adaptive_chunk(kernel, ws_step, chunk_draws, thinning, n_chains,
                                  method=chain_method)

    @jax.jit
    def ws_start():
        ws = jax.vmap(lambda _: ws_init(dim_u, step_size, eta0))(jnp.arange(n_chains))
        # BlackJAX's initial adaptation states hold weakly typed floats (python 0.0) that
        # the warm-up step returns strongly typed: made strong here, so that the chunk
        # program compiles once, not twice; the integer counters stay weak in and out
        return jax.tree.map(lambda a: jnp.asarray(a, a.dtype) if jnp.issubdtype(a.dtype, jnp.floating)
                            else a, ws)

    @jax.jit
    def ws_frozen(frozen):
        # a warm-up state whose kernel parameters are exactly ``frozen`` (eta_scale * exp(0))
        ws = ws_start()
        # the collapsed moves' factor is the same base times its own multiplier (trace ratio);
        # a checkpoint from before them has none
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
    no_stage, no_adapt = np.zeros((n_chains, chunk_draws, thinning, 2), np.int32), np.zeros(n_chains, bool)

    def chunk(keys, states, frozen):
        (states, _, _), out = mapped.run(samp_keys(keys), states, (ws_frozen(frozen), no_stage, no_adapt))
        return states, out

    def init_states():
        return jax.vmap(lambda x: gibbs.init(target, x, interior0)[0])(x0)

    def warm_up():
        t0 = time.perf_counter()
        states = jax.jit(init_states)()
        _check_finite(states)
        ws = ws_start()
        per_chunk = chunk_draws * thinning
        n_warm = int(np.ceil(warmup_steps / per_chunk)) if warmup_steps else 0
        stages = gw.schedule(n_warm * per_chunk) if n_warm else np.zeros((0, 2), np.int32)
        adapt = np.ones(n_chains, bool)

        from tqdm.auto import tqdm

        timings = {}
        warm_acc = np.full(n_blocks, np.nan)
        bar = tqdm(total=n_warm, disable=not progress or n_warm == 0, desc="warm-up", unit="chunk")
        for k in range(n_warm):
            keys = jax.random.split(jax.random.fold_in(key_warm, k), n_chains)
            stage = stages[k * per_chunk:(k + 1) * per_chunk].reshape(chunk_draws, thinning, 2)
            (states, ws, (acc, div, grads)), _ = mapped.run(
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

    per_chunk = chunk_draws * thinning
    n_warm = int(np.ceil(warmup_steps / per_chunk)) if warmup_steps else 0
    info = SamplerInfo(
        kind=kind, blocks=(("joint", "normaliser")[:n_blocks] if target.log_jacobian is not None
                           else ("u_b", "elastic", "collapsed")[:n_blocks]),
        # the solves counted: with the cached map the trajectory needs none, and the elastic
        # block makes elastic_moves solves plus one evaluation before them; without it every
        # gradient solves (uncounted) and the count per step varies
        solves_per_step=(float(elastic_moves + 1) if target.condensed and target.n_free else None),
        preconditioner=target.preconditioner, condensed=target.condensed,
        chain_method=mapped.method,
        thinning=int(thinning), warmup_steps=n_warm * per_chunk,
        rhat_threshold=float(rhat_threshold), rhat_split=bool(rhat_split), adapted={},
        stop_rule=rule)
    return _drive(chunk, init_states, warm_up, key_samp, n_chains=n_chains, n_blocks=n_blocks,
                  max_draws=max_draws, min_draws=min_draws, chunk_draws=chunk_draws,
                  rule=rule, estimands=estimands,
                  progress=progress, on_chunk=on_chunk, resume=resume, resume_draws=resume_draws,
                  params_type=lambda *a: gibbs.GibbsParams(*a), info=info, adapted=_adapted_gradient)


def _marginal_sd(scale: np.ndarray, factor: bool) -> np.ndarray:
    """Marginal proposal standard deviations ``(..., d)`` of independent scales ``(..., d)``
    or of lower-triangular factors ``L`` ``(..., d, d)`` (``sqrt(diag(L L^T))``)."""
    return np.sqrt(np.sum(scale ** 2, axis=-1)) if factor else np.abs(scale)


def _adapted_rwmh(sigma: tuple) -> dict:
    """The random walk's frozen proposal scales, for :attr:`SamplerInfo.adapted`."""
    sds = [_marginal_sd(np.asarray(s_), np.ndim(s_) == 2) for s_ in sigma]
    return {"proposal_sd_rms_per_block": [float(np.sqrt(np.mean(sd ** 2))) for sd in sds],
            "elastic_proposal_sd": sds[-1].tolist() if len(sds) > 1 else None}


def _adapted_gradient(sigma: tuple) -> dict:
    """The gradient kernel's frozen step sizes, mass matrices and elastic factors."""
    step, inv_mass, eta_scale = (np.asarray(a) for a in sigma[:3])
    collapsed = {} if len(sigma) < 4 or sigma[3] is None else {
        "collapsed_proposal_sd_per_chain": _marginal_sd(np.asarray(sigma[3]), np.ndim(sigma[3]) == 3).tolist()}
    return {**collapsed, "step_size_per_chain": step.tolist(),
            "inverse_mass_diag_quantiles_0_50_100": np.quantile(
                inv_mass if inv_mass.ndim == 2 else np.diagonal(inv_mass, axis1=1, axis2=2),
                [0, 0.5, 1]).tolist(),
            "elastic_proposal_sd_per_chain": _marginal_sd(eta_scale, eta_scale.ndim == 3).tolist(),
            "elastic_factor_per_chain": eta_scale.tolist()}
