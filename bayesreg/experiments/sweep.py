"""Many runs at once: a sweep over config keys on Dask distributed.

A sweep file names base configs and the keys to vary::

    name: paper_brainweb
    configs: [../paper_three_compartment_nuts.yaml, ../paper_uniform_nuts.yaml]
    set: {data.source: brainweb}              # applied to every run
    grid: {data.subject: [5, 6, 18, 20]}      # every combination, for every config
    runs: [{seed: 1}, {seed: 2}]              # and/or a list (combined with the grid)
    dir: runs/sweeps/paper_brainweb           # default runs/sweeps/NAME

Every run is an ordinary run directory (``DIR/<config>--<key>=<value>...``) made by
:func:`run_or_resume`: a finished run is reused, an unfinished one resumed, a missing one
made, so running a sweep again finishes what is left.  The runs are tasks of a
:mod:`distributed` client: a ``LocalCluster`` of one single-threaded worker process per core
by default, or the scheduler at an address (a cluster started by ``dask-jobqueue`` on
SLURM/PBS, one worker per GPU with ``dask-cuda``).  A run's failure is its row's ``error``;
it never stops the others.  After each run the sweep rewrites ``sweep.csv`` (one row per
run), ``sweep.md`` (per config: median and interquartile range over the runs that met
their stop rule from a good start, next to the paper's values; the other runs listed, never
averaged in), ``sweep_table1.png`` (each run's Table 1 as points, the paper's as lines) and
``sweep.json`` (the runs, their keys, status and errors).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import sys
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bayesreg._files import dumps_json, write_text_atomic
from bayesreg.checkpoint import Checkpoint
from bayesreg.config import Config, ConfigError, load_config
from bayesreg.config.loading import load_model_file
from bayesreg.outputs.result import RunResult
from bayesreg.outputs.printed import reference_method
from bayesreg.pipeline import run
from bayesreg.report.data import PAPER, load_run
from bayesreg.report.figures import plot_sweep_table1
from bayesreg.report.tables import coverage_table, ratio_table, table1, table2

__all__ = ["SweepSpec", "SweepRun", "load_sweep", "expand", "run_or_resume", "check_same_config",
           "run_one", "run_row", "run_sweep", "write_tables", "sweep_report", "THREAD_ENV"]

#: Environment of a sweep's worker processes: one thread per run (XLA, BLAS, OpenMP), so
#: that ``n`` workers on ``n`` cores do not oversubscribe them.
THREAD_ENV = {
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
    "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
}


class SweepSpec(BaseModel):
    """A sweep file (YAML), validated.  Paths in ``configs`` are relative to the file's
    folder; ``dir`` to the working directory."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(description="the sweep's name (default folder runs/sweeps/NAME)")
    configs: list[Path] = Field(min_length=1, description="base configs: every run of the grid "
                                "and list is made from each of them")
    set: dict[str, Any] = Field({}, description="dotted keys applied to every run (as --set)")
    grid: dict[str, list[Any]] = Field({}, description="dotted keys and their values: every "
                                       "combination is a run")
    runs: list[dict[str, Any]] = Field([], description="runs given as mappings of dotted keys, "
                                       "each combined with every point of the grid")
    dir: Path | None = Field(None, description="the sweep's folder (default runs/sweeps/NAME)")


class SweepRun(NamedTuple):
    """One run of a sweep: its id (the folder's name), base config, ``--set`` overrides,
    the keys that distinguish it, and its run directory."""

    id: str
    config: Path
    overrides: tuple[str, ...]
    keys: dict
    dir: Path


def load_sweep(path) -> SweepSpec:
    """Read and validate a sweep file; ``configs`` become absolute paths.

    Raises
    ------
    FileNotFoundError
        The file or one of its configs does not exist.
    ConfigError
        Bad YAML, an unknown key, a grid key with no values (the message names it).
    """
    path = Path(path)
    spec = load_model_file(path, SweepSpec, what="sweep file")
    empty = [k for k, v in spec.grid.items() if not v]
    if empty:
        raise ConfigError(f"{path}: grid key(s) {empty} have no values")
    configs = [(path.parent / c).resolve() if not c.is_absolute() else c for c in spec.configs]
    missing = [str(c) for c in configs if not c.is_file()]
    if missing:
        raise FileNotFoundError(f"{path}: config(s) not found: {', '.join(missing)}")
    return spec.model_copy(update={"configs": configs,
                                   "dir": spec.dir or Path("runs/sweeps") / spec.name})


