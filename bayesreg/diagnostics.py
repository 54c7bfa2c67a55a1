"""Diagnostics of finished draws: ArviZ conversion, fast ESS, calibration against a truth.

ArviZ's default R-hat is the rank-normalised split R-hat (Vehtari et al. 2021); the classic
Gelman-Rubin R-hat of the paper's stopping rule is :mod:`bayesreg.convergence`.
:func:`coverage` checks the calibration of credible intervals against a synthetic truth.
:func:`arviz_fast_ess` runs ArviZ's ESS (bulk, tail, MCSE) with the end of Geyer's
initial sequence found in one vectorised search (:func:`geyer_ess`) instead of ArviZ's
Python loop over lags: the same numbers, and the summary of a long, slowly mixing run in
seconds instead of minutes.
"""

from __future__ import annotations

import contextlib

import numpy as np

__all__ = ["coverage", "to_datatree", "group_draws", "geyer_ess", "arviz_fast_ess"]


def coverage(draws, truth, levels=(0.5, 0.9, 0.95), *, block: int = 64) -> dict[float, float]:
    """Fraction of true values inside the central posterior credible intervals.

    For every component ``k`` and level ``l`` the central interval is bounded by the
    empirical ``(1 - l)/2`` and ``(1 + l)/2`` quantiles of the draws of component ``k``
    (linear interpolation, ``numpy.quantile``); the truth counts as covered if it lies in
    the closed interval.  For a calibrated posterior and truths drawn from it, the
    coverage is ``l`` up to a binomial error of sd ``sqrt(l (1 - l) / K)``.

    Parameters
    ----------
    draws : (..., K) array_like
        Posterior draws; every axis but the last is a sample axis and all are pooled,
        e.g. ``(C, D, K)`` chains x draws or ``(S, K)``.  At least 2 draws.
    truth : (K,) array_like
        True value of each component (same units as ``draws``).
    levels : sequence of float
        Credible levels, each in ``(0, 1)``.
    block : int, keyword-only
        Components processed at once (memory ``S x block`` doubles; a strided view of the
        draws, e.g. the boundary coordinates of a position array, is never copied whole).

    Returns
    -------
    dict
        ``{level: fraction of the K components covered}``, fractions in ``[0, 1]``.

    Raises
    ------
    ValueError
        If ``truth`` is not ``(K,)`` with ``K`` the last axis of ``draws``, there are fewer
        than 2 draws, a value is not finite, or a level is outside ``(0, 1)``.
    """
    x = np.asarray(draws)
    t = np.asarray(truth, dtype=np.float64)
    if t.ndim != 1 or x.ndim < 2 or x.shape[-1] != t.shape[0]:
        raise ValueError(f"draws (..., K) and truth (K,) expected, got {x.shape} and {t.shape}")
    n_draws = x.size // max(t.shape[0], 1)
    if n_draws < 2:
        raise ValueError(f"need at least 2 draws, got {n_draws}")
    levels = [float(lev) for lev in levels]
    for lev in levels:
        if not 0.0 < lev < 1.0:
            raise ValueError(f"credible level must be in (0, 1), got {lev}")
    if not np.all(np.isfinite(t)):
        raise ValueError("draws and truth must be finite")
    inside = {lev: np.zeros(t.shape[0], bool) for lev in levels}
    for a in range(0, t.shape[0], block):  # components in blocks: memory S x block
        xb = np.asarray(x[..., a:a + block], dtype=np.float64).reshape(n_draws, -1)
        if not np.all(np.isfinite(xb)):
            raise ValueError("draws and truth must be finite")
        tb = t[a:a + block]
        for lev in levels:
            lo, hi = np.quantile(xb, [(1.0 - lev) / 2.0, (1.0 + lev) / 2.0], axis=0)
            inside[lev][a:a + block] = (tb >= lo) & (tb <= hi)
    return {lev: float(np.mean(inside[lev])) for lev in levels}


def to_datatree(posterior: dict, *, sample_stats: dict | None = None, dims=None, coords=None,
                attrs=None, constant_data: dict | None = None):
    """ArviZ ``DataTree`` from ``{name: (chain, draw, ...)}`` arrays (``az.from_dict``);
    ``constant_data``: arrays without chain and draw axes (fixed parameters)."""
    import arviz as az

    groups = {"posterior": posterior}
    if sample_stats:
        groups["sample_stats"] = sample_stats
    if constant_data:
        groups["constant_data"] = constant_data
    tree = az.from_dict(groups, dims=dims or {}, coords=coords or {})
    if attrs:
        tree.attrs.update(attrs)
    return tree


def group_draws(tree, var: str) -> np.ndarray:
    """Draws ``(chain, draw, G)`` of ``lam`` or ``mu`` over every parameter group of a run's
    ``posterior.nc``, the fixed ones (stored as ``constant_data[var + "_fixed"]``, not as
    sampled variables) filled in at their value; groups in the order of the ``group``
    coordinate.  Files that stored every group as a sampled variable read as they are."""
    post = tree.posterior
    if var in post and "group" in post[var].dims:
        return np.asarray(post[var].transpose("chain", "draw", "group").values, np.float64)
    groups = [str(g) for g in post["group"].values]
    out = np.empty((post.sizes["chain"], post.sizes["draw"], len(groups)))
    if var in post:  # the free groups (none: every group fixed, only constant data)
        x = post[var]
        vals = np.asarray(x.transpose("chain", "draw", f"{var}_group").values, np.float64)
        for k, g in enumerate(str(g) for g in x[f"{var}_group"].values):
            out[..., groups.index(g)] = vals[..., k]
    fixed = tree.constant_data[f"{var}_fixed"]
    for g, v in zip(fixed[f"{var}_fixed_group"].values, np.asarray(fixed.values)):
        out[..., groups.index(str(g))] = float(v)
    return out


