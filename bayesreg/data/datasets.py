"""Data sources: the MNI ICBM152 2009a brain shipped inside the nilearn wheel, and BrainWeb's
anatomical models with a T1-weighted image made from their labels.

BrainWeb (McConnell Brain Imaging Centre, MNI) distributes twenty normal anatomical models:
a "crisp" label per voxel on a 0.5 mm grid (Aubert-Broche et al., IEEE TMI 25(11) 2006).
:func:`brainweb` maps their classes to bayesreg's coding and makes a T1-weighted image from
them the way an MR simulator does at first order (:func:`t1_weighted_signal`): each class's
signal from its tissue parameters under BrainWeb's T1 sequence, partial volume by averaging
the 0.5 mm signals over each voxel of the working grid, and optional Rician noise.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from bayesreg.data import labels as L
from bayesreg.data.images import Image, pad, resample_to_spacing

__all__ = ["mni152", "brainweb", "brainweb_model", "t1_weighted_signal", "BRAINWEB_CLASSES",
           "BRAINWEB_TISSUE", "BRAINWEB_T1_SEQUENCE", "BRAINWEB_LABELS", "BRAINWEB_SUBJECTS"]


def mni152(resolution_mm: float = 2.0, *, margin_mm: float = 20.0):
    """The MNI ICBM152 2009a brain shipped inside the nilearn wheel (no download).

    Parameters
    ----------
    resolution_mm : float
        Isotropic output spacing; the 1 mm template is resampled when different.
    margin_mm : float
        Zero padding on every side (:func:`bayesreg.data.images.pad`): the template's field of
        view cuts the brainstem, and the mesh and the free shell around it must lie inside
        the grid.

    Returns
    -------
    t1, gm, wm, mask : Image
        T1 intensities, grey/white-matter probability maps in [0, 1], brain mask (0/1),
        all on one grid.  Fresh copies on every call: the resampled template is kept per
        process for each ``(resolution_mm, margin_mm)`` (a few of them), so that a second
        run in a notebook or a test session does not resample it again.
    """
    kept = _mni152_kept(float(resolution_mm), float(margin_mm))
    return tuple(Image(o.data.copy(), o.affine.copy()) for o in kept)


@functools.lru_cache(maxsize=4)
def _mni152_kept(resolution_mm: float, margin_mm: float):
    """:func:`mni152`'s images, computed once per process and arguments (never handed out)."""
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


BRAINWEB_SUBJECTS = (4, 5, 6, 18, 20, 38, 41, 42, 43, 44, 45, 46, 47, 48, 49, 50, 51, 52, 53, 54)
"""The twenty normal BrainWeb subjects (the numbers of their model files)."""

BRAINWEB_CLASSES = ("background", "csf", "gm", "wm", "fat", "muscle", "muscle/skin", "skull",
                    "vessels", "around fat", "dura", "marrow")
"""BrainWeb's classes of the twenty normal models, by label value."""

BRAINWEB_LABELS = np.array([L.BACKGROUND, L.CSF, L.GM, L.WM, L.SKULL, L.SKULL, L.SKULL, L.SKULL,
                            L.CSF, L.SKULL, L.SKULL, L.SKULL], np.uint8)
"""bayesreg's coding of each BrainWeb class: the intracranial tissues as themselves, the
vessels (blood inside the intracranial volume, mechanically soft) as CSF, the skull, dura
and marrow as the skull region, and the scalp (fat, muscle, skin, connective tissue)
outside the skull as part of the forbidden region too."""

BRAINWEB_TISSUE = {
    "background": (0.0, 0.0, 0.0),
    "csf": (2569.0, 58.0, 1.00),
    "gm": (833.0, 69.0, 0.86),
    "wm": (500.0, 61.0, 0.77),
    "fat": (350.0, 58.0, 1.00),
    "muscle": (569.0, 30.0, 1.00),
    "muscle/skin": (569.0, 30.0, 1.00),
    "skull": (0.0, 0.0, 0.0),
    "vessels": (2569.0, 58.0, 1.00),
    "around fat": (500.0, 61.0, 0.77),
    "dura": (2569.0, 58.0, 1.00),
    "marrow": (350.0, 58.0, 1.00),
}
"""Tissue parameters at 1.5 T, ``(T1 ms, T2* ms, proton density)`` per class, as BrainWeb's
MR simulator uses them (Kwan, Evans & Pike, IEEE TMI 18(11) 1999; Collins et al., IEEE TMI
17(3) 1998): CSF, GM, WM, fat, muscle and skin as published there.  The classes the
original phantom lacked take those of the nearest published class: muscle as the
"muscle/skin" class (569 ms, 30 ms, 1.0), the connective tissue around fat as WM-like
connective tissue (500 ms, 61 ms, 0.77), the dura as the "skin" class (2569 ms, 58 ms,
1.0), the marrow as fat, and the vessels as CSF (flowing blood has no single T1-weighted
value).  The skull gives no signal."""

