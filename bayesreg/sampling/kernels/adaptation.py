"""Warm-ups: the random walk's (:func:`rwmh_warmup`) and the gradient Gibbs kernel's.

The random walk tunes each block's scale by Robbins-Monro toward a target acceptance rate
and re-estimates its marginal scales (or, for the few elastic parameters, a dense factor)
from two windows of warm-up draws.  The gradient kernel (:mod:`bayesreg.sampling.kernels.gibbs`) uses
Stan's windowed adaptation with BlackJAX's pieces
(:func:`blackjax.adaptation.step_size.dual_averaging_adaptation` for the step size,
:func:`blackjax.adaptation.mass_matrix.mass_matrix_adaptation` for a diagonal or dense inverse
mass matrix, :func:`blackjax.adaptation.window_adaptation.build_schedule` for the windows),
the elastic random walk's covariance from the same windows' covariance of ``eta``
(``2.38^2 / n_free`` times it, dense: Haario et al.'s adaptive Metropolis), and
Robbins-Monro on the log of a common multiplier toward acceptance 0.3.  Each chain adapts
its own values; they are frozen after the warm-up.
"""

from __future__ import annotations

from typing import NamedTuple

import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from bayesreg.sampling.kernels.base import Kernel
from bayesreg.sampling.kernels.gibbs import ELASTIC_TARGET_ACCEPTANCE, GibbsParams

__all__ = ["WarmupState", "schedule", "build_warmup_step", "rwmh_warmup", "DENSE_MAX"]


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


def build_warmup_step(kernel: Kernel, *, target_acceptance: float, dense_mass: bool = False,
                      adapt_mass: bool = True):
    """``(init, step, final)`` of the windowed warm-up of :func:`bayesreg.sampling.kernels.gibbs.build_kernel`'s kernel.

    ``adapt_mass=False`` keeps the identity inverse mass matrix (the preconditioned
    coordinates ``w`` already have about unit scale) and adapts the step size alone, by
    dual averaging over the whole warm-up (no restarts at the window ends).

    ``init(dim_u, initial_step_size, eta_scale) -> WarmupState``;
    ``step(key, state, ws, cache, stage) -> (state, ws, cache, info)`` with ``stage`` the
    ``(slow?, window ends?)`` row of :func:`schedule`; ``final(ws) -> GibbsParams``.
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
        return WarmupState(da, mm, jnp.asarray(initial_step_size, jnp.float64), mm.inverse_mass_matrix,
                           mm_eta_init(max(eta_scale.shape[0], 1)), eta_scale, jnp.zeros(()), jnp.asarray(0),
                           jnp.zeros(()))

    def params_of(ws: WarmupState, step_size) -> GibbsParams:
        return GibbsParams(step_size, ws.inverse_mass, ws.eta_base * jnp.exp(ws.log_eta_scale),
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

    def final(ws: WarmupState) -> GibbsParams:
        # the dual average, once it has averaged anything: BlackJAX's initial state holds
        # log_step_size_avg = 0, so with no warm-up step (or none since a window's restart)
        # the step in use is kept
        step_size = jnp.where(ws.da.step > 1, jnp.exp(ws.da.log_step_size_avg), ws.step_size)
        return params_of(ws, step_size)

    return init_ws, step, final


def _scaled(sigmas, log_scales):
    return tuple(jnp.asarray(s_) * np.exp(ls) for s_, ls in zip(sigmas, log_scales))


DENSE_MAX = 16  # blocks up to this size (the elastic parameters) adapt a dense proposal


def rwmh_warmup(chunk, states, key_warm, sigmas, idxs, adapt, n_chains, warmup_steps, chunk_draws,
                thinning, target_acceptance, progress):
    """The random walk's warm-up (:func:`bayesreg.sampling.driver.sample`), run chunk by chunk on the
    host: Robbins-Monro on each block's log-scale toward ``target_acceptance``; scales
    re-estimated from the draws of two windows (``[n/4, n/2)`` and ``[n/2, 3n/4)`` of the
    ``n`` warm-up chunks): a dense factor ``2.38 / sqrt(d) chol(C)`` (Haario et al.) for the
    blocks ``adapt`` marks with at most :data:`DENSE_MAX` coordinates (the elastic
    parameters), per-coordinate scales for larger ones.

    ``chunk(keys (C,), states, sigmas) -> (states, out)`` runs one chunk
    (:func:`bayesreg.sampling.chains.build_chunk`); ``idxs`` are the blocks' coordinate indices.

    Returns
    -------
    states, frozen sigmas (tuple of arrays), acceptance per block in the last chunk, timings
    """
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
