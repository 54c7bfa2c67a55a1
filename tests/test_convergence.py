"""The stopping rule's statistic (bayesreg.sampling.convergence): classic and split R-hat on known
cases, in blocks, and running over chunks."""

import numpy as np
import pytest

from bayesreg.sampling.convergence import RunningGelmanRubin, gelman_rubin


def test_gelman_rubin_known_cases():
    rng = np.random.default_rng(0)
    iid = rng.normal(size=(4, 2000, 3))
    assert np.all(np.abs(gelman_rubin(iid) - 1) < 0.01)
    shifted = iid + np.array([0.0, 0.0, 3.0, 3.0])[:, None, None]
    assert np.all(gelman_rubin(shifted) > 1.5)
    # the formula: W = mean within variance, B/n = variance of means
    x = rng.normal(size=(3, 50))
    n = 50
    w = x.var(1, ddof=1).mean()
    var_plus = (n - 1) / n * w + x.mean(1).var(ddof=1)
    assert gelman_rubin(x) == pytest.approx(np.sqrt(var_plus / w))
    with pytest.raises(ValueError):
        gelman_rubin(np.zeros((1, 10)))


def test_split_rhat_detects_a_common_drift():
    rng = np.random.default_rng(5)
    trend = np.linspace(0.0, 5.0, 1000)
    drifting = rng.normal(size=(3, 1000)) + trend  # every chain drifts the same way
    assert gelman_rubin(drifting) < 1.01  # whole-chain R-hat is blind to it
    assert gelman_rubin(drifting, split=True) > 1.2  # the stopping threshold catches it
    assert abs(gelman_rubin(rng.normal(size=(3, 1000)), split=True) - 1) < 0.01


@pytest.mark.parametrize("split", [False, True])
def test_running_rhat_equals_the_statistic_of_the_concatenated_draws(split):
    """Chunks of different lengths (an odd total, halves that cut a chunk), estimands that
    map draws to other scalars, a chain that never moves: the running statistic is the
    direct one to rounding."""
    rng = np.random.default_rng(5)
    x = rng.normal(size=(3, 47, 4)) + np.arange(3)[:, None, None] * 0.3
    x[:, :, 3] = 2.0  # identical everywhere: R-hat 1
    est = lambda d: np.concatenate([d, d[..., :1] * d[..., 1:2]], axis=-1)  # noqa: E731
    monitor = RunningGelmanRubin(est)
    with pytest.raises(ValueError, match="draws"):
        monitor.rhat(split=split)
    start = 0
    for n in (5, 1, 12, 7, 9, 13):
        monitor.add(x[:, start:start + n])
        start += n
        if start >= 4:
            np.testing.assert_allclose(monitor.rhat(split=split), gelman_rubin(est(x[:, :start]), split=split),
                                       rtol=1e-12)
    assert monitor.n_draws == 47 and monitor.rhat(split=split)[3] == 1.0


@pytest.mark.parametrize("block", [1, 3, 1000])
def test_blocked_rhat_equals_whole(block):
    """R-hat computed over blocks of estimands (of a strided view, of an estimand array of
    several axes) equals the R-hat of all estimands at once."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(3, 200, 40)) + rng.normal(0.0, 0.3, (3, 1, 40))
    view = np.concatenate([x, rng.normal(size=(3, 200, 5))], axis=-1)[..., :40]  # strided
    for split in (False, True):  # equal up to the order of summation
        np.testing.assert_allclose(gelman_rubin(view, split=split, block=block),
                                   gelman_rubin(x, split=split, block=10**6), rtol=1e-14)
    two = gelman_rubin(x.reshape(3, 200, 8, 5), block=block)
    assert two.shape == (8, 5)
    np.testing.assert_allclose(two.ravel(), gelman_rubin(x, block=block), rtol=1e-14)
