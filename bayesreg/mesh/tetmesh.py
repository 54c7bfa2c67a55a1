"""Tetrahedral FE meshes: the :class:`Mesh` type, its topology and quality, reading one.

A :class:`Mesh` holds nodes ``(N, 3)`` in world mm, positively oriented tets ``(M, 4)``, a
tissue index per element (0 CSF, 1 GM, 2 WM, by :func:`label_elements`) and the boundary
(surface) nodes, whose displacements the sampler moves.  :func:`read_mesh` reads a mesh
file made elsewhere or by an earlier run (``mesh.file``); meshing the label map is
:mod:`bayesreg.mesh.meshing`.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import scipy.ndimage as ndi

from bayesreg.data import labels as L
from bayesreg.data.images import Image, check_image, interpolate_numpy

__all__ = [
    "Mesh", "MeshError", "read_mesh", "box_mesh", "boundary_faces", "boundary_nodes", "signed_volumes",
    "orient_tets", "dihedral_angles", "mesh_quality", "label_elements", "compact_nodes",
    "tangle_report", "mesh_pieces",
]


class MeshError(ValueError):
    """The mesher failed or produced an unusable mesh (inverted/degenerate elements)."""


class Mesh(NamedTuple):
    """A labelled tetrahedral mesh.

    Attributes
    ----------
    nodes : (N, 3) float64
        World coordinates, mm.
    tets : (M, 4) int64
        Positively oriented connectivity.
    tissue : (M,) int64
        Tissue index per element: 0 CSF, 1 GM, 2 WM (``labels.TISSUES``).
    boundary : (n_b,) int64
        Sorted indices of the nodes on the mesh surface (the sampled nodes).
    """

    nodes: np.ndarray
    tets: np.ndarray
    tissue: np.ndarray
    boundary: np.ndarray

    @property
    def interior(self) -> np.ndarray:
        mask = np.ones(len(self.nodes), bool)
        mask[self.boundary] = False
        return np.flatnonzero(mask)


#: Kuhn subdivision of the unit cube into 6 tetrahedra around its diagonal 0-7 (corners
#: numbered ``4 a + 2 b + c`` for offsets ``(a, b, c)``): conforming across neighbouring cubes.
_KUHN = ((0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7))


def box_mesh(n=(3, 3, 3), size=(30.0, 30.0, 30.0), origin=(0.0, 0.0, 0.0), tissue=None) -> Mesh:
    """Structured tetrahedral mesh of a box: ``n`` cubes per axis, 6 tetrahedra per cube.

    Parameters
    ----------
    n : (3,) ints
        Cells per axis (>= 1).
    size, origin : (3,) floats
        Edge lengths and lowest corner, world mm.
    tissue : (M,) ints, optional
        Label of each element; default thirds along x (0, 1, 2 by the centroid).

    Returns
    -------
    Mesh
        ``(n_x + 1)(n_y + 1)(n_z + 1)`` nodes (x slowest), ``6 n_x n_y n_z`` positively
        oriented tetrahedra.

    Examples
    --------
    >>> m = box_mesh((2, 2, 2), size=(20.0, 20.0, 20.0))
    >>> m.nodes.shape, m.tets.shape, len(m.boundary)
    ((27, 3), (48, 4), 26)
    """
    n = tuple(int(k) for k in n)
    if len(n) != 3 or min(n) < 1:
        raise ValueError(f"box_mesh needs three cell counts >= 1, got {n}")
    grid = np.stack(np.meshgrid(*[np.linspace(0, s, k + 1) for s, k in zip(size, n)],
                                indexing="ij"), -1)
    nodes = grid.reshape(-1, 3) + np.asarray(origin, np.float64)
    idx = np.arange(len(nodes)).reshape(n[0] + 1, n[1] + 1, n[2] + 1)
    corners = np.stack([idx[a:a + n[0], b:b + n[1], c:c + n[2]].ravel()
                        for a in (0, 1) for b in (0, 1) for c in (0, 1)], axis=1)
    tets = orient_tets(nodes, corners[:, np.array(_KUHN)].reshape(-1, 4))
    if tissue is None:
        cent = nodes[tets].mean(1)
        x0, sx = float(np.asarray(origin)[0]), float(size[0])
        tissue = np.digitize(cent[:, 0], [x0 + sx / 3, x0 + 2 * sx / 3])
    return Mesh(nodes, tets, np.asarray(tissue, np.int64), boundary_nodes(tets))


def boundary_faces(tets):
    """Triangles that belong to exactly one tetrahedron, ``(F, 3)``, outward oriented."""
    tets = np.asarray(tets)
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.ravel()] == 1]


def boundary_nodes(tets):
    """Indices of nodes on the surface of the mesh (sorted), ``(n_b,)``."""
    return np.unique(boundary_faces(tets))


def mesh_pieces(tets) -> np.ndarray:
    """The piece of each element, ``(M,)`` ints from 0, largest piece first: elements joined
    by a shared face are in one piece.

    A mesh of more than one piece is not one elastic body: each further piece moves rigidly
    without strain (six more zero modes of ``K``), and so does a piece attached to the rest
    by a node or an edge only, which this counts apart too.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    tets = np.asarray(tets)
    m = len(tets)
    key = np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    order = np.argsort(inv.ravel(), kind="stable")
    face, elem = inv.ravel()[order], order // 4
    pair = np.flatnonzero(face[1:] == face[:-1])  # an interior face: its two elements
    graph = sp.coo_matrix((np.ones(len(pair)), (elem[pair], elem[pair + 1])), shape=(m, m))
    _, piece = connected_components(graph, directed=False)
    rank = np.argsort(np.argsort(-np.bincount(piece), kind="stable"), kind="stable")
    return rank[piece]