def _value(v) -> str:
    """A value as a ``--set`` item's YAML (JSON is YAML)."""
    return json.dumps(v) if not isinstance(v, Path) else json.dumps(str(v))


def _slug(v) -> str:
    return re.sub(r"[^A-Za-z0-9._+-]+", "_", str(v)).strip("_") or "_"


def expand(spec: SweepSpec) -> list[SweepRun]:
    """The runs of a sweep: every config times every point of ``runs`` (or one empty point)
    times every combination of ``grid``; ids ``<config stem>--<key>=<value>...`` with each
    key's last dotted name (its full name where two would clash).

    Raises
    ------
    ConfigError
        Two runs with the same id (the same config and keys twice).
    """
    grid_keys = list(spec.grid)
    points = spec.runs or [{}]
    varied = list(dict.fromkeys([k for p in points for k in p] + grid_keys))
    last = [k.rsplit(".", 1)[-1] for k in varied]
    short = {k: (s if last.count(s) == 1 else k) for k, s in zip(varied, last)}
    out, seen = [], set()
    for config in spec.configs:
        for point in points:
            for combo in itertools.product(*spec.grid.values()):
                keys = {**point, **dict(zip(grid_keys, combo))}
                rid = "--".join([config.stem] + [f"{short[k]}={_slug(keys[k])}" for k in varied if k in keys])
                if rid in seen:
                    raise ConfigError(f"sweep {spec.name}: run {rid} appears twice")
                seen.add(rid)
                overrides = tuple(f"{k}={_value(v)}" for k, v in {**spec.set, **keys}.items())
                out.append(SweepRun(rid, config, overrides, keys, Path(spec.dir) / rid))
    return out


def _flat(d: dict, prefix="") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def check_same_config(config, out: Path, overrides) -> None:
    """Refuse to reuse or resume the run in ``out`` if its config is not ``config`` with
    ``overrides`` (``output.*`` aside: where and how it was written).

    Raises
    ------
    ValueError
        The configs differ (up to five differing keys named), or the run's saved config
        cannot be read.
    """
    want = load_config(config, overrides=overrides)
    ckpt = Checkpoint(out)
    try:
        if ckpt.config_path.is_file():
            have = ckpt.load_config()
        else:  # a finished run written without checkpoints: its run.json has the config
            have = Config.model_validate(json.loads((out / "run.json").read_text())["config"])
    except (ConfigError, ValueError, KeyError) as exc:
        raise ValueError(f"{out}: the run's config cannot be read back to compare it with "
                         f"{config} ({exc}); choose another --out") from None
    a, b = (_flat({k: v for k, v in c.model_dump(mode="json").items() if k != "output"})
            for c in (have, want))
    diff = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
    if diff:
        shown = "; ".join(f"{k}: {a.get(k)!r} there, {b.get(k)!r} asked" for k in diff[:5])
        raise ValueError(f"{out} holds a run of another config ({shown}"
                         f"{'; ...' if len(diff) > 5 else ''}): choose another --out, or remove "
                         "that run to make this one")


def run_or_resume(config, out: Path, overrides, progress, *, quiet: bool = False) -> tuple[RunResult, str]:
    """Run ``config`` into ``out``; resume it if unfinished; reuse it if finished (either
    only if it was made with ``config`` and ``overrides``: :func:`check_same_config`).

    Returns
    -------
    result : RunResult
        For a reused run, only ``dir`` and ``info`` (its ``run.json``).
    action : str
        ``"reused"``, ``"resumed"`` or ``"new"``.
    """
    out = Path(out)
    say = (lambda msg: None) if quiet else print
    if (out / "run.json").is_file() or (out / "checkpoint" / "config.json").is_file():
        check_same_config(config, out, overrides)
    if (out / "run.json").is_file():
        say(f"{out}: finished run found, reused")
        return RunResult(out, None, None, None, json.loads((out / "run.json").read_text())), "reused"
    if (out / "checkpoint" / "config.json").is_file():
        say(f"{out}: unfinished run found, resumed")
        return run(resume=out, progress=progress), "resumed"
    return run(config, out=out, overrides=list(overrides), progress=progress), "new"


