"""The elastic parameters' unconstrained coordinates (bayesreg.model.parameters)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.model.parameters import from_unconstrained, to_unconstrained


def test_unconstrained_map_round_trip_and_jacobian(small):
    _, post, theta = small
    phi = jnp.asarray(theta[-5:])
    eta = to_unconstrained(post.prior, phi)
    back, log_jac = from_unconstrained(post.prior, eta)
    np.testing.assert_allclose(np.asarray(back), np.asarray(phi), rtol=1e-12)
    jac = jax.jacfwd(lambda e: from_unconstrained(post.prior, e)[0])(eta)
    assert float(log_jac) == pytest.approx(float(jnp.sum(jnp.log(jnp.diag(jac)))), rel=1e-12)
    # every real eta is a valid parameter, strictly inside the prior support
    far, _ = from_unconstrained(post.prior, jnp.array([-30.0, 30.0, 0.0, -30.0, 30.0]))
    assert np.all(np.asarray(far) > 0) and np.all(np.asarray(far) <= np.asarray(post.prior.r2))
