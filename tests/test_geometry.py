"""``benchmarks/geometry.py``: the shape of a run's draws in the sampler's whitened
coordinates, checked on draws with a planted ridge (one direction of ``w`` that follows a
parameter) against the values it was made with."""

import numpy as np
import pytest

from helpers import load_benchmark


@pytest.fixture(scope="module")
def geometry():
    return load_benchmark("geometry")


def test_a_planted_ridge_is_found_with_its_share_and_r2(geometry):
    """``w`` white except along one unit direction ``e`` (in the discrepancy's entries of
    ``x = F w``, ``F`` the identity) where it is ``5 v + N(0, 1)``, ``v = log phi_0``
    standard normal, ``log phi_1`` independent: one direction above the noise edge, with
    variance ``26``, all in the discrepancy; ``R^2`` of ``log phi_0`` on it ``25 / 26``, of
    ``log phi_1`` about 0.  White draws: none."""
    rng = np.random.default_rng(0)
    n, n_x, n_b3 = 6000, 60, 30
    e = np.zeros(n_x)
    e[40:44] = 0.5  # unit norm, in the discrepancy's entries
    log_phi = rng.standard_normal((n, 2))
    w = rng.standard_normal((n, n_x)) + np.outer(5 * log_phi[:, 0], e)
    g = geometry.whitened_geometry(w, log_phi, np.eye(n_x), n_b3)
    assert g["edge"] == pytest.approx((1 + np.sqrt(n_x / n)) ** 2)
    assert g["n_wide"] == 1
    assert g["eigenvalues"][-1] == pytest.approx(26.0, rel=0.05)
    np.testing.assert_allclose(g["share"], [1.0], atol=1e-3)
    assert g["r2"][0] == pytest.approx(25 / 26, abs=0.01)
    assert abs(g["r2"][1]) < 0.01
    white = geometry.whitened_geometry(rng.standard_normal((n, n_x)), log_phi, np.eye(n_x), n_b3)
    assert white["n_wide"] == 0 and np.all(np.isnan(white["r2"]))
    assert np.median(white["variance"]) == pytest.approx(1.0, abs=0.05)
