"""The run directory's figures: traces and marginals of the elastic parameters, uncertainty maps.

Drawn with Matplotlib's object-oriented API on the Agg canvas (no pyplot state is left
behind).
"""

from __future__ import annotations

import numpy as np

from bayesreg.images import Image
from bayesreg.rundir import RunDirectory

__all__ = ["plot_parameters", "plot_uncertainty"]


def plot_parameters(run_dir: RunDirectory, tree, names, truth_ratio):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ratio = np.asarray(tree.posterior["ratio"].values)  # (C, D, G)
    n = min(ratio.shape[-1], 6)
    fig, axes = plt.subplots(n, 2, figsize=(10, 2.2 * n), squeeze=False)
    for k in range(n):
        for c in range(ratio.shape[0]):
            axes[k, 0].plot(ratio[c, :, k], lw=0.6, label=f"chain {c}")
            axes[k, 1].hist(ratio[c, :, k], bins=40, histtype="step", density=True)
        axes[k, 0].set_ylabel(f"lam/mu {names[k]}")
        if truth_ratio is not None:
            axes[k, 0].axhline(truth_ratio[k], color="k", ls="--", lw=1)
            axes[k, 1].axvline(truth_ratio[k], color="k", ls="--", lw=1, label="truth")
    axes[0, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("draw (thinned)")
    axes[-1, 1].set_xlabel("lam/mu")
    fig.tight_layout()
    fig.savefig(run_dir.file("trace.png"), dpi=90)
    plt.close(fig)

    ub = np.asarray(tree.posterior["u_b"].values)  # (C, D, nb, 3)
    sd = ub.reshape(-1, ub.shape[2], 3).std(0).sum(1)
    node = int(np.argmax(sd))
    fig, axes = plt.subplots(1, 3, figsize=(11, 3))
    for a, ax in enumerate(axes):
        for c in range(ub.shape[0]):
            ax.hist(ub[c, :, node, a], bins=40, histtype="step", density=True)
        ax.set_xlabel(f"u_{'xyz'[a]} (mm), boundary node {int(tree.posterior['node'][node])}")
    fig.suptitle("marginal posterior of the most uncertain boundary node")
    fig.tight_layout()
    fig.savefig(run_dir.file("marginals.png"), dpi=90)
    plt.close(fig)


def plot_uncertainty(run_dir: RunDirectory, f: Image, iqr, labels: Image):
    """``uncertainty.png``: IQR of ``|u|`` over ``f`` on three orthogonal slices."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    brain = np.isin(labels.data, (1, 2, 3))
    c = np.round(np.argwhere(brain).mean(0)).astype(int) if brain.any() else np.array(f.data.shape) // 2
    vmax = float(np.quantile(iqr[brain], 0.99)) if brain.any() and iqr[brain].max() > 0 else None
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    for ax, axis, name in zip(axes, range(3), ("sagittal", "coronal", "axial")):
        sl = [slice(None)] * 3
        sl[axis] = c[axis]
        img = np.asarray(f.data)[tuple(sl)].T
        unc = np.ma.masked_where(~brain[tuple(sl)].T, iqr[tuple(sl)].T)
        ax.imshow(img, cmap="gray", origin="lower")
        im = ax.imshow(unc, cmap="magma", alpha=0.7, origin="lower", vmin=0, vmax=vmax)
        ax.set_title(f"{name} slice {c[axis]}")
        ax.axis("off")
    fig.colorbar(im, ax=axes, shrink=0.8, label="IQR of |u| (mm)")
    fig.suptitle("posterior uncertainty of the displacement magnitude over f")
    fig.savefig(run_dir.file("uncertainty.png"), dpi=90)
    plt.close(fig)
