"""Diagnostics of finished draws: ArviZ conversion, fast ESS, calibration against a truth.

ArviZ's default R-hat is the rank-normalised split R-hat (Vehtari et al. 2021); the classic
Gelman-Rubin R-hat of the paper's stopping rule is :mod:`bayesreg.sampling.convergence`.
:func:`coverage` checks the calibration of credible intervals against a synthetic truth.
:func:`sampler_health` gives the gradient kernels' per-chain checks that Stan prints
(divergent transitions, trajectories cut at the maximum tree depth, E-BFMI).
:func:`arviz_fast_ess` (from :mod:`bayesreg.sampling.convergence`, where the samplers' stop rule
uses it too) runs ArviZ's ESS with the end of Geyer's initial sequence found in one
vectorised search instead of ArviZ's Python loop over lags.
"""

from __future__ import annotations


import numpy as np

from bayesreg.sampling.convergence import arviz_fast_ess, geyer_ess

__all__ = ["coverage", "to_datatree", "group_draws", "contraction", "IDENTIFIED_MIN", "EDGE", "geyer_ess",
           "arviz_fast_ess", "sampler_health", "EBFMI_MIN", "normaliser_note"]


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


IDENTIFIED_MIN = 0.5
"""Contraction below which a quantity is reported as not identified by the images: the data
removed less than half of its prior variance (Betancourt, *Calibrating model-based
inferences and decisions*, arXiv:1803.08393, 2018)."""

EDGE = 0.01
"""Fraction of a prior's support at either end within which a posterior median counts as on
the prior's edge (:func:`contraction`'s ``at_prior_edge``)."""


def _beta_moments(a, b, r1, r2, fn):
    """Mean and variance of ``fn(r1 + (r2 - r1) X)``, ``X ~ Beta(a, b)`` (SciPy quadrature)."""
    from scipy import stats

    d = stats.beta(a, b)
    m = d.expect(lambda x: fn(r1 + (r2 - r1) * x))
    return m, d.expect(lambda x: (fn(r1 + (r2 - r1) * x) - m) ** 2)


def contraction(layout, priors, phi, *, groups: int = 16, phi_true=None) -> dict:
    """How far the images moved each elastic parameter and ratio from its prior.

    ``contraction = 1 - posterior variance / prior variance`` on the scale the sampler moves
    in: the logit of each free parameter's position in its prior support
    (``logit((phi - r1) / (r2 - r1))``, whose prior variance under ``Beta(a, b)`` is
    ``psi'(a) + psi'(b)``) and the log of each group's ``lam/mu`` (prior variance
    ``var log lam + var log mu`` of the independent scaled Beta priors, a fixed parameter
    contributing 0; SciPy quadrature).  1: the data fixed it; 0: the posterior is the
    prior; negative: wider than the prior (a chain stuck far out, or too few draws).

    Parameters
    ----------
    layout : bayesreg.model.parameters.ParamLayout
    priors : bayesreg.model.parameters.BetaPriors
        ``a, b, r1, r2``, each ``(n_free,)``.
    phi : (C, D, n_free) array_like
        Draws of the free parameters (natural scale).
    groups : int
        Ratios of at most this many groups.
    phi_true : (n_free,) array_like, optional
        The free parameters' truths (a synthetic case made by the model): each free
        parameter's entry then also says whether its truth lies in that outer 1%
        (``truth_at_prior_edge``), where a posterior on the edge is the prior's support,
        not a misfit.

    Returns
    -------
    dict
        ``{"lam_gm": {...}, ..., "ratio_csf": {...}, ...}``, each with ``scale`` (``"logit"``
        or ``"log"``), ``prior_sd`` and ``posterior_sd`` on that scale, ``contraction`` and
        ``identified`` (``contraction >= IDENTIFIED_MIN``); a free parameter's also
        ``at_prior_edge``: its posterior median lies in the outer ``EDGE`` (1%) of its prior
        support at either end (the data push it onto the prior's edge, as a misfit the model
        cannot make pays itself with extreme stiffness).

    Raises
    ------
    ValueError
        ``phi`` not ``(C, D, n_free)``, or ``phi_true`` not ``(n_free,)``.
    """
    from scipy.special import polygamma

    phi = np.asarray(phi, np.float64)
    a, b, r1, r2 = (np.asarray(v, np.float64) for v in priors)
    if phi.ndim != 3 or phi.shape[-1] != len(layout.free):
        raise ValueError(f"phi must be (C, D, {len(layout.free)}), got {phi.shape}")
    lo = np.maximum(r1, 0.0)
    flat = phi.reshape(-1, phi.shape[-1])
    if phi_true is not None:
        phi_true = np.asarray(phi_true, np.float64)
        if phi_true.shape != (len(layout.free),):
            raise ValueError(f"phi_true must be ({len(layout.free)},), got {phi_true.shape}")

    def on_edge(x):  # positions in the support, [0, 1]
        return bool(x < EDGE or x > 1.0 - EDGE)

    def entry(scale, prior_var, post_var):
        c = 1.0 - post_var / prior_var if prior_var > 0 else float("nan")
        return {"scale": scale, "prior_sd": float(np.sqrt(prior_var)),
                "posterior_sd": float(np.sqrt(post_var)), "contraction": float(c),
                "identified": bool(c >= IDENTIFIED_MIN)}

    out = {}
    for k, name in enumerate(layout.free_names):
        x = np.clip((flat[:, k] - lo[k]) / (r2[k] - lo[k]), 1e-300, 1.0 - 1e-16)
        out[name] = entry("logit", float(polygamma(1, a[k]) + polygamma(1, b[k])),
                          float(np.var(np.log(x) - np.log1p(-x))))
        out[name]["at_prior_edge"] = on_edge(float(np.median(x)))
        if phi_true is not None:
            out[name]["truth_at_prior_edge"] = on_edge((phi_true[k] - lo[k]) / (r2[k] - lo[k]))
    for g, gname in enumerate(layout.group_names[:groups]):
        prior_var, log_ratio = 0.0, 0.0
        for sign, p in ((1.0, "lam"), (-1.0, "mu")):
            k = next((k for k, (pk, gk) in enumerate(layout.free) if (pk, gk) == (p, g)), None)
            if k is None:
                continue  # fixed: no variance
            prior_var += _beta_moments(a[k], b[k], lo[k], r2[k], np.log)[1]
            log_ratio = log_ratio + sign * np.log(flat[:, k])
        if prior_var > 0:
            out[f"ratio_{gname}"] = entry("log", prior_var, float(np.var(log_ratio)))
    return out


