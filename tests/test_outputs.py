"""The run's outputs (bayesreg.outputs): the summary table in threads equals ArviZ's own."""

from __future__ import annotations

import warnings

import arviz as az
import numpy as np
import pytest

from bayesreg import outputs
from bayesreg.diagnostics import arviz_fast_ess, to_datatree


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
            ref = az.summary(tree, var_names=["lam", "mu", "ratio", "u_b"], ci_prob=0.9, ci_kind="eti")
            got = outputs.summary_table(tree, ["lam", "mu", "ratio"], "u_b", "node", parts=parts)
    assert list(got.index) == list(ref.index) and list(got.columns) == list(ref.columns)
    np.testing.assert_array_equal(got.to_numpy(float), ref.to_numpy(float))
