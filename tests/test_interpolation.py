"""Trilinear interpolation in JAX (bayesreg.data.interpolation): values against SciPy, the
hand-written JVPs against finite differences, the clamped variant against the plain one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from bayesreg.data.images import interpolate_numpy
from bayesreg.data.interpolation import interpolate, trilinear_clamped
from helpers import grid_image


def test_trilinear_matches_scipy_and_outside_is_cval():
    rng = np.random.default_rng(1)
    img = grid_image(lambda x: rng.random(x.shape[:-1]), shape=(8, 9, 10))
    pts = rng.uniform(-4.0, 2.0, size=(200, 3))
    inv = jnp.asarray(np.linalg.inv(img.affine))
    np.testing.assert_allclose(np.asarray(interpolate(jnp.asarray(img.data), inv, jnp.asarray(pts))),
                               interpolate_numpy(img, pts), atol=1e-12)
    far = jnp.asarray([[100.0, 0.0, 0.0]])
    assert float(interpolate(jnp.asarray(img.data), inv, far, 0.25)[0]) == 0.25


def test_trilinear_derivatives_match_finite_differences_in_every_argument():
    """The hand-written JVP of ``interpolate`` (points, volume, affine and cval; forward
    and reverse mode) against central differences, at points inside the grid and within
    one voxel of its border (where the value blends toward ``cval``)."""
    rng = np.random.default_rng(3)
    img = grid_image(lambda x: rng.random(x.shape[:-1]), shape=(8, 9, 10))
    inv = jnp.asarray(np.linalg.inv(img.affine))
    # cell offsets kept away from 0 and 1 so that a difference step stays in one cell
    c = np.concatenate([rng.integers(0, 7, size=(30, 3)) + rng.uniform(0.2, 0.8, size=(30, 3)),
                        [[-0.5, 3.3, 4.6], [7.4, 8.3, 9.6]]])
    pts = jnp.asarray(c @ np.asarray(img.affine)[:3, :3].T + np.asarray(img.affine)[:3, 3])
    vol = jnp.asarray(img.data)
    check_grads(lambda p: interpolate(vol, inv, p, 0.3), (pts,), order=1, modes=("fwd", "rev"),
                eps=1e-6)
    check_grads(lambda v, a, cv: interpolate(v, a, pts, cv), (vol, inv, jnp.asarray(0.3)),
                order=1, modes=("fwd", "rev"), eps=1e-6)
    # the gradient in the points is the slope of the cell's trilinear polynomial: exact
    # for a linear image
    lin = grid_image(lambda x: x @ np.array([0.5, -1.5, 2.0]) + 1.0, shape=(8, 9, 10))
    g = jax.grad(lambda p: jnp.sum(interpolate(jnp.asarray(lin.data), inv, p)))(pts[:30])
    np.testing.assert_allclose(np.asarray(g), np.tile([0.5, -1.5, 2.0], (30, 1)), atol=1e-10)


def test_clamped_trilinear_with_a_cval_border_equals_interpolate_everywhere():
    """``trilinear_clamped`` on a volume with one voxel of ``cval`` around it is
    ``interpolate`` with that ``cval``: inside, in the band where it blends toward ``cval``
    and far outside; its JVP (coordinates and volume, forward and reverse) against
    central differences; a NaN coordinate gives NaN (its gather is clamped, not out of
    bounds)."""
    rng = np.random.default_rng(4)
    img = grid_image(lambda x: rng.random(x.shape[:-1]), shape=(8, 9, 10))
    inv = np.linalg.inv(img.affine)
    padded = jnp.asarray(np.pad(img.data, 1, constant_values=0.25))
    c = rng.uniform(-3.0, 12.0, size=(400, 3))  # inside, in the border band and beyond
    pts = c @ np.asarray(img.affine)[:3, :3].T + np.asarray(img.affine)[:3, 3]
    ref = interpolate(jnp.asarray(img.data), jnp.asarray(inv), jnp.asarray(pts), 0.25)
    out = trilinear_clamped(padded, jnp.asarray(c + 1.0))
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=0, atol=1e-14)
    assert float(trilinear_clamped(padded, jnp.asarray([[-50.0, 3.0, 200.0]]))[0]) == 0.25
    inside = jnp.asarray(rng.integers(0, 8, size=(30, 3)) + rng.uniform(0.2, 0.8, size=(30, 3)))
    check_grads(lambda x: trilinear_clamped(padded, x), (inside,), order=1, modes=("fwd", "rev"),
                eps=1e-6)
    check_grads(lambda v: trilinear_clamped(v, inside), (padded,), order=1, modes=("fwd", "rev"),
                eps=1e-6)
    lin = grid_image(lambda x: x @ np.array([0.5, -1.5, 2.0]) + 1.0, shape=(8, 9, 10))
    g = jax.grad(lambda x: jnp.sum(trilinear_clamped(jnp.asarray(lin.data), x)))(inside * 0.85)
    np.testing.assert_allclose(np.asarray(g), np.tile([0.5, -1.5, 2.0], (30, 1)), atol=1e-10)
    nan = trilinear_clamped(padded, jnp.asarray([[np.nan, 1.0, 1.0], [1.0, 1.0, 1.0]]))
    assert np.isnan(float(nan[0])) and np.isfinite(float(nan[1]))
    with pytest.raises(ValueError, match="at least 2 voxels"):
        trilinear_clamped(jnp.zeros((1, 4, 4)), inside)


def test_cubic_bspline_matches_scipy_and_its_derivatives_are_smooth_and_exact():
    """The cubic B-spline interpolant (prefiltered coefficients) equals SciPy's
    ``map_coordinates(order=3)`` of the edge-padded volume to 1e-12, passes through the voxel
    values, clamps outside the grid; its hand-written JVP (coordinates and coefficients)
    passes JAX's finite-difference check, and its gradient is continuous across a voxel face
    where the trilinear one jumps."""
    import scipy.ndimage as ndi

    from bayesreg.data.interpolation import CUBIC_PAD, cubic_clamped, cubic_coefficients

    rng = np.random.default_rng(3)
    vol = rng.random((9, 10, 11))
    coef = jnp.asarray(cubic_coefficients(vol))
    pts = rng.uniform(-2.0, 12.0, size=(300, 3))
    clamped = np.clip(pts, 0.0, np.array(vol.shape) - 1.0)
    ref = ndi.map_coordinates(np.pad(vol, CUBIC_PAD, "edge"), (clamped + CUBIC_PAD).T, order=3,
                              mode="mirror")
    np.testing.assert_allclose(np.asarray(cubic_clamped(coef, jnp.asarray(pts))), ref, rtol=0, atol=1e-12)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in vol.shape], indexing="ij"), -1).reshape(-1, 3)
    np.testing.assert_allclose(np.asarray(cubic_clamped(coef, jnp.asarray(grid, jnp.float64))),
                               vol.reshape(-1), atol=1e-12)
    inside = jnp.asarray(rng.uniform(0.5, 7.5, size=(20, 3)))
    check_grads(lambda c, x: cubic_clamped(c, x), (coef, inside), order=1, modes=("fwd", "rev"))
    # across the face x = 4 of a voxel: the cubic gradient is continuous, the trilinear one jumps
    face = np.array([[4.0, 4.3, 5.6]])
    eps = np.array([[1e-7, 0.0, 0.0]])

    def grad(f, x):
        return np.asarray(jax.grad(lambda y: jnp.sum(f(y)))(jnp.asarray(x)))

    cubic = lambda x: cubic_clamped(coef, x)  # noqa: E731
    linear = lambda x: trilinear_clamped(jnp.asarray(vol), x)  # noqa: E731
    assert np.abs(grad(cubic, face + eps) - grad(cubic, face - eps)).max() < 1e-5
    assert np.abs(grad(linear, face + eps) - grad(linear, face - eps)).max() > 1e-2
    with pytest.raises(ValueError, match="cubic_coefficients"):
        cubic_clamped(jnp.zeros((3, 3, 3)), inside)
