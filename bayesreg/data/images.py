"""Images with their affine: NIfTI loading and saving, world frames, resampling.

An :class:`Image` is a 3D array plus the 4x4 voxel-to-world affine (NIfTI convention:
``world_mm = affine @ [i, j, k, 1]``).  Every geometric quantity in bayesreg is in world mm;
voxel indices appear only inside interpolation.
"""

from __future__ import annotations

import os
import uuid
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np
import scipy.ndimage as ndi

from bayesreg._checks import check_affine, check_number, count_nonfinite
from bayesreg._files import replace_durably

__all__ = [
    "Image",
    "load_nifti",
    "save_nifti",
    "write_nifti_atomic",
    "nifti_frame",
    "check_same_frame",
    "to_reference_grid",
    "resample",
    "resample_to_spacing",
    "check_same_space",
    "pad",
    "world_to_voxel",
    "interpolate_numpy",
    "grid_points",
    "grid_box",
    "check_image",
]


class Image(NamedTuple):
    """A 3D image and its voxel-to-world affine.

    Attributes
    ----------
    data : (I, J, K) ndarray
    affine : (4, 4) ndarray
        Maps voxel indices ``(i, j, k, 1)`` to world coordinates in mm.
    """

    data: np.ndarray
    affine: np.ndarray

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size along each array axis, mm, shape ``(3,)``."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)


def check_image(img: Image, name: str = "image", *, finite: bool = False) -> Image:
    """``img`` with array data and a float64 affine; ``ValueError`` unless it is an
    :class:`Image` with 3D data and a finite invertible affine (and, with ``finite``,
    finite voxel values)."""
    if not (hasattr(img, "data") and hasattr(img, "affine")):
        raise ValueError(f"{name} must be an Image(data, affine), got {type(img).__name__}")
    data = np.asarray(img.data)
    if data.ndim != 3:
        raise ValueError(f"{name} must be 3D, got shape {data.shape}")
    affine = check_affine(img.affine, name)
    if finite:
        bad = count_nonfinite(data)
        if bad:
            raise ValueError(f"{name} must have finite voxel values, got {bad} NaN or infinite")
    return Image(data, affine)


#: Tolerances of :func:`load_nifti`'s qform/sform agreement check.
QFORM_SFORM_ATOL_MM = 1e-3
QFORM_SFORM_ATOL_LINEAR = 1e-4


def load_nifti(path) -> Image:
    """Load a 3D NIfTI image (``.nii`` / ``.nii.gz``) with nibabel.

    The affine is nibabel's best affine (the sform when its code is > 0, else the qform).
    When the header carries both a qform and an sform with codes > 0 they must describe the
    same voxel-to-world map, otherwise it is ambiguous which one the user meant.  The frame
    the affine refers to (scanner, aligned, MNI, ...) is not stored on the returned
    :class:`Image`; read it with :func:`nifti_frame`.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    Image
        ``data`` of shape ``(I, J, K)`` and the ``(4, 4)`` voxel-to-world affine (mm).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If ``path`` is not a NIfTI file, its data cannot be read (a truncated or corrupted
        file, named), the image is not 3D (a trailing singleton 4th axis
        is dropped), or its qform
        and sform (both with codes > 0) disagree by more than ``1e-3`` mm in translation or
        ``1e-4`` in the linear part.
    """
    import nibabel as nib

    from nibabel.filebasedimages import ImageFileError

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"image not found: {path}")
    if path.is_dir():
        raise ValueError(f"{path} is a directory, not a NIfTI image")
    try:
        nii = nib.load(str(path))
    except ImageFileError as exc:
        raise ValueError(f"{path} is not an image nibabel can read ({exc})") from None
    if not isinstance(nii, nib.Nifti1Pair):  # NIfTI-1 and -2, single file or pair
        raise ValueError(f"{path} is a {type(nii).__name__}, not a NIfTI image")
    _check_qform_sform(nii, path)
    try:
        data = np.asanyarray(nii.dataobj)
    except (EOFError, OSError, zlib.error, ValueError) as exc:  # gzip's errors are OSErrors
        raise ValueError(f"{path}: the image data cannot be read ({type(exc).__name__}: {exc}): "
                         "the file is truncated or damaged") from None
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    return check_image(Image(np.asarray(data), nii.affine), str(path))


