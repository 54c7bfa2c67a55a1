"""ANTs SyN through ANTsPy: the registration users of the field already run, as a reference.

A synthetic run reports a dense registration of ``f`` to ``m`` beside its posterior mean,
the point estimate to beat (``output.reference``); :func:`syn_displacement` is ANTs'
symmetric normalisation (Avants et al. 2008), read back as a displacement field in the
package's convention (``m(x + u(x)) ~= f(x)``, world RAS mm).  ANTsPy (``antspyx``) is an
optional dependency: imported when called, with a clear error where it is missing.
"""

from __future__ import annotations

import numpy as np

from bayesreg.data.images import Image
from bayesreg.data.registration import field_on_grid, prepare_pair
from bayesreg.interop.transforms import load_displacement

__all__ = ["SYN_DEFAULTS", "syn_displacement"]


#: ANTs SyN as :func:`syn_displacement` runs it by default: the deformable stage of ANTs'
#: ``antsRegistrationSyNQuick.sh`` alone (ANTsPy's ``"SyNOnly"``: the images of a run
#: already share a world frame), ``SyN[0.1,3,0]`` with Mattes mutual information (32 bins,
#: every voxel) over four levels of 100, 70, 50 and 20 iterations (shrink factors 8, 4, 2,
#: 1; smoothing 3, 2, 1, 0 voxels), the finest level which the quick script skips kept.
#: Cross-correlation of radius 4 (``syn_metric="CC", syn_sampling=4``, the full script's)
#: cost 10x as much on a 48^3 test image and was not more accurate there.
SYN_DEFAULTS = {"type_of_transform": "SyNOnly", "syn_metric": "mattes", "syn_sampling": 32,
                "reg_iterations": (100, 70, 50, 20), "grad_step": 0.1}


def syn_displacement(f: Image, m: Image, *, mask=None, margin: int | None = 16,
                     **kwargs) -> Image:
    """Dense displacement from ``f`` to ``m`` by ANTs SyN (ANTsPy's ``ants.registration``).

    Parameters
    ----------
    f : Image
        Pre-operative (fixed) image, ``data`` of shape ``(I, J, K)``.
    m : Image
        Intra-operative (moving) image on the same grid as ``f``.
    mask : (I, J, K) bool array_like, optional
        Where the field is kept; it is set to 0 elsewhere (e.g. outside the brain).
    margin : int or None
        With a ``mask``, register the mask's bounding box grown by this many voxels
        (clipped to the grid) rather than the whole grid; ``None``: the whole grid.
    **kwargs
        Passed to ``ants.registration`` over :data:`SYN_DEFAULTS` (e.g.
        ``type_of_transform="SyN"`` for an affine stage first, ``reg_iterations``,
        ``syn_sampling``).

    Returns
    -------
    Image
        ``data`` of shape ``(I, J, K, 3)`` (float64): ``u`` in world RAS mm at each voxel
        centre, ``m(x + u(x)) ~= f(x)``: all of ANTs' forward transforms (rigid, affine and
        warp) composed into one displacement field by ``antsApplyTransforms``; ``affine``
        is ``f``'s.

    Raises
    ------
    ImportError
        ANTsPy is not installed (``pip install 'bayesreg[ants]'``, or ``antspyx``; wheels for
        Linux x86_64 and macOS).
    ValueError
        As :func:`bayesreg.data.registration.optical_flow_displacement` (grids, mask,
        margin).
    RuntimeError
        ANTs failed (its message attached).

    Notes
    -----
    ANTs registers ``moving = m`` to ``fixed = f``: its forward transforms map a point of
    ``f``'s space to ``m``'s, ``T(x) = x + u(x)``, which is the package's ``u``; ANTs writes it
    in LPS, :func:`bayesreg.interop.transforms.load_displacement` reads it back in RAS.  ANTs
    runs its own threads on every core; a stage with a sampled metric (ANTsPy's affine
    stages) varies between calls.  Reference: Avants, Epstein, Grossman, Gee 2008,
    *Symmetric diffeomorphic image registration with cross-correlation*, Med. Image Anal.
    12(1).
    """
    import tempfile
    from pathlib import Path

    import nibabel as nib

    try:
        import ants
    except ImportError as exc:
        raise ImportError("the SyN reference needs ANTsPy: pip install 'bayesreg[ants]' (or "
                          "antspyx; wheels for Linux x86_64 and macOS), or output.reference: "
                          "tvl1 | none") from exc
    f, m, mask, box = prepare_pair(f, m, mask, margin)
    start = np.array([b.start or 0 for b in box], float)
    affine = f.affine.copy()
    affine[:3, 3] = f.affine[:3, :3] @ start + f.affine[:3, 3]
    options = {**SYN_DEFAULTS, **kwargs}
    with tempfile.TemporaryDirectory(prefix="bayesreg-syn-") as tmp:
        tmp = Path(tmp)
        for name, img in (("f", f), ("m", m)):
            nib.save(nib.Nifti1Image(np.asarray(img.data, np.float32)[box], affine),
                     tmp / f"{name}.nii.gz")
        fixed, moving = (ants.image_read(str(tmp / f"{n}.nii.gz")) for n in ("f", "m"))
        try:
            reg = ants.registration(fixed, moving, outprefix=str(tmp / "syn_"), **options)
            field = ants.apply_transforms(fixed, moving, reg["fwdtransforms"],
                                          compose=str(tmp / "total_"))
        except Exception as exc:  # ANTs raises bare RuntimeErrors and ValueErrors
            raise RuntimeError(f"ANTs SyN failed: {type(exc).__name__}: {exc}") from exc
        if field is None:
            raise RuntimeError("ANTs SyN failed: antsApplyTransforms wrote no composite field")
        v = load_displacement(field)
    if v.data.shape[:3] != f.data[box].shape or not np.allclose(v.affine, affine, atol=1e-4):
        raise RuntimeError(f"ANTs SyN failed: its field's grid {v.data.shape[:3]} is not the "
                           f"registered box's {f.data[box].shape}")
    return field_on_grid(v.data, f, box, mask)
