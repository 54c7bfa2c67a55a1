"""Convergence diagnostics: the classic Gelman-Rubin R-hat and ArviZ conversion.

The paper (Sec. 3.2) stops when the *scale reduction* of every scalar estimand is below
1.2, the classic potential scale reduction factor of Gelman et al., *Bayesian Data
Analysis* (2nd ed., Sec. 11.6), ref. [12] of the paper.  ArviZ's default R-hat is the
rank-normalised split R-hat (Vehtari et al. 2021), which is stricter; reports give both.
"""

from __future__ import annotations

import numpy as np

__all__ = ["gelman_rubin", "to_datatree"]


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
