"""The run directory's figures: traces and marginals of the elastic parameters, uncertainty maps.

Drawn with Matplotlib's object-oriented API (:class:`matplotlib.figure.Figure`, no pyplot:
no global state is touched).
"""

from __future__ import annotations

import numpy as np

from bayesreg.data.images import Image
from bayesreg.rundir import RunDirectory

__all__ = ["plot_parameters", "parameter_figures", "plot_uncertainty", "plot_brain_map",
           "most_uncertain_voxel", "rank_histograms"]


def plot_parameters(run_dir: RunDirectory, tree, names, truth_ratio, *, nodes=None, u_true_b=None):
    """Write ``trace.png`` and ``marginals.png`` (:func:`parameter_figures`) to ``run_dir``."""
    for fig, name in zip(parameter_figures(tree, names, truth_ratio, nodes=nodes, u_true_b=u_true_b),
                         ("trace.png", "marginals.png")):
        fig.savefig(run_dir.file(name), dpi=90)


def parameter_figures(tree, names, truth_ratio, *, nodes=None, u_true_b=None):
    """The figures of ``trace.png`` and ``marginals.png``.

    ``trace.png``: per group (at most six), the ``lam/mu`` ratio's traces on a log axis, its
    rank plot (the histogram of each chain's ranks among all draws: flat when the chains
    agree; Vehtari et al., Bayesian Analysis 16(2), 2021) and its marginal on a log axis,
    the truth dashed.  ``marginals.png``: the three displacement components of the boundary
    node with the largest posterior spread, named by its index and rest position, its true
    displacement dashed.

    Parameters
    ----------
    tree : xarray.DataTree
        The run's posterior (``ratio`` ``(chain, draw, group)``, ``u_b``
        ``(chain, draw, node, axis)`` with coordinate ``node``, mesh node indices).
    names : sequence of str
        Group names.
    truth_ratio : sequence of float or None
        True ratio per group (first six).
    nodes : (N, 3) ndarray, optional
        Rest positions of the mesh nodes, world mm (RAS).
    u_true_b : (nb, 3) ndarray, optional
        True displacement of the boundary nodes, mm.

    Returns
    -------
    trace, marginals : matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, NullFormatter
    from scipy.stats import rankdata

    plain = FuncFormatter(lambda v, _: f"{v:g}")  # 2, 5, 10, 20 rather than 2x10^0

    ratio = np.asarray(tree.posterior["ratio"].values)  # (C, D, G)
    n_chains, n_draws = ratio.shape[:2]
    n = min(ratio.shape[-1], 6)
    fig = Figure(figsize=(13, 2.3 * n))
    axes = fig.subplots(n, 3, squeeze=False, gridspec_kw={"width_ratios": [2.2, 1, 1.3]})
    bins = int(np.clip(n_draws // 10, 5, 20))  # rank-plot bins
    for k in range(n):
        x = np.clip(ratio[..., k], np.finfo(float).tiny, None)
        ranks = rankdata(x.ravel()).reshape(x.shape)
        edges = np.geomspace(x.min(), x.max(), 41) if x.max() > x.min() else 40
        for c in range(n_chains):
            axes[k, 0].plot(x[c], lw=0.6, label=f"chain {c}")
            axes[k, 1].hist(ranks[c], bins=np.linspace(0.5, x.size + 0.5, bins + 1),
                            histtype="step")
            axes[k, 2].hist(x[c], bins=edges, histtype="step", density=True)
        axes[k, 1].axhline(x.size / n_chains / bins, color="k", ls=":", lw=1)
        axes[k, 0].set_yscale("log")
        axes[k, 2].set_xscale("log")
        for axis in (axes[k, 0].yaxis, axes[k, 2].xaxis):  # minor labels only within a decade
            axis.set_major_formatter(plain)
            axis.set_minor_formatter(plain if x.max() < 10 * x.min() else NullFormatter())
        axes[k, 0].set_ylabel(f"lam/mu {names[k]}")
        axes[k, 1].set_yticks([])
        if truth_ratio is not None:
            axes[k, 0].axhline(truth_ratio[k], color="k", ls="--", lw=1)
            axes[k, 2].axvline(truth_ratio[k], color="k", ls="--", lw=1, label="truth")
    axes[0, 0].legend(fontsize=7)
    axes[0, 0].set_title("traces (log scale)")
    axes[0, 1].set_title("rank plot (flat: chains agree)")
    axes[0, 2].set_title("marginals (log scale)")
    if truth_ratio is not None:
        axes[0, 2].legend(fontsize=7)
    axes[-1, 0].set_xlabel("draw (thinned)")
    axes[-1, 1].set_xlabel("rank among all draws")
    axes[-1, 2].set_xlabel("lam/mu")
    fig.tight_layout()
    trace = fig

    ub = np.asarray(tree.posterior["u_b"].values)  # (C, D, nb, 3)
    sd = ub.reshape(-1, ub.shape[2], 3).std(0).sum(1)
    b = int(np.argmax(sd))
    node = int(tree.posterior["node"][b])
    fig = Figure(figsize=(11, 3.2))
    axes = fig.subplots(1, 3)
    for a, ax in enumerate(axes):
        x = ub[:, :, b, a]
        lo, hi = float(x.min()), float(x.max())
        if hi - lo <= 1e-9 * max(1.0, abs(hi)):  # (draws equal to rounding: one bin a mm wide)
            lo, hi = lo - 0.5, hi + 0.5
        edges = np.linspace(lo, hi, 41)  # shared by the chains, so their shapes compare
        for c in range(ub.shape[0]):
            ax.hist(x[c], bins=edges, histtype="step", density=True, label=f"chain {c}")
        if u_true_b is not None:
            ax.axvline(u_true_b[b, a], color="k", ls="--", lw=1, label="truth")
        ax.set_xlabel(f"u_{'xyz'[a]} (mm)")
    axes[0].legend(fontsize=7)
    where = "" if nodes is None else " at ({:.1f}, {:.1f}, {:.1f}) mm RAS".format(*nodes[node])
    fig.suptitle(f"the most uncertain boundary node: mesh node {node}{where}")
    fig.tight_layout()
    return trace, fig


def most_uncertain_voxel(spread, mask, *, sigma_vox: float = 2.0) -> np.ndarray:
    """The voxel at the centre of the most uncertain region: the maximum of ``spread``
    smoothed by a Gaussian of ``sigma_vox`` voxels, inside ``mask`` (a single outlying voxel
    does not win over a region).

    Parameters
    ----------
    spread : (I, J, K) ndarray
        A per-voxel spread (IQR or sd of ``|u|``, mm).
    mask : (I, J, K) bool ndarray
        Where to look (the brain); the centre of the grid if empty.

    Returns
    -------
    (3,) int ndarray
        Voxel index.
    """
    from scipy.ndimage import gaussian_filter

    if not mask.any():
        return np.array(spread.shape[:3]) // 2
    w = gaussian_filter(mask.astype(np.float64), sigma_vox)
    smooth = gaussian_filter(np.where(mask, spread, 0.0), sigma_vox) / np.maximum(w, 1e-12)
    return np.array(np.unravel_index(np.argmax(np.where(mask, smooth, -np.inf)), mask.shape))


def plot_uncertainty(run_dir: RunDirectory, f: Image, iqr, labels: Image):
    """``uncertainty.png``: IQR of ``|u|`` over ``f`` on three orthogonal slices through the
    most uncertain region (:func:`most_uncertain_voxel`), marked by a cross.

    Parameters
    ----------
    run_dir : RunDirectory
    f : Image
        The fixed image, ``(I, J, K)``.
    iqr : (I, J, K) ndarray
        Interquartile range of ``|u|`` per voxel, mm.
    labels : Image
        Tissue labels on ``f``'s grid (the brain: 1, 2, 3).
    """
    plot_brain_map(run_dir, "uncertainty.png", f, iqr, labels, colorbar="IQR of |u| (mm)",
                   title="posterior uncertainty of the displacement magnitude over f, through "
                   "the most uncertain region")


def plot_brain_map(run_dir: RunDirectory, name: str, f: Image, values, labels: Image, *,
                   colorbar: str, title: str):
    """``name``: a map ``values`` ``(I, J, K)`` over ``f`` (brain voxels only) on three
    orthogonal slices through its largest brain value (:func:`most_uncertain_voxel`), marked
    by a cross; ``title`` is followed by that voxel's index."""
    from matplotlib.figure import Figure

    brain = np.isin(labels.data, (1, 2, 3))
    c = most_uncertain_voxel(values, brain)
    vmax = (float(np.quantile(values[brain], 0.99)) if brain.any() and values[brain].max() > 0
            else None)
    fig = Figure(figsize=(12, 4))
    axes = fig.subplots(1, 3)
    for ax, axis, view in zip(axes, range(3), ("sagittal", "coronal", "axial")):
        sl = [slice(None)] * 3
        sl[axis] = c[axis]
        img = np.asarray(f.data)[tuple(sl)].T
        shown = np.ma.masked_where(~brain[tuple(sl)].T, values[tuple(sl)].T)
        ax.imshow(img, cmap="gray", origin="lower")
        im = ax.imshow(shown, cmap="magma", alpha=0.7, origin="lower", vmin=0, vmax=vmax)
        rest = [c[i] for i in range(3) if i != axis]
        ax.plot(*rest, "+", color="cyan", ms=12, mew=1.5)
        ax.set_title(f"{view} slice {c[axis]}")
        ax.axis("off")
    fig.colorbar(im, ax=axes, shrink=0.8, label=colorbar)
    fig.suptitle(f"{title} (voxel {tuple(int(v) for v in c)})")
    fig.savefig(run_dir.file(name), dpi=90)


