"""FE interpolation on image grids: point location, interpolation matrices, warped images.

The FE map ``x -> x + u(x)`` is piecewise affine on the tetrahedra.  :func:`locate` and
:func:`locate_voxels` find the element holding each point and its barycentric coordinates;
:func:`interpolation_matrix` turns that into a sparse ``(n_voxels, N)`` matrix of shape-function
values (nodal fields to images); :func:`grid_moments_from` gives the posterior mean and sd of
the interpolated displacement on a grid from nodal moments; :func:`warp_image` makes
``m(x + u(x)) = f(x)`` exactly for the FE map (the synthetic intra-operative image), and
:func:`warp_image_field` for a dense voxel field (a truth the model did not make).

Units: points and displacements in world mm; grids carry their voxel-to-world affine.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
from scipy.spatial import cKDTree

from bayesreg.data.images import Image, grid_points, interpolate_numpy, world_to_voxel
from bayesreg.mesh.tetmesh import Mesh, signed_volumes

__all__ = ["locate", "locate_voxels", "locate_grid", "interpolation_matrix", "grid_moments",
           "grid_moments_from", "continue_displacement", "warp_image", "warp_image_field"]


def locate(nodes, tets, points, *, tol=1e-9):
    """Element containing each point and its barycentric coordinates.

    Each element is rasterised over the points inside its bounding box, so the search is
    exact (no candidate lists).

    Parameters
    ----------
    nodes : (N, 3)
        world mm
    tets : (M, 4)
    points : (P, 3)
        world mm, e.g. voxel centres

    Returns
    -------
    elem : (P,) int
        (-1 where no element contains the point)
    bary : (P, 4)
    """
    points = np.asarray(points, np.float64)
    # sort points along x for bounding-box range queries
    order = np.argsort(points[:, 0], kind="stable")
    px = points[order, 0]

    def candidates(e, lo, hi):
        a, b = np.searchsorted(px, [lo[0] - tol, hi[0] + tol])
        cand = order[a:b]
        pc = points[cand]
        inb = np.all((pc[:, 1:] >= lo[1:] - tol) & (pc[:, 1:] <= hi[1:] + tol), axis=1)
        return cand[inb], pc[inb]

    return _rasterise(nodes, tets, len(points), candidates, tol)


def _rasterise(nodes, tets, n_points, candidates, tol):
    """The element search of :func:`locate` and :func:`locate_voxels`: each element tests the
    points ``candidates(e, lo, hi) -> (indices, (k, 3) world mm)`` inside its bounding box
    ``[lo, hi]`` (enlarged by ``tol``); the lowest element index wins a shared point."""
    nodes = np.asarray(nodes, np.float64)
    tets = np.asarray(tets)
    elem = np.full(n_points, -1, np.int64)
    bary = np.zeros((n_points, 4))
    x = nodes[tets]
    lo, hi = x.min(1), x.max(1)
    t_inv = np.linalg.inv(np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], -1))
    for e in range(len(tets)):
        cand, pc = candidates(e, lo[e], hi[e])
        if cand.size == 0:
            continue
        lam = (pc - x[e, 0]) @ t_inv[e].T
        bc = np.column_stack([1 - lam.sum(1), lam])
        hit = np.all(bc >= -tol, axis=1) & (elem[cand] < 0)
        elem[cand[hit]] = e
        bary[cand[hit]] = bc[hit]
    return elem, bary


def locate_voxels(nodes, tets, shape, affine, *, tol=1e-9):
    """:func:`locate` for the voxel centres of a grid, flattened in C order.

    The same rule and the same result as ``locate(nodes, tets, centres)`` (the lowest
    element index wins a point two elements share; a point within ``tol`` of a face
    counts), but each element visits only the voxels of its bounding box in voxel
    coordinates (about 500 for a 16 mm element on a 2 mm grid) instead of every voxel of
    its slab along x.

    Parameters
    ----------
    nodes : (N, 3)
        world mm
    tets : (M, 4)
    shape : (3,) int
        grid shape ``(I, J, K)``
    affine : (4, 4)
        voxel-to-world matrix of the grid

    Returns
    -------
    elem : (I*J*K,) int
        (-1 where no element contains the voxel centre)
    bary : (I*J*K, 4)
    """
    affine = np.asarray(affine, np.float64)
    shape = np.asarray(shape[:3], np.int64)
    inv = np.linalg.inv(affine)
    c = np.asarray(nodes, np.float64)[np.asarray(tets)] @ inv[:3, :3].T + inv[:3, 3]  # voxel coords
    c_lo = np.maximum(np.floor(c.min(1) - 1e-6), 0).astype(np.int64)
    c_hi = np.minimum(np.ceil(c.max(1) + 1e-6), shape - 1).astype(np.int64)
    strides = np.array([shape[1] * shape[2], shape[2], 1])
    empty = (np.zeros(0, np.int64), np.zeros((0, 3)))

    def candidates(e, lo, hi):
        if np.any(c_lo[e] > c_hi[e]):
            return empty
        axes = [np.arange(c_lo[e, k], c_hi[e, k] + 1) for k in range(3)]
        ijk = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        pc = ijk @ affine[:3, :3].T + affine[:3, 3]
        inb = np.all((pc >= lo - tol) & (pc <= hi + tol), axis=1)
        return ijk[inb] @ strides, pc[inb]

    return _rasterise(nodes, tets, int(np.prod(shape)), candidates, tol)


def interpolation_matrix(mesh: Mesh, grid: Image, *, located=None):
    """Sparse ``(n_voxels, N)`` matrix of FE shape-function values at the voxel centres.

    Rows of voxels outside the (undeformed) mesh are zero; ``inside`` marks the others.
    ``located``: :func:`locate_grid` of ``(mesh, grid)``, if already computed.

    Returns
    -------
    W : scipy.sparse.csr_array
    inside : (I, J, K) bool
    """
    elem, bary = located if located is not None else locate_grid(mesh, grid)
    rows = np.flatnonzero(elem >= 0)
    cols = mesh.tets[elem[rows]]
    w = sp.csr_array(
        (bary[rows].ravel(), (np.repeat(rows, 4), cols.ravel())), shape=(len(elem), len(mesh.nodes))
    )
    return w, (elem >= 0).reshape(grid.data.shape[:3])


def locate_grid(mesh: Mesh, grid: Image):
    """:func:`locate` for every voxel centre of ``grid`` (flattened C order):
    ``elem (I*J*K,)``, ``bary (I*J*K, 4)``; pass it as ``located`` to avoid repeating it
    (:func:`locate_voxels`)."""
    return locate_voxels(mesh.nodes, mesh.tets, grid.data.shape, grid.affine)


def grid_moments(mesh: Mesh, grid: Image, draws, *, located=None):
    """Posterior mean and sd of the FE-interpolated displacement on an image grid.

    The interpolant is linear in the nodal values, so per voxel ``v`` and axis ``c``
    ``Var u_c(v) = w_v^T Cov_c w_v`` with ``w_v`` the 4 barycentric weights of the element
    containing ``v`` and ``Cov_c`` the ``(N, N)`` posterior covariance of axis ``c``; no
    per-draw interpolation is needed.

    Parameters
    ----------
    mesh : Mesh
    grid : Image
        (only its shape and affine are used)
    draws : (S, N, 3) array
        nodal displacement draws, mm
    located : tuple, optional
        :func:`locate_grid` of ``(mesh, grid)``, if already computed

    Returns
    -------
    mean, sd : (I, J, K, 3) ndarray
        mm; zero outside the mesh
    """
    draws = np.asarray(draws, np.float64)
    mean_n = draws.mean(0)
    centred = draws - mean_n
    cov = np.stack([centred[:, :, c].T @ centred[:, :, c] for c in range(3)]) / len(draws)
    return grid_moments_from(mesh, grid, mean_n, cov, located=located)


def grid_moments_from(mesh: Mesh, grid: Image, mean, cov, *, located=None):
    """:func:`grid_moments` from the nodal posterior mean and per-axis covariances.

    For draws that are never held at once (``bayesreg.outputs.write`` accumulates the moments
    over chunks of draws).

    Parameters
    ----------
    mesh : Mesh
    grid : Image
        (only its shape and affine are used)
    mean : (N, 3) array
        posterior mean of the nodal displacement, mm
    cov : (3, N, N) array
        posterior covariance of the nodal displacement per axis, mm^2
    located : tuple, optional
        :func:`locate_grid` of ``(mesh, grid)``, if already computed

    Returns
    -------
    mean, sd : (I, J, K, 3) ndarray
        mm; zero outside the mesh

    Raises
    ------
    ValueError
        If ``mean`` is not ``(N, 3)`` or ``cov`` not ``(3, N, N)`` for the mesh's ``N`` nodes.
    """
    n = len(mesh.nodes)
    mean_n, cov = np.asarray(mean, np.float64), np.asarray(cov, np.float64)
    if mean_n.shape != (n, 3) or cov.shape != (3, n, n):
        raise ValueError(f"mean (N, 3) and cov (3, N, N) with N = {n} expected, "
                         f"got {mean_n.shape} and {cov.shape}")
    elem, bary = located if located is not None else locate_grid(mesh, grid)
    inside = np.flatnonzero(elem >= 0)
    idx = mesh.tets[elem[inside]]  # (P, 4)
    w = bary[inside]
    mean = np.zeros((len(elem), 3))
    sd = np.zeros((len(elem), 3))
    mean[inside] = np.einsum("pa,pac->pc", w, mean_n[idx])
    for c in range(3):
        var = np.einsum("pa,pb,pab->p", w, w, cov[c][idx[:, :, None], idx[:, None, :]])
        sd[inside, c] = np.sqrt(np.maximum(var, 0.0))
    shape = grid.data.shape[:3]
    return mean.reshape(*shape, 3), sd.reshape(*shape, 3)


def continue_displacement(points, anchors, u, *, k: int = 8) -> np.ndarray:
    """A displacement continued beyond the mesh: at each point the inverse-square-distance
    mean of the displacements ``u`` ``(A, 3)`` mm of its ``k`` nearest ``anchors`` ``(A, 3)``
    (world mm; boundary nodes).  Returns ``(P, 3)`` mm for ``points`` ``(P, 3)``."""
    points = np.asarray(points, np.float64)
    k = min(int(k), len(anchors))
    dist, j = cKDTree(anchors).query(points, k=k)
    dist, j = dist.reshape(len(points), k), j.reshape(len(points), k)
    w = 1.0 / np.maximum(dist, 1e-9) ** 2
    return np.einsum("pk,pkd->pd", w, np.asarray(u)[j]) / w.sum(axis=1, keepdims=True)


def warp_image(f: Image, mesh: Mesh, u, *, background=0.0, outside: str = "background",
               extend_k: int = 8, order: int = 1) -> Image:
    """Intra-operative image ``m`` with ``m(x + u(x)) = f(x)`` for the FE map ``x -> x + u(x)``.

    For every voxel centre ``y`` of ``m`` (same grid as ``f``) the deformed element
    containing ``y`` is found; its barycentric coordinates give ``x`` in the undeformed
    element and ``m(y) = f(x)`` (``f`` read by a spline of ``order``: 1 trilinear, 3 cubic
    B-spline with its prefilter).  Voxels covered by no deformed element take
    ``background`` (``outside="background"``) or, with ``outside="extend"``,
    ``f(y - u~(y))``, ``u~`` the inverse-square-distance mean of the displacements of the
    ``extend_k`` deformed boundary nodes nearest ``y``: the displacement continued outside
    the mesh.  The SSD samples ``m`` trilinearly at points up to a voxel from the deformed
    surface, so a constant background there blends into every element at the surface and
    moves the likelihood's optimum away from the truth; the extension halves that shift.

    Parameters
    ----------
    f : Image
        Pre-operative image; ``m`` gets its grid and affine.
    mesh : Mesh
        Undeformed mesh, nodes ``(N, 3)`` world mm.
    u : (N, 3) array
        Nodal displacements, mm.
    background : float
        Value of uncovered voxels (``"background"``), and of ``f`` outside its grid.
    outside : {"background", "extend"}
    extend_k : int
        Boundary nodes averaged by ``"extend"``.
    order : {1, 3}
        Spline order of ``f``'s interpolation (SciPy's ``map_coordinates``).  The synthetic
        truths use 3 (:data:`bayesreg.model.problem.SYNTHETIC_ORDER`): trilinear resampling blurs
        ``f`` unevenly where the map stretches it, a misfit no deformation explains.

    Raises
    ------
    ValueError
        If the deformed mesh has an inverted element (the map is then not invertible), or
        ``outside`` is not one of the two.
    """
    if outside not in ("background", "extend"):
        raise ValueError(f"outside must be 'background' or 'extend', got {outside!r}")
    u = np.asarray(u, np.float64)
    deformed = mesh.nodes + u
    vol = signed_volumes(deformed, mesh.tets)
    if np.any(vol <= 0):
        raise ValueError(f"{int(np.sum(vol <= 0))} inverted element(s) in the deformed mesh")
    pts = grid_points(f)
    elem, bary = locate_voxels(deformed, mesh.tets, f.data.shape, f.affine)
    inside = elem >= 0
    x = np.einsum("pa,pad->pd", bary[inside], mesh.nodes[mesh.tets[elem[inside]]])
    out = np.full(len(pts), float(background))
    out[inside] = interpolate_numpy(f, x, order=order, cval=background)
    if outside == "extend" and not np.all(inside):
        b = np.asarray(mesh.boundary)
        u_ext = continue_displacement(pts[~inside], deformed[b], u[b], k=extend_k)
        out[~inside] = interpolate_numpy(f, pts[~inside] - u_ext, order=order, cval=background)
    return Image(out.reshape(f.data.shape), f.affine)


def warp_image_field(f: Image, field: Image, *, background=0.0, max_iter=100, tol_mm=1e-4,
                     order: int = 1) -> Image:
    """Intra-operative image ``m`` with ``m(y) = f(x)``, ``x + u(x) = y``, for a dense field.

    The inverse map is found per voxel centre ``y`` by the fixed-point iteration
    ``x <- y - u(x)`` from ``x = y`` (``u`` trilinear between voxel centres, continued by
    its nearest face beyond the grid), which converges where ``|grad u| < 1``.  Before
    that, the Jacobian determinant of ``x -> x + u(x)`` (central differences) must be
    positive at every voxel: a folding field has no inverse.

    Parameters
    ----------
    f : Image
        Pre-operative image ``(I, J, K)``; ``m`` gets its grid.
    field : Image
        ``(I, J, K, 3)`` displacement ``u`` in world mm on ``f``'s grid.
    background : float
        Value of ``f`` beyond its grid.
    max_iter : int
    tol_mm : float
        Largest allowed ``|x + u(x) - y|`` at the end, mm.
    order : {1, 3}
        Spline order of ``f``'s interpolation, as :func:`warp_image`'s.

    Returns
    -------
    Image

    Raises
    ------
    ValueError
        If ``field`` is not ``(I, J, K, 3)`` on ``f``'s grid, folds (the number of voxels of
        non-positive Jacobian determinant is given), or the iteration does not reach
        ``tol_mm`` (the largest residual is given).
    """
    data = np.asarray(field.data, np.float64)
    if data.shape != (*f.data.shape[:3], 3) or not np.allclose(field.affine, f.affine, atol=1e-6):
        raise ValueError(f"the displacement field ({data.shape}) must lie on f's grid "
                         f"({f.data.shape[:3]} x 3, same affine)")
    if not np.all(np.isfinite(data)):
        raise ValueError("the displacement field holds NaN or infinite values")
    if min(data.shape[:3]) < 2:
        raise ValueError(f"the grid needs at least 2 voxels along each axis, got {data.shape[:3]}")
    folded = _count_folds(data, f.affine)
    if folded:
        raise ValueError(f"the displacement field folds at {folded} voxel(s) (Jacobian "
                         "determinant <= 0): it has no inverse")

    def u_at(points):  # trilinear, continued by the nearest face beyond the grid
        c = world_to_voxel(f.affine, points).T
        return np.stack([ndi.map_coordinates(data[..., k], c, order=1, mode="nearest")
                         for k in range(3)], -1)

    y = grid_points(f)
    x = y.copy()
    todo = np.arange(len(y))
    for _ in range(int(max_iter)):
        u = u_at(x[todo])
        new = y[todo] - u
        step = np.linalg.norm(new - x[todo], axis=1)
        x[todo] = new
        todo = todo[step > tol_mm * 0.1]
        if todo.size == 0:
            break
    u = u_at(x)
    residual = float(np.max(np.linalg.norm(x + u - y, axis=1)))
    if residual > tol_mm:
        raise ValueError(f"inverting the displacement field did not converge: largest residual "
                         f"{residual:.3g} mm after {max_iter} iterations (tolerance {tol_mm:g} mm)")
    return Image(interpolate_numpy(f, x, order=order, cval=background).reshape(f.data.shape[:3]),
                 f.affine)


def _count_folds(data, affine, slab: int = 16) -> int:
    """Voxels where ``x -> x + u(x)`` has Jacobian determinant <= 0 (central differences,
    one-sided at the grid's faces), slab by slab along the first axis to bound memory."""
    a_inv = np.linalg.inv(np.asarray(affine, np.float64)[:3, :3])
    n = data.shape[0]
    folded = 0
    for lo in range(0, n, slab):
        hi = min(lo + slab, n)
        a, b = max(lo - 1, 0), min(hi + 1, n)
        block = data[a:b]
        # d u_c / d voxel axis k, then world: J = I + grad_vox(u) A^-1
        grad = np.stack([np.stack(np.gradient(block[..., c]), -1) for c in range(3)],
                        -2)[lo - a: lo - a + hi - lo]
        folded += int(np.sum(np.linalg.det(np.eye(3) + grad @ a_inv) <= 0))
    return folded
