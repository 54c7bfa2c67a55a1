"""The paper's Section 4 tables and figures from finished runs (synthetic truth needed).

:func:`write_report` reads finished run directories (see :mod:`bayesreg.outputs`), one per
model (e.g. ``{"uniform": ..., "three_compartment": ...}``), and writes a report directory:

==========================  ==========================================================
``table1.csv``              boundary-node error of the posterior mean (and of the initial
                            configuration) against the truth: median, 95th quantile, max, mm
                            (paper Table 1)
``table2.csv``              MSE of the deformation on the image grid over the brain and per
                            tissue, mm^2 (paper Table 2)
``coverage.csv``            coverage of the true boundary displacement components by the
                            central 50/90/95 % credible intervals
``ratios.csv``              lam/mu posterior per model and elastic group, with the truth
``fig2_dataset.png``        the dataset: images, labels, mesh cut, divergence and x/y
                            components of the true field (paper Fig. 2)
``fig3_errors.png``         error norm and divergence of the posterior mean (paper Fig. 3)
``fig4_ratios.png``         marginal posteriors of lam/mu (paper Fig. 4)
``fig5_boundary_node.png``  marginal posterior of a boundary node next to the skull (Fig. 5)
``uncertainty.png``         interquartile range of ``|u|`` over the fixed image
``report.md``, ``report.json``  all of it, side by side with the paper's values
==========================  ==========================================================

The pieces are small functions of a :class:`RunData` (:func:`load_run`) so that a notebook
can redraw one table or figure: ``table1({"tissue": load_run("runs/a")})``.  Figures are
built with the object-oriented Matplotlib API on the Agg canvas (no pyplot state).
Units: displacements and distances in world mm, MSE in mm^2, divergence in mm/mm.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import scipy.ndimage as ndi

from bayesreg.diagnostics import coverage
from bayesreg.outputs import RunDirectory

__all__ = [
    "PAPER",
    "RunData",
    "load_run",
    "table1",
    "table2",
    "coverage_table",
    "ratio_table",
    "divergence",
    "skull_distance",
    "skull_node",
    "skull_limits",
    "mesh_cut",
    "slice_index",
    "plot_dataset",
    "plot_errors",
    "plot_ratios",
    "plot_boundary_node",
    "plot_uncertainty",
    "write_report",
]

# Risholm, Samset, Wells, "Bayesian Estimation of Deformation and Elastic Parameters in
# Non-rigid Registration", Section 4 (shared/paper.md).  Keys "tissue" / "uniform" are the
# values of config["model"]["elastic"] of the matching run ("Different" / "Uniform Elastic
# Parameters" in the paper).
PAPER = {
    # Table 1: |E[u_b] - u_b_true| over the boundary nodes, mm
    "table1_mm": {
        "initial": {"median": 2.56, "q95": 8.24, "max": 15.08},
        "tissue": {"median": 0.16, "q95": 0.72, "max": 2.43},
        "uniform": {"median": 0.18, "q95": 0.83, "max": 2.40},
    },
    # Table 2: MSE of the deformation over the brain and per tissue, mm^2
    "table2_mm2": {
        "tissue": {"brain": 0.040, "csf": 0.049, "gm": 0.049, "wm": 0.023},
        "uniform": {"brain": 0.065, "csf": 0.087, "gm": 0.067, "wm": 0.048},
    },
    # Fig. 4 caption: true ratios and what the marginal posteriors showed
    "fig4": {
        "true_ratio": {"csf": 1.0, "gm": 10.0, "wm": 30.0},
        "findings": (
            "the ratios distinguish the tissue types but do not recover the exact values; "
            "they are biased towards zero, WM (larger volume) more than GM"
        ),
    },
    # Sec. 4.1-4.2: dataset and sampling
    "setup": {
        "n_nodes": 801, "n_tets": 3807, "n_boundary": 349, "chains": 3,
        "steps_per_chain": 250_000, "thinning": 10, "draws_per_chain": 25_000,
        "steps_per_s_per_chain": 5, "wall_time_h": 14, "acceptance": 0.25,
        "rhat_threshold": 1.2,
        "truth": {"lam": {"csf": 1e-6, "gm": 10.0, "wm": 30.0},
                  "mu": {"csf": 1e-6, "gm": 1.0, "wm": 1.0}},
    },
}

TISSUE_NAMES = ("csf", "gm", "wm")
TISSUE_LABELS = {"csf": 1, "gm": 2, "wm": 3}  # label map coding (bayesreg.labels)
SKULL_LABEL = 4
TISSUE_COLORS = {"csf": "tab:red", "gm": "tab:green", "wm": "gold", "all": "tab:blue"}
LEVELS = (0.5, 0.9, 0.95)
_REQUIRED = ("run.json", "posterior.nc", "mesh.vtu", "f.nii.gz", "labels.nii.gz",
             "displacement_mean.nii.gz")


class RunData(NamedTuple):
    """Everything the report reads from one finished run directory.

    Attributes
    ----------
    path : Path
    info : dict  ``run.json``
    u_b : (C, D, B, 3) ndarray  boundary displacement draws, mm
    boundary : (B,) int ndarray  mesh node index of each sampled boundary node
    lam, mu, ratio : (C, D, G) ndarray  Lamé parameter draws and ``lam/mu`` per group
    groups : tuple of str  elastic group names (``("csf", "gm", "wm")`` or ``("all",)``)
    points : (N, 3) ndarray  undeformed mesh nodes, world mm
    tets : (M, 4) int ndarray
    tissue : (M,) int ndarray  0 CSF, 1 GM, 2 WM
    u_true : (N, 3) ndarray  synthetic truth, mm
    u_init : (N, 3) ndarray or None  central starting configuration, mm
    affine : (4, 4) ndarray  voxel-to-world of the image grid
    f, m : (I, J, K) ndarray  fixed and moving image (``m`` None if absent)
    labels : (I, J, K) int ndarray  0 background, 1 CSF, 2 GM, 3 WM, 4 skull
    disp_mean, disp_true : (I, J, K, 3) ndarray  posterior mean and true field, mm
    disp_init, disp_sd : (I, J, K, 3) ndarray or None  initial field, posterior sd, mm
    disp_norm_iqr : (I, J, K) ndarray or None  posterior IQR of ``|u|``, mm
    in_mesh : (I, J, K) bool ndarray or None  voxels inside the undeformed mesh
        (``mesh_mask.nii.gz``), where the FE field is defined
    """

    path: Path
    info: dict
    u_b: np.ndarray
    boundary: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    ratio: np.ndarray
    groups: tuple
    points: np.ndarray
    tets: np.ndarray
    tissue: np.ndarray
    u_true: np.ndarray
    u_init: np.ndarray | None
    affine: np.ndarray
    f: np.ndarray
    m: np.ndarray | None
    labels: np.ndarray
    disp_mean: np.ndarray
    disp_true: np.ndarray
    disp_init: np.ndarray | None
    disp_sd: np.ndarray | None
    disp_norm_iqr: np.ndarray | None
    in_mesh: np.ndarray | None = None

    @property
    def elastic(self) -> str:
        """``config["model"]["elastic"]`` (``"uniform"``, ``"tissue"``, ...), or ``"?"``."""
        return str(self.info.get("config", {}).get("model", {}).get("elastic", "?"))

    @property
    def name(self) -> str:
        return str(self.info.get("name", self.path.name))

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size along each array axis, mm, ``(3,)``."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def true_elastic(self) -> dict | None:
        """``{"lam": {tissue: value}, "mu": {...}}`` from ``run.json["truth"]``, or None."""
        t = self.info.get("truth")
        return t if isinstance(t, dict) and "lam" in t and "mu" in t else None


# ---------------------------------------------------------------------------- loading


def _nifti(path: Path, *, required: bool = True):
    import nibabel as nib

    if not path.exists():
        if required:
            raise FileNotFoundError(f"{path.name} not found in run directory {path.parent}")
        return None, None
    img = nib.load(str(path))
    return np.asarray(img.dataobj), np.asarray(img.affine, np.float64)


def load_run(path) -> RunData:
    """Read a finished run directory (written by :func:`bayesreg.outputs.write_outputs`).

    Parameters
    ----------
    path : str or Path
        The run directory.

    Returns
    -------
    RunData

    Raises
    ------
    FileNotFoundError
        If the directory or a required file (``run.json``, ``posterior.nc``, ``mesh.vtu``,
        ``f.nii.gz``, ``labels.nii.gz``, ``displacement_mean.nii.gz``,
        ``displacement_true.nii.gz``) is missing; the message names the file.
    ValueError
        If the run has no synthetic truth (no ``u_true`` in ``mesh.vtu``), or the
        posterior lacks ``u_b``/``lam``/``mu``.
    """
    import arviz as az
    import meshio

    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"run directory {path} not found")
    for name in _REQUIRED:
        if not (path / name).exists():
            raise FileNotFoundError(f"{name} not found in run directory {path}")
    info = json.loads((path / "run.json").read_text())

    mesh = meshio.read(path / "mesh.vtu")
    if "u_true" not in mesh.point_data:
        raise ValueError(f"the report needs a synthetic truth: run {path} has no u_true in "
                         "mesh.vtu (was it run on real data?)")
    tets = next((np.asarray(c.data) for c in mesh.cells if c.type == "tetra"), None)
    if tets is None:
        raise ValueError(f"mesh.vtu of run {path} has no tetra cells")
    tissue = np.asarray(mesh.cell_data["tissue"][0]).astype(int) if "tissue" in mesh.cell_data \
        else np.zeros(len(tets), int)
    u_init = mesh.point_data.get("u_init")

    tree = az.from_netcdf(path / "posterior.nc")
    try:
        post = tree.posterior
        missing = [v for v in ("u_b", "lam", "mu") if v not in post]
        if missing:
            raise ValueError(f"posterior.nc of run {path} lacks {missing}")
        u_b = np.asarray(post["u_b"].transpose("chain", "draw", "node", "axis").values, float)
        boundary = np.asarray(post["node"].values, int)
        lam, mu = (np.asarray(post[v].transpose("chain", "draw", "group").values, float)
                   for v in ("lam", "mu"))
        ratio = (np.asarray(post["ratio"].transpose("chain", "draw", "group").values, float)
                 if "ratio" in post else lam / mu)
        groups = tuple(str(g) for g in post["group"].values)
    finally:
        tree.close()

    f, affine = _nifti(path / "f.nii.gz")
    labels, _ = _nifti(path / "labels.nii.gz")
    disp_mean, _ = _nifti(path / "displacement_mean.nii.gz")
    disp_true, _ = _nifti(path / "displacement_true.nii.gz")
    m, _ = _nifti(path / "m.nii.gz", required=False)
    disp_init, _ = _nifti(path / "displacement_init.nii.gz", required=False)
    disp_sd, _ = _nifti(path / "displacement_sd.nii.gz", required=False)
    iqr, _ = _nifti(path / "displacement_norm_iqr.nii.gz", required=False)
    in_mesh, _ = _nifti(path / "mesh_mask.nii.gz", required=False)

    def flt(a):
        return None if a is None else np.asarray(a, np.float64)

    return RunData(
        path=path, info=info, u_b=u_b, boundary=boundary, lam=lam, mu=mu, ratio=ratio,
        groups=groups, points=np.asarray(mesh.points, np.float64), tets=tets.astype(int),
        tissue=tissue, u_true=np.asarray(mesh.point_data["u_true"], np.float64),
        u_init=flt(u_init), affine=affine, f=flt(f), m=flt(m),
        labels=np.rint(np.asarray(labels)).astype(int), disp_mean=flt(disp_mean),
        disp_true=flt(disp_true), disp_init=flt(disp_init), disp_sd=flt(disp_sd),
        disp_norm_iqr=flt(iqr), in_mesh=None if in_mesh is None else np.asarray(in_mesh) > 0,
    )


def _as_runs(runs) -> dict:
    """``{label: RunData}`` from a RunData or a mapping of labels to RunData or paths."""
    if isinstance(runs, RunData):
        return {runs.name: runs}
    return {str(k): (v if isinstance(v, RunData) else load_run(v)) for k, v in runs.items()}


# ----------------------------------------------------------------------------- tables


def _stats(err) -> dict:
    return {"median": float(np.median(err)), "q95": float(np.quantile(err, 0.95)),
            "max": float(np.max(err))}


def _initial_rows(runs: dict, get) -> dict:
    """``{row: (run, value)}`` for the initial configuration (``get(run)`` or None).

    One row ``"initial"`` when every run that has it started from the same configuration,
    else one row ``"initial (label)"`` per run.
    """
    have = {k: (r, get(r)) for k, r in runs.items() if get(r) is not None}
    if not have:
        return {}
    vals = [v for _, v in have.values()]
    if all(v.shape == vals[0].shape and np.allclose(v, vals[0], atol=1e-9) for v in vals):
        return {"initial": next(iter(have.values()))}
    return {f"initial ({k})": rv for k, rv in have.items()}


def table1(runs) -> pd.DataFrame:
    """Paper Table 1: error of the boundary-node displacements against the truth, mm.

    Per boundary node (the ``node`` coordinate of ``posterior.nc``) the Euclidean norm of
    ``E[u_b] - u_true`` with ``E[u_b]`` the mean over all chains and draws; for the row
    ``initial`` that of ``u_init - u_true``.

    Parameters
    ----------
    runs : RunData or Mapping[str, RunData or path]

    Returns
    -------
    DataFrame
        Index: ``"initial"`` (if ``u_init`` is in ``mesh.vtu``; one ``"initial (label)"``
        row per run instead when the runs started from different configurations) and the
        run labels; columns ``median``, ``q95``, ``max`` (mm).
    """
    runs = _as_runs(runs)
    rows = {}
    for row, (r, u0) in _initial_rows(runs, lambda r: None if r.u_init is None
                                       else r.u_init[r.boundary]).items():
        rows[row] = _stats(np.linalg.norm(u0 - r.u_true[r.boundary], axis=1))
    for k, r in runs.items():
        mean_b = r.u_b.reshape(-1, *r.u_b.shape[2:]).mean(0)
        rows[k] = _stats(np.linalg.norm(mean_b - r.u_true[r.boundary], axis=1))
    return pd.DataFrame.from_dict(rows, orient="index", columns=["median", "q95", "max"])


def _mse(disp, truth, labels, in_mesh=None) -> dict:
    sq = np.sum((disp - truth) ** 2, axis=-1)
    where = np.ones(labels.shape, bool) if in_mesh is None else in_mesh
    brain = np.isin(labels, list(TISSUE_LABELS.values())) & where
    out = {"brain": float(sq[brain].mean()) if brain.any() else math.nan}
    for t, lab in TISSUE_LABELS.items():
        sel = (labels == lab) & where
        out[t] = float(sq[sel].mean()) if sel.any() else math.nan
    return out


def table2(runs) -> pd.DataFrame:
    """Paper Table 2: MSE of the deformation on the image grid, mm^2.

    Mean over voxels of ``|u - u_true|^2`` with ``u`` the posterior mean
    (``displacement_mean.nii.gz``; ``displacement_init.nii.gz`` for the row ``initial``)
    and ``u_true`` from ``displacement_true.nii.gz``, over the brain (labels 1-3) and per
    tissue (label 1 CSF, 2 GM, 3 WM), restricted to the voxels inside the undeformed mesh
    (``mesh_mask.nii.gz``, where the FE field is defined) when the run has that file.

    Parameters
    ----------
    runs : RunData or Mapping[str, RunData or path]

    Returns
    -------
    DataFrame
        Index: ``"initial"`` (if ``displacement_init.nii.gz`` exists; per run as in
        :func:`table1`) and the run labels; columns ``brain``, ``csf``, ``gm``, ``wm``
        (mm^2; NaN for a tissue with no voxel).
    """
    runs = _as_runs(runs)
    rows = {}
    for row, (r, d0) in _initial_rows(runs, lambda r: r.disp_init).items():
        rows[row] = _mse(d0, r.disp_true, r.labels, r.in_mesh)
    for k, r in runs.items():
        rows[k] = _mse(r.disp_mean, r.disp_true, r.labels, r.in_mesh)
    return pd.DataFrame.from_dict(rows, orient="index", columns=["brain", *TISSUE_NAMES])


def coverage_table(runs, levels=LEVELS) -> pd.DataFrame:
    """Coverage of the true boundary displacement components (B x 3 per run).

    Parameters
    ----------
    runs : RunData or Mapping[str, RunData or path]
    levels : sequence of float  central credible levels

    Returns
    -------
    DataFrame
        Index: run labels; one column per level (``"50%"``, ...), the fraction of the
        ``3 B`` components whose truth lies in the central interval (chains pooled).
    """
    runs = _as_runs(runs)
    rows = {}
    for k, r in runs.items():
        c, d, b, _ = r.u_b.shape
        cov = coverage(r.u_b.reshape(c, d, 3 * b), r.u_true[r.boundary].ravel(), levels)
        rows[k] = {f"{100 * lev:g}%": v for lev, v in cov.items()}
    return pd.DataFrame.from_dict(rows, orient="index")


def _true_ratio(run: RunData, group: str) -> float | None:
    t = run.true_elastic
    if t is not None and group in t["lam"] and group in t["mu"]:
        return float(t["lam"][group]) / float(t["mu"][group])
    r = (run.info.get("errors") or {}).get("ratio", {}).get(group, {})
    return float(r["true"]) if "true" in r else None


def ratio_table(runs) -> pd.DataFrame:
    """``lam/mu`` posterior per run and elastic group (paper Fig. 4 in numbers).

    Returns
    -------
    DataFrame
        One row per (run label, group): ``mean``, ``median``, ``q05``, ``q95`` of the draws
        (chains pooled) and ``true`` (NaN where the truth has no such group).
    """
    rows = []
    for k, r in _as_runs(runs).items():
        for g, name in enumerate(r.groups):
            x = r.ratio[..., g].ravel()
            tr = _true_ratio(r, name)
            rows.append({"run": k, "group": name, "mean": float(x.mean()),
                         "median": float(np.median(x)), "q05": float(np.quantile(x, 0.05)),
                         "q95": float(np.quantile(x, 0.95)),
                         "true": math.nan if tr is None else tr})
    return pd.DataFrame(rows).set_index(["run", "group"])


# ------------------------------------------------------------------------- geometry


def divergence(u, affine) -> np.ndarray:
    """Divergence of a displacement field on an image grid, mm/mm.

    Central differences (``np.gradient``) along the voxel axes, mapped to world
    derivatives by the inverse of the affine's linear part (for a diagonal affine this is
    ``np.gradient`` with the voxel spacing).

    Parameters
    ----------
    u : (I, J, K, 3) array_like  world-mm displacement (x, y, z components)
    affine : (4, 4) array_like  voxel-to-world

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
    b : int  index into ``run.boundary``
    reach_mm : float  how far to scan

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
    k : float  plane index along the third voxel axis

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