def rank_histograms(summary: dict, bins: int):
    """Rank histograms of a calibration (:func:`bayesreg.experiments.calibration.summarise`): one panel per
    quantity and one for the boundary coordinates pooled, each with the count a uniform
    histogram expects and its 99% band (binomial), and the chi-square p in the title
    (Talts et al. 2018, Fig. 2).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure
    from scipy.stats import binom

    rows = dict(summary["quantities"], u_b=summary["u_b"])
    n = len(rows)
    ncol = min(4, n)
    nrow = -(-n // ncol)
    fig = Figure(figsize=(3.2 * ncol, 2.6 * nrow), layout="constrained")
    for k, (name, row) in enumerate(rows.items()):
        ax = fig.add_subplot(nrow, ncol, k + 1)
        counts = np.asarray(row["histogram"])
        total = counts.sum()
        lo, hi = binom.interval(0.99, total, 1.0 / bins)
        ax.axhspan(lo, hi, color="0.85", zorder=0)
        ax.axhline(total / bins, color="0.4", lw=1)
        ax.bar(np.arange(bins), counts, width=0.9, color="C0")
        pooled = " (pooled)" if name == "u_b" else ""
        ax.set_title(f"{name}: p = {row['p']:.2g}{pooled}", fontsize=9)
        ax.set_xticks([0, bins - 1], ["low", "high"])
        ax.tick_params(labelsize=8)
    fig.suptitle(f"ranks of the truths among the posterior draws, {summary['replicas']} replicas "
                 "(grey: 99% band of a uniform histogram)", fontsize=9)
    return fig
