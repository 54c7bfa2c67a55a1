"""The paper's figures from finished runs (Figs. 2-5) and an uncertainty map.

Built with the object-oriented Matplotlib API on the Agg canvas (no pyplot state); each
returns a :class:`matplotlib.figure.Figure`.  Units: world mm, divergence in mm/mm.
"""

from __future__ import annotations


import numpy as np
import scipy.ndimage as ndi

from bayesreg.outputs.plots import most_uncertain_voxel
from bayesreg.report.data import (
    SKULL_LABEL, TISSUE_COLORS, TISSUE_LABELS, TISSUE_NAMES, RunData, as_runs, true_ratio)

__all__ = ["divergence", "skull_distance", "skull_node", "skull_limits", "mesh_cut", "slice_index",
           "plot_dataset", "plot_errors", "plot_ratios", "plot_boundary_node", "plot_uncertainty"]


def divergence(u, affine) -> np.ndarray:
    """Divergence of a displacement field on an image grid, mm/mm.

    Central differences (``np.gradient``) along the voxel axes, mapped to world
    derivatives by the inverse of the affine's linear part (for a diagonal affine this is
    ``np.gradient`` with the voxel spacing).

    Parameters
    ----------
    u : (I, J, K, 3) array_like
        world-mm displacement (x, y, z components)
    affine : (4, 4) array_like
        voxel-to-world

    Returns
    -------
    (I, J, K) ndarray
    """
    u = np.asarray(u, np.float64)
    a_inv = np.linalg.inv(np.asarray(affine, np.float64)[:3, :3])  # d vox_a / d x_b
    div = np.zeros(u.shape[:3])
    for c in range(3):
        for a, g in enumerate(np.gradient(u[..., c])):
            if a_inv[a, c] != 0.0:
                div += g * a_inv[a, c]
    return div


def _voxel(affine, points) -> np.ndarray:
    inv = np.linalg.inv(np.asarray(affine, np.float64))
    return np.asarray(points, np.float64) @ inv[:3, :3].T + inv[:3, 3]


def _nearest(volume, affine, points, outside):
    """Nearest-voxel lookup (as the sampler's hard constraint); ``outside`` off the grid."""
    idx = np.floor(_voxel(affine, points) + 0.5).astype(int)
    shape = np.array(volume.shape[:3])
    inside = np.all((idx >= 0) & (idx < shape), axis=-1)
    idc = np.clip(idx, 0, shape - 1)
    return np.where(inside, volume[idc[..., 0], idc[..., 1], idc[..., 2]], outside)


def skull_distance(labels, affine) -> np.ndarray | None:
    """Distance of every voxel centre to the nearest skull voxel (label 4), mm.

    ``scipy.ndimage.distance_transform_edt`` of ``labels != 4`` with the voxel spacing;
    None if the label map has no skull.

    Returns
    -------
    (I, J, K) ndarray or None
    """
    labels = np.asarray(labels)
    if not np.any(labels == SKULL_LABEL):
        return None
    spacing = np.linalg.norm(np.asarray(affine, np.float64)[:3, :3], axis=0)
    return ndi.distance_transform_edt(labels != SKULL_LABEL, sampling=spacing)


def skull_node(run: RunData) -> tuple[int, float | None]:
    """The boundary node whose true deformed position is closest to the skull.

    Returns
    -------
    b : int
        Index into ``run.boundary`` (mesh node ``run.boundary[b]``).
    distance : float or None
        :func:`skull_distance` interpolated (trilinear) at ``points + u_true`` of that node,
        mm; None when the label map has no skull, in which case ``b`` is the boundary node
        with the largest posterior sd.
    """
    dist = skull_distance(run.labels, run.affine)
    if dist is None:
        sd = run.u_b.reshape(-1, *run.u_b.shape[2:]).std(0).sum(1)
        return int(np.argmax(sd)), None
    x = run.points[run.boundary] + run.u_true[run.boundary]
    d = ndi.map_coordinates(dist, _voxel(run.affine, x).T, order=1, mode="nearest")
    b = int(np.argmin(d))
    return b, float(d[b])


