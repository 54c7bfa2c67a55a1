"""Displacement fields as transforms: the files ITK, ANTs and 3D Slicer read, and the FE map
applied to points and inverted on a grid.

Direction
---------
bayesreg's displacement ``u`` is defined on the fixed (pre-operative) image ``f`` and sends
each fixed point ``x`` to ``x + u(x)`` in the moving (intra-operative) image ``m``, so that
``m(x + u(x)) = f(x)`` (paper Eq. 2).  This is ITK's *resampling* convention, "fixed to
moving": the field resamples ``m`` onto ``f``'s grid (``antsApplyTransforms -i m -r f -t
field``, ``sitk.Resample(m, f, DisplacementFieldTransform(field))``) and carries points of
``f`` (a planned target) to their positions in ``m``.  Its inverse, "moving to fixed",
resamples ``f`` and anything drawn on it (a tumour segmentation) onto ``m``'s grid.

Files
-----
``"itk"``
    5-D ``(I, J, K, 1, 3)`` float32 NIfTI, ``NIFTI_INTENT_VECTOR``, vectors in LPS mm, the
    form ITK, ANTs (``*Warp.nii.gz``) and 3D Slicer (as a grid transform) write and read;
    conversion by NiTransforms (:class:`nitransforms.io.itk.ITKDisplacementsField`).
``"nifti"``
    5-D, ``NIFTI_INTENT_DISPVECT``, vectors in RAS mm (nibabel's world frame, as bayesreg
    computes them); ITK converts such vectors to LPS when it reads them.

Every file records its direction in the NIfTI ``descrip`` field and its units (mm).
Outside the mesh (``u`` is defined inside the brain only) a field is zero: the identity.

Conventions: nodes ``(N, 3)`` and points ``(P, 3)`` world (RAS) mm; displacements ``(N, 3)``
mm; grids carry their voxel-to-world affine.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bayesreg.data.images import Image, write_nifti_atomic
from bayesreg.mesh.tetmesh import Mesh, signed_volumes
from bayesreg.mesh.warp import locate, locate_voxels

__all__ = ["CONVENTIONS", "field_image", "save_displacement", "load_displacement",
           "inverse_displacement", "locate_points", "displace_points", "FIXED_TO_MOVING",
           "MOVING_TO_FIXED"]


CONVENTIONS = ("itk", "nifti")

NIFTI_INTENT_VECTOR = 1007
NIFTI_INTENT_DISPVECT = 1006

FIXED_TO_MOVING = "bayesreg u fixed->moving: x_m = x_f + u(x_f); resamples m onto f"
MOVING_TO_FIXED = "bayesreg inverse moving->fixed: x_f = x_m + v(x_m); resamples f onto m"


def field_image(u, affine, *, convention: str = "itk", description: str = FIXED_TO_MOVING):
    """A displacement field as a nibabel image in the form of ``convention``.

    Parameters
    ----------
    u : (I, J, K, 3) array
        Displacement vectors in world RAS mm on the grid of ``affine``.
    affine : (4, 4) array
        Voxel-to-world (RAS) matrix of the grid.
    convention : {"itk", "nifti"}
        ``"itk"``: intent VECTOR, LPS vectors (NiTransforms' ITK writer); ``"nifti"``: intent
        DISPVECT, RAS vectors.
    description : str
        Stored in the header's ``descrip`` (at most 80 characters).

    Returns
    -------
    nibabel.Nifti1Image
        ``(I, J, K, 1, 3)`` float32, spatial units mm.

    Raises
    ------
    ValueError
        If ``u`` is not ``(I, J, K, 3)`` or ``convention`` is unknown.
    """
    import nibabel as nib

    u = np.asarray(u, np.float64)
    if u.ndim != 4 or u.shape[-1] != 3:
        raise ValueError(f"a displacement field is (I, J, K, 3), got shape {u.shape}")
    affine = np.asarray(affine, np.float64)
    if convention == "itk":
        from nitransforms.io.itk import ITKDisplacementsField

        # a copy: NiTransforms flips the vectors of the array it is given in place
        nii = ITKDisplacementsField.to_image(nib.Nifti1Image(u.copy(), affine))
        data = np.asarray(nii.dataobj, np.float32)
    elif convention == "nifti":
        data = u.reshape(*u.shape[:3], 1, 3).astype(np.float32)
    else:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    out = nib.Nifti1Image(data, affine)
    out.header.set_intent(NIFTI_INTENT_VECTOR if convention == "itk" else NIFTI_INTENT_DISPVECT)
    out.header.set_xyzt_units("mm")
    out.header["descrip"] = description[:79].encode()
    out.set_qform(affine, code=1)
    out.set_sform(affine, code=1)
    return out


def save_displacement(u, affine, path, *, convention: str = "itk",
                      description: str = FIXED_TO_MOVING) -> Path:
    """Write a displacement field (:func:`field_image`) atomically to ``path``; returns it."""
    path = Path(path)
    write_nifti_atomic(field_image(u, affine, convention=convention, description=description), path)
    return path


def load_displacement(path) -> Image:
    """Read a displacement field written by bayesreg, ITK, ANTs or Slicer.

    Parameters
    ----------
    path : str or Path
        NIfTI file: 5-D ``(I, J, K, 1, 3)`` with intent VECTOR (LPS vectors, ITK/ANTs) or
        DISPVECT (RAS vectors), or 4-D ``(I, J, K, 3)`` RAS vectors (runs written by earlier
        bayesreg versions).

    Returns
    -------
    Image
        ``data`` ``(I, J, K, 3)`` float64 RAS mm, and the grid's affine.

    Raises
    ------
    ValueError
        If the file holds no 3-D displacement field (the message names it).
    """
    import nibabel as nib

    nii = nib.load(str(path))
    shape, intent = nii.shape, int(nii.header["intent_code"])
    if len(shape) == 5 and shape[3] == 1 and shape[4] == 3:
        data = np.asarray(nii.dataobj, np.float64)[:, :, :, 0, :]
        if intent == NIFTI_INTENT_DISPVECT:
            return Image(data, nii.affine)
        data[..., :2] *= -1.0  # ITK/ANTs (intent VECTOR or unset): LPS -> RAS
        return Image(data, nii.affine)
    if len(shape) == 4 and shape[3] == 3:
        return Image(np.asarray(nii.dataobj, np.float64), nii.affine)
    raise ValueError(f"{path}: not a 3-D displacement field (shape {shape}; expected "
                     "(I, J, K, 1, 3) as ITK/ANTs write it, or (I, J, K, 3))")


def inverse_displacement(mesh: Mesh, u, grid: Image):
    """The inverse of the FE map ``x -> x + u(x)`` as a displacement field on ``grid``.

    Every voxel centre ``y`` inside the deformed mesh is located in its deformed element;
    the element's barycentric coordinates give ``x`` with ``x + u(x) = y`` exactly (the FE
    map is affine per element), and ``v(y) = x - y``.  Elsewhere ``v = 0``.

    Parameters
    ----------
    mesh : Mesh
        Undeformed mesh, nodes ``(N, 3)`` world mm.
    u : (N, 3) array
        Nodal displacements, mm.
    grid : Image
        The grid of the field (its ``data`` gives the shape ``(I, J, K)``), usually ``m``'s.

    Returns
    -------
    v : (I, J, K, 3) ndarray
        RAS mm.
    inside : (I, J, K) bool
        Voxels inside the deformed mesh.

    Raises
    ------
    ValueError
        If an element is inverted by ``u`` (the map has no inverse there).
    """
    u = np.asarray(u, np.float64)
    deformed = mesh.nodes + u
    n_bad = int(np.sum(signed_volumes(deformed, mesh.tets) <= 0))
    if n_bad:
        raise ValueError(f"{n_bad} element(s) inverted by the displacement: the FE map has no "
                         "inverse there")
    shape = grid.data.shape[:3]
    elem, bary = locate_voxels(deformed, mesh.tets, shape, grid.affine)
    inside = elem >= 0
    ijk = np.stack(np.unravel_index(np.flatnonzero(inside), shape), -1)
    y = ijk @ grid.affine[:3, :3].T + grid.affine[:3, 3]
    x = np.einsum("pa,pad->pd", bary[inside], mesh.nodes[mesh.tets[elem[inside]]])
    v = np.zeros((int(np.prod(shape)), 3))
    v[inside] = x - y
    return v.reshape(*shape, 3), inside.reshape(shape)


def locate_points(mesh: Mesh, points):
    """Element and barycentric coordinates of each point in the undeformed mesh.

    Parameters
    ----------
    mesh : Mesh
    points : (P, 3) array
        World mm.

    Returns
    -------
    elem : (P,) int
        ``-1`` for a point outside the mesh.
    bary : (P, 4)
    """
    return locate(mesh.nodes, mesh.tets, np.asarray(points, np.float64).reshape(-1, 3))


def displace_points(mesh: Mesh, u, points, *, located=None):
    """Positions ``p + u(p)`` of points under the FE map (one field or many draws).

    Parameters
    ----------
    mesh : Mesh
    u : (N, 3) or (S, N, 3) array
        Nodal displacements, mm (``S`` posterior draws).
    points : (P, 3) array
        World mm in the fixed frame.
    located : tuple, optional
        :func:`locate_points` of ``(mesh, points)``, to reuse.

    Returns
    -------
    moved : (P, 3) or (S, P, 3) ndarray
        World mm in the moving frame; a point outside the mesh does not move.
    inside : (P,) bool
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    elem, bary = located if located is not None else locate_points(mesh, points)
    u = np.asarray(u, np.float64)
    inside = elem >= 0
    tets = mesh.tets[np.where(inside, elem, 0)]
    w = np.where(inside[:, None], bary, 0.0)
    disp = np.einsum("pa,...pad->...pd", w, u[..., tets, :])
    return points + disp, inside
