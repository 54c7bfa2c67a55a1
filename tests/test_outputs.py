"""The run's outputs (bayesreg.outputs.write, .printed): the threaded summary table equals
ArviZ's own; the printed table and its verdict."""

from __future__ import annotations

import warnings

import arviz as az
import numpy as np
import pytest

from bayesreg.outputs import printed
from bayesreg.outputs import write as outputs
from bayesreg.sampling.diagnostics import arviz_fast_ess, to_datatree


@pytest.mark.parametrize("parts", [1, 2, 3, 7])
def test_summary_in_threads_equals_one_arviz_call(parts):
    """The run's summary table, ``u_b`` in threads over blocks of nodes, is ArviZ's own
    table of all the variables in one call: the same rows in the same order, the same values."""
    rng = np.random.default_rng(4)
    c, d, n = 3, 150, 7
    ub = np.cumsum(rng.normal(size=(c, d, n, 3)), axis=1) * 0.1 + rng.normal(size=(c, d, n, 3))
    lam = rng.uniform(1, 2, (c, d, 3))
    mu = np.concatenate([rng.uniform(0.5, 1, (c, d, 2)), np.ones((c, d, 1))], axis=-1)  # a fixed one
    tree = to_datatree({"u_b": ub, "lam": lam, "mu": mu, "ratio": lam / mu},
                       dims={"u_b": ["node", "axis"], "lam": ["group"], "mu": ["group"],
                             "ratio": ["group"]},
                       coords={"node": np.arange(10, 10 + n), "axis": ["x", "y", "z"],
                               "group": ["csf", "gm", "wm"]})
    with warnings.catch_warnings():  # the fixed mu: zero variance, NaN R-hat
        warnings.simplefilter("ignore", RuntimeWarning)
        with arviz_fast_ess():
            names = ["lam", "mu", "ratio", "u_b"]
            ref = az.summary(tree, var_names=names, ci_prob=0.9, ci_kind="eti")
            tail = az.ess(tree, var_names=names, method="tail", prob=(0.05, 0.95))
            ref["ess_tail"] = np.concatenate([np.ravel(tail[n].values) for n in names])
            for col, prob in (("mcse_eti90_lb", 0.05), ("mcse_eti90_ub", 0.95)):
                m = az.mcse(tree, var_names=names, method="quantile", prob=prob)
                ref[col] = np.concatenate([np.ravel(m[n].values) for n in names])
            got = outputs.summary_table(tree, ["lam", "mu", "ratio"], "u_b", "node", parts=parts)
    assert list(got.index) == list(ref.index) and list(got.columns) == list(ref.columns)
    # the interval ends' MCSE sit in the rows they belong to: one element picked by label
    with arviz_fast_ess():
        one = az.mcse(tree.isel(node=[2], axis=[1]), var_names=["u_b"], method="quantile", prob=0.95)
    assert got.loc["u_b[12, y]", "mcse_eti90_ub"] == pytest.approx(float(one["u_b"].values.ravel()[0]), rel=1e-12)
    np.testing.assert_array_equal(got.to_numpy(float), ref.to_numpy(float))


def _sampler(**kw):
    s = {"converged": True, "rhat_threshold": 1.2, "rhat_split_monitored": False,
         "rhat_classic_max": 1.05, "rhat_classic_split_max": 1.06, "rhat_rank_max": 1.004,
         "ess_bulk_min": 812.0, "ess_tail_min": 655.0, "stuck_chains": [], "draws_per_chain": 500}
    return {**s, **kw}


