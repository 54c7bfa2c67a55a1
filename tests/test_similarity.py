"""SSD by Gauss quadrature: exact integrals of analytic images, zero for identical images."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.data.images import Image
from bayesreg.model.similarity import (GAUSS_BARY, build_ssd, gauss_points, quadrature_rule, reach_box, ssd,
                                 ssd_residuals)
from conftest import box_mesh
from helpers import grid_image


@pytest.mark.parametrize("level", [0, 1])
def test_quadrature_of_linear_image_is_exact(level):
    m = box_mesh((2, 2, 2), size=(20.0, 20.0, 20.0))
    lin = grid_image(lambda x: 0.5 + 0.01 * x[..., 0] - 0.02 * x[..., 1] + 0.03 * x[..., 2])
    zero = Image(np.zeros_like(lin.data), lin.affine)
    term = build_ssd(m.nodes, m.tets, lin, zero, quadrature_level=level)
    # E_s with m = 0 is the integral of f^2 (a quadratic: the 4-point rule is exact)
    a = np.array([0.01, -0.02, 0.03])
    # int over [0,20]^3 of (0.5 + a.x)^2
    L = 20.0
    vol = L**3
    mean_lin = a.sum() * L / 2
    var_terms = np.sum(a**2) * L**2 / 12
    exact = vol * ((0.5 + mean_lin) ** 2 + var_terms)
    got = float(ssd(term, jnp.zeros((len(m.tets), 4, 3))))
    assert got == pytest.approx(exact, rel=1e-10)
    pts, w = gauss_points(m.nodes, m.tets, level)
    assert w.sum() == pytest.approx(vol)
    assert pts.shape == (len(m.tets), 4 * 8**level, 3)


def _monomial_integral(p):
    """Mean of l1^p1 l2^p2 l3^p3 l4^p4 over a tetrahedron: 3! prod(p_i!) / (|p| + 3)!."""
    from math import factorial
    return 6 * np.prod([factorial(k) for k in p]) / factorial(sum(p) + 3)


def test_composite_rule_partitions_the_element_and_converges():
    assert np.array_equal(quadrature_rule(0)[0], GAUSS_BARY)
    # degree <= 2 exact at every level (only true if the children tile the element exactly)
    for level in (0, 1, 2):
        bary, w = quadrature_rule(level)
        assert bary.shape == (4 * 8**level, 4) and w.sum() == pytest.approx(1.0)
        assert np.allclose(bary.sum(1), 1.0) and bary.min() > 0
        for p in [(0, 0, 0, 0), (1, 0, 0, 0), (2, 0, 0, 0), (1, 1, 0, 0), (0, 1, 0, 1)]:
            got = np.sum(w * np.prod(bary ** np.asarray(p), axis=1))
            assert got == pytest.approx(_monomial_integral(p), rel=1e-12), (level, p)
    # a smooth non-polynomial: error O(h^3), i.e. down ~8x per level
    fn = lambda b: np.exp(2.0 * b[:, 0] - b[:, 1] + 0.5 * b[:, 2] * b[:, 3])  # noqa: E731
    ref_b, ref_w = quadrature_rule(3)
    ref = np.sum(ref_w * fn(ref_b))
    err = [abs(np.sum(w * fn(b)) - ref) for b, w in map(quadrature_rule, (0, 1, 2))]
    assert err[0] / err[1] > 6 and err[1] / err[2] > 6
    with pytest.raises(ValueError, match="quadrature level"):
        quadrature_rule(4)


def test_identical_images_zero_displacement_give_zero():
    m = box_mesh((2, 2, 2), size=(20.0, 20.0, 20.0))
    rng = np.random.default_rng(0)
    img = grid_image(lambda x: rng.random(x.shape[:-1]))
    term = build_ssd(m.nodes, m.tets, img, img)
    # f_q and m are the same trilinear interpolant evaluated by two routines (round-off apart):
    # residuals of about 1e-16 on intensities of about 0.5, E_s of about 1e-29
    assert float(ssd(term, jnp.zeros((len(m.tets), 4, 3)))) < 1e-24
    assert float(ssd(term, jnp.full((len(m.tets), 4, 3), 0.7))) > 1e-3


def test_translation_of_moving_image_is_recovered():
    # m(x) = f(x - t): the SSD vanishes at u = t (trilinear of a linear field is exact)
    t = np.array([1.5, -2.0, 0.5])
    f = grid_image(lambda x: 0.01 * x[..., 0] + 0.02 * x[..., 1] ** 1 - 0.005 * x[..., 2])
    mimg = grid_image(lambda x: 0.01 * (x[..., 0] - t[0]) + 0.02 * (x[..., 1] - t[1])
                       - 0.005 * (x[..., 2] - t[2]))
    m = box_mesh((2, 2, 2), size=(20.0, 20.0, 20.0))
    term = build_ssd(m.nodes, m.tets, f, mimg)
    u = jnp.broadcast_to(jnp.asarray(t), (len(m.tets), 4, 3))
    assert float(ssd(term, u)) == pytest.approx(0.0, abs=1e-20)


def test_moving_image_kept_over_the_reachable_box_gives_the_same_ssd():
    """``build_ssd(reach=...)`` stores ``m`` over the box that allowed nodes can reach: at
    displacements that keep every node allowed, ``E_s`` and its gradient equal those of the
    whole image, from a smaller array; without ``reach`` the whole grid is kept."""
    m = box_mesh((2, 2, 2), size=(20.0, 20.0, 20.0))
    rng = np.random.default_rng(5)
    f = grid_image(lambda x: rng.random(x.shape[:-1]))
    mov = grid_image(lambda x: rng.random(x.shape[:-1]))
    allowed = np.zeros(f.data.shape, np.uint8)
    allowed[3:30, 4:31, 2:29] = 1  # grid from -5 mm: voxel centres [-2, 24] x [-1, 25] x [-3, 23]
    reach = Image(allowed, f.affine)
    box = reach_box(reach)
    np.testing.assert_allclose(box, [[-2.5, -1.5, -3.5], [24.5, 25.5, 23.5]])
    whole = build_ssd(m.nodes, m.tets, f, mov)
    kept = build_ssd(m.nodes, m.tets, f, mov, reach=reach)
    assert whole.m.shape == (42, 42, 42) and kept.m.size < 0.5 * whole.m.size
    for k in range(5):
        u = jnp.asarray(rng.uniform(-2.0, 2.0, size=(len(m.nodes), 3)))[m.tets]
        a, ga = jax.value_and_grad(lambda x: ssd(whole, x))(u)
        b, gb = jax.value_and_grad(lambda x: ssd(kept, x))(u)
        assert float(b) == pytest.approx(float(a), rel=1e-13)
        np.testing.assert_allclose(np.asarray(gb), np.asarray(ga), rtol=1e-10, atol=1e-13)
    assert reach_box(Image(np.zeros_like(allowed), f.affine)) is None


def test_moving_image_in_float32_is_the_rounded_image_sampled_in_float64():
    """``moving_dtype="float32"`` stores ``m`` rounded once and changes nothing else: ``E_s``
    and its gradients equal, to float64 round-off, those of the float64 term built from
    the rounded image, and differ from the exact image's by the rounding alone (relative
    ``2^-24`` of the values); the sums and the interpolation stay float64."""
    m = box_mesh((2, 2, 2), size=(20.0, 20.0, 20.0))
    rng = np.random.default_rng(6)
    f = grid_image(lambda x: rng.random(x.shape[:-1]))
    mov = grid_image(lambda x: rng.random(x.shape[:-1]))
    rounded = Image(mov.data.astype(np.float32).astype(np.float64), mov.affine)
    assert not np.array_equal(rounded.data, mov.data)  # the rounding is real
    t32 = build_ssd(m.nodes, m.tets, f, mov, moving_dtype="float32")
    t64 = build_ssd(m.nodes, m.tets, f, rounded)
    exact = build_ssd(m.nodes, m.tets, f, mov)
    assert t32.m.dtype == jnp.float32 and exact.m.dtype == jnp.float64
    assert t32.m.nbytes * 2 == exact.m.nbytes
    for _ in range(4):
        u = jnp.asarray(rng.uniform(-2.0, 2.0, size=(len(m.nodes), 3)))[m.tets]
        a, ga = jax.value_and_grad(lambda x: ssd(t32, x))(u)
        b, gb = jax.value_and_grad(lambda x: ssd(t64, x))(u)
        c = ssd(exact, u)
        assert a.dtype == jnp.float64 and ga.dtype == jnp.float64
        assert float(a) == pytest.approx(float(b), rel=1e-14)
        np.testing.assert_allclose(np.asarray(ga), np.asarray(gb), rtol=1e-12, atol=1e-14)
        # E_s(m32) - E_s(m) = sum_q w_q dm_q (dm_q - 2 r_q), r_q = f - m at the point and
        # |dm_q| <= eps = 2^-24 max|m| (a convex combination of rounded voxels)
        eps = 2.0 ** -24 * float(np.abs(mov.data).max())
        res = ssd_residuals(exact, u)  # sqrt(w_q) r_q
        w = exact.sqrt_w ** 2
        bound = float(jnp.sum(2.0 * eps * exact.sqrt_w * jnp.abs(res) + eps ** 2 * w))
        assert 0.0 < abs(float(a) - float(c)) <= bound
    with pytest.raises(ValueError, match="moving_dtype must be one of"):
        build_ssd(m.nodes, m.tets, f, mov, moving_dtype="float16")


def _bad_image_cases():
    good = grid_image(lambda x: x[..., 0] * 0.0 + 0.5, shape=(24, 24, 24))
    nan = good.data.copy()
    nan[10, 10, 10] = np.nan
    return [
        ("f", Image(good.data, np.diag([1.0, 1.0, 0.0, 1.0])), "f affine is singular"),
        ("m", Image(good.data, np.zeros((4, 4))), "m affine is singular"),
        ("f", Image(good.data[:, :, 0], good.affine), r"f must be 3D, got shape \(24, 24\)"),
        ("m", None, r"m must be an Image\(data, affine\), got NoneType"),
        ("f", Image(nan, good.affine), "f must have finite voxel values, got 1 NaN or infinite"),
        ("m", Image(nan, good.affine), "m must have finite voxel values"),
    ], good


@pytest.mark.parametrize("case", range(6))
def test_build_ssd_rejects_bad_images(case):
    cases, good = _bad_image_cases()
    which, bad, match = cases[case]
    m = box_mesh((1, 1, 1), size=(10.0, 10.0, 10.0))
    f_img, m_img = (bad, good) if which == "f" else (good, bad)
    with pytest.raises(ValueError, match=match):
        build_ssd(m.nodes, m.tets, f_img, m_img)


def test_build_ssd_rejects_a_mesh_outside_the_images_and_warns_on_little_overlap():
    img = grid_image(lambda x: x[..., 0] * 0.0 + 0.5, shape=(24, 24, 24))  # world -5.5 .. 18.5
    far_affine = img.affine.copy()
    far_affine[:3, 3] += 500.0
    far = Image(img.data, far_affine)
    mesh = box_mesh((1, 1, 1), size=(10.0, 10.0, 10.0))
    # a mesh outside an image would see only its cval: refused
    with pytest.raises(ValueError, match="no quadrature point of the mesh lies inside f's grid"):
        build_ssd(mesh.nodes, mesh.tets, far, img)
    with pytest.raises(ValueError, match="no quadrature point of the mesh lies inside m's grid"):
        build_ssd(mesh.nodes, mesh.tets, img, far)
    # 6 of the 24 quadrature points of a box from x = 14 to 34 mm lie in the grid (x <= 18.5 mm)
    shifted = box_mesh((1, 1, 1), size=(20.0, 20.0, 20.0), origin=(14.0, 0.0, 0.0))
    with pytest.warns(UserWarning, match=r"only 25\.0% of the mesh's quadrature points lie inside f's grid"):
        build_ssd(shifted.nodes, shifted.tets, img, img)


def test_cubic_interpolation_reads_both_images_by_the_spline_and_its_gradient_is_exact():
    """``interpolation="cubic"``: ``f`` at the fixed points and ``m`` at the displaced ones
    are SciPy's cubic B-spline (``map_coordinates(order=3)``) of each image with a voxel of
    ``cval`` around it; ``E_s``'s gradient passes JAX's finite-difference check; kept over
    the reachable box it equals the whole image's (the spline's wider taps inside the
    margin), and an unknown interpolation is refused."""
    import scipy.ndimage as ndi
    from jax.test_util import check_grads

    from bayesreg.data.interpolation import CUBIC_PAD

    m = box_mesh((2, 2, 2), size=(20.0, 20.0, 20.0))
    rng = np.random.default_rng(6)
    f = grid_image(lambda x: np.sin(0.3 * x[..., 0]) + np.cos(0.2 * x[..., 1] * x[..., 2] / 10))
    mov = grid_image(lambda x: np.sin(0.3 * x[..., 0] + 0.4) * np.cos(0.1 * x[..., 2]))
    term = build_ssd(m.nodes, m.tets, f, mov, quadrature_level=1, interpolation="cubic")
    assert term.interpolation == "cubic"
    pts = np.asarray(term.points).reshape(-1, 3)

    def reference(img, x):
        vox = (x - img.affine[:3, 3]) / np.diag(img.affine)[:3] + 1  # one voxel of cval (0)
        padded = np.pad(np.pad(img.data, 1), CUBIC_PAD, "edge")
        return ndi.map_coordinates(padded, (vox + CUBIC_PAD).T, order=3, mode="mirror")

    np.testing.assert_allclose(np.asarray(term.f_q).reshape(-1), reference(f, pts), atol=1e-10)
    u = jnp.asarray(rng.uniform(-1.5, 1.5, size=(len(m.nodes), 3)))[m.tets]
    moved = np.asarray(term.points + jnp.sum(term.bary[None, :, :, None] * u[:, None], axis=2))
    r = np.asarray(term.f_q).reshape(-1) - reference(mov, moved.reshape(-1, 3))
    assert float(ssd(term, u)) == pytest.approx(float(np.sum(np.asarray(term.sqrt_w).reshape(-1) ** 2 * r**2)),
                                                rel=1e-10)
    check_grads(lambda x: ssd(term, x), (u,), order=1, modes=("rev",))
    allowed = np.zeros(f.data.shape, np.uint8)
    allowed[3:30, 4:31, 2:29] = 1
    kept = build_ssd(m.nodes, m.tets, f, mov, reach=Image(allowed, f.affine), interpolation="cubic")
    whole = build_ssd(m.nodes, m.tets, f, mov, interpolation="cubic")
    a, ga = jax.value_and_grad(lambda x: ssd(whole, x))(u)
    b, gb = jax.value_and_grad(lambda x: ssd(kept, x))(u)
    assert float(b) == pytest.approx(float(a), rel=1e-9)
    np.testing.assert_allclose(np.asarray(gb), np.asarray(ga), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="interpolation must be one of"):
        build_ssd(m.nodes, m.tets, f, mov, interpolation="quintic")