def signed_volumes(nodes, tets):
    """Signed element volumes ``(M,)``, mm^3 (positive for positive orientation)."""
    x = np.asarray(nodes)[np.asarray(tets)]
    return np.einsum(
        "mi,mi->m", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]
    ) / 6.0


def orient_tets(nodes, tets):
    """Swap two nodes of negatively oriented elements so every volume is positive."""
    tets = np.array(tets, dtype=np.int64)
    neg = signed_volumes(nodes, tets) < 0
    tets[neg, 2], tets[neg, 3] = tets[neg, 3].copy(), tets[neg, 2].copy()
    return tets


def dihedral_angles(nodes, tets):
    """The six dihedral angles of every element, degrees, ``(M, 6)``."""
    x = np.asarray(nodes)[np.asarray(tets)]
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    out = []
    for a, b in pairs:
        c, d = [k for k in range(4) if k not in (a, b)]
        e = x[:, b] - x[:, a]
        e /= np.linalg.norm(e, axis=1, keepdims=True)
        vc = x[:, c] - x[:, a]
        vd = x[:, d] - x[:, a]
        vc -= np.sum(vc * e, 1, keepdims=True) * e
        vd -= np.sum(vd * e, 1, keepdims=True) * e
        cos = np.sum(vc * vd, 1) / (np.linalg.norm(vc, axis=1) * np.linalg.norm(vd, axis=1))
        out.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.stack(out, axis=1)


def mesh_quality(mesh: Mesh) -> dict:
    """Size and quality figures: counts, volume range (mm^3), dihedral range (deg), inverted."""
    vol = signed_volumes(mesh.nodes, mesh.tets)
    dih = dihedral_angles(mesh.nodes, mesh.tets)
    counts = np.bincount(mesh.tissue, minlength=3)
    return {
        "n_nodes": int(len(mesh.nodes)),
        "n_tets": int(len(mesh.tets)),
        "n_boundary_nodes": int(len(mesh.boundary)),
        "n_interior_nodes": int(len(mesh.nodes) - len(mesh.boundary)),
        "volume_min_mm3": float(vol.min()),
        "volume_max_mm3": float(vol.max()),
        "volume_total_ml": float(vol.sum() / 1000.0),
        "dihedral_min_deg": float(dih.min()),
        "dihedral_max_deg": float(dih.max()),
        "n_inverted": int(np.sum(vol <= 0)),
        "tets_per_tissue": {t: int(c) for t, c in zip(L.TISSUES, counts)},
    }


#: meshio's volume cell types other than linear tetrahedra: a file holding any of them is
#: refused by :func:`read_mesh` rather than read in part
def compact_nodes(nodes, tets):
    """Drop the nodes no element uses: ``(nodes (N', 3) float64, tets (M, 4))`` renumbered."""
    used = np.unique(tets)
    remap = np.full(len(nodes), -1, np.int64)
    remap[used] = np.arange(len(used))
    return np.asarray(nodes, np.float64)[used], remap[tets]


