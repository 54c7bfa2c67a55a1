"""The LNCC similarity term: its windows, its value against a NumPy/SciPy reference, its
gradient, and an image pair of other intensities where SSD fails and LNCC finds the truth."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage as ndi
import scipy.optimize as opt

import jax
import jax.numpy as jnp

from bayesreg.data.images import Image
from bayesreg.mesh.tetmesh import box_mesh
from bayesreg.model.lncc import OVERLAP, build_lncc, lncc_windows
from bayesreg.model.similarity import build_ssd, gauss_points, residual_gram

SHAPE = (40, 40, 40)


def _pattern(x):
    """A smooth image of world points ``x`` ``(..., 3)`` (1 mm voxels, identity affine)."""
    return (np.sin(x[..., 0] / 3.0) + np.cos(x[..., 1] / 4.0) * np.sin(x[..., 2] / 5.0)
            + 0.02 * x[..., 2])


def _grid():
    return np.moveaxis(np.indices(SHAPE).astype(float), 0, -1)


def _images(shift, intensity=lambda v, x: v):
    """``f`` and ``m(y) = intensity(f(y - shift), y)``: ``m(x + shift) = f(x)`` up to the
    intensity change."""
    x = _grid()
    f = Image(_pattern(x), np.eye(4))
    m = Image(intensity(_pattern(x - np.asarray(shift)), x), np.eye(4))
    return f, m


def test_windows_are_the_cubes_around_their_centres():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 20, (600, 3))
    w = rng.uniform(0.5, 1.5, 600)
    window, point, a, wk = lncc_windows(pts, w, 6.0, min_points=1)
    step = 3.0
    centres = np.stack(np.meshgrid(*[np.arange(pts[:, d].min(), pts[:, d].max() + step, step)
                                     for d in range(3)], indexing="ij"), -1).reshape(-1, 3)
    brute = [np.flatnonzero(np.max(np.abs(pts - c), axis=1) < step) for c in centres]
    brute = sorted(tuple(sorted(b)) for b in brute if len(b))
    got = sorted(tuple(sorted(point[window == k])) for k in range(len(wk)))
    assert got == brute and np.all(np.diff(window) >= 0)
    np.testing.assert_allclose(np.bincount(window, weights=a), 1.0)
    # every point lies in at most OVERLAP windows; the weights add up to the points' volume
    assert np.bincount(point, minlength=600).max() <= OVERLAP
    assert wk.sum() == pytest.approx(w.sum(), rel=0.3)


def test_windows_refuse_a_window_too_small():
    with pytest.raises(ValueError, match="too small for the quadrature"):
        lncc_windows(np.random.default_rng(0).uniform(0, 50, (30, 3)), np.ones(30), 2.0)
    with pytest.raises(ValueError, match="finite and > 0"):
        lncc_windows(np.zeros((3, 3)), np.ones(3), 0.0)


def _reference(term, mesh, m, u):
    """E from SciPy's trilinear interpolation and NumPy loops over the windows."""
    pts, wq = gauss_points(mesh.nodes, mesh.tets, 1)
    from bayesreg.model.similarity import quadrature_rule
    bary, _ = quadrature_rule(1)
    u_q = np.einsum("qa,mad->mqd", bary, u[mesh.tets])
    y = (pts + u_q).reshape(-1, 3)
    mv = ndi.map_coordinates(m.data, y.T, order=1, mode="constant", cval=0.0)
    fv = np.asarray(term.quad.f_q).ravel()
    window, point, a = np.asarray(term.window), np.asarray(term.point), np.asarray(term.a)
    eps = float(term.eps)
    total = 0.0
    for k in range(len(np.asarray(term.sqrt_w))):
        sel = window == k
        ak, fk, mk = a[sel], fv[point[sel]], mv[point[sel]]
        ft, mt = fk - ak @ fk, mk - ak @ mk
        vf, vm, c = ak @ ft**2, ak @ mt**2, ak @ (ft * mt)
        rho = c / np.sqrt((vf + eps) * (vm + eps))
        wk = wq.ravel()[point[sel]].sum() / OVERLAP
        total += wk * (vm / (vm + eps) - 2 * rho**2 + rho**2 * vf / (vf + eps))
    return total


def test_value_matches_a_numpy_reference_and_the_gradient_finite_differences():
    mesh = box_mesh((3, 3, 3), (24.0, 24.0, 24.0), origin=(6.0, 6.0, 6.0))
    f, m = _images((1.0, -0.5, 0.7), lambda v, x: (1 + 0.01 * x[..., 0]) * (2.0 - 0.7 * v))
    term = build_lncc(mesh.nodes, mesh.tets, f, m, window_mm=8.0, eps=1e-4)
    rng = np.random.default_rng(1)
    u = rng.normal(0, 0.6, mesh.nodes.shape)
    e = float(term.energy(jnp.asarray(u)[mesh.tets]))
    assert e == pytest.approx(_reference(term, mesh, m, u), rel=1e-10)
    # 0 <= E <= sum W_k, and E is the sum of squared residuals
    assert 0 < e < float(jnp.sum(term.sqrt_w**2))
    assert float(jnp.sum(term.residuals(jnp.asarray(u)[mesh.tets]) ** 2)) == pytest.approx(e, rel=1e-12)
    fn = jax.jit(lambda v: term.energy(v[jnp.asarray(mesh.tets)]))
    g = np.asarray(jax.grad(fn)(jnp.asarray(u)))
    d = rng.normal(size=u.shape)
    h = 1e-5
    fd = (float(fn(jnp.asarray(u + h * d))) - float(fn(jnp.asarray(u - h * d)))) / (2 * h)
    assert float(np.sum(g * d)) == pytest.approx(fd, rel=1e-5)


