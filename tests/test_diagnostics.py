"""Diagnostics: credible-interval coverage, ArviZ's ESS vectorised."""

from __future__ import annotations

import numpy as np
import pytest

import arviz as az
from bayesreg.sampling.diagnostics import EBFMI_MIN, arviz_fast_ess, coverage, sampler_health

LEVELS = (0.5, 0.9, 0.95)
K, C, D = 2000, 4, 500  # components, chains, draws per chain


def _tolerance(level, k=K, s=C * D):
    """Monte Carlo tolerance on the coverage fraction.

    With truths drawn from the posterior itself, the K indicators "truth k inside its
    interval" are independent Bernoulli variables whose success probability is
    ``F_k(q_hi) - F_k(q_lo)`` with ``q`` the empirical quantiles of S draws.  Marginally
    each is Bernoulli(``level + O(1/S)``) (the CDF of an order statistic has mean
    ``r / (S + 1)``), so the fraction has sd ``sqrt(l (1 - l) / K)``; 4 sd plus a bias
    allowance of ``2/S`` fails a correct implementation with probability < 1e-4.
    """
    return 4.0 * np.sqrt(level * (1.0 - level) / k) + 2.0 / s


def _gaussian(seed, shift_sd=0.0, scale=1.0):
    rng = np.random.default_rng(seed)
    mean = rng.normal(0.0, 5.0, K)
    sd = rng.uniform(0.5, 2.0, K)
    truth = mean + sd * rng.standard_normal(K)
    post_mean = mean + shift_sd * sd
    draws = post_mean + scale * sd * rng.standard_normal((C, D, K))
    return draws, truth


def test_calibrated_gaussian_covers_at_nominal_level():
    draws, truth = _gaussian(0)
    cov = coverage(draws, truth, LEVELS)
    assert set(cov) == set(LEVELS)
    for lev in LEVELS:
        assert abs(cov[lev] - lev) < _tolerance(lev), (lev, cov[lev])


def test_chain_axes_are_pooled():
    draws, truth = _gaussian(1)
    assert coverage(draws, truth) == coverage(draws.reshape(C * D, K), truth)


def test_biased_posterior_under_covers():
    # posterior mean 2 sd off: P(|Z - 2| < z_l) is 0.09, 0.36, 0.48 at 50, 90, 95 %
    draws, truth = _gaussian(2, shift_sd=2.0)
    cov = coverage(draws, truth, LEVELS)
    for lev in LEVELS:
        assert cov[lev] < lev - _tolerance(lev), (lev, cov[lev])


def test_overdispersed_posterior_over_covers():
    draws, truth = _gaussian(3, scale=3.0)
    cov = coverage(draws, truth, LEVELS)
    for lev in LEVELS:
        assert cov[lev] > lev + _tolerance(lev), (lev, cov[lev])


def test_exact_small_case():
    draws = np.tile(np.arange(101.0)[:, None], (1, 4))  # quantile q of each column = 100 q
    truth = np.array([50.0, 20.0, 25.0, 97.6])
    cov = coverage(draws, truth, (0.5, 0.95))
    assert cov[0.5] == 0.5  # [25, 75] holds 50 and 25
    assert cov[0.95] == 0.75  # [2.5, 97.5] holds all but 97.6


@pytest.mark.parametrize(
    "draws, truth, levels",
    [
        (np.zeros((10, 3)), np.zeros(4), (0.5,)),
        (np.zeros((1, 3)), np.zeros(3), (0.5,)),
        (np.zeros((10, 3)), np.zeros(3), (1.0,)),
        (np.full((10, 3), np.nan), np.zeros(3), (0.5,)),
    ],
)
def test_invalid_input(draws, truth, levels):
    with pytest.raises(ValueError):
        coverage(draws, truth, levels)