def _quantiles(x) -> dict:
    return {"median": float(np.median(x)), "q95": float(np.quantile(x, 0.95)), "max": float(np.max(x))}


def run_row(run_dir) -> dict:
    """The figures of one finished run, flat (``sweep.csv``'s columns after the keys).

    Sampler: ``converged`` (its stop rule met), ``rhat_rank_max``, ``rhat_classic_max``,
    ``ess_bulk_min``, ``divergences``, ``draws_per_chain``; start: ``start_median_mm``
    (boundary nodes, chains' start to the truth); ``brain_mse_posterior_mean``,
    ``brain_mse_start``, ``brain_mse_reference`` (mm^2 over the brain's voxels; the
    reference is the run's ``output.reference`` on the same images, named in ``reference``:
    ``tvl1``, ``ilk`` or ``syn``), ``boundary_reference_q95`` (mm, the reference's error at
    the boundary nodes, 95th percentile) and ``coverage_moving_90`` (where the truth moves
    the tissue at least 1 mm), and for a dense truth the mesh's best fit to it
    (``brain_mse_best_fit``, mm^2, and ``coverage_best_fit_90``, its coverage where the
    tissue moves: :func:`bayesreg.outputs.fields.mesh_best_fit`), from ``errors.json``; Table 1: ``t1_median``, ``t1_q95``,
    ``t1_max`` (mm); Table 2: ``t2_brain``, ``t2_csf``, ``t2_gm``, ``t2_wm`` (mm^2);
    ``coverage_90`` (boundary components inside their 90% intervals); per elastic group
    ``G`` with a true ratio: ``ratio_G_median``, ``ratio_G_q05``, ``ratio_G_q95``,
    ``ratio_G_true``, ``ratio_G_inside`` (the truth in the 90% interval); the truth's
    ``truth_energy`` and ``truth_n_active``; ``run_s`` (the run's own wall time).  Without a
    synthetic truth, the truth's columns are absent.
    """
    run_dir = Path(run_dir)
    info = json.loads((run_dir / "run.json").read_text())
    s = info.get("sampler", {})
    row = {"converged": s.get("converged"), "rhat_rank_max": s.get("rhat_rank_max"),
           "rhat_classic_max": s.get("rhat_classic_max"), "ess_bulk_min": s.get("ess_bulk_min"),
           "divergences": s.get("divergences"), "draws_per_chain": s.get("draws_per_chain"),
           "stuck_chains": len(s.get("stuck_chains") or []),
           "n_nodes": info.get("mesh", {}).get("n_nodes"),
           "run_s": info.get("timings_s", {}).get("total_before_outputs_s")}
    truth = info.get("truth") or {}
    for k in ("energy", "n_active"):
        if k in truth:
            row[f"truth_{k}"] = truth[k]
    errors = info.get("errors") or {}
    start = errors.get("boundary_initial_mm") or {}
    if "median" in start:
        row["start_median_mm"] = start["median"]
    brain = errors.get("brain") or {}
    for field, mse in (brain.get("mse_mm2") or {}).items():  # posterior_mean, start, reference
        row[f"brain_mse_{field}"] = mse
    if "boundary_reference_mm" in errors:
        row["reference"] = reference_method(errors)
        row["boundary_reference_q95"] = errors["boundary_reference_mm"]["q95"]
    if errors.get("coverage_moving"):
        row["coverage_moving_90"] = errors["coverage_moving"]["0.9"]
    best = errors.get("mesh_best_fit") or {}
    if best.get("coverage_moving"):
        row["coverage_best_fit_90"] = best["coverage_moving"]["0.9"]
    if "brain_mse_mm2" in best:
        row["brain_mse_best_fit"] = best["brain_mse_mm2"]
    if not (run_dir / "displacement_true.nii.gz").is_file():
        return row
    data = load_run(run_dir)
    runs = {"run": data}
    t1 = table1(runs).loc["run"]
    row.update({f"t1_{k}": float(t1[k]) for k in ("median", "q95", "max")})
    t2 = table2(runs).loc["run"]
    row.update({f"t2_{k}": float(t2[k]) for k in t2.index})
    row["coverage_90"] = float(coverage_table(runs).loc["run", "90%"])
    for (_, group), r in ratio_table(runs).iterrows():
        if math.isnan(r["true"]):
            continue
        row.update({f"ratio_{group}_median": float(r["median"]), f"ratio_{group}_q05": float(r["q05"]),
                    f"ratio_{group}_q95": float(r["q95"]), f"ratio_{group}_true": float(r["true"]),
                    f"ratio_{group}_inside": bool(r["q05"] <= r["true"] <= r["q95"])})
    return row


