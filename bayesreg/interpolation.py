"""Differentiable trilinear interpolation of images at world points (JAX).

Used by the similarity term (:mod:`bayesreg.similarity`): the moving image ``m`` is sampled at
the deformed Gauss points, and the log-density's gradient needs the derivative of the
interpolant.  Its JVP is defined explicitly (``jax.custom_jvp``): the trilinear gradient of
the cell the point lies in, from the same eight corner values as the value.  Host-side
(NumPy/SciPy) interpolation is :func:`bayesreg.images.interpolate_numpy`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["interpolate", "trilinear_clamped"]


def interpolate(volume, inv_affine, points, cval=0.0):
    """Trilinear interpolation of ``volume`` at world points (JAX, differentiable).

    Parameters
    ----------
    volume : (I, J, K) array
    inv_affine : (4, 4) array
        World-to-voxel matrix (inverse of the image affine).
    points : (..., 3) array
        World coordinates, mm.
    cval : float
        Value of voxels outside the grid: a point blends toward ``cval`` within one voxel
        of the border and equals ``cval`` beyond it.

    Returns
    -------
    (...,) array

    Notes
    -----
    Differentiable in every argument through a hand-written JVP (``jax.custom_jvp`` with
    symbolic zeros): the derivative in ``points`` is that of the trilinear polynomial of
    the point's cell, computed from the same 8 gathered corners as the value (JAX's own
    reverse mode of the gather-and-blend is several times slower).
    """
    return _interpolate(volume, inv_affine, points, cval)


def _cell_corners(volume, inv_affine, points, cval):
    """Voxel coordinates ``c`` ``(..., 3)``, their offsets ``t`` in the cell, the 8 corner
    values ``(..., 8)`` and which corners lie inside the grid."""
    c = points @ inv_affine[:3, :3].T + inv_affine[:3, 3]
    shp = volume.shape
    c0 = jnp.floor(c)
    t = c - c0
    c0 = c0.astype(jnp.int32)
    # the 8 corners gathered at once from the flattened volume: one gather of (..., 8)
    # instead of eight 3-D advanced-indexing gathers (faster on XLA:CPU)
    offs = jnp.array(_CORNERS, jnp.int32)  # (8, 3)
    idx = c0[..., None, :] + offs
    inside = jnp.all((idx >= 0) & (idx < jnp.array(shp)), axis=-1)
    idc = jnp.clip(idx, 0, jnp.array(shp) - 1)
    flat = (idc[..., 0] * shp[1] + idc[..., 1]) * shp[2] + idc[..., 2]
    v = jnp.where(inside, jnp.take(volume.reshape(-1), flat, mode="clip"), cval)
    return t, v, flat, inside


def _trilinear_factors(t):
    """Per-axis factors ``(..., 8, 3)`` (``t`` or ``1 - t``) and their signs ``(8, 3)``."""
    offs = np.array(_CORNERS)
    return jnp.where(offs == 1, t[..., None, :], 1.0 - t[..., None, :]), np.where(offs == 1, 1.0, -1.0)


@jax.custom_jvp
def _interpolate(volume, inv_affine, points, cval):
    t, v, _, _ = _cell_corners(volume, inv_affine, points, cval)
    f, _ = _trilinear_factors(t)
    return jnp.sum(f[..., 0] * f[..., 1] * f[..., 2] * v, axis=-1)


def _interpolate_jvp(primals, tangents):
    from jax.custom_derivatives import SymbolicZero

    volume, inv_affine, points, cval = primals
    d_vol, d_inv, d_pts, d_cval = tangents
    t, v, flat, inside = _cell_corners(volume, inv_affine, points, cval)
    f, sign = _trilinear_factors(t)
    w = f[..., 0] * f[..., 1] * f[..., 2]
    val = jnp.sum(w * v, axis=-1)
    out = jnp.zeros_like(val)
    zero = (lambda d: isinstance(d, SymbolicZero))
    if not (zero(d_pts) and zero(d_inv)):
        # d val / d c (voxel coordinates): the cell's trilinear polynomial differentiated
        dw = jnp.stack([sign[:, 0] * f[..., 1] * f[..., 2], f[..., 0] * sign[:, 1] * f[..., 2],
                        f[..., 0] * f[..., 1] * sign[:, 2]], axis=-1)  # (..., 8, 3)
        g_c = jnp.sum(dw * v[..., None], axis=-2)
        dc = jnp.zeros_like(t)
        if not zero(d_pts):
            dc = dc + d_pts @ inv_affine[:3, :3].T
        if not zero(d_inv):
            dc = dc + points @ d_inv[:3, :3].T + d_inv[:3, 3]
        out = out + jnp.sum(g_c * dc, axis=-1)
    if not zero(d_vol):
        dv = jnp.where(inside, jnp.take(d_vol.reshape(-1), flat, mode="clip"), 0.0)
        out = out + jnp.sum(w * dv, axis=-1)
    if not zero(d_cval):
        out = out + jnp.sum(jnp.where(inside, 0.0, w), axis=-1) * d_cval
    return val, out


_interpolate.defjvp(_interpolate_jvp, symbolic_zeros=True)


_CORNERS = [(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]


# the 2x2x2 voxels of a cell are four pairs of neighbours along the last (contiguous) axis:
# four gathers of 2 values from the flattened volume
_PAIR_GATHER = jax.lax.GatherDimensionNumbers(offset_dims=(1,), collapsed_slice_dims=(),
                                              start_index_map=(0,))


def trilinear_clamped(volume, coords):
    """Trilinear interpolation at voxel coordinates clamped to the grid (JAX, differentiable).

    The fast path of the similarity term (:func:`bayesreg.similarity.moving_values`): each
    point's cell is fetched as four pairs of neighbours along the contiguous axis and
    blended by nested linear interpolations (z, then y, then x).  A point outside the grid takes the value at
    its nearest point of the grid (coordinates clamped to ``[0, shape - 1]``), so a volume
    with one voxel of a constant ``c`` around its data interpolates exactly as
    :func:`interpolate` with ``cval=c`` does everywhere (inside, in the one-voxel band
    where it blends toward ``c``, and beyond), from four gathers of pairs instead of
    :func:`interpolate`'s eight single-value gathers.

    Parameters
    ----------
    volume : (I, J, K) array
        ``I, J, K >= 2``.
    coords : (..., 3) array
        Continuous voxel coordinates ``(i, j, k)`` (voxel centres at integers).  A NaN
        coordinate gives NaN (never an out-of-bounds read: the gather clamps its indices).

    Returns
    -------
    (...,) array
        Differentiable in ``volume`` and ``coords`` (hand-written JVP: the derivative of the
        cell's trilinear polynomial; zero across a clamped coordinate).

    Raises
    ------
    ValueError
        ``volume`` not 3-D or smaller than 2 voxels along an axis, or ``coords`` not ``(..., 3)``.
    """
    if volume.ndim != 3 or min(volume.shape) < 2:
        raise ValueError(f"volume must be 3-D with at least 2 voxels per axis, got shape {volume.shape}")
    if coords.shape[-1:] != (3,):
        raise ValueError(f"coords must have shape (..., 3), got {coords.shape}")
    hi = jnp.asarray(volume.shape, coords.dtype) - 1.0
    return _trilinear_cells(volume, jnp.clip(coords, 0.0, hi))


def _cell_block(volume, c):
    """Offsets ``t`` ``(..., 3)`` in the cell of ``c`` (clamped coordinates) and its 2x2x2 voxels.

    The flat index of each cell's first corner is materialised (``optimization_barrier``)
    before the gathers: fused into them, XLA:CPU recomputes it for every gathered value.
    """
    c0 = jnp.minimum(jnp.floor(c), jnp.asarray(volume.shape, c.dtype) - 2.0)
    ci = c0.astype(jnp.int32)
    _, nj, nk = volume.shape
    base = jax.lax.optimization_barrier((ci[..., 0] * nj + ci[..., 1]) * nk + ci[..., 2]).reshape(-1)
    starts = (base[:, None] + jnp.asarray([0, nk, nj * nk, nj * nk + nk], jnp.int32)).reshape(-1, 1)
    v = jax.lax.gather(volume.reshape(-1), starts, _PAIR_GATHER, (2,), mode=jax.lax.GatherScatterMode.CLIP)
    return c - c0, v.reshape(c.shape[:-1] + (2, 2, 2)).astype(c.dtype)


def _lerp(a, b, t):
    return a * (1.0 - t) + b * t  # exact at t = 0 and t = 1


def _blend(t, v):
    """Trilinear value of the blocks ``v`` ``(..., 2, 2, 2)`` at offsets ``t`` ``(..., 3)``."""
    vz = _lerp(v[..., 0], v[..., 1], t[..., 2, None, None])  # (..., 2, 2): x, y
    vy = _lerp(vz[..., 0], vz[..., 1], t[..., 1, None])  # (..., 2): x
    return _lerp(vy[..., 0], vy[..., 1], t[..., 0]), vz, vy


@jax.custom_jvp
def _trilinear_cells(volume, c):
    t, v = _cell_block(volume, c)
    return _blend(t, v)[0]


def _trilinear_cells_jvp(primals, tangents):
    from jax.custom_derivatives import SymbolicZero

    volume, c = primals
    d_vol, d_c = tangents
    t, v = _cell_block(volume, c)
    val, vz, vy = _blend(t, v)
    out = jnp.zeros_like(val)
    if not isinstance(d_c, SymbolicZero):
        dz = v[..., 1] - v[..., 0]  # d/dt_z at the four (x, y) edges
        dzy = _lerp(dz[..., 0], dz[..., 1], t[..., 1, None])
        g = jnp.stack([vy[..., 1] - vy[..., 0],
                       _lerp(vz[..., 0, 1] - vz[..., 0, 0], vz[..., 1, 1] - vz[..., 1, 0], t[..., 0]),
                       _lerp(dzy[..., 0], dzy[..., 1], t[..., 0])], axis=-1)
        out = out + jnp.sum(g * d_c, axis=-1)
    if not isinstance(d_vol, SymbolicZero):
        out = out + _trilinear_cells(d_vol, c)  # linear in the volume
    return val, out


_trilinear_cells.defjvp(_trilinear_cells_jvp, symbolic_zeros=True)
