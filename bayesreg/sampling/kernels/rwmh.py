"""Random-walk Metropolis-Hastings on the posterior's position (paper Sec. 3.2, Algorithm 1).

The Normal jumping kernel (:func:`blackjax.mcmc.random_walk.normal`) and the Metropolis
accept step (:func:`blackjax.mcmc.proposal.static_binomial_sampling`) are BlackJAX's.  The
position may be updated in coordinate blocks (systematic-scan Metropolis-within-Gibbs); one
block with every coordinate is the paper's joint proposal (Eq. 14).  Proposals are
symmetric, so the acceptance probability is the posterior ratio of Eq. 13.

The state also carries the chain's interior FE solution, the warm start of the next solve.
A :class:`KernelCache` (the condensation ``H``, the CG preconditioner ``K_ii^-1``) is built
from the state at every chunk start (:attr:`bayesreg.sampling.kernels.base.Kernel.init_cache`) and
carried from step to step.  The driver (warm-up, chunks, stopping) is
:func:`bayesreg.sampling.driver.sample`.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from bayesreg.sampling.kernels.base import Kernel

__all__ = ["RWMHState", "RWMHInfo", "Condensation", "Preconditioner", "KernelCache", "init",
           "build_kernel"]


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
