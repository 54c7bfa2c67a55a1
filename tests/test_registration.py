"""Optical-flow start: sign convention, accuracy on a known warp, field interpolation."""

import numpy as np
import pytest

from bayesreg.data.images import Image
from bayesreg.data.registration import displacement_at, optical_flow_displacement


def _blobs(rng, n_blobs, low, high, sigma):
    """A smooth random texture: sum of Gaussian blobs, a function of (..., 3) points."""
    centres = rng.uniform(low, high, size=(n_blobs, 3))
    sig = rng.uniform(*sigma, size=n_blobs)
    amp = rng.uniform(-1.0, 1.0, size=n_blobs)

    def g(x):
        d2 = np.sum((x[..., None, :] - centres) ** 2, axis=-1)
        return np.exp(-d2 / (2 * sig**2)) @ amp

    return g


def _world(affine, shape):
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    return ijk @ affine[:3, :3].T + affine[:3, 3]


def test_sign_convention_translation_with_flipped_permuted_axes():
    # 2 mm voxels; array axis 0 runs along world y, axis 1 along -x (flipped), axis 2 along z
    n = 32
    aff = np.array([[0.0, -2.0, 0.0, 40.0],
                    [2.0, 0.0, 0.0, -30.0],
                    [0.0, 0.0, 2.0, -35.0],
                    [0.0, 0.0, 0.0, 1.0]])
    x = _world(aff, (n, n, n))
    lo, hi = x.reshape(-1, 3).min(0), x.reshape(-1, 3).max(0)
    g = _blobs(np.random.default_rng(2), 200, lo - 6, hi + 6, (4.0, 7.0))
    t = np.array([2.0, 0.0, 0.0])
    f = Image(g(x), aff)
    m = Image(g(x - t), aff)  # the content of f moved by +2 mm along world x: m(x + t) = f(x)
    u = optical_flow_displacement(f, m)
    assert u.data.shape == (n, n, n, 3)
    np.testing.assert_array_equal(u.affine, aff)
    inner = u.data[5:-5, 5:-5, 5:-5].reshape(-1, 3)
    np.testing.assert_allclose(np.median(inner, axis=0), t, atol=0.1)
    assert np.sqrt(np.mean(np.sum((inner - t) ** 2, axis=1))) < 0.4  # mm, a fifth of a voxel


def test_recovers_a_smooth_displacement():
    n = 40
    aff = np.diag([1.0, 1.0, 1.0, 1.0])
    aff[:3, 3] = [-20.0, -15.0, -25.0]
    x = _world(aff, (n, n, n))
    p = x - aff[:3, 3]  # position inside the box, 0..39 mm
    u_true = 1.5 * np.stack([np.sin(p[..., 1] / 9.0), 0.8 * np.cos(p[..., 2] / 11.0),
                             np.sin((p[..., 0] + p[..., 1]) / 13.0)], -1)
    g = _blobs(np.random.default_rng(0), 250, aff[:3, 3] - 3, aff[:3, 3] + n + 2, (2.0, 3.5))
    m = Image(g(x), aff)
    f = Image(g(x + u_true), aff)  # m(x + u(x)) = f(x) exactly
    sl = (slice(6, -6),) * 3
    err0 = np.linalg.norm(u_true[sl], axis=-1)
    for method, rms_tol, max_tol in (("tvl1", 0.3, 0.75), ("ilk", 0.5, 1.5)):
        u = optical_flow_displacement(f, m, method=method)
        err = np.linalg.norm(u.data[sl] - u_true[sl], axis=-1)
        rms = np.sqrt(np.mean(err**2))
        assert rms < rms_tol and err.max() < max_tol, (method, rms, err.max())
        assert rms < 0.35 * np.sqrt(np.mean(err0**2))


def test_a_masked_flow_on_the_masks_box_agrees_with_the_whole_grids():
    """With a mask the flow is computed on its bounding box grown by ``margin`` voxels (8: a
    box of 30-36 voxels in a grid of 40): inside
    the mask it recovers the truth as well as the whole grid's flow does and stays within a
    tenth of a voxel (rms) of it; ``margin=None`` is the whole grid."""
    n = 40
    aff = np.diag([1.0, 1.0, 1.0, 1.0])
    x = _world(aff, (n, n, n))
    u_true = 1.2 * np.stack([np.sin(x[..., 1] / 9.0), 0.8 * np.cos(x[..., 2] / 11.0),
                             np.sin((x[..., 0] + x[..., 1]) / 13.0)], -1)
    g = _blobs(np.random.default_rng(0), 250, -3, n + 2, (2.0, 3.5))
    m, f = Image(g(x), aff), Image(g(x + u_true), aff)
    mask = np.zeros((n, n, n), bool)
    mask[12:28, 10:30, 13:27] = True
    box = optical_flow_displacement(f, m, mask=mask, margin=8)
    full = optical_flow_displacement(f, m, mask=mask, margin=None)
    assert np.all(box.data[~mask] == 0)

    def rms(a):
        return float(np.sqrt(np.mean(np.sum(a[mask] ** 2, axis=-1))))

    assert rms(box.data - u_true) < 0.3 and rms(box.data - u_true) < 1.2 * rms(full.data - u_true)
    assert rms(box.data - full.data) < 0.1, rms(box.data - full.data)
    with pytest.raises(ValueError, match="margin"):
        optical_flow_displacement(f, m, mask=mask, margin=-1)


