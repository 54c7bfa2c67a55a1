"""Label maps (bayesreg.data.labels): a user's coding remapped, labels from tissue probabilities."""

import numpy as np
import pytest

from bayesreg.data import labels as L
from bayesreg.data.images import Image


def test_remap_labels_and_errors():
    data = np.array([1, 2, 3, 4, 5, 0, 9]).reshape(7, 1, 1)
    img = Image(data, np.eye(4))
    out = L.remap_labels(img, {"csf": 1, "gm": 2, "wm": 3, "skull": [4, 5]})
    assert out.data.ravel().tolist() == [L.CSF, L.GM, L.WM, L.SKULL, L.SKULL, 0, 0]
    with pytest.raises(ValueError, match="unknown label names"):
        L.remap_labels(img, {"csf": 1, "grey": 2})
    with pytest.raises(ValueError, match="both"):
        L.remap_labels(img, {"csf": 1, "gm": 1, "wm": 3})
    with pytest.raises(ValueError, match="tissue 'wm' is empty in the label map: no voxel has "
                                         "the label value 7"):
        L.remap_labels(img, {"csf": 1, "gm": 2, "wm": 7})
    # a coded value with no voxel: an error naming the tissue and the value (a typo would
    # otherwise drop the skull constraint or part of a tissue silently)
    with pytest.raises(ValueError, match=r"region 'skull' is empty .* value 8 .*skull constraint "
                                         "would be lost"):
        L.remap_labels(img, {"csf": 1, "gm": 2, "wm": 3, "skull": 8})
    # some of a list of codes absent (an atlas's structure a subject lacks): a warning
    with pytest.warns(UserWarning, match=r"region 'skull' is incomplete .* value 8 of "
                                         r"label_coding skull: \[4, 8\]"):
        L.remap_labels(img, {"csf": 1, "gm": 2, "wm": 3, "skull": [4, 8]})
    with pytest.warns(UserWarning, match=r"tissue 'csf' is incomplete .* values 6, 7 "):
        out = L.remap_labels(img, {"csf": [1, 6, 7], "gm": 2, "wm": 3})
    assert out.data.ravel().tolist()[:3] == [L.CSF, L.GM, L.WM]
    assert L.remap_labels(img, {"csf": 1, "gm": 2, "wm": 3}).data.ravel().tolist()[3:5] == [0, 0]  # no skull


def test_labels_from_probabilities_recipe():
    shape = (30, 30, 30)
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    r = np.linalg.norm(ijk - 14.5, axis=-1)
    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    wm = Image((r < 5).astype(float), aff)
    gm = Image(((r >= 6) & (r < 10)).astype(float), aff)
    mask = Image((r < 10).astype(float), aff)
    lab = L.labels_from_probabilities(gm, wm, mask, skull_margin_mm=4.0)
    d = lab.data
    assert d[15, 15, 15] == L.WM and d[15, 15, 23] == L.GM
    assert d[15, 15, 20] == L.CSF  # inside the brain, neither GM nor WM
    assert d[15, 15, 25] == L.BACKGROUND  # within the 4 mm shell
    assert d[0, 0, 0] == L.SKULL


def test_free_shell_frees_a_shell_of_the_margin_and_forbids_beyond():
    """A skull touching the brain, scalp beyond it and air around the head: within the
    margin everything is free, beyond it everything is skull; the tissues are kept."""
    shape = (40, 40, 40)
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    r = np.linalg.norm(ijk - 19.5, axis=-1)
    data = np.zeros(shape, np.uint8)  # air around the head
    data[r < 17] = 5  # scalp (here: skull region after a coding), to be kept beyond the shell
    data[r < 14] = L.SKULL
    data[r < 10] = L.GM  # skull touching the brain
    data[r < 5] = L.WM
    data[(r < 3)] = L.CSF
    lab = Image(data, np.diag([1.5, 1.5, 1.5, 1.0]))
    out, n = L.free_shell(lab, 3.0)
    d = out.data
    tissue = np.isin(data, L.TISSUE_LABELS)
    np.testing.assert_array_equal(d[tissue], data[tissue])
    from scipy import ndimage as ndi
    dist = ndi.distance_transform_edt(~tissue, sampling=lab.spacing)
    assert np.all(d[~tissue & (dist <= 3.0)] == L.BACKGROUND)
    assert np.all(d[~tissue & (dist > 3.0)] == L.SKULL)  # skull, scalp and air alike
    assert n == int(np.sum(d != data)) > 0
    # the MNI152 recipe's labels already have the shell: nothing changes
    same, n0 = L.free_shell(out, 3.0)
    np.testing.assert_array_equal(same.data, d)
    assert n0 == 0
    with pytest.raises(ValueError, match="skull_margin_mm"):
        L.free_shell(lab, 0.0)
    with pytest.raises(ValueError, match="no CSF, GM or WM"):
        L.free_shell(Image(np.zeros(shape, np.uint8), np.eye(4)), 3.0)
