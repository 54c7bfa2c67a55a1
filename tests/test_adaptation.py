"""The gradient kernels' warm-up (bayesreg.sampling.kernels.adaptation): the elastic block's dense
proposal factor follows the parameters' correlation."""

import numpy as np

import arviz as az
import jax
import jax.numpy as jnp

from helpers import assert_moments, correlated_target, ETA_COV, sample_gibbs


def test_elastic_random_walk_adapts_a_dense_factor_to_correlated_parameters():
    """The warm-up's elastic factor ``L`` follows the parameters' correlation (0.98), and the
    draws recover their covariance within Monte Carlo error."""
    rng = np.random.default_rng(3)
    x0 = np.concatenate([rng.normal(size=(3, 2)), rng.multivariate_normal([0, 0], ETA_COV, size=3)], axis=1)
    res = sample_gibbs(jax.random.key(4), correlated_target(), x0, jnp.zeros((1, 3)), kind="hmc",
                          step_size=0.5, eta_scale=0.05, num_integration_steps=4, warmup_steps=1000,
                          elastic_moves=4, max_draws=2000, min_draws=2000, chunk_draws=100, progress=False)
    factor = res.sigma[2]  # (C, 2, 2)
    cov_prop = factor @ np.swapaxes(factor, 1, 2)
    corr = cov_prop[:, 0, 1] / np.sqrt(cov_prop[:, 0, 0] * cov_prop[:, 1, 1])
    assert np.all(corr > 0.9), corr
    ess = min(float(az.ess(res.positions[..., j], method="bulk")) for j in (2, 3))
    assert ess > 100, ess
    for j in range(2):  # Gaussian marginals: fourth central moment 3 var^2
        var = ETA_COV[j, j]
        assert_moments(res.positions[..., 2 + j], 0.0, var, 3 * var**2, n_se=5.0, what=j)
    acc = res.acceptance.reshape(-1, 2).mean(axis=0)
    assert 0.15 < acc[1] < 0.5, acc  # Robbins-Monro toward 0.3 on top of the dense factor
