"""End to end: the CLI on tiny settings writes every output; bad input fails clearly."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from bayesreg import cli
from bayesreg.checkpoint import Checkpoint
from bayesreg.cli import main
from bayesreg.config import load_config

# the quickstart (NUTS) on tiny settings: a coarse mesh on 3 mm images, a short mode search
# and warm-up, 2 elastic moves per transition (24 in the config)
TINY = [
    "data.resolution_mm=3.0",
    "mesh.edge_length_mm=26",
    "sampler.warmup_steps=30",
    "sampler.max_draws=20",
    "sampler.min_draws=10",
    "sampler.chunk_draws=10",
    "sampler.max_tree_depth=3",
    "sampler.elastic_moves=2",
    "init.optimizer_iterations=40",
    "output.progress=false",
    "output.reference=false",  # (TV-L1 beside the posterior: the tiny run below checks it)
]
# the paper's random-walk configs on tiny settings
TINY_RW = [s for s in TINY if not s.startswith(("sampler.warmup_steps", "sampler.max_tree_depth"))]
TINY_RW += ["sampler.warmup_steps=40", "sampler.thinning=2"]

OUTPUTS = [
    "posterior.nc", "summary.csv", "displacement_mean.nii.gz", "displacement_sd.nii.gz",
    "displacement_norm_sd.nii.gz", "displacement_norm_iqr.nii.gz", "displacement_init.nii.gz",
    "displacement_true.nii.gz", "displacement_reference.nii.gz", "mesh.vtu", "trace.png", "marginals.png", "uncertainty.png",
    "run.json", "errors.json", "f.nii.gz", "m.nii.gz", "labels.nii.gz",
]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, tiny_mesh):
    """The quickstart through the CLI on tiny settings (3 warm-up chunks, then 4 chunks of 10
    draws per chain, the normaliser's surrogate rebuilt after the warm-up), with a copy of
    its run directory as it stood after warm-up chunk 2 (a run killed there).

    One run serves the output checks and the resume check (a tiny run is the costliest
    setup of the suite).  Returns ``(out, killed, args, printed, compiled)``, ``compiled``
    the run's XLA compilations by program name.
    """
    import contextlib
    import io
    import shutil

    from conftest import compilations

    root = tmp_path_factory.mktemp("tiny")
    out, killed = root / "run", root / "killed"
    original = Checkpoint.on_warmup_chunk

    def snapshot(self, ckpt):  # copy the run directory as it stands after warm-up chunk 2
        original(self, ckpt)
        if ckpt.chunks_done == 2 and self.dir.parent == out:
            shutil.copytree(out, killed)

    args = ["run", "configs/quickstart.yaml", "--out", str(out)]
    for s in TINY + [f"mesh.file={tiny_mesh}", "sampler.max_draws=40", "sampler.min_draws=40",
                     "output.reference=tvl1", "sampler.normaliser_surrogate=warmup"]:
        args += ["--set", s]
    printed = io.StringIO()
    with (pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(printed),
          compilations() as compiled):
        mp.setattr(Checkpoint, "on_warmup_chunk", snapshot)
        assert main(args) == 0
    return out, killed, args, printed.getvalue(), compiled


@pytest.mark.slow
@pytest.mark.xdist_group("tiny_run")
def test_cli_tiny_run_writes_every_output_and_a_killed_run_resumes(tiny_run, capsys):
    out, _, args, printed, compiled = tiny_run
    # one compilation for each program that evaluates the posterior (one trace per shape):
    # the start check (central and dispersed starts share it), the L-BFGS step, the NUTS
    # states' initialisation and the chunk, which warm-up and sampling share but for the
    # surrogate rebuilt after the warm-up (a second target: one more chunk program)
    for program in ("jit(start_logdensity)", "jit(step)", "jit(init_states)"):
        assert compiled.get(program) == 1, (program, compiled)
    assert compiled.get("jit(mapped)") == 2, compiled
    assert "error vs truth" in printed and "lam/mu posterior" in printed
    for name in OUTPUTS:
        assert (out / name).is_file(), name
    info = json.loads((out / "run.json").read_text())
    assert info["sampler"]["chains"] == 3 and info["sampler"]["draws_per_chain"] >= 10
    assert info["mesh"]["n_inverted"] == 0 and info["mesh"]["n_tets"] > 100
    assert info["config"]["sampler"]["max_draws"] == 40
    # joint trajectories on the normaliser's surrogate, corrected once per transition
    assert info["sampler"]["blocks"] == ["joint", "normaliser"]
    center = info["sampler"]["adapted"]["normaliser_surrogate_center"]  # the chains' median
    assert len(center) == len(info["parameters"]["free"]) and all(c > 0 for c in center), center
    assert all(0.0 < a < 1.0 for a in info["sampler"]["acceptance"])
    assert info["sampler"]["solve_failures"] == 0
    health = info["sampler"]["health"]  # NUTS: Stan's per-chain checks, one line each printed
    assert len(health["divergent_fraction"]) == len(health["max_depth_fraction"]) == 3
    assert len(health["e_bfmi"]) == 3 and health["divergent_fraction"][0] >= 0
    assert all(f"sampler check: {w}" in printed for w in health["warnings"])
    assert info["versions"]["jax"]

    import arviz as az
    import meshio
    import nibabel as nib

    tree = az.from_netcdf(out / "posterior.nc")
    ratio = tree.posterior["ratio"]
    assert ratio.shape[0] == 3 and list(ratio["group"].values) == ["csf", "gm", "wm"]
    assert np.all(np.isfinite(tree.posterior["u_b"].values))
    assert "acceptance_rate" in tree.sample_stats
    mean = nib.load(out / "displacement_mean.nii.gz")
    assert mean.shape[-1] == 3 and np.abs(mean.get_fdata()).max() > 0
    vtu = meshio.read(out / "mesh.vtu")
    assert {"u_mean", "u_sd", "u_true", "u_init", "u_norm_iqr"} <= set(vtu.point_data)
    iqr = nib.load(out / "displacement_norm_iqr.nii.gz").get_fdata()
    assert iqr.shape == mean.shape[:3] and iqr.max() > 0 and iqr.min() >= 0
    errors = json.loads((out / "errors.json").read_text())
    cov = errors["coverage_boundary"]
    assert set(cov) == {"0.5", "0.9", "0.95"} and cov["0.5"] <= cov["0.9"] <= cov["0.95"]
    # over the brain's voxels: the posterior mean, the start and TV-L1 on the same images
    brain = errors["brain"]
    assert set(brain["mse_mm2"]) == {"posterior_mean", "start", "reference"} and brain["n_voxels"] > 1000
    assert errors["reference_method"] == "tvl1" and "boundary, tvl1" in printed
    assert errors["truth_made_by_model"] and errors["coverage_moving"]["n_components"] > 0
    # the checkpoint keeps config, problem and starts; its draws are gone once outputs exist
    assert (out / "checkpoint" / "problem.npz").is_file()
    assert not (out / "checkpoint" / "draws").exists() and not (out / ".outputs-partial").exists()

    # the run directory is never overwritten silently
    assert main(args) == 2
    assert "exists" in capsys.readouterr().err
    assert (out / "run.json").read_text() == json.dumps(info, indent=2)

    # one test, not two: each pytest-xdist worker that ran one of them would build the
    # module's fixture (the tiny run) again
    _killed_run_resumes_to_the_uninterrupted_result(tiny_run)
    _arviz_reads_the_posterior_as_its_own(out)
    _open_run_gives_what_run_returned(out, info)
    _quickstart_notebook_executes_on_a_finished_run(out)
    _exported_transforms_and_applied_posterior(out, capsys)


def _open_run_gives_what_run_returned(out, info):
    """:func:`bayesreg.open_run`: the files read back into a RunResult; a missing file named."""
    import arviz as az
    import pandas as pd

    import bayesreg

    res = bayesreg.open_run(out)
    assert res.dir == out and res.info == info
    assert res.errors == json.loads((out / "errors.json").read_text())
    assert res.summary.index[0].startswith(("lam", "mu", "ratio")) and "r_hat" in res.summary
    pd.testing.assert_frame_equal(res.summary, pd.read_csv(out / "summary.csv", index_col=0))
    tree = az.from_netcdf(out / "posterior.nc")
    np.testing.assert_array_equal(res.posterior.posterior["u_b"].values,
                                  tree.posterior["u_b"].values)
    tree.close()
    with pytest.raises(FileNotFoundError, match="summary.csv not found in .*resume"):
        bayesreg.open_run(out / "checkpoint")


def _arviz_reads_the_posterior_as_its_own(out):
    """NUTS sample stats under ArviZ's names and types; the fixed mu[gm] as constant data."""
    import warnings

    import arviz as az
    import matplotlib

    matplotlib.use("Agg")
    tree = az.from_netcdf(out / "posterior.nc")
    ss = tree.sample_stats
    for name in ("energy", "tree_depth", "step_size", "n_steps", "lp", "acceptance_rate"):
        assert name in ss and np.all(np.isfinite(ss[name].values)), name
    assert ss["diverging"].dtype == bool
    assert np.all(ss["tree_depth"].values >= 1) and np.all(ss["step_size"].values > 0)
    assert list(tree.posterior["mu"]["mu_group"].values) == ["csf", "wm"]
    assert float(tree.constant_data["mu_fixed"].sel(mu_fixed_group="gm")) == 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # no NaN R-hat of a constant "draw"
        summary = az.summary(tree, var_names=["lam", "mu"])
    assert np.all(np.isfinite(summary["r_hat"]))
    bfmi = np.asarray(az.bfmi(tree)["energy"].values)  # one E-BFMI per chain
    assert bfmi.shape == (3,) and np.all(bfmi > 0)
    az.plot_energy(tree)
    az.plot_rank(tree, var_names=["lam"])
    matplotlib.pyplot.close("all")


def _exported_transforms_and_applied_posterior(out, capsys):
    """The posterior as ITK/ANTs/Slicer transforms that SimpleITK applies as the project's own
    warp; label maps and points carried through the draws."""
    import meshio
    import nibabel as nib

    from bayesreg import apply as A
    from bayesreg.data.images import Image, load_nifti

    sitk = pytest.importorskip("SimpleITK")
    vtu = meshio.read(out / "mesh.vtu")
    assert set(np.unique(vtu.cell_data["label"][0])) <= {1, 2, 3}  # the label map's coding

    for fmt in ("itk", "ants", "slicer", "nifti"):
        assert main(["export", str(out), "--format", fmt, "--draws", "2"]) == 0
        man = json.loads((out / "export" / fmt / "transforms.json").read_text())
        assert [f["what"] for f in man["files"]][0] == "mean" and len(man["files"]) == 3
        for f in man["files"]:
            assert (out / "export" / fmt / f["fixed_to_moving"]).is_file()
            assert (out / "export" / fmt / f["moving_to_fixed"]).is_file()
    assert (out / "export" / "ants" / "mean_1Warp.nii.gz").is_file()
    slicer_mesh = meshio.read(out / "export" / "slicer" / "mesh.vtk")
    np.testing.assert_allclose(slicer_mesh.points[:, :2], -vtu.points[:, :2])  # LPS
    assert b"SPACE=LPS" in (out / "export" / "slicer" / "mesh.vtk").read_bytes().split(b"\n")[1]  # for Slicer

    # SimpleITK resamples m through the exported mean as the project's own warp does
    rp = A.load_posterior(out)
    # a draw's interior by the direct solve agrees with the sampler's stored interiors
    np.testing.assert_allclose(A.nodal_field_draws(rp, np.arange(rp.n_draws)).mean(axis=0),
                               vtu.point_data["u_mean"], atol=1e-6)
    m = sitk.ReadImage(str(out / "m.nii.gz"), sitk.sitkFloat64)
    f = sitk.ReadImage(str(out / "f.nii.gz"), sitk.sitkFloat64)
    field = sitk.ReadImage(str(out / "export" / "itk" / "fixed_to_moving_mean.nii.gz"),
                           sitk.sitkVectorFloat64)
    got = sitk.GetArrayFromImage(sitk.Resample(m, f, sitk.DisplacementFieldTransform(field),
                                               sitk.sitkLinear, 0.0)).transpose(2, 1, 0)
    m_img = load_nifti(out / "m.nii.gz")
    own = A.warp_image(rp, Image(np.asarray(m_img.data, np.float64), m_img.affine)).data
    in_mesh = np.asarray(nib.load(out / "mesh_mask.nii.gz").dataobj) > 0
    assert np.abs(got - own)[in_mesh].max() < 1e-4 * np.abs(own[in_mesh]).max()

    # a label map through the draws: probabilities per voxel sum to 1; where every draw
    # agrees the most probable label is the nearest-neighbour warp of the mean
    labels = load_nifti(out / "labels.nii.gz")
    lp = A.warp_labels(rp, labels, draws=8)
    prob = lp.probability.data
    assert prob.min() >= 0 and prob.max() <= 1
    np.testing.assert_allclose(prob.sum(axis=-1), 1.0, atol=1e-6)
    nn_mean = A.warp_image(rp, Image(labels.data.astype(float), labels.affine),
                           direction="to_moving", order=0).data
    sure = prob.max(axis=-1) == 1.0
    assert np.mean(lp.most_probable.data[sure] == nn_mean[sure]) > 0.999
    assert np.mean(prob.max(axis=-1) < 1.0) > 0  # the draws differ somewhere

    # points: posterior positions, 95% ellipsoids and their coverage of the synthetic truth
    nodes = rp.mesh.nodes[rp.mesh.interior[::5]]
    csv = out / "targets.csv"
    csv.write_text("name,x,y,z\n" + "".join(f"t{k},{a},{b},{c}\n" for k, (a, b, c) in enumerate(nodes)))
    capsys.readouterr()
    assert main(["apply", str(out), str(csv), "--out", str(out / "targets_moved.csv"),
                 "--truth", "synthetic"]) == 0
    said = capsys.readouterr().out
    assert "TRE median" in said and "95% ellipsoid" in said
    rows = (out / "targets_moved.csv").read_text().splitlines()
    assert len(rows) == len(nodes) + 1 and "semi_axis_1" in rows[0] and "inside_95" in rows[0]
    pp = A.map_points(rp, nodes)
    err = A.target_errors(pp, nodes + rp.u_true[rp.mesh.interior[::5]])
    assert 0.0 <= err["coverage_95"] <= 1.0 and np.all(pp.semi_axes > 0)
    assert err["tre_median_mm"] < np.median(err["tre_start_mm"])  # better than not moving them
    assert main(["apply", str(out), str(out / "labels.nii.gz"), "--out", str(out / "seg"),
                 "--draws", "4"]) == 0
    assert (out / "seg_probability.nii.gz").is_file() and (out / "seg_most_probable.nii.gz").is_file()


def test_version_prints_the_package_version(capsys):
    import bayesreg

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"bayesreg {bayesreg.__version__}"
    # the installed metadata's, which pyproject.toml reads from bayesreg.__version__
    from importlib import metadata

    assert bayesreg.__version__ == metadata.version("bayesreg")


def test_cli_bad_config_fails_with_message(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("sampler:\n  thinning: 0\n  colour: red\n")
    assert main(["run", str(cfg), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "sampler.thinning" in err and "sampler.colour: unknown key" in err
    assert not (tmp_path / "r").exists()


def test_nifti_images_in_different_world_frames_fail_clearly(tmp_path, capsys):
    import nibabel as nib

    data = np.zeros((10, 10, 10), np.float32)
    nib.save(nib.Nifti1Image(data, np.eye(4)), tmp_path / "f.nii.gz")
    aff = np.eye(4)
    aff[0, 3] = 50.0  # a label grid with no overlap: not the same world frame
    nib.save(nib.Nifti1Image(data.astype(np.int16), aff), tmp_path / "labels.nii.gz")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "data:\n  source: nifti\n  fixed: f.nii.gz\n  labels: labels.nii.gz\n"
        "  label_coding: {csf: 1, gm: 2, wm: 3}\ninit: {start: registration}\n"
    )
    assert main(["run", str(cfg), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "world frame" in err and "data.labels" in err


def test_a_run_that_fails_before_sampling_leaves_nothing_and_puts_back_what_it_replaced(tmp_path, capsys):
    import nibabel as nib

    data = np.ones((10, 10, 10), np.float32)
    data[3, 3, 3] = np.nan
    nib.save(nib.Nifti1Image(data, np.eye(4)), tmp_path / "f.nii.gz")
    nib.save(nib.Nifti1Image(np.full((10, 10, 10), 2, np.int16), np.eye(4)), tmp_path / "labels.nii.gz")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "data:\n  source: nifti\n  fixed: f.nii.gz\n  labels: labels.nii.gz\n"
        "  label_coding: {csf: 1, gm: 2, wm: 3}\ninit: {start: registration}\n"
    )
    out = tmp_path / "r"
    assert main(["run", str(cfg), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "data.fixed" in err and "has 1 non-finite voxels" in err
    assert not out.exists()  # the same command runs once the input is fixed
    out.mkdir()
    (out / "run.json").write_text('{"earlier": "run"}')
    assert main(["run", str(cfg), "--out", str(out), "--overwrite"]) == 2
    assert "non-finite voxels" in capsys.readouterr().err
    assert (out / "run.json").read_text() == '{"earlier": "run"}'  # put back
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.yaml", "f.nii.gz", "labels.nii.gz", "r"]
    # a folder of the user's own files is never replaced; a file is not a run directory
    assert main(["run", str(cfg), "--out", str(tmp_path), "--overwrite"]) == 2
    assert "holds none of run.json, checkpoint" in capsys.readouterr().err
    assert main(["run", str(cfg), "--out", str(tmp_path / "c.yaml" / "r")]) == 2
    assert "is a file" in capsys.readouterr().err
    # a damaged saved config is named
    bad = tmp_path / "bad"
    (bad / "checkpoint").mkdir(parents=True)
    (bad / "checkpoint" / "config.json").write_text("{")
    assert main(["run", "--resume", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "config.json: not valid JSON" in err


def test_overwrite_refuses_inputs_inside_the_directory_it_replaces(tmp_path, capsys):
    """A rerun on a run's own mesh into that run's directory with --overwrite is refused with
    the key named, before anything moves (the directory and the mesh in it stay)."""
    run = tmp_path / "qs"
    run.mkdir()
    (run / "run.json").write_text("{}")
    (run / "mesh.vtu").write_text("a mesh")
    args = ["run", "configs/quickstart.yaml", "--out", str(run), "--overwrite",
            "--set", f"mesh.file={run / 'mesh.vtu'}"]
    assert main(args) == 2
    assert f"mesh.file ({run / 'mesh.vtu'}) lies inside the run directory" in capsys.readouterr().err
    assert sorted(p.name for p in run.iterdir()) == ["mesh.vtu", "run.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["qs"]


def test_resume_needs_an_unfinished_run(tmp_path, capsys):
    assert main(["run", "--resume", str(tmp_path)]) == 2
    assert "nothing to resume" in capsys.readouterr().err
    assert main(["run", "configs/quickstart.yaml", "--resume", str(tmp_path)]) == 2
    assert "either CONFIG or --resume" in capsys.readouterr().err


@pytest.fixture
def reports(monkeypatch):
    """The ``{label: run directory}`` mappings ``bayesreg report``/``reproduce`` hand to
    :func:`bayesreg.report.write_report` (replaced here: the runs are not real)."""
    handed = []

    def write_report(runs, out, overwrite=False):
        handed.append(dict(runs))
        return Path(out)

    monkeypatch.setattr(cli, "write_report", write_report)
    return handed


def test_report_labels_paths_with_equals_signs_and_refuses_one_label_for_two_runs(tmp_path, capsys, reports):
    """``bayesreg report [LABEL=]RUN_DIR ...``: an existing directory is a run directory, ``=``
    and all; otherwise the label ends at the first ``=``; without a label the directory's
    name is the label.  Two runs labelled alike, or an empty label, are refused."""
    (tmp_path / "t_r=300").mkdir()
    for d in ("a/uniform", "b/uniform"):
        (tmp_path / d).mkdir(parents=True)

    def labels(*items):
        assert main(["report", *items, "--out", str(tmp_path / "r")]) == 0
        assert "report in" in capsys.readouterr().out
        return reports.pop()

    assert labels(str(tmp_path / "t_r=300")) == {"t_r=300": tmp_path / "t_r=300"}
    assert labels(f"hot={tmp_path / 't_r=300'}") == {"hot": tmp_path / "t_r=300"}
    assert labels(str(tmp_path / "a/uniform"), f"b={tmp_path / 'b/uniform'}") == {
        "uniform": tmp_path / "a/uniform", "b": tmp_path / "b/uniform"}
    args = ["report", str(tmp_path / "a/uniform"), str(tmp_path / "b/uniform"), "--out", str(tmp_path / "r")]
    assert main(args) == 2
    assert "two runs are labelled 'uniform'" in capsys.readouterr().err
    assert main(["report", "=x", "--out", str(tmp_path / "r")]) == 2
    assert "empty label in '=x'" in capsys.readouterr().err
    assert not reports and not (tmp_path / "r").exists()


def test_reproduce_reuses_or_resumes_only_a_run_of_the_same_config(tmp_path, capsys, monkeypatch, reports):
    """``bayesreg reproduce`` into a folder that holds runs reuses a finished run only if its
    config is the one asked for, ``--set`` included; a run of another config (read from its
    checkpoint, or from ``run.json`` without one) is refused with the differing keys named."""
    monkeypatch.setattr(cli, "format_report", lambda errors, info: "")  # the runs hold no results
    paper = tmp_path / "paper"
    made = {}
    for label, name in cli.PAPER_CONFIGS.items():
        out = paper / label
        made[label] = load_config(f"configs/{name}", overrides=["sampler.max_draws=500"])
        made[label].output.dir = out  # as the run saved it
        Checkpoint(out).save_config(made[label])
        (out / "run.json").write_text(json.dumps({"config": made[label].model_dump(mode="json"), "errors": None}))
    args = ["reproduce", "--out", str(paper), "--no-progress", "--set", "sampler.max_draws=500"]
    assert main(args) == 0  # the same configs: reused
    assert capsys.readouterr().out.count("finished run found, reused") == 2
    assert reports.pop() == {label: paper / label for label in cli.PAPER_CONFIGS}
    assert main(["reproduce", "--out", str(paper), "--no-progress", "--set", "model.t_r=99"]) == 2
    assert re.search(r"holds a run of another config \(model.t_r: 10000.0 there, 99.0 asked; "
                     r"sampler.max_draws: 500 there, \d+ asked\)", capsys.readouterr().err)
    # a run without checkpoints: run.json's config (here the uniform model's) is compared
    first = paper / next(iter(cli.PAPER_CONFIGS))
    (Checkpoint(first).config_path).unlink()
    (first / "run.json").write_text(json.dumps({"config": made["uniform"].model_dump(mode="json")}))
    assert main(args) == 2
    assert "model.elastic: 'uniform' there, 'tissue' asked" in capsys.readouterr().err
    assert not reports


def _killed_run_resumes_to_the_uninterrupted_result(tiny_run):
    """A run killed in its warm-up (after warm-up chunk 2 of 3), resumed, gives the draws of
    the run never killed: the adaptation's state was kept."""
    import arviz as az

    full, killed, *_ = tiny_run
    assert (killed / "checkpoint" / "warmup.npz").is_file()
    assert not (killed / "checkpoint" / "draws").exists() and not (killed / "checkpoint" / "state.npz").exists()
    assert not (killed / "run.json").exists()
    # a plain run into the killed directory is refused and points at --resume
    assert main(["run", "configs/quickstart.yaml", "--out", str(killed)]) == 2
    assert main(["run", "--resume", str(killed), "--no-progress"]) == 0
    pa = az.from_netcdf(full / "posterior.nc").posterior
    pb = az.from_netcdf(killed / "posterior.nc").posterior
    for v in ("u_b", "lam", "mu"):
        np.testing.assert_array_equal(pa[v].values, pb[v].values)
    info = json.loads((killed / "run.json").read_text())
    full_info = json.loads((full / "run.json").read_text())
    assert info["sampler"]["draws_per_chain"] == full_info["sampler"]["draws_per_chain"] == 40
    assert info["resumed"] is True and full_info["resumed"] is False


def _quickstart_notebook(first_cell=None, replace=None):
    """Notebook 01 executed in a fresh kernel; ``replace`` ``(old, new)`` edits the one cell
    that calls :func:`bayesreg.run`, ``first_cell`` replaces it.  Returns the text printed."""
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read("notebooks/01_quickstart.ipynb", as_version=4)
    cells = [c for c in nb.cells if c.cell_type == "code" and "bayesreg.run(" in c.source]
    assert len(cells) == 1
    if replace is not None:
        assert replace[0] in cells[0].source
        cells[0].source = cells[0].source.replace(*replace)
    if first_cell is not None:
        cells[0].source = first_cell
    NotebookClient(nb, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": "notebooks"}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not any(o.get("output_type") == "error" for o in outputs)
    return "".join(o.get("text", "") for o in outputs)


def _quickstart_notebook_executes_on_a_finished_run(out):
    """Every cell of notebook 01 after the run, on the CLI's tiny run reopened by
    :func:`bayesreg.open_run` (the run cell itself is the CLI's call: its full execution is
    the heavy test below)."""
    text = _quickstart_notebook(first_cell=f"import bayesreg\nresult = bayesreg.open_run({str(out)!r})")
    assert "lam/mu posterior" in text


@pytest.mark.heavy
def test_quickstart_notebook_executes(tiny_mesh):
    text = _quickstart_notebook(replace=('"mesh.edge_length_mm=26"', repr(f"mesh.file={tiny_mesh}")))
    assert "lam/mu posterior" in text


REPORT_FILES = [
    "table1.csv", "table2.csv", "coverage.csv", "ratios.csv", "fig2_dataset.png",
    "fig3_errors.png", "fig4_ratios.png", "fig5_boundary_node.png", "uncertainty.png",
    "report.md", "report.json",
]


@pytest.mark.heavy
def test_paper_notebook_executes_on_a_tiny_reproduction(tmp_path, monkeypatch, capsys):
    """`bayesreg reproduce` on tiny settings writes the report; notebook 02 redraws it."""
    import nbformat
    from nbclient import NotebookClient

    paper = tmp_path / "paper"
    # a 26 mm mesh has a few elements across the brain: a 15 mm push can invert one of them
    # (the truth is then refused, rightly); 6 mm keeps every element valid on any meshing
    tiny = TINY_RW + ["init.start=registration", "synthetic.shift_mm=6"]
    # the paper configs mesh to 801 nodes; here to the 26 mm mesh's own 270-310 (3 mm images)
    tiny += ["mesh.target_nodes=290", "mesh.target_tolerance=0.5"]
    overrides = sum((["--set", s] for s in tiny), [])
    assert main(["reproduce", "--out", str(paper), "--no-progress"] + overrides) == 0
    out = capsys.readouterr().out
    assert "report in" in out and out.count("target 290 within 50%: met in") == 2
    for model in ("uniform", "three_compartment"):
        run = json.loads((paper / model / "run.json").read_text())
        meshing = run["mesh"]["meshing"]
        assert meshing["target_nodes"] == 290 and meshing["within_tolerance"]
        assert meshing["attempts"][-1]["n_nodes"] == run["mesh"]["n_nodes"]
        assert abs(run["mesh"]["n_nodes"] - 290) <= 145
    for name in REPORT_FILES:
        assert (paper / "report" / name).is_file(), name
    md = (paper / "report" / "report.md").read_text()
    assert "Table 1" in md and "Table 2" in md
    assert "0.160" in md and "0.040" in md  # the paper's values beside ours

    monkeypatch.setenv("BAYESREG_PAPER_RUNS", str(paper))
    nb = nbformat.read("notebooks/02_paper_experiment.ipynb", as_version=4)
    assert not any(c.get("outputs") for c in nb.cells if c.cell_type == "code")  # stored stripped
    NotebookClient(nb, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": "notebooks"}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not any(o.get("output_type") == "error" for o in outputs)
    text = "".join(o.get("text", "") for o in outputs)
    assert "Table 1" in text and "Table 2" in text and "Brain MSE" in text
    n_png = sum("image/png" in o.get("data", {}) for o in outputs)
    assert n_png >= 7  # Fig. 2-5, uncertainty and the ArviZ plot per run


@pytest.mark.heavy
# MALA: NUTS runs end to end in the tiny quickstart above (and in the notebook); the two
# kinds share the driver, and each recovers a known joint in tests/test_kernels.py
@pytest.mark.parametrize("kind,discrepancy,carry", [("mala", "none", "conditional"),
                                                    ("mala", "interior", "conditional"),
                                                    ("mala", "interior", "displacement")])
def test_gradient_kernel_run_with_exact_normaliser_and_all_parameters_free(tmp_path, capsys, kind,
                                                                          discrepancy, carry, tiny_mesh):
    """A gradient kernel end to end: exact normaliser, no fixed parameter, collapsed moves of
    the parameters (Laplace proposal; with a model discrepancy they carry ``[u_b, d]`` by
    their Gaussian or keep the nodal displacement, the default there), sample stats and
    adapted values written."""
    out = tmp_path / "run"
    tiny = [s for s in TINY if not s.startswith(("sampler.thinning", "sampler.warmup_steps",
                                                 "sampler.proposal", "sampler.max_draws"))]
    sets = tiny + [f"mesh.file={tiny_mesh}", f"sampler.kind={kind}", "sampler.thinning=1",
                   "sampler.warmup_steps=20", "sampler.max_draws=10", "model.prior_normaliser=exact",
                   "model.fixed=null",
                   "sampler.proposal=laplace", "sampler.collapsed_moves=1",
                   f"model.discrepancy={discrepancy}",
                   "init.method=perturb"]  # (the mode search under exact: the tiny run above)
    if carry == "conditional" and discrepancy != "none":
        sets.append("sampler.carry=conditional")
    args = ["run", "configs/quickstart.yaml", "--out", str(out)] + sum((["--set", s] for s in sets), [])
    assert main(args) == 0
    assert f"{kind}: gradients/step" in capsys.readouterr().out
    info = json.loads((out / "run.json").read_text())
    s = info["sampler"]
    assert s["kind"] == kind and s["prior_normaliser"] == "exact"
    assert s["blocks"] == ["u_b", "elastic", "collapsed"] and s["collapsed_carry"] == carry
    assert len(s["adapted"]["collapsed_proposal_sd_per_chain"]) == 3
    assert info["parameters"]["fixed"] == [] and len(info["parameters"]["free"]) == 6
    assert len(s["adapted"]["step_size_per_chain"]) == 3 and all(x > 0 for x in s["adapted"]["step_size_per_chain"])
    assert s["gradient_evaluations_per_step_mean"] >= 1
    import arviz as az

    tree = az.from_netcdf(out / "posterior.nc")
    assert {"n_steps", "diverging", "acceptance_rate", "step_size"} <= set(tree.sample_stats.data_vars)
    assert np.all(np.isfinite(tree.posterior["lam"].values)) and np.all(tree.posterior["mu"].values > 0)
    assert ("d" in tree.posterior) == (discrepancy != "none")


def test_strict_gives_each_failure_its_own_exit_status(monkeypatch, tmp_path, capsys):
    """``run --strict``: 3 for chains that never moved, 4 for a stop rule not met by
    ``max_draws``, 0 for a converged run; without ``--strict`` every finished run is 0."""
    from bayesreg.outputs.result import RunResult

    monkeypatch.setattr(cli, "format_report", lambda errors, info: "")
    for sampler, strict in (({"converged": True, "stuck_chains": []}, 0),
                            ({"converged": False, "stuck_chains": []}, 4),
                            ({"converged": False, "stuck_chains": [1]}, 3)):
        result = RunResult(tmp_path, None, None, None, {"sampler": sampler, "timings_s": {}})
        monkeypatch.setattr(cli, "run", lambda *a, **k: result)
        assert main(["run", "configs/quickstart.yaml", "--strict"]) == strict, sampler
        assert main(["run", "configs/quickstart.yaml"]) == 0
