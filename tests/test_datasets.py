"""Data sources (bayesreg.data.datasets): a BrainWeb-like crisp model made here (the real models
are not needed), its T1-weighted image, labels, grid and noise."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest

from bayesreg.data import labels as L
from bayesreg.data.datasets import (BRAINWEB_CLASSES, BRAINWEB_T1_SEQUENCE, BRAINWEB_TISSUE, brainweb,
                               brainweb_model, t1_weighted_signal)


def _signal(name):
    return float(t1_weighted_signal(*BRAINWEB_TISSUE[name], **BRAINWEB_T1_SEQUENCE))


def crisp_model(path, shape=(24, 28, 20)):
    """A 0.5 mm crisp model in BrainWeb's classes, stored with a flipped, shifted affine
    (as MINC files often are): background, scalp (fat), skull, dura, CSF, GM, WM."""
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    r = np.linalg.norm((ijk - (np.array(shape) - 1) / 2) * 0.5, axis=-1)  # mm
    c = BRAINWEB_CLASSES.index
    data = np.full(shape, c("background"), np.uint8)
    data[r < 6.5] = c("fat")
    data[r < 5.5] = c("skull")
    data[r < 4.5] = c("dura")
    data[r < 4.0] = c("csf")
    data[r < 3.5] = c("gm")
    data[r < 2.0] = c("wm")
    affine = np.diag([-0.5, 0.5, 0.5, 1.0])
    affine[:3, 3] = [10.0, -20.0, 5.0]
    nib.save(nib.Nifti1Image(data, affine), path)
    return data, affine


def test_brainweb_image_and_labels_from_a_crisp_model(tmp_path):
    data, affine = crisp_model(tmp_path / "m.nii.gz")
    t1, lab = brainweb(tmp_path / "m.nii.gz", resolution_mm=1.0, margin_mm=2.0)
    # canonical (RAS) 1 mm grid, 2 voxels of padding; world coordinates kept: the new voxel
    # (i, j, k) is the centre of the 2x2x2 model voxels it averages
    assert np.allclose(np.diag(t1.affine)[:3], 1.0) and t1.data.shape == (12 + 4, 14 + 4, 10 + 4)
    np.testing.assert_array_equal(t1.affine, lab.affine)
    canon = nib.as_closest_canonical(nib.Nifti1Image(data, affine))
    model = np.asarray(canon.dataobj)
    centre_world = canon.affine[:3, :3] @ [0.5, 0.5, 0.5] + canon.affine[:3, 3]
    np.testing.assert_allclose(t1.affine[:3, :3] @ [2, 2, 2] + t1.affine[:3, 3], centre_world)
    # partial volume: each voxel's signal is the mean of its 8 model voxels' class signals
    sig = np.array([_signal(n) for n in BRAINWEB_CLASSES])
    blocks = model.reshape(12, 2, 14, 2, 10, 2).transpose(0, 2, 4, 1, 3, 5).reshape(12, 14, 10, 8)
    np.testing.assert_allclose(t1.data[2:-2, 2:-2, 2:-2], sig[blocks].mean(-1), rtol=1e-12)
    assert np.all(t1.data[:2] == 0)
    # T1 contrast of BrainWeb's sequence: WM > GM > CSF, skull dark
    assert _signal("wm") > _signal("gm") > _signal("csf") > 0 == _signal("skull")
    # labels: the majority of each block, in the internal coding; the dura and the scalp
    # are skull region; the padding is skull too
    inner = lab.data[2:-2, 2:-2, 2:-2]
    assert inner[6, 7, 5] == L.WM and set(np.unique(lab.data)) == {L.BACKGROUND, L.CSF, L.GM, L.WM, L.SKULL}
    assert np.all(lab.data[:2] == L.SKULL)
    full = np.all(blocks == blocks[..., :1], axis=-1)  # blocks of one class
    from bayesreg.data.datasets import BRAINWEB_LABELS
    np.testing.assert_array_equal(inner[full], BRAINWEB_LABELS[blocks[..., 0][full]])


def test_brainweb_rician_noise(tmp_path):
    crisp_model(tmp_path / "m.nii.gz", shape=(40, 40, 40))
    clean, _ = brainweb(tmp_path / "m.nii.gz", resolution_mm=0.5, margin_mm=0.0)
    noisy, _ = brainweb(tmp_path / "m.nii.gz", resolution_mm=0.5, margin_mm=0.0, noise_percent=3.0, seed=4)
    again, _ = brainweb(tmp_path / "m.nii.gz", resolution_mm=0.5, margin_mm=0.0, noise_percent=3.0, seed=4)
    np.testing.assert_array_equal(noisy.data, again.data)  # seeded
    sigma = 0.03 * _signal("wm")
    # in the background (signal 0) the magnitude is Rayleigh: mean sigma sqrt(pi / 2)
    bg = noisy.data[clean.data == 0]
    assert bg.size > 10000
    assert bg.mean() == pytest.approx(sigma * np.sqrt(np.pi / 2), rel=0.03)
    # where the signal is high (s >> sigma) it is about Gaussian of sd sigma around s
    wm = (noisy.data - clean.data)[np.isclose(clean.data, _signal("wm"))]
    assert wm.std() == pytest.approx(sigma, rel=0.1) and abs(wm.mean()) < 0.2 * sigma


def test_brainweb_bad_arguments(tmp_path, monkeypatch):
    crisp_model(tmp_path / "m.nii.gz")
    with pytest.raises(ValueError, match="multiple of 0.5"):
        brainweb(tmp_path / "m.nii.gz", resolution_mm=0.75)
    with pytest.raises(ValueError, match="noise_percent"):
        brainweb(tmp_path / "m.nii.gz", noise_percent=-1)
    bad = np.full((4, 4, 4), 12, np.uint8)
    nib.save(nib.Nifti1Image(bad, np.eye(4)), tmp_path / "bad.nii.gz")
    with pytest.raises(ValueError, match="outside BrainWeb's classes"):
        brainweb(tmp_path / "bad.nii.gz")


def test_brainweb_model_finds_a_subject_or_says_where_it_looked(tmp_path, monkeypatch):
    (tmp_path / "subject05_crisp_v.mnc.gz").write_bytes(b"")
    assert brainweb_model(5, directory=tmp_path) == tmp_path / "subject05_crisp_v.mnc.gz"
    monkeypatch.setenv("BAYESREG_BRAINWEB_DIR", str(tmp_path))
    assert brainweb_model(5) == tmp_path / "subject05_crisp_v.mnc.gz"
    with pytest.raises(FileNotFoundError, match=r"subject 06: no subject06_crisp_v.mnc\(.gz\) in"):
        brainweb_model(6)
    with pytest.raises(ValueError, match="no normal subject 7"):
        brainweb_model(7)
    with pytest.raises(FileNotFoundError, match="not found"):
        brainweb_model(path=tmp_path / "nope.mnc")
    monkeypatch.delenv("BAYESREG_BRAINWEB_DIR")
    with pytest.raises(FileNotFoundError, match="BAYESREG_BRAINWEB_DIR"):
        brainweb_model(5)