@pytest.mark.parametrize("case, sampler, start, names", [
    ("both met", _sampler(), "verdict: converged", ["1.004", "812", "655"]),
    ("paper's rule only", _sampler(rhat_rank_max=1.108, ess_bulk_min=24.0),
     "verdict: NOT converged by today's criterion", ["1.108", "24", "1.050"]),
    ("tail ESS short", _sampler(ess_tail_min=120.0), "verdict: NOT converged by today's", ["120"]),
    ("no rule met", _sampler(converged=False, rhat_classic_max=5.77, rhat_rank_max=float("nan")),
     "verdict: NOT converged: 500 draws per chain", ["5.770", "R-hat n/a"]),
    ("stuck chains", _sampler(stuck_chains=[2]), "verdict: NOT converged: chains [2] never moved", []),
    ("an old run.json", {k: v for k, v in _sampler().items() if k != "ess_tail_min"},
     "verdict: converged", ["bulk ESS 812"]),
    ("the rank rule met", _sampler(stop="rank"), "verdict: converged: rank-normalised R-hat 1.004",
     ["812", "655"]),
    ("the rank rule not met", _sampler(stop="rank", converged=False, ess_tail_min=120.0),
     "verdict: NOT converged: 500 draws per chain (max_draws) without meeting the stop rule",
     ["tail ESS 120", "sampler.max_draws"]),
    ("the rank rule with its own thresholds", _sampler(stop="rank", ess_min=100.0, ess_tail_min=120.0),
     "verdict: converged", ["need >= 100"]),
])
def test_the_verdict_names_the_criterion_and_the_figures_that_fail(case, sampler, start, names):
    line = printed.verdict(sampler)
    assert line.startswith(start), (case, line)
    assert "\n" not in line
    for name in names:
        assert name in line, (case, name, line)


def test_the_printed_summary_gives_medians_and_intervals_and_ends_with_the_verdict():
    """A heavy-tailed ratio (the CSF one) prints as its median and 90% interval, never as
    a mean and sd; the verdict is the last line."""
    rng = np.random.default_rng(0)
    csf = np.exp(rng.normal(3.0, 3.0, 4000))  # lognormal: mean >> median
    ratio = {"csf": {"mean": float(csf.mean()), "sd": float(csf.std()),
                     "median": float(np.median(csf)), "q05": float(np.quantile(csf, 0.05)),
                     "q95": float(np.quantile(csf, 0.95)), "true": 1e-6 / 1e-6}}
    info = {"sampler": {**_sampler(converged=False), "blocks": ["u_b"], "acceptance": [0.3],
                        "thinning": 1, "chains": 4, "cg_iterations_per_step_mean": 2.0,
                        "solve_failures": 0, "steps_per_s_per_chain": 10.0}}
    text = printed.format_report({"ratio": ratio}, info)
    row = next(line for line in text.splitlines() if line.strip().startswith("csf"))
    assert f"{np.median(csf):.4g}" in row and f"{np.quantile(csf, 0.95):.4g}" in row
    assert f"{csf.mean():.4g}" not in row and "sd" not in text.splitlines()[-3]
    assert "median" in text and text.splitlines()[-1].startswith("verdict: NOT converged")
    # a gradient kernel's failed per-chain checks print just above the verdict
    info["sampler"]["health"] = {"warnings": ["12 divergent transitions (chain 1; up to 3.0% in chain 1)"]}
    lines = printed.format_report({"ratio": ratio}, info).splitlines()
    assert lines[-2] == "sampler check: 12 divergent transitions (chain 1; up to 3.0% in chain 1)"
    assert lines[-1].startswith("verdict: NOT converged")
    # a posterior on its prior's edge: a question where the truth is not there, a plain
    # statement where it is (the quickstart's CSF truths, 0.01 of supports 100 and 10)
    info["identification"] = {
        "lam_csf": {"at_prior_edge": True, "truth_at_prior_edge": True},
        "mu_csf": {"at_prior_edge": True, "truth_at_prior_edge": True},
        "lam_gm": {"at_prior_edge": True, "truth_at_prior_edge": False},
        "lam_wm": {"at_prior_edge": False, "truth_at_prior_edge": False},
        "ratio_csf": {"contraction": 0.0}}
    lines = printed.format_report({"ratio": ratio}, info).splitlines()
    assert lines[-4].startswith("on the prior's edge: lam_gm (") and lines[-4].endswith("parameters?)")
    assert lines[-3] == ("on the prior's edge with their truths: lam_csf, mu_csf (posterior median "
                         "and truth in the outer 1% of the prior's support)")
    del info["identification"]["lam_gm"]  # real data: no truths, the question for each
    info["identification"]["lam_csf"].pop("truth_at_prior_edge")
    lines = printed.format_report({"ratio": ratio}, info).splitlines()
    assert lines[-4].startswith("on the prior's edge: lam_csf (")