#: Outward faces of a positively oriented tetrahedron ``(0, 1, 2, 3)``: the vertex order of
#: each face whose right-hand normal points away from the opposite vertex.
_OUTWARD_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


def tangle_report(nodes, tets) -> dict:
    """How far a mesh of positively oriented tetrahedra is from a valid (untangled) one.

    In a valid mesh every interior face is shared by exactly two elements that see it with
    opposite orientations (they lie on its two sides), and the elements fill the volume
    their surface encloses exactly once.  A folded mesh (an element turned inside out, then
    re-oriented by :func:`orient_tets`) has faces seen with the same orientation twice, or
    by more than two elements, and elements whose volumes add up to more than the enclosed
    volume.

    Parameters
    ----------
    nodes : (N, 3) array
        World mm.
    tets : (M, 4) int array
        Positively oriented (:func:`orient_tets`).

    Returns
    -------
    dict
        ``same_side_faces`` (faces seen with one orientation by two elements),
        ``crowded_faces`` (faces of more than two elements), ``volume_mm3`` (the elements'
        total), ``enclosed_mm3`` (the volume the boundary faces enclose, by the divergence
        theorem), ``tangled`` (any of the above, or a total volume above the enclosed one
        by more than 1e-6 relative).
    """
    nodes = np.asarray(nodes, np.float64)
    tets = np.asarray(tets)
    faces = tets[:, _OUTWARD_FACES].reshape(-1, 3)  # (4M, 3) outward
    key = np.sort(faces, axis=1)
    # the orientation of each face relative to its sorted vertex order: +1 even, -1 odd
    order = np.argsort(faces, axis=1)
    parity = np.where((order == [0, 1, 2]).all(1) | (order == [1, 2, 0]).all(1)
                      | (order == [2, 0, 1]).all(1), 1, -1)
    uniq, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.bincount(inverse, weights=parity, minlength=len(uniq))
    two = counts == 2
    same_side = int(np.sum(two & (sums != 0)))
    crowded = int(np.sum(counts > 2))
    once = counts[inverse] == 1
    b = faces[once]
    x0, x1, x2 = nodes[b[:, 0]], nodes[b[:, 1]], nodes[b[:, 2]]
    enclosed = float(np.sum(np.einsum("ij,ij->i", x0, np.cross(x1, x2))) / 6.0)
    volume = float(np.sum(signed_volumes(nodes, tets)))
    tangled = bool(same_side or crowded or volume > enclosed * (1 + 1e-6))
    return {"same_side_faces": same_side, "crowded_faces": crowded, "volume_mm3": volume,
            "enclosed_mm3": enclosed, "tangled": tangled}


_OTHER_VOLUME_CELLS = ("tetra10", "hexahedron", "hexahedron20", "hexahedron24", "hexahedron27",
                       "wedge", "wedge12", "wedge15", "pyramid", "pyramid13", "pyramid14")

#: least fraction of a mesh's element centroids that must lie in the intracranial tissues
#: of the label map for :func:`read_mesh` (the check that catches a mesh in another frame)
MIN_INSIDE_FRACTION = 0.5


