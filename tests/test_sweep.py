"""bayesreg.experiments.sweep: the grid of a sweep file, and a sweep on a Dask LocalCluster (one run
failing, isolated; a second pass reusing the finished runs; the aggregate tables)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import yaml

from bayesreg.cli import main
from bayesreg.config import ConfigError
from bayesreg.experiments.sweep import expand, load_sweep, run_sweep

CONFIGS = Path(__file__).resolve().parents[1] / "configs"

# the quickstart's problem on tiny settings (as bayesreg.run's example)
TINY = {"data.resolution_mm": 3.0, "mesh.edge_length_mm": 26, "sampler.kind": "rwmh",
        "sampler.chains": 2, "sampler.proposal": "isotropic", "init.method": "perturb",
        "sampler.warmup_steps": 20, "sampler.thinning": 1, "sampler.chunk_draws": 10,
        "sampler.max_draws": 10, "sampler.min_draws": 10, "output.progress": False,
        "output.reference": False}


def _write(path: Path, spec: dict) -> Path:
    path.write_text(yaml.safe_dump(spec))
    return path


def test_expand_gives_every_combination_with_readable_ids(tmp_path):
    spec = _write(tmp_path / "s.yaml", {
        "name": "s", "configs": [str(CONFIGS / "paper_uniform.yaml"), str(CONFIGS / "paper_three_compartment.yaml")],
        "set": {"data.source": "brainweb"}, "grid": {"data.subject": [5, 43], "seed": [1, 2]},
        "dir": str(tmp_path / "out")})
    runs = expand(load_sweep(spec))
    assert len(runs) == 8
    assert runs[0].id == "paper_uniform--subject=5--seed=1"
    assert runs[0].overrides == ('data.source="brainweb"', "data.subject=5", "seed=1")
    assert runs[-1].id == "paper_three_compartment--subject=43--seed=2"
    assert runs[-1].dir == tmp_path / "out" / runs[-1].id
    assert len({r.id for r in runs}) == 8


def test_a_list_combines_with_the_grid_and_clashing_names_stay_apart(tmp_path):
    spec = _write(tmp_path / "s.yaml", {
        "name": "s", "configs": [str(CONFIGS / "quickstart.yaml")],
        "runs": [{"model.prior_lam.r2": 50}, {"model.prior_mu.r2": 5}], "grid": {"seed": [0, 1]}})
    runs = expand(load_sweep(spec))
    assert [r.id for r in runs] == [
        "quickstart--model.prior_lam.r2=50--seed=0", "quickstart--model.prior_lam.r2=50--seed=1",
        "quickstart--model.prior_mu.r2=5--seed=0", "quickstart--model.prior_mu.r2=5--seed=1"]
    assert runs[0].dir == Path("runs/sweeps/s") / runs[0].id


@pytest.mark.parametrize("spec, message", [
    ({"name": "s", "configs": ["nope.yaml"]}, "not found"),
    ({"name": "s", "configs": [str(CONFIGS / "quickstart.yaml")], "grids": {}}, "grids"),
    ({"name": "s", "configs": [str(CONFIGS / "quickstart.yaml")], "grid": {"seed": []}}, "no values"),
    ({"name": "s", "configs": [str(CONFIGS / "quickstart.yaml")], "runs": [{"seed": 1}, {"seed": 1}]},
     "twice"),
])
def test_bad_sweep_files_are_refused_naming_the_problem(tmp_path, spec, message):
    path = _write(tmp_path / "s.yaml", spec)
    with pytest.raises((ConfigError, FileNotFoundError), match=message):
        expand(load_sweep(path))


def test_a_run_whose_config_does_not_validate_stops_the_sweep_before_any_run(tmp_path):
    path = _write(tmp_path / "s.yaml", {"name": "s", "configs": [str(CONFIGS / "quickstart.yaml")],
                                         "runs": [{"seed": 1}, {"sampler.chains": 0}],
                                         "dir": str(tmp_path / "out")})
    with pytest.raises(ConfigError, match=r"(?s)sweep run quickstart--chains=0:.*sampler\.chains"):
        run_sweep(path)
    assert not (tmp_path / "out").exists()


def _rows(folder: Path) -> dict:
    with open(folder / "sweep.csv") as fh:
        return {r["id"]: r for r in csv.DictReader(fh)}


@pytest.mark.slow
@pytest.mark.xdist_group("tiny_run")  # after the CLI's tiny run: its programs are cached
def test_a_sweep_on_a_local_cluster_isolates_a_failure_and_resumes(tmp_path, capsys, tiny_mesh):
    """Two tiny runs on a two-worker LocalCluster, one with a truth pushed into the skull:
    that run fails in its truth stage and the other finishes; a second pass reuses the
    finished run and tries the failed one again; the tables hold every run."""
    out = tmp_path / "sweep"
    path = _write(tmp_path / "tiny.yaml", {
        "name": "tiny", "configs": [str(CONFIGS / "quickstart.yaml")],
        "set": {**TINY, "mesh.file": tiny_mesh},
        "runs": [{"seed": 1}, {"seed": 4, "synthetic.shift_mm": 60}],
        "dir": str(out)})
    folder, rows = run_sweep(path, workers=2)
    assert folder == out
    bad = "quickstart--seed=4--shift_mm=60"
    assert rows[bad]["status"] == "failed"
    assert rows[bad]["error"].startswith("ValueError: truth:") and "skull" in rows[bad]["error"]
    good = [k for k in rows if k != bad]
    assert len(good) == 1
    for k in good:
        assert rows[k]["status"] in ("finished", "unconverged"), rows[k]
        assert rows[k]["action"] == "new"
        assert (out / k / "run.json").is_file() and (out / k / "posterior.nc").is_file()
    assert not (out / bad).exists()  # a run failed before sampling leaves no directory
    table = _rows(out)
    assert set(table) == set(rows)
    assert table[bad]["status"] == "failed" and table[bad]["t1_median"] == ""
    for k in good:
        info = json.loads((out / k / "run.json").read_text())
        assert float(table[k]["rhat_rank_max"]) == pytest.approx(info["sampler"]["rhat_rank_max"])
        assert float(table[k]["t1_median"]) > 0 and float(table[k]["t2_brain"]) > 0
        assert table[k]["ratio_gm_inside"] in ("True", "False")
        mse = info["errors"]["brain"]["mse_mm2"]  # (no TV-L1 here: output.reference false)
        assert float(table[k]["brain_mse_posterior_mean"]) == pytest.approx(mse["posterior_mean"])
        assert table[k].get("brain_mse_reference", "") == ""
    md = (out / "sweep.md").read_text()
    assert "1 failed" in md and (out / "sweep_table1.png").is_file()
    if rows[good[0]]["status"] == "finished":  # a result: in the medians, beside the paper's
        assert "Table 1 median (mm)" in md and "| 0.160 |" in md
    else:  # listed with its status, not averaged in
        assert "Left out (below, run by run): 1 unconverged, 1 failed." in md
        assert f"| {good[0]} | unconverged |" in md
    err = capsys.readouterr().err
    assert "[2/2 done, 1 failed" in err

    mtimes = {k: (out / k / "run.json").stat().st_mtime_ns for k in good}
    _, again = run_sweep(path, workers=2)
    assert {k: again[k]["action"] for k in good} == dict.fromkeys(good, "reused")
    assert {k: (out / k / "run.json").stat().st_mtime_ns for k in good} == mtimes
    assert again[bad]["status"] == "failed"
    for k in good:
        assert again[k]["t1_median"] == pytest.approx(rows[k]["t1_median"])

    # the tables, rebuilt from the run directories by `bayesreg report SWEEP_DIR`
    (out / "sweep.csv").unlink()
    assert main(["report", str(out)]) == 0
    assert set(_rows(out)) == set(rows)


def test_the_tables_average_only_runs_that_met_their_rule(tmp_path):
    """``sweep.md``'s medians are over the runs that met their stop rule from a good start; an
    unconverged run, a bad start, a failure and a run not yet made are listed run by run and
    counted as left out, never averaged in (an unconverged run's wild Table 1 would move
    the median); the configs' run-by-run comparison counts only pairs that both met their
    rule; ``sweep_table1.png`` draws every run with figures."""
    from bayesreg.experiments.sweep import SweepRun, write_tables

    def run(stem, subject):
        return SweepRun(f"{stem}--subject={subject}", Path(f"{stem}.yaml"), (), {"data.subject": subject},
                        tmp_path / f"{stem}-{subject}")

    def figures(t1, brain):
        return {"t1_median": t1, "t1_q95": 4 * t1, "t1_max": 10 * t1, "t2_brain": brain,
                "converged": True}

    tissue = [run("three", s) for s in (4, 5, 6, 18, 20, 38)]
    uniform = [run("uniform", s) for s in (4, 5, 6, 18, 20, 38)]
    rows = {
        tissue[0].id: {"status": "finished", "elastic": "tissue", **figures(0.10, 0.030)},
        tissue[1].id: {"status": "finished", "elastic": "tissue", **figures(0.20, 0.040)},
        tissue[2].id: {"status": "finished", "elastic": "tissue", **figures(0.30, 0.050)},
        tissue[3].id: {"status": "unconverged", "elastic": "tissue", **figures(9.0, 9.0), "converged": False},
        tissue[4].id: {"status": "bad start", "elastic": "tissue", **figures(5.0, 5.0)},
        tissue[5].id: {"status": "failed", "error": "ValueError: truth: no"},
        uniform[0].id: {"status": "finished", "elastic": "uniform", **figures(0.15, 0.060)},
        uniform[1].id: {"status": "finished", "elastic": "uniform", **figures(0.25, 0.020)},
        uniform[3].id: {"status": "finished", "elastic": "uniform", **figures(0.25, 0.070)},
    }
    write_tables("ten", tissue + uniform, rows, tmp_path)
    md = (tmp_path / "sweep.md").read_text()
    three = md.split("## three")[1].split("## uniform")[0]
    assert "3 of 6 runs met their stop rule from a good start" in three
    assert "Left out (below, run by run): 1 unconverged, 1 bad start, 1 failed." in three
    assert "| Table 1 median (mm) | 0.200 | 0.150-0.250 | 0.160 |" in three
    assert "| Table 2 brain MSE (mm^2) | 0.040 | 0.035-0.045 | 0.040 |" in three
    for r in tissue[3:]:
        assert f"| {r.id} | {rows[r.id]['status']}" in three  # each listed with its status
    uni = md.split("## uniform")[1].split("## Configs")[0]
    assert "3 of 6 runs met" in uni and "3 not run" in uni
    # subjects 4 and 5 met the rule in both: three is lower on 4, uniform on 5 (18: three's
    # run did not meet its rule, no pair)
    assert "| three | uniform | 1 of 2 |" in md and "| uniform | three | 1 of 2 |" in md
    assert (tmp_path / "sweep_table1.png").stat().st_size > 10_000


def test_the_shipped_sweeps_validate_every_run():
    """``configs/sweeps/*.yaml``: every run's config validates (as the sweep checks before
    its first run), e.g. the mismatch benchmarks: two truths the model did not make and an FE
    truth plus a random field, each on MNI152 and three BrainWeb brains, with ANTs SyN as the
    reference."""
    from bayesreg.config import load_config

    for path in sorted((CONFIGS / "sweeps").glob("*.yaml")):
        runs = expand(load_sweep(path))
        assert runs, path
        for r in runs:
            load_config(r.config, overrides=list(r.overrides))
    mismatch = [load_config(r.config, overrides=list(r.overrides))
                for r in expand(load_sweep(CONFIGS / "sweeps" / "mismatch.yaml"))]
    assert len(mismatch) == 12
    assert {(c.synthetic.truth, c.synthetic.discrepancy_mm > 0) for c in mismatch} == {
        ("bump", False), ("random", False), ("smooth", True)}
    paper = [load_config(r.config, overrides=list(r.overrides))
             for r in expand(load_sweep(CONFIGS / "sweeps" / "paper_brainweb.yaml"))]
    assert len(paper) == 20 and {c.model.interpolation for c in paper} == {"cubic"}


def test_a_run_rows_columns_come_from_its_run_json(tmp_path):
    """``run_row`` on a finished run's ``run.json`` (no truth field on disk): the sampler's
    figures, the brain MSEs, the reference and, for a dense truth, the mesh's best fit
    (``brain_mse_best_fit``, ``coverage_best_fit_90``) as written; absent without it."""
    from bayesreg.experiments.sweep import run_row

    errors = {"boundary_initial_mm": {"median": 0.3}, "brain": {"mse_mm2": {
        "posterior_mean": 0.03, "start": 0.04, "reference": 0.7}},
        "boundary_reference_mm": {"q95": 3.2}, "reference_method": "tvl1",
        "coverage_moving": {"0.9": 0.79}, "mesh_best_fit": {
            "brain_mse_mm2": 0.0086, "coverage_moving": {"0.9": 0.84},
            "nodes_from_truth_mm": {"median": 0.13}}}
    info = {"sampler": {"converged": False, "rhat_rank_max": 1.02, "ess_bulk_min": 211.0,
                        "draws_per_chain": 1500}, "mesh": {"n_nodes": 344},
            "timings_s": {"total_before_outputs_s": 639.5}, "errors": errors}
    (tmp_path / "run.json").write_text(json.dumps(info))
    row = run_row(tmp_path)
    assert row["brain_mse_posterior_mean"] == 0.03 and row["brain_mse_reference"] == 0.7
    assert row["reference"] == "tvl1" and row["boundary_reference_q95"] == 3.2
    assert row["coverage_moving_90"] == 0.79 and row["start_median_mm"] == 0.3
    assert row["coverage_best_fit_90"] == 0.84 and row["brain_mse_best_fit"] == 0.0086
    assert row["ess_bulk_min"] == 211.0 and row["n_nodes"] == 344 and row["run_s"] == 639.5
    del errors["mesh_best_fit"]
    (tmp_path / "run.json").write_text(json.dumps(info))
    assert "coverage_best_fit_90" not in run_row(tmp_path)
