"""Dense intensity registrations: a start for the sampler, and the references to beat.

The paper starts its chains between the identity and the truth; with real data there is no
truth, and a fast intensity registration of the pre-operative image ``f`` to the
intra-operative image ``m`` gives a data-driven start instead (scikit-image optical flow,
:func:`optical_flow_displacement`).  A synthetic run also reports such a registration beside
its posterior mean, the point estimate to beat: optical flow, or ANTs SyN
(:func:`bayesreg.interop.syn.syn_displacement`), the registration users already run.
Every displacement follows the package's convention: ``m(x + u(x)) ~= f(x)`` (the
intra-operative image is the pre-operative one moved by ``u``), with ``x`` and ``u`` in world
mm.
"""

from __future__ import annotations

import numpy as np

from bayesreg.data.images import Image, check_image, check_same_space, interpolate_numpy

__all__ = ["optical_flow_displacement", "displacement_at", "prepare_pair", "field_on_grid"]


def _normalise(f: np.ndarray, m: np.ndarray):
    """Map both volumes with one linear map taking ``f``'s 1st-99th percentiles to [0, 1].

    TV-L1's ``attachment`` weight assumes intensities of order one; one common map keeps
    the brightness constancy between ``f`` and ``m``.
    """
    lo, hi = np.percentile(f, [1.0, 99.0])
    if not hi > lo:
        lo, hi = float(f.min()), float(f.max())
    scale = 1.0 / (hi - lo) if hi > lo else 1.0
    return (f - lo) * scale, (m - lo) * scale


def _mask_box(mask, shape, margin: int | None) -> tuple:
    """The bounding box of ``mask`` ``(I, J, K)`` grown by ``margin`` voxels and clipped to
    the grid ``shape``, as three slices; the whole grid with no mask, an empty one, or
    ``margin`` None."""
    if mask is None or margin is None or not mask.any():
        return tuple(slice(None) for _ in range(3))
    idx = np.nonzero(mask)
    return tuple(slice(max(int(i.min()) - margin, 0), min(int(i.max()) + margin + 1, n))
                 for i, n in zip(idx, shape))


def prepare_pair(f: Image, m: Image, mask=None, margin: int | None = None):
    """What every registration of ``f`` to ``m`` here starts from: ``(f, m, mask, box)``, the
    images checked (valid, one grid), ``mask`` as a bool array of that grid's shape (or
    None), and ``box`` the three slices of the grid to register: the mask's bounding box
    grown by ``margin`` voxels and clipped to the grid, or the whole grid (no mask, an
    empty one, or ``margin`` None).  :func:`field_on_grid` puts the box's field back.

    Raises
    ------
    ValueError
        Naming what is wrong: the grids, the mask's shape, a negative ``margin``.
    """
    f = check_image(f, "f")
    m = check_image(m, "m")
    check_same_space(f, m, names=("f", "m"))
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != f.data.shape:
            raise ValueError(f"mask shape {mask.shape} differs from the image grid {f.data.shape}")
    if margin is not None and margin < 0:
        raise ValueError(f"margin must be >= 0 voxels or None, got {margin}")
    return f, m, mask, _mask_box(mask, f.data.shape, margin)


def field_on_grid(u_box, f: Image, box: tuple, mask=None) -> Image:
    """The displacement ``u_box`` ``(*box shape, 3)`` (world mm) registered on ``box`` of
    :func:`prepare_pair`, as a field on ``f``'s whole grid: 0 outside the box and, with a
    ``mask``, outside the mask."""
    u = np.zeros(f.data.shape + (3,))
    u[box] = u_box
    if mask is not None:
        u[~mask] = 0.0
    return Image(u, f.affine)


