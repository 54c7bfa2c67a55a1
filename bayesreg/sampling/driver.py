"""The chains' driver: warm-up, chunks of draws, the stop rule, checkpoints.

:func:`sample` is the one driver of every kernel family: it takes a
:class:`~bayesreg.sampling.kernels.base.SamplingAlgorithm` (the random walk of
:mod:`bayesreg.sampling.kernels.rwmh`, paper Sec. 3.2; MALA, HMC or NUTS in the Gibbs kernel of
:mod:`bayesreg.sampling.kernels.gibbs`), runs its warm-up chunk by chunk (:func:`run_warmup`)
and freezes what it tuned, then runs the chains in chunks of thinned draws (one jitted
program per chunk, mapped over the chains by :mod:`bayesreg.sampling.chains`) until the stop
rule holds (rank-normalised R-hat and ESS, or the paper's classic R-hat:
:class:`bayesreg.sampling.convergence.StopRule`) or a maximum number of draws.

After every warm-up chunk an ``on_warmup_chunk`` callback receives a
:class:`WarmupCheckpoint`; after the warm-up and after every sampling chunk an ``on_chunk``
callback receives a :class:`SamplerCheckpoint` and the chunk's draws.  A run given either
back (``resume``) continues to the same draws as one never interrupted: the key of chunk
``k`` is ``fold_in(key, k)``.  The result (:class:`SamplerResult`) describes its own run
(:class:`SamplerInfo`).
"""

from __future__ import annotations

import time
import warnings
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesreg.jaxconfig import require_x64
from bayesreg.sampling.convergence import RunningGelmanRubin, StopRule, rank_figures
from bayesreg.sampling.kernels.base import SamplingAlgorithm, Warmup

__all__ = ["SamplerInfo", "SamplerResult", "SamplerCheckpoint", "WarmupCheckpoint", "sample",
           "run_warmup"]


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
    sample_stats : tuple of str
        The kernel's own sample stats
        (:attr:`bayesreg.sampling.kernels.base.SamplingAlgorithm.sample_stats`).
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
    sample_stats: tuple = ()