def run_one(config, overrides, out, *, max_start_mm: float | None = None) -> dict:
    """Make (or resume, or reuse) one run of a sweep and return its row; never raises.

    The task a sweep gives its workers.  ``status`` is ``finished`` (the stop rule met),
    ``unconverged`` (it was not: the figures are those of chains that did not meet it),
    ``bad start`` (the chains' start lies more than ``max_start_mm`` from the truth, median
    over the boundary nodes) or ``failed`` (``error`` holds the message, which names the
    stage); ``action`` says whether the run was ``new``, ``resumed`` or ``reused``;
    ``wall_s`` is this task's time; ``warnings`` the run's warnings, one per line.
    """
    t = time.perf_counter()
    row: dict = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            res, action = run_or_resume(Path(config), Path(out), list(overrides), False, quiet=True)
            row = {"action": action, **run_row(res.dir)}
            status = "finished" if row.get("converged") else "unconverged"
            if row.get("stuck_chains"):
                status = "failed"
                row["error"] = f"sampling: {row['stuck_chains']} chain(s) never moved"
            elif (max_start_mm is not None and row.get("start_median_mm") is not None
                  and row["start_median_mm"] > max_start_mm):
                status = "bad start"
            row["status"] = status
        except Exception as exc:  # noqa: BLE001 - a run's failure is its row, never the sweep's
            row = {"status": "failed", "error": f"{type(exc).__name__}: {exc}".strip()}
    row["wall_s"] = time.perf_counter() - t
    seen = dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in caught)
    row["warnings"] = "\n".join(seen)
    return row


# the aggregate: which columns, against which of the paper's figures
_SUMMARY = [
    ("chains' start to truth, median (mm)", "start_median_mm", None),
    ("Table 1 median (mm)", "t1_median", ("table1_mm", "median")),
    ("Table 1 95th percentile (mm)", "t1_q95", ("table1_mm", "q95")),
    ("Table 1 max (mm)", "t1_max", ("table1_mm", "max")),
    ("Table 2 brain MSE (mm^2)", "t2_brain", ("table2_mm2", "brain")),
    ("Table 2 CSF (mm^2)", "t2_csf", ("table2_mm2", "csf")),
    ("Table 2 GM (mm^2)", "t2_gm", ("table2_mm2", "gm")),
    ("Table 2 WM (mm^2)", "t2_wm", ("table2_mm2", "wm")),
    ("brain MSE of the posterior mean (mm^2)", "brain_mse_posterior_mean", None),
    ("brain MSE of the reference registration (mm^2)", "brain_mse_reference", None),
    ("reference's boundary-node error, 95th percentile (mm)", "boundary_reference_q95", None),
    ("boundary coverage of 90% intervals", "coverage_90", None),
    ("coverage of 90% intervals where the tissue moves", "coverage_moving_90", None),
    ("brain MSE of the mesh's best fit to a dense truth (mm^2)", "brain_mse_best_fit", None),
    ("coverage of the mesh's best fit where the tissue moves", "coverage_best_fit_90", None),
    ("lam/mu GM, posterior median", "ratio_gm_median", None),
    ("lam/mu WM, posterior median", "ratio_wm_median", None),
    ("R-hat (rank-normalised), max", "rhat_rank_max", None),
    ("bulk ESS, min", "ess_bulk_min", None),
    ("wall time per run (s)", "run_s", None),
]


def _fmt(v, nd=3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, float):
        return f"{v:.{nd}g}" if abs(v) >= 1000 else f"{v:.{nd}f}"
    return str(v)


def _numbers(rows, col) -> np.ndarray:
    x = [r.get(col) for r in rows]
    return np.array([v for v in x if isinstance(v, (int, float)) and not isinstance(v, bool)
                     and math.isfinite(v)], np.float64)


