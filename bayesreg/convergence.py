"""The classic Gelman-Rubin R-hat, batch and running (the samplers' stopping rule).

The paper (Sec. 3.2) stops when the *scale reduction* of every scalar estimand is below
1.2, the classic potential scale reduction factor of Gelman et al., *Bayesian Data
Analysis* (2nd ed., Sec. 11.6), ref. [12] of the paper.  :class:`RunningGelmanRubin` gives
the same statistic for draws that arrive chunk by chunk, from per-chunk moments, at a cost
per check that does not grow with the draws.  The rank-normalised split R-hat of Vehtari et
al. (2021), stricter, is ArviZ's (:mod:`bayesreg.diagnostics`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["gelman_rubin", "RunningGelmanRubin"]


def gelman_rubin(draws, *, split: bool = False, block: int = 64) -> np.ndarray:
    """Classic potential scale reduction factor per estimand.

    Parameters
    ----------
    draws : (C, D, ...) array_like
        ``C >= 2`` chains of ``D >= 2`` draws.
    split : bool
        Split every chain into halves first (BDA 3rd ed., Sec. 11.4): detects a trend that
        all chains share, which the whole-chain statistic cannot see.
    block : int
        Estimands processed at once (memory ``C x D x block`` doubles).

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
    x = np.asarray(draws)
    if x.ndim < 2 or x.shape[0] < 2 or x.shape[1] < (4 if split else 2):
        raise ValueError(f"need at least 2 chains x {4 if split else 2} draws, got shape {x.shape}")
    c, d, rest = x.shape[0], x.shape[1], x.shape[2:]
    x = x.reshape(c, d, -1)  # a view where the trailing axes allow it
    out = np.empty(x.shape[2])
    for a in range(0, x.shape[2], block):  # estimands in blocks: memory C x D x block
        xb = np.asarray(x[:, :, a:a + block], dtype=np.float64)
        if split:
            half = d // 2
            xb = np.concatenate([xb[:, :half], xb[:, d - half:]], axis=0)
        out[a:a + block] = _rhat_from_moments(*_moments(xb))
    return out.reshape(rest)


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
    would cost a concatenation and a pass over every draw, growing with the run.

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
