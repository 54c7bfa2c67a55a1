"""Surrogate transitions of a joint target: the Metropolis correction after each trajectory,
and the surrogate rebuilt where the chains are once the warm-up ends.

A joint target's trajectories see a cheap smooth surrogate of the exact normaliser
(:func:`bayesreg.sampling.kernels.target.joint_target`).  :func:`correct` keeps the
trajectory's end ``z'`` with probability ``min(1, exp(Delta(z') - Delta(z)))``, ``Delta`` the
exact normaliser less the surrogate: the trajectory leaves the surrogate posterior invariant
and is reversible, so the chain's stationary distribution is the exact posterior whatever the
surrogate (Liu 2001, *Monte Carlo Strategies in Scientific Computing*, Sec. 9.4; Christen
and Fox 2005, *JCGS* 14(4)).  How often it accepts depends on the surrogate: built at the
starts' centre (the mode), it can be far from exact where the posterior's mass lies, and
:class:`SurrogateRebuild` rebuilds it at the chains' median after the warm-up
(:func:`bayesreg.sampling.kernels.gibbs.as_algorithm`).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesreg.sampling.kernels.target import Target

__all__ = ["SurrogateRebuild", "Rebuilds", "correct", "correction_span", "surrogate_center"]


def correct(target: Target, key, moved, ustate, old_u, interior, old_interior, log_norm):
    """The surrogate transition's Metropolis step after a trajectory of a joint target.

    ``moved`` ``()`` bool: whether the trajectory left ``old_u`` (the chain's
    ``HMCState`` before it) for ``ustate``; ``log_norm`` ``()`` the correction ``Delta`` at
    ``old_u``.  Returns ``(ustate, interior, log_norm, acceptance (), accepted ())``: the end
    kept or the chain back at ``old_u`` (and ``old_interior``), with ``Delta`` where it
    stands; a ``Delta`` that is NaN (the exact normaliser failed) rejects.
    """
    from blackjax.mcmc.proposal import static_binomial_sampling

    def step(_):
        delta = jnp.asarray(target.correction(ustate.position), jnp.float64)
        log_ratio = delta - log_norm
        log_ratio = jnp.where(jnp.isnan(log_ratio), -jnp.inf, log_ratio)
        _, (do, p_acc, _) = static_binomial_sampling(key, log_ratio, jnp.zeros(()), jnp.ones(()))
        return do, p_acc, jnp.where(do, delta, log_norm)

    keep, p_acc, delta = jax.lax.cond(
        moved, step, lambda _: (jnp.asarray(True), jnp.ones(()), log_norm), None)
    ustate = jax.tree.map(lambda a, b: jnp.where(keep, a, b), ustate, old_u)
    return ustate, jnp.where(keep, interior, old_interior), delta, p_acc, moved & keep


class SurrogateRebuild(NamedTuple):
    """How :func:`bayesreg.sampling.kernels.gibbs.as_algorithm` rebuilds a joint target's
    surrogate when the warm-up ends.

    Where the correction ``Delta`` at the chains' states spans more than ``tolerance`` over
    the chains, the surrogate is rebuilt at :func:`surrogate_center` of their positions, the
    chains' states are evaluated again on the rebuilt target, and the sampling kernel, fixed
    from then on, runs on it (one more compilation of the sampling program).  The warm-up's
    draws are discarded and the correction keeps the chain exact whatever the surrogate.
    The centre is frozen with the tuned values
    (:attr:`~bayesreg.sampling.kernels.gibbs.GibbsParams.surrogate_center`: checkpoints,
    ``run.json``), so a resumed run samples the same target.

    Attributes
    ----------
    n_params : int
        The free parameters at the end of each position ``[..., phi]`` (natural units).
    build : callable
        ``phi (n_params,) ndarray -> Target``: the joint target, identical but for its
        surrogate, built at ``phi`` (host code; called once per centre).
    tolerance : float
        Nats: the span ``max_c Delta_c - min_c Delta_c`` up to which the surrogate is kept
        (its correction then accepts nearly every trajectory, and a rebuild would cost a
        compilation for nothing); ``0`` rebuilds always.
    """

    n_params: int
    build: Callable
    tolerance: float = 1.0


def surrogate_center(positions, n_params: int) -> np.ndarray:
    """Where :class:`SurrogateRebuild` rebuilds the surrogate: the chains' median of each
    free parameter ending their positions (``positions`` ``(C, dim)``, natural units;
    returns ``(n_params,)``), robust to a chain that the warm-up left apart."""
    return np.median(np.asarray(positions, np.float64)[:, -n_params:], axis=0)


def correction_span(target: Target, states) -> float:
    """``max - min`` over the chains of a joint target's correction ``Delta`` at their states
    (:class:`~bayesreg.sampling.kernels.gibbs.GibbsState` with a leading chain axis):
    ``logdensity`` is the natural log-density with ``Delta``, ``u.logdensity`` the
    trajectory's, with the surrogate and the log-Jacobian; ``inf`` where one is not finite."""
    jac = jax.jit(jax.vmap(target.log_jacobian))(states.u.position)
    delta = np.asarray(states.logdensity - states.u.logdensity + jac)
    return float(np.ptp(delta)) if np.all(np.isfinite(delta)) else np.inf