def geyer_ess(rho, n_chain: int, n_draw: int, *, relative: bool = False) -> float:
    """Effective sample size from the combined autocorrelations by Geyer's initial monotone
    sequence, vectorised over the lags.

    The estimator of Geyer (1992) as Vehtari et al. (2021) use it, exactly as ArviZ's
    ``_ess`` computes it (``arviz_stats.base.diagnostics``) lag by lag in a Python loop:
    the first pair sum ``rho_2k + rho_2k+1`` that is not positive ends the initial positive
    sequence, the pair sums before it are made non-increasing (running minimum), and
    ``tau = -1 + 2 sum(pairs) + rho_2K``, floored at ``1 / log10(C D)``.  Here the end of
    the sequence is found with one search over all pair sums, so the cost no longer grows
    with the autocorrelation time (ArviZ's loop visits every lag up to the end).

    Parameters
    ----------
    rho : (D,) ndarray
        ``1 - (W - mean_c acov_c(t)) / var_plus`` for every lag ``t`` (``rho[0]`` is taken as 1).
    n_chain, n_draw : int
        Chains and draws per chain of the (split) draws.
    relative : bool, keyword-only
        ESS per draw instead of the ESS.

    Returns
    -------
    float
        The ESS; NaN when ``rho[1]`` is NaN (as ArviZ).
    """
    rho = np.array(rho, dtype=float)
    rho[0] = 1.0
    if np.isnan(rho[1]):
        return float("nan")
    # ArviZ's loop computes pair k (lags 2k, 2k+1) for k = 1, 2, ... while the previous pair
    # sum is positive and 2k - 1 < D - 3
    k_max = (n_draw - 3) // 2
    pairs = rho[0:2 * k_max + 2:2] + rho[1:2 * k_max + 2:2]  # pair sums k = 0..k_max
    if not pairs[0] > 0.0 or k_max < 1:
        big_k = 0
    else:
        stop = np.flatnonzero(~(pairs[1:k_max + 1] > 0.0))
        big_k = int(stop[0]) + 1 if stop.size else k_max
    if big_k == 0:
        last_even = 1.0
    else:
        # the even lag of the last pair: kept if its pair was stored (sum >= 0) or if > 0
        last_even = rho[2 * big_k] if (pairs[big_k] >= 0.0 or rho[2 * big_k] > 0.0) else 0.0
    monotone = np.minimum.accumulate(pairs[:big_k])
    tau = -1.0 + 2.0 * float(np.sum(monotone)) + float(last_even)
    total = n_chain * n_draw
    tau = max(tau, 1.0 / np.log10(total))
    return (1.0 if relative else total) / tau


def _fast_backend():
    """ArviZ's NumPy stats backend with :func:`geyer_ess` in place of the lag loop of
    ``_ess`` (``None`` if this ArviZ has no such method to replace)."""
    try:
        from arviz_stats.base.array import BaseArray
        from arviz_stats.base.dataarray import BaseDataArray
    except ImportError:  # pragma: no cover - another ArviZ layout: keep its own
        return None
    if not hasattr(BaseArray, "_ess") or not hasattr(BaseArray, "autocov"):
        return None  # pragma: no cover

    class GeyerArray(BaseArray):
        def _ess(self, ary, relative=False):
            ary = np.asarray(ary, dtype=float)
            if ary.ndim != 2 or ary.shape[1] < 8 or not np.isfinite(ary).all():
                return super()._ess(ary, relative=relative)
            if (np.max(ary) - np.min(ary)) < np.finfo(float).resolution:
                return ary.size
            n_chain, n_draw = ary.shape
            acov = self.autocov(ary, axis=1)
            mean_var = np.mean(acov[:, 0]) * n_draw / (n_draw - 1.0)
            var_plus = mean_var * (n_draw - 1.0) / n_draw
            if n_chain > 1:
                var_plus += np.var(ary.mean(axis=1), axis=None, ddof=1)
            rho = 1.0 - (mean_var - acov.mean(axis=0)) / var_plus
            return geyer_ess(rho, n_chain, n_draw, relative=relative)

    arrays = GeyerArray()

    class Backend:
        """``rcParams["stats.module"]`` object: ArviZ's base functions, faster ESS."""

        array_stats = arrays
        dataarray_stats = BaseDataArray(array_class=arrays)
        eti = dataarray_stats.eti  # what arviz_base checks a stats module by
        rhat = dataarray_stats.rhat

    return Backend()


_BACKEND = None


@contextlib.contextmanager
def arviz_fast_ess():
    """Context in which ArviZ (``az.summary``, ``az.ess``, ``az.mcse``) computes every ESS
    with :func:`geyer_ess`: the same numbers as ArviZ's own (tests: equal to 1e-12 relative),
    without its Python loop over lags.

    ArviZ stays the implementation of every diagnostic (rank normalisation, splitting,
    quantiles, MCSE, R-hat); only the search for the end of Geyer's initial positive
    sequence is vectorised.  Through ArviZ's documented ``stats.module`` rcParam, restored
    on exit, so a user's own settings are untouched (and a backend the user chose, e.g.
    ``"numba"``, is left in place).  It matters for long, slowly mixing runs, where the
    initial positive sequence runs over thousands of lags.
    """
    global _BACKEND
    from arviz_base import rc_context, rcParams

    if _BACKEND is None:
        _BACKEND = _fast_backend() or False
    if not _BACKEND or rcParams["stats.module"] != "base":
        yield  # another backend chosen by the user (e.g. numba): theirs
        return
    with rc_context({"stats.module": _BACKEND}):
        yield
