"""The kernel type the chain driver runs (in the style of BlackJAX's ``SamplingAlgorithm``)."""

from __future__ import annotations

from typing import Callable, NamedTuple

__all__ = ["Kernel"]


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