def test_mask_and_errors():
    n = 20
    rng = np.random.default_rng(1)
    g = _blobs(rng, 60, -3, n + 2, (2.0, 3.0))
    x = _world(np.eye(4), (n, n, n))
    f = Image(g(x), np.eye(4))
    m = Image(g(x - [1.0, 0.0, 0.0]), np.eye(4))
    mask = np.zeros((n, n, n), bool)
    mask[5:15, 5:15, 5:15] = True
    u = optical_flow_displacement(f, m, mask=mask, num_warp=2)
    assert np.all(u.data[~mask] == 0) and np.any(u.data[mask] != 0)
    with pytest.raises(ValueError, match="affines disagree"):
        optical_flow_displacement(f, Image(m.data, np.diag([2.0, 1.0, 1.0, 1.0])))
    with pytest.raises(ValueError, match="different grids"):
        optical_flow_displacement(f, Image(m.data[:-1], m.affine))
    with pytest.raises(ValueError, match="unknown optical-flow method"):
        optical_flow_displacement(f, m, method="demons")
    with pytest.raises(ValueError, match="mask shape"):
        optical_flow_displacement(f, m, mask=mask[:-1])


def test_displacement_at_is_exact_on_a_linear_field():
    aff = np.array([[0.0, -1.5, 0.2, 10.0],
                    [1.2, 0.0, 0.0, -4.0],
                    [0.0, 0.3, 2.0, 3.0],
                    [0.0, 0.0, 0.0, 1.0]])
    shape = (12, 10, 9)
    a = np.array([[0.1, -0.2, 0.05], [0.0, 0.3, -0.1], [0.2, 0.1, 0.0]])
    b = np.array([1.0, -2.0, 0.5])
    field = Image(_world(aff, shape) @ a.T + b, aff)
    rng = np.random.default_rng(4)
    ijk = rng.uniform(0, np.array(shape) - 1, size=(200, 3))
    pts = ijk @ aff[:3, :3].T + aff[:3, 3]
    got = displacement_at(field, pts)
    assert got.shape == (200, 3)
    np.testing.assert_allclose(got, pts @ a.T + b, atol=1e-10)
    assert displacement_at(field, pts.reshape(20, 10, 3)).shape == (20, 10, 3)
    with pytest.raises(ValueError, match=r"\(I, J, K, 3\)"):
        displacement_at(Image(field.data[..., 0], aff), pts)


def _ants():
    try:
        import ants  # noqa: F401
    except Exception as exc:  # pragma: no cover - depends on the platform's wheel
        pytest.skip(f"ANTsPy is not installed here ({type(exc).__name__}: {exc}); the test "
                    "extra installs it on Linux x86_64 only")


