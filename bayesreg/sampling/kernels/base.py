"""What the chain driver runs: a kernel, its warm-up and the two together as a sampling
algorithm (in the style of BlackJAX's ``SamplingAlgorithm``).

A kernel family is one module of :mod:`bayesreg.sampling.kernels` whose ``as_algorithm``
returns a :class:`SamplingAlgorithm`; :func:`bayesreg.sampling.driver.sample` runs any of
them (warm-up, chunks of draws, the stop rule, checkpoints and resume).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

__all__ = ["Kernel", "Warmup", "Program", "SamplingAlgorithm", "marginal_sd"]


class Kernel(NamedTuple):
    """A transition kernel as :mod:`bayesreg.sampling.chains` and :mod:`bayesreg.sampling.driver` run it.

    Attributes
    ----------
    step : callable
        ``(rng_key, state, params, cache) -> (state, info, cache)``: one transition (pure,
        jittable).  ``params`` are the tuned values (proposal scales, step size and mass
        matrix); ``info`` a NamedTuple with at least ``acceptance_rate (B,)``,
        ``is_accepted (B,)``, ``cg_iterations ()`` and ``solve_failed ()``.
    init_cache : callable
        ``state -> cache``: what the kernel carries besides the state (a cached interior
        map, a CG preconditioner), built at every chunk start so that a resumed run repeats
        the same arithmetic.
    per_chain_params : bool
        ``params`` has a leading chain axis (each chain adapts its own values).
    """

    step: Callable
    init_cache: Callable
    per_chain_params: bool = False


class Warmup(NamedTuple):
    """A warm-up the driver runs chunk by chunk (its loop, keys, progress bar and timings are
    the driver's; what is tuned and how is the algorithm's).

    Attributes
    ----------
    init : callable
        ``states -> ws``: the adaptation's state (on the device or the host).
    chunk : callable
        ``(k, keys (C,), states, ws) -> (states, ws, acceptance (B,) ndarray, postfix dict)``:
        warm-up chunk ``k`` of the chains, ``postfix`` the figures the progress bar shows.
    final : callable
        ``(ws, states) -> (params, states)``: the tuned values to freeze (arrays, or a
        NamedTuple of them) and the chains' states to sample from (the warm-up's, or the same
        positions re-evaluated where the tuned values change what the kernel carries in
        them: a gradient kernel whose target is rebuilt after the warm-up).
    """

    init: Callable
    chunk: Callable
    final: Callable


class Program(NamedTuple):
    """An algorithm built for one run's shape (chains, draws per chunk, thinning, warm-up).

    Attributes
    ----------
    chunk : callable
        ``(keys (C,), states, params) -> (states, out)``: ``chunk_draws`` thinned draws of
        every chain at the frozen ``params`` (``out`` as
        :func:`bayesreg.sampling.chains.build_chunk`'s).
    warmup : Warmup
    method : str
        How the chains run (:data:`bayesreg.sampling.chains.CHAIN_METHODS`).
    """

    chunk: Callable
    warmup: Warmup
    method: str


class SamplingAlgorithm(NamedTuple):
    """A kernel family as the driver (:func:`bayesreg.sampling.driver.sample`) runs it.

    Attributes
    ----------
    kind : str
        Its name in ``sampler.kind`` and ``run.json`` (``"rwmh"``, ``"mala"``, ``"hmc"``,
        ``"nuts"``).
    blocks : tuple of str
        Names of the acceptance columns (coordinate blocks or moves), in order.
    init : callable
        ``position (dim,) -> state``: one chain's state (pure; the driver maps it over chains);
        with ``chain_data``, ``(position, data) -> state``.
    build : callable
        ``(n_chains, dim, chunk_draws, thinning, n_warm, chain_method) -> Program`` with
        ``dim`` the position's size and ``n_warm`` the warm-up's chunks (raises
        ``ValueError`` where the algorithm does not fit that shape).
    params : callable
        ``(*arrays) -> params``: the frozen tuned values rebuilt from their arrays (a
        checkpoint stores the arrays).
    describe : callable
        ``(tuple of arrays) -> dict``: the tuned values for ``run.json`` (JSON-ready).
    solves_per_step : float or None
        CG solves counted in the kernel's ``cg_iterations`` per step (``None``: it varies).
    preconditioner : str
        The counted solves' CG preconditioner (``"unknown"`` where not said).
    condensed : bool
        Moves of ``u_b`` take the interior from a cached dense map (no CG solve).
    sample_stats : tuple of str
        The ArviZ sample stats the kernel's draws carry beyond acceptance, ``lp`` and the
        CG figures: any of ``"n_steps"`` (gradient evaluations), ``"step_size"`` (from
        ``describe``'s ``step_size_per_chain``), ``"energy"``, ``"tree_depth"``; a gradient
        kernel names ``"n_steps"`` (its runs get Stan's per-chain checks).
    chain_data : pytree or None
        Each chain's own data (leaves ``(C, ...)``) where the chains sample different
        targets in one program (:func:`bayesreg.sampling.kernels.gibbs.as_algorithm`); the
        driver maps ``init`` over the starts and these together.  ``None``: one target.
    """

    kind: str
    blocks: tuple
    init: Callable
    build: Callable
    params: Callable
    describe: Callable
    solves_per_step: float | None
    preconditioner: str
    condensed: bool
    sample_stats: tuple = ()
    chain_data: object = None


def marginal_sd(scale: np.ndarray, factor: bool) -> np.ndarray:
    """Marginal proposal standard deviations ``(..., d)`` of independent scales ``(..., d)``
    or of lower-triangular factors ``L`` ``(..., d, d)`` (``sqrt(diag(L L^T))``): what the
    families' ``describe`` reports of a random walk's tuned proposal."""
    return np.sqrt(np.sum(scale ** 2, axis=-1)) if factor else np.abs(scale)