# -------------------------------------------------------------------------- figures


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
    runs = _as_runs(runs)
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
    runs = _as_runs(runs)
    fig, ax = _figure(1, len(runs), size=(4.5, 3.2))
    for i, (lab, r) in enumerate(runs.items()):
        a = ax[0, i]
        xs = [r.ratio[..., g].ravel() for g in range(len(r.groups))]
        marked = TISSUE_NAMES if len(r.groups) == 1 else r.groups
        truths = {name: _true_ratio(r, name) for name in marked}
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


def plot_uncertainty(runs, k: int | None = None):
    """Posterior uncertainty over ``f`` on slice ``k``, one panel per run (common scale).

    The IQR of ``|u|`` (``displacement_norm_iqr.nii.gz``), or, for runs without it, the
    norm of the per-component sd ``sqrt(sum_c sd_c^2)`` (``displacement_sd.nii.gz``), mm,
    on brain voxels.

    Returns
    -------
    matplotlib.figure.Figure
    """
    runs = _as_runs(runs)
    first = next(iter(runs.values()))
    world = _brain_centroid(first) if k is None else first.affine[:3, :3] @ [0, 0, k] + first.affine[:3, 3]
    maps = {}
    for lab, r in runs.items():
        kk = slice_index(r, world)
        if r.disp_norm_iqr is not None:
            u, what = r.disp_norm_iqr[:, :, kk], "IQR of |u|"
        elif r.disp_sd is not None:
            u, what = np.linalg.norm(r.disp_sd[:, :, kk], axis=-1), "sd norm"
        else:
            u, what = None, "no uncertainty map"
        maps[lab] = (kk, u, what)
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


