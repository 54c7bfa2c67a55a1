"""Images, labels and the synthetic warp."""

import numpy as np
import pytest

from bayesreg import labels as L
from bayesreg.images import Image, check_same_space, interpolate_numpy, pad, resample_to_spacing
from bayesreg.synthetic import interpolation_matrix, locate, warp_image
from conftest import box_mesh


def _smooth_image(shape=(40, 40, 40), origin=-5.0):
    affine = np.eye(4)
    affine[:3, 3] = origin
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1) + origin
    data = np.sin(ijk[..., 0] / 6.0) + np.cos(ijk[..., 1] / 5.0) * ijk[..., 2] / 30.0
    return Image(data, affine)


def test_remap_labels_and_errors():
    data = np.array([1, 2, 3, 4, 5, 0, 9]).reshape(7, 1, 1)
    img = Image(data, np.eye(4))
    out = L.remap_labels(img, {"csf": 1, "gm": 2, "wm": 3, "skull": [4, 5]})
    assert out.data.ravel().tolist() == [L.CSF, L.GM, L.WM, L.SKULL, L.SKULL, 0, 0]
    with pytest.raises(ValueError, match="unknown label names"):
        L.remap_labels(img, {"csf": 1, "grey": 2})
    with pytest.raises(ValueError, match="both"):
        L.remap_labels(img, {"csf": 1, "gm": 1, "wm": 3})
    with pytest.raises(ValueError, match="tissue 'wm' is empty"):
        L.remap_labels(img, {"csf": 1, "gm": 2, "wm": 7})


def test_check_same_space_names_the_problem():
    a = _smooth_image()
    b = Image(a.data, a.affine + np.diag([0, 0, 0.5, 0]))
    with pytest.raises(ValueError, match="affines disagree"):
        check_same_space(a, b)
    with pytest.raises(ValueError, match="different grids"):
        check_same_space(a, Image(a.data[:-1], a.affine))


def test_pad_and_resample_keep_world_frame():
    img = _smooth_image()
    p = pad(img, 3.0)
    pts = np.array([[1.0, 2.0, 3.0], [10.5, -2.0, 7.25]])
    np.testing.assert_allclose(interpolate_numpy(p, pts), interpolate_numpy(img, pts), atol=1e-12)
    r = resample_to_spacing(img, 2.0)
    assert np.allclose(r.spacing, 2.0)
    np.testing.assert_allclose(interpolate_numpy(r, pts), interpolate_numpy(img, pts), atol=0.1)


def test_locate_and_interpolation_reproduce_linear_fields():
    m = box_mesh((2, 2, 2), size=(20.0, 20.0, 20.0))
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.5, 19.5, size=(300, 3))
    elem, bary = locate(m.nodes, m.tets, pts)
    assert np.all(elem >= 0)
    np.testing.assert_allclose(np.einsum("pa,pad->pd", bary, m.nodes[m.tets[elem]]), pts, atol=1e-10)
    outside, _ = locate(m.nodes, m.tets, np.array([[-1.0, 5.0, 5.0]]))
    assert outside[0] == -1
    grid = _smooth_image(shape=(12, 12, 12), origin=0.0)
    w, inside = interpolation_matrix(m, grid)
    field = m.nodes @ np.array([0.1, -0.2, 0.3])
    ijk = np.argwhere(inside)
    np.testing.assert_allclose((w @ field)[inside.ravel()], ijk @ np.array([0.1, -0.2, 0.3]), atol=1e-10)


def test_warp_inverts_a_known_affine_map():
    # u(x) = A x + t on a box: m(x + u(x)) = f(x), i.e. m(y) = f(phi^-1(y))
    m = box_mesh((3, 3, 3), size=(24.0, 24.0, 24.0), origin=(3.0, 3.0, 3.0))
    f = _smooth_image()
    a = np.array([[0.05, 0.01, 0.0], [-0.02, 0.03, 0.01], [0.0, 0.02, -0.04]])
    t = np.array([0.7, -0.4, 0.3])
    u = m.nodes @ a.T + t
    warped = warp_image(f, m, u, background=-1.0)
    rng = np.random.default_rng(3)
    x = rng.uniform(5.0, 25.0, size=(200, 3))
    y = x + x @ a.T + t
    # sample m at y exactly on voxel centres is what warp computes; compare at voxels
    yv = np.round(y)
    xv = np.linalg.solve(np.eye(3) + a, (yv - t).T).T
    got = interpolate_numpy(warped, yv, order=0)
    want = interpolate_numpy(f, xv, order=1)
    np.testing.assert_allclose(got, want, atol=1e-10)
    # voxels outside the deformed box take the background
    assert interpolate_numpy(warped, np.array([[-4.0, -4.0, -4.0]]), order=0)[0] == -1.0


def test_warp_refuses_inverted_map():
    m = box_mesh((1, 1, 1), size=(10.0, 10.0, 10.0))
    u = np.zeros_like(m.nodes)
    u[0] = [20.0, 20.0, 20.0]
    with pytest.raises(ValueError, match="inverted"):
        warp_image(_smooth_image(), m, u)


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