def _check_qform_sform(nii, path) -> None:
    header = nii.header
    if not hasattr(header, "get_qform") or not hasattr(header, "get_sform"):
        return  # not a NIfTI header (Analyze, MGH, ...): a single affine
    q, q_code = header.get_qform(coded=True)
    s, s_code = header.get_sform(coded=True)
    if q is None or s is None or int(q_code) <= 0 or int(s_code) <= 0:
        return
    d_lin = float(np.max(np.abs(q[:3, :3] - s[:3, :3])))
    d_trans = float(np.max(np.abs(q[:3, 3] - s[:3, 3])))
    if d_lin > QFORM_SFORM_ATOL_LINEAR or d_trans > QFORM_SFORM_ATOL_MM:
        raise ValueError(
            f"{path}: qform and sform disagree (linear part by up to {d_lin:.3g}, translation "
            f"by up to {d_trans:.3g} mm; tolerances {QFORM_SFORM_ATOL_LINEAR:g} and "
            f"{QFORM_SFORM_ATOL_MM:g} mm), so the voxel-to-world map is ambiguous.\n"
            f"  qform (code {_frame_name(q_code)}): {_fmt_affine(q)}\n"
            f"  sform (code {_frame_name(s_code)}): {_fmt_affine(s)}\n"
            "Fix the header, e.g. set the wrong one's code to 0 (nibabel: "
            "img.set_qform(None, code=0)) or copy one onto the other (FSL: fslorient "
            "-copysform2qform)."
        )


def _frame_name(code) -> str:
    import nibabel as nib

    try:
        return str(nib.nifti1.xform_codes.label[int(code)])
    except KeyError:
        return f"code {int(code)}"


def _fmt_affine(a) -> str:
    return str(np.round(np.asarray(a, dtype=np.float64), 3).tolist())


def nifti_frame(path) -> str:
    """Name of the world frame a NIfTI file's affine refers to.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    str
        nibabel's xform code label of the affine :func:`load_nifti` uses: the sform code
        when > 0, else the qform code: ``"unknown"`` (0, or not a NIfTI file),
        ``"scanner"`` (1), ``"aligned"`` (2), ``"talairach"`` (3), ``"mni"`` (4),
        ``"template"`` (5).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    """
    import nibabel as nib

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"image not found: {path}")
    header = nib.load(str(path)).header
    if not hasattr(header, "get_qform") or not hasattr(header, "get_sform"):
        return "unknown"
    s_code = int(header["sform_code"])
    q_code = int(header["qform_code"])
    return _frame_name(s_code if s_code > 0 else q_code)


#: Frames treated as one by :func:`check_same_frame` unless ``strict``: nibabel (and so
#: :func:`save_nifti`) and SPM write "aligned" for images derived from a scanner image.
_SUBJECT_FRAMES = frozenset({"scanner", "aligned"})


def check_same_frame(*paths, names=None, strict: bool = False) -> None:
    """Raise ``ValueError`` if NIfTI files' xform codes name different world frames.

    Parameters
    ----------
    *paths : str, path-like or None
        Files to compare; ``None`` entries (an optional input not given) are skipped.
    names : sequence of str, optional
        Names used in the message (default: the paths), one per entry of ``paths``.
    strict : bool
        If False (default), ``"scanner"`` and ``"aligned"`` count as one frame (a subject's
        own space: nibabel and SPM label derived images "aligned").  Files whose frame is
        ``"unknown"`` are never in conflict.

    Raises
    ------
    ValueError
        If two files have known frames (code > 0) that differ, e.g. ``"scanner"`` and
        ``"mni"``; or if ``names`` does not match ``paths`` in length.
    FileNotFoundError
        If a path does not exist.
    """
    if names is None:
        names = [str(p) for p in paths]
    names = list(names)
    if len(names) != len(paths):
        raise ValueError(f"check_same_frame: {len(paths)} paths but {len(names)} names")
    known = []
    for p, n in zip(paths, names):
        if p is None:
            continue
        frame = nifti_frame(p)
        if frame != "unknown":
            known.append((n, frame))

    def key(frame):
        return "subject" if not strict and frame in _SUBJECT_FRAMES else frame

    if len({key(f) for _, f in known}) > 1:
        listing = ", ".join(f"{n}: {f}" for n, f in known)
        raise ValueError(
            f"the inputs' NIfTI headers name different world frames ({listing}): their "
            "world coordinates are not comparable. Bring them into one space first "
            "(e.g. register the label map to the fixed image) and save them with that "
            "space's code."
        )


def save_nifti(img: Image, path) -> None:
    """Write ``img`` as NIfTI atomically (temporary file in the same folder, then rename)."""
    import nibabel as nib

    write_nifti_atomic(nib.Nifti1Image(np.asarray(img.data), np.asarray(img.affine)), path)