def _paper_key(rows: list) -> str | None:
    """The paper's model (``"tissue"`` or ``"uniform"``) a config's runs reproduce, from the
    first of their ``rows`` that says (``elastic``); None for any other model."""
    elastic = next((row.get("elastic") for row in rows if row.get("elastic")), None)
    return elastic if elastic in ("tissue", "uniform") else None


def _markdown(name: str, runs: list[SweepRun], rows: dict) -> str:
    lines = [f"# Sweep {name}", ""]
    by_config: dict[str, list] = {}
    for r in runs:
        by_config.setdefault(r.config.stem, []).append(r)
    status = [rows.get(r.id, {}).get("status", "not run") for r in runs]
    counts = {s: status.count(s) for s in dict.fromkeys(status)}
    lines += ["Runs: " + ", ".join(f"{n} {s}" for s, n in counts.items()) + f" (of {len(runs)}).", ""]
    for stem, rs in by_config.items():
        # only runs that met their stop rule from a good start are results: an unconverged
        # run, a bad start or a failure is listed below, never averaged in
        done = [rows[r.id] for r in rs if rows.get(r.id, {}).get("status") == "finished"]
        left = [rows.get(r.id, {}).get("status", "not run") for r in rs]
        left = {st: left.count(st) for st in dict.fromkeys(left) if st != "finished"}
        paper_key = _paper_key([rows.get(r.id, {}) for r in rs])
        excluded = ("" if not left else " Left out (below, run by run): "
                    + ", ".join(f"{n} {st}" for st, n in left.items()) + ".")
        lines += [f"## {stem}", "",
                  f"{len(done)} of {len(rs)} runs met their stop rule from a good start; median "
                  f"and interquartile range over them, the paper's value where it reports one."
                  + excluded, "",
                  "| figure | median | IQR | paper |", "|---|---|---|---|"]
        for label, col, paper in _SUMMARY:
            x = _numbers(done, col)
            if not len(x):
                continue
            ref = "-"
            if paper and paper_key:
                ref = _fmt(PAPER[paper[0]].get(paper_key, {}).get(paper[1]))
            lines.append(f"| {label} | {_fmt(float(np.median(x)))} | {_fmt(float(np.quantile(x, 0.25)))}"
                         f"-{_fmt(float(np.quantile(x, 0.75)))} | {ref} |")
        for g in ("csf", "gm", "wm"):
            inside = [r.get(f"ratio_{g}_inside") for r in done if r.get(f"ratio_{g}_inside") is not None]
            if inside:
                lines.append(f"| lam/mu {g.upper()} truth inside the 90% interval | {sum(inside)} of "
                             f"{len(inside)} | | |")
        lines.append("")
        lines += ["| run | status | Table 1 median / q95 / max | brain MSE | GM ratio 90% | WM ratio 90% "
                  "| R-hat | wall s |", "|---|---|---|---|---|---|---|---|"]
        for r in rs:
            row = rows.get(r.id, {})
            ratio = {g: (f"{_fmt(row.get(f'ratio_{g}_q05'), 2)}-{_fmt(row.get(f'ratio_{g}_q95'), 2)}"
                         if f"ratio_{g}_q05" in row else "-") for g in ("gm", "wm")}
            t1 = "-" if "t1_median" not in row else " / ".join(_fmt(row[f"t1_{k}"], 2) for k in ("median", "q95", "max"))
            stat = row.get("status", "not run")
            if stat == "failed":
                stat += ": " + str(row.get("error", ""))[:120].replace("|", "/").replace("\n", " ")
            lines.append(f"| {r.id} | {stat} | {t1} | {_fmt(row.get('t2_brain'))} | {ratio['gm']} | "
                         f"{ratio['wm']} | {_fmt(row.get('rhat_rank_max'))} | {_fmt(row.get('wall_s'), 0)} |")
        lines.append("")
    lines += _pairs(by_config, rows)
    return "\n".join(lines) + "\n"


