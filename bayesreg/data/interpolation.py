"""Differentiable trilinear interpolation of images at world points (JAX).

Used by the similarity term (:mod:`bayesreg.model.similarity`): the moving image ``m`` is sampled at
the deformed Gauss points, and the log-density's gradient needs the derivative of the
interpolant.  Its JVP is defined explicitly (``jax.custom_jvp``): the trilinear gradient of
the cell the point lies in, from the same eight corner values as the value.  Host-side
(NumPy/SciPy) interpolation is :func:`bayesreg.data.images.interpolate_numpy`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["interpolate", "trilinear_clamped", "cubic_coefficients", "cubic_clamped", "CUBIC_PAD"]


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

    The fast path of the similarity term (:func:`bayesreg.model.similarity.moving_values`): each
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


# --- cubic B-spline interpolation (C2) -------------------------------------------------------

#: Voxels of padding (edge values) around a volume before its B-spline prefilter
#: (:func:`cubic_coefficients`): the interpolant's taps reach two voxels beyond a point, and
#: the prefilter's boundary extension fades within a few.
CUBIC_PAD = 3


def cubic_coefficients(volume) -> np.ndarray:
    """Cubic B-spline coefficients of ``volume`` ``(I, J, K)`` for :func:`cubic_clamped`.

    The volume is padded by :data:`CUBIC_PAD` voxels of its edge values, then prefiltered
    (``scipy.ndimage.spline_filter(order=3, mode="mirror")``), so that the interpolant passes
    through every voxel value: the coefficients of SciPy's
    ``map_coordinates(np.pad(volume, CUBIC_PAD, "edge"), coords + CUBIC_PAD, order=3,
    mode="mirror")`` (host code, float64; shape ``(I + 6, J + 6, K + 6)``).
    """
    import scipy.ndimage as ndi

    v = np.pad(np.asarray(volume, np.float64), CUBIC_PAD, mode="edge")
    return ndi.spline_filter(v, order=3, mode="mirror")


def _bspline_weights(t):
    """Uniform cubic B-spline weights ``(..., 4)`` at offsets ``t`` in ``[0, 1]`` and their
    first derivatives (taps at ``floor - 1 .. floor + 2``)."""
    s = 1.0 - t
    t2, t3 = t * t, t * t * t
    w = jnp.stack([s * s * s, 3.0 * t3 - 6.0 * t2 + 4.0, -3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0, t3],
                  axis=-1) / 6.0
    dw = jnp.stack([-3.0 * s * s, 9.0 * t2 - 12.0 * t, -9.0 * t2 + 6.0 * t + 3.0, 3.0 * t2],
                   axis=-1) / 6.0
    return w, dw


_ROW_GATHER = jax.lax.GatherDimensionNumbers(offset_dims=(1,), collapsed_slice_dims=(),
                                             start_index_map=(0,))


def _cubic_block(coeffs, c):
    """Offsets ``t`` ``(..., 3)`` of the (clamped, padded-grid) coordinates ``c`` in their
    cells and the 4x4x4 coefficients around them ``(..., 4, 4, 4)``: sixteen gathers of four
    neighbours along the contiguous axis from the flattened array (several times faster on
    XLA:CPU than one gather of 4x4x4 blocks), their first flat index materialised as in
    :func:`_cell_block`."""
    c0 = jnp.floor(c)
    ci = c0.astype(jnp.int32) - 1
    _, nj, nk = coeffs.shape
    base = jax.lax.optimization_barrier((ci[..., 0] * nj + ci[..., 1]) * nk + ci[..., 2]).reshape(-1)
    offs = jnp.asarray([a * nj * nk + b * nk for a in range(4) for b in range(4)], jnp.int32)
    starts = (base[:, None] + offs).reshape(-1, 1)
    blk = jax.lax.gather(coeffs.reshape(-1), starts, _ROW_GATHER, (4,),
                         mode=jax.lax.GatherScatterMode.CLIP)
    return c - c0, blk.reshape(c.shape[:-1] + (4, 4, 4)).astype(c.dtype)


def _contract(wx, wy, wz, blk):
    """``sum_abc wx_a wy_b wz_c blk_abc`` by nested multiply-and-sum (no einsum over gathered
    values: slower on XLA:CPU)."""
    vz = jnp.sum(blk * wz[..., None, None, :], axis=-1)  # (..., 4, 4): x, y
    vy = jnp.sum(vz * wy[..., None, :], axis=-1)  # (..., 4): x
    return jnp.sum(vy * wx, axis=-1)


@jax.custom_jvp
def _cubic_cells(coeffs, c):
    t, blk = _cubic_block(coeffs, c)
    w, _ = _bspline_weights(t)
    return _contract(w[..., 0, :], w[..., 1, :], w[..., 2, :], blk)


def _cubic_cells_jvp(primals, tangents):
    from jax.custom_derivatives import SymbolicZero

    coeffs, c = primals
    d_coeffs, d_c = tangents
    t, blk = _cubic_block(coeffs, c)
    # the gathered blocks materialised once (fused, XLA:CPU repeats the gather per consumer)
    blk = jax.lax.optimization_barrier(blk)
    w, dw = _bspline_weights(t)
    wx, wy, wz = w[..., 0, :], w[..., 1, :], w[..., 2, :]
    # shared partial sums: z, then y, then x (value and the three derivatives)
    vz = jnp.sum(blk * wz[..., None, None, :], axis=-1)
    vz_z = jnp.sum(blk * dw[..., 2, None, None, :], axis=-1)
    vy = jnp.sum(vz * wy[..., None, :], axis=-1)
    vy_y = jnp.sum(vz * dw[..., 1, None, :], axis=-1)
    vy_z = jnp.sum(vz_z * wy[..., None, :], axis=-1)
    val = jnp.sum(vy * wx, axis=-1)
    out = jnp.zeros_like(val)
    if not isinstance(d_c, SymbolicZero):
        g = jnp.stack([jnp.sum(vy * dw[..., 0, :], axis=-1), jnp.sum(vy_y * wx, axis=-1),
                       jnp.sum(vy_z * wx, axis=-1)], axis=-1)
        out = out + jnp.sum(g * d_c, axis=-1)
    if not isinstance(d_coeffs, SymbolicZero):
        out = out + _cubic_cells(d_coeffs, c)  # linear in the coefficients
    return val, out


_cubic_cells.defjvp(_cubic_cells_jvp, symbolic_zeros=True)


def cubic_clamped(coeffs, coords):
    """Cubic B-spline interpolation at voxel coordinates clamped to the grid (JAX, C2).

    The smooth counterpart of :func:`trilinear_clamped` for gradient samplers: its value,
    first and second derivatives are continuous (the trilinear interpolant's gradient jumps
    at every voxel face).  ``coeffs`` are :func:`cubic_coefficients` of the volume, so the
    interpolant passes through the voxel values; a point outside the grid takes the value
    at its nearest point of the grid (coordinates clamped to ``[0, shape - 1]``).

    Parameters
    ----------
    coeffs : (I + 6, J + 6, K + 6) array
        :func:`cubic_coefficients` of a volume ``(I, J, K)``.
    coords : (..., 3) array
        Continuous voxel coordinates of the volume (voxel centres at integers).

    Returns
    -------
    (...,) array
        Differentiable in ``coeffs`` and ``coords`` (hand-written JVP: the spline's gradient
        from the same 64 gathered coefficients; zero across a clamped coordinate).

    Raises
    ------
    ValueError
        ``coeffs`` not 3-D with at least 7 entries per axis, or ``coords`` not ``(..., 3)``.

    Examples
    --------
    >>> import numpy as np, jax.numpy as jnp, scipy.ndimage as ndi
    >>> v = np.random.default_rng(0).random((8, 9, 10))
    >>> x = np.array([[3.3, 4.1, 5.7]])
    >>> ref = ndi.map_coordinates(np.pad(v, CUBIC_PAD, "edge"), (x + CUBIC_PAD).T, order=3, mode="mirror")
    >>> bool(np.isclose(float(cubic_clamped(jnp.asarray(cubic_coefficients(v)), jnp.asarray(x))[0]), ref[0]))
    True
    """
    if coeffs.ndim != 3 or min(coeffs.shape) < 2 * CUBIC_PAD + 1:
        raise ValueError(f"coeffs must be 3-D with at least {2 * CUBIC_PAD + 1} entries per axis "
                         f"(cubic_coefficients of a volume), got shape {coeffs.shape}")
    if coords.shape[-1:] != (3,):
        raise ValueError(f"coords must have shape (..., 3), got {coords.shape}")
    hi = jnp.asarray(coeffs.shape, coords.dtype) - 2 * CUBIC_PAD - 1.0
    return _cubic_cells(coeffs, jnp.clip(coords, 0.0, hi) + CUBIC_PAD)
