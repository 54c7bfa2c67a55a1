"""Bundled data sources: the MNI ICBM152 2009a brain shipped inside the nilearn wheel."""

from __future__ import annotations

import numpy as np

from bayesreg.images import Image, pad, resample_to_spacing

__all__ = ["mni152"]


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
