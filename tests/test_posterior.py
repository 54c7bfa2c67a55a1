"""The log-density: hard constraints give -inf; gradients match finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi

from bayesreg.images import Image
from bayesreg.posterior import ParamLayout, build_posterior, log_density, split_position
from bayesreg.similarity import build_ssd
from conftest import box_mesh


@pytest.fixture(scope="module")
def small():
    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    rng = np.random.default_rng(0)
    shape = (48, 48, 48)
    affine = np.diag([1.0, 1.0, 1.0, 1.0])
    affine[:3, 3] = -9.0
    f = Image(ndi.gaussian_filter(rng.random(shape), 2.0) * 4, affine)
    m = Image(np.roll(f.data, 1, axis=0), affine)
    # skull: everything with world x > 36 mm
    x = np.arange(shape[0]) - 9.0
    forbidden = Image(np.broadcast_to((x > 36.0)[:, None, None], shape).astype(np.uint8), affine)
    layout = ParamLayout(("csf", "gm", "wm"),
                         free=(("lam", 0), ("lam", 1), ("lam", 2), ("mu", 0), ("mu", 2)),
                         fixed=(("mu", 1, 1.0),))
    prior = {"lam": (2.0, 3.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
    phi = np.array([1.0, 10.0, 30.0, 0.5, 1.0])
    post = build_posterior(mesh, build_ssd(mesh.nodes, mesh.tets, f, m), forbidden, t_s=0.5,
                           t_r=3.0, layout=layout, element_group=mesh.tissue, prior=prior,
                           phi_ref=phi)
    theta = np.concatenate([0.3 * rng.normal(size=3 * len(mesh.boundary)), phi])
    return mesh, post, theta


def _lp(post, theta):
    return log_density(post, jnp.asarray(theta), jnp.zeros((post.op.n_interior, 3)), rtol=1e-12)


def test_finite_at_valid_point_and_matches_energies(small):
    mesh, post, theta = small
    lp, aux = _lp(post, theta)
    assert np.isfinite(float(lp)) and bool(aux.solve.converged)
    # prior: Beta(2,3) on [0,100] for lam, uniform on [0,10] for mu
    from scipy import stats

    lam = theta[-5:-2]
    mu = theta[-2:]
    lprior = stats.beta(2, 3).logpdf(lam / 100).sum() - 3 * np.log(100) - 2 * np.log(10)
    expected = -float(aux.e_s) / 0.5 - float(aux.e_r) / 3.0 + lprior
    assert float(lp) == pytest.approx(expected, rel=1e-10)
    assert float(aux.e_r) > 0 and float(aux.e_s) > 0


def test_constraint_violations_give_minus_inf(small):
    mesh, post, theta = small
    nb3 = 3 * len(mesh.boundary)
    # a non-positive parameter
    t = theta.copy()
    t[nb3 + 3] = -0.1
    assert float(_lp(post, t)[0]) == -np.inf
    # outside the prior range [r1, r2]
    t = theta.copy()
    t[nb3] = 150.0
    assert float(_lp(post, t)[0]) == -np.inf
    # a boundary node moved into the skull (x > 36 mm)
    t = theta.copy()
    k = int(np.argmax(mesh.nodes[mesh.boundary, 0]))
    t[3 * k] = 8.0
    assert float(_lp(post, t)[0]) == -np.inf
    # an inverted element: push one corner through the opposite face
    t = theta.copy()
    corner = int(np.flatnonzero(np.all(mesh.nodes[mesh.boundary] == 0.0, axis=1))[0])
    t[3 * corner: 3 * corner + 3] = [25.0, 25.0, 25.0]
    assert float(_lp(post, t)[0]) == -np.inf


def test_nonconverged_solve_gives_minus_inf(small):
    _, post, theta = small
    lp, aux = log_density(post, jnp.asarray(theta), jnp.zeros((post.op.n_interior, 3)), maxiter=2)
    assert not bool(aux.solve.converged) and float(lp) == -np.inf


def test_gradient_finite_and_equal_to_finite_differences(small):
    _, post, theta = small
    f = jax.jit(lambda th: _lp(post, th)[0])
    g = np.asarray(jax.grad(f)(jnp.asarray(theta)))
    assert np.all(np.isfinite(g))
    rng = np.random.default_rng(5)
    for _ in range(3):
        d = rng.normal(size=theta.shape)
        d[-5:] *= 0.1
        h = 1e-6
        fd = (float(f(theta + h * d)) - float(f(theta - h * d))) / (2 * h)
        assert float(g @ d) == pytest.approx(fd, rel=1e-4, abs=1e-6)
    # derivative with respect to one elastic parameter alone (through K_ii in the solve)
    e = np.zeros_like(theta)
    e[-4] = 1.0
    h = 1e-5
    fd = (float(f(theta + h * e)) - float(f(theta - h * e))) / (2 * h)
    assert g[-4] == pytest.approx(fd, rel=1e-4)


def test_split_position_is_node_major(small):
    mesh, post, theta = small
    u_b, phi = split_position(post, jnp.asarray(theta))
    assert u_b.shape == (len(mesh.boundary), 3)
    assert float(u_b[1, 2]) == theta[3 * 1 + 2]
    assert phi.shape == (5,)


def test_bad_temperatures_and_priors_raise(small):
    mesh, post, _ = small
    from bayesreg.similarity import SSDTerm  # noqa: F401

    kw = dict(layout=ParamLayout(("all",), (("lam", 0),), (("mu", 0, 1.0),)),
              element_group=np.zeros(len(mesh.tets), int), prior={"lam": (1, 1, 0, 10), "mu": (1, 1, 0, 1)},
              phi_ref=[5.0])
    forb = Image(np.zeros((4, 4, 4), np.uint8), np.eye(4))
    with pytest.raises(ValueError, match="temperatures"):
        build_posterior(mesh, post.ssd, forb, t_s=0.0, t_r=1.0, **kw)
    with pytest.raises(ValueError, match="outside the prior support"):
        build_posterior(mesh, post.ssd, forb, t_s=1.0, t_r=1.0, **{**kw, "phi_ref": [50.0]})
