"""The skull constraint (bayesreg.mesh.constraints): one smooth signed distance, its sign the hard
rule and the barrier a smooth function of it, the same for the truth (NumPy) and the samplers."""

import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage as ndi
import pytest

from bayesreg.mesh.constraints import points_forbidden, skull_barrier, skull_distance
from bayesreg.data.images import Image
from bayesreg.model.parameters import ParamLayout
from bayesreg.model.posterior import build_posterior, with_skull_barrier
from bayesreg.model.similarity import build_ssd
from conftest import box_mesh
from helpers import log_p


def test_skull_barrier_matches_its_formula_near_a_planar_wall(small):
    """Near a planar wall (the skull at world x > 36 mm on 1 mm voxels) the smooth signed
    distance is exactly ``x - 36.5`` (the B-spline reproduces the linear distance, and the
    zero level lies where the nearest-voxel rule flips); the barrier adds ``-(w/s - 1)^3``
    at clearance ``s < w``, nothing beyond, keeps the hard ``-inf`` across the wall, and its
    gradient is the formula's."""
    mesh, post, theta = small
    w = 1.0
    barred = with_skull_barrier(post, w)
    k = int(np.argmax(mesh.nodes[mesh.boundary, 0]))  # a node at x = 30 mm
    x0 = np.asarray(mesh.nodes[mesh.boundary[k]])
    for dx in (0.5, 0.1, 0.9, 1.5):
        t = theta.copy()
        p = x0 + np.array([36.5 - dx - x0[0], 0.0, 0.0])
        t[3 * k: 3 * k + 3] = p - x0
        d = float(skull_distance(barred.skull, jnp.asarray(p[None]))[0])
        assert d == pytest.approx(-dx, abs=1e-12)
        lp0, lp1 = float(log_p(post, t)[0]), float(log_p(barred, t)[0])
        expected = -(w / dx - 1.0) ** 3 if dx < w else 0.0
        assert lp1 - lp0 == pytest.approx(expected, abs=1e-8), dx
    t[3 * k] = 36.6 - x0[0]  # across the wall: -inf
    assert float(log_p(barred, t)[0]) == -np.inf
    assert float(log_p(post, t)[0]) == -np.inf
    t[3 * k] = 36.2 - x0[0]
    g = jax.grad(lambda th: log_p(barred, th)[0])(jnp.asarray(t))
    g0 = jax.grad(lambda th: log_p(post, th)[0])(jnp.asarray(t))
    s = 0.3
    assert float(g[3 * k] - g0[3 * k]) == pytest.approx(-3 * (w / s - 1) ** 2 * w / s**2, rel=1e-8)


def test_the_barriers_own_wall_is_forbidden_below_its_floor(small):
    """The barrier and the hard wall are one surface, ``d = 0``.  A point allowed by the hard
    rule but closer than ``BARRIER_FLOOR * w`` to it is forbidden with the barrier (``-inf``,
    as the skull; clamped, it would be a flat plateau that holds a chain), allowed without
    it, and clear for the mode search (its wall off: the huge finite values kept); 0.2 mm
    in front the barrier follows its formula and the point is clear."""
    from bayesreg.mesh.constraints import BARRIER_FLOOR

    mesh, post, theta = small
    w = 1.0
    barred = with_skull_barrier(post, w)
    k = int(np.argmax(mesh.nodes[mesh.boundary, 0]))
    x0 = np.asarray(mesh.nodes[mesh.boundary[k]])
    for dx, clear in ((0.5 * BARRIER_FLOOR * w, False), (0.2, True)):
        p = np.array([36.5 - dx, np.floor(x0[1]) + 0.5, np.floor(x0[2]) + 0.5])  # a voxel corner
        t = theta.copy()
        t[3 * k: 3 * k + 3] = p - x0
        assert not bool(points_forbidden(barred.skull, jnp.asarray(p[None]))[0])
        assert bool(skull_barrier(barred.skull, jnp.asarray(p[None]))[1]) is clear
        assert bool(skull_barrier(post.skull, jnp.asarray(p[None]))[1])  # no barrier: no wall of its own
        off = barred.skull._replace(barrier_wall=jnp.asarray(False))
        assert bool(skull_barrier(off, jnp.asarray(p[None]))[1])
        lp0, lp1 = float(log_p(post, t)[0]), float(log_p(barred, t)[0])
        assert np.isfinite(lp0)
        if clear:
            assert lp1 - lp0 == pytest.approx(-(w / dx - 1.0) ** 3, rel=1e-9)
        else:
            assert lp1 == -np.inf