BRAINWEB_T1_SEQUENCE = {"tr_ms": 18.0, "te_ms": 10.0, "flip_deg": 30.0}
"""BrainWeb's T1-weighted sequence: spoiled FLASH, TR 18 ms, TE 10 ms, flip angle 30 degrees."""


def t1_weighted_signal(t1_ms, t2s_ms, pd, *, tr_ms=18.0, te_ms=10.0, flip_deg=30.0):
    """Steady-state signal of a spoiled gradient echo (FLASH):
    ``PD sin(a) (1 - E1) / (1 - cos(a) E1) exp(-TE / T2*)``, ``E1 = exp(-TR / T1)``; 0 where
    ``T1`` or ``T2*`` is 0 (no signal).  Arrays broadcast."""
    t1 = np.asarray(t1_ms, np.float64)
    t2s = np.asarray(t2s_ms, np.float64)
    a = np.deg2rad(flip_deg)
    with np.errstate(divide="ignore", invalid="ignore"):
        e1 = np.exp(-tr_ms / t1)
        s = np.asarray(pd) * np.sin(a) * (1 - e1) / (1 - np.cos(a) * e1) * np.exp(-te_ms / t2s)
    return np.where((t1 > 0) & (t2s > 0), s, 0.0)


def brainweb_model(subject=None, *, path=None, directory=None) -> Path:
    """The file of BrainWeb subject ``subject``'s crisp model, or ``path`` itself.

    Parameters
    ----------
    subject : int, optional
        One of :data:`BRAINWEB_SUBJECTS`; its file is ``subjectNN_crisp_v.mnc.gz`` (or
        ``.mnc``) in ``directory``.
    path : str or Path, optional
        The model file instead.
    directory : str or Path, optional
        Where the models are; default the environment variable ``BAYESREG_BRAINWEB_DIR``.

    Raises
    ------
    FileNotFoundError
        No such file (the message says where it looked and where the models come from).
    ValueError
        Neither or both of ``subject`` and ``path``, or an unknown subject.
    """
    if (subject is None) == (path is None):
        raise ValueError("give a BrainWeb subject number or the path of a crisp model, not both")
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"BrainWeb model not found: {path}")
        return path
    if int(subject) not in BRAINWEB_SUBJECTS:
        raise ValueError(f"BrainWeb has no normal subject {subject}: {list(BRAINWEB_SUBJECTS)}")
    directory = directory or os.environ.get("BAYESREG_BRAINWEB_DIR")
    if directory is None:
        raise FileNotFoundError(
            "BrainWeb's models are not bundled: download the crisp model of the subject "
            "(https://brainweb.bic.mni.mcgill.ca/brainweb/anatomic_normal_20.html) and give "
            "its folder as data.brainweb_dir or BAYESREG_BRAINWEB_DIR")
    for suffix in (".mnc.gz", ".mnc"):
        p = Path(directory) / f"subject{int(subject):02d}_crisp_v{suffix}"
        if p.is_file():
            return p
    raise FileNotFoundError(f"BrainWeb subject {int(subject):02d}: no subject{int(subject):02d}"
                            f"_crisp_v.mnc(.gz) in {directory}")


