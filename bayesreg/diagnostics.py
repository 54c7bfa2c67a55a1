"""Convergence diagnostics: the classic Gelman-Rubin R-hat and ArviZ conversion.

The paper (Sec. 3.2) stops when the *scale reduction* of every scalar estimand is below
1.2, the classic potential scale reduction factor of Gelman et al., *Bayesian Data
Analysis* (2nd ed., Sec. 11.6), ref. [12] of the paper.  ArviZ's default R-hat is the
rank-normalised split R-hat (Vehtari et al. 2021), which is stricter; reports give both.
:func:`coverage` checks the calibration of credible intervals against a synthetic truth.
"""

from __future__ import annotations

import numpy as np

__all__ = ["gelman_rubin", "coverage", "to_datatree"]


def gelman_rubin(draws, *, split: bool = False) -> np.ndarray:
    """Classic potential scale reduction factor per estimand.

    Parameters
    ----------
    draws : (C, D, ...) array_like
        ``C >= 2`` chains of ``D >= 2`` draws.
    split : bool
        Split every chain into halves first (BDA 3rd ed., Sec. 11.4): detects a trend that
        all chains share, which the whole-chain statistic cannot see.

    Returns
    -------
    (...) ndarray
        ``sqrt(((D-1)/D W + B/D) / W)`` with ``W`` the mean within-chain variance and ``B/D``
        the variance of the chain means.  ``inf`` where a chain never moved (``W = 0``) and
        the chains disagree; 1 where all draws are identical.

    Raises
    ------
    ValueError
        Fewer than 2 chains or 2 draws.
    """
    x = np.asarray(draws, dtype=np.float64)
    if x.ndim < 2 or x.shape[0] < 2 or x.shape[1] < (4 if split else 2):
        raise ValueError(f"need at least 2 chains x {4 if split else 2} draws, got shape {x.shape}")
    if split:
        half = x.shape[1] // 2
        x = np.concatenate([x[:, :half], x[:, x.shape[1] - half:]], axis=0)
    n = x.shape[1]
    w = x.var(axis=1, ddof=1).mean(axis=0)
    b_over_n = x.mean(axis=1).var(axis=0, ddof=1)
    var_plus = (n - 1) / n * w + b_over_n
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.sqrt(var_plus / w)
    r = np.where((w == 0) & (b_over_n == 0), 1.0, r)
    return np.where((w == 0) & (b_over_n > 0), np.inf, r)


def coverage(draws, truth, levels=(0.5, 0.9, 0.95)) -> dict[float, float]:
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
    x = np.asarray(draws, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if t.ndim != 1 or x.ndim < 2 or x.shape[-1] != t.shape[0]:
        raise ValueError(f"draws (..., K) and truth (K,) expected, got {x.shape} and {t.shape}")
    x = x.reshape(-1, t.shape[0])
    if x.shape[0] < 2:
        raise ValueError(f"need at least 2 draws, got {x.shape[0]}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(t))):
        raise ValueError("draws and truth must be finite")
    out = {}
    for lev in levels:
        lev = float(lev)
        if not 0.0 < lev < 1.0:
            raise ValueError(f"credible level must be in (0, 1), got {lev}")
        lo, hi = np.quantile(x, [(1.0 - lev) / 2.0, (1.0 + lev) / 2.0], axis=0)
        out[lev] = float(np.mean((t >= lo) & (t <= hi)))
    return out


def to_datatree(posterior: dict, *, sample_stats: dict | None = None, dims=None, coords=None,
                attrs=None):
    """ArviZ ``DataTree`` from ``{name: (chain, draw, ...)}`` arrays (``az.from_dict``)."""
    import arviz as az

    groups = {"posterior": posterior}
    if sample_stats:
        groups["sample_stats"] = sample_stats
    tree = az.from_dict(groups, dims=dims or {}, coords=coords or {})
    if attrs:
        tree.attrs.update(attrs)
    return tree
