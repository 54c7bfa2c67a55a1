"""The skull constraint (bayesreg.constraints): the hard nearest-voxel rule, the soft
distance to the forbidden voxel cubes, and the barrier built on it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.constraints import points_forbidden, skull_barrier, skull_distance
from bayesreg.images import Image
from bayesreg.parameters import ParamLayout
from bayesreg.posterior import build_posterior, with_skull_barrier
from bayesreg.similarity import build_ssd
from conftest import box_mesh
from helpers import log_p


def test_skull_barrier_matches_its_formula_near_a_planar_wall(small):
    """The barrier adds -(w/d - 1)^2 for a node at distance d < w of the skull's voxel
    cubes (a wall at world x = 36.5 mm, where the nearest-voxel rule flips), with d the
    soft minimum over the wall's cubes, nothing beyond w, and keeps the hard -inf; its
    gradient is finite and equals the formula's."""
    mesh, post, theta = small

    w = 1.0
    barred = with_skull_barrier(post, w)
    assert barred.skull.barrier_offsets.shape == (27, 3)  # 1 mm voxels, w = 1 mm: the 27 nearest cubes
    k = int(np.argmax(mesh.nodes[mesh.boundary, 0]))  # a node at x = 30 mm
    x0 = np.asarray(mesh.nodes[mesh.boundary[k]])
    tau = w / 20.0

    def soft(p):  # the wall's cubes x >= 36.5 next to p (voxel centres on integers)
        v = np.floor(p + 0.5)
        d = []
        for o in np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3):
            cc = v + o
            if cc[0] > 36.0:
                gap = np.maximum(np.abs(p - cc) - 0.5, 0.0)
                d.append(np.linalg.norm(gap))
        return -tau * np.log(np.sum(np.exp(-np.array(d) / tau)))

    for dx in (0.5, 0.1, 0.9, 1.5):
        t = theta.copy()
        p = x0 + np.array([36.5 - dx - x0[0], 0.0, 0.0])
        t[3 * k: 3 * k + 3] = p - x0
        lp0, lp1 = float(log_p(post, t)[0]), float(log_p(barred, t)[0])
        got = float(skull_distance(barred.skull, jnp.asarray(p[None]))[0])
        if dx >= w:  # no cube within w: none searched (+inf) or farther than w
            assert got >= w
            d = got
        else:
            d = soft(p)
            assert d == pytest.approx(got, abs=1e-12)
            assert dx - tau * np.log(9) <= d <= dx
        expected = -(w / d - 1.0) ** 2 if d < w else 0.0
        assert lp1 - lp0 == pytest.approx(expected, abs=1e-8), dx
    t[3 * k] = 36.6 - x0[0]  # across the wall: still -inf
    assert float(log_p(barred, t)[0]) == -np.inf
    t[3 * k] = 36.2 - x0[0]
    g = jax.grad(lambda th: log_p(barred, th)[0])(jnp.asarray(t))
    assert np.all(np.isfinite(np.asarray(g)))
    # d(barrier)/dx = 2 (w/d - 1) w / d^2 * dd/dx, dd/dx = -1 in front of one cube's face
    g0 = jax.grad(lambda th: log_p(post, th)[0])(jnp.asarray(t))
    p = x0 + np.array([36.2 - x0[0], 0.0, 0.0])
    d = soft(p)
    dd = (soft(p + [1e-7, 0, 0]) - soft(p - [1e-7, 0, 0])) / 2e-7
    assert dd == pytest.approx(-1.0, abs=0.02)  # the lateral cubes bend it slightly
    assert float(g[3 * k] - g0[3 * k]) == pytest.approx(2 * (w / d - 1) * w / d**2 * dd, rel=1e-5)