def read_mesh(path, labels: Image) -> Mesh:
    """A tetrahedral mesh from a file, labelled as :func:`bayesreg.mesh.meshing.mesh_brain` labels its elements.

    Any format that meshio reads (VTU, XDMF, Gmsh ``.msh``, Medit ``.mesh``, ...): for
    instance a run's own ``mesh.vtu``, to sample again on the very mesh of that run (fTetWild
    is not reproducible), or a mesh made with another tool.  Nodes not used by any
    tetrahedron are dropped, elements are oriented positively (:func:`orient_tets`), the
    boundary nodes are those of the mesh's surface, and each element's tissue is the
    majority over sample points of ``labels`` (:func:`label_elements`; a ``tissue`` cell
    array in the file is not read: the label map decides, as for a generated mesh).  Lower
    dimensional cells (a Gmsh file's surface triangles, lines, vertices) are ignored.

    Parameters
    ----------
    path : str or path-like
        The mesh file.  Its points are world coordinates in mm, in the frame of ``labels``
        (the images' affines); their order is kept, apart from unused ones.
    labels : Image
        Internal label coding (see :mod:`bayesreg.data.labels`).

    Returns
    -------
    Mesh

    Raises
    ------
    FileNotFoundError
        ``path`` is not a file.
    MeshError
        (a ``ValueError``) meshio cannot read the file; it holds no linear tetrahedra
        (``tetra``), or volume cells of another type (quadratic tetrahedra, hexahedra,
        wedges, pyramids); its points are not 3-D and finite, or a tetrahedron names a point
        that does not exist; an element is degenerate (volume at most 1e-9 of the largest); it
        is more than one piece (:func:`mesh_pieces`); or
        fewer than :data:`MIN_INSIDE_FRACTION` of the element centroids lie in the
        intracranial tissues of ``labels`` (a mesh in voxel coordinates, or of another
        subject or space: the message gives both extents); the mesh is tangled (folded
        elements, :func:`tangle_report`: the counts and volumes are named); or its volume
        or extent is not the brain's of ``labels`` (:data:`VOLUME_RANGE`,
        :data:`EXTENT_RANGE`: both named).
    """
    import meshio

    labels = check_image(labels, "labels")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        raw = meshio.read(path)
    except SystemExit:  # meshio exits when no reader of the suffix's formats can read it
        raise MeshError(f"cannot read mesh file {path}: no meshio reader for its suffix "
                        f"({path.suffix or 'none'}) could read it") from None
    except Exception as exc:  # meshio raises many types (ReadError, KeyError, ValueError, ...)
        raise MeshError(f"cannot read mesh file {path}: {type(exc).__name__}: {exc}") from None
    types = sorted({c.type for c in raw.cells})
    other = [t for t in types if t in _OTHER_VOLUME_CELLS or t.startswith("polyhedron")]
    if other:
        raise MeshError(f"mesh file {path} holds volume cells of type {', '.join(other)}: "
                        "bayesreg's elements are linear tetrahedra (meshio type 'tetra') only")
    blocks = [np.asarray(c.data, np.int64) for c in raw.cells if c.type == "tetra"]
    if not blocks:
        raise MeshError(f"mesh file {path} holds no tetrahedra (its cells: "
                        f"{', '.join(types) or 'none'})")
    nodes = np.asarray(raw.points, np.float64)
    if nodes.ndim != 2 or nodes.shape[1] != 3 or not np.all(np.isfinite(nodes)):
        raise MeshError(f"mesh file {path}: points must be finite 3-D coordinates (mm), got an "
                        f"array of shape {nodes.shape}")
    tets = np.concatenate(blocks)
    if tets.min() < 0 or tets.max() >= len(nodes):
        raise MeshError(f"mesh file {path}: a tetrahedron names point {int(tets.max())} of "
                        f"{len(nodes)} (or a negative index)")
    nodes, tets = compact_nodes(nodes, tets)
    tets = orient_tets(nodes, tets)
    vol = np.abs(signed_volumes(nodes, tets))
    if not vol.min() > 1e-9 * vol.max():
        bad = np.flatnonzero(vol <= 1e-9 * vol.max())
        raise MeshError(f"mesh file {path}: {len(bad)} degenerate (flat or repeated-node) "
                        f"element(s), the first {bad[:5].tolist()}")
    pieces = np.bincount(mesh_pieces(tets))
    if len(pieces) > 1:
        raise MeshError(
            f"mesh file {path} is {len(pieces)} pieces joined by no face (elements "
            f"{', '.join(str(int(c)) for c in pieces[:5])}{', ...' if len(pieces) > 5 else ''}): "
            "the FE model needs one body (a loose piece moves without strain, so K is "
            "singular); keep its largest piece")
    tangle = tangle_report(nodes, tets)
    if tangle["tangled"]:
        raise MeshError(
            f"mesh file {path} is tangled (folded elements): {tangle['same_side_faces']} "
            f"interior face(s) have both their elements on one side, "
            f"{tangle['crowded_faces']} belong to more than two elements, and its elements "
            f"fill {tangle['volume_mm3'] / 1e3:.1f} ml where its surface encloses "
            f"{tangle['enclosed_mm3'] / 1e3:.1f} ml; untangle it (or remesh) before use")
    centroids = nodes[tets].mean(axis=1)
    at = interpolate_numpy(labels, centroids, order=0, cval=L.BACKGROUND)
    inside = float(np.mean(np.isin(at, L.TISSUE_LABELS)))
    if inside < MIN_INSIDE_FRACTION:
        mask = np.argwhere(np.isin(np.asarray(labels.data), L.TISSUE_LABELS)).astype(np.float64)
        brain = mask @ labels.affine[:3, :3].T + labels.affine[:3, 3] if len(mask) else np.zeros((1, 3))
        span = lambda x: " x ".join(f"[{a:.0f}, {b:.0f}]" for a, b in zip(x.min(0), x.max(0)))  # noqa: E731
        raise MeshError(
            f"mesh file {path}: only {inside:.0%} of its element centroids lie in the "
            f"intracranial tissues of the label map (at least {MIN_INSIDE_FRACTION:.0%} "
            f"needed).  Its points must be world coordinates in mm, in the images' frame: the "
            f"mesh spans {span(nodes)} mm, the intracranial region {span(brain)} mm")
    _check_matches_brain(path, nodes, tangle["volume_mm3"], labels)
    tissue = label_elements(labels, nodes, tets)
    return Mesh(nodes, tets, tissue, boundary_nodes(tets))


