"""The gradient Gibbs kernel's warm-up, one transition at a time.

The gradient kernel (:mod:`bayesreg.sampling.kernels.gibbs`) uses Stan's windowed adaptation
with BlackJAX's pieces
(:func:`blackjax.adaptation.step_size.dual_averaging_adaptation` for the step size,
:func:`blackjax.adaptation.mass_matrix.mass_matrix_adaptation` for a diagonal or dense inverse
mass matrix, :func:`blackjax.adaptation.window_adaptation.build_schedule` for the windows),
the elastic random walk's covariance from the same windows' covariance of ``eta``
(``2.38^2 / n_free`` times it, dense: Haario et al.'s adaptive Metropolis), and
Robbins-Monro on the log of a common multiplier toward acceptance 0.3.  Each chain adapts
its own values; they are frozen after the warm-up.  (The random walk's warm-up is
:func:`bayesreg.sampling.kernels.rwmh.as_algorithm`'s.)
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesreg.sampling.kernels.base import Kernel

__all__ = ["WarmupState", "schedule", "build_warmup_step", "ELASTIC_TARGET_ACCEPTANCE"]

#: Warm-up target of the elastic random walk's (and the collapsed moves') acceptance.
ELASTIC_TARGET_ACCEPTANCE = 0.3


class WarmupState(NamedTuple):
    """Adaptation state of one chain: BlackJAX's dual averaging and mass-matrix (Welford)
    states for the u_b kernel, a dense Welford state of ``eta`` whose window covariance
    ``C`` sets the elastic random walk's factor ``2.38 / sqrt(n_free) chol(C)`` (Haario et
    al.'s adaptive Metropolis; the posterior of the parameters is strongly correlated along
    the overall stiffness scale under the exact normaliser), and the Robbins-Monro
    log-multipliers of that factor for the random-walk and for the collapsed moves (each
    toward acceptance 0.3)."""

    da: tuple
    mm: tuple
    step_size: jax.Array
    inverse_mass: jax.Array
    mm_eta: tuple
    eta_base: jax.Array
    log_eta_scale: jax.Array
    count: jax.Array
    log_collapsed_scale: jax.Array | float = 0.0


def schedule(num_steps: int) -> np.ndarray:
    """Stan's warm-up windows ``(num_steps, 2)``: ``(slow?, window ends?)`` per step
    (:func:`blackjax.adaptation.window_adaptation.build_schedule`)."""
    from blackjax.adaptation.window_adaptation import build_schedule

    return np.array(build_schedule(num_steps), dtype=np.int32).reshape(-1, 2)


def build_warmup_step(kernel: Kernel, params_type: Callable, *, target_acceptance: float,
                      dense_mass: bool = False, adapt_mass: bool = True):
    """``(init, step, final)`` of the windowed warm-up of :func:`bayesreg.sampling.kernels.gibbs.build_kernel`'s kernel.

    ``params_type(step_size, inverse_mass, eta_scale, collapsed_scale)`` makes the kernel's
    parameters (:class:`bayesreg.sampling.kernels.gibbs.GibbsParams`).

    ``adapt_mass=False`` keeps the identity inverse mass matrix (the preconditioned
    coordinates ``w`` already have about unit scale) and adapts the step size alone, by
    dual averaging over the whole warm-up (no restarts at the window ends).

    ``init(dim_u, initial_step_size, eta_scale) -> WarmupState`` (its floats strongly typed);
    ``step(key, state, ws, cache, stage) -> (state, ws, cache, info)`` with ``stage`` the
    ``(slow?, window ends?)`` row of :func:`schedule`; ``final(ws) -> params``.
    """
    # BlackJAX imported here, not with the module: importing it starts JAX's backend
    from blackjax.adaptation.mass_matrix import mass_matrix_adaptation
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    mm_init, mm_update, mm_final = mass_matrix_adaptation(not dense_mass)
    da_init, da_update, da_final = dual_averaging_adaptation(target_acceptance)

    mm_eta_init, mm_eta_update, mm_eta_final = mass_matrix_adaptation(False)

    def init_ws(dim_u: int, initial_step_size, eta_scale) -> WarmupState:
        mm = mm_init(dim_u)
        da = da_init(jnp.asarray(initial_step_size, jnp.float64))
        eta_scale = jnp.asarray(eta_scale, jnp.float64)
        if eta_scale.ndim == 1:
            eta_scale = jnp.diag(eta_scale)
        ws = WarmupState(da, mm, jnp.asarray(initial_step_size, jnp.float64), mm.inverse_mass_matrix,
                         mm_eta_init(max(eta_scale.shape[0], 1)), eta_scale, jnp.zeros(()), jnp.asarray(0),
                         jnp.zeros(()))
        # BlackJAX's initial states hold weakly typed floats (python 0.0) that the warm-up
        # step returns strongly typed: made strong here, so that a program carrying the state
        # (a scan, a chunk) compiles once, not twice; the integer counters stay weak in and out
        return jax.tree.map(lambda a: jnp.asarray(a, jnp.asarray(a).dtype)
                            if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a, ws)

    def params_of(ws: WarmupState, step_size):
        return params_type(step_size, ws.inverse_mass, ws.eta_base * jnp.exp(ws.log_eta_scale),
                           ws.eta_base * jnp.exp(ws.log_collapsed_scale))

    def step(key, state, ws: WarmupState, cache, stage):
        params = params_of(ws, ws.step_size)
        state, info, cache = kernel.step(key, state, params, cache)
        slow, window_end = stage[0] == 1, stage[1] == 1
        acc_u = jnp.nan_to_num(info.acceptance_rate[0])
        da = da_update(ws.da, acc_u)
        eta_pad = state.eta if state.eta.shape[0] else jnp.zeros(1)
        mm, mm_eta = jax.lax.cond(
            slow, lambda m: (mm_update(m[0], state.u.position) if adapt_mass else m[0],
                             mm_eta_update(m[1], eta_pad)),
            lambda m: m, (ws.mm, ws.mm_eta))
        n_free = state.eta.shape[0]

        def end_window(args):
            da_, mm_, mm_eta_, base, log_eta, log_col = args
            if adapt_mass:
                mm_ = mm_final(mm_)
                da_ = da_init(da_final(da_))
            mm_eta_ = mm_eta_final(mm_eta_)
            if n_free:  # factor from the window's (regularised) covariance, multiplier reset
                base = 2.38 / jnp.sqrt(n_free) * jnp.linalg.cholesky(mm_eta_.inverse_mass_matrix)
                log_eta, log_col = jnp.zeros(()), jnp.zeros(())
            return da_, mm_, mm_eta_, base, log_eta, log_col

        count = jnp.where(window_end, 0, ws.count + 1)
        da, mm, mm_eta, base, log_eta, log_col = jax.lax.cond(
            window_end, end_window, lambda a: a,
            (da, mm, mm_eta, ws.eta_base, ws.log_eta_scale, jnp.asarray(ws.log_collapsed_scale)))
        gain = 1.0 / ((count + 1).astype(jnp.float64) ** 0.6)
        # (a joint target's second column is the normaliser's correction: nothing to adapt)
        if n_free and info.acceptance_rate.shape[0] > 1:
            log_eta = log_eta + gain * (jnp.nan_to_num(info.acceptance_rate[1]) - ELASTIC_TARGET_ACCEPTANCE)
        if n_free and info.acceptance_rate.shape[0] > 2:  # collapsed moves
            log_col = log_col + gain * (jnp.nan_to_num(info.acceptance_rate[2]) - ELASTIC_TARGET_ACCEPTANCE)
        ws = WarmupState(da, mm, jnp.exp(da.log_step_size), mm.inverse_mass_matrix, mm_eta, base,
                         log_eta, count, log_col)
        return state, ws, cache, info

    def final(ws: WarmupState):
        # the dual average, once it has averaged anything: BlackJAX's initial state holds
        # log_step_size_avg = 0, so with no warm-up step (or none since a window's restart)
        # the step in use is kept
        step_size = jnp.where(ws.da.step > 1, jnp.exp(ws.da.log_step_size_avg), ws.step_size)
        return params_of(ws, step_size)

    return init_ws, step, final
