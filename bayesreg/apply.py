"""The posterior of a finished run applied to what users carry: transforms for ITK, ANTs and
3D Slicer, images, label maps and points (targets), with their uncertainty.

A run stores the sampled boundary displacements ``u_b`` and the elastic parameters of every
kept draw (``posterior.nc``) and its mesh and images (``checkpoint/problem.npz``).  A draw's
full nodal field is its interior FE solve ``K_ii u_i = -K_ib u_b`` at the draw's ``lam`` and
``mu`` (the model's own interior, paper Eq. 5), here by a sparse direct solve (SciPy).

Directions (:mod:`bayesreg.interop.transforms`): ``"to_fixed"`` resamples an image given in the
moving (intra-operative) frame onto the fixed grid through ``x -> x + u(x)``;
``"to_moving"`` carries an image given in the fixed (pre-operative) frame, such as a tumour
segmentation, onto the moving grid through the FE map's exact inverse.  Points always go
from the fixed frame to the moving frame (``p -> p + u(p)``).

Units: world (RAS) mm everywhere; point files in other conventions (3D Slicer's LPS) are
converted on reading and writing.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from bayesreg._files import dumps_json, write_text_atomic
from bayesreg.data.images import Image, grid_points, interpolate_numpy, save_nifti
from bayesreg.data.labels import tissue_label
from bayesreg.mesh.tetmesh import Mesh
from bayesreg.interop.transforms import (FIXED_TO_MOVING, MOVING_TO_FIXED, displace_points,
                                 inverse_displacement, locate_points, save_displacement)
from bayesreg.mesh.warp import interpolation_matrix

__all__ = ["RunPosterior", "load_posterior", "draw_indices", "nodal_field_draws", "export",
           "FORMATS", "warp_image", "warp_labels", "LabelPosterior", "map_points", "PointPosterior",
           "target_errors", "read_points", "write_points", "save_label_posterior"]


FORMATS = ("itk", "ants", "slicer", "nifti")

CHI2_95_3D = 7.814727903251178  # scipy.stats.chi2.ppf(0.95, 3): 95% region of a 3-D Gaussian


class RunPosterior(NamedTuple):
    """What a finished run holds of its posterior (:func:`load_posterior`).

    Attributes
    ----------
    path : Path
    mesh : Mesh
        Nodes ``(N, 3)`` world mm, tets ``(M, 4)``, tissue ``(M,)`` (0 CSF, 1 GM, 2 WM).
    f, m : Image
        Fixed and moving images (the fields' grids).
    labels : Image
        The run's label map.
    u_b : (S, n_b, 3) ndarray
        Pooled draws of the boundary displacements, mm (chains one after another).
    lam, mu : (S, G) ndarray
        Lamé parameters of each parameter group per draw (fixed ones included).
    group : (M,) int ndarray
        Parameter group of each element.
    u_mean, u_sd : (N, 3) ndarray
        Posterior mean and sd of the nodal displacement, mm (RAS components), as the run
        wrote them in ``mesh.vtu``.
    u_true : (N, 3) ndarray or None
        The synthetic truth (synthetic runs).
    d : (S, n_i, 3) ndarray or None
        The model discrepancy per draw, mm, in ``mesh.interior`` order (runs with
        ``model.discrepancy: interior`` or ``modes``), added to the interior's FE solve.
    """

    path: Path
    mesh: Mesh
    f: Image
    m: Image
    labels: Image
    u_b: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    group: np.ndarray
    u_mean: np.ndarray
    u_sd: np.ndarray
    u_true: np.ndarray | None
    d: np.ndarray | None = None

    @property
    def n_draws(self) -> int:
        return len(self.u_b)


def load_posterior(run_dir) -> RunPosterior:
    """Read a finished run directory's posterior, mesh and images.

    Parameters
    ----------
    run_dir : str or Path

    Returns
    -------
    RunPosterior

    Raises
    ------
    FileNotFoundError
        If ``posterior.nc``, ``mesh.vtu`` or the checkpoint (config, problem) is missing: the
        run has not finished, or was written without ``output.checkpoint``.
    """
    import arviz as az
    import meshio

    from bayesreg.checkpoint import Checkpoint
    from bayesreg.sampling.diagnostics import group_draws
    from bayesreg.model.problem import parameter_layout, sampled_mesh

    path = Path(run_dir)
    for name in ("posterior.nc", "mesh.vtu"):
        if not (path / name).is_file():
            raise FileNotFoundError(f"{path / name} not found: {path} is not a finished run")
    ckpt = Checkpoint(path)
    if not ckpt.problem_path.is_file():
        raise FileNotFoundError(f"{ckpt.problem_path} not found: the run's mesh and images are "
                                "needed (a run written with output.checkpoint: true)")
    cfg = ckpt.load_config()
    data = ckpt.load_problem()
    data = data._replace(mesh=sampled_mesh(cfg, data.mesh))  # boundary: the sampled nodes
    _, group = parameter_layout(cfg, data.mesh)
    tree = az.from_netcdf(path / "posterior.nc")
    try:
        post = tree.posterior
        u_b = np.asarray(post["u_b"].transpose("chain", "draw", "node", "axis").values, np.float64)
        lam, mu = group_draws(tree, "lam"), group_draws(tree, "mu")
        nodes = np.asarray(post["node"].values)
        disc = (np.asarray(post["d"].transpose("chain", "draw", "interior_node", "axis").values,
                           np.float64) if "d" in post else None)
    finally:
        tree.close()
    if not np.array_equal(nodes, data.mesh.boundary):
        raise ValueError(f"{path}: posterior.nc's boundary nodes differ from the checkpoint's "
                         "mesh (files of two different runs?)")
    c, d = u_b.shape[:2]
    u_b, lam, mu = (a.reshape(c * d, *a.shape[2:]) for a in (u_b, lam, mu))
    if disc is not None:
        disc = disc.reshape(c * d, *disc.shape[2:])
    # the run's own nodal moments (over every draw's stored interior): no solve of all draws
    point_data = meshio.read(path / "mesh.vtu").point_data
    return RunPosterior(path, data.mesh, data.f, data.m, data.labels, u_b, lam, mu,
                        np.asarray(group), np.asarray(point_data["u_mean"], np.float64),
                        np.asarray(point_data["u_sd"], np.float64),
                        None if data.truth is None else np.asarray(data.truth.u), disc)


def draw_indices(n_draws: int, k: int | None) -> np.ndarray:
    """``k`` draws spread evenly over the pooled ``n_draws`` (every draw for ``None`` or
    ``k >= n_draws``): indices ``(min(k, n_draws),)``."""
    if k is None or k >= n_draws:
        return np.arange(n_draws)
    if k < 1:
        raise ValueError(f"the number of draws must be >= 1, got {k}")
    return np.unique(np.linspace(0, n_draws - 1, int(k)).round().astype(int))


def nodal_field_draws(rp: RunPosterior, indices) -> np.ndarray:
    """Full nodal displacements ``(K, N, 3)`` mm of the draws ``indices``: the sampled
    boundary and the interior's FE solve at each draw's ``lam``, ``mu`` (SciPy sparse LU),
    plus the draw's model discrepancy where the run has one.
    Draws sharing their parameters (a fixed-parameter model) share one factorisation."""
    from bayesreg.fem.element import interior_solver, node_dofs, stiffness_matrix

    mesh = rp.mesh
    n = len(mesh.nodes)
    b = np.asarray(mesh.boundary)
    inner = mesh.interior
    db, di = node_dofs(b), node_dofs(inner)
    out = np.empty((len(indices), n, 3))
    cache: dict[bytes, tuple] = {}
    for k, s in enumerate(np.asarray(indices)):
        full = np.empty(3 * n)
        full[db] = rp.u_b[s].ravel()
        if len(di):  # (none where every node is sampled: model.interior: sample)
            key = np.concatenate([rp.lam[s], rp.mu[s]]).tobytes()
            if key not in cache:
                if len(cache) > 8:
                    cache.clear()
                cache[key] = interior_solver(stiffness_matrix(
                    mesh.nodes, mesh.tets, rp.lam[s][rp.group], rp.mu[s][rp.group]), b, inner)
            full[di] = cache[key].solve(full[db])
            if rp.d is not None:
                full[di] += rp.d[s].ravel()
        out[k] = full.reshape(n, 3)
    return out


def _grid_field(w, u, grid: Image) -> np.ndarray:
    """Nodal ``u`` ``(N, 3)`` on ``grid`` through the interpolation matrix ``w`` of
    :func:`bayesreg.mesh.warp.interpolation_matrix` (located once per grid, reused per field)."""
    return (w @ u).reshape(*grid.data.shape[:3], 3)


_NAMES = {
    # format: (fixed->moving, moving->fixed) file names of the mean ({} = "mean" or "draw0007")
    "itk": ("fixed_to_moving_{}.nii.gz", "moving_to_fixed_{}.nii.gz"),
    "nifti": ("fixed_to_moving_{}.nii.gz", "moving_to_fixed_{}.nii.gz"),
    "slicer": ("fixed_to_moving_{}.nii.gz", "moving_to_fixed_{}.nii.gz"),
    "ants": ("{}_1Warp.nii.gz", "{}_1InverseWarp.nii.gz"),
}


def export(run_dir, fmt: str = "itk", *, draws: int = 0, out=None, inverse: bool = True) -> dict:
    """Write a run's posterior mean (and ``draws`` posterior draws) as transforms.

    Parameters
    ----------
    run_dir : str or Path
        A finished run directory.
    fmt : {"itk", "ants", "slicer", "nifti"}
        ``itk``/``ants``/``slicer``: 5-D ITK displacement fields (LPS vectors, intent VECTOR;
        ANTs' ``*_1Warp`` / ``*_1InverseWarp`` names for ``ants``); ``slicer`` adds the mesh
        as ``mesh.vtk`` in LPS (3D Slicer's convention for model files) with ``u_mean`` and
        ``u_sd`` and the elements' tissue as ``label`` (1 CSF, 2 GM, 3 WM); ``nifti``: RAS vectors, intent DISPVECT.
    draws : int
        Number of posterior draws to write besides the mean (evenly spread over the chains).
    out : str or Path, optional
        Folder (default ``RUN_DIR/export/<fmt>``), created if needed.
    inverse : bool
        Also write the inverse fields (moving to fixed, on ``m``'s grid).

    Returns
    -------
    dict
        The manifest written to ``transforms.json``: files, their direction and convention,
        and how each tool applies them.

    Raises
    ------
    ValueError
        On an unknown ``fmt`` or negative ``draws``; an inverse field where a draw inverts
        an element (the message names the draw).
    FileNotFoundError
        See :func:`load_posterior`.

    Examples
    --------
    >>> export("runs/quickstart", "ants", draws=10)                 # doctest: +SKIP
    """
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    if draws < 0:
        raise ValueError(f"draws must be >= 0, got {draws}")
    rp = load_posterior(run_dir)
    out = Path(out) if out is not None else rp.path / "export" / fmt
    out.mkdir(parents=True, exist_ok=True)
    conv = "nifti" if fmt == "nifti" else "itk"
    fwd_name, inv_name = _NAMES[fmt]
    idx = draw_indices(rp.n_draws, draws) if draws else np.zeros(0, int)
    fields = [("mean", rp.u_mean)]
    if len(idx):
        fields += [(f"draw{int(s):05d}", u) for s, u in zip(idx, nodal_field_draws(rp, idx))]
    files = []
    w_f, _ = interpolation_matrix(rp.mesh, rp.f)
    for tag, u in fields:
        fwd = save_displacement(_grid_field(w_f, u, rp.f), rp.f.affine, out / fwd_name.format(tag),
                                convention=conv, description=FIXED_TO_MOVING)
        entry = {"what": tag, "fixed_to_moving": fwd.name}
        if inverse:
            try:
                v, _ = inverse_displacement(rp.mesh, u, rp.m)
            except ValueError as exc:
                raise ValueError(f"export {tag}: {exc}") from None
            entry["moving_to_fixed"] = save_displacement(
                v, rp.m.affine, out / inv_name.format(tag), convention=conv,
                description=MOVING_TO_FIXED).name
        files.append(entry)
    if fmt == "slicer":
        _write_slicer_mesh(rp, out / "mesh.vtk")
    manifest = {
        "run": str(rp.path), "format": fmt,
        "convention": ("5-D (I,J,K,1,3) NIfTI, NIFTI_INTENT_DISPVECT, RAS vectors, mm" if conv == "nifti"
                       else "5-D (I,J,K,1,3) NIfTI, NIFTI_INTENT_VECTOR, LPS vectors, mm (ITK/ANTs)"),
        "fixed_to_moving": "x_m = x_f + u(x_f) on the fixed image's grid: resamples the moving "
                           "(intra-operative) image onto the fixed grid, and maps points of the fixed "
                           "image to the moving frame (ITK's resampling convention)",
        "moving_to_fixed": "its inverse on the moving image's grid: resamples the fixed "
                           "(pre-operative) image and its segmentations onto the moving grid",
        "outside_mesh": "zero displacement (identity)",
        "draws_of": int(rp.n_draws), "files": files,
        "apply": {
            "ants": "antsApplyTransforms -d 3 -i m.nii.gz -r f.nii.gz -t <fixed_to_moving> -o m_on_f.nii.gz",
            "simpleitk": "sitk.Resample(m, f, sitk.DisplacementFieldTransform("
                         "sitk.ReadImage(<fixed_to_moving>, sitk.sitkVectorFloat64)))",
            "slicer": "Add Data, choose 'Transform' for the file; put the moving image under it "
                      "(fixed_to_moving) or the pre-operative segmentation (moving_to_fixed)",
        },
    }
    write_text_atomic(out / "transforms.json", dumps_json(manifest, indent=2))
    return manifest


def _write_slicer_mesh(rp: RunPosterior, path: Path) -> None:
    """The mesh in LPS (3D Slicer's convention for model files), ``SPACE=LPS`` in its legacy
    VTK header (where Slicer reads a model file's space), with ``u_mean``, ``u_sd`` (LPS
    components) and ``label`` (the label-map coding of the tissue)."""
    import meshio

    lps = np.array([-1.0, -1.0, 1.0])
    point_data = {"u_mean": rp.u_mean * lps, "u_sd": rp.u_sd}  # an sd has no sign
    if rp.u_true is not None:
        point_data["u_true"] = rp.u_true * lps
    # legacy format 4.2: VTK's reader refuses the integer arrays of meshio's 5.1 ("vtktypeint32")
    meshio.vtk.write(str(path), meshio.Mesh(rp.mesh.nodes * lps, [("tetra", rp.mesh.tets)],
                                            point_data=point_data,
                                            cell_data={"label": [tissue_label(rp.mesh.tissue)]}),
                     binary=True, fmt_version="4.2")
    # the legacy header's title line (ASCII before the binary data) carries the space: 3D
    # Slicer reads "SPACE=LPS" there (vtkMRMLModelStorageNode::GetCoordinateSystemFromFileHeader)
    lines = path.read_bytes().split(b"\n", 2)
    lines[1] = b"bayesreg posterior mesh, world mm SPACE=LPS"
    path.write_bytes(b"\n".join(lines))


# ---- images and label maps -------------------------------------------------------------

def _direction(direction: str) -> str:
    d = direction.replace("-", "_")
    if d not in ("to_fixed", "to_moving"):
        raise ValueError(f"direction must be 'to_fixed' or 'to_moving', got {direction!r}")
    return d


def _sample_points(rp: RunPosterior, u, direction: str, w_f=None):
    """Output grid and, per output voxel centre, the point of the input image to sample
    (``w_f``: the interpolation matrix on ``f``'s grid, when already built)."""
    if direction == "to_fixed":
        grid = rp.f
        if w_f is None:
            w_f, _ = interpolation_matrix(rp.mesh, grid)
        return grid, grid_points(grid) + _grid_field(w_f, u, grid).reshape(-1, 3)
    grid = rp.m
    v, _ = inverse_displacement(rp.mesh, u, grid)
    return grid, grid_points(grid) + v.reshape(-1, 3)


def warp_image(rp: RunPosterior, image: Image, *, direction: str = "to_fixed", order: int = 1,
               cval: float = 0.0) -> Image:
    """Resample an image through the posterior mean.

    Parameters
    ----------
    rp : RunPosterior
    image : Image
        In the moving frame (``"to_fixed"``) or the fixed frame (``"to_moving"``), any grid.
    direction : {"to_fixed", "to_moving"}
    order : int
        Spline order of the interpolation (0 nearest, 1 linear, 3 cubic; SciPy).
    cval : float
        Value outside ``image``.

    Returns
    -------
    Image
        On the fixed grid (``"to_fixed"``) or the moving grid (``"to_moving"``).
    """
    grid, pts = _sample_points(rp, rp.u_mean, _direction(direction))
    vals = interpolate_numpy(image, pts, order=int(order), cval=cval)
    return Image(vals.reshape(grid.data.shape[:3]), grid.affine)


class LabelPosterior(NamedTuple):
    """A label map carried through posterior draws (:func:`warp_labels`).

    Attributes
    ----------
    probability : Image
        ``(I, J, K, L)``: the fraction of draws in which each voxel takes each label, in
        [0, 1], summing to 1 per voxel.
    most_probable : Image
        ``(I, J, K)``: the label of highest probability.
    values : (L,) ndarray
        The label values, in the order of the last axis of ``probability``.
    n_draws : int
    """

    probability: Image
    most_probable: Image
    values: np.ndarray
    n_draws: int


def warp_labels(rp: RunPosterior, labels: Image, *, direction: str = "to_moving",
                draws: int | None = 100) -> LabelPosterior:
    """Carry a label map through posterior draws: per-label probability and most probable label.

    Each draw's FE map resamples ``labels`` by nearest neighbour (labels are never blended);
    the probabilities are the fractions of draws.

    Parameters
    ----------
    rp : RunPosterior
    labels : Image
        Integer label map (e.g. a tumour segmentation), in the fixed frame for
        ``"to_moving"`` (the default: pre-operative to intra-operative) or the moving frame
        for ``"to_fixed"``.
    direction : {"to_moving", "to_fixed"}
    draws : int or None
        Number of draws (evenly spread; ``None``: every kept draw).

    Returns
    -------
    LabelPosterior

    Raises
    ------
    ValueError
        If ``labels`` holds non-integer values.
    """
    direction = _direction(direction)
    data = np.asarray(labels.data)
    if not np.all(np.mod(data, 1) == 0):
        raise ValueError("warp_labels: the label map holds non-integer values")
    values = np.unique(data).astype(np.int64)
    idx = draw_indices(rp.n_draws, draws)
    w_f = interpolation_matrix(rp.mesh, rp.f)[0] if direction == "to_fixed" else None
    counts = None
    for u in nodal_field_draws(rp, idx):
        grid, pts = _sample_points(rp, u, direction, w_f)
        lab = interpolate_numpy(Image(data.astype(np.float64), labels.affine), pts, order=0,
                                cval=float(values[0] if 0 not in values else 0))
        k = np.searchsorted(values, lab.astype(np.int64))
        k = np.clip(k, 0, len(values) - 1)
        if counts is None:
            counts = np.zeros((len(pts), len(values)), np.int32)
        np.add.at(counts, (np.arange(len(pts)), k), 1)
    shape = grid.data.shape[:3]
    prob = counts / float(len(idx))
    best = values[np.argmax(counts, axis=1)]
    return LabelPosterior(Image(prob.reshape(*shape, len(values)).astype(np.float32), grid.affine),
                          Image(best.reshape(shape).astype(np.int32), grid.affine), values, len(idx))


# ---- points -----------------------------------------------------------------------------

class PointPosterior(NamedTuple):
    """Fixed-frame points carried to the moving frame through the posterior (:func:`map_points`).

    Attributes
    ----------
    names : list of str
    points : (P, 3) ndarray
        The given points, fixed frame, world mm.
    mean : (P, 3) ndarray
        Posterior mean position in the moving frame, mm.
    cov : (P, 3, 3) ndarray
        Posterior covariance of the position, mm^2.
    semi_axes : (P, 3) ndarray
        Semi-axes of the 95% credible ellipsoid (Gaussian approximation,
        ``sqrt(chi2_3(0.95) * eigenvalues)``), mm, largest first.
    axes : (P, 3, 3) ndarray
        Unit directions of the semi-axes (``axes[p, :, k]``).
    draws : (S, P, 3) ndarray
        The positions in every draw used.
    inside : (P,) bool
        The point lies inside the mesh (outside, the model does not move it).
    """

    names: list
    points: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    semi_axes: np.ndarray
    axes: np.ndarray
    draws: np.ndarray
    inside: np.ndarray


def map_points(rp: RunPosterior, points, names=None, *, draws: int | None = None) -> PointPosterior:
    """Posterior of the moving-frame positions of fixed-frame points (targets, landmarks).

    Parameters
    ----------
    rp : RunPosterior
    points : (P, 3) array
        Fixed frame, world (RAS) mm.
    names : list of str, optional
    draws : int or None
        Number of draws (``None``: every kept draw).

    Returns
    -------
    PointPosterior
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    names = list(names) if names is not None else [f"p{k}" for k in range(len(points))]
    located = locate_points(rp.mesh, points)
    idx = draw_indices(rp.n_draws, draws)
    pos, inside = displace_points(rp.mesh, nodal_field_draws(rp, idx), points, located=located)
    mean = pos.mean(axis=0)
    dev = pos - mean
    cov = np.einsum("spi,spj->pij", dev, dev) / max(len(pos) - 1, 1)
    evals, evecs = np.linalg.eigh(cov)
    evals, evecs = evals[:, ::-1], evecs[:, :, ::-1]
    semi = np.sqrt(CHI2_95_3D * np.clip(evals, 0.0, None))
    return PointPosterior(names, points, mean, cov, semi, evecs, pos, inside)


def target_errors(pp: PointPosterior, true_moving) -> dict:
    """Target registration error of the posterior against known moving-frame positions.

    Parameters
    ----------
    pp : PointPosterior
    true_moving : (P, 3) array
        The points' true positions in the moving frame, world mm.

    Returns
    -------
    dict
        ``tre_mm`` (P,) error of the posterior mean; ``tre_start_mm`` (P,) the error of
        not moving the points; ``mahalanobis2`` (P,) squared Mahalanobis distance of the truth
        from the mean; ``inside_95`` (P,) the truth inside its 95% ellipsoid; summaries
        ``tre_median_mm``, ``tre_max_mm``, ``coverage_95`` (fraction inside).
    """
    true_moving = np.asarray(true_moving, np.float64).reshape(-1, 3)
    err = true_moving - pp.mean
    d2 = np.array([e @ np.linalg.pinv(c, hermitian=True) @ e for e, c in zip(err, pp.cov)])
    inside = d2 <= CHI2_95_3D
    tre = np.linalg.norm(err, axis=1)
    return {"tre_mm": tre, "tre_start_mm": np.linalg.norm(true_moving - pp.points, axis=1),
            "mahalanobis2": d2, "inside_95": inside, "tre_median_mm": float(np.median(tre)),
            "tre_max_mm": float(tre.max()), "coverage_95": float(inside.mean())}


_LPS = np.array([-1.0, -1.0, 1.0])


def read_points(path):
    """Points from a CSV (columns ``x, y, z`` world RAS mm, optional ``name``), a 3D Slicer
    markups file (``.mrk.json``) or a Slicer fiducial list (``.fcsv``).

    Returns
    -------
    names : list of str
    points : (P, 3) ndarray
        World RAS mm (Slicer's LPS files converted).

    Raises
    ------
    ValueError
        If the file has no points or lacks coordinates (the message names the file).
    """
    path = Path(path)
    name = path.name.lower()
    names, pts = [], []
    if name.endswith(".mrk.json") or name.endswith(".json"):
        doc = json.loads(path.read_text())
        for mk in doc.get("markups", []):
            lps = str(mk.get("coordinateSystem", "LPS")).upper() == "LPS"
            for cp in mk.get("controlPoints", []):
                p = np.asarray(cp["position"], np.float64)
                pts.append(p * _LPS if lps else p)
                names.append(str(cp.get("label") or f"p{len(names)}"))
    elif name.endswith(".fcsv"):
        lps, cols = False, None
        for line in path.read_text().splitlines():
            if line.startswith("#"):
                if "CoordinateSystem" in line:
                    v = line.split("=", 1)[1].strip().upper()
                    lps = v in ("LPS", "1")
                if line.startswith("# columns"):
                    cols = [c.strip() for c in line.split("=", 1)[1].split(",")]
                continue
            if not line.strip():
                continue
            row = next(csv.reader([line]))
            c = cols or ["id", "x", "y", "z"]
            p = np.array([float(row[c.index(a)]) for a in ("x", "y", "z")])
            pts.append(p * _LPS if lps else p)
            lab = row[c.index("label")] if "label" in c and c.index("label") < len(row) else ""
            names.append(lab or f"p{len(names)}")
    else:
        with path.open(newline="") as fh:
            reader = csv.DictReader(fh)
            fields = {f.strip().lower(): f for f in reader.fieldnames or []}
            if not {"x", "y", "z"} <= set(fields):
                raise ValueError(f"{path}: a points CSV needs columns x, y, z (world RAS mm)")
            for row in reader:
                pts.append([float(row[fields[a]]) for a in ("x", "y", "z")])
                nm = row.get(fields.get("name", ""), "") if "name" in fields else ""
                names.append(nm or f"p{len(names)}")
    if not pts:
        raise ValueError(f"{path}: no points found")
    return names, np.asarray(pts, np.float64).reshape(-1, 3)


def write_points(path, pp: PointPosterior, errors: dict | None = None) -> Path:
    """Write a :class:`PointPosterior`: a CSV table (one row per point: the given position,
    the posterior mean, sd per axis, the 95% ellipsoid's semi-axes, and with ``errors`` the
    TRE and whether the truth is inside), or a 3D Slicer markups file of the mean positions
    (``.mrk.json``, LPS) when ``path`` ends so."""
    path = Path(path)
    if path.name.lower().endswith(".mrk.json"):
        doc = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                          "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
               "markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
                            "controlPoints": [
                                {"id": str(k + 1), "label": n, "position": list(map(float, p * _LPS)),
                                 "description": f"posterior mean; 95% semi-axes {np.round(a, 2).tolist()} mm"}
                                for k, (n, p, a) in enumerate(zip(pp.names, pp.mean, pp.semi_axes))]}]}
        write_text_atomic(path, json.dumps(doc, indent=2))
        return path
    sd = np.sqrt(np.einsum("pii->pi", pp.cov))
    head = ["name", "x", "y", "z", "mean_x", "mean_y", "mean_z", "sd_x", "sd_y", "sd_z",
            "semi_axis_1", "semi_axis_2", "semi_axis_3", "inside_mesh"]
    if errors is not None:
        head += ["tre_mm", "tre_start_mm", "inside_95"]
    rows = [",".join(head)]
    for k, n in enumerate(pp.names):
        vals = [*pp.points[k], *pp.mean[k], *sd[k], *pp.semi_axes[k]]
        row = [n] + [f"{v:.4f}" for v in vals] + [str(bool(pp.inside[k]))]
        if errors is not None:
            row += [f"{errors['tre_mm'][k]:.4f}", f"{errors['tre_start_mm'][k]:.4f}",
                    str(bool(errors["inside_95"][k]))]
        rows.append(",".join(row))
    write_text_atomic(path, "\n".join(rows) + "\n")
    return path


def save_label_posterior(lp: LabelPosterior, out) -> tuple[Path, Path]:
    """Write ``<out>_probability.nii.gz`` (``(I, J, K, L)``, one volume per label, the
    label values in the description) and ``<out>_most_probable.nii.gz``."""
    out = str(out).removesuffix(".nii.gz")
    p1, p2 = Path(f"{out}_probability.nii.gz"), Path(f"{out}_most_probable.nii.gz")
    save_nifti(lp.probability, p1)
    save_nifti(lp.most_probable, p2)
    write_text_atomic(Path(f"{out}_labels.json"),
                      dumps_json({"labels": [int(v) for v in lp.values], "draws": lp.n_draws,
                                  "probability_file": p1.name}, indent=2))
    return p1, p2
