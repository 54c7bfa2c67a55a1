"""Posterior field statistics over chunks of draws (bayesreg.outputs.fields).

A run of the paper's size stores 3 x 25,000 draws; the displacement statistics are
accumulated chunk by chunk and must equal those of all draws held at once.
"""

from __future__ import annotations

import numpy as np
import pytest

from bayesreg.outputs import fields
from helpers import fake_run


@pytest.mark.parametrize("chunk", [1, 7, 4096])
def test_nodal_statistics_over_chunks_equal_all_draws(monkeypatch, chunk):
    mesh, problem, result, draws = fake_run()
    monkeypatch.setattr(fields, "CHUNK_DRAWS", chunk)
    np.testing.assert_array_equal(fields.nodal_draws(problem, result, slice(None)), draws)
    np.testing.assert_array_equal(fields.nodal_draws(problem, result, slice(5, None, 9)),
                                  draws[5::9])
    mean = fields.nodal_mean(problem, result)
    np.testing.assert_allclose(mean, draws.mean(0), rtol=1e-13, atol=1e-13)
    cov, sd, norm_sd, norm_iqr = fields.nodal_spread(problem, result, mean, block=5)
    centred = draws - draws.mean(0)
    for a in range(3):
        np.testing.assert_allclose(cov[a], centred[:, :, a].T @ centred[:, :, a] / len(draws),
                                   rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(sd, draws.std(0), rtol=1e-12)
    norm = np.linalg.norm(draws, axis=2)
    np.testing.assert_allclose(norm_sd, norm.std(0), rtol=1e-12)
    np.testing.assert_allclose(norm_iqr, np.subtract(*np.quantile(norm, [0.75, 0.25], axis=0)),
                               rtol=1e-12)


def test_nodal_statistics_in_one_thread_when_memory_is_short(monkeypatch):
    """Above the accumulators' byte budget the covariances are summed in one thread; the
    figures are those of the threaded sum."""
    _, problem, result, _ = fake_run()
    monkeypatch.setattr(fields, "CHUNK_DRAWS", 7)
    monkeypatch.setattr(fields, "available_cores", lambda: 3)  # three threads whatever the machine
    mean = fields.nodal_mean(problem, result)
    threaded = fields.nodal_spread(problem, result, mean)
    monkeypatch.setattr(fields, "SPREAD_MAX_BYTES", 1)
    single = fields.nodal_spread(problem, result, mean)
    for a, b in zip(threaded, single):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)
