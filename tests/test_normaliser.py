"""The exact normaliser of the elastic prior and the unconstrained parameterisation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.fem import stiffness_matrix
from bayesreg.kernels import make_target
from bayesreg.posterior import (
    elastic_groups, from_unconstrained, log_density, log_normaliser, to_unconstrained,
)
from test_posterior import _box_posterior


@pytest.fixture(scope="module")
def small():
    prior = {"lam": (2.0, 3.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
    return _box_posterior(prior, 3.0, np.array([1.0, 10.0, 30.0, 0.5, 1.0]))


def _schur_pdet(mesh, post, phi):
    """(1/2) sum log of the non-zero eigenvalues of the dense Schur complement (NumPy)."""
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, jnp.asarray(phi)))
    g = np.asarray(post.group)
    k = stiffness_matrix(mesh.nodes, mesh.tets, lam_g[g], mu_g[g]).toarray()
    b = np.asarray(mesh.boundary)
    i = np.setdiff1d(np.arange(len(mesh.nodes)), b)
    bd = (3 * b[:, None] + np.arange(3)).ravel()
    idf = (3 * i[:, None] + np.arange(3)).ravel()
    s = k[np.ix_(bd, bd)] - k[np.ix_(bd, idf)] @ np.linalg.solve(k[np.ix_(idf, idf)], k[np.ix_(idf, bd)])
    ev = np.linalg.eigvalsh(s)
    assert np.all(np.abs(ev[:6]) < 1e-8 * ev[-1])  # the six rigid-body modes
    return 0.5 * np.sum(np.log(ev[6:]))


def test_normaliser_equals_half_log_pseudo_determinant_of_the_schur_complement(small):
    mesh, post, theta = small
    phi = theta[-5:]
    for scale in (1.0, 0.3):
        p = phi * np.array([scale, 1, 1, scale, 1])
        assert float(log_normaliser(post, jnp.asarray(p))) == pytest.approx(_schur_pdet(mesh, post, p), rel=1e-10)


def test_normaliser_gradient_matches_finite_differences(small):
    _, post, theta = small
    phi = jnp.asarray(theta[-5:])
    f = jax.jit(lambda p: log_normaliser(post, p))
    g = np.asarray(jax.grad(f)(phi))
    for j in range(5):
        e = np.zeros(5)
        e[j] = 1e-5 * float(phi[j])
        fd = (float(f(phi + e)) - float(f(phi - e))) / (2 * e[j])
        assert g[j] == pytest.approx(fd, rel=1e-6)


def test_unconstrained_map_round_trip_and_jacobian(small):
    _, post, theta = small
    phi = jnp.asarray(theta[-5:])
    eta = to_unconstrained(post, phi)
    back, log_jac = from_unconstrained(post, eta)
    np.testing.assert_allclose(np.asarray(back), np.asarray(phi), rtol=1e-12)
    jac = jax.jacfwd(lambda e: from_unconstrained(post, e)[0])(eta)
    assert float(log_jac) == pytest.approx(float(jnp.sum(jnp.log(jnp.diag(jac)))), rel=1e-12)
    # every real eta is a valid parameter, strictly inside the prior support
    far, _ = from_unconstrained(post, jnp.array([-30.0, 30.0, 0.0, -30.0, 30.0]))
    assert np.all(np.asarray(far) > 0) and np.all(np.asarray(far) <= np.asarray(post.prior_r2))


@pytest.mark.parametrize("condensed", [False, True])
def test_gibbs_target_agrees_with_the_posterior(small, condensed):
    """The kernel's target: natural log-density = log_density + normaliser; the u_b
    gradient in the preconditioned coordinates matches finite differences."""
    _, post, theta = small
    nb3 = 3 * post.n_boundary
    rng = np.random.default_rng(3)
    factor = 0.1 * (1 + rng.random(nb3))
    tg = make_target(post, center_u=np.zeros(nb3), factor=factor, exact=True, condensed=condensed, rtol=1e-12)
    w, eta = tg.coordinates(jnp.asarray(theta))
    np.testing.assert_allclose(np.asarray(tg.position(w, eta)), theta, rtol=1e-10, atol=1e-12)
    zeros = jnp.zeros((post.op.n_interior, 3))
    ln = tg.log_norm(eta)
    lz, lnat, _, _, ok = tg.evaluate(w, eta, zeros, ln)
    lp, _ = log_density(post, jnp.asarray(theta), zeros, rtol=1e-12)
    assert bool(ok)
    assert float(lnat) == pytest.approx(float(lp) + float(log_normaliser(post, jnp.asarray(theta[-5:]))), rel=1e-9)
    assert float(lz) == pytest.approx(float(lnat) + float(from_unconstrained(post, eta)[1]), rel=1e-12)
    cache = tg.build_cache(eta, ln)
    f = jax.jit(lambda w_: tg.u_logdensity(w_, eta, cache, zeros))
    assert float(f(w)) == pytest.approx(float(lp), rel=1e-9)
    g = np.asarray(jax.grad(f)(w))
    d = rng.normal(size=nb3)
    h = 1e-5
    fd = (float(f(w + h * d)) - float(f(w - h * d))) / (2 * h)
    assert float(g @ d) == pytest.approx(fd, rel=1e-5)