def test_the_barriers_own_wall_is_forbidden_where_its_soft_distance_reaches_zero(small):
    """At a voxel corner 0.02 mm in front of the wall the soft minimum over the four cubes
    there is ``0.02 - tau log 4 < 0`` while the hard rule allows the point: with the barrier
    the posterior forbids it (``-inf``, as the skull; clamped, it was a flat plateau near
    ``-1e12`` that held a chain), without the barrier it is allowed; 0.1 mm in front the
    barrier follows its formula and the point is clear."""
    mesh, post, theta = small
    w = 1.0
    barred = with_skull_barrier(post, w)
    k = int(np.argmax(mesh.nodes[mesh.boundary, 0]))
    x0 = np.asarray(mesh.nodes[mesh.boundary[k]])
    tau = w / 20.0
    for dx, clear in ((0.02, False), (0.2, True)):
        p = np.array([36.5 - dx, np.floor(x0[1]) + 0.5, np.floor(x0[2]) + 0.5])  # a voxel corner
        t = theta.copy()
        t[3 * k: 3 * k + 3] = p - x0
        assert not bool(points_forbidden(barred.skull, jnp.asarray(p[None]))[0])
        d = float(skull_distance(barred.skull, jnp.asarray(p[None]))[0])
        assert d == pytest.approx(dx - tau * np.log(4), abs=2e-3)
        assert bool(skull_barrier(barred.skull, jnp.asarray(p[None]))[1]) is clear
        assert bool(skull_barrier(post.skull, jnp.asarray(p[None]))[1])  # no barrier: no wall of its own
        # the mode search's barrier: the wall off, the huge finite values kept
        off = barred.skull._replace(barrier_wall=jnp.asarray(False))
        assert bool(skull_barrier(off, jnp.asarray(p[None]))[1])
        lp0, lp1 = float(log_p(post, t)[0]), float(log_p(barred, t)[0])
        assert np.isfinite(lp0)
        if clear:
            assert lp1 - lp0 == pytest.approx(-(w / d - 1.0) ** 2, rel=1e-9)
        else:
            assert lp1 == -np.inf
            g = np.asarray(jax.grad(lambda th: log_p(barred, th)[0])(jnp.asarray(t)))
            assert np.all(np.isfinite(g))


def test_skull_distance_is_never_positive_where_the_hard_rule_forbids():
    """At random points near a random voxel set (the staircase corners that defeated a
    trilinear signed distance), the barrier's distance is <= 0 wherever the nearest-voxel
    rule forbids, equals the distance to the nearest forbidden cube within tau log 27
    elsewhere, and its gradient is finite."""
    rng = np.random.default_rng(7)
    mesh = box_mesh((2, 2, 2), size=(4.0, 4.0, 4.0))
    spacing = np.array([2.0, 2.0, 1.5])
    mask = rng.random((12, 12, 12)) < 0.15
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = -8.0
    ssd_img = Image(np.zeros((12, 12, 12)), affine)
    post = build_posterior(
        mesh, build_ssd(mesh.nodes, mesh.tets, ssd_img, ssd_img), Image(mask.astype(np.uint8), affine),
        t_s=1.0, t_r=1.0, layout=ParamLayout(("all",), free=(("lam", 0),), fixed=(("mu", 0, 1.0),)),
        element_group=np.zeros(len(mesh.tets), int), prior={"lam": (1.0, 1.0, 0.0, 10.0),
                                                             "mu": (1.0, 1.0, 0.0, 10.0)},
        phi_ref=np.array([1.0]), barrier_mm=1.2)
    pts = rng.uniform(-6.0, 8.0, size=(4000, 3))
    d = np.asarray(skull_distance(post.skull, jnp.asarray(pts)))
    forb = np.asarray(points_forbidden(post.skull, jnp.asarray(pts)))
    assert forb.sum() > 300 and (~forb).sum() > 300
    assert np.all(d[forb] <= 0.0)
    # brute force: distance to every forbidden cube (and to the outside of the grid)
    centres = np.argwhere(mask) * spacing - 8.0
    gap = np.maximum(np.abs(pts[:, None, :] - centres[None]) - spacing / 2, 0.0)
    exact = np.linalg.norm(gap, axis=-1).min(axis=1)
    lo, hi = -8.0 - spacing / 2, -8.0 + 11.5 * spacing
    exact = np.minimum(exact, np.min(np.concatenate([pts - lo, hi - pts], 1), axis=1))
    near = ~forb & (exact < 1.2)
    tau = 1.2 / 20
    assert near.sum() > 300
    assert np.all(d[near] <= exact[near] + 1e-12)
    assert np.all(d[near] >= exact[near] - tau * np.log(27) - 1e-12)
    g = jax.grad(lambda p: jnp.sum(skull_distance(post.skull, p)))(jnp.asarray(pts[near]))
    assert np.all(np.isfinite(np.asarray(g)))