# --------------------------------------------------------------------------- report


def _clean(x):
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def _fmt(v, nd=3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return f"{float(v):.{nd}f}"


def _md_table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _paper_key(row: str, runs: dict) -> str | None:
    if row.startswith("initial"):
        return "initial"
    return runs[row].elastic if row in runs else None


def _run_summary(run: RunData) -> dict:
    s, mesh, t = run.info.get("sampler", {}), run.info.get("mesh", {}), run.info.get("timings_s", {})
    wall = t.get("total_before_outputs_s", sum(v for v in t.values() if isinstance(v, (int, float))))
    cfg = run.info.get("config", {})
    model, kind = cfg.get("model", {}), cfg.get("sampler", {}).get("kind")
    # how E_s, the skull constraint and Eq. 12 were evaluated (older runs: the defaults of then)
    setup = ", ".join(x for x in [
        kind, f"quadrature {4 * 8 ** int(model.get('quadrature_level', 0))} pts/tet",
        f"barrier {float(model.get('skull_barrier_mm', 0.0)):g} mm",
        f"normaliser {model['prior_normaliser']}" if "prior_normaliser" in model else None,
    ] if x) if cfg else "–"
    return {
        "path": str(run.path), "name": run.name, "elastic": run.elastic, "setup": setup,
        "n_nodes": mesh.get("n_nodes", len(run.points)),
        "n_boundary": mesh.get("n_boundary", mesh.get("n_boundary_nodes", len(run.boundary))),
        "n_tets": mesh.get("n_tets", len(run.tets)),
        "chains": s.get("chains", run.u_b.shape[0]),
        "draws_per_chain": s.get("draws_per_chain", run.u_b.shape[1]),
        "thinning": s.get("thinning"), "steps_per_chain": s.get("steps_per_chain"),
        "acceptance": s.get("acceptance"), "wall_time_s": wall,
        "rhat_classic_max": s.get("rhat_classic_max"), "converged": s.get("converged"),
        "ess_bulk_min": s.get("ess_bulk_min"),
        "steps_per_s_per_chain": s.get("steps_per_s_per_chain"),
    }


def _side_by_side(df: pd.DataFrame, paper: dict, runs: dict, nd: int) -> str:
    header = ["", *[h for c in df.columns for h in (c, f"{c} (paper)")]]
    rows = []
    for row, vals in df.iterrows():
        ref = paper.get(_paper_key(row, runs) or "", {})
        rows.append([row, *[x for c in df.columns for x in (_fmt(vals[c], nd), _fmt(ref.get(c), nd))]])
    return _md_table(header, rows)


_CAPTIONS = {
    "fig2_dataset.png": "Fig. 2 (paper): the synthetic dataset: images, labels (CSF red, GM "
    "green, WM yellow, skull gray), the mesh cut, divergence of the true field (collapse of "
    "the ventricles shows as its sign) and its x and y components.",
    "fig3_errors.png": "Fig. 3 (paper): norm of the error of the posterior-mean field and "
    "divergence of the posterior-mean field per model (common color scales).",
    "fig4_ratios.png": "Fig. 4 (paper): marginal posteriors of lam/mu, truth dashed. The paper "
    "found: " + PAPER["fig4"]["findings"] + ".",
    "fig5_boundary_node.png": "Fig. 5 (paper): marginal posterior of the displacement of the "
    "boundary node closest to the skull; the red line is where that component alone would take "
    "the node into the skull (the sampler rejects it: truncation).",
    "uncertainty.png": "Posterior uncertainty of the displacement over the fixed image.",
}


def _markdown(runs, summaries, t1, t2, cov, ratios, fig5) -> str:
    out = ["# Bayesian registration: reproduction of Risholm et al., Section 4", ""]
    out += ["## Runs", ""]
    keys = ["name", "elastic", "setup", "n_nodes", "n_boundary", "n_tets", "chains", "draws_per_chain",
            "thinning", "wall_time_s", "steps_per_s_per_chain", "rhat_classic_max", "converged"]
    ps = PAPER["setup"]
    rows = [[lab, *[s[k] if isinstance(s[k], str) else _fmt(s[k], 2) for k in keys]]
            for lab, s in summaries.items()]
    rows.append(["paper", "BrainWeb", "uniform / tissue",
                 "rwmh, quadrature 4 pts/tet, hard constraint, normaliser paper", ps["n_nodes"], ps["n_boundary"],
                 ps["n_tets"], ps["chains"], ps["draws_per_chain"], ps["thinning"],
                 f"~{ps['wall_time_h']} h", ps["steps_per_s_per_chain"],
                 f"< {ps['rhat_threshold']}", "yes"])
    out += [_md_table(["run", *keys], rows), "",
            "Paper columns: *Different Elastic Parameters* for runs with `elastic: tissue`, "
            "*Uniform Elastic Parameters* for `elastic: uniform`; – where the paper has no value.",
            ""]
    if not any(str(i).startswith("initial") for i in t1.index):
        out += ["No initial configuration (`u_init` in mesh.vtu) in these runs: no initial rows.", ""]
    out += ["## Table 1: boundary-node error of the posterior mean (mm)", "",
            "Euclidean norm per boundary node of E[u_b] - u_true (initial: u_init - u_true).", "",
            _side_by_side(t1, PAPER["table1_mm"], runs, 3), ""]
    out += ["## Table 2: MSE of the deformation on the image grid (mm²)", "",
            "Mean over voxels of |E[u] - u_true|² over the brain (labels 1-3) and per tissue.", "",
            _side_by_side(t2, PAPER["table2_mm2"], runs, 4), ""]
    out += ["## Coverage of the true boundary displacements", "",
            "Fraction of the 3 x n_boundary true components inside the central credible "
            "interval (a calibrated posterior gives the nominal level).", "",
            _md_table(["run", *cov.columns], [[lab, *[_fmt(v, 3) for v in row]]
                                              for lab, row in cov.iterrows()]), ""]
    out += ["## Elastic ratios lam/mu", "",
            _md_table(["run", "group", *ratios.columns],
                      [[i[0], i[1], *[_fmt(v, 3) for v in row]] for i, row in ratios.iterrows()]),
            "", f"Paper (Fig. 4): true ratios CSF 1, GM 10, WM 30; {PAPER['fig4']['findings']}.", ""]
    lim = "; ".join(f"{'xyz'[a]} ({_fmt(lo, 2)}, {_fmt(hi, 2)})"
                    for a, (lo, hi) in enumerate(fig5["skull_limits_mm"]))
    out += ["## Figures", ""]
    for name, cap in _CAPTIONS.items():
        if name == "fig5_boundary_node.png":
            cap += (f" Run {fig5['run']}, mesh node {fig5['node']}; skull limits (lower, upper) "
                    f"per axis, mm (– = none within 30 mm): {lim}.")
        out += [f"![{name}]({name})", "", f"*{cap}*", ""]
    return "\n".join(out)


def write_report(runs: Mapping[str, str | Path], out: str | Path, *, overwrite: bool = False) -> Path:
    """Write the paper's Section 4 tables and figures for finished runs (module docstring).

    Parameters
    ----------
    runs : Mapping[str, str or Path]
        Model label (e.g. ``"uniform"``, ``"three_compartment"``) -> finished run directory
        (a :class:`RunData` is accepted too).  Each needs a synthetic truth.
    out : str or Path
        Report directory.  Written in a staging folder beside it and moved in place at the
        end (:class:`bayesreg.outputs.RunDirectory`).
    overwrite : bool
        Replace an existing non-empty ``out`` that holds a report (``report.json`` or
        ``report.md``); a folder of other files is never replaced.

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    FileExistsError
        ``out`` exists, is not empty and ``overwrite`` is false, or holds no report.
    FileNotFoundError
        A run directory or one of its required files is missing (named).
    ValueError
        No runs, a run without synthetic truth (named), or ``out`` is or contains a run
        directory.
    """
    if not runs:
        raise ValueError("write_report needs at least one run")
    out = Path(out)
    for p in runs.values():
        rp = (p.path if isinstance(p, RunData) else Path(p)).resolve()
        if out.resolve() == rp or out.resolve() in rp.parents:
            raise ValueError(f"report directory {out} is or contains the run directory {rp}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise FileExistsError(f"report directory {out} exists and is not empty; pass "
                              "overwrite=True to replace it")
    data = _as_runs(runs)  # fails (missing file, no truth) before anything is written
    rd = RunDirectory(out, overwrite=overwrite, marks=("report.json", "report.md"))
    try:
        _write(rd, data)
        return rd.commit()
    except BaseException:
        # a report is all or nothing: this one's files go, and a report it was to replace
        # (overwrite) comes back (before: only the staging went, leaving the directory empty)
        rd.rollback()
        raise


def _write(rd: RunDirectory, runs: dict) -> None:
    t1, t2, cov, ratios = table1(runs), table2(runs), coverage_table(runs), ratio_table(runs)
    t1.to_csv(rd.file("table1.csv"), index_label="row")
    t2.to_csv(rd.file("table2.csv"), index_label="row")
    cov.to_csv(rd.file("coverage.csv"), index_label="run")
    ratios.to_csv(rd.file("ratios.csv"))

    first = next(iter(runs.values()))
    k = slice_index(first)
    fig5_label = next((lab for lab, r in runs.items() if r.elastic == "tissue"), next(iter(runs)))
    figs = {
        "fig2_dataset.png": plot_dataset(first, k),
        "fig3_errors.png": plot_errors(runs, k),
        "fig4_ratios.png": plot_ratios(runs),
        "uncertainty.png": plot_uncertainty(runs, k),
    }
    figs["fig5_boundary_node.png"], fig5 = plot_boundary_node(runs[fig5_label])
    fig5["run"] = fig5_label
    for name, fig in figs.items():
        fig.savefig(rd.file(name), dpi=100)

    summaries = {lab: _run_summary(r) for lab, r in runs.items()}
    report = {
        "runs": summaries,
        "slice_k": k,
        "table1_mm": t1.to_dict(orient="index"),
        "table2_mm2": t2.to_dict(orient="index"),
        "coverage": cov.to_dict(orient="index"),
        "ratios": {f"{a}/{g}": v for (a, g), v in ratios.to_dict(orient="index").items()},
        "fig5": fig5,
        "paper": PAPER,
    }
    rd.file("report.json").write_text(json.dumps(_clean(report), indent=2))
    rd.file("report.md").write_text(_markdown(runs, summaries, t1, t2, cov, ratios, fig5))