def optical_flow_displacement(f: Image, m: Image, *, method: str = "tvl1", mask=None,
                              margin: int | None = 16, **kwargs) -> Image:
    """Dense displacement from ``f`` to ``m`` by scikit-image optical flow.

    Parameters
    ----------
    f : Image
        Pre-operative (fixed) image, ``data`` of shape ``(I, J, K)``.
    m : Image
        Intra-operative (moving) image on the same grid as ``f``.
    method : {"tvl1", "ilk"}
        :func:`skimage.registration.optical_flow_tvl1` (TV-L1, coarse to fine) or
        :func:`skimage.registration.optical_flow_ilk` (iterative Lucas-Kanade).
    mask : (I, J, K) bool array_like, optional
        Where the field is kept; it is set to 0 elsewhere (e.g. outside the brain).
    margin : int or None
        With a ``mask``, the flow is computed on the mask's bounding box grown by this many
        voxels (clipped to the grid) rather than on the whole grid: the field is kept only
        inside the mask, and the images' far background costs time (on a 1 mm head image
        most of it) without informing it.  ``None``: the whole grid.
    **kwargs
        Passed to the scikit-image function (e.g. ``attachment``, ``tightness``,
        ``num_warp``, ``num_iter`` for TV-L1; ``radius``, ``num_warp`` for ILK).

    Returns
    -------
    Image
        ``data`` of shape ``(I, J, K, 3)`` (float64): the displacement ``u`` in world mm
        at each voxel centre, such that ``m(x + u(x)) ~= f(x)``; ``affine`` is ``f``'s.

    Raises
    ------
    ValueError
        If ``f`` and ``m`` are not on the same grid (:func:`check_same_space`), ``method``
        is unknown, or ``mask`` has the wrong shape.

    Notes
    -----
    Both volumes are mapped to roughly [0, 1] with one common linear map (``f``'s 1st and
    99th percentiles).  scikit-image's flow ``v`` (voxels) satisfies
    ``reference(x) ~= moving(x + v(x))``; with ``reference = f`` and ``moving = m`` this is
    the package's ``u`` in voxel units, converted to world mm by the affine's linear part
    ``u = A[:3, :3] @ v``.  The smoothness regularisation acts in voxel units: for strongly
    anisotropic voxels resample to isotropic spacing first.
    """
    from skimage.registration import optical_flow_ilk, optical_flow_tvl1

    solvers = {"tvl1": optical_flow_tvl1, "ilk": optical_flow_ilk}
    if method not in solvers:
        raise ValueError(f"unknown optical-flow method {method!r}: use one of {sorted(solvers)}")
    f, m, mask, box = prepare_pair(f, m, mask, margin)
    fa, ma = _normalise(np.asarray(f.data, np.float64), np.asarray(m.data, np.float64))
    kwargs.setdefault("dtype", np.float32)
    v = solvers[method](fa[box].astype(kwargs["dtype"]), ma[box].astype(kwargs["dtype"]), **kwargs)
    return field_on_grid(np.einsum("dc,c...->...d", f.affine[:3, :3], np.asarray(v, dtype=np.float64)),
                         f, box, mask)


def displacement_at(field: Image, points) -> np.ndarray:
    """Trilinear interpolation of a displacement field at world points.

    Parameters
    ----------
    field : Image
        ``data`` of shape ``(I, J, K, 3)``, world mm (e.g. from
        :func:`optical_flow_displacement`).
    points : (..., 3) array_like
        World coordinates, mm (e.g. mesh nodes).

    Returns
    -------
    (..., 3) ndarray
        Displacement in mm; 0 beyond the grid's outermost voxel centres.

    Raises
    ------
    ValueError
        If ``field.data`` is not ``(I, J, K, 3)`` or ``points`` does not end in 3.
    """
    data = np.asarray(field.data)
    if data.ndim != 4 or data.shape[3] != 3:
        raise ValueError(f"a displacement field must have shape (I, J, K, 3), got {data.shape}")
    points = np.asarray(points, dtype=np.float64)
    if points.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3), got {points.shape}")
    return np.stack(
        [interpolate_numpy(Image(data[..., c], field.affine), points, order=1) for c in range(3)],
        axis=-1,
    )
