"""The posterior in the gradient kernels' coordinates (bayesreg.kernels.target)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.kernels.target import make_target
from bayesreg.parameters import from_unconstrained
from bayesreg.posterior import log_density, log_normaliser


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
    assert float(lz) == pytest.approx(float(lnat) + float(from_unconstrained(post.prior, eta)[1]), rel=1e-12)
    cache = tg.build_cache(eta, ln)
    f = jax.jit(lambda w_: tg.u_logdensity(w_, eta, cache, zeros))
    assert float(f(w)) == pytest.approx(float(lp), rel=1e-9)
    g = np.asarray(jax.grad(f)(w))
    d = rng.normal(size=nb3)
    h = 1e-5
    fd = (float(f(w + h * d)) - float(f(w - h * d))) / (2 * h)
    assert float(g @ d) == pytest.approx(fd, rel=1e-5)