@pytest.mark.parametrize("block", [1, 3, 1000])
def test_blocked_coverage_equals_whole(block):
    """Coverage computed over blocks of components of a strided view equals the coverage of
    all components at once."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(3, 200, 40)) + rng.normal(0.0, 0.3, (3, 1, 40))
    view = np.concatenate([x, rng.normal(size=(3, 200, 5))], axis=-1)[..., :40]  # strided
    truth = rng.normal(0.0, 1.2, 40)
    ref = coverage(x.reshape(-1, 40), truth, block=10**6)
    assert coverage(view, truth, block=block) == ref


def _ar1(rng, c, d, phi):
    e = rng.normal(size=(c, d))
    x = np.empty_like(e)
    x[:, 0] = e[:, 0]
    for t in range(1, d):
        x[:, t] = phi * x[:, t - 1] + e[:, t]
    return x


def test_vectorised_geyer_ess_equals_arviz_lag_loop():
    """Inside ``arviz_fast_ess`` ArviZ's ESS (``az.ess`` of the draws as given, and per draw)
    equals its own lag loop's to round-off on every kind of input the loop distinguishes:
    positive and negative autocorrelation, sequences ended by a non-positive pair or by the
    number of draws, binary (quantile-indicator) draws, chains with different means,
    constant and non-finite draws."""
    rng = np.random.default_rng(5)
    worst, nan_cases = 0.0, 0
    for trial in range(600):
        c, d = int(rng.integers(1, 6)), int(rng.integers(8, 80))
        x = _ar1(rng, c, d, rng.uniform(-0.95, 0.999))
        if trial % 5 == 0:
            x = (x > rng.normal()).astype(float)
        if trial % 7 == 0:
            x += np.arange(c)[:, None] * rng.uniform(0.0, 5.0)
        if trial % 97 == 0:
            x[0, 3] = np.nan
        if trial % 89 == 0:
            x[:] = 2.5
        for rel in (False, True):
            with np.errstate(all="ignore"):
                a = float(az.ess(x, method="identity", relative=rel))
                with arviz_fast_ess():
                    b = float(az.ess(x, method="identity", relative=rel))
            if np.isnan(a):
                assert np.isnan(b)
                nan_cases += 1
                continue
            worst = max(worst, abs(a - b) / abs(a))
    assert nan_cases > 0
    assert worst < 1e-12


def test_arviz_fast_ess_summary_equals_arviz_and_restores_settings():
    from arviz_base import rc_context, rcParams

    rng = np.random.default_rng(2)
    x = np.stack([_ar1(rng, 3, 3000, 0.995) for _ in range(6)], axis=-1)  # slow mixing: long loop
    x[..., 0] = x[..., 0] > 0
    tree = az.from_dict({"posterior": {"u": x}})
    ref = az.summary(tree, ci_prob=0.9, ci_kind="eti")
    with arviz_fast_ess():
        assert rcParams["stats.module"] != "base"
        got = az.summary(tree, ci_prob=0.9, ci_kind="eti")
    assert rcParams["stats.module"] == "base"
    assert list(got.columns) == list(ref.columns) and list(got.index) == list(ref.index)
    np.testing.assert_allclose(got.to_numpy(float), ref.to_numpy(float), rtol=1e-12)
    assert (ref["ess_bulk"] < 200).all()  # the case the loop is slow on
    from arviz_stats.base import dataarray_stats

    with rc_context({"stats.module": dataarray_stats}), arviz_fast_ess():
        assert rcParams["stats.module"] is dataarray_stats  # a user's own backend is kept
    with pytest.raises(RuntimeError), arviz_fast_ess():
        raise RuntimeError
    assert rcParams["stats.module"] == "base"


def test_contraction_is_zero_for_prior_draws_and_near_one_for_a_narrow_posterior():
    """Against Monte Carlo: draws from the scaled Beta priors themselves contract by 0 (to
    Monte Carlo error), on the logit scale of each parameter and the log scale of the ratio;
    a narrow posterior contracts by nearly 1; a fixed mu adds no prior variance."""
    from bayesreg.sampling.diagnostics import IDENTIFIED_MIN, contraction
    from bayesreg.model.parameters import BetaPriors, ParamLayout

    layout = ParamLayout(("csf", "gm"), (("lam", 0), ("mu", 0), ("lam", 1)), (("mu", 1, 1.0),))
    priors = BetaPriors(np.array([2.0, 3.0, 1.5]), np.array([5.0, 3.0, 1.5]),
                        np.array([0.0, 0.0, 0.0]), np.array([100.0, 10.0, 50.0]))
    rng = np.random.default_rng(0)
    n = 400_000
    prior_draws = np.stack([100.0 * rng.beta(2.0, 5.0, n), 10.0 * rng.beta(3.0, 3.0, n),
                            50.0 * rng.beta(1.5, 1.5, n)], axis=-1).reshape(4, n // 4, 3)
    c = contraction(layout, priors, prior_draws)
    assert set(c) == {"lam_csf", "mu_csf", "lam_gm", "ratio_csf", "ratio_gm"}
    for name, e in c.items():
        assert abs(e["contraction"]) < 0.02, (name, e)
        assert not e["identified"]
    # the prior sd against the Monte Carlo sd of the same transform
    x = prior_draws[..., 0].ravel() / 100.0
    assert c["lam_csf"]["prior_sd"] == pytest.approx(np.std(np.log(x / (1 - x))), rel=0.01)
    ratio = np.log(prior_draws[..., 0] / prior_draws[..., 1]).ravel()
    assert c["ratio_csf"]["prior_sd"] == pytest.approx(np.std(ratio), rel=0.01)
    assert c["ratio_gm"]["scale"] == "log" and c["lam_gm"]["scale"] == "logit"

    narrow = np.array([30.0, 2.0, 25.0]) * np.exp(0.01 * rng.normal(size=(3, 500, 3)))
    for name, e in contraction(layout, priors, narrow).items():
        assert e["contraction"] > 0.99 and e["identified"], (name, e)
        assert not e.get("at_prior_edge"), (name, e)
    assert 0 < IDENTIFIED_MIN < 1
    # a posterior pressed onto the edges of the support: lam_csf near 0 (below 1% of 100),
    # lam_gm near its top (above 99% of 50); mu_csf at 5 of 10 is not
    edge = np.array([0.3, 5.0, 49.8]) * np.exp(0.05 * rng.normal(size=(3, 500, 3)))
    edge[..., 2] = np.minimum(edge[..., 2], 49.99)
    flags = {k: e["at_prior_edge"] for k, e in contraction(layout, priors, edge).items()
             if "at_prior_edge" in e}
    assert flags == {"lam_csf": True, "mu_csf": False, "lam_gm": True}
    # with the truths: lam_csf's (0.5 of 100) is on the edge too, lam_gm's (30 of 50) is not
    known = contraction(layout, priors, edge, phi_true=[0.5, 5.0, 30.0])
    assert {k: e["truth_at_prior_edge"] for k, e in known.items() if "at_prior_edge" in e} == \
        {"lam_csf": True, "mu_csf": False, "lam_gm": False}
    assert "truth_at_prior_edge" not in contraction(layout, priors, edge)["lam_csf"]
    with pytest.raises(ValueError, match="phi_true"):
        contraction(layout, priors, edge, phi_true=[1.0, 2.0])


def test_sampler_health_counts_divergences_tree_depth_and_e_bfmi_per_chain():
    """Fractions per chain against counts by hand; E-BFMI against its definition
    (Betancourt 2017, Eq. 6.1: the mean squared lag-1 change of the energy over its
    variance): about 2 for independent energies, far below 0.3 for a random walk."""
    rng = np.random.default_rng(0)
    c, d, thin = 3, 400, 2
    div = np.zeros((c, d), int)
    div[1, :100] = 1  # 100 of 800 transitions
    div[2, :10] = 2   # 20 of 800
    depth = np.full((c, d), 4)
    depth[0, ::4] = 6  # a quarter of chain 0's draws at the maximum
    energy = rng.normal(size=(c, d))
    energy[2] = np.cumsum(energy[2])  # chain 2: a random walk in energy
    h = sampler_health(div, steps_per_draw=thin, tree_depth=depth, max_tree_depth=6, energy=energy)
    assert h["divergent_fraction"] == pytest.approx([0.0, 100 / 800, 20 / 800])
    assert h["max_depth_fraction"] == pytest.approx([0.25, 0.0, 0.0])
    by_hand = [np.mean(np.diff(e) ** 2) / np.var(e) for e in energy]
    assert h["e_bfmi"] == pytest.approx(by_hand, rel=0.01)
    assert h["e_bfmi"][0] == pytest.approx(2.0, abs=0.3) and h["e_bfmi"][2] < EBFMI_MIN
    warn = h["warnings"]
    assert len(warn) == 3
    assert warn[0].startswith("120 divergent transitions (chains 1, 2; up to 12.5% in chain 1)")
    assert "model.skull_barrier_mm" in warn[0]  # the barrier is off: suggested
    barred = sampler_health(div, steps_per_draw=thin, skull_barrier_mm=1.0)["warnings"][0]
    assert "model.skull_barrier_mm" not in barred and "pressed against the skull" in barred
    assert "maximum tree depth 6 in chain 0 (up to 25.0%" in warn[1]
    assert warn[2].startswith(f"E-BFMI below {EBFMI_MIN} in chain 2")
    # a healthy run: no lines; without tree depth or energy (HMC, MALA) only divergences
    calm = sampler_health(np.zeros((2, 50), int), tree_depth=np.full((2, 50), 3), max_tree_depth=6,
                          energy=rng.normal(size=(2, 50)))
    assert calm["warnings"] == [] and calm["max_depth_fraction"] == [0.0, 0.0]
    bare = sampler_health(np.zeros((2, 50), int), energy=np.full((2, 50), np.nan))
    assert bare["max_depth_fraction"] is None and bare["e_bfmi"] is None and bare["warnings"] == []
    with pytest.raises(ValueError, match="max_tree_depth"):
        sampler_health(div, tree_depth=depth)
    with pytest.raises(ValueError, match="shape"):
        sampler_health(div, energy=energy[:, :10])
    with pytest.raises(ValueError, match="chains, draws"):
        sampler_health(div.ravel())