def write_nifti_atomic(nii, path) -> None:
    """Write the nibabel image ``nii`` to ``path`` atomically: a temporary file in the same
    folder, flushed, then renamed (a reader never sees half a file)."""
    import nibabel as nib

    path = Path(path)
    suffix = ".nii.gz" if path.name.endswith(".nii.gz") else path.suffix
    # a unique name that nibabel creates, so the file gets the umask's mode as every other
    # output does (tempfile.mkstemp's 0600 made the maps unreadable to a shared group)
    tmp = str(path.with_name(f".{path.name[:-len(suffix)] if suffix else path.name}-"
                             f"{uuid.uuid4().hex[:12]}.tmp{suffix}"))
    try:
        nib.save(nii, tmp)
        replace_durably(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def check_same_space(a: Image, b: Image, *, names=("f", "m"), atol_mm=1e-3) -> None:
    """Raise ``ValueError`` unless ``a`` and ``b`` share grid shape and affine (within ``atol_mm``)."""
    if a.data.shape != b.data.shape:
        raise ValueError(
            f"{names[0]} and {names[1]} have different grids: {a.data.shape} vs {b.data.shape}"
        )
    if not np.allclose(a.affine, b.affine, atol=atol_mm):
        raise ValueError(
            f"{names[0]} and {names[1]} affines disagree by up to "
            f"{np.max(np.abs(a.affine - b.affine)):.3g} mm (tolerance {atol_mm} mm)"
        )


def resample(img: Image, affine, shape, *, order=1, cval=0.0, mode="constant") -> Image:
    """Resample ``img`` onto the grid ``(affine, shape)`` sharing its world frame (SciPy).

    Parameters
    ----------
    img : Image
    affine : (4, 4) array_like
        Target voxel-to-world affine.
    shape : tuple of 3 int
        Target grid shape.
    order : int
        Spline order (0 for label maps, 1 for intensities/probabilities).
    cval : float
        Value outside the source grid.
    mode : str
        :func:`scipy.ndimage.affine_transform` boundary mode: ``"constant"`` gives ``cval``
        beyond the outermost voxel centres; ``"grid-constant"`` treats each voxel as
        covering its extent (with ``order=0``, nearest neighbour up to half a voxel
        outside the centres).  A target centre within ``EDGE_TOLERANCE`` voxels outside
        the source's outermost centres (rounding in the composed affines: an oblique grid's
        own centres land ``1e-16`` outside) takes the value at the nearest point of the
        source grid, not ``cval``.

    Raises
    ------
    ValueError
        If ``img`` is not a 3D image with a finite invertible affine, ``affine`` is not a
        finite invertible ``(4, 4)`` matrix, or ``shape`` is not 3 positive integers.
    """
    img = check_image(img)
    affine = check_affine(affine, "target")
    shape = _grid_shape(shape)
    src_from_tgt = np.linalg.solve(img.affine, affine)
    source = np.asarray(img.data, dtype=np.float64 if order else img.data.dtype)
    data = ndi.affine_transform(source, src_from_tgt[:3, :3], offset=src_from_tgt[:3, 3],
                                output_shape=shape, order=order, mode=mode, cval=cval)
    if mode == "constant":
        index, coords = _edge_rounded(src_from_tgt, shape, source.shape)
        if len(index):
            data[tuple(index.T)] = ndi.map_coordinates(source, coords.T, order=order,
                                                       mode=mode, cval=cval)
    return Image(data, affine)


#: Voxels (source grid) by which a target centre may fall outside the source's outermost
#: centres and still read the source at its nearest point (:func:`resample`).
EDGE_TOLERANCE = 1e-6


def _edge_rounded(src_from_tgt, shape, source_shape):
    """The target voxels ``(n, 3)`` int whose source coordinates lie outside
    ``[0, n - 1]`` on some axis by at most :data:`EDGE_TOLERANCE` (and inside it, so
    widened, on every axis), with those coordinates clamped onto the grid ``(n, 3)``.
    One target slab at a time: memory of one slab's coordinates."""
    m, off = src_from_tgt[:3, :3], src_from_tgt[:3, 3]
    upper = np.asarray(source_shape, float) - 1.0
    corners = np.stack(np.meshgrid(*[(0, n - 1) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    lo, hi = (f(corners @ m.T + off, axis=0) for f in (np.min, np.max))  # affine: the extremes
    below = (lo < 0.0) & (hi >= -EDGE_TOLERANCE)
    above = (hi > upper) & (lo <= upper + EDGE_TOLERANCE)
    if not np.any(below | above):
        return np.zeros((0, 3), int), np.zeros((0, 3))  # no centre in either band
    jk = np.stack(np.meshgrid(np.arange(shape[1]), np.arange(shape[2]), indexing="ij"), -1)
    plane = jk.reshape(-1, 2) @ m[:, 1:].T + off  # (J K, 3) source coordinates at i = 0
    index, coords = [], []
    for i in range(shape[0]):
        c = plane + i * m[:, 0]
        near = np.all((c >= -EDGE_TOLERANCE) & (c <= upper + EDGE_TOLERANCE), axis=1)
        fix = near & np.any((c < 0.0) | (c > upper), axis=1)
        if fix.any():
            index.append(np.column_stack([np.full(fix.sum(), i), jk.reshape(-1, 2)[fix]]))
            coords.append(np.clip(c[fix], 0.0, upper))
    if not index:
        return np.zeros((0, 3), int), np.zeros((0, 3))
    return np.concatenate(index), np.concatenate(coords)


def _grid_shape(shape) -> tuple:
    """``shape`` as a tuple of 3 ints; ``ValueError`` unless 3 positive integers."""
    arr = np.asarray(shape)
    if (arr.shape != (3,) or arr.dtype.kind not in "iuf" or not np.all(np.isfinite(arr))
            or np.any(arr != np.round(arr)) or np.any(arr < 1)):
        raise ValueError(f"shape must be 3 positive integers, got {shape!r}")
    return tuple(int(n) for n in arr)


def grid_box(affine, shape) -> np.ndarray:
    """World axis-aligned bounding box ``(2, 3)`` (min, max rows) of a grid's voxel extent."""
    corners = np.array(np.meshgrid(*[(-0.5, n - 0.5) for n in shape], indexing="ij"))
    corners = corners.reshape(3, -1).T
    world = corners @ np.asarray(affine)[:3, :3].T + np.asarray(affine)[:3, 3]
    return np.stack([world.min(axis=0), world.max(axis=0)])


def to_reference_grid(
    img: Image,
    reference: Image,
    *,
    name: str,
    reference_name: str,
    order: int,
    atol_mm: float = 1e-3,
    min_overlap: float = 0.5,
    cval: float = 0.0,
) -> Image:
    """Put ``img`` on ``reference``'s voxel grid (both must share the world frame).

    Parameters
    ----------
    img : Image
        ``data`` of shape ``(I', J', K')`` or a vector image ``(I', J', K', C)`` (each
        component is resampled separately; world-mm vector components are unchanged by a
        change of grid in the same world frame).
    reference : Image
        Target grid: ``reference.data.shape[:3]`` and ``reference.affine``; its data are
        not used.
    name, reference_name : str
        Names of the two inputs in error messages (e.g. ``"data.labels"``,
        ``"data.fixed"``).
    order : int
        Spline order: 0 (nearest neighbour) for label maps, 1 (trilinear) for intensities.
    atol_mm : float
        Affines equal within this tolerance (as :func:`check_same_space`) and equal shapes
        mean "already on the grid".
    min_overlap : float
        Smallest accepted fraction of the reference grid's world bounding box that
        ``img``'s world bounding box covers.
    cval : float
        Value of reference voxels outside ``img``'s grid: with ``order=0`` a voxel of
        ``img`` covers its extent (centre +- half a voxel); with ``order > 0`` values are
        interpolated between voxel centres only and ``cval`` is used beyond them.

    Returns
    -------
    Image
        ``img`` itself (the same object, data untouched) when it is already on the
        reference grid; else a new image with ``data`` of shape ``reference.shape[:3]``
        (``+ (C,)`` for vector images; float64 for ``order > 0``, ``img``'s dtype for
        ``order == 0``) and ``reference``'s affine.

    Raises
    ------
    ValueError
        If ``img`` is not 3D/4D, an affine is not a finite invertible ``(4, 4)`` matrix,
        or the world bounding boxes overlap less than ``min_overlap`` of the reference's
        volume: the two images then do not appear to share a world frame.
    """
    data = np.asarray(img.data)
    if data.ndim not in (3, 4):
        raise ValueError(f"{name} must be 3D or a 4D vector image, got shape {data.shape}")
    ref_shape = tuple(int(n) for n in np.shape(reference.data)[:3])
    ref = check_image(Image(np.empty(ref_shape, dtype=np.uint8), reference.affine), reference_name)
    src = check_image(Image(data[..., 0] if data.ndim == 4 else data, img.affine), name)
    if data.shape[:3] == ref_shape and np.allclose(src.affine, ref.affine, atol=atol_mm):
        return img
    box_src = grid_box(src.affine, data.shape[:3])
    box_ref = grid_box(ref.affine, ref_shape)
    inter = np.minimum(box_src[1], box_ref[1]) - np.maximum(box_src[0], box_ref[0])
    inter = np.clip(inter, 0.0, None)
    fraction = float(np.prod(inter) / np.prod(box_ref[1] - box_ref[0]))
    if fraction < min_overlap:
        raise ValueError(
            f"{name} and {reference_name} do not appear to share a world frame: {name}'s "
            f"world bounding box covers {100 * fraction:.1f}% of {reference_name}'s "
            f"(minimum {100 * min_overlap:.0f}%).\n"
            f"  {name}: affine {_fmt_affine(src.affine)}, shape {data.shape[:3]}, "
            f"box {_fmt_affine(box_src)} mm\n"
            f"  {reference_name}: affine {_fmt_affine(ref.affine)}, shape {ref_shape}, "
            f"box {_fmt_affine(box_ref)} mm\n"
            "Check that both files are in the same space (same subject, same scanner "
            "session or registered) and that their qform/sform are right."
        )
    mode = "grid-constant" if order == 0 else "constant"
    if data.ndim == 3:
        return resample(src, ref.affine, ref_shape, order=order, cval=cval, mode=mode)
    comps = [
        resample(Image(data[..., c], src.affine), ref.affine, ref_shape, order=order, cval=cval,
                 mode=mode).data
        for c in range(data.shape[3])
    ]
    return Image(np.stack(comps, axis=-1), ref.affine)


def resample_to_spacing(img: Image, spacing_mm: float, *, order=1) -> Image:
    """Resample to isotropic voxels of ``spacing_mm`` covering the same field of view.

    For downsampling with ``order > 0`` the image is first smoothed with a Gaussian of
    ``sigma = (factor - 1) / 2`` source voxels (anti-aliasing, as scikit-image's
    ``rescale``).

    Raises
    ------
    ValueError
        If ``spacing_mm`` is not a finite number > 0, or ``img`` is not a 3D image with a
        finite invertible affine.
    """
    spacing = check_number(spacing_mm, "spacing_mm")
    img = check_image(img)
    factor = spacing / img.spacing
    if np.allclose(factor, 1.0):
        return img
    data = np.asarray(img.data)
    if order > 0 and np.any(factor > 1):
        data = ndi.gaussian_filter(data.astype(np.float64), np.maximum((factor - 1) / 2, 0))
    shape = np.maximum(np.floor((np.array(data.shape) - 1) / factor).astype(int) + 1, 1)
    affine = img.affine.copy()
    affine[:3, :3] = img.affine[:3, :3] * factor
    return resample(Image(data, img.affine), affine, shape, order=order)


def pad(img: Image, margin_mm: float, *, value=0) -> Image:
    """Pad ``img`` on every side by ``ceil(margin_mm / spacing)`` voxels of ``value``.

    The affine is shifted so that world coordinates are unchanged.

    Raises
    ------
    ValueError
        If ``margin_mm`` is not a finite number >= 0, or ``img`` is not a 3D image with a
        finite invertible affine.
    """
    margin = check_number(margin_mm, "margin_mm", positive=False)
    img = check_image(img)
    n = np.ceil(margin / img.spacing).astype(int)
    data = np.pad(np.asarray(img.data), [(k, k) for k in n], constant_values=value)
    affine = img.affine.copy()
    affine[:3, 3] = img.affine[:3, :3] @ (-n) + img.affine[:3, 3]
    return Image(data, affine)


def world_to_voxel(affine, points):
    """World mm ``(..., 3)`` to continuous voxel indices ``(..., 3)``."""
    inv = np.linalg.inv(np.asarray(affine, dtype=np.float64))
    return np.asarray(points) @ inv[:3, :3].T + inv[:3, 3]


def interpolate_numpy(img: Image, points, *, order=1, cval=0.0):
    """NumPy/SciPy interpolation of ``img`` at world ``points`` (``(..., 3)`` mm)."""
    c = world_to_voxel(img.affine, points)
    flat = c.reshape(-1, 3).T
    vals = ndi.map_coordinates(
        np.asarray(img.data, dtype=np.float64), flat, order=order, mode="constant", cval=cval
    )
    return vals.reshape(c.shape[:-1])


def grid_points(img: Image) -> np.ndarray:
    """World coordinates ``(I*J*K, 3)`` mm of every voxel centre of ``img``, C order."""
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in img.data.shape[:3]], indexing="ij"), -1)
    return ijk.reshape(-1, 3) @ img.affine[:3, :3].T + img.affine[:3, 3]
