"""The paper's Section 4 tables and figures from finished runs (synthetic truth needed).

:func:`write_report` reads finished run directories (see :mod:`bayesreg.outputs.write`), one per
model (e.g. ``{"uniform": ..., "three_compartment": ...}``), and writes a report directory:

==========================  ==========================================================
``table1.csv``              boundary-node error of the posterior mean (and of the initial
                            configuration) against the truth: median, 95th quantile, max, mm
                            (paper Table 1)
``table2.csv``              MSE of the deformation on the image grid over the brain and per
                            tissue, mm^2 (paper Table 2)
``coverage.csv``            coverage of the true boundary displacement components by the
                            central 50/90/95 % credible intervals
``ratios.csv``              lam/mu posterior per model and elastic group, with the truth
``fig2_dataset.png``        the dataset: images, labels, mesh cut, divergence and x/y
                            components of the true field (paper Fig. 2)
``fig3_errors.png``         error norm and divergence of the posterior mean (paper Fig. 3)
``fig4_ratios.png``         marginal posteriors of lam/mu (paper Fig. 4)
``fig5_boundary_node.png``  marginal posterior of a boundary node next to the skull (Fig. 5)
``uncertainty.png``         interquartile range of ``|u|`` over the fixed image
``report.md``, ``report.json``  all of it, side by side with the paper's values
==========================  ==========================================================

The pieces are small functions of a :class:`RunData` (:func:`load_run`) so that a notebook
can redraw one table or figure: ``table1({"tissue": load_run("runs/a")})``.  Figures are
built with the object-oriented Matplotlib API on the Agg canvas (no pyplot state).
Units: displacements and distances in world mm, MSE in mm^2, divergence in mm/mm.
"""

from bayesreg.report.data import PAPER, TISSUE_COLORS, RunData, load_run
from bayesreg.report.figures import (
    divergence, mesh_cut, plot_boundary_node, plot_dataset, plot_errors, plot_ratios,
    plot_uncertainty, skull_distance, skull_limits, skull_node, slice_index)
from bayesreg.report.tables import coverage_table, ratio_table, table1, table2
from bayesreg.report.write import write_report

__all__ = [
    "PAPER", "TISSUE_COLORS", "RunData", "load_run", "table1", "table2", "coverage_table", "ratio_table",
    "divergence", "skull_distance", "skull_node", "skull_limits", "mesh_cut", "slice_index",
    "plot_dataset", "plot_errors", "plot_ratios", "plot_boundary_node", "plot_uncertainty",
    "write_report",
]
