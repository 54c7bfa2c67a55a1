"""FE fields on image grids (bayesreg.mesh.warp): point location, interpolation matrices, the
moments of interpolated draws, and the inverse warp of an image by a mesh displacement or
a dense field."""

import numpy as np
import pytest

from bayesreg.data.images import Image, grid_points, interpolate_numpy
from bayesreg.mesh.warp import (grid_moments, grid_moments_from, interpolation_matrix, locate, locate_voxels,
                           warp_image, warp_image_field)
from conftest import box_mesh
from helpers import fake_run, smooth_image, world_grid


def test_locate_and_interpolation_reproduce_linear_fields():
    m = box_mesh((2, 2, 2), size=(20.0, 20.0, 20.0))
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.5, 19.5, size=(300, 3))
    elem, bary = locate(m.nodes, m.tets, pts)
    assert np.all(elem >= 0)
    np.testing.assert_allclose(np.einsum("pa,pad->pd", bary, m.nodes[m.tets[elem]]), pts, atol=1e-10)
    outside, _ = locate(m.nodes, m.tets, np.array([[-1.0, 5.0, 5.0]]))
    assert outside[0] == -1
    grid = smooth_image(shape=(12, 12, 12), origin=0.0)
    w, inside = interpolation_matrix(m, grid)
    field = m.nodes @ np.array([0.1, -0.2, 0.3])
    ijk = np.argwhere(inside)
    np.testing.assert_allclose((w @ field)[inside.ravel()], ijk @ np.array([0.1, -0.2, 0.3]), atol=1e-10)


def test_warp_inverts_a_known_affine_map():
    # u(x) = A x + t on a box: m(x + u(x)) = f(x), i.e. m(y) = f(phi^-1(y))
    m = box_mesh((3, 3, 3), size=(24.0, 24.0, 24.0), origin=(3.0, 3.0, 3.0))
    f = smooth_image()
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
        warp_image(smooth_image(), m, u)


def test_warp_image_inverts_an_affine_map():
    mesh = box_mesh(n=(3, 3, 3), size=(30, 30, 30))
    a = np.array([[1.05, 0.03, -0.02], [-0.04, 0.97, 0.05], [0.02, -0.03, 1.02]])
    b = np.array([1.5, -2.0, 0.8])
    assert np.linalg.det(a) > 0
    u = mesh.nodes @ a.T + b - mesh.nodes
    _, aff, xyz = world_grid(-6.0, 36.0, 1.5)
    coef, c0 = np.array([0.7, -1.3, 2.1]), 4.0
    f = Image(xyz @ coef + c0, aff)
    m = warp_image(f, mesh, u, background=-99.0)
    x = (xyz - b) @ np.linalg.inv(a).T  # exact preimage of every voxel centre
    inside = np.all((x > 0.5) & (x < 29.5), axis=-1)
    outside = np.any((x < -0.5) | (x > 30.5), axis=-1)
    assert inside.sum() > 1000 and outside.sum() > 1000
    np.testing.assert_allclose(m.data[inside], x[inside] @ coef + c0, rtol=0, atol=1e-10)
    assert np.all(m.data[outside] == -99.0)
    # extended: the covered voxels are unchanged, the others take f at a finite preimage
    ext = warp_image(f, mesh, u, background=-99.0, outside="extend")
    np.testing.assert_array_equal(ext.data[inside], m.data[inside])
    assert np.all(np.isfinite(ext.data)) and np.sum(ext.data[outside] != -99.0) > 1000
    with pytest.raises(ValueError, match="outside"):
        warp_image(f, mesh, u, outside="zero")


def test_warp_image_extended_translation_is_exact_everywhere():
    """A rigid translation continued outside the mesh is the same translation, so the
    extended ``m`` is ``f(y - t)`` on every voxel whose preimage is inside ``f``'s grid."""
    mesh = box_mesh(n=(3, 3, 3), size=(30, 30, 30))
    t = np.array([1.3, -2.1, 0.6])
    _, aff, xyz = world_grid(-6.0, 36.0, 1.5)
    coef, c0 = np.array([0.7, -1.3, 2.1]), 4.0
    f = Image(xyz @ coef + c0, aff)
    m = warp_image(f, mesh, np.broadcast_to(t, mesh.nodes.shape), background=-99.0, outside="extend")
    pre = xyz - t
    ok = np.all((pre > -6.0) & (pre < 36.0 - 1.5), axis=-1)
    assert ok.mean() > 0.7
    np.testing.assert_allclose(m.data[ok], pre[ok] @ coef + c0, rtol=0, atol=1e-9)