class SamplerResult(NamedTuple):
    """Output of :func:`sample` (host NumPy arrays).

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


class WarmupCheckpoint(NamedTuple):
    """Everything :func:`sample` needs to continue a warm-up after one of its chunks (host
    NumPy arrays): a run interrupted in a long warm-up loses one chunk, not the warm-up.

    Attributes
    ----------
    states : list of arrays
        the leaves of the chains' states after the chunk
    adaptation : list of arrays
        the leaves of the algorithm's adaptation state
        (:attr:`bayesreg.sampling.kernels.base.Warmup.init`'s)
    chunks_done : int
        warm-up chunks finished
    warmup_acceptance : (B,) ndarray
        acceptance per block in the last chunk
    timings : dict
        seconds spent so far
    """

    states: list
    adaptation: list
    chunks_done: int
    warmup_acceptance: np.ndarray
    timings: dict


def sample(
    rng_key,
    algorithm: SamplingAlgorithm,
    initial_positions,
    *,
    thinning: int = 1,
    warmup_steps: int = 1000,
    max_draws: int = 1000,
    min_draws: int = 100,
    chunk_draws: int = 50,
    rhat_threshold: float = 1.2,
    rhat_split: bool = False,
    stop: str = "rank",
    rhat_rank_max: float = 1.01,
    ess_min: float = 400.0,
    estimands: Callable | None = None,
    progress: bool = True,
    on_chunk: Callable | None = None,
    resume: SamplerCheckpoint | WarmupCheckpoint | None = None,
    resume_draws: tuple | None = None,
    chain_method: str = "auto",
    on_warmup_chunk: Callable | None = None,
) -> SamplerResult:
    """Run parallel chains of any kernel family with warm-up, thinning and a stop rule.

    The one driver of every kernel (:class:`~bayesreg.sampling.kernels.base.SamplingAlgorithm`:
    :func:`bayesreg.sampling.kernels.rwmh.as_algorithm`, the paper's random walk;
    :func:`bayesreg.sampling.kernels.gibbs.as_algorithm`, MALA, HMC and NUTS in Gibbs with
    the elastic moves).  It starts the chains, runs the algorithm's warm-up chunk by chunk
    and freezes what it tuned, then runs chunks of thinned draws (one jitted program per
    chunk, mapped over the chains by :mod:`bayesreg.sampling.chains`) until the stop rule is
    met or ``max_draws``.

    Parameters
    ----------
    rng_key : PRNGKey
    algorithm : SamplingAlgorithm
        The kernel with its warm-up.
    initial_positions : (C, dim) array
        One start per chain (dispersed starts make R-hat meaningful).
    thinning : int
        Steps per stored draw (paper: 10).
    warmup_steps : int
        Steps per chain spent tuning (discarded); rounded up to whole chunks.
    max_draws, min_draws : int
        Bounds on stored draws per chain after warm-up, counted in whole chunks: sampling
        stops at the first chunk that reaches ``max_draws``, so a ``max_draws`` that is not
        a multiple of ``chunk_draws`` is rounded up to one.
    chunk_draws : int
        Draws per jitted call (the stop rule's check and progress-bar interval).
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
        Show tqdm progress bars (warm-up, sampling) with acceptance and the stop rule's figures.
    on_chunk : callable, optional
        ``on_chunk(checkpoint, out)`` after the warm-up (``out=None``) and after every
        sampling chunk; ``out`` is the chunk's ``(positions (C, n, dim), interior
        (C, n, n_i, 3), logdensity (C, n), acceptance (C, n, B), cg_iterations (C, n),
        solve_failures (C, n), grad_evals (C, n), divergences (C, n), tree_depth (C, n),
        energy (C, n))`` with ``n = chunk_draws``.  Persisting both lets a killed run
        continue (``resume``).
    resume : SamplerCheckpoint or WarmupCheckpoint, optional
        Continue from a checkpoint: a :class:`SamplerCheckpoint` skips the warm-up, a
        :class:`WarmupCheckpoint` continues it after its last chunk.  Warm-up chunk ``k``
        always uses the key ``fold_in(split(rng_key)[0], k)`` and sampling chunk ``k``
        ``fold_in(split(rng_key)[1], k)``, so a resumed run gives the same draws as an
        uninterrupted one with the same ``rng_key``.
    resume_draws : tuple of 10 arrays, optional
        The draws of the finished chunks (as ``out``, concatenated along axis 1); required
        with a :class:`SamplerCheckpoint` after a sampling chunk.
    chain_method : str
        How the chains run (:data:`bayesreg.sampling.chains.CHAIN_METHODS`; the draws do not
        depend on it; the gradient kernels cannot be cut into ``"pieces"``).
    on_warmup_chunk : callable, optional
        ``on_warmup_chunk(checkpoint)`` with a :class:`WarmupCheckpoint` after every warm-up
        chunk but the last (whose state ``on_chunk`` receives as the warm-up's end).

    Returns
    -------
    SamplerResult

    Raises
    ------
    ValueError
        On bad arguments (among them: ``min_draws > max_draws`` or ``chunk_draws >
        max_draws``; an unknown ``chain_method``; what the algorithm refuses for this shape,
        e.g. random-walk blocks that do not partition ``range(dim)``; an algorithm whose
        ``chain_data`` are not for ``C`` chains) or if any chain starts
        at a point of zero posterior density.
    RuntimeError
        JAX runs in float32 (call :func:`bayesreg.configure_jax` first).

    Examples
    --------
    Three random-walk chains on a 2-D standard normal (``aux`` carries the interior solution
    and the solve's figures, here placeholders):

    >>> import jax, jax.numpy as jnp, numpy as np
    >>> import bayesreg
    >>> from bayesreg.model.posterior import Aux
    >>> from bayesreg.sampling.driver import sample
    >>> from bayesreg.sampling.kernels import rwmh
    >>> from bayesreg.fem.solver import SolveInfo
    >>> bayesreg.configure_jax()
    >>> def logdensity(x, interior):
    ...     solve = SolveInfo(jnp.asarray(0), jnp.asarray(0.0), jnp.asarray(True))
    ...     return -0.5 * jnp.sum(x ** 2), Aux(interior, solve, jnp.zeros(()), jnp.zeros(()))
    >>> walk = rwmh.as_algorithm(logdensity, jnp.zeros((0, 3)), np.ones(2))
    >>> result = sample(jax.random.key(0), walk, np.zeros((3, 2)), thinning=1,
    ...                 warmup_steps=200, max_draws=400, min_draws=400, progress=False)
    >>> result.positions.shape  # (chains, draws, dim)
    (3, 400, 2)
    >>> bool(abs(result.positions.std() - 1.0) < 0.2)
    True
    """
    require_x64("sample")
    rule = StopRule(stop, float(rhat_threshold), bool(rhat_split), float(rhat_rank_max),
                    float(ess_min)).check()
    x0, n_chains = _check_starts(initial_positions, thinning, chunk_draws, max_draws, min_draws)
    per_chunk = chunk_draws * thinning
    n_warm = int(np.ceil(warmup_steps / per_chunk)) if warmup_steps else 0
    program = algorithm.build(n_chains, x0.shape[1], chunk_draws, thinning, n_warm, chain_method)
    key_warm, key_samp = jax.random.split(rng_key)
    n_blocks = len(algorithm.blocks)

    if algorithm.chain_data is None:
        def init_states():
            return jax.vmap(algorithm.init)(x0)
    else:
        sizes = {np.shape(a)[0] for a in jax.tree.leaves(algorithm.chain_data)}
        if sizes != {n_chains}:
            raise ValueError(f"the algorithm carries data for {sorted(sizes)} chains, the starts "
                             f"are {n_chains}")

        def init_states():
            return jax.vmap(algorithm.init)(x0, algorithm.chain_data)

    def warm_up(resume_warmup=None):
        t0 = time.perf_counter()
        if resume_warmup is None:
            states = jax.jit(init_states)()
            _check_finite(states)
            return run_warmup(program.warmup, states, key_warm, n_warm, n_chains, n_blocks,
                              progress, t0, on_chunk=on_warmup_chunk)
        w = resume_warmup
        if not 0 < w.chunks_done < n_warm:
            raise ValueError(f"the warm-up checkpoint holds {w.chunks_done} chunks of a warm-up "
                             f"of {n_warm}")
        states = _rebuild_states(init_states, w.states)
        return run_warmup(program.warmup, states, key_warm, n_warm, n_chains, n_blocks,
                          progress, t0, on_chunk=on_warmup_chunk, resume=w)

    info = SamplerInfo(
        kind=algorithm.kind, blocks=tuple(algorithm.blocks),
        solves_per_step=algorithm.solves_per_step, preconditioner=algorithm.preconditioner,
        condensed=algorithm.condensed, chain_method=program.method, thinning=int(thinning),
        warmup_steps=n_warm * per_chunk, rhat_threshold=float(rhat_threshold),
        rhat_split=bool(rhat_split), adapted={}, stop_rule=rule,
        sample_stats=tuple(algorithm.sample_stats))
    return _drive(program.chunk, init_states, warm_up, key_samp, n_chains=n_chains,
                  n_blocks=n_blocks, max_draws=max_draws, min_draws=min_draws,
                  chunk_draws=chunk_draws, rule=rule, estimands=estimands, progress=progress,
                  on_chunk=on_chunk, resume=resume, resume_draws=resume_draws,
                  params_type=algorithm.params, info=info, adapted=algorithm.describe)


def run_warmup(warmup: Warmup, states, key_warm, n_warm: int, n_chains: int, n_blocks: int,
               progress: bool, t0: float | None = None, *, on_chunk: Callable | None = None,
               resume: WarmupCheckpoint | None = None):
    """The warm-up loop of every algorithm: chunk ``k`` of the chains with the keys
    ``split(fold_in(key_warm, k), n_chains)``, a progress bar, and the tuned values frozen.

    ``on_chunk(WarmupCheckpoint)`` after every chunk but the last; ``resume`` continues
    after its ``chunks_done`` chunks (``states`` are then its states, already rebuilt).

    Returns
    -------
    states, frozen params (tuple of arrays), acceptance per block in the last warm-up chunk
    ``(n_blocks,)`` (NaN without a warm-up), timings (``first_chunk_incl_compile_s``, and
    ``warmup_s`` of the chunks before a resume)
    """
    from tqdm.auto import tqdm

    t0 = time.perf_counter() if t0 is None else t0
    timings = {}
    warm_acc = np.full(n_blocks, np.nan)
    ws = warmup.init(states)
    start = 0
    if resume is not None:
        ws = jax.tree.unflatten(jax.tree.structure(ws), list(resume.adaptation))
        start, warm_acc = int(resume.chunks_done), np.asarray(resume.warmup_acceptance)
        timings = dict(resume.timings)
    spent = timings.pop("warmup_s", 0.0)
    bar = tqdm(total=n_warm, initial=start, disable=not progress or n_warm == 0, desc="warm-up",
               unit="chunk")
    for k in range(start, n_warm):
        keys = jax.random.split(jax.random.fold_in(key_warm, k), n_chains)
        states, ws, warm_acc, postfix = warmup.chunk(k, keys, states, ws)
        if k == start and "first_chunk_incl_compile_s" not in timings:
            timings["first_chunk_incl_compile_s"] = time.perf_counter() - t0
        bar.set_postfix(**postfix)
        bar.update(1)
        if on_chunk is not None and k + 1 < n_warm:
            on_chunk(WarmupCheckpoint(
                [np.asarray(a) for a in jax.tree.leaves(states)],
                [np.asarray(a) for a in jax.tree.leaves(ws)], k + 1, np.asarray(warm_acc),
                {**timings, "warmup_s": spent + time.perf_counter() - t0}))
    bar.close()
    frozen, states = warmup.final(ws, states)
    if spent:
        timings["warmup_s"] = spent
    return states, _as_arrays(frozen), np.asarray(warm_acc), timings


def _check_starts(initial_positions, thinning, chunk_draws, max_draws, min_draws):
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
    return x0, x0.shape[0]


def _rebuild_states(init_states, saved):
    """The chains' states from a checkpoint's ``saved`` states: the pytree itself or the list
    of its leaves (from a file), given the structure ``init_states()`` has."""
    leaves = saved if isinstance(saved, list) else jax.tree.leaves(saved)
    return jax.tree.unflatten(jax.tree.structure(jax.eval_shape(init_states)),
                              [jnp.asarray(a) for a in leaves])


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

    ``warm_up(resume_warmup) -> (states, frozen params, warm-up acceptance per block,
    timings)`` (``resume_warmup`` a :class:`WarmupCheckpoint` or ``None``);
    ``init_states()`` gives the structure of the states (to rebuild a checkpoint's leaves);
    ``params_type`` rebuilds the frozen parameters from their tuple of arrays;
    ``adapted(frozen arrays) -> dict`` describes them for :attr:`SamplerInfo.adapted`.
    """
    estimands = estimands or (lambda d: d)
    n_samp = int(np.ceil(max_draws / chunk_draws))
    t0 = time.perf_counter()
    if resume is None or isinstance(resume, WarmupCheckpoint):
        states, frozen, warm_acc, timings = warm_up(resume)
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
        states = _rebuild_states(init_states, resume.states)
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
    """The frozen values' arrays (trailing ``None`` fields, absent from an older checkpoint's
    tuple, left out)."""
    fields = list(frozen)
    while fields and fields[-1] is None:
        fields.pop()
    return tuple(np.asarray(f_) for f_ in fields)
