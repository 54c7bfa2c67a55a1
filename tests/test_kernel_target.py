"""The posterior in the gradient kernels' coordinates (bayesreg.sampling.kernels.target)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.sampling.kernels.target import make_target
from bayesreg.model.parameters import from_unconstrained
from bayesreg.model.posterior import log_density, log_normaliser


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


def test_joint_target_moves_the_parameters_with_u_b_and_stores_the_natural_density(small):
    """The joint target: ``z = [w, v]`` maps back to the position; its log-density is the
    Gibbs target's over ``(w, eta)`` (with the log-Jacobian); its gradient in every
    coordinate, the parameters' through the CG solve, matches finite differences; a NUTS
    transition of the kernel stores the natural log-density of where it went."""
    from bayesreg.sampling.kernels import gibbs as gk
    from bayesreg.sampling.kernels.target import joint_target

    _, post, theta = small
    nb3 = 3 * post.n_boundary
    rng = np.random.default_rng(5)
    base = make_target(post, center_u=np.zeros(nb3), factor=0.1 * (1 + rng.random(nb3)), exact=False,
                       condensed=False, rtol=1e-12)
    w, eta = base.coordinates(jnp.asarray(theta))
    jac = lambda e: from_unconstrained(post.prior, e)[1]  # noqa: E731
    tg = joint_target(base, center_eta=eta + 0.05, eta_scale=0.2, log_jacobian=jac)
    assert tg.n_free == 0 and tg.log_jacobian is not None and not tg.condensed
    z, none = tg.coordinates(jnp.asarray(theta))
    assert none.shape == (0,) and z.shape == (nb3 + post.n_free,)
    np.testing.assert_allclose(np.asarray(z[nb3:]), -0.25, rtol=1e-9)  # (eta - (eta + 0.05)) / 0.2
    np.testing.assert_allclose(np.asarray(tg.position(z, none)), theta, rtol=1e-10, atol=1e-12)
    zeros = jnp.zeros((post.op.n_interior, 3))
    cache = tg.build_cache(none, tg.log_norm(none))
    f = jax.jit(lambda z_: tg.u_logdensity(z_, none, cache, zeros))
    lz, lnat, _, _, _ = base.evaluate(w, eta, zeros, base.log_norm(eta))
    lp, _ = log_density(post, jnp.asarray(theta), zeros, rtol=1e-12)
    assert float(f(z)) == pytest.approx(float(lz), rel=1e-12)
    assert float(f(z)) - float(tg.log_jacobian(z)) == pytest.approx(float(lp), rel=1e-9)
    g = np.asarray(jax.grad(f)(z))
    for d in (np.eye(len(z))[-2], rng.normal(size=len(z))):  # one parameter alone, then all
        h = 1e-5
        fd = (float(f(z + h * d)) - float(f(z - h * d))) / (2 * h)
        assert float(g @ d) == pytest.approx(fd, rel=1e-5)
    kernel = gk.build_kernel(tg, "nuts", max_num_doublings=4)
    state, _ = gk.init(tg, jnp.asarray(theta), zeros)
    params = gk.GibbsParams(jnp.asarray(0.05), jnp.ones(len(z)), jnp.zeros((0, 0)))
    step, init_cache = jax.jit(kernel.step), jax.jit(kernel.init_cache)
    for k in range(3):
        state, info, cache = step(jax.random.key(k), state, params, init_cache(state))
    assert bool(info.is_accepted[0]) and info.acceptance_rate.shape == (1,)
    assert not np.allclose(np.asarray(state.position[nb3:]), theta[nb3:])  # the parameters moved
    lp_new, _ = log_density(post, state.position, state.interior, rtol=1e-12)
    assert float(state.logdensity) == pytest.approx(float(lp_new), rel=1e-9)
    with pytest.raises(ValueError, match="center_eta"):
        joint_target(base, center_eta=eta[:2], eta_scale=0.2, log_jacobian=jac)