def test_locate_voxels_equals_locate_at_the_voxel_centres():
    """The grid search gives ``locate``'s elements and barycentric coordinates (bit for bit)
    on an oblique, flipped grid whose voxels overhang the mesh."""
    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    rot = np.linalg.qr(np.random.default_rng(2).normal(size=(3, 3)))[0]
    affine = np.eye(4)
    affine[:3, :3] = rot @ np.diag([2.0, -1.5, 2.5])
    affine[:3, 3] = [15.0, 15.0, 15.0] - affine[:3, :3] @ [10.0, 12.0, 8.0]
    grid = Image(np.zeros((21, 25, 17)), affine)
    expect = locate(mesh.nodes, mesh.tets, grid_points(grid))
    got = locate_voxels(mesh.nodes, mesh.tets, grid.data.shape, grid.affine)
    assert 0 < np.sum(expect[0] >= 0) < len(expect[0])  # some centres inside, some outside
    np.testing.assert_array_equal(got[0], expect[0])
    np.testing.assert_array_equal(got[1], expect[1])


def test_grid_moments_equal_the_moments_of_interpolated_draws():
    """``w^T Cov w`` per voxel is the variance of the FE-interpolated draws (linearity)."""
    mesh, _, _, draws = fake_run(seed=1)
    affine = np.array([[2.5, 0, 0, -1.0], [0, 2.6, 0, -0.5], [0, 0, 3.1, 0.3], [0, 0, 0, 1]])
    grid = Image(np.zeros((9, 8, 7)), affine)  # voxels in and outside the 20 mm box
    w, inside = interpolation_matrix(mesh, grid)
    assert inside.sum() > 100
    interp = np.stack([w @ x for x in draws])  # (S, voxels, 3)
    mean, sd = grid_moments(mesh, grid, draws)
    np.testing.assert_allclose(mean.reshape(-1, 3), interp.mean(0), atol=1e-12)
    np.testing.assert_allclose(sd.reshape(-1, 3), interp.std(0), rtol=1e-9, atol=1e-12)
    assert np.all(sd.reshape(-1, 3)[~inside.ravel()] == 0.0)
    centred = draws - draws.mean(0)
    cov = np.stack([centred[:, :, a].T @ centred[:, :, a] for a in range(3)]) / len(draws)
    m2, s2 = grid_moments_from(mesh, grid, draws.mean(0), cov)
    np.testing.assert_array_equal(m2, mean)
    np.testing.assert_array_equal(s2, sd)
    with pytest.raises(ValueError, match="cov"):
        grid_moments_from(mesh, grid, draws.mean(0), cov[:2])


def test_warp_image_field_inverts_a_dense_affine_field_and_refuses_a_fold():
    """``m(y) = f(x)`` with ``x + u(x) = y`` for a dense affine field (trilinear exact), at
    every voxel whose preimage lies inside the grid; a folding field and one off ``f``'s
    grid are refused with their reason."""
    f = smooth_image()
    pts = grid_points(f)
    a = np.array([[0.05, 0.01, 0.0], [-0.02, 0.03, 0.01], [0.0, 0.02, -0.04]])
    t = np.array([0.7, -0.4, 0.3])
    field = Image((pts @ a.T + t).reshape(*f.data.shape, 3), f.affine)
    m = warp_image_field(f, field)
    x = np.linalg.solve(np.eye(3) + a, (pts - t).T).T
    lo, hi = pts.min(0), pts.max(0)
    inside = np.all((x >= lo) & (x <= hi), axis=1)
    assert inside.mean() > 0.8
    np.testing.assert_allclose(m.data.ravel()[inside], interpolate_numpy(f, x[inside]), atol=1e-5)
    with pytest.raises(ValueError, match=r"folds at \d+ voxel"):
        warp_image_field(f, Image((pts @ (-1.5 * np.eye(3)).T).reshape(field.data.shape), f.affine))
    with pytest.raises(ValueError, match="must lie on f's grid"):
        warp_image_field(f, Image(field.data[1:], f.affine))
