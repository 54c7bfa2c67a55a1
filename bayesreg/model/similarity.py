"""The similarity term's interface, and SSD ``E_s`` (paper Eq. 1) by Gauss quadrature on every
tetrahedron.

A similarity term is a pytree (a NamedTuple) with

* ``residuals(u_e)``: weighted residuals ``r`` (any shape) for element displacements ``u_e``
  ``(M, 4, 3)`` mm, with the term's value ``E = sum r^2``;
* ``energy(u_e)``: ``E`` ``()``, the value the log-density takes as ``-E / T_s``;
* ``gram(u, tets, n_nodes)``: the Gauss-Newton Gram matrix ``J^T J`` ``(3N, 3N)`` of the
  residuals with respect to the nodal displacements (DOF order ``3*i + axis``), for the
  Laplace proposal (:func:`bayesreg.inference.initialisation.laplace_precision`);
* ``kind``: its name in ``model.similarity``; ``n_observations``: how many values it sees.

Its temperature ``T_s`` is the posterior's (:func:`bayesreg.model.posterior.build_posterior`),
set per term in the config.  :class:`SSDTerm` (here) is the paper's; :class:`LNCCTerm`
(:mod:`bayesreg.model.lncc`, local normalised cross-correlation) the one for image pairs of
different intensities.

SSD
---

``E_s(u) = sum_e sum_q w_eq (f(x_eq) - m(x_eq + u(x_eq)))^2`` with the degree-2 exact
4-point rule (Zienkiewicz & Taylor, ref. [11] of the paper): barycentric points
``(a, b, b, b)`` and permutations, ``a = (5 + 3 sqrt 5) / 20``, ``b = (5 - sqrt 5) / 20``,
weights ``V_e / 4``.  ``u(x_eq)`` is the FE interpolant of the nodal displacements;
``m`` is sampled by trilinear interpolation in world coordinates through its affine and
takes the value ``cval`` (default 0, background) outside its grid.  :class:`SSDTerm` keeps
``m`` only over the box that the quadrature points can reach while the log-density is
finite (``reach`` of :func:`build_ssd`: every node outside the skull), with one voxel of
``cval`` where that box leaves ``m``'s grid: the values of ``E_s`` are those of the whole
image, from a smaller array (the paper's 2 mm MNI image: 15 MB of float64 down to about
5 MB, which the chains' other arrays then evict less from the cache).  ``moving_dtype``
float32 stores that array in half the bytes again; its values are rounded once (relative
``2^-24``), and the interpolation and the sums stay float64.

Beyond the paper, ``level`` k > 0 uses the composite rule: every tetrahedron is split k
times into 8 of equal volume (edge midpoints; the inner octahedron cut along one
diagonal, Bey's red refinement) and the 4-point rule applied in each of the ``8^k``
children, ``4 * 8^k`` points of weight ``V_e / (4 * 8^k)``.  On a paper-size mesh (16 mm
edges, about 60 voxels of 2 mm per element) the paper's 4 points sample the image far
below its resolution, so ``E_s`` as a function of ``u`` wiggles at the voxel scale
(aliasing: local modes of the boundary nodes); the composite rule converges to the
integral of Eq. 1.

Units: intensities as given (the pipeline scales them to about [0, 1]), volumes in mm^3,
so ``E_s`` is in ``intensity^2 mm^3``.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

import jax
import jax.numpy as jnp

from bayesreg.data.images import Image, check_image, grid_box, world_to_voxel
from bayesreg.data.interpolation import cubic_clamped, cubic_coefficients, interpolate, trilinear_clamped
from bayesreg.mesh.tetmesh import signed_volumes

__all__ = ["GAUSS_BARY", "MOVING_DTYPES", "quadrature_rule", "gauss_points", "SSDTerm", "build_ssd",
           "reach_box", "sample_moving", "moving_values", "ssd_residuals", "ssd", "moving_jacobian",
           "ssd_gram", "residual_gram"]

_A = (5.0 + 3.0 * np.sqrt(5.0)) / 20.0
_B = (5.0 - np.sqrt(5.0)) / 20.0
GAUSS_BARY = np.full((4, 4), _B) + np.eye(4) * (_A - _B)
"""Barycentric coordinates of the 4 Gauss points, ``(4 points, 4 nodes)``."""


# children of the red refinement, as indices into [v0, v1, v2, v3, m01, m02, m03, m12, m13, m23]
_RED_CHILDREN = np.array([
    [0, 4, 5, 6], [4, 1, 7, 8], [5, 7, 2, 9], [6, 8, 9, 3],  # corner tetrahedra
    [4, 5, 6, 8], [4, 5, 7, 8], [5, 6, 8, 9], [5, 7, 8, 9],  # octahedron, diagonal m02-m13
])
_EDGES = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]


def quadrature_rule(level: int = 0):
    """Barycentric points and weights of the composite Gauss rule on one tetrahedron.

    Parameters
    ----------
    level : int
        0: the paper's 4-point rule; k: that rule in each of the ``8^k`` children of k red
        refinements (module docstring).

    Returns
    -------
    bary : (Q, 4) ndarray
        Barycentric coordinates of the ``Q = 4 * 8^level`` points (rows sum to 1).
    weights : (Q,) ndarray
        Fractions of the element volume (sum to 1; all ``1 / Q``).

    Raises
    ------
    ValueError
        ``level`` negative or above 3 (``4 * 8^3 = 2048`` points per element).
    """
    level = int(level)
    if not 0 <= level <= 3:
        raise ValueError(f"quadrature level must be 0..3, got {level}")
    verts = np.eye(4)[None]  # (children, 4 vertices, 4 barycentric)
    for _ in range(level):
        mids = np.stack([(verts[:, i] + verts[:, j]) / 2 for i, j in _EDGES], axis=1)
        allv = np.concatenate([verts, mids], axis=1)  # (C, 10, 4)
        verts = allv[:, _RED_CHILDREN].reshape(-1, 4, 4)
    bary = np.einsum("qa,cad->cqd", GAUSS_BARY, verts).reshape(-1, 4)
    return bary, np.full(len(bary), 1.0 / len(bary))


def gauss_points(nodes, tets, level: int = 0):
    """World coordinates ``(M, Q, 3)`` and weights ``(M, Q)`` (mm^3) of the quadrature points.

    ``Q = 4 * 8^level`` (:func:`quadrature_rule`); ``level=0`` is the paper's rule.
    """
    bary, frac = quadrature_rule(level)
    x = np.asarray(nodes, dtype=np.float64)[np.asarray(tets)]
    pts = np.einsum("qa,mad->mqd", bary, x)
    vol = np.abs(signed_volumes(nodes, tets))
    return pts, vol[:, None] * frac[None, :]


class SSDTerm(NamedTuple):
    """Static data of ``E_s``: fixed image values at Gauss points and the moving image.

    Attributes
    ----------
    points : (M, Q, 3)
        Quadrature points in the undeformed mesh, world mm (``Q = 4`` for the paper's rule).
    sqrt_w : (M, Q)
        Square roots of the quadrature weights (mm^1.5).
    f_q : (M, Q)
        Pre-operative image ``f`` at the quadrature points.
    bary : (Q, 4)
        Barycentric coordinates of the points (:func:`quadrature_rule`).
    m : (I, J, K)
        Intra-operative image over the box the quadrature points can reach (see
        :func:`build_ssd`), with one voxel of ``cval`` wherever the box leaves the image's
        own grid, in float64 or float32 (``moving_dtype``); sampled by :func:`sample_moving`
        (in float64 either way).  With cubic interpolation, the cubic B-spline coefficients
        of that volume (:func:`bayesreg.data.interpolation.cubic_coefficients`).
    m_inv_affine : (4, 4)
        World-to-voxel matrix of the array ``m`` (world mm to its voxel indices).
    cval : ()
        Value of the moving image outside its grid.
    spline : (0,) or (1,)
        Its length says how ``m`` is interpolated (static, a shape): 0 trilinear, 1 cubic
        B-spline (:data:`INTERPOLATIONS`).
    """

    points: jax.Array
    sqrt_w: jax.Array
    f_q: jax.Array
    bary: jax.Array
    m: jax.Array
    m_inv_affine: jax.Array
    cval: jax.Array
    spline: jax.Array = None

    kind = "ssd"

    @property
    def interpolation(self) -> str:
        """``"cubic"`` or ``"linear"`` (trilinear)."""
        return "cubic" if self.spline is not None and self.spline.shape[0] else "linear"

    @property
    def n_observations(self) -> int:
        """The number of quadrature points ``M * Q``."""
        return int(np.size(self.sqrt_w))

    def residuals(self, u_e):
        """:func:`ssd_residuals` ``(M, Q)``."""
        return ssd_residuals(self, u_e)

    def energy(self, u_e):
        """:func:`ssd` ``()``, intensity^2 mm^3."""
        return ssd(self, u_e)

    def gram(self, u, tets, n_nodes: int):
        """:func:`ssd_gram` (sparse, exact for this term's residuals)."""
        return ssd_gram(self, u, tets, n_nodes)


def reach_box(reach: Image):
    """World bounding box ``(2, 3)`` mm of the points that a node may occupy.

    ``reach`` is a 0/1 image of the voxels where a node is allowed (the complement of the
    hard-constraint region; a node belongs to its nearest voxel, and outside the grid is
    forbidden, as in :mod:`bayesreg.model.posterior`).  A node lies within half a voxel of an
    allowed voxel centre, so inside the box of the allowed voxels grown by half a voxel;
    every quadrature point of an element whose four nodes are allowed lies inside the same
    (convex) box.  Returns ``None`` when no voxel is allowed.
    """
    idx = np.argwhere(np.asarray(reach.data) > 0)
    if len(idx) == 0:
        return None
    lo, hi = idx.min(axis=0) - 0.5, idx.max(axis=0) + 0.5
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    world = corners @ np.asarray(reach.affine, np.float64)[:3, :3].T + np.asarray(reach.affine)[:3, 3]
    return np.stack([world.min(axis=0), world.max(axis=0)])


def _moving_array(m: Image, cval: float, box=None, margin: int = 1):
    """``m`` over the voxel box that covers ``box`` (world, ``(2, 3)``; ``None``: the whole
    grid), ``margin`` voxels beyond it and ``cval`` outside ``m``'s grid; with its inverse
    affine."""
    data = np.asarray(m.data, dtype=np.float64)
    shape = np.array(data.shape)
    if box is None:
        lo, hi = np.zeros(3, int), shape - 1
    else:
        corners = np.array([[a, b, c] for a in box[:, 0] for b in box[:, 1] for c in box[:, 2]])
        vox = world_to_voxel(m.affine, corners)
        # the trilinear corners of a point c are floor(c) and floor(c) + 1: one more for round-off
        lo = np.floor(vox.min(axis=0)).astype(int) - margin
        hi = np.floor(vox.max(axis=0)).astype(int) + 1 + margin
        lo, hi = np.maximum(lo, -1), np.minimum(hi, shape)  # never more than the grid + 1 voxel
    # one voxel of cval where the box reaches past the grid (the clamped sampler then
    # blends toward cval exactly as images.interpolate does, and stays at cval beyond)
    lo = np.where(lo <= 0, -1, lo)
    hi = np.where(hi >= shape - 1, shape, hi)
    out = np.full(tuple(hi - lo + 1), float(cval))
    src_lo, src_hi = np.maximum(lo, 0), np.minimum(hi, shape - 1)
    dst = tuple(slice(a - l, b - l + 1) for a, b, l in zip(src_lo, src_hi, lo))
    out[dst] = data[tuple(slice(a, b + 1) for a, b in zip(src_lo, src_hi))]
    shift = np.eye(4)
    shift[:3, 3] = -lo
    return out, shift @ np.linalg.inv(np.asarray(m.affine, np.float64))


#: :func:`build_ssd` warns when fewer than this fraction of the quadrature points lie in ``f``.
MIN_INSIDE_FRACTION = 0.5


def _check_overlap(img: Image, name: str, pts) -> None:
    """Raise if no point of ``pts`` ``(..., 3)`` lies in ``img``'s grid (voxel extent);
    warn if less than :data:`MIN_INSIDE_FRACTION` of them do (for ``f`` only)."""
    pts = np.reshape(pts, (-1, 3))
    c = world_to_voxel(img.affine, pts)
    inside = np.all((c >= -0.5) & (c <= np.array(img.data.shape) - 0.5), axis=1)
    frac = float(np.mean(inside)) if len(inside) else 1.0
    if frac == 0.0:
        box = grid_box(img.affine, img.data.shape)
        raise ValueError(
            f"no quadrature point of the mesh lies inside {name}'s grid (mesh box "
            f"{_fmt_box(pts.min(axis=0), pts.max(axis=0))} mm, {name} box {_fmt_box(*box)} mm): "
            f"the mesh and {name} do not share a world frame")
    if name == "f" and frac < MIN_INSIDE_FRACTION:
        warnings.warn(f"only {100 * frac:.1f}% of the mesh's quadrature points lie inside f's "
                      "grid; outside it f takes the value cval", UserWarning, stacklevel=3)


def _fmt_box(lo, hi) -> str:
    return f"{np.round(lo, 1).tolist()} to {np.round(hi, 1).tolist()}"


#: storage precisions of the moving image that :func:`build_ssd` accepts
MOVING_DTYPES = ("float64", "float32")

#: interpolations of the moving image that :func:`build_ssd` accepts: ``linear`` (trilinear,
#: the paper's: its gradient jumps at every voxel face) and ``cubic`` (B-spline with its
#: prefilter: C2, for gradient samplers)
INTERPOLATIONS = ("linear", "cubic")


def build_ssd(nodes, tets, f: Image, m: Image, *, cval=0.0, quadrature_level: int = 0,
              reach: Image | None = None, moving_dtype: str = "float64",
              interpolation: str = "linear") -> SSDTerm:
    """Precompute :class:`SSDTerm` for a mesh and an image pair (world frames must agree).

    Parameters
    ----------
    nodes : (N, 3) array_like
        world mm
    tets : (M, 4) array_like of int
    f, m : Image
        pre- and intra-operative images
    cval : float
        value of ``m`` outside its grid
    quadrature_level : int
        0 is the paper's 4 Gauss points per element, k the composite rule with ``4 * 8^k``
        (:func:`quadrature_rule`; ``ValueError`` outside 0..3).
    reach : Image, optional
        0/1 image of where a node may lie (the complement of the skull region).  ``m`` is
        then kept only over :func:`reach_box` (plus a voxel): every quadrature point of a
        finite log-density lies inside it, so ``E_s`` keeps the values of the whole image
        there.  Outside the box (some node already in the forbidden region, whose
        log-density is ``-inf`` anyway) the moving image is clamped to the box's faces.
        ``None``: the whole image.
    moving_dtype : {"float64", "float32"}
        Storage precision of ``m`` in the term.  float64 (default) keeps its values as
        given; float32 rounds them once (relative error at most ``2^-24``) and halves the
        bytes that every evaluation gathers from (several chains share a CPU's cache).
        The interpolation, the residuals and ``E_s`` are float64 either way; the rounding
        moves ``log p`` by an offset nearly constant over the chains' states, of the size
        of the CG tolerance's effect.
    interpolation : {"linear", "cubic"}
        How ``m`` is sampled at the displaced points: trilinear (the paper's; its gradient
        jumps at every voxel face) or cubic B-spline with its prefilter (C2: what a
        gradient sampler needs, several times the cost per point;
        :func:`bayesreg.data.interpolation.cubic_clamped`).  ``f`` at the fixed points is read
        the same way.

    Raises
    ------
    ValueError
        If ``f``, ``m`` (or ``reach``) is not a 3D :class:`Image` with a finite invertible
        affine, ``f`` or ``m`` has a NaN or infinite voxel, ``quadrature_level`` is outside
        0..3, ``moving_dtype`` is not one of :data:`MOVING_DTYPES`, ``interpolation`` not one
        of :data:`INTERPOLATIONS`, or no quadrature point
        of the mesh lies inside ``f``'s grid or ``m``'s grid (the mesh and the images then
        do not share a world frame).

    Warns
    -----
    UserWarning
        If less than half of the quadrature points lie inside ``f``'s grid.
    """
    if moving_dtype not in MOVING_DTYPES:
        raise ValueError(f"moving_dtype must be one of {MOVING_DTYPES}, got {moving_dtype!r}")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    cubic = interpolation == "cubic"
    f = check_image(f, "f", finite=True)
    m = check_image(m, "m", finite=True)
    if reach is not None:
        reach = check_image(reach, "reach")
    bary, _ = quadrature_rule(quadrature_level)
    pts, w = gauss_points(nodes, tets, quadrature_level)
    for img, name in ((f, "f"), (m, "m")):
        _check_overlap(img, name, pts)
    f_inv = jnp.asarray(np.linalg.inv(f.affine))
    if cubic:  # f read as m is: its whole grid with a voxel of cval around it
        f_arr, f_inv = _moving_array(f, float(cval))
        f_q = jax.jit(cubic_clamped)(jnp.asarray(cubic_coefficients(f_arr)), jnp.asarray(
            pts @ f_inv[:3, :3].T + f_inv[:3, 3]))
    else:
        f_q = jax.jit(interpolate)(jnp.asarray(f.data, dtype=jnp.float64), f_inv, jnp.asarray(pts),
                                   float(cval))  # one program, not one per op
    box = None if reach is None else reach_box(reach)
    # cubic: the spline's taps reach two voxels past a point, and its prefilter's boundary
    # effect decays by 0.27 a voxel (8 voxels: 3e-5)
    m_arr, m_inv = _moving_array(m, float(cval), box, margin=8 if cubic else 1)
    if cubic:
        m_arr = cubic_coefficients(m_arr)
    return SSDTerm(
        points=jnp.asarray(pts),
        sqrt_w=jnp.sqrt(jnp.asarray(w)),
        f_q=f_q,
        bary=jnp.asarray(bary),
        m=jnp.asarray(m_arr.astype(moving_dtype)),
        m_inv_affine=jnp.asarray(m_inv),
        cval=jnp.asarray(float(cval)),
        spline=jnp.zeros((1 if cubic else 0,)),
    )


def sample_moving(term: SSDTerm, points):
    """The moving image at world points ``(..., 3)`` mm, ``(...,)``: trilinear or cubic
    (:attr:`SSDTerm.interpolation`), ``cval`` outside its grid, valid inside the box of
    :func:`build_ssd` (``reach``); differentiable
    (:func:`bayesreg.data.interpolation.trilinear_clamped`, :func:`~bayesreg.data.interpolation.cubic_clamped`)."""
    a = term.m_inv_affine
    coords = points @ a[:3, :3].T + a[:3, 3]
    if term.interpolation == "cubic":
        return cubic_clamped(term.m, coords)
    return trilinear_clamped(term.m, coords)


def moving_values(term: SSDTerm, u_e):
    """``m(x_q + u(x_q))`` ``(M, Q)``: the moving image at the displaced quadrature points.

    Parameters
    ----------
    term : SSDTerm
    u_e : (M, 4, 3) array
        Displacements of each element's nodes, mm (``u(x_q)`` is their FE interpolant).
    """
    # explicit multiply-and-sum: einsum over gathered values is slower on XLA:CPU
    u_q = jnp.sum(term.bary[None, :, :, None] * u_e[:, None, :, :], axis=2)
    return sample_moving(term, term.points + u_q)


def ssd_residuals(term: SSDTerm, u_e):
    """Weighted residuals ``sqrt(w_q) (f(x_q) - m(x_q + u(x_q)))``, ``(M, Q)``.

    Parameters
    ----------
    term : SSDTerm
    u_e : (M, 4, 3) array
        Displacements of each element's nodes, mm.
    """
    return term.sqrt_w * (term.f_q - moving_values(term, u_e))


def ssd(term: SSDTerm, u_e):
    """``E_s`` (paper Eq. 1) for element displacements ``u_e`` ``(M, 4, 3)``."""
    r = ssd_residuals(term, u_e)
    return jnp.sum(r * r)


def moving_jacobian(term: SSDTerm, u, tets, n_nodes: int, scale=None):
    """The Jacobian of the moving image's values at the displaced quadrature points,
    ``scale * m(x_q + u(x_q))`` ``(M * Q,)``, with respect to the nodal displacements: sparse
    (CSR) ``(M * Q, 3N)``, 12 entries a row (each point moves with its element's four nodes).

    Parameters
    ----------
    term : SSDTerm
        The quadrature and the moving image.
    u : (N, 3) array_like
        Nodal displacements, mm.
    tets : (M, 4) int array_like
    n_nodes : int
    scale : (M, Q) array_like, optional
        A factor per point (default 1).
    """
    tets = np.asarray(tets)
    bary = np.asarray(term.bary)  # (Q, 4)
    nq = len(bary)
    u_q = np.einsum("qa,mad->mqd", bary, np.asarray(u)[tets])
    y = np.asarray(term.points) + u_q
    grad_m = jax.jit(jax.vmap(jax.grad(lambda p: sample_moving(term, p))))(
        jnp.asarray(y.reshape(-1, 3))
    )
    grad_m = np.asarray(grad_m).reshape(len(tets), nq, 3)
    scale = np.ones((len(tets), nq)) if scale is None else np.asarray(scale)
    vals = scale[:, :, None, None] * bary[None, :, :, None] * grad_m[:, :, None, :]
    rows = np.broadcast_to(np.arange(nq * len(tets)).reshape(-1, nq)[:, :, None, None], vals.shape)
    cols = 3 * tets[:, None, :, None] + np.arange(3)[None, None, None, :]
    cols = np.broadcast_to(cols, vals.shape)
    return sp.csr_array((vals.ravel(), (rows.ravel(), cols.ravel())),
                        shape=(nq * len(tets), 3 * n_nodes))


def ssd_gram(term: SSDTerm, u, tets, n_nodes: int):
    """Gauss-Newton Gram matrix ``J^T J`` of :func:`ssd_residuals` with respect to the nodal
    displacements, ``(3N, 3N)`` sparse (CSR): ``J = -diag(sqrt w) dm/du``
    (:func:`moving_jacobian`).

    Parameters
    ----------
    term : SSDTerm
    u : (N, 3) array_like
        Nodal displacements, mm.
    tets : (M, 4) int array_like
    n_nodes : int
    """
    jac = moving_jacobian(term, u, tets, n_nodes, scale=-np.asarray(term.sqrt_w))
    return (jac.T @ jac).tocsr()


#: basis vectors per batch of :func:`residual_gram` (memory: this many residual vectors)
GRAM_BATCH = 32


def residual_gram(residuals, u, *, batch: int = GRAM_BATCH):
    """``J^T J`` ``(3N, 3N)`` (CSR) of any residual function at nodal displacements ``u``.

    ``J`` is the Jacobian of ``residuals(u)`` (any shape) with respect to ``u`` ``(N, 3)``;
    its Gram matrix is formed column by column, ``J^T (J e_j)``, by forward- then
    reverse-mode products in batches of ``batch`` columns (``3N`` of each in all), never
    ``J`` itself (one row per residual).  The fallback for a new term without a structure
    of its own (SSD's and LNCC's ``gram`` use theirs: :func:`ssd_gram`,
    :func:`bayesreg.model.lncc.lncc_gram`); dense work ``O(N^2)`` memory, ``3N`` products.

    Parameters
    ----------
    residuals : callable
        ``u`` ``(N, 3)`` -> residuals (any shape), differentiable by JAX.
    u : (N, 3) array_like
        Nodal displacements, mm.
    batch : int
        Columns per compiled batch.

    Returns
    -------
    (3N, 3N) scipy.sparse.csr_array
    """
    u = jnp.asarray(u, jnp.float64)
    n = u.size
    _, vjp = jax.vjp(residuals, u)

    @jax.jit
    def columns(basis):
        def one(e):
            _, jv = jax.jvp(residuals, (u,), (e.reshape(u.shape),))
            return vjp(jv)[0].ravel()
        return jax.vmap(one)(basis)

    out = np.empty((n, n))
    eye = np.eye(n)
    for start in range(0, n, batch):
        stop = min(start + batch, n)
        block = np.zeros((batch, n))
        block[: stop - start] = eye[start:stop]
        out[start:stop] = np.asarray(columns(jnp.asarray(block)))[: stop - start]
    return sp.csr_array(0.5 * (out + out.T))
