"""The report directory: tables, figures and ``report.md`` side by side with the paper."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from bayesreg.report.data import PAPER, RunData, as_runs
from bayesreg.report.figures import (
    plot_boundary_node, plot_dataset, plot_errors, plot_ratios, plot_uncertainty, slice_index)
from bayesreg.report.tables import coverage_table, ratio_table, table1, table2
from bayesreg._files import dumps_json, write_text_atomic
from bayesreg.sampling.diagnostics import normaliser_note
from bayesreg.outputs.printed import verdict
from bayesreg.rundir import RunDirectory

__all__ = ["write_report"]


def _fmt(v, nd=3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return f"{float(v):.{nd}f}"


def _md_table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _paper_key(row: str, runs: dict) -> str | None:
    if row.startswith("initial"):
        return "initial"
    return runs[row].elastic if row in runs else None


def _run_summary(run: RunData) -> dict:
    s, mesh, t = run.info.get("sampler", {}), run.info.get("mesh", {}), run.info.get("timings_s", {})
    wall = t.get("total_before_outputs_s", sum(v for v in t.values() if isinstance(v, (int, float))))
    cfg = run.info.get("config", {})
    model, kind = cfg.get("model", {}), cfg.get("sampler", {}).get("kind")
    # how E_s, the skull constraint and Eq. 12 were evaluated (older runs: the defaults of then)
    setup = ", ".join(x for x in [
        kind, f"quadrature {4 * 8 ** int(model.get('quadrature_level', 0))} pts/tet",
        f"barrier {float(model.get('skull_barrier_mm', 0.0)):g} mm",
        f"normaliser {model['prior_normaliser']}" if "prior_normaliser" in model else None,
    ] if x) if cfg else "–"
    return {
        "path": str(run.path), "name": run.name, "elastic": run.elastic, "setup": setup,
        "n_nodes": mesh.get("n_nodes", len(run.points)),
        "n_boundary": mesh.get("n_boundary", mesh.get("n_boundary_nodes", len(run.boundary))),
        "n_tets": mesh.get("n_tets", len(run.tets)),
        "chains": s.get("chains", run.u_b.shape[0]),
        "draws_per_chain": s.get("draws_per_chain", run.u_b.shape[1]),
        "thinning": s.get("thinning"), "steps_per_chain": s.get("steps_per_chain"),
        "acceptance": s.get("acceptance"), "wall_time_s": wall,
        "rhat_classic_max": s.get("rhat_classic_max"), "converged": s.get("converged"),
        "ess_bulk_min": s.get("ess_bulk_min"),
        "steps_per_s_per_chain": s.get("steps_per_s_per_chain"),
        # the run's verdict line (older runs: made from their figures)
        "verdict": s.get("verdict") or (verdict(s) if "rhat_rank_max" in s else None),
        "checks": (s.get("health") or {}).get("warnings", []) + [
            n for n in [normaliser_note(run.info)] if n],
    }


def _side_by_side(df: pd.DataFrame, paper: dict, runs: dict, nd: int) -> str:
    header = ["", *[h for c in df.columns for h in (c, f"{c} (paper)")]]
    rows = []
    for row, vals in df.iterrows():
        ref = paper.get(_paper_key(row, runs) or "", {})
        rows.append([row, *[x for c in df.columns for x in (_fmt(vals[c], nd), _fmt(ref.get(c), nd))]])
    return _md_table(header, rows)


_CAPTIONS = {
    "fig2_dataset.png": "Fig. 2 (paper): the synthetic dataset: images, labels (CSF red, GM "
    "green, WM yellow, skull gray), the mesh cut, divergence of the true field (collapse of "
    "the ventricles shows as its sign) and its x and y components.",
    "fig3_errors.png": "Fig. 3 (paper): norm of the error of the posterior-mean field and "
    "divergence of the posterior-mean field per model (common color scales).",
    "fig4_ratios.png": "Fig. 4 (paper): marginal posteriors of lam/mu, truth dashed. The paper "
    "found: " + PAPER["fig4"]["findings"] + ".",
    "fig5_boundary_node.png": "Fig. 5 (paper): marginal posterior of the displacement of the "
    "boundary node closest to the skull; the red line is where that component alone would take "
    "the node into the skull (the sampler rejects it: truncation).",
    "uncertainty.png": "Posterior uncertainty of the displacement over the fixed image.",
}


def _markdown(runs, summaries, t1, t2, cov, ratios, fig5) -> str:
    out = ["# Bayesian registration: reproduction of Risholm et al., Section 4", ""]
    out += ["## Runs", ""]
    keys = ["name", "elastic", "setup", "n_nodes", "n_boundary", "n_tets", "chains", "draws_per_chain",
            "thinning", "wall_time_s", "steps_per_s_per_chain", "rhat_classic_max", "converged"]
    ps = PAPER["setup"]
    rows = [[lab, *[s[k] if isinstance(s[k], str) else _fmt(s[k], 2) for k in keys]]
            for lab, s in summaries.items()]
    rows.append(["paper", "BrainWeb", "uniform / tissue",
                 "rwmh, quadrature 4 pts/tet, hard constraint, normaliser paper", ps["n_nodes"], ps["n_boundary"],
                 ps["n_tets"], ps["chains"], ps["draws_per_chain"], ps["thinning"],
                 f"~{ps['wall_time_h']} h", ps["steps_per_s_per_chain"],
                 f"< {ps['rhat_threshold']}", "yes"])
    out += [_md_table(["run", *keys], rows), "",
            "Paper columns: *Different Elastic Parameters* for runs with `elastic: tissue`, "
            "*Uniform Elastic Parameters* for `elastic: uniform`; – where the paper has no value.",
            ""]
    verdicts = [f"- **{lab}**: {s['verdict'].removeprefix('verdict: ')}"
                + "".join(f"; sampler check: {w}" for w in s.get("checks", []))
                for lab, s in summaries.items() if s.get("verdict")]
    if verdicts:
        out += ["Convergence (the run's stop rule, and today's: rank-normalised R-hat <= 1.01, "
                "bulk and tail ESS >= 400):", "", *verdicts, ""]
    if not any(str(i).startswith("initial") for i in t1.index):
        out += ["No initial configuration (`u_init` in mesh.vtu) in these runs: no initial rows.", ""]
    out += ["## Table 1: boundary-node error of the posterior mean (mm)", "",
            "Euclidean norm per boundary node of E[u_b] - u_true (initial: u_init - u_true).", "",
            _side_by_side(t1, PAPER["table1_mm"], runs, 3), ""]
    out += ["## Table 2: MSE of the deformation on the image grid (mm²)", "",
            "Mean over voxels of |E[u] - u_true|² over the brain (labels 1-3) and per tissue.", "",
            _side_by_side(t2, PAPER["table2_mm2"], runs, 4), ""]
    out += ["## Coverage of the true boundary displacements", "",
            "Fraction of the 3 x n_boundary true components inside the central credible "
            "interval (a calibrated posterior gives the nominal level).", "",
            _md_table(["run", *cov.columns], [[lab, *[_fmt(v, 3) for v in row]]
                                              for lab, row in cov.iterrows()]), ""]
    out += ["## Elastic ratios lam/mu", "",
            _md_table(["run", "group", *ratios.columns],
                      [[i[0], i[1], *[_fmt(v, 3) for v in row]] for i, row in ratios.iterrows()]),
            "", f"Paper (Fig. 4): true ratios CSF 1, GM 10, WM 30; {PAPER['fig4']['findings']}.", ""]
    lim = "; ".join(f"{'xyz'[a]} ({_fmt(lo, 2)}, {_fmt(hi, 2)})"
                    for a, (lo, hi) in enumerate(fig5["skull_limits_mm"]))
    out += ["## Figures", ""]
    for name, cap in _CAPTIONS.items():
        if name == "fig5_boundary_node.png":
            cap += (f" Run {fig5['run']}, mesh node {fig5['node']}; skull limits (lower, upper) "
                    f"per axis, mm (– = none within 30 mm): {lim}.")
        out += [f"![{name}]({name})", "", f"*{cap}*", ""]
    return "\n".join(out)


def write_report(runs: Mapping[str, str | Path], out: str | Path, *, overwrite: bool = False) -> Path:
    """Write the paper's Section 4 tables and figures for finished runs (module docstring).

    Parameters
    ----------
    runs : Mapping[str, str or Path]
        Model label (e.g. ``"uniform"``, ``"three_compartment"``) -> finished run directory
        (a :class:`RunData` is accepted too).  Each needs a synthetic truth.
    out : str or Path
        Report directory.  Written in a staging folder beside it and moved in place at the
        end (:class:`bayesreg.rundir.RunDirectory`).
    overwrite : bool
        Replace an existing non-empty ``out`` that holds a report (``report.json`` or
        ``report.md``); a folder of other files is never replaced.

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    NotADirectoryError
        ``out`` is a file.
    FileExistsError
        ``out`` exists, is not empty and ``overwrite`` is false, or holds no report.
    FileNotFoundError
        A run directory or one of its required files is missing (named).
    ValueError
        No runs, a run without synthetic truth (named), or ``out`` is or contains a run
        directory.
    """
    if not runs:
        raise ValueError("write_report needs at least one run")
    out = Path(out)
    for p in runs.values():
        rp = (p.path if isinstance(p, RunData) else Path(p)).resolve()
        if out.resolve() == rp or out.resolve() in rp.parents:
            raise ValueError(f"report directory {out} is or contains the run directory {rp}")
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"report directory {out} is a file: choose a folder for --out")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"report directory {out} exists and is not empty; pass "
                              "--overwrite (overwrite=True in Python) to replace it, or choose "
                              "another --out")
    data = as_runs(runs)  # fails (missing file, no truth) before anything is written
    rd = RunDirectory(out, overwrite=overwrite, marks=("report.json", "report.md"))
    try:
        _write(rd, data)
        return rd.commit()
    except BaseException:
        # a report is all or nothing: this one's files go, and a report it was to replace
        # (overwrite) comes back
        rd.rollback()
        raise


def _write(rd: RunDirectory, runs: dict) -> None:
    t1, t2, cov, ratios = table1(runs), table2(runs), coverage_table(runs), ratio_table(runs)
    t1.to_csv(rd.file("table1.csv"), index_label="row")
    t2.to_csv(rd.file("table2.csv"), index_label="row")
    cov.to_csv(rd.file("coverage.csv"), index_label="run")
    ratios.to_csv(rd.file("ratios.csv"))

    first = next(iter(runs.values()))
    k = slice_index(first)
    fig5_label = next((lab for lab, r in runs.items() if r.elastic == "tissue"), next(iter(runs)))
    figs = {
        "fig2_dataset.png": plot_dataset(first, k),
        "fig3_errors.png": plot_errors(runs, k),
        "fig4_ratios.png": plot_ratios(runs),
        "uncertainty.png": plot_uncertainty(runs, k),
    }
    figs["fig5_boundary_node.png"], fig5 = plot_boundary_node(runs[fig5_label])
    fig5["run"] = fig5_label
    for name, fig in figs.items():
        fig.savefig(rd.file(name), dpi=100)

    summaries = {lab: _run_summary(r) for lab, r in runs.items()}
    report = {
        "runs": summaries,
        "slice_k": k,
        "table1_mm": t1.to_dict(orient="index"),
        "table2_mm2": t2.to_dict(orient="index"),
        "coverage": cov.to_dict(orient="index"),
        "ratios": {f"{a}/{g}": v for (a, g), v in ratios.to_dict(orient="index").items()},
        "fig5": fig5,
        "paper": PAPER,
    }
    write_text_atomic(rd.file("report.json"), dumps_json(report, indent=2))
    rd.file("report.md").write_text(_markdown(runs, summaries, t1, t2, cov, ratios, fig5))