def _pairs(by_config: dict, rows: dict) -> list[str]:
    """Brain MSE of each config against each other one, over the runs with the same keys
    where both met their stop rule."""
    stems = list(by_config)
    if len(stems) < 2:
        return []
    out = ["## Configs compared, run by run", "", "| brain MSE lower | than | on |", "|---|---|---|"]
    for a, b in itertools.permutations(stems, 2):
        pairs = []
        for ra in by_config[a]:
            rb = next((r for r in by_config[b] if r.keys == ra.keys), None)
            if rb is None:
                continue
            row_a, row_b = rows.get(ra.id, {}), rows.get(rb.id, {})
            if "finished" != row_a.get("status") or "finished" != row_b.get("status"):
                continue  # a pair is a result only where both met their rule
            xa, xb = row_a.get("t2_brain"), row_b.get("t2_brain")
            if isinstance(xa, float) and isinstance(xb, float):
                pairs.append(xa < xb)
        if pairs:
            out.append(f"| {a} | {b} | {sum(pairs)} of {len(pairs)} |")
    return out + [""]


def write_tables(name: str, runs: list[SweepRun], rows: dict, out) -> None:
    """Write ``sweep.csv``, ``sweep.md`` and ``sweep.json`` of ``rows`` (``{run id: row}``)
    into ``out`` (atomically, so an interrupted sweep leaves the last complete tables), and
    ``sweep_table1.png`` (:func:`bayesreg.report.figures.plot_sweep_table1`) once a run has
    Table 1's figures."""
    import pandas as pd

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    records = []
    for r in runs:
        row = rows.get(r.id, {"status": "not run"})
        records.append({"id": r.id, "config": r.config.stem, **{k: r.keys.get(k) for k in _keys(runs)},
                        **row})
    df = pd.DataFrame.from_records(records)
    write_text_atomic(out / "sweep.csv", df.to_csv(index=False))
    write_text_atomic(out / "sweep.md", _markdown(name, runs, rows))
    by_config: dict[str, list] = {}
    for r in runs:
        row = rows.get(r.id, {})
        by_config.setdefault(r.config.stem, []).append(
            {"id": r.id, "label": "-".join(_value(v) for v in r.keys.values()) or r.id, **row})
    if any(isinstance(row.get("t1_median"), (int, float)) for rs in by_config.values() for row in rs):
        paper = {stem: PAPER["table1_mm"][key] for stem, rs in by_config.items()
                 if (key := _paper_key(rs))}
        fig = plot_sweep_table1(by_config, paper)
        tmp = out / ".sweep_table1.png"
        fig.savefig(tmp, dpi=110)
        tmp.replace(out / "sweep_table1.png")
    state = {"name": name, "runs": [{"id": r.id, "config": str(r.config), "overrides": list(r.overrides),
                                     "keys": r.keys, "dir": str(r.dir), **rows.get(r.id, {})} for r in runs]}
    write_text_atomic(out / "sweep.json", dumps_json(state, indent=1))


def _keys(runs) -> list[str]:
    return list(dict.fromkeys(k for r in runs for k in r.keys))


def _client(scheduler, workers):
    """A :class:`distributed.Client` on ``scheduler`` (an address) or on a new
    ``LocalCluster`` of ``workers`` single-threaded processes (default one per core)."""
    from distributed import Client, LocalCluster

    if scheduler is not None:
        return Client(scheduler), None
    n = workers or os.cpu_count() or 1
    env = {**THREAD_ENV, "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} {THREAD_ENV['XLA_FLAGS']}".strip()}
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           dashboard_address=None, env=env)
    return Client(cluster), cluster


