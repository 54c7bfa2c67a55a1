"""The elastic parameters: their layout, scaled Beta priors and unconstrained coordinates.

The Lamé parameters live on groups of elements: one group (``elastic: uniform``), one per
tissue (CSF, GM, WM) or one per element.  Some can be held fixed to pin the scale (paper
Sec. 3.3: ``mu_GM = 1``); the others are the free parameters ``phi`` ``(n_free,)``, in the
order of :attr:`ParamLayout.free`.  Each free parameter has a Beta(A, B) prior scaled to
``[r1, r2]`` (paper Sec. 3.1; NumPyro's Beta).  Gradient kernels move ``eta``, the logit of
``phi`` on its support (:func:`from_unconstrained`, with the log-Jacobian).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import numpyro.distributions as dist

from bayesreg._checks import check_last_axis

__all__ = ["ParamLayout", "BetaPriors", "beta_priors", "log_prior", "from_unconstrained",
           "to_unconstrained"]


class ParamLayout(NamedTuple):
    """Host-side description of the elastic parameters (names for reports).

    Attributes
    ----------
    group_names : tuple of str
        ``("all",)``, ``("csf", "gm", "wm")`` or ``("e0", ...)``.
    free : tuple of (str, int)
        ``("lam" | "mu", group)`` of each free parameter, in ``phi`` order.
    fixed : tuple of (str, int, float)
        Parameters held fixed.
    """

    group_names: tuple
    free: tuple
    fixed: tuple

    @property
    def free_names(self) -> list[str]:
        return [f"{p}_{self.group_names[g]}" for p, g in self.free]


class BetaPriors(NamedTuple):
    """Scaled Beta priors of the free parameters, each ``(n_free,)``: ``phi = r1 + (r2 - r1) x``
    with ``x ~ Beta(a, b)``."""

    a: jax.Array
    b: jax.Array
    r1: jax.Array
    r2: jax.Array

    @property
    def n_free(self) -> int:
        return self.a.shape[0]


def beta_priors(prior, layout: ParamLayout) -> BetaPriors:
    """The priors of ``layout``'s free parameters from a mapping of prior tuples.

    Parameters
    ----------
    prior : dict
        ``{"lam": (A, B, r1, r2), "mu": ...}`` (one prior for every group) or
        ``{"lam": [(A, B, r1, r2) per group], ...}``.
    layout : ParamLayout

    Raises
    ------
    ValueError
        ``prior`` not a mapping with an entry for each kind of free parameter, an entry of
        the wrong shape, or one without finite ``A, B > 0`` and ``0 <= r1 < r2 < inf`` (the
        message names the parameter).
    """
    n_groups = len(layout.group_names)
    if not isinstance(prior, Mapping):
        raise ValueError(f"prior must be a dict {{'lam': (A, B, r1, r2), 'mu': ...}}, got "
                         f"{type(prior).__name__}")
    entries = {}
    for p in sorted({p for p, _ in layout.free}):
        if p not in prior:
            needed = next(n for n, (q, _) in zip(layout.free_names, layout.free) if q == p)
            raise ValueError(f"prior has no {p!r} entry (needed by the free parameter {needed}); "
                             f"expected {{'lam': (A, B, r1, r2), 'mu': (A, B, r1, r2)}}")
        try:
            pr = np.asarray(prior[p], dtype=np.float64)
        except (TypeError, ValueError):
            pr = None
        if pr is None or pr.shape not in ((4,), (n_groups, 4)):
            got = "a ragged or non-numeric sequence" if pr is None else f"shape {pr.shape}"
            raise ValueError(f"prior[{p!r}] must be (A, B, r1, r2) or one such tuple per group, "
                             f"shape ({n_groups}, 4); got {got}")
        entries[p] = pr
    rows = np.array([entries[p] if entries[p].ndim == 1 else entries[p][g] for p, g in layout.free],
                    dtype=np.float64).reshape(-1, 4)
    a, b, r1, r2 = rows.T
    ok = np.all(np.isfinite(rows), axis=1) & (a > 0) & (b > 0) & (r1 >= 0) & (r1 < r2)
    if not np.all(ok):
        k = int(np.argmin(ok))
        raise ValueError(f"invalid Beta prior of {layout.free_names[k]}: need finite A, B > 0 and "
                         f"0 <= r1 < r2 < inf, got (A, B, r1, r2) = "
                         f"({', '.join(f'{v:g}' for v in rows[k])})")
    return BetaPriors(*(jnp.asarray(c) for c in (a, b, r1, r2)))


def log_prior(prior: BetaPriors, phi):
    """``(sum of the log prior densities, whether every parameter is inside its support)``.

    A parameter outside ``(r1, r2)`` or not positive gives ``inside = False`` (its density is
    evaluated at the clipped value, so the sum stays finite: the caller rejects).
    """
    x = (phi - prior.r1) / (prior.r2 - prior.r1)
    inside = (x > 0) & (x < 1) & (phi > 0)
    xs = jnp.clip(x, 1e-12, 1 - 1e-12)
    lp = dist.Beta(prior.a, prior.b).log_prob(xs) - jnp.log(prior.r2 - prior.r1)
    return jnp.sum(lp), jnp.all(inside)


def _support(prior: BetaPriors):
    lo = jnp.maximum(prior.r1, 0.0)
    return lo, prior.r2 - lo


def from_unconstrained(prior: BetaPriors, eta):
    """Free parameters from their unconstrained values, with the log-Jacobian.

    ``phi = r1 + (r2 - r1) sigmoid(eta)`` maps the real line onto the prior support
    ``(r1, r2)`` of each parameter (``r1 >= 0``), so every ``eta`` is a valid parameter.

    Parameters
    ----------
    prior : BetaPriors
    eta : (..., n_free) array

    Returns
    -------
    phi : (..., n_free) array
    log_jac : (...) array
        ``sum log |d phi / d eta|``: add it to a density over ``phi`` to get the density
        over ``eta``.

    Raises
    ------
    ValueError
        ``eta`` not of shape ``(..., n_free)``.
    """
    check_last_axis("eta", eta, prior.n_free, "the unconstrained free elastic parameters")
    lo, width = _support(prior)
    phi = lo + width * jax.nn.sigmoid(eta)
    log_jac = jnp.sum(jnp.log(width) + jax.nn.log_sigmoid(eta) + jax.nn.log_sigmoid(-eta), axis=-1)
    return phi, log_jac


def to_unconstrained(prior: BetaPriors, phi):
    """Inverse of :func:`from_unconstrained` (``phi`` ``(..., n_free)`` strictly inside the
    prior support).  Raises ``ValueError`` on ``phi`` not of shape ``(..., n_free)``."""
    check_last_axis("phi", phi, prior.n_free, "the free elastic parameters")
    lo, width = _support(prior)
    x = (jnp.asarray(phi) - lo) / width
    return jnp.log(x) - jnp.log1p(-x)