EBFMI_MIN = 0.3
"""E-BFMI below which a chain's momentum resampling explores the energy too slowly
(Betancourt, *A conceptual introduction to Hamiltonian Monte Carlo*, arXiv:1701.02434,
2017, Sec. 6.1; Stan's and ArviZ's threshold)."""


def sampler_health(divergences, *, steps_per_draw: int = 1, tree_depth=None,
                   max_tree_depth: int | None = None, energy=None,
                   skull_barrier_mm: float = 0.0) -> dict:
    """Per-chain checks of a gradient kernel's draws, as Stan reports them after sampling.

    A divergent transition (an energy error above the kernel's threshold, or a trajectory
    that met ``-inf``: the skull's hard constraint, a failed solve) means the step size is
    too large for some region, which the chain then under-visits: its means may be biased
    however well R-hat and ESS look.  A trajectory cut at ``max_tree_depth`` means NUTS
    stopped before its U-turn: a correct but slow chain (the step size is small for the
    posterior's extent).  E-BFMI (the energy's lag-1 change against its spread, from
    :func:`arviz_stats.bfmi`) below :data:`EBFMI_MIN` means momentum resampling cannot move
    the chain through the energy levels the posterior spans (heavy tails, a funnel).

    Parameters
    ----------
    divergences : (C, D) array_like of int
        Divergent transitions per recorded draw (with thinning, per interval of
        ``steps_per_draw`` transitions).
    steps_per_draw : int
        Transitions per recorded draw (the thinning).
    tree_depth : (C, D) array_like of int, optional
        NUTS's tree depth (trajectory doublings) of each recorded draw's transition.
    max_tree_depth : int, optional
        The kernel's maximum tree depth (needed with ``tree_depth``).
    energy : (C, D) array_like, optional
        The Hamiltonian at each recorded draw; E-BFMI is skipped if it is absent or not
        finite.
    skull_barrier_mm : float
        The run's ``model.skull_barrier_mm``: the divergence line suggests the barrier only
        where it is off (0); with it on, divergences come from nodes pressed against the
        skull, and the line says to check for them.

    Returns
    -------
    dict
        ``divergent_fraction`` (per chain: divergent transitions / transitions),
        ``max_depth_fraction`` (per chain, or ``None`` without ``tree_depth``), ``e_bfmi``
        (per chain, or ``None``) and ``warnings``: one plain line per failed check, naming
        the chains (empty when all pass).

    Raises
    ------
    ValueError
        ``divergences`` not 2-D, another array of another shape, or ``tree_depth`` without
        ``max_tree_depth``.

    References
    ----------
    Stan Development Team, *Stan Reference Manual*, "Diagnostic information" (divergent
    transitions, maximum tree depth, E-BFMI); Betancourt (2017), Sec. 6.
    """
    div = np.asarray(divergences)
    if div.ndim != 2:
        raise ValueError(f"divergences must be (chains, draws), got shape {div.shape}")
    n = div.shape[1] * max(int(steps_per_draw), 1)
    frac = div.sum(axis=1) / max(n, 1)
    out = {"divergent_fraction": [float(f) for f in frac], "max_depth_fraction": None,
           "e_bfmi": None, "warnings": []}
    warn = out["warnings"]

    def chains(mask):
        idx = np.flatnonzero(mask)
        return ("chain " if len(idx) == 1 else "chains ") + ", ".join(str(c) for c in idx)

    if div.sum() > 0:
        worst = int(np.argmax(frac))
        advice = ("a smooth skull barrier: model.skull_barrier_mm" if not skull_barrier_mm > 0
                  else "with the skull barrier on: nodes pressed against the skull")
        n_div = int(div.sum())
        warn.append(f"{n_div} divergent transition{'s' if n_div != 1 else ''} ({chains(frac > 0)}; up to "
                    f"{frac[worst]:.1%} in chain {worst}): the chains under-visit a region, means "
                    f"may be biased (a larger sampler.target_acceptance; {advice})")
    if tree_depth is not None:
        depth = np.asarray(tree_depth)
        if depth.shape != div.shape:
            raise ValueError(f"tree_depth must have the shape of divergences {div.shape}, got {depth.shape}")
        if max_tree_depth is None:
            raise ValueError("tree_depth needs max_tree_depth")
        sat = np.mean(depth >= max_tree_depth, axis=1)
        out["max_depth_fraction"] = [float(f) for f in sat]
        if np.any(sat > 0):
            worst = int(np.argmax(sat))
            warn.append(f"trajectories cut at the maximum tree depth {max_tree_depth} in "
                        f"{chains(sat > 0)} (up to {sat[worst]:.1%} of draws, chain {worst}): "
                        "correct but slow (a larger sampler.max_tree_depth)")
    if energy is not None:
        e = np.asarray(energy, np.float64)
        if e.shape != div.shape:
            raise ValueError(f"energy must have the shape of divergences {div.shape}, got {e.shape}")
        if e.shape[1] >= 2 and np.all(np.isfinite(e)):
            from arviz_stats import bfmi

            with np.errstate(divide="ignore", invalid="ignore"):  # a constant energy: NaN
                b = np.asarray(bfmi(e), np.float64).reshape(-1)
            out["e_bfmi"] = [float(x) for x in b]
            low = ~(b >= EBFMI_MIN)  # NaN counts as low
            if np.any(low):
                warn.append(f"E-BFMI below {EBFMI_MIN} in {chains(low)} (lowest "
                            f"{np.nanmin(b) if np.any(np.isfinite(b)) else float('nan'):.2f}): "
                            "momentum resampling explores the energy slowly (heavy tails)")
    return out


def normaliser_note(info: dict) -> str | None:
    """The bias a run's model brings, for a run (``run.json``) with the paper's unnormalised
    elastic prior and free elastic parameters; ``None`` otherwise."""
    model = (info.get("config") or {}).get("model") or {}
    which = model.get("prior_normaliser", (info.get("sampler") or {}).get("prior_normaliser"))
    free = [k for k in (info.get("identification") or {}) if k.startswith(("lam", "mu"))]
    if which != "paper" or not (free or (info.get("errors") or {}).get("ratio")):
        return None
    return ("the paper's unnormalised elastic prior (model.prior_normaliser: paper, Eq. 12 as "
            "published) pulls lam and mu toward soft tissue: on bayesreg calibrate's problem its "
            "90% intervals held 0-1% of the lam/mu truths, against 89-93% with "
            "model.prior_normaliser: exact (docs: Is the posterior calibrated?)")
