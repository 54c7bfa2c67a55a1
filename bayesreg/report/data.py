"""Reading finished run directories for the report (:class:`RunData`), and the paper's values.

Units: displacements and distances in world mm, MSE in mm^2.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = ["PAPER", "RunData", "load_run", "as_runs", "true_ratio", "TISSUE_NAMES", "TISSUE_LABELS",
           "SKULL_LABEL", "TISSUE_COLORS", "LEVELS"]


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


TISSUE_LABELS = {"csf": 1, "gm": 2, "wm": 3}  # label map coding (bayesreg.data.labels)


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
    info : dict
        ``run.json``
    u_b : (C, D, B, 3) ndarray
        boundary displacement draws, mm (the mesh surface's nodes: of a run that sampled
        every node, ``model.interior: sample``, the surface's draws alone)
    boundary : (B,) int ndarray
        mesh node index of each boundary node in ``u_b``
    lam, mu, ratio : (C, D, G) ndarray
        Lamé parameter draws and ``lam/mu`` per group
    groups : tuple of str
        elastic group names (``("csf", "gm", "wm")`` or ``("all",)``)
    points : (N, 3) ndarray
        undeformed mesh nodes, world mm
    tets : (M, 4) int ndarray
    tissue : (M,) int ndarray
        0 CSF, 1 GM, 2 WM
    u_true : (N, 3) ndarray
        synthetic truth, mm
    u_init : (N, 3) ndarray or None
        central starting configuration, mm
    affine : (4, 4) ndarray
        voxel-to-world of the image grid
    f, m : (I, J, K) ndarray
        fixed and moving image (``m`` None if absent)
    labels : (I, J, K) int ndarray
        0 background, 1 CSF, 2 GM, 3 WM, 4 skull
    disp_mean, disp_true : (I, J, K, 3) ndarray
        posterior mean and true field, mm
    disp_init, disp_sd : (I, J, K, 3) ndarray or None
        initial field, posterior sd, mm
    disp_norm_iqr : (I, J, K) ndarray or None
        posterior IQR of ``|u|``, mm
    in_mesh : (I, J, K) bool ndarray or None
        voxels inside the undeformed mesh
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


def _nifti(path: Path, *, required: bool = True):
    import nibabel as nib

    if not path.exists():
        if required:
            raise FileNotFoundError(f"{path.name} not found in run directory {path.parent}")
        return None, None
    img = nib.load(str(path))
    return np.asarray(img.dataobj), np.asarray(img.affine, np.float64)


def _field(path: Path, *, required: bool = True):
    """A displacement field file as ``(I, J, K, 3)`` RAS mm (any form
    :func:`bayesreg.interop.transforms.load_displacement` reads)."""
    from bayesreg.interop.transforms import load_displacement

    if not path.exists():
        if required:
            raise FileNotFoundError(f"{path.name} not found in run directory {path.parent}")
        return None, None
    img = load_displacement(path)
    return img.data, np.asarray(img.affine, np.float64)


def load_run(path) -> RunData:
    """Read a finished run directory (written by :func:`bayesreg.outputs.write.write_outputs`).

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

    from bayesreg.sampling.diagnostics import group_draws
    from bayesreg.mesh.tetmesh import boundary_nodes

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
    if "label" in mesh.cell_data:  # the label map's coding, 1 CSF, 2 GM, 3 WM
        tissue = np.asarray(mesh.cell_data["label"][0]).astype(int) - 1
    elif "tissue" in mesh.cell_data:  # runs written before: tissue index 0, 1, 2
        tissue = np.asarray(mesh.cell_data["tissue"][0]).astype(int)
    else:
        tissue = np.zeros(len(tets), int)
    u_init = mesh.point_data.get("u_init")

    tree = az.from_netcdf(path / "posterior.nc")
    try:
        post = tree.posterior
        consts = tree.constant_data if "constant_data" in tree.children else {}
        missing = [v for v in ("u_b", "lam", "mu") if v not in post and f"{v}_fixed" not in consts]
        if missing:
            raise ValueError(f"posterior.nc of run {path} lacks {missing}")
        u_b = np.asarray(post["u_b"].transpose("chain", "draw", "node", "axis").values, float)
        boundary = np.asarray(post["node"].values, int)
        # a run that sampled every node (model.interior: sample): the surface's alone, as
        # the paper's tables and figures mean by boundary
        surface = np.isin(boundary, boundary_nodes(tets))
        if not surface.all():
            u_b, boundary = u_b[:, :, surface], boundary[surface]
        lam, mu = (group_draws(tree, v) for v in ("lam", "mu"))
        ratio = (np.asarray(post["ratio"].transpose("chain", "draw", "group").values, float)
                 if "ratio" in post else lam / mu)
        groups = tuple(str(g) for g in post["group"].values)
    finally:
        tree.close()

    f, affine = _nifti(path / "f.nii.gz")
    labels, _ = _nifti(path / "labels.nii.gz")
    disp_mean, _ = _field(path / "displacement_mean.nii.gz")
    disp_true, _ = _field(path / "displacement_true.nii.gz")
    m, _ = _nifti(path / "m.nii.gz", required=False)
    disp_init, _ = _field(path / "displacement_init.nii.gz", required=False)
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


def as_runs(runs) -> dict:
    """``{label: RunData}`` from a RunData or a mapping of labels to RunData or paths."""
    if isinstance(runs, RunData):
        return {runs.name: runs}
    return {str(k): (v if isinstance(v, RunData) else load_run(v)) for k, v in runs.items()}


def true_ratio(run: RunData, group: str) -> float | None:
    t = run.true_elastic
    if t is not None and group in t["lam"] and group in t["mu"]:
        return float(t["lam"][group]) / float(t["mu"][group])
    r = (run.info.get("errors") or {}).get("ratio", {}).get(group, {})
    return float(r["true"]) if "true" in r else None
