"""When the chains stop: the samplers' stop rules and the R-hat and ESS they read.

Two rules (:class:`StopRule`):

* ``"rank"`` (the default): the rank-normalised split R-hat of every scalar estimand at
  most 1.01 and its bulk and tail effective sample sizes at least 400 (Vehtari, Gelman,
  Simpson, Carpenter & Buerkner, *Rank-normalization, folding, and localization: an
  improved R-hat*, Bayesian Analysis 16(2), 2021; the defaults of ArviZ and Stan), by
  ArviZ (:func:`rank_figures`).  Rank-based, so the same on the sampler's log or logit
  scale as on the natural one.
* ``"paper"`` (Sec. 3.2): the classic Gelman-Rubin potential scale reduction factor of every
  estimand below 1.2 (Gelman et al., *Bayesian Data Analysis*, 2nd ed., Sec. 11.6, ref. [12]
  of the paper).  :class:`RunningGelmanRubin` gives it for draws that arrive chunk by
  chunk, from per-chunk moments, at a cost per check that does not grow with the draws.

:func:`arviz_fast_ess` runs ArviZ's ESS with the end of Geyer's initial positive sequence
found in one vectorised search (:func:`geyer_ess`) instead of ArviZ's Python loop over
lags: the same numbers, and the check of a long, slowly mixing run in a second instead of
minutes.
"""

from __future__ import annotations

import contextlib
from typing import NamedTuple

import numpy as np

__all__ = ["gelman_rubin", "RunningGelmanRubin", "StopRule", "STOP_RULES", "rank_figures",
           "geyer_ess", "arviz_fast_ess"]

STOP_RULES = ("rank", "paper")
"""The stop rules a sampler knows (:class:`StopRule`)."""


class StopRule(NamedTuple):
    """When a sampler stops (after ``min_draws``, at the latest at ``max_draws``).

    Attributes
    ----------
    kind : {"rank", "paper"}
        ``"rank"``: every estimand's rank-normalised split R-hat ``<= rhat_rank_max`` and its
        bulk and tail ESS ``>= ess_min``; ``"paper"``: every estimand's classic (or, with
        ``rhat_split``, split) Gelman-Rubin R-hat ``< rhat_threshold``.
    rhat_threshold : float
    rhat_split : bool
    rhat_rank_max : float
    ess_min : float
    """

    kind: str = "rank"
    rhat_threshold: float = 1.2
    rhat_split: bool = False
    rhat_rank_max: float = 1.01
    ess_min: float = 400.0

    def check(self) -> "StopRule":
        """The rule itself, or ``ValueError`` naming what is wrong."""
        if self.kind not in STOP_RULES:
            raise ValueError(f"stop rule must be one of {STOP_RULES}, got {self.kind!r}")
        if not self.rhat_threshold > 1.0 or not self.rhat_rank_max > 1.0:
            raise ValueError("R-hat thresholds must be > 1, got "
                             f"{self.rhat_threshold} and {self.rhat_rank_max}")
        if not self.ess_min > 0:
            raise ValueError(f"ess_min must be > 0, got {self.ess_min}")
        return self

    def met(self, classic: float, rank: float, bulk: float, tail: float) -> bool:
        """Whether figures (max classic R-hat, max rank-normalised R-hat, min bulk and tail
        ESS over the estimands; NaN where not computed) meet the rule."""
        if self.kind == "paper":
            return bool(classic < self.rhat_threshold)
        return bool(rank <= self.rhat_rank_max and bulk >= self.ess_min and tail >= self.ess_min)

    def describe(self) -> str:
        """The rule in words (``"rank-normalised R-hat <= 1.01, bulk and tail ESS >= 400"``)."""
        if self.kind == "paper":
            return f"{'split ' if self.rhat_split else ''}classic R-hat < {self.rhat_threshold:g}"
        return f"rank-normalised R-hat <= {self.rhat_rank_max:g}, bulk and tail ESS >= {self.ess_min:g}"


def rank_figures(draws) -> tuple[float, float, float]:
    """The worst rank-normalised split R-hat and the smallest bulk and tail ESS over the
    estimands of ``draws``, by ArviZ (``arviz_stats``'s array functions with
    :func:`geyer_ess`).

    Parameters
    ----------
    draws : (C, D, K) array_like
        Chains x draws x estimands; at least 2 chains and 4 draws.

    Returns
    -------
    rhat_max, ess_bulk_min, ess_tail_min : float
        Over the estimands that vary (a constant estimand has no R-hat); the tail ESS is
        that of the 5% and 95% quantiles (Vehtari et al.'s; ``az.summary`` would take its
        quantiles from ``rcParams["stats.ci_prob"]``, 11% and 89% by default).
    """
    x = np.moveaxis(np.asarray(draws, np.float64), -1, 0)  # (K, C, D)
    stats = _array_stats()
    with np.errstate(divide="ignore", invalid="ignore"):  # a chain that never moved: inf, NaN
        rhat = np.asarray(stats.rhat(x, method="rank"), np.float64)
        bulk = np.asarray(stats.ess(x, method="bulk"), np.float64)
        tail = np.asarray(stats.ess(x, method="tail", prob=(0.05, 0.95)), np.float64)
    varies = np.ptp(x.reshape(x.shape[0], -1), axis=1) > 0
    if not varies.any():
        return float("nan"), float("nan"), float("nan")
    # NaN (a chain that never moved) counts as failing: max/min propagate it
    return float(np.max(rhat[varies])), float(np.min(bulk[varies])), float(np.min(tail[varies]))


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


def _array_stats():
    """ArviZ's array functions with :func:`geyer_ess` (ArviZ's own where it cannot be
    replaced)."""
    global _BACKEND
    if _BACKEND is None:
        _BACKEND = _fast_backend() or False
    if _BACKEND:
        return _BACKEND.array_stats
    from arviz_stats.base import array_stats  # pragma: no cover - another ArviZ layout

    return array_stats  # pragma: no cover


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