def test_gram_matches_the_jacobian():
    """LNCC's structured Gram matrix and the generic column-by-column one equal ``J^T J`` of
    the residuals' Jacobian (``jax.jacfwd``)."""
    mesh = box_mesh((2, 2, 2), (20.0, 20.0, 20.0), origin=(8.0, 8.0, 8.0))
    f, m = _images((0.5, 0.0, 0.0))
    term = build_lncc(mesh.nodes, mesh.tets, f, m, window_mm=10.0)
    u = np.random.default_rng(2).normal(0, 0.3, mesh.nodes.shape)
    tets = jnp.asarray(mesh.tets)
    jac = jax.jacfwd(lambda v: term.residuals(v.reshape(-1, 3)[tets]).ravel())(jnp.asarray(u.ravel()))
    gram = term.gram(jnp.asarray(u), tets, len(mesh.nodes)).toarray()
    np.testing.assert_allclose(gram, np.asarray(jac.T @ jac), rtol=1e-9, atol=1e-12)
    # the generic fallback for a term without a structure of its own
    generic = residual_gram(lambda v: term.residuals(v[tets]), jnp.asarray(u), batch=16).toarray()
    np.testing.assert_allclose(generic, np.asarray(jac.T @ jac), rtol=1e-9, atol=1e-12)


def test_lncc_finds_the_shift_under_a_bias_field_and_another_contrast_where_ssd_fails():
    """m is f shifted by ``t`` mm, times a smooth bias field, with its contrast inverted
    (another MR weighting): minimising over a rigid shift of the mesh, SSD lands far from
    ``t``, LNCC within 0.15 mm of it (the bias changes by 12% across a window, so m is not
    exactly an affine function of f there: 0.11 mm off along the bias's axis)."""
    t = np.array([1.5, -1.0, 0.8])
    change = lambda v, x: (0.7 + 0.6 * x[..., 0] / 40.0) * (2.5 - v)  # noqa: E731
    f, m = _images(t, change)
    mesh = box_mesh((3, 3, 3), (24.0, 24.0, 24.0), origin=(8.0, 8.0, 8.0))
    tets = jnp.asarray(mesh.tets)
    kw = dict(quadrature_level=1, interpolation="cubic")
    terms = {"ssd": build_ssd(mesh.nodes, mesh.tets, f, m, **kw),
             "lncc": build_lncc(mesh.nodes, mesh.tets, f, m, window_mm=8.0, **kw)}
    found = {}
    for name, term in terms.items():
        fn = jax.jit(jax.value_and_grad(
            lambda s: term.energy(jnp.broadcast_to(s, (len(mesh.nodes), 3))[tets])))
        res = opt.minimize(lambda s: tuple(np.asarray(v, float) for v in fn(jnp.asarray(s))),
                           np.zeros(3), jac=True, method="L-BFGS-B")
        found[name] = res.x
    assert np.linalg.norm(found["lncc"] - t) < 0.15, found
    assert np.linalg.norm(found["ssd"] - t) > 1.0, found


def test_the_config_selects_the_term_and_its_temperature(tiny_mesh):
    """``model.similarity: lncc`` builds the LNCC term with ``model.lncc``'s window and
    temperature; the log-density is finite at rest; the SSD's integrated temperature is
    refused with another term, naming the keys."""
    from bayesreg import configure_jax
    from bayesreg.config import ConfigError, load_config
    from bayesreg.model.posterior import log_density
    from bayesreg.model.problem import assemble, make_data

    configure_jax()
    over = ["data.resolution_mm=3.0", f"mesh.file={tiny_mesh}", "model.similarity=lncc",
            "model.lncc.window_mm=12", "model.lncc.t_s=0.02"]
    cfg = load_config("configs/quickstart.yaml", overrides=over)
    problem = assemble(cfg, make_data(cfg))
    post = problem.posterior
    assert post.similarity.kind == "lncc" and float(post.inv_t_s) == pytest.approx(50.0)
    theta = np.concatenate([np.zeros(3 * post.n_boundary), problem.phi_init])
    logp, aux = log_density(post, jnp.asarray(theta), jnp.zeros((post.op.n_interior, 3)))
    assert np.isfinite(float(logp)) and 0 < float(aux.e_s) < float(jnp.sum(post.similarity.sqrt_w**2))
    with pytest.raises(ConfigError, match="t_s_prior.*similarity: ssd"):
        load_config("configs/quickstart.yaml",
                    overrides=over + ["model.t_s_prior.shape=1", "model.t_s_prior.rate=1"])
