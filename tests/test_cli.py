"""End to end: the CLI on tiny settings writes every output; bad input fails clearly."""

import json

import numpy as np
import pytest

from bayesreg.cli import main

TINY = [
    "data.resolution_mm=3.0",
    "mesh.edge_length_mm=26",
    "sampler.warmup_steps=200",
    "sampler.max_draws=20",
    "sampler.min_draws=10",
    "sampler.chunk_draws=10",
    "sampler.thinning=5",
    "output.progress=false",
]

OUTPUTS = [
    "posterior.nc", "summary.csv", "displacement_mean.nii.gz", "displacement_sd.nii.gz",
    "mesh.vtu", "trace.png", "marginals.png", "run.json", "errors.json", "f.nii.gz",
    "m.nii.gz", "labels.nii.gz",
]


@pytest.mark.slow
def test_cli_tiny_run_writes_every_output(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["run", "configs/quickstart.yaml", "--out", str(out)]
    for s in TINY:
        args += ["--set", s]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "error vs truth" in printed and "lam/mu posterior" in printed
    for name in OUTPUTS:
        assert (out / name).is_file(), name
    info = json.loads((out / "run.json").read_text())
    assert info["sampler"]["chains"] == 3 and info["sampler"]["draws_per_chain"] >= 10
    assert info["mesh"]["n_inverted"] == 0 and info["mesh"]["n_tets"] > 100
    assert info["config"]["sampler"]["max_draws"] == 20
    assert info["sampler"]["blocks"] == ["u_b", "elastic"]
    assert all(0.0 < a < 1.0 for a in info["sampler"]["acceptance"])
    assert info["sampler"]["solve_failures"] == 0
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
    assert {"u_mean", "u_sd", "u_true"} <= set(vtu.point_data)

    # the run directory is never overwritten silently
    assert main(args) == 2
    assert "exists" in capsys.readouterr().err
    assert (out / "run.json").read_text() == json.dumps(info, indent=2)


def test_cli_bad_config_fails_with_message(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("sampler:\n  thinning: 0\n  colour: red\n")
    assert main(["run", str(cfg), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "sampler.thinning" in err and "sampler.colour: unknown key" in err
    assert not (tmp_path / "r").exists()


def test_mismatched_nifti_images_fail_clearly(tmp_path, capsys):
    import nibabel as nib

    data = np.zeros((10, 10, 10), np.float32)
    nib.save(nib.Nifti1Image(data, np.eye(4)), tmp_path / "f.nii.gz")
    aff = np.eye(4)
    aff[0, 3] = 5.0
    nib.save(nib.Nifti1Image(data.astype(np.int16), aff), tmp_path / "labels.nii.gz")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "data:\n  source: nifti\n  fixed: f.nii.gz\n  labels: labels.nii.gz\n"
        "  label_coding: {csf: 1, gm: 2, wm: 3}\n"
    )
    assert main(["run", str(cfg), "--out", str(tmp_path / "r")]) == 2
    assert "data.fixed and data.labels affines disagree" in capsys.readouterr().err


@pytest.mark.slow
def test_quickstart_notebook_executes(tmp_path):
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read("notebooks/01_quickstart.ipynb", as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": "notebooks"}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not any(o.get("output_type") == "error" for o in outputs)
    text = "".join(o.get("text", "") for o in outputs)
    assert "lam/mu posterior" in text
