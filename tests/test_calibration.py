"""bayesreg.experiments.calibration: truths from the prior and data from the likelihood against their
distributions (Monte Carlo, from the posterior's own JAX energies), ranks and their tests
against exact cases, the proper rigid-body prior against its closed form, and a tiny
``bayesreg calibrate`` writing its folder."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import chisquare

from bayesreg.experiments import calibration as cal
from bayesreg.cli import main
from bayesreg.config import ConfigError
from bayesreg.data.images import Image
from bayesreg.model.posterior import build_posterior, energies, rigid_log_prior
from helpers import box_posterior, log_p

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture(scope="module")
def problem():
    return cal.calibration_problem(cal.CalibrationSpec())


def test_prior_draws_have_the_elastic_priors_chi_square_energy(problem):
    """u_b ~ N(0, P^-1) with P = S / T_r + c R R^T: then 2 E_r / T_r ~ chi2(3 n_b - 6) and the
    rigid part's c |R^T u_b|^2 ~ chi2(6); E_r here is the posterior's JAX element energy of
    the draw (the draw itself comes from SciPy's sparse Schur complement)."""
    rng = np.random.default_rng(1)
    post = problem.posterior
    phi = np.array([7.0, 12.0, 1.3])
    n = 300
    quad = jax.jit(lambda u: (2 * energies(post, u, jnp.asarray(phi))[1] * post.inv_t_r,
                              -2 * rigid_log_prior(post, u[post.boundary])))
    q_el, q_rig = np.array([quad(jnp.asarray(cal._prior_draw(problem, rng, phi)))
                            for _ in range(n)]).T
    dof = 3 * post.n_boundary - 6
    assert abs(np.mean(q_el) - dof) < 5 * np.sqrt(2 * dof / n)
    assert abs(np.mean(q_rig) - 6) < 5 * np.sqrt(12 / n)
    assert abs(np.var(q_el) / (2 * dof) - 1) < 5 * np.sqrt(2 / n) * 1.5  # var of a sample var


def test_simulated_data_have_the_likelihoods_noise(problem):
    """f_q - m(x_q + u(x_q)) at the truth is N(0, T_s / (2 w_q)): 2 E_s / T_s ~ chi2(n_q)."""
    rng = np.random.default_rng(2)
    truths = cal.simulate(problem, 4, rng)
    post = problem.posterior
    for theta, f_q in zip(truths.theta, truths.f_q):
        p = post._replace(similarity=post.similarity._replace(f_q=jnp.asarray(f_q)))
        lp, aux = log_p(p, theta)
        n_q = f_q.size
        stat = 2 * float(aux.e_s) * float(post.inv_t_s)
        assert abs(stat - n_q) < 5 * np.sqrt(2 * n_q)
        assert np.isfinite(float(lp))
    assert truths.theta.shape == (4, post.dim)
    assert truths.f_q.shape == (4, *post.similarity.f_q.shape)


@pytest.mark.parametrize("sets", [["model.t_s_prior={shape: 3, rate: 1.5}"], ["model.data_t_s=2.0"]])
def test_simulated_noise_has_each_replicas_temperature(sets):
    """With ``t_s_prior`` each replica's 1 / T_s is a Gamma draw (mean shape / rate over 40
    replicas, 5 standard errors) and its noise has that temperature (chi-square); with
    ``data_t_s`` the noise has that one, not the model's."""
    spec = cal.load_spec(overrides=sets)
    cp = cal.calibration_problem(spec)
    truths = cal.simulate(cp, 40, np.random.default_rng(4))
    post = cp.posterior
    n_q = post.similarity.f_q.size
    if cp.t_s_prior is not None:
        assert float(post.t_s_shape) == 3 + n_q / 2 and float(post.t_s_rate) == 1.5
        tau = 1 / truths.t_s
        assert abs(tau.mean() - 2.0) < 5 * np.sqrt(3 / 1.5**2 / 40)
    else:
        np.testing.assert_array_equal(truths.t_s, 2.0)
        assert float(post.inv_t_s) == 1 / spec.model.t_s and float(post.t_s_shape) == 0
    for theta, f_q, t_s in list(zip(truths.theta, truths.f_q, truths.t_s))[:3]:
        p = post._replace(similarity=post.similarity._replace(f_q=jnp.asarray(f_q)))
        stat = 2 * float(log_p(p, theta)[1].e_s) / t_s
        assert abs(stat - n_q) < 5 * np.sqrt(2 * n_q)


def test_rigid_prior_of_a_translation_is_its_closed_form():
    """A translation t of every boundary node lies in the rigid modes: the prior adds
    -|t|^2 / (2 sigma^2) (rms displacement |t| along a mode of sd sigma), and nothing else
    changes."""
    prior = {"lam": (1.0, 1.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
    phi = np.array([5.0, 5.0, 5.0, 1.0, 1.0])
    mesh, post, _ = box_posterior(prior, 3.0, phi)
    sigma, t = 2.0, np.array([0.4, -0.3, 0.2])
    theta = np.r_[np.tile(t, post.n_boundary), phi]
    with_rigid = post._replace(inv_rigid_var=jnp.asarray(1.0 / (post.n_boundary * sigma**2)))
    diff = float(log_p(with_rigid, theta)[0] - log_p(post, theta)[0])
    assert diff == pytest.approx(-float(t @ t) / (2 * sigma**2), rel=1e-10)


def test_build_posterior_refuses_a_bad_rigid_sd(problem):
    cp = problem
    skull = Image(np.zeros((8, 8, 8), np.uint8), np.diag([8.0, 8.0, 8.0, 1.0]))
    for bad in (-1.0, 0.0, float("inf")):
        with pytest.raises(ValueError, match="rigid_sd"):
            build_posterior(cp.mesh, cp.posterior.similarity, skull, t_s=1.0, t_r=1.0,
                            layout=cp.layout, element_group=cp.element_group,
                            prior={"lam": (1, 1, 0, 20), "mu": (1, 1, 0.5, 2)},
                            phi_ref=[5.0, 5.0, 1.0], rigid_sd=bad)


def test_ranks_of_exact_posterior_draws_are_uniform():
    """A conjugate normal (prior N(0, 1), one observation of sd 1): truths from the prior,
    draws from the exact posterior; the ranks pass SciPy's chi-square test, and the ranks
    of a posterior shifted by one posterior sd do not."""
    rng = np.random.default_rng(3)
    r, n_draw = 2000, 99
    truth = rng.standard_normal((r, 1))
    y = truth + rng.standard_normal((r, 1))
    draws = y[:, None, :] / 2 + np.sqrt(0.5) * rng.standard_normal((r, n_draw, 1))
    ranks = cal.ranks_of(truth, draws)
    assert ranks.min() >= 0 and ranks.max() <= n_draw
    good = cal._test(ranks[:, 0], n_draw, 10)
    counts = np.bincount(ranks[:, 0] // 10, minlength=10)
    assert good["histogram"] == counts.tolist()
    assert good["p"] == pytest.approx(chisquare(counts).pvalue)
    assert good["p"] > 1e-3
    bad = cal._test(cal.ranks_of(truth, draws + np.sqrt(0.5))[:, 0], n_draw, 10)
    assert bad["p"] < 1e-6
    cov = np.mean(cal._covered(truth, draws, 0.9))
    assert abs(cov - 0.9) < 5 * np.sqrt(0.09 / r)


def test_spec_errors_name_the_key(tmp_path):
    with pytest.raises(ConfigError, match="bins"):
        cal.load_spec(overrides=["sampler.bins=7"])
    with pytest.raises(ConfigError, match="replicas"):
        cal.load_spec(overrides=["replicas=1"])
    with pytest.raises(FileNotFoundError):
        cal.load_spec(tmp_path / "missing.yaml")
    assert cal.load_spec(CONFIGS / "calibration.yaml").model.prior_normaliser == "exact"


def test_calibrate_command_writes_its_folder(tmp_path, capsys):
    out = tmp_path / "cal"
    status = main(["calibrate", str(CONFIGS / "calibration.yaml"), "--out", str(out),
                   "--set", "replicas=3", "--set", "sampler.chains=2",
                   "--set", "sampler.warmup_steps=20", "--set", "sampler.draws=10",
                   "--set", "sampler.ranks=9", "--set", "sampler.max_tree_depth=3"])
    assert status == 0
    printed = capsys.readouterr().out
    assert "| lam/mu_b |" in printed and "calibrated" in printed
    for name in ("calibration.json", "calibration.md", "ranks.csv", "rank_histograms.png"):
        assert (out / name).is_file()
    summary = json.loads((out / "calibration.json").read_text())["summary"]
    assert summary["replicas"] == 3
    for name, row in summary["quantities"].items():
        assert len(row["ranks"]) == 3 and all(0 <= k <= 9 for k in row["ranks"])
        assert sum(row["histogram"]) == 3 and 0 <= row["p"] <= 1
        assert set(row["coverage"]) == {"0.5", "0.9", "0.95"}
    assert sum(summary["u_b"]["histogram"]) == 3 * 3 * 56
    assert len(summary["convergence"]["rhat_rank_max"]) == 3
    v = summary["verdict"]
    assert v["calibrated"] == (not v["problems"])


def test_strict_calibrate_exits_5_when_not_calibrated(monkeypatch, capsys):
    summary = {"levels": [0.9], "quantities": {}, "u_b": {"coverage": {"0.9": 0.5}, "p": 0.0},
               "verdict": {"calibrated": False, "problems": ["u_b: 90% intervals hold 50%"]}}
    monkeypatch.setattr(cal, "calibrate", lambda spec, out: summary)
    assert main(["calibrate", "--strict"]) == 5
    assert "NOT calibrated: u_b: 90% intervals hold 50%" in capsys.readouterr().out
    assert main(["calibrate"]) == 0
    summary["verdict"] = {"calibrated": True, "problems": []}
    assert main(["calibrate", "--strict"]) == 0