class Rebuilds:
    """A :class:`SurrogateRebuild` at work: the targets and kernels built at each centre
    (cached), and the warm-up's end that decides on a rebuild.

    Parameters
    ----------
    spec : SurrogateRebuild or None
        ``None``: never rebuilt.
    kernel_of : callable
        ``Target -> (kernel, ws_init, ws_step, ws_final)`` (the algorithm's kernel and
        warm-up step on a target).
    init : callable
        ``(target, position (dim,), interior (n_i, 3)) -> state`` of one chain.
    """

    def __init__(self, spec: SurrogateRebuild | None, kernel_of: Callable, init: Callable):
        self.spec, self._kernel_of, self._init, self._at, self._programs = spec, kernel_of, init, {}, {}

    def at(self, center) -> tuple:
        """``(target, kernel, ws_step)`` with the surrogate built at ``center`` ``(n_params,)``."""
        center = np.asarray(center, np.float64)
        key = center.tobytes()
        if key not in self._at:
            target = self.spec.build(center)
            kernel, _, ws_step, _ = self._kernel_of(target)
            self._at[key] = (target, kernel, ws_step)
        return self._at[key]

    def program(self, centers, default, make: Callable):
        """The sampling program for the frozen ``centers`` ``(C, n_params)`` (one centre for
        every chain): ``make(kernel, ws_step)`` on the target rebuilt at it (cached by
        ``make`` and centre), or ``default`` where nothing was rebuilt (``None`` or
        ``(C, 0)``)."""
        if centers is None or not np.size(centers):
            return default
        key = (make, np.asarray(centers[0], np.float64).tobytes())
        if key not in self._programs:
            _, kernel, ws_step = self.at(centers[0])
            self._programs[key] = make(kernel, ws_step)
        return self._programs[key]

    def freeze(self, target: Target, frozen, states):
        """The warm-up's end: ``(frozen, states)`` with ``frozen.surrogate_center`` ``(C,
        n_params)`` (each chain the same centre) and the states evaluated on the rebuilt
        target, or ``(C, 0)`` and the states unchanged where ``target``'s surrogate is kept
        (no ``spec``, or a span within its tolerance).

        Raises
        ------
        ValueError
            A chain's log-density not finite on the rebuilt target.
        """
        n_chains = np.shape(states.logdensity)[0]
        if self.spec is None or correction_span(target, states) <= self.spec.tolerance:
            return frozen._replace(surrogate_center=jnp.zeros((n_chains, 0))), states
        center = surrogate_center(states.position, self.spec.n_params)
        rebuilt = self.at(center)[0]
        states = jax.jit(jax.vmap(lambda x, interior: self._init(rebuilt, x, interior)))(
            states.position, states.interior)
        lp = np.asarray(states.logdensity)
        if not np.all(np.isfinite(lp)):
            raise ValueError("the chains' states on the normaliser's surrogate rebuilt after the "
                             f"warm-up: log-density not finite for chains "
                             f"{np.flatnonzero(~np.isfinite(lp)).tolist()}")
        return frozen._replace(surrogate_center=jnp.tile(jnp.asarray(center), (n_chains, 1))), states
