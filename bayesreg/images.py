"""Images with their affine: loading, saving, resampling, interpolation.

An :class:`Image` is a 3D array plus the 4x4 voxel-to-world affine (NIfTI convention:
``world_mm = affine @ [i, j, k, 1]``).  Every geometric quantity in bayesreg is in world mm;
voxel indices appear only inside interpolation.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import NamedTuple

import numpy as np
import scipy.ndimage as ndi

from bayesreg import _xla

_xla.configure()
import jax.numpy as jnp  # noqa: E402

__all__ = [
    "Image",
    "load_nifti",
    "save_nifti",
    "resample",
    "resample_to_spacing",
    "check_same_space",
    "pad",
    "world_to_voxel",
    "interpolate",
    "interpolate_numpy",
    "mni152",
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


def _check_image(img: Image, name: str = "image") -> Image:
    data = np.asarray(img.data)
    affine = np.asarray(img.affine, dtype=np.float64)
    if data.ndim != 3:
        raise ValueError(f"{name} must be 3D, got shape {data.shape}")
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)):
        raise ValueError(f"{name} affine must be a finite (4, 4) matrix, got {affine.shape}")
    if abs(np.linalg.det(affine[:3, :3])) < 1e-9:
        raise ValueError(f"{name} affine is singular")
    return Image(data, affine)


def load_nifti(path) -> Image:
    """Load a 3D NIfTI image (``.nii`` / ``.nii.gz``) with nibabel.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If the image is not 3D (a trailing singleton 4th axis is dropped).
    """
    import nibabel as nib

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"image not found: {path}")
    nii = nib.load(str(path))
    data = np.asanyarray(nii.dataobj)
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    return _check_image(Image(np.asarray(data), nii.affine), str(path))


def save_nifti(img: Image, path) -> None:
    """Write ``img`` as NIfTI atomically (temporary file in the same folder, then rename)."""
    import nibabel as nib

    path = Path(path)
    suffix = ".nii.gz" if path.name.endswith(".nii.gz") else path.suffix
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=suffix)
    os.close(fd)
    try:
        nib.save(nib.Nifti1Image(np.asarray(img.data), np.asarray(img.affine)), tmp)
        os.replace(tmp, path)
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


def resample(img: Image, affine, shape, *, order=1, cval=0.0) -> Image:
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
    """
    img = _check_image(img)
    affine = np.asarray(affine, dtype=np.float64)
    src_from_tgt = np.linalg.solve(img.affine, affine)
    data = ndi.affine_transform(
        np.asarray(img.data, dtype=np.float64 if order else img.data.dtype),
        src_from_tgt[:3, :3],
        offset=src_from_tgt[:3, 3],
        output_shape=tuple(int(s) for s in shape),
        order=order,
        mode="constant",
        cval=cval,
    )
    return Image(data, affine)


def resample_to_spacing(img: Image, spacing_mm: float, *, order=1) -> Image:
    """Resample to isotropic voxels of ``spacing_mm`` covering the same field of view.

    For downsampling with ``order > 0`` the image is first smoothed with a Gaussian of
    ``sigma = (factor - 1) / 2`` source voxels (anti-aliasing, as scikit-image's
    ``rescale``).
    """
    img = _check_image(img)
    factor = float(spacing_mm) / img.spacing
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
    """
    img = _check_image(img)
    n = np.ceil(float(margin_mm) / img.spacing).astype(int)
    data = np.pad(np.asarray(img.data), [(k, k) for k in n], constant_values=value)
    affine = img.affine.copy()
    affine[:3, 3] = img.affine[:3, :3] @ (-n) + img.affine[:3, 3]
    return Image(data, affine)


def world_to_voxel(affine, points):
    """World mm ``(..., 3)`` to continuous voxel indices ``(..., 3)``."""
    inv = np.linalg.inv(np.asarray(affine, dtype=np.float64))
    return np.asarray(points) @ inv[:3, :3].T + inv[:3, 3]


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
    """
    c = points @ inv_affine[:3, :3].T + inv_affine[:3, 3]
    shape = jnp.array(volume.shape)
    c0 = jnp.floor(c)
    t = c - c0
    c0 = c0.astype(jnp.int32)
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                idx = c0 + jnp.array([dx, dy, dz], dtype=jnp.int32)
                inside = jnp.all((idx >= 0) & (idx < shape), axis=-1)
                idc = jnp.clip(idx, 0, shape - 1)
                v = volume[idc[..., 0], idc[..., 1], idc[..., 2]]
                v = jnp.where(inside, v, cval)
                w = (
                    (t[..., 0] if dx else 1 - t[..., 0])
                    * (t[..., 1] if dy else 1 - t[..., 1])
                    * (t[..., 2] if dz else 1 - t[..., 2])
                )
                out = out + w * v
    return out


def interpolate_numpy(img: Image, points, *, order=1, cval=0.0):
    """NumPy/SciPy interpolation of ``img`` at world ``points`` (``(..., 3)`` mm)."""
    c = world_to_voxel(img.affine, points)
    flat = c.reshape(-1, 3).T
    vals = ndi.map_coordinates(
        np.asarray(img.data, dtype=np.float64), flat, order=order, mode="constant", cval=cval
    )
    return vals.reshape(c.shape[:-1])


def mni152(resolution_mm: float = 2.0, *, margin_mm: float = 20.0):
    """The MNI ICBM152 2009a brain shipped inside the nilearn wheel (no download).

    Parameters
    ----------
    resolution_mm : float
        Isotropic output spacing; the 1 mm template is resampled when different.
    margin_mm : float
        Zero padding on every side (:func:`pad`): the template's field of view cuts the
        brainstem, and the mesh and the free shell around it must lie inside the grid.

    Returns
    -------
    t1, gm, wm, mask : Image
        T1 intensities, grey/white-matter probability maps in [0, 1], brain mask (0/1),
        all on one grid.
    """
    from nilearn import datasets

    imgs = [
        datasets.load_mni152_template(resolution=1),
        datasets.load_mni152_gm_template(resolution=1),
        datasets.load_mni152_wm_template(resolution=1),
        datasets.load_mni152_brain_mask(resolution=1),
    ]
    out = [Image(np.asarray(i.get_fdata(), dtype=np.float64), np.asarray(i.affine)) for i in imgs]
    if not np.isclose(resolution_mm, 1.0):
        out = [resample_to_spacing(o, resolution_mm, order=1) for o in out]
        out[3] = Image((out[3].data > 0.5).astype(np.float64), out[3].affine)
    return tuple(pad(o, margin_mm) for o in out)
