"""Synthetic brain shift with known truth, and FE-to-image-grid interpolation.

* :func:`brain_shift` - boundary nodes at the top of the brain pushed toward the brain's
  centre of gravity (a supine craniotomy, paper Sec. 4.1), the push fading smoothly over
  the surrounding boundary; interior nodes from the FE solve with known ``lam``, ``mu``.
* :func:`warp_image` - ``m`` from ``f`` with ``m(x + u(x)) = f(x)`` exactly for the
  piecewise-affine FE map: each voxel of ``m`` is located in the *deformed* mesh and mapped
  back with barycentric coordinates.
* :func:`interpolation_matrix` - sparse FE interpolation of nodal values on an image grid
  (used for displacement maps in NIfTI).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bayesreg.fem import stiffness_matrix
from bayesreg.images import Image, interpolate_numpy
from bayesreg.mesh import Mesh, signed_volumes

__all__ = [
    "Truth", "brain_shift", "locate", "interpolation_matrix", "grid_moments", "warp_image",
    "solve_dirichlet",
]


class Truth(NamedTuple):
    """Known deformation of a synthetic case.

    Attributes
    ----------
    u : (N, 3)  nodal displacements, mm
    lam_e, mu_e : (M,)  per-element Lamé parameters used
    pushed : (P,) int  nodes given the full push (Dirichlet)
    """

    u: np.ndarray
    lam_e: np.ndarray
    mu_e: np.ndarray
    pushed: np.ndarray


def solve_dirichlet(mesh: Mesh, lam_e, mu_e, fixed, u_fixed):
    """Direct (SciPy) solve of ``K u = 0`` with ``u[fixed] = u_fixed``; returns ``(N, 3)``."""
    k = stiffness_matrix(mesh.nodes, mesh.tets, lam_e, mu_e)
    n = len(mesh.nodes)
    is_f = np.zeros(n, bool)
    is_f[fixed] = True
    fd = (3 * np.flatnonzero(is_f)[:, None] + np.arange(3)).ravel()
    fr = (3 * np.flatnonzero(~is_f)[:, None] + np.arange(3)).ravel()
    u = np.zeros(3 * n)
    u[fd] = np.asarray(u_fixed, dtype=np.float64).ravel()
    u[fr] = spla.spsolve(sp.csc_matrix(k[fr][:, fr]), -(k[fr][:, fd] @ u[fd]))
    return u.reshape(n, 3)


def brain_shift(mesh: Mesh, lam_e, mu_e, *, shift_mm=10.0, n_pushed=20, falloff_mm=30.0) -> Truth:
    """Synthetic brain shift toward the centre of gravity.

    The ``n_pushed`` boundary nodes with the largest world ``z`` (superior) move
    ``shift_mm`` toward the volume-weighted centroid of the mesh.  Every other boundary
    node ``p`` moves toward the centroid by ``shift_mm * exp(-d^2 / (2 falloff_mm^2))``,
    ``d`` its distance to the nearest pushed node; interior nodes solve ``K u = 0``.

    Raises
    ------
    ValueError
        Non-positive ``shift_mm``/``falloff_mm`` or ``n_pushed`` outside ``[1, n_b]``.
    """
    nb = len(mesh.boundary)
    if not 1 <= n_pushed <= nb:
        raise ValueError(f"n_pushed must lie in [1, {nb}], got {n_pushed}")
    if shift_mm <= 0 or falloff_mm <= 0:
        raise ValueError("shift_mm and falloff_mm must be > 0")
    vol = np.abs(signed_volumes(mesh.nodes, mesh.tets))
    cog = (vol[:, None] * mesh.nodes[mesh.tets].mean(axis=1)).sum(0) / vol.sum()
    pb = mesh.nodes[mesh.boundary]
    order = np.argsort(-pb[:, 2])
    pushed_local = order[:n_pushed]
    d = np.min(np.linalg.norm(pb[:, None, :] - pb[None, pushed_local, :], axis=2), axis=1)
    weight = np.exp(-0.5 * (d / falloff_mm) ** 2)
    weight[pushed_local] = 1.0
    direction = cog - pb
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    u_b = shift_mm * weight[:, None] * direction
    u = solve_dirichlet(mesh, lam_e, mu_e, mesh.boundary, u_b)
    return Truth(u, np.asarray(lam_e, float), np.asarray(mu_e, float), mesh.boundary[pushed_local])


def locate(nodes, tets, points, *, tol=1e-9):
    """Element containing each point and its barycentric coordinates.

    Each element is rasterised over the points inside its bounding box, so the search is
    exact (no candidate lists).

    Parameters
    ----------
    nodes : (N, 3)  world mm
    tets : (M, 4)
    points : (P, 3)  world mm, e.g. voxel centres

    Returns
    -------
    elem : (P,) int  (-1 where no element contains the point)
    bary : (P, 4)
    """
    nodes = np.asarray(nodes, np.float64)
    tets = np.asarray(tets)
    points = np.asarray(points, np.float64)
    elem = np.full(len(points), -1, np.int64)
    bary = np.zeros((len(points), 4))
    x = nodes[tets]
    lo, hi = x.min(1), x.max(1)
    # sort points along x for bounding-box range queries
    order = np.argsort(points[:, 0], kind="stable")
    px = points[order, 0]
    t_inv = np.linalg.inv(np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], -1))
    for e in range(len(tets)):
        a, b = np.searchsorted(px, [lo[e, 0] - tol, hi[e, 0] + tol])
        if a == b:
            continue
        cand = order[a:b]
        pc = points[cand]
        inb = np.all((pc[:, 1:] >= lo[e, 1:] - tol) & (pc[:, 1:] <= hi[e, 1:] + tol), axis=1)
        cand = cand[inb]
        if cand.size == 0:
            continue
        lam = (points[cand] - x[e, 0]) @ t_inv[e].T
        bc = np.column_stack([1 - lam.sum(1), lam])
        hit = np.all(bc >= -tol, axis=1) & (elem[cand] < 0)
        elem[cand[hit]] = e
        bary[cand[hit]] = bc[hit]
    return elem, bary


def _grid_points(img: Image):
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in img.data.shape[:3]], indexing="ij"), -1)
    return ijk.reshape(-1, 3) @ img.affine[:3, :3].T + img.affine[:3, 3]


def interpolation_matrix(mesh: Mesh, grid: Image):
    """Sparse ``(n_voxels, N)`` matrix of FE shape-function values at the voxel centres.

    Rows of voxels outside the (undeformed) mesh are zero; ``inside`` marks the others.

    Returns
    -------
    W : scipy.sparse.csr_array
    inside : (I, J, K) bool
    """
    pts = _grid_points(grid)
    elem, bary = locate(mesh.nodes, mesh.tets, pts)
    rows = np.flatnonzero(elem >= 0)
    cols = mesh.tets[elem[rows]]
    w = sp.csr_array(
        (bary[rows].ravel(), (np.repeat(rows, 4), cols.ravel())), shape=(len(pts), len(mesh.nodes))
    )
    return w, (elem >= 0).reshape(grid.data.shape[:3])


def grid_moments(mesh: Mesh, grid: Image, draws):
    """Posterior mean and sd of the FE-interpolated displacement on an image grid.

    The interpolant is linear in the nodal values, so per voxel ``v`` and axis ``c``
    ``Var u_c(v) = w_v^T Cov_c w_v`` with ``w_v`` the 4 barycentric weights of the element
    containing ``v`` and ``Cov_c`` the ``(N, N)`` posterior covariance of axis ``c``; no
    per-draw interpolation is needed.

    Parameters
    ----------
    mesh : Mesh
    grid : Image  (only its shape and affine are used)
    draws : (S, N, 3) array  nodal displacement draws, mm

    Returns
    -------
    mean, sd : (I, J, K, 3) ndarray  mm; zero outside the mesh
    """
    draws = np.asarray(draws, np.float64)
    pts = _grid_points(grid)
    elem, bary = locate(mesh.nodes, mesh.tets, pts)
    inside = np.flatnonzero(elem >= 0)
    idx = mesh.tets[elem[inside]]  # (P, 4)
    w = bary[inside]
    mean_n = draws.mean(0)
    centred = draws - mean_n
    mean = np.zeros((len(pts), 3))
    sd = np.zeros((len(pts), 3))
    mean[inside] = np.einsum("pa,pac->pc", w, mean_n[idx])
    for c in range(3):
        cov = centred[:, :, c].T @ centred[:, :, c] / len(draws)
        var = np.einsum("pa,pb,pab->p", w, w, cov[idx[:, :, None], idx[:, None, :]])
        sd[inside, c] = np.sqrt(np.maximum(var, 0.0))
    shape = grid.data.shape[:3]
    return mean.reshape(*shape, 3), sd.reshape(*shape, 3)


def warp_image(f: Image, mesh: Mesh, u, *, background=0.0) -> Image:
    """Intra-operative image ``m`` with ``m(x + u(x)) = f(x)`` for the FE map ``x -> x + u(x)``.

    For every voxel centre ``y`` of ``m`` (same grid as ``f``) the deformed element
    containing ``y`` is found; its barycentric coordinates give ``x`` in the undeformed
    element and ``m(y) = f(x)`` (trilinear).  Voxels covered by no deformed element take
    ``background``.

    Raises
    ------
    ValueError
        If the deformed mesh has an inverted element (the map is then not invertible).
    """
    u = np.asarray(u, np.float64)
    deformed = mesh.nodes + u
    vol = signed_volumes(deformed, mesh.tets)
    if np.any(vol <= 0):
        raise ValueError(f"{int(np.sum(vol <= 0))} inverted element(s) in the deformed mesh")
    pts = _grid_points(f)
    elem, bary = locate(deformed, mesh.tets, pts)
    inside = elem >= 0
    x = np.einsum("pa,pad->pd", bary[inside], mesh.nodes[mesh.tets[elem[inside]]])
    out = np.full(len(pts), float(background))
    out[inside] = interpolate_numpy(f, x, order=1, cval=background)
    return Image(out.reshape(f.data.shape), f.affine)