def test_syn_gives_the_packages_displacement_on_flipped_permuted_axes():
    """ANTs SyN read back in the package's convention, ``m(x + u(x)) ~= f(x)``: on a grid whose
    axes are permuted and flipped (LPS and RAS, voxel and world), a translation of 2 mm along
    world x comes out along +x (SyN's regularised solution overshoots a one-voxel shift by
    about a tenth; ANTs' own warped image agrees), and pulling ``m`` back through the field
    leaves under 40% of the intensity residual; a smooth field is recovered within 40% rms."""
    from bayesreg.data.images import interpolate_numpy

    _ants()
    from bayesreg.interop.syn import syn_displacement

    n = 32
    aff = np.array([[0.0, -2.0, 0.0, 40.0], [2.0, 0.0, 0.0, -30.0], [0.0, 0.0, 2.0, -35.0],
                    [0.0, 0.0, 0.0, 1.0]])
    x = _world(aff, (n, n, n))
    lo, hi = x.reshape(-1, 3).min(0), x.reshape(-1, 3).max(0)
    g = _blobs(np.random.default_rng(2), 200, lo - 6, hi + 6, (4.0, 7.0))
    t = np.array([2.0, 0.0, 0.0])
    f, m = Image(g(x), aff), Image(g(x - t), aff)
    u = syn_displacement(f, m)
    np.testing.assert_array_equal(u.affine, aff)
    sl = (slice(5, -5),) * 3
    ux, uy, uz = np.median(u.data[sl].reshape(-1, 3), axis=0)
    assert 1.8 < ux < 2.5 and abs(uy) < 0.3 and abs(uz) < 0.3, (ux, uy, uz)  # 2.24, -0.14, -0.01 seen
    pulled = interpolate_numpy(m, x + u.data, order=1)
    rms = np.sqrt(np.mean((pulled - f.data)[sl] ** 2))
    assert rms < 0.4 * np.sqrt(np.mean((m.data - f.data)[sl] ** 2))  # with -u: above 1

    n = 40
    aff = np.diag([1.0, 1.0, 1.0, 1.0])
    aff[:3, 3] = [-20.0, -15.0, -25.0]
    x = _world(aff, (n, n, n))
    p = x - aff[:3, 3]
    u_true = 1.5 * np.stack([np.sin(p[..., 1] / 9.0), 0.8 * np.cos(p[..., 2] / 11.0),
                             np.sin((p[..., 0] + p[..., 1]) / 13.0)], -1)
    g = _blobs(np.random.default_rng(0), 250, aff[:3, 3] - 3, aff[:3, 3] + n + 2, (2.0, 3.5))
    f, m = Image(g(x + u_true), aff), Image(g(x), aff)
    mask = np.zeros((n,) * 3, bool)
    mask[6:-6, 6:-6, 6:-6] = True
    u = syn_displacement(f, m, mask=mask, margin=4)
    err = np.linalg.norm(u.data[mask] - u_true[mask], axis=-1)
    rms0 = np.sqrt(np.mean(np.sum(u_true[mask] ** 2, axis=-1)))
    assert np.sqrt(np.mean(err**2)) < 0.4 * rms0, (np.sqrt(np.mean(err**2)), rms0)  # 0.31 seen
    assert np.all(u.data[~mask] == 0.0)


def test_syn_without_antspy_says_what_to_install(monkeypatch):
    import sys

    from bayesreg.config import ConfigError, load_config
    from bayesreg.interop.syn import syn_displacement
    from bayesreg.pipeline import check_optional_packages

    monkeypatch.setitem(sys.modules, "ants", None)  # import ants raises ImportError
    f = Image(np.zeros((8, 8, 8)), np.eye(4))
    with pytest.raises(ImportError, match=r"pip install 'bayesreg\[ants\]'"):
        syn_displacement(f, f)
    cfg = load_config(None, overrides=["output.reference=syn"])
    monkeypatch.setattr("importlib.util.find_spec", lambda name, *a: None)
    with pytest.raises(ConfigError, match="output.reference: syn needs ANTsPy"):
        check_optional_packages(cfg)
    check_optional_packages(load_config(None, overrides=["output.reference=true"]))


@pytest.mark.slow
def test_a_registration_start_on_an_fe_truth_registers_the_images_that_were_made():
    """The quickstart's FE truth at 3 mm on a head: a bright skull and scalp added around the
    brain of ``f`` (the MNI152 template has none; BrainWeb has them), ``m`` that ``f`` warped
    and continued outside the brain (``synthetic.outside: extend``, the default).
    :func:`registration_field` registers both images whole, and TV-L1 lands near the truth
    at the brain's surface nodes.  Masking ``f`` to its brain against that ``m`` (what
    ``outside="background"``, for an ``m`` made with a zero background, asks for) pulls the
    surface toward the skull that only ``m`` shows: errors several times larger."""
    import scipy.ndimage as ndi

    from bayesreg.config import load_config
    from bayesreg.data import labels as L
    from bayesreg.inference.initialisation import registration_field
    from bayesreg.mesh.warp import warp_image
    from bayesreg.model.problem import SYNTHETIC_ORDER, assemble, make_data

    cfg = load_config("configs/quickstart.yaml", overrides=["data.resolution_mm=3.0",
                                                            "mesh.edge_length_mm=26"])
    assert cfg.synthetic.outside == "extend"
    data = make_data(cfg)
    brain = np.isin(data.labels.data, L.TISSUE_LABELS)
    near = ndi.binary_dilation(brain, iterations=2)
    head = (ndi.binary_dilation(brain, iterations=5) & ~near).astype(float)
    f = Image(data.f.data + 1.5 * np.percentile(data.f.data[brain], 99) * head, data.f.affine)
    m = warp_image(f, data.mesh, data.truth.u, background=0.0, outside="extend", order=SYNTHETIC_ORDER)
    problem = assemble(cfg, data._replace(f=f, m=m))
    surface = problem.mesh.nodes[problem.mesh.boundary]
    truth = problem.truth.u[problem.mesh.boundary]

    def error(outside):
        flow = registration_field(problem, "tvl1", outside=outside)
        return np.median(np.linalg.norm(displacement_at(flow, surface) - truth, axis=1))

    whole, masked = error("extend"), error("background")
    assert whole < 3.0 and masked > 4 * whole, (whole, masked)
    with pytest.raises(ValueError, match="synthetic.outside"):
        registration_field(problem, "tvl1", outside="constant")
