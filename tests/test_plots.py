"""The run directory's figures (bayesreg.outputs.plots): log axes for ratios, a rank plot beside the
traces, the marginal plot naming its node and marking the truth, the uncertainty slice
through the most uncertain region."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from bayesreg.sampling.diagnostics import to_datatree
from bayesreg.outputs.plots import most_uncertain_voxel, parameter_figures


def test_the_most_uncertain_voxel_is_the_centre_of_a_region_not_a_lone_spike():
    rng = np.random.default_rng(1)
    spread = rng.uniform(0.0, 0.1, (40, 44, 36))
    mask = np.ones(spread.shape, bool)
    mask[:3] = False
    blob = np.zeros(spread.shape)
    blob[25, 12, 20] = 1.0
    spread += 40.0 * gaussian_filter(blob, 3.0) / gaussian_filter(blob, 3.0).max() * 0.05
    spread[5, 30, 8] = 5.0  # one outlying voxel, far higher than the region's peak of 2
    spread[1, 1, 1] = 50.0  # outside the mask
    assert tuple(most_uncertain_voxel(spread, mask)) == (25, 12, 20)
    assert tuple(most_uncertain_voxel(spread, np.zeros_like(mask))) == (20, 22, 18)


def test_parameter_figures_log_ratio_axes_rank_plot_and_a_named_node_with_its_truth():
    rng = np.random.default_rng(2)
    c, d, nb = 3, 60, 5
    ratio = np.exp(rng.normal([0.0, 2.3, 3.4], [2.0, 0.05, 0.1], (c, d, 3)))  # CSF heavy-tailed
    ub = rng.normal(0.0, [0.1, 0.1, 3.0, 0.1, 0.1], (c, d, 3, nb)).transpose(0, 1, 3, 2)
    tree = to_datatree({"ratio": ratio, "u_b": ub},
                       dims={"ratio": ["group"], "u_b": ["node", "axis"]},
                       coords={"group": ["csf", "gm", "wm"], "node": np.arange(10, 10 + nb),
                               "axis": ["x", "y", "z"]})
    nodes = np.zeros((20, 3))
    nodes[12] = [1.5, -2.25, 30.0]
    u_true_b = np.arange(3 * nb, dtype=float).reshape(nb, 3)
    trace, marginals = parameter_figures(tree, ["csf", "gm", "wm"], [1.0, 10.0, 30.0],
                                         nodes=nodes, u_true_b=u_true_b)
    axes = np.array(trace.axes).reshape(3, 3)
    for k, truth in enumerate([1.0, 10.0, 30.0]):
        assert axes[k, 0].get_yscale() == "log" and axes[k, 2].get_xscale() == "log"
        # the rank plot: one histogram per chain, and the flat line of agreeing chains at
        # draws per chain / bins (60 / 6)
        assert len(axes[k, 1].patches) == c
        assert np.allclose(axes[k, 1].get_lines()[0].get_ydata(), d / 6)
        assert any(np.isclose(line.get_xdata()[0], truth) for line in axes[k, 2].get_lines())
    assert "rank" in axes[0, 1].get_title()
    # the node with the largest spread is boundary node 2 = mesh node 12
    assert "mesh node 12 at (1.5, -2.2, 30.0) mm" in marginals._suptitle.get_text()
    for a, ax in enumerate(marginals.axes):
        assert any(np.isclose(line.get_xdata()[0], u_true_b[2, a]) for line in ax.get_lines())


def test_a_node_whose_draws_differ_by_rounding_alone_still_gets_its_marginals():
    """A boundary node that moved by rounding only (a move that rewrote ``u_b`` through its
    coordinates): NumPy refuses 40 bins over a range of 1e-15 mm; the figure draws them over
    one mm instead, and the chains share their bins."""
    c, d, nb = 3, 10, 2
    ub = np.zeros((c, d, nb, 3)) + 1.25
    ub[:, ::2, 0, :] += 1e-15
    ub[:, :, 1, :] += np.linspace(0.0, 1e-12, d)[None, :, None]
    tree = to_datatree({"ratio": np.full((c, d, 3), 10.0), "u_b": ub},
                       dims={"ratio": ["group"], "u_b": ["node", "axis"]},
                       coords={"group": ["csf", "gm", "wm"], "node": np.arange(nb),
                               "axis": ["x", "y", "z"]})
    _, marginals = parameter_figures(tree, ["csf", "gm", "wm"], None)
    for ax in marginals.axes:
        lo, hi = ax.get_xlim()
        assert lo <= 0.75 + 1e-9 and hi >= 1.75 - 1e-9