def brainweb(model, *, resolution_mm: float = 1.0, noise_percent: float = 0.0, seed: int = 0,
             margin_mm: float = 20.0):
    """A T1-weighted image and a label map from a BrainWeb crisp anatomical model.

    The model (0.5 mm voxels) is put in the closest canonical (RAS) orientation.  Each voxel's
    signal is its class's :func:`t1_weighted_signal` under :data:`BRAINWEB_T1_SEQUENCE` with
    the parameters of :data:`BRAINWEB_TISSUE`; the working grid's voxels average the
    ``k^3`` model voxels they cover (``k = resolution_mm / 0.5``: partial volume), and take
    the class most of them hold, mapped by :data:`BRAINWEB_LABELS`.  With ``noise_percent``
    the image gets Rician noise: ``|s + n_1 + i n_2|`` with ``n_1, n_2`` Gaussian of standard
    deviation ``noise_percent / 100`` times the white matter's signal (BrainWeb's
    convention for its T1-weighted images).  Both are padded by ``margin_mm``: the image with
    0, the labels with the skull region, so that a brainstem cut by the model's edge stays
    closed.

    Parameters
    ----------
    model : str or Path
        A crisp model file (:func:`brainweb_model`), MINC1 as BrainWeb gives it (read by
        nibabel).
    resolution_mm : float
        Voxel size of the working grid, a multiple of 0.5 mm.
    noise_percent : float
        Rician noise level, % of the white matter's signal (0: none).
    seed : int
        Seed of the noise.
    margin_mm : float
        Padding on every side, mm.

    Returns
    -------
    t1 : Image
        T1-weighted intensities (arbitrary units, about 0-0.12).
    labels : Image
        Internal coding (uint8).

    Raises
    ------
    ValueError
        ``resolution_mm`` not a positive multiple of 0.5, a negative noise level, or a model
        with labels outside BrainWeb's classes.
    """
    import nibabel as nib

    k = float(resolution_mm) / 0.5
    if not (k >= 1 and abs(k - round(k)) < 1e-9):
        raise ValueError(f"resolution_mm must be a positive multiple of 0.5 mm (BrainWeb's "
                         f"models are 0.5 mm), got {resolution_mm}")
    if not noise_percent >= 0:
        raise ValueError(f"noise_percent must be >= 0, got {noise_percent}")
    k = int(round(k))
    img = nib.load(str(model))
    canon = nib.as_closest_canonical(nib.Nifti1Image(np.asarray(img.dataobj), img.affine))
    classes = np.rint(np.asarray(canon.dataobj)).astype(np.int64)
    if classes.min() < 0 or classes.max() >= len(BRAINWEB_CLASSES):
        raise ValueError(f"{model}: labels outside BrainWeb's classes 0-{len(BRAINWEB_CLASSES) - 1}")
    params = np.array([BRAINWEB_TISSUE[c] for c in BRAINWEB_CLASSES])
    signal = t1_weighted_signal(params[:, 0], params[:, 1], params[:, 2], **BRAINWEB_T1_SEQUENCE)
    shape = np.array(classes.shape) // k
    cut = classes[:shape[0] * k, :shape[1] * k, :shape[2] * k]
    blocks = cut.reshape(shape[0], k, shape[1], k, shape[2], k).transpose(0, 2, 4, 1, 3, 5)
    blocks = blocks.reshape(*shape, k ** 3)
    t1 = signal[blocks].mean(axis=-1)
    # majority of the internal codes over each block (ties to the lower code)
    codes = BRAINWEB_LABELS[blocks]
    labels = np.zeros(tuple(shape), np.uint8)
    best = np.full(tuple(shape), -1, np.int64)
    for code in (L.BACKGROUND, L.CSF, L.GM, L.WM, L.SKULL):
        count = (codes == code).sum(axis=-1)
        labels[count > best] = code
        best = np.maximum(best, count)
    del codes, blocks
    affine = np.array(canon.affine, np.float64)
    # the new voxel (i, j, k) is the centre of model voxels k i .. k i + k - 1
    affine[:3, 3] = affine[:3, :3] @ np.full(3, (k - 1) / 2.0) + affine[:3, 3]
    affine[:3, :3] = affine[:3, :3] * k
    if noise_percent > 0:
        sigma = noise_percent / 100.0 * signal[BRAINWEB_CLASSES.index("wm")]
        rng = np.random.default_rng(seed)
        t1 = np.hypot(t1 + rng.normal(0.0, sigma, t1.shape), rng.normal(0.0, sigma, t1.shape))
    t1_img = pad(Image(t1, affine), margin_mm, value=0.0)
    labels_img = pad(Image(labels, affine), margin_mm, value=L.SKULL)
    return t1_img, labels_img