def run_sweep(path, *, scheduler: str | None = None, workers: int | None = None,
              max_start_mm: float | None = 1.0, log=None) -> tuple[Path, dict]:
    """Run (or finish) the sweep of a sweep file on Dask distributed.

    Parameters
    ----------
    path : str or Path
        The sweep file (:class:`SweepSpec`).
    scheduler : str, optional
        A Dask scheduler's address (``tcp://host:8786``); default a ``LocalCluster``.
    workers : int, optional
        Worker processes of the ``LocalCluster`` (default one per core).
    max_start_mm : float, optional
        A run whose chains started further than this from the truth (median over boundary
        nodes) has status ``bad start``; None: not checked.
    log : file, optional
        Where progress goes (default standard error): one line per finished run (done /
        failed / running of all).

    Returns
    -------
    folder : Path
        The sweep's folder (``sweep.csv``, ``sweep.md``, ``sweep.json`` and the runs).
    rows : dict
        ``{run id: row}`` (:func:`run_one`).

    Raises
    ------
    ConfigError, FileNotFoundError
        A bad sweep file, or a run's config that does not validate (checked for every run
        before any starts).

    Examples
    --------
    >>> from bayesreg.experiments.sweep import run_sweep
    >>> folder, rows = run_sweep("configs/sweeps/paper_brainweb.yaml")  # doctest: +SKIP
    """
    log = sys.stderr if log is None else log
    spec = load_sweep(path)
    runs = expand(spec)
    for r in runs:  # every config validates before any run starts
        try:
            load_config(r.config, overrides=list(r.overrides))
        except ConfigError as exc:
            raise ConfigError(f"sweep run {r.id}: {exc}") from None
    folder = Path(spec.dir)
    previous = {}
    if (folder / "sweep.json").is_file():
        try:
            previous = {r["id"]: r for r in json.loads((folder / "sweep.json").read_text())["runs"]}
        except (ValueError, KeyError):
            previous = {}
    rows: dict = {}
    for r in runs:  # keep what an earlier pass said of a run until this pass says otherwise
        if r.id in previous:
            rows[r.id] = {k: v for k, v in previous[r.id].items()
                          if k not in ("id", "config", "overrides", "keys", "dir")}
    write_tables(spec.name, runs, rows, folder)
    client, cluster = _client(scheduler, workers)
    try:
        from distributed import as_completed

        futures = {}
        for r in runs:
            fut = client.submit(run_one, str(r.config), r.overrides, str(r.dir.resolve()),
                                max_start_mm=max_start_mm, pure=False, key=f"bayesreg-run-{r.id}-{time.time_ns()}")
            futures[fut] = r
        done = failed = 0
        print(f"sweep {spec.name}: {len(runs)} runs on {len(client.scheduler_info()['workers'])} "
              f"worker(s); tables in {folder}", file=log, flush=True)
        for fut in as_completed(futures):
            r = futures[fut]
            try:
                row = fut.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker (killed, out of memory)
                row = {"status": "failed", "error": f"worker: {type(exc).__name__}: {exc}"}
            cfg_elastic = _config_elastic(r)
            rows[r.id] = {"elastic": cfg_elastic, **row}
            done += 1
            failed += row["status"] == "failed"
            write_tables(spec.name, runs, rows, folder)
            what = row["status"] + (f" ({row.get('action')})" if row.get("action") else "")
            if row["status"] == "failed":
                what += f": {row.get('error', '')}"
            print(f"[{done}/{len(runs)} done, {failed} failed, {len(runs) - done} running or "
                  f"waiting] {r.id}: {what}", file=log, flush=True)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return folder, rows


def _config_elastic(r: SweepRun) -> str | None:
    try:
        return load_config(r.config, overrides=list(r.overrides)).model.elastic
    except (ConfigError, OSError):
        return None


def sweep_report(folder, out=None) -> Path:
    """Rebuild a sweep's tables from its run directories (``bayesreg report SWEEP_DIR``).

    Every finished run's row is read again from its directory (:func:`run_row`); a run with
    no directory keeps what ``sweep.json`` said of it (its error).  Writes ``sweep.csv``,
    ``sweep.md`` and ``sweep.json`` into ``out`` (default the sweep's folder).

    Raises
    ------
    FileNotFoundError
        ``folder`` holds no ``sweep.json``.
    """
    folder = Path(folder)
    if not (folder / "sweep.json").is_file():
        raise FileNotFoundError(f"{folder}: no sweep.json (not a sweep's folder)")
    state = json.loads((folder / "sweep.json").read_text())
    runs, rows = [], {}
    for e in state["runs"]:
        r = SweepRun(e["id"], Path(e["config"]), tuple(e["overrides"]), e["keys"], Path(e["dir"]))
        runs.append(r)
        row = {k: v for k, v in e.items() if k not in ("id", "config", "overrides", "keys", "dir")}
        if (r.dir / "run.json").is_file():
            fresh = run_row(r.dir)
            row.update(fresh)
            if row.get("status") in (None, "not run"):
                row["status"] = "finished" if fresh.get("converged") else "unconverged"
        rows[r.id] = row
    out = folder if out is None else Path(out)
    write_tables(state["name"], runs, rows, out)
    return out