#: The volume of a given mesh over that of the label map's intracranial tissues must lie in
#: this range, and each of its bounding box's extents over the tissues' in ``EXTENT_RANGE``.
VOLUME_RANGE = (1 / 3, 3.0)
EXTENT_RANGE = (0.5, 2.0)


def _check_matches_brain(path, nodes, volume_mm3: float, labels: Image) -> None:
    """:class:`MeshError` unless the mesh's volume and extent are those of the brain of
    ``labels`` within :data:`VOLUME_RANGE` and :data:`EXTENT_RANGE` (a mesh in voxel units,
    or of another subject, can still have most of its elements inside the tissues)."""
    mask = np.isin(np.asarray(labels.data), L.TISSUE_LABELS)
    if not mask.any():
        return
    voxel = abs(float(np.linalg.det(np.asarray(labels.affine, np.float64)[:3, :3])))
    brain_ml = float(mask.sum()) * voxel / 1e3
    ijk = np.argwhere(mask).astype(np.float64)
    world = ijk @ labels.affine[:3, :3].T + labels.affine[:3, 3]
    brain_extent = np.ptp(world, axis=0) + np.linalg.norm(labels.affine[:3, :3], axis=0)
    extent = np.ptp(nodes, axis=0)
    ratio = volume_mm3 / 1e3 / brain_ml
    extent_ratio = extent / brain_extent
    if (VOLUME_RANGE[0] <= ratio <= VOLUME_RANGE[1]
            and np.all((extent_ratio >= EXTENT_RANGE[0]) & (extent_ratio <= EXTENT_RANGE[1]))):
        return
    fmt = lambda e: " x ".join(f"{x:.0f}" for x in e)  # noqa: E731
    raise MeshError(
        f"mesh file {path} does not match the brain of the label map: the mesh holds "
        f"{volume_mm3 / 1e3:.0f} ml in a box of {fmt(extent)} mm, the intracranial tissues "
        f"{brain_ml:.0f} ml in {fmt(brain_extent)} mm.  Its points must be world coordinates in "
        "mm of these images (a mesh in voxel units, or of another subject, does not fit)")


# 11 sample points per element: 4 vertices pulled to the centroid, the centroid, 6 edge mids
_SAMPLE_BARY = np.array(
    [[0.55, 0.15, 0.15, 0.15], [0.15, 0.55, 0.15, 0.15], [0.15, 0.15, 0.55, 0.15],
     [0.15, 0.15, 0.15, 0.55], [0.25, 0.25, 0.25, 0.25]]
    + [[0.5 if k in (a, b) else 0.0 for k in range(4)] for a in range(4) for b in range(a + 1, 4)]
)


def label_elements(labels: Image, nodes, tets) -> np.ndarray:
    """Majority tissue over 11 sample points per element (0 CSF, 1 GM, 2 WM).

    Sample points outside the tissues take the label of the nearest tissue voxel, so every
    element gets a tissue.
    """
    data = np.asarray(labels.data)
    tissue_mask = np.isin(data, L.TISSUE_LABELS)
    _, idx = ndi.distance_transform_edt(~tissue_mask, return_indices=True)
    filled = data[tuple(idx)]
    pts = np.einsum("sk,mkd->msd", _SAMPLE_BARY, np.asarray(nodes)[tets])
    lab = interpolate_numpy(Image(filled, labels.affine), pts, order=0, cval=L.GM)
    lab = np.where(np.isin(lab, L.TISSUE_LABELS), lab, L.GM).astype(np.int64) - 1
    counts = np.stack([(lab == t).sum(1) for t in range(3)], axis=1)
    return np.argmax(counts, axis=1).astype(np.int64)