def test_one_smooth_signed_distance_for_the_truth_and_the_samplers():
    """On a random skull (a thick slab with random bumps and holes, 1.5-2 mm anisotropic
    voxels): the samplers' signed distance (JAX) and the truth's (NumPy, with gradient and
    Hessian) are the same function to 1e-12, its Hessian matches finite differences of its
    gradient, its gradient is continuous across voxel faces (C2, where a voxel staircase
    jumps), its sign is the nearest-voxel rule's away from the staircase's edges, points
    outside the grid are forbidden, and, given the mesh at rest, so is an allowed pocket
    that the skull separates from it."""
    from bayesreg.mesh.constraints import SignedDistance, skull_constraint

    rng = np.random.default_rng(7)
    spacing = np.array([2.0, 2.0, 1.5])
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = -8.0
    idx = np.stack(np.meshgrid(*[np.arange(16)] * 3, indexing="ij"), -1)
    mask = (idx[..., 0] >= 9) | ((idx[..., 0] == 8) & (rng.random((16, 16, 16)) < 0.4))
    mask[12:15, 5:8, 5:8] = False  # a pocket inside the skull
    skull = skull_constraint(Image(mask.astype(np.uint8), affine), nodes=np.zeros((1, 3)))
    host = SignedDistance(skull)
    pts = rng.uniform(-10.0, 24.0, size=(20000, 3))
    d = np.asarray(skull_distance(skull, jnp.asarray(pts)))
    dh, gh, hh = host(pts, hessian=True)
    np.testing.assert_allclose(d, dh, atol=1e-12)
    # SciPy's reference: the EDT between voxel centres less half a voxel on the grid padded by
    # 5 forbidden voxels (the pocket forbidden), read as a cubic B-spline without prefilter
    pad = np.pad(mask | np.pad(np.ones((3, 3, 3), bool), ((12, 1), (5, 8), (5, 8))), 5,
                 constant_values=True)
    h = 0.5 * spacing.min()
    samples = np.where(pad, ndi.distance_transform_edt(pad, sampling=spacing) - h,
                       h - ndi.distance_transform_edt(~pad, sampling=spacing))
    cv = np.clip((pts - affine[:3, 3]) / spacing + 5.0, 0.0, np.array(pad.shape) - 1.0)
    ref = ndi.map_coordinates(samples, cv.T, order=3, prefilter=False, mode="nearest")
    np.testing.assert_allclose(d, ref, atol=1e-10)
    gj = np.asarray(jax.vmap(jax.grad(lambda q: skull_distance(skull, q)))(jnp.asarray(pts)))
    np.testing.assert_allclose(gj, gh, atol=1e-10)
    inside = np.all((pts > -7.0) & (pts < np.array([22.0, 22.0, 13.0])), axis=1)
    q = pts[inside][:50]
    eps = 1e-6
    fd = np.stack([(host(q + eps * e)[1] - host(q - eps * e)[1]) / (2 * eps) for e in np.eye(3)], -1)
    np.testing.assert_allclose(host(q, hessian=True)[2], fd, atol=1e-5)
    # C2 across a voxel face (x = -8 + 2 * 8.5 mm), where the staircase's gradient jumps
    face = np.array([[-8.0 + 2 * 8.5, 3.3, 4.1]])
    step = np.array([[1e-7, 0.0, 0.0]])
    assert np.abs(host(face + step)[1] - host(face - step)[1]).max() < 1e-5
    # the nearest-voxel rule inside uniform 3x3x3 blocks (the spline rounds the staircase's
    # corners and erodes features of a voxel or two)
    c = (pts - affine[:3, 3]) / spacing
    frac = np.abs(c - np.floor(c) - 0.5)
    vox = np.floor(c + 0.5).astype(int)
    in_grid = np.all((vox >= 0) & (vox < 16), axis=1)
    rule = ~in_grid | mask[tuple(np.clip(vox, 0, 15).T)]
    pocket = in_grid & np.all((vox >= [12, 5, 5]) & (vox <= [14, 7, 7]), axis=1)
    offs = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    nb = np.stack([np.clip(vox + o, 0, 15) for o in offs])  # the 3x3x3 block around the voxel
    same = np.all(mask[tuple(nb.transpose(2, 0, 1))] == mask[tuple(np.clip(vox, 0, 15).T)], axis=0)
    away = np.all((vox >= 1) & (vox <= 14), axis=1) & same & np.all(frac < 0.2, axis=1)
    assert away.sum() > 300
    np.testing.assert_array_equal((d >= 0)[away & ~pocket], rule[away & ~pocket])
    assert np.all(d[away & pocket] > 0)  # the pocket: forbidden, given the mesh
    assert np.all(d[~in_grid & np.any(np.abs(c - 7.5) > 9.0, axis=1)] > 0)  # beyond the grid
    open_skull = skull_constraint(Image(mask.astype(np.uint8), affine))
    assert np.all(np.asarray(skull_distance(open_skull, jnp.asarray(pts[away & pocket]))) < 0)


def test_inversion_barrier_follows_its_formula_in_the_volume_ratio():
    """One unit tetrahedron squashed along z to the volume ratio ``J = s``: the barrier is
    ``-(r / J - 1)^3`` below ``r``, 0 above with a zero derivative at ``r`` (C2), finite for an
    inverted element (the hard constraint rejects it), and a sum over elements."""
    from bayesreg.mesh.constraints import element_volumes, inversion_barrier

    nodes = jnp.asarray([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tets = jnp.asarray([[0, 1, 2, 3]])
    v0 = element_volumes(nodes, tets)
    assert float(v0[0]) == pytest.approx(1.0 / 6.0)
    r = 0.1

    def barrier(s):
        return inversion_barrier(nodes * jnp.asarray([1.0, 1.0, s]), tets, v0, r)

    for s in (0.5, 0.1, 0.05, 0.01, 1e-4):
        expected = -((r / s - 1.0) ** 3) if s < r else 0.0
        assert float(barrier(s)) == pytest.approx(expected, rel=1e-12, abs=1e-15)
    assert float(jax.grad(barrier)(r)) == pytest.approx(0.0, abs=1e-12)
    assert float(jax.grad(barrier)(0.05)) == pytest.approx(3 * (r / 0.05 - 1) ** 2 * r / 0.05**2, rel=1e-10)
    assert np.isfinite(float(barrier(-0.5)))
    two = jnp.asarray([[0, 1, 2, 3], [0, 1, 2, 3]])
    squashed = nodes * jnp.asarray([1.0, 1.0, 0.05])
    assert float(inversion_barrier(squashed, two, jnp.concatenate([v0, v0]), r)) == pytest.approx(-2.0)
