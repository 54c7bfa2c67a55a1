"""Tetrahedral meshing of the intracranial volume (paper Sec. 2.1, 4.1).

Recipe: smooth the intracranial mask, extract its surface with
``skimage.measure.marching_cubes``, tetrahedralise with fTetWild (``pytetwild``) at a target
edge length, then label every element by the majority tissue over sample points inside it
(:func:`bayesreg.mesh.tetmesh.label_elements`), so that the element labels follow the tissue
boundaries at the resolution of the mesh (as in the paper's Fig. 2c).
:func:`mesh_brain_sized` re-meshes until the node count is near a target (the paper's 801);
:func:`carve_skull` frees the skull voxels that a coarse mesh covers at rest.

Meshing is not bit-reproducible (fTetWild draws from an unseeded generator: one thread
gives a different mesh at every call too); a run stores its mesh, and
:func:`bayesreg.mesh.tetmesh.read_mesh` (``mesh.file`` in a config) reads it back.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import scipy.ndimage as ndi

from bayesreg.data import labels as L
from bayesreg._checks import check_number
from bayesreg.mesh.constraints import points_forbidden, skull_constraint
from bayesreg.data.images import Image, check_image, world_to_voxel
from bayesreg.mesh.tetmesh import (
    Mesh, MeshError, boundary_nodes, compact_nodes, label_elements, mesh_pieces, mesh_quality,
    orient_tets)
from bayesreg.mesh.warp import interpolation_matrix

__all__ = ["mesh_brain", "mesh_brain_sized", "carve_skull", "tetrahedralize"]


def _surface(mask: np.ndarray, affine, sigma_vox: float, step_size: int, sigma_mm: float = 0.0):
    from skimage.measure import marching_cubes

    smooth = ndi.gaussian_filter(mask.astype(np.float64), sigma_vox) if sigma_vox > 0 else mask
    peak = float(np.max(smooth))
    if not peak > 0.5:  # marching cubes: "Surface level must be within volume data range"
        raise MeshError(
            f"smoothing_sigma_mm={sigma_mm:g} removed the brain surface: the smoothed "
            f"intracranial mask peaks at {peak:.3g}, below the 0.5 level of the surface; "
            "use a smaller smoothing_sigma_mm")
    padded = np.pad(smooth, 2)
    verts, faces, _, _ = marching_cubes(padded, level=0.5, step_size=step_size)
    verts = verts - 2.0
    world = verts @ np.asarray(affine)[:3, :3].T + np.asarray(affine)[:3, 3]
    faces = faces.astype(np.int32)
    # outward orientation: positive enclosed volume
    tri = world[faces]
    vol = np.sum(np.einsum("fi,fi->f", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))) / 6.0
    if vol < 0:
        faces = faces[:, ::-1].copy()
    return world, faces


def tetrahedralize(verts, faces, *, edge_length_mm: float, epsilon: float = 2e-2,
                   num_threads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """fTetWild (``pytetwild.tetrahedralize``) of a closed surface, in a child process.

    fTetWild's native library replaces the process's signal handlers: in the calling
    process, Ctrl-C during the call would end it outright, and after the call it would no
    longer raise ``KeyboardInterrupt`` (the run could not say what it kept, nor put back a
    run that ``--overwrite`` replaced).  The child (``bayesreg/mesh/_tetwild_worker.py``, a
    fresh interpreter that imports only NumPy and pytetwild: about half a second) keeps the
    caller's signal handling intact and turns a crash of the mesher into an error.  Ctrl-C
    in a terminal reaches both processes; an interrupt of the caller alone (a notebook's)
    ends the child too; either way ``KeyboardInterrupt`` is raised here.

    Parameters
    ----------
    verts : (V, 3) array
        Surface vertices, world mm.
    faces : (F, 3) int array
        Triangles, oriented outward.
    edge_length_mm : float
        Target edge length (fTetWild's ``edge_length_abs``), mm.
    epsilon : float
        Envelope size relative to the bounding-box diagonal.
    num_threads : int
        fTetWild's threads (0: all).

    Returns
    -------
    nodes : (N, 3) float64 array
        World mm.
    tets : (M, 4) int64 array

    Raises
    ------
    MeshError
        fTetWild failed or crashed (its last lines of output, or the signal, in the message).
    KeyboardInterrupt
        The meshing was interrupted (Ctrl-C, SIGTERM under the CLI).
    """
    worker = Path(__file__).with_name("_tetwild_worker.py")
    # fTetWild writes a scratch file (__tracked_surface.stl) into its working folder
    with tempfile.TemporaryDirectory(prefix="bayesreg-tetwild-") as scratch:
        src, dst = Path(scratch) / "surface.npz", Path(scratch) / "mesh.npz"
        np.savez(src, verts=np.asarray(verts, np.float64), faces=np.asarray(faces, np.int32),
                 edge_length_abs=float(edge_length_mm), epsilon=float(epsilon),
                 num_threads=int(num_threads))
        with open(Path(scratch) / "log.txt", "w+b") as log:
            proc = subprocess.Popen([sys.executable, str(worker), str(src), str(dst)], cwd=scratch,
                                    stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
            try:
                status = proc.wait()
            except BaseException:  # KeyboardInterrupt (the caller's alone: a notebook's)
                proc.kill()
                proc.wait()
                raise
            if status in (-signal.SIGINT, 128 + signal.SIGINT):
                # Ctrl-C reached the mesher (its handler exits with 130) before this process
                # raised its own KeyboardInterrupt
                raise KeyboardInterrupt("meshing interrupted")
            if status != 0 or not dst.is_file():
                log.seek(0)
                lines = log.read().decode(errors="replace").strip().splitlines()
                why = (f"killed by signal {-status}" if status < 0 else f"exit status {status}")
                tail = "; ".join(lines[-3:]) if lines else "no output"
                raise MeshError(f"fTetWild failed ({why}): {tail}")
        with np.load(dst) as out:
            return out["nodes"], out["tets"]


_UNSET = object()


def _check_mesh_args(edge_length_mm, smoothing_sigma_mm=_UNSET, epsilon=_UNSET,
                     step_size=_UNSET) -> None:
    """``ValueError`` naming the first invalid argument of :func:`mesh_brain` (those given)."""
    check_number(edge_length_mm, "edge_length_mm")
    if smoothing_sigma_mm is not _UNSET:
        check_number(smoothing_sigma_mm, "smoothing_sigma_mm", positive=False)
    if epsilon is not _UNSET:
        check_number(epsilon, "epsilon")
    if step_size is not _UNSET:
        ok = isinstance(step_size, (int, float, np.integer, np.floating)) and not isinstance(
            step_size, (bool, np.bool_)) and np.isfinite(step_size) and step_size >= 1
        if not (ok and int(step_size) == step_size):
            raise ValueError(f"step_size must be an integer >= 1, got {step_size!r}")


def mesh_brain(
    labels: Image,
    *,
    edge_length_mm: float = 16.0,
    smoothing_sigma_mm: float = 4.0,
    epsilon: float = 2e-2,
    step_size: int = 2,
    num_threads: int = 0,
) -> Mesh:
    """Tetrahedral mesh of the intracranial volume (CSF + GM + WM) of a label map.

    Parameters
    ----------
    labels : Image
        Internal label coding (see :mod:`bayesreg.data.labels`).
    edge_length_mm : float
        Target edge length; 16 mm gives about the paper's mesh (~800 nodes, ~3800 tets).
    smoothing_sigma_mm : float
        Gaussian smoothing of the mask before surface extraction, mm.
    epsilon : float
        fTetWild envelope size relative to the bounding-box diagonal.
    step_size : int
        Marching-cubes step (voxels).
    num_threads : int
        fTetWild threads (0: all).

    Returns
    -------
    Mesh

    Raises
    ------
    ValueError
        If ``labels`` is not a 3D :class:`~bayesreg.data.images.Image` with a finite invertible
        affine, ``edge_length_mm`` or ``epsilon`` is not a finite number > 0,
        ``smoothing_sigma_mm`` not a finite number >= 0, or ``step_size`` not an integer >= 1.
    MeshError
        (a ``ValueError``) If the label map has (almost) no intracranial voxels, the smoothing
        removes the brain surface (``smoothing_sigma_mm`` too large for the brain),
        ``edge_length_mm`` exceeds the largest extent of the brain's surface (checked before
        fTetWild runs: beyond the brain's size its run time grows and its mesh does not
        coarsen), meshing fails, returns too few elements, or any element is
        inverted/degenerate.

    Warns
    -----
    UserWarning
        fTetWild's mesh had pieces joined to the largest by no face (islands of the smoothed
        mask): only the largest is kept, the count of dropped elements is named.
    """
    _check_mesh_args(edge_length_mm, smoothing_sigma_mm, epsilon, step_size)
    labels = check_image(labels, "labels")
    data = np.asarray(labels.data)
    inside = np.isin(data, L.TISSUE_LABELS)
    if inside.sum() < 27:
        raise MeshError("the label map has (almost) no intracranial voxels to mesh")
    sigma_vox = float(smoothing_sigma_mm) / float(np.mean(labels.spacing))
    verts, faces = _surface(inside, labels.affine, sigma_vox, int(step_size), float(smoothing_sigma_mm))
    extent = np.ptp(verts, axis=0)
    if float(edge_length_mm) > float(extent.max()):
        raise MeshError(
            f"edge_length_mm={float(edge_length_mm):g} exceeds the largest extent of the "
            f"intracranial surface ({extent.max():.0f} mm; its box is "
            f"{' x '.join(f'{e:.0f}' for e in extent)} mm): no element can be that long, and "
            "fTetWild spends minutes trying; use a smaller edge length")
    nodes, tets = tetrahedralize(verts, faces, edge_length_mm=float(edge_length_mm),
                                 epsilon=float(epsilon), num_threads=num_threads)
    if len(tets) < 4:
        raise MeshError(f"fTetWild returned {len(tets)} elements; check the label map and size")
    # one elastic body: fTetWild can return loose pieces (islands of the smoothed mask), each
    # of which would move rigidly without strain (K singular); the largest is the brain
    piece = mesh_pieces(tets)
    if piece.max() > 0:
        sizes = np.bincount(piece)
        warnings.warn(f"the mesh had {len(sizes)} pieces joined by no face; kept the largest "
                      f"({sizes[0]} elements), dropped {int(sizes[1:].sum())} element(s) in "
                      f"the others", UserWarning, stacklevel=2)
        tets = tets[piece == 0]
    nodes, tets = compact_nodes(nodes, tets)
    tets = orient_tets(nodes, tets)
    tissue = label_elements(labels, nodes, tets)
    mesh = Mesh(nodes, tets, tissue, boundary_nodes(tets))
    q = mesh_quality(mesh)
    vmax = q["volume_max_mm3"]
    if q["n_inverted"] or q["volume_min_mm3"] <= 1e-9 * vmax:
        raise MeshError(f"mesh has inverted or degenerate elements: {q}")
    return mesh


NODES_EXPONENT = 4.0
"""``p`` of the node count ``n = A h^-p`` of fTetWild meshes at edge length ``h``
(:func:`mesh_brain_sized`): 4, rounded from 3.9, the slope of the mean counts of the MNI152
brain at 2 mm, 897, 691 and 569 nodes at 16, 17 and 18 mm (12, 6 and 2 meshes)."""


def mesh_brain_sized(
    labels: Image,
    target_nodes: int,
    *,
    tolerance: float = 0.05,
    max_attempts: int = 12,
    edge_length_mm: float = 16.0,
    **mesh_kwargs,
) -> tuple[Mesh, dict]:
    """:func:`mesh_brain` re-run until its node count is within ``tolerance`` of a target.

    fTetWild's node count at one edge length scatters between runs (MNI152 at 2 mm, 16 mm
    edges: 813-989 nodes against the paper's 801; 16.5-16.6 mm: 723-908), and the count
    sets the size of every FE array, the cost of a step and what a run reproduces.  The
    count follows ``n = A h^-p`` in the edge length ``h`` with ``p`` about 4
    (:data:`NODES_EXPONENT`) and a scatter of about 7%, so after each attempt that misses,
    ``log A`` is estimated as the mean of ``log n + p log h`` over all attempts so far and
    the next edge length is ``(A / target_nodes)^(1/p)`` (the mean damps the scatter that a
    step from the last attempt alone would chase), its change clipped to a factor in
    ``[0.7, 1.4]`` and the length to 0.9 of the brain's largest extent (of the last mesh's
    nodes): a target below the coarsest mesh fTetWild makes of the surface (about 170-190
    nodes for MNI152 at 2 mm) ends the search there, with the warning below.

    Parameters
    ----------
    labels : Image
        Internal label coding, as for :func:`mesh_brain`.
    target_nodes : int
        Wanted number of nodes (>= 20).
    tolerance : float
        Accept a mesh with ``|n - target_nodes| <= tolerance * target_nodes`` (in (0, 1)).
        fTetWild's node counts scatter by a few percent at one edge length, so a tolerance
        below about 0.05 can take many attempts.
    max_attempts : int
        Meshes to try at most (>= 1).  When none is within the tolerance, the closest is
        returned, a :class:`UserWarning` names the counts, and ``info["within_tolerance"]``
        is False.
    edge_length_mm : float
        Edge length of the first attempt, mm.
    **mesh_kwargs
        ``smoothing_sigma_mm``, ``epsilon``, ``step_size``, ``num_threads`` of :func:`mesh_brain`.

    Returns
    -------
    mesh : Mesh
        The first mesh within the tolerance (else the closest to the target).
    info : dict
        ``target_nodes``, ``tolerance``, ``edge_length_mm`` (of the mesh returned),
        ``within_tolerance`` and ``attempts``: ``[{"edge_length_mm", "n_nodes"}, ...]`` in order.

    Raises
    ------
    ValueError
        ``target_nodes < 20``, ``tolerance`` outside (0, 1), ``max_attempts < 1``,
        ``edge_length_mm`` not a finite number > 0, or an invalid ``smoothing_sigma_mm``,
        ``epsilon`` or ``step_size`` (as :func:`mesh_brain`), before any meshing.
    MeshError
        As :func:`mesh_brain`, from any attempt.
    """
    if int(target_nodes) != target_nodes or target_nodes < 20:
        raise ValueError(f"target_nodes must be an integer >= 20, got {target_nodes}")
    if not 0.0 < tolerance < 1.0:
        raise ValueError(f"tolerance must lie in (0, 1), got {tolerance}")
    if int(max_attempts) != max_attempts or max_attempts < 1:
        raise ValueError(f"max_attempts must be an integer >= 1, got {max_attempts}")
    _check_mesh_args(edge_length_mm, **{k: v for k, v in mesh_kwargs.items()
                                        if k in ("smoothing_sigma_mm", "epsilon", "step_size")})
    target_nodes = int(target_nodes)
    edge = float(edge_length_mm)
    attempts: list[dict] = []
    log_a: list[float] = []
    best: tuple[int, float, Mesh] | None = None
    for _ in range(int(max_attempts)):
        mesh = mesh_brain(labels, edge_length_mm=edge, **mesh_kwargs)
        n = len(mesh.nodes)
        attempts.append({"edge_length_mm": round(edge, 4), "n_nodes": n})
        if best is None or abs(n - target_nodes) < abs(best[0] - target_nodes):
            best = (n, edge, mesh)
        if abs(n - target_nodes) <= tolerance * target_nodes:
            break
        log_a.append(np.log(n) + NODES_EXPONENT * np.log(edge))
        wanted = np.exp((np.mean(log_a) - np.log(target_nodes)) / NODES_EXPONENT)
        # never beyond the brain's largest extent (mesh_brain refuses it: fTetWild makes no
        # coarser mesh there, only slower), and no further attempt once there
        # (0.9: fTetWild may place nodes a little outside the surface)
        cap = 0.9 * float(np.ptp(mesh.nodes, axis=0).max())
        if edge >= cap and wanted > edge:
            break
        edge = min(edge * float(np.clip(wanted / edge, 0.7, 1.4)), cap)
    n, edge, mesh = best
    within = abs(n - target_nodes) <= tolerance * target_nodes
    if not within:
        warnings.warn(
            f"no mesh within {tolerance:.0%} of {target_nodes} nodes in {len(attempts)} attempts "
            f"(node counts {[a['n_nodes'] for a in attempts]}); keeping the closest, {n} nodes at "
            f"{edge:.3g} mm", UserWarning, stacklevel=2)
    info = {"target_nodes": target_nodes, "tolerance": float(tolerance),
            "edge_length_mm": round(edge, 4), "within_tolerance": bool(within), "attempts": attempts}
    return mesh, info


def carve_skull(labels: Image, mesh: Mesh, *, clearance_mm: float = 2.0) -> tuple[Image, int]:
    """Make the skull region consistent with the mesh at rest.

    The mesh surface approximates the smoothed intracranial surface within fTetWild's
    envelope, so a coarse mesh can poke a few mm past the brain mask.  Skull voxels closer
    than ``clearance_mm`` to the volume covered by the undeformed mesh (voxel centres inside
    an element, and the 8 voxels around each node) become background.

    Returns
    -------
    labels : Image
        The carved label map.
    n_carved : int
        Voxels turned from skull into background.

    Raises
    ------
    MeshError
        If a mesh node still lies in the skull region as the samplers see it
        (:func:`bayesreg.mesh.constraints.points_forbidden`; it cannot, unless the clearance is 0).
    """
    _, covered = interpolation_matrix(mesh, labels)
    # the voxels nearest to the nodes count as covered too (thin protrusions, tips)
    base = np.floor(world_to_voxel(labels.affine, mesh.nodes)).astype(int)
    for corner in np.ndindex(2, 2, 2):
        idx = base + np.array(corner)
        ok = np.all((idx >= 0) & (idx < np.array(covered.shape)), axis=1)
        covered[tuple(idx[ok].T)] = True
    dist = ndi.distance_transform_edt(~covered, sampling=labels.spacing)
    data = np.array(labels.data, copy=True)
    carve = (data == L.SKULL) & (dist < clearance_mm)
    data[carve] = L.BACKGROUND
    out = Image(data, labels.affine)
    # at rest every node must be allowed by the samplers' own rule (the smooth skull)
    skull = skull_constraint(Image((data == L.SKULL).astype(np.uint8), labels.affine))
    n_bad = int(np.sum(np.asarray(points_forbidden(skull, jnp.asarray(mesh.nodes)))))
    if n_bad:
        raise MeshError(f"{n_bad} mesh node(s) lie in the skull region before any deformation")
    return out, int(carve.sum())