def skull_limits(run: RunData, b: int, *, reach_mm: float = 30.0) -> np.ndarray:
    """Displacement at which one component alone takes boundary node ``b`` into the skull.

    From the posterior-mean position ``points + E[u_b]`` of node ``b``, each axis is
    scanned in both directions (steps of 1/20 of the smallest voxel) until the nearest
    voxel is skull or off the grid, the sampler's hard constraint.

    Parameters
    ----------
    run : RunData
    b : int
        index into ``run.boundary``
    reach_mm : float
        how far to scan

    Returns
    -------
    (3, 2) ndarray
        ``[axis, (lower, upper)]`` displacement values, mm; NaN where no skull within
        ``reach_mm``.
    """
    mean = run.u_b[:, :, b].reshape(-1, 3).mean(0)
    base = run.points[run.boundary[b]] + mean
    step = float(run.spacing.min()) / 20.0
    t = np.arange(step, reach_mm + step, step)
    forbidden = (run.labels == SKULL_LABEL).astype(np.int8)
    out = np.full((3, 2), np.nan)
    for a in range(3):
        for s, sign in enumerate((-1.0, 1.0)):
            p = np.repeat(base[None], len(t), 0)
            p[:, a] += sign * t
            hit = np.flatnonzero(_nearest(forbidden, run.affine, p, outside=1))
            if hit.size:
                out[a, s] = mean[a] + sign * t[hit[0]]
    return out


def mesh_cut(points, tets, affine, k: float):
    """Intersection of the tetrahedra with the voxel plane ``k`` (third voxel axis).

    Parameters
    ----------
    points : (N, 3) world mm
    tets : (M, 4) int
    affine : (4, 4) voxel-to-world of the image grid
    k : float
        plane index along the third voxel axis

    Returns
    -------
    polygons : list of (3 or 4, 2) ndarray
        Cut polygons in voxel coordinates ``(i, j)`` of the slice, vertices in order.
    cells : (P,) int ndarray
        Tetrahedron of each polygon.
    """
    v = _voxel(affine, points)
    s = v[:, 2] - k
    st = s[tets]
    cand = np.flatnonzero((st.min(1) <= 0) & (st.max(1) >= 0) & (np.abs(st).max(1) > 0))
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    polys, cells = [], []
    for e in cand:
        nd = tets[e]
        pts = [v[n, :2] for n in nd if s[n] == 0]
        for a, b in edges:
            sa, sb = s[nd[a]], s[nd[b]]
            if sa * sb < 0:
                pts.append(v[nd[a], :2] + sa / (sa - sb) * (v[nd[b], :2] - v[nd[a], :2]))
        if len(pts) < 3:
            continue
        p = np.unique(np.round(np.array(pts), 9), axis=0)
        if len(p) < 3:
            continue
        c = p.mean(0)
        p = p[np.argsort(np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0]))]
        polys.append(p)
        cells.append(e)
    return polys, np.asarray(cells, int)


def slice_index(run: RunData, world=None) -> int:
    """Index along the third voxel axis (axial for RAS images) of the slice to show.

    Parameters
    ----------
    run : RunData
    world : (3,) array_like, optional
        A world point (mm) the slice must contain; default the centroid of the brain
        voxels (labels 1-3) of ``run``.
    """
    if world is None:
        world = _brain_centroid(run)
    k = int(np.rint(_voxel(run.affine, np.asarray(world, float)[None])[0, 2]))
    return int(np.clip(k, 0, run.labels.shape[2] - 1))


def _brain_centroid(run: RunData) -> np.ndarray:
    ijk = np.argwhere(np.isin(run.labels, list(TISSUE_LABELS.values())))
    if len(ijk) == 0:
        ijk = np.argwhere(np.ones(run.labels.shape, bool))
    c = ijk.mean(0)
    return run.affine[:3, :3] @ c + run.affine[:3, 3]


def _figure(nrows, ncols, size=(3.2, 3.0)):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] * ncols, size[1] * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def _show(fig, ax, img2d, title, *, cbar=None, **kw):
    im = ax.imshow(np.asarray(img2d).T, origin="lower", interpolation="nearest", **kw)
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    if cbar:
        fig.colorbar(im, ax=ax, shrink=0.8, label=cbar)
    return im


def _label_cmap():
    from matplotlib.colors import ListedColormap

    return ListedColormap(["black", TISSUE_COLORS["csf"], TISSUE_COLORS["gm"],
                           TISSUE_COLORS["wm"], "lightgray"])


