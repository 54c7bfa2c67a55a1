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


def test_the_mesh_best_fit_is_the_ridge_least_squares_projection():
    """``mesh_best_fit``: NumPy's least squares of ``[W; sqrt(eps) I] v = [t; sqrt(eps)
    u_ref]`` per axis, ``eps`` the ridge times the mean diagonal of ``W^T W``; a target that
    is an FE field gives its nodal values back whatever ``u_ref``; bad shapes are refused."""
    import scipy.sparse as sp

    from bayesreg.outputs.fields import BEST_FIT_RIDGE, mesh_best_fit

    rng = np.random.default_rng(5)
    v, n = 400, 30
    w = sp.random(v, n, density=0.1, random_state=rng, format="csr")
    t, u_ref = rng.normal(size=(v, 3)), rng.normal(size=(n, 3))
    eps = BEST_FIT_RIDGE * float((w.T @ w).diagonal().mean())
    a = np.vstack([w.toarray(), np.sqrt(eps) * np.eye(n)])
    want = np.linalg.lstsq(a, np.vstack([t, np.sqrt(eps) * u_ref]), rcond=None)[0]
    np.testing.assert_allclose(mesh_best_fit(w, t, u_ref), want, rtol=1e-9, atol=1e-10)
    v0 = rng.normal(size=(n, 3))
    dense = sp.csr_matrix(rng.uniform(size=(v, n)))
    np.testing.assert_allclose(mesh_best_fit(dense, dense @ v0, u_ref, ridge=1e-12), v0, atol=1e-6)
    with pytest.raises(ValueError, match="do not match"):
        mesh_best_fit(w, t[:-1], u_ref)
    with pytest.raises(ValueError, match="ridge must be > 0"):
        mesh_best_fit(w, t, u_ref, ridge=0.0)
