"""The paper's tables from finished runs: boundary errors (Table 1), MSE (Table 2), coverage,
``lam/mu`` ratios.  Each takes a :class:`~bayesreg.report.data.RunData` or a mapping of
labels to runs or run directories and returns a pandas DataFrame."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from bayesreg.sampling.diagnostics import coverage
from bayesreg.report.data import LEVELS, TISSUE_LABELS, TISSUE_NAMES, as_runs, true_ratio

__all__ = ["table1", "table2", "coverage_table", "ratio_table"]


def _stats(err) -> dict:
    return {"median": float(np.median(err)), "q95": float(np.quantile(err, 0.95)),
            "max": float(np.max(err))}


def _initial_rows(runs: dict, get) -> dict:
    """``{row: (run, value)}`` for the initial configuration (``get(run)`` or None).

    One row ``"initial"`` when every run that has it started from the same configuration,
    else one row ``"initial (label)"`` per run.
    """
    have = {k: (r, get(r)) for k, r in runs.items() if get(r) is not None}
    if not have:
        return {}
    vals = [v for _, v in have.values()]
    if all(v.shape == vals[0].shape and np.allclose(v, vals[0], atol=1e-9) for v in vals):
        return {"initial": next(iter(have.values()))}
    return {f"initial ({k})": rv for k, rv in have.items()}


def table1(runs) -> pd.DataFrame:
    """Paper Table 1: error of the boundary-node displacements against the truth, mm.

    Per boundary node (the ``node`` coordinate of ``posterior.nc``) the Euclidean norm of
    ``E[u_b] - u_true`` with ``E[u_b]`` the mean over all chains and draws; for the row
    ``initial`` that of ``u_init - u_true``.

    Parameters
    ----------
    runs : RunData or Mapping[str, RunData or path]

    Returns
    -------
    DataFrame
        Index: ``"initial"`` (if ``u_init`` is in ``mesh.vtu``; one ``"initial (label)"``
        row per run instead when the runs started from different configurations) and the
        run labels; columns ``median``, ``q95``, ``max`` (mm).
    """
    runs = as_runs(runs)
    rows = {}
    for row, (r, u0) in _initial_rows(runs, lambda r: None if r.u_init is None
                                       else r.u_init[r.boundary]).items():
        rows[row] = _stats(np.linalg.norm(u0 - r.u_true[r.boundary], axis=1))
    for k, r in runs.items():
        mean_b = r.u_b.reshape(-1, *r.u_b.shape[2:]).mean(0)
        rows[k] = _stats(np.linalg.norm(mean_b - r.u_true[r.boundary], axis=1))
    return pd.DataFrame.from_dict(rows, orient="index", columns=["median", "q95", "max"])


def _mse(disp, truth, labels, in_mesh=None) -> dict:
    sq = np.sum((disp - truth) ** 2, axis=-1)
    where = np.ones(labels.shape, bool) if in_mesh is None else in_mesh
    brain = np.isin(labels, list(TISSUE_LABELS.values())) & where
    out = {"brain": float(sq[brain].mean()) if brain.any() else math.nan}
    for t, lab in TISSUE_LABELS.items():
        sel = (labels == lab) & where
        out[t] = float(sq[sel].mean()) if sel.any() else math.nan
    return out


def table2(runs) -> pd.DataFrame:
    """Paper Table 2: MSE of the deformation on the image grid, mm^2.

    Mean over voxels of ``|u - u_true|^2`` with ``u`` the posterior mean
    (``displacement_mean.nii.gz``; ``displacement_init.nii.gz`` for the row ``initial``)
    and ``u_true`` from ``displacement_true.nii.gz``, over the brain (labels 1-3) and per
    tissue (label 1 CSF, 2 GM, 3 WM), restricted to the voxels inside the undeformed mesh
    (``mesh_mask.nii.gz``, where the FE field is defined) when the run has that file.

    Parameters
    ----------
    runs : RunData or Mapping[str, RunData or path]

    Returns
    -------
    DataFrame
        Index: ``"initial"`` (if ``displacement_init.nii.gz`` exists; per run as in
        :func:`table1`) and the run labels; columns ``brain``, ``csf``, ``gm``, ``wm``
        (mm^2; NaN for a tissue with no voxel).
    """
    runs = as_runs(runs)
    rows = {}
    for row, (r, d0) in _initial_rows(runs, lambda r: r.disp_init).items():
        rows[row] = _mse(d0, r.disp_true, r.labels, r.in_mesh)
    for k, r in runs.items():
        rows[k] = _mse(r.disp_mean, r.disp_true, r.labels, r.in_mesh)
    return pd.DataFrame.from_dict(rows, orient="index", columns=["brain", *TISSUE_NAMES])


def coverage_table(runs, levels=LEVELS) -> pd.DataFrame:
    """Coverage of the true boundary displacement components (B x 3 per run).

    Parameters
    ----------
    runs : RunData or Mapping[str, RunData or path]
    levels : sequence of float
        central credible levels

    Returns
    -------
    DataFrame
        Index: run labels; one column per level (``"50%"``, ...), the fraction of the
        ``3 B`` components whose truth lies in the central interval (chains pooled).
    """
    runs = as_runs(runs)
    rows = {}
    for k, r in runs.items():
        c, d, b, _ = r.u_b.shape
        cov = coverage(r.u_b.reshape(c, d, 3 * b), r.u_true[r.boundary].ravel(), levels)
        rows[k] = {f"{100 * lev:g}%": v for lev, v in cov.items()}
    return pd.DataFrame.from_dict(rows, orient="index")


def ratio_table(runs) -> pd.DataFrame:
    """``lam/mu`` posterior per run and elastic group (paper Fig. 4 in numbers).

    Returns
    -------
    DataFrame
        One row per (run label, group): ``mean``, ``median``, ``q05``, ``q95`` of the draws
        (chains pooled) and ``true`` (NaN where the truth has no such group).
    """
    rows = []
    for k, r in as_runs(runs).items():
        for g, name in enumerate(r.groups):
            x = r.ratio[..., g].ravel()
            tr = true_ratio(r, name)
            rows.append({"run": k, "group": name, "mean": float(x.mean()),
                         "median": float(np.median(x)), "q05": float(np.quantile(x, 0.05)),
                         "q95": float(np.quantile(x, 0.95)),
                         "true": math.nan if tr is None else tr})
    return pd.DataFrame(rows).set_index(["run", "group"])
