"""Tissue label maps: CSF, GM, WM inside the intracranial volume, and the skull region.

Internal label coding (used by every other module)::

    0 background (free space between brain and skull: nodes may move there)
    1 CSF   2 GM   3 WM   4 skull (hard constraint: no node may enter it)

User label maps are translated with :func:`remap_labels` from a coding given in the config,
e.g. ``{csf: 1, gm: 2, wm: 3, skull: [4, 5]}``.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.ndimage as ndi

from bayesreg.data.images import Image, check_same_space

__all__ = [
    "BACKGROUND",
    "CSF",
    "GM",
    "WM",
    "SKULL",
    "TISSUES",
    "TISSUE_LABELS",
    "labels_from_probabilities",
    "remap_labels",
    "check_labels",
    "free_shell",
    "tissue_label",
]

BACKGROUND, CSF, GM, WM, SKULL = 0, 1, 2, 3, 4
TISSUES = ("csf", "gm", "wm")
"""Tissue names in the order of tissue indices 0, 1, 2 (element ``tissue`` arrays)."""
TISSUE_LABELS = (CSF, GM, WM)


def tissue_label(tissue):
    """Label-map codes (1 CSF, 2 GM, 3 WM) of element tissue indices (0, 1, 2): the one
    coding of every output file.  Returns an int32 array of the same shape."""
    return np.asarray(TISSUE_LABELS, np.int32)[np.asarray(tissue)]


def labels_from_probabilities(gm: Image, wm: Image, brain_mask: Image, *, skull_margin_mm=5.0):
    """Label map from GM/WM probability maps and a brain mask (the MNI152 recipe).

    The intracranial volume is the brain mask with holes filled; inside it each voxel takes
    the most probable of CSF (``1 - GM - WM``), GM and WM, so ventricles and sulci come out
    as CSF.  The skull region is everything outside the intracranial mask dilated by
    ``skull_margin_mm``; the shell in between is background.

    Parameters
    ----------
    gm, wm : Image
        Probabilities in [0, 1], same grid.
    brain_mask : Image
        Non-zero inside the brain, same grid.
    skull_margin_mm : float
        Width of the free shell between brain and skull, mm (> 0).

    Returns
    -------
    Image
        uint8 labels in the internal coding.

    Raises
    ------
    ValueError
        Mismatched grids, a non-positive margin or an empty tissue.
    """
    check_same_space(gm, wm, names=("gm", "wm"))
    check_same_space(gm, brain_mask, names=("gm", "brain_mask"))
    if skull_margin_mm <= 0:
        raise ValueError(f"skull_margin_mm must be > 0, got {skull_margin_mm}")
    inside = ndi.binary_fill_holes(np.asarray(brain_mask.data) > 0.5)
    p_gm = np.clip(np.asarray(gm.data, dtype=np.float64), 0, 1)
    p_wm = np.clip(np.asarray(wm.data, dtype=np.float64), 0, 1)
    p_csf = np.clip(1.0 - p_gm - p_wm, 0, 1)
    tissue = np.argmax(np.stack([p_csf, p_gm, p_wm]), axis=0) + 1
    labels = np.where(inside, tissue, BACKGROUND).astype(np.uint8)
    dist = ndi.distance_transform_edt(~inside, sampling=gm.spacing)
    labels[(dist > skull_margin_mm) & ~inside] = SKULL
    out = Image(labels, gm.affine)
    check_labels(out)
    return out


def remap_labels(labels: Image, coding: dict) -> Image:
    """Translate a user label map to the internal coding.

    Parameters
    ----------
    labels : Image
        Integer label map.
    coding : dict
        ``{"csf": int | list[int], "gm": ..., "wm": ..., "skull": ...}``; values not listed
        become background; every listed value must occur.  ``skull`` may be omitted (a run
        then takes its skull region from :func:`free_shell` alone).

    Raises
    ------
    ValueError
        Unknown keys, a value claimed by two tissues, or a tissue or skull none of whose
        listed values has a voxel (a typo in the coding would otherwise empty a tissue or
        silently drop the skull constraint); the message names the tissue and the values.

    Warns
    -----
    UserWarning
        Some, not all, of a tissue's listed values have no voxel (named).
    """
    allowed = {"csf": CSF, "gm": GM, "wm": WM, "skull": SKULL}
    unknown = set(coding) - set(allowed)
    if unknown:
        raise ValueError(f"unknown label names {sorted(unknown)}; allowed: {sorted(allowed)}")
    data = np.asarray(labels.data)
    if not np.issubdtype(data.dtype, np.integer):
        if not np.allclose(data, np.round(data)):
            raise ValueError("label map must hold integer values")
        data = np.round(data).astype(np.int64)
    out = np.full(data.shape, BACKGROUND, np.uint8)
    seen: dict[int, str] = {}
    for name, values in coding.items():
        values = [int(v) for v in np.atleast_1d(values)]
        missing = []
        for v in values:
            if v in seen:
                raise ValueError(f"label value {v} assigned to both {seen[v]} and {name}")
            seen[v] = name
            hit = data == v
            if not hit.any():
                missing.append(v)
            out[hit] = allowed[name]
        if missing:
            what = "tissue" if name in TISSUES else "region"
            empty = len(missing) == len(values)
            msg = (f"{what} '{name}' is {'empty' if empty else 'incomplete'} in the label map: no "
                   f"voxel has the label value{'s' if len(missing) > 1 else ''} "
                   f"{', '.join(map(str, missing))} of label_coding {name}: {coding[name]}"
                   + (" (the skull constraint would be lost)" if name == "skull" and empty else ""))
            if empty:
                raise ValueError(msg)
            # a list of codes (an atlas's structures) may name some a subject lacks
            warnings.warn(msg, stacklevel=2)
    res = Image(out, labels.affine)
    check_labels(res)
    return res


def check_labels(labels: Image) -> None:
    """Raise ``ValueError`` if a tissue (CSF, GM, WM) has no voxel or codes are unknown."""
    data = np.asarray(labels.data)
    bad = np.setdiff1d(np.unique(data), [BACKGROUND, CSF, GM, WM, SKULL])
    if bad.size:
        raise ValueError(f"label map holds codes {bad.tolist()} outside the internal coding")
    for name, code in zip(TISSUES, TISSUE_LABELS):
        if not np.any(data == code):
            raise ValueError(f"tissue '{name}' is empty in the label map")


def free_shell(labels: Image, margin_mm: float) -> tuple[Image, int]:
    """The free space of the skull constraint: every voxel outside the intracranial tissues
    within ``margin_mm`` of them becomes background (free), every one beyond it skull.

    This is the MNI152 recipe's rule (:func:`labels_from_probabilities`, where it changes
    nothing), applied to any label map: whatever the labels say around the brain (a skull
    that touches it, as in BrainWeb's models and most atlases; scalp; air outside the head
    or in a sinus), the brain may move into a shell of ``margin_mm`` and slide in it, and
    never beyond.  Without the second half, free space beyond the skull (the air around the
    head) would let a node that jumps across the skull in one solver step land outside it.

    Parameters
    ----------
    labels : Image
        Internal coding.
    margin_mm : float
        Width of the shell, mm (> 0).

    Returns
    -------
    labels : Image
        uint8, internal coding.
    n_changed : int
        Voxels whose label changed (skull or scalp made free, free space made skull).

    Raises
    ------
    ValueError
        A non-positive margin, or no tissue voxel.
    """
    if not margin_mm > 0:
        raise ValueError(f"skull_margin_mm must be > 0, got {margin_mm}")
    data = np.asarray(labels.data)
    tissue = np.isin(data, TISSUE_LABELS)
    if not tissue.any():
        raise ValueError("the label map has no CSF, GM or WM voxel")
    dist = ndi.distance_transform_edt(~tissue, sampling=labels.spacing)
    out = np.where(tissue, data, np.where(dist > margin_mm, SKULL, BACKGROUND)).astype(np.uint8)
    return Image(out, labels.affine), int(np.sum(out != data))