def _brain(run: RunData, erode: int = 0) -> np.ndarray:
    """Brain voxels (labels 1-3); with ``erode``, only those whose true displacement is
    non-zero (inside the mesh) eroded by ``erode`` voxels (central differences valid)."""
    m = np.isin(run.labels, list(TISSUE_LABELS.values()))
    if not erode:
        return m
    m &= np.any(run.disp_true != 0, axis=-1)
    return ndi.binary_erosion(m, iterations=erode)


def _sym_limit(values) -> float:
    v = np.abs(np.asarray(values))
    v = v[np.isfinite(v)]
    return float(np.quantile(v, 0.99)) if v.size and np.quantile(v, 0.99) > 0 else 1.0


def _bins(x) -> int:
    return int(np.clip(np.sqrt(len(x)), 10, 60))


def plot_dataset(run: RunData, k: int | None = None):
    """Paper Fig. 2: the synthetic dataset on slice ``k`` (third voxel axis).

    Panels: ``f``, ``m``, labels (CSF red, GM green, WM yellow, skull gray), the mesh cut
    (tetrahedra intersecting the slice plane, colored by tissue, over ``f``), the
    divergence of the true field (mm/mm; brain voxels inside the mesh, eroded by one voxel), its x and y
    components and its norm (mm).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.collections import PolyCollection

    k = slice_index(run) if k is None else k
    fig, ax = _figure(2, 4)
    _show(fig, ax[0, 0], run.f[:, :, k], "(a) fixed image f", cmap="gray")
    if run.m is not None:
        _show(fig, ax[0, 1], run.m[:, :, k], "(b) moving image m", cmap="gray")
    else:
        ax[0, 1].set_axis_off()
        ax[0, 1].text(0.5, 0.5, "m.nii.gz not in the run", ha="center", transform=ax[0, 1].transAxes)
    _show(fig, ax[0, 2], run.labels[:, :, k], "(c) labels", cmap=_label_cmap(), vmin=-0.5, vmax=4.5)
    _show(fig, ax[0, 3], run.f[:, :, k], f"(d) mesh cut ({len(run.tets)} tets)", cmap="gray")
    polys, cells = mesh_cut(run.points, run.tets, run.affine, k)
    if polys:
        colors = [TISSUE_COLORS[TISSUE_NAMES[min(int(t), 2)]] for t in run.tissue[cells]]
        ax[0, 3].add_collection(PolyCollection(polys, facecolors=colors, edgecolors="k",
                                               linewidths=0.3, alpha=0.7))
    brain = _brain(run, erode=1)[:, :, k]
    div = divergence(run.disp_true, run.affine)[:, :, k]
    lim = _sym_limit(div[brain])
    _show(fig, ax[1, 0], np.where(brain, div, np.nan), "(e) div u_true", cmap="RdBu_r",
          vmin=-lim, vmax=lim, cbar="mm/mm")
    ut = run.disp_true[:, :, k]
    ulim = _sym_limit(ut[..., :2])
    for a, (i, name) in enumerate(((0, "x"), (1, "y"))):
        _show(fig, ax[1, 1 + a], ut[..., i], f"({'fg'[a]}) u_true {name}", cmap="RdBu_r",
              vmin=-ulim, vmax=ulim, cbar="mm")
    _show(fig, ax[1, 3], np.linalg.norm(ut, axis=-1), "(h) |u_true|", cmap="viridis", cbar="mm")
    fig.suptitle(f"synthetic dataset, slice k={k}")
    return fig


def plot_errors(runs, k: int | None = None):
    """Paper Fig. 3: per run, ``|E[u] - u_true|`` (mm) and ``div E[u]`` (mm/mm) on slice ``k``.

    One row per run; the two columns share their color scale across runs (the divergence
    scale also covers the true field's, as in Fig. 2).

    Returns
    -------
    matplotlib.figure.Figure
    """
    runs = as_runs(runs)
    first = next(iter(runs.values()))
    world = _brain_centroid(first) if k is None else first.affine[:3, :3] @ [0, 0, k] + first.affine[:3, 3]
    err, div, ks = {}, {}, {}
    for lab, r in runs.items():
        ks[lab] = slice_index(r, world)
        brain = _brain(r)[:, :, ks[lab]]
        inner = _brain(r, erode=1)[:, :, ks[lab]]
        e = np.linalg.norm(r.disp_mean - r.disp_true, axis=-1)[:, :, ks[lab]]
        err[lab] = np.where(brain, e, np.nan)
        div[lab] = np.where(inner, divergence(r.disp_mean, r.affine)[:, :, ks[lab]], np.nan)
    true_div = divergence(first.disp_true, first.affine)[:, :, ks[next(iter(runs))]]
    emax = max(float(np.nanmax(e)) if np.isfinite(e).any() else 0.0 for e in err.values()) or 1.0
    dlim = max(_sym_limit(np.concatenate([d[np.isfinite(d)] for d in div.values()])),
               _sym_limit(true_div[_brain(first, 1)[:, :, ks[next(iter(runs))]]]))
    fig, ax = _figure(len(runs), 2)
    for i, (lab, r) in enumerate(runs.items()):
        _show(fig, ax[i, 0], err[lab], f"{lab}: |E[u] - u_true|", cmap="inferno", vmin=0,
              vmax=emax, cbar="mm")
        _show(fig, ax[i, 1], div[lab], f"{lab}: div E[u]", cmap="RdBu_r", vmin=-dlim,
              vmax=dlim, cbar="mm/mm")
    fig.suptitle(f"error and divergence of the posterior mean, slice k={ks[next(iter(runs))]}")
    return fig


def _ratio_axis(x_by_group, truths):
    """Bins and scale for ratio histograms: the central 99 % of the draws and the truths,
    on a log axis when that spans more than 1.5 decades (the CSF ratio is heavy-tailed)."""
    pooled = np.concatenate([np.quantile(x, [0.005, 0.995]) for x in x_by_group] + [truths])
    pooled = pooled[np.isfinite(pooled) & (pooled > 0)]
    lo, hi = (pooled.min(), pooled.max()) if pooled.size else (1e-3, 1.0)
    n = int(np.clip(np.sqrt(min(len(x) for x in x_by_group)), 10, 120))
    if hi / lo > 10**1.5:
        return np.geomspace(lo / 1.2, hi * 1.2, n), "log"
    pad = 0.05 * (hi - lo) or 0.5
    return np.linspace(max(lo - pad, 0.0), hi + pad, n), "linear"


def _group_bins(x, scale, n):
    """``n`` bins over the central 99 % of one group's finite positive draws ``x``, on the
    axis' scale (``"log"`` or ``"linear"``); a constant sample gets one narrow bin."""
    x = x[np.isfinite(x) & (x > 0)] if scale == "log" else x[np.isfinite(x)]
    if not x.size:
        return n
    lo, hi = np.quantile(x, [0.005, 0.995])
    if not hi > lo:
        lo, hi = lo * 0.99 - 1e-12, hi * 1.01 + 1e-12
    return np.geomspace(lo, hi, n) if scale == "log" else np.linspace(lo, hi, n)


def plot_ratios(runs):
    """Paper Fig. 4: marginal posterior of ``lam/mu`` per elastic group, chains pooled.

    One panel per run; per-tissue truth as dashed lines.  For a run with a single group
    (uniform model) every tissue's true ratio is marked, the legend says so.  The axis
    covers the central 99 % of each group's draws and the truths (log scale over a wide
    range); each group has its own bins over its own central 99 % (a narrow GM or WM
    posterior next to the heavy-tailed CSF one would otherwise fill one or two bins), and
    each histogram gives the fraction of that group's draws per bin.

    Returns
    -------
    matplotlib.figure.Figure
    """
    runs = as_runs(runs)
    fig, ax = _figure(1, len(runs), size=(4.5, 3.2))
    for i, (lab, r) in enumerate(runs.items()):
        a = ax[0, i]
        xs = [r.ratio[..., g].ravel() for g in range(len(r.groups))]
        marked = TISSUE_NAMES if len(r.groups) == 1 else r.groups
        truths = {name: true_ratio(r, name) for name in marked}
        truths = {k: v for k, v in truths.items() if v is not None}
        bins, scale = _ratio_axis(xs, list(truths.values()))
        for g, (name, x) in enumerate(zip(r.groups, xs)):
            w = np.full(len(x), 1.0 / len(x))
            a.hist(x, bins=_group_bins(x, scale, len(bins)), weights=w, histtype="stepfilled",
                   alpha=0.35, color=TISSUE_COLORS.get(name, f"C{g}"), label=f"{name} posterior")
        for name, tr in truths.items():
            what = (f"true {name} ratio (not a model parameter: uniform fit)"
                    if len(r.groups) == 1 else f"true {name} = {tr:.3g}")
            a.axvline(tr, color=TISSUE_COLORS.get(name, "k"), ls="--", label=what)
        a.set_xscale(scale)
        a.set_xlim(bins[0], bins[-1])
        a.set_xlabel("lam / mu")
        a.set_ylabel("fraction of draws per bin")
        a.set_title(f"{lab} ({r.elastic})", fontsize=9)
        a.legend(fontsize=6)
    fig.suptitle("marginal posteriors of the elastic ratio")
    return fig


def plot_boundary_node(run: RunData, b: int | None = None):
    """Paper Fig. 5: marginal posterior of the three components of one boundary node.

    Default node: :func:`skull_node` (closest to the skull after the true deformation).
    Marks the truth, the posterior mean and, where found within the scan range and near
    the draws, the skull limit of each component (:func:`skull_limits`).

    Returns
    -------
    fig : matplotlib.figure.Figure
    info : dict
        ``node`` (mesh index), ``b`` (index into ``run.boundary``), ``skull_distance_mm``,
        ``true_mm``, ``mean_mm``, ``skull_limits_mm`` ((3, 2) lower/upper, None = not found).
    """
    dist = None
    if b is None:
        b, dist = skull_node(run)
    x = run.u_b[:, :, b].reshape(-1, 3)
    node = int(run.boundary[b])
    truth = run.u_true[node]
    limits = skull_limits(run, b) if np.any(run.labels == SKULL_LABEL) else np.full((3, 2), np.nan)
    fig, ax = _figure(1, 3, size=(3.6, 3.0))
    for a in range(3):
        axx = ax[0, a]
        axx.hist(x[:, a], bins=_bins(x), density=True, histtype="stepfilled", alpha=0.5, color="C0",
                 label="posterior")
        axx.axvline(truth[a], color="k", ls="--", label="truth")
        axx.axvline(x[:, a].mean(), color="C0", ls=":", label="posterior mean")
        lo, hi = x[:, a].min(), x[:, a].max()
        pad = max(hi - lo, 1e-6)
        for lim in limits[a]:
            if np.isfinite(lim) and lo - pad <= lim <= hi + pad:
                axx.axvline(lim, color="tab:red", lw=2, label="skull (this component alone)")
        axx.set_xlabel(f"u_{'xyz'[a]} (mm)")
        axx.legend(fontsize=6)
    where = "" if dist is None else f", true position {dist:.1f} mm from the skull"
    fig.suptitle(f"boundary node {node}{where}")
    info = {"node": node, "b": int(b), "skull_distance_mm": dist,
            "true_mm": truth.tolist(), "mean_mm": x.mean(0).tolist(),
            "skull_limits_mm": [[None if not np.isfinite(v) else float(v) for v in row]
                                for row in limits]}
    return fig, info


def _spread(r: RunData):
    """The run's per-voxel spread of ``u``, mm: the IQR of ``|u|``, or for runs without it
    the norm of the per-component sd ``sqrt(sum_c sd_c^2)``; ``None`` if neither."""
    if r.disp_norm_iqr is not None:
        return r.disp_norm_iqr
    if r.disp_sd is not None:
        return np.linalg.norm(r.disp_sd, axis=-1)
    return None


def plot_uncertainty(runs, k: int | None = None):
    """Posterior uncertainty over ``f`` on axial slice ``k``, one panel per run (common scale).

    By default the slice goes through the first run's most uncertain region
    (:func:`bayesreg.outputs.plots.most_uncertain_voxel`), not the centre of the brain.

    The IQR of ``|u|`` (``displacement_norm_iqr.nii.gz``), or, for runs without it, the
    norm of the per-component sd ``sqrt(sum_c sd_c^2)`` (``displacement_sd.nii.gz``), mm,
    on brain voxels.

    Returns
    -------
    matplotlib.figure.Figure
    """
    runs = as_runs(runs)
    first = next(iter(runs.values()))
    if k is None:
        spread = _spread(first)
        k = (int(most_uncertain_voxel(spread, _brain(first))[2]) if spread is not None
             else slice_index(first, _brain_centroid(first)))
    world = first.affine[:3, :3] @ [0, 0, k] + first.affine[:3, 3]
    maps = {}
    for lab, r in runs.items():
        kk = slice_index(r, world)
        spread = _spread(r)
        what = ("IQR of |u|" if r.disp_norm_iqr is not None else "sd norm" if spread is not None
                else "no uncertainty map")
        maps[lab] = (kk, None if spread is None else spread[:, :, kk], what)
    vals = [u[_brain(r)[:, :, kk]] for (kk, u, _), r in zip(maps.values(), runs.values())
            if u is not None]
    vmax = max([float(v.max()) for v in vals if v.size] + [0.0]) or 1.0
    fig, ax = _figure(1, len(runs), size=(3.8, 3.2))
    for i, (lab, r) in enumerate(runs.items()):
        kk, u, what = maps[lab]
        _show(fig, ax[0, i], r.f[:, :, kk], f"{lab}: {what}", cmap="gray")
        if u is not None:
            ov = np.ma.masked_where(~_brain(r)[:, :, kk] | (u <= 0), u)
            im = ax[0, i].imshow(ov.T, origin="lower", cmap="magma", alpha=0.75, vmin=0,
                                 vmax=vmax, interpolation="nearest")
            fig.colorbar(im, ax=ax[0, i], shrink=0.8, label="mm")
    fig.suptitle("posterior uncertainty of the displacement")
    return fig


#: Table 1's statistics (boundary-node error of the posterior mean, mm) and their colours.
_TABLE1_STATS = (("t1_median", "median", "C0"), ("t1_q95", "95th percentile", "C1"),
                 ("t1_max", "max", "C3"))


def plot_sweep_table1(configs: dict, paper: dict | None = None):
    """Table 1 of every run of a sweep as points: one panel per config, one column of points
    per run (the boundary-node error of the posterior mean, median, 95th percentile and max,
    mm), the paper's values as dashed lines.

    Parameters
    ----------
    configs : dict
        ``{config name: [row, ...]}``, each row a dict with ``id``, ``status`` and, where the
        run has results, ``t1_median``, ``t1_q95``, ``t1_max`` (mm;
        :func:`bayesreg.experiments.sweep.run_row`).  Runs whose status is not
        ``finished`` (unconverged, a bad start) are drawn hollow and grey: shown, not
        results; runs without figures are left out.
    paper : dict, optional
        ``{config name: {"median": ..., "q95": ..., "max": ...}}``, the paper's Table 1 row
        each config reproduces (:data:`bayesreg.report.data.PAPER`).

    Returns
    -------
    matplotlib.figure.Figure
    """
    paper = paper or {}
    names = list(configs)
    fig, axes = _figure(1, max(1, len(names)), size=(4.2, 3.2))
    for ax, name in zip(axes[0], names):
        rows = [r for r in configs[name] if isinstance(r.get("t1_median"), (int, float))]
        for j, r in enumerate(rows):
            ok = r.get("status") == "finished"
            for col, label, colour in _TABLE1_STATS:
                ax.plot([j], [r[col]], "o", color=colour if ok else "0.6",
                        mfc=colour if ok else "none", ms=5)
        for col, label, colour in _TABLE1_STATS:
            ax.plot([], [], "o", color=colour, ms=5, label=label)  # the legend's, in colour
            ref = paper.get(name, {}).get(label if label != "95th percentile" else "q95")
            if ref is not None:
                ax.axhline(ref, ls="--", lw=1, color=colour)
        ax.set_xticks(range(len(rows)))
        ax.set_xticklabels([str(r.get("label", r["id"])) for r in rows], rotation=60, fontsize=7,
                           ha="right")
        ax.set_yscale("log")
        ax.set_ylabel("boundary-node error of E[u] (mm)")
        ax.set_title(f"{name}: filled, rule met; hollow, not", fontsize=9)
        if rows:
            ax.legend(fontsize=7, loc="upper right")
    fig.suptitle("Table 1 per run (dashed: the paper)", fontsize=10)
    return fig
