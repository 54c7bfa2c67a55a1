"""Convergence diagnostics: the classic Gelman-Rubin R-hat and ArviZ conversion.

The paper (Sec. 3.2) stops when the *scale reduction* of every scalar estimand is below
1.2, the classic potential scale reduction factor of Gelman et al., *Bayesian Data
Analysis* (2nd ed., Sec. 11.6), ref. [12] of the paper.  ArviZ's default R-hat is the
rank-normalised split R-hat (Vehtari et al. 2021), which is stricter; reports give both.
:class:`RunningGelmanRubin` gives the same statistic for draws that arrive chunk by chunk
from per-chunk moments (the sampler's stopping rule: constant work per chunk).
:func:`coverage` checks the calibration of credible intervals against a synthetic truth.
"""

from __future__ import annotations

import numpy as np

__all__ = ["gelman_rubin", "RunningGelmanRubin", "coverage", "to_datatree"]


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
    return _rhat_from_moments(*_moments(x))


def _rhat_from_moments(n, mean, m2) -> np.ndarray:
    """:func:`gelman_rubin` from per-chain ``n`` draws, means and sums of squared deviations
    ``m2`` (``(C, ...)`` each)."""
    w = (m2 / (n - 1)).mean(axis=0)
    b_over_n = mean.var(axis=0, ddof=1)
    var_plus = (n - 1) / n * w + b_over_n
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.sqrt(var_plus / w)
    r = np.where((w == 0) & (b_over_n == 0), 1.0, r)
    return np.where((w == 0) & (b_over_n > 0), np.inf, r)


def _moments(x):
    """``(n, mean, m2)`` over axis 1 of ``x`` ``(C, n, ...)`` (two-pass)."""
    mean = x.mean(axis=1)
    return x.shape[1], mean, np.sum((x - mean[:, None]) ** 2, axis=1)


def _merge(a, b):
    """Moments of two consecutive blocks of draws (Chan, Golub and LeVeque 1983)."""
    (na, ma, sa), (nb, mb, sb) = a, b
    if na == 0:
        return b
    n = na + nb
    delta = mb - ma
    return n, ma + delta * (nb / n), sa + sb + delta**2 * (na * nb / n)


class RunningGelmanRubin:
    """:func:`gelman_rubin` of draws that arrive in chunks, at a cost per check that does not
    grow with the draws.

    Each chunk's estimands are reduced to per-chain means and sums of squared deviations
    when it arrives; R-hat merges them (Chan, Golub and LeVeque's pairwise update).  The
    split version needs the moments of each chain's halves: whole chunks are merged and the
    chunk that straddles a half's edge is reduced again from its draws (kept by reference,
    not copied).  Equal to :func:`gelman_rubin` on the concatenated draws to rounding
    (about 1e-13 relative; tested).  Recomputing R-hat over all the draws after every chunk
    instead cost 1.7 + 1.8 s (concatenation + statistic) per chunk at 25,000 draws of
    1,058 estimands and 3 chains, a third of the paper's chunks' time at the end of its run.

    Parameters
    ----------
    estimands : callable, optional
        ``(draws (C, n, dim)) -> (C, n, K)``, acting draw by draw (as the sampler's
        ``estimands``); default the draws themselves.
    """

    def __init__(self, estimands=None):
        self._estimands = estimands or (lambda d: d)
        self._chunks: list = []  # (draws, (n, mean, m2)) per chunk
        self.n_draws = 0

    def add(self, draws) -> None:
        """Append a chunk of draws ``(C, n, dim)`` (the same chains, in order)."""
        draws = np.asarray(draws)
        self._chunks.append((draws, _moments(np.asarray(self._estimands(draws), np.float64))))
        self.n_draws += draws.shape[1]

    def _range(self, lo: int, hi: int):
        out = (0, 0.0, 0.0)
        start = 0
        for draws, mom in self._chunks:
            n = draws.shape[1]
            a, b = max(lo - start, 0), min(hi - start, n)
            if a < b:
                part = mom if (a, b) == (0, n) else _moments(
                    np.asarray(self._estimands(draws[:, a:b]), np.float64))
                out = _merge(out, part)
            start += n
        return out

    def rhat(self, *, split: bool = False) -> np.ndarray:
        """R-hat per estimand of the draws added so far (see :func:`gelman_rubin`).

        Raises
        ------
        ValueError
            Fewer than 2 draws (4 with ``split``) or fewer than 2 chains.
        """
        d = self.n_draws
        chains = self._chunks[0][0].shape[0] if self._chunks else 0
        if chains < 2 or d < (4 if split else 2):
            raise ValueError(f"need at least 2 chains x {4 if split else 2} draws, got {chains} x {d}")
        if not split:
            return _rhat_from_moments(*self._range(0, d))
        half = d // 2
        (n1, m1, s1), (_, m2_, s2) = self._range(0, half), self._range(d - half, d)
        return _rhat_from_moments(n1, np.concatenate([m1, m2_]), np.concatenate([s1, s2]))


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
