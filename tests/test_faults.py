"""Faults: an interrupt or a kill at any stage loses no finished run and a resume repeats the
uninterrupted run; one process per run directory; no wrong result passes without a word.

Every run here is the quickstart's problem on tiny settings (the paper's random walk, two
chains) on one fixed mesh (fTetWild is not reproducible), so that draws can be compared
across processes.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import meshio
import numpy as np
import pytest

import bayesreg.sampling.driver
import bayesreg.outputs.write
import bayesreg.model.problem
from bayesreg.checkpoint import Checkpoint
from bayesreg.cli import main

# one pytest-xdist worker runs this file (pyproject's --dist loadgroup): the module's
# reference run is made once, not once in each worker
pytestmark = pytest.mark.xdist_group("faults")

CONFIG = str(Path(__file__).resolve().parents[1] / "configs" / "quickstart.yaml")
TINY = [
    "data.resolution_mm=3.0", "mesh.edge_length_mm=26", "sampler.kind=rwmh", "sampler.chains=2",
    "sampler.proposal=isotropic", "init.method=perturb", "sampler.warmup_steps=20",
    "sampler.thinning=10", "sampler.chunk_draws=10", "sampler.max_draws=30",
    "sampler.min_draws=30", "output.progress=false", "output.reference=false",
]
OUTPUTS = ("run.json", "summary.csv", "posterior.nc", "errors.json")


def _args(mesh, out, *extra):
    args = ["run", CONFIG, "--out", str(out), "--set", f"mesh.file={mesh}"]
    for s in TINY:
        args += ["--set", s]
    return args + list(extra)


def _draws(run_dir, n: int = 30) -> np.ndarray:
    import arviz as az

    tree = az.from_netcdf(Path(run_dir) / "posterior.nc")
    return np.concatenate([np.asarray(tree.posterior[v].values).reshape(2, n, -1)
                           for v in ("u_b", "lam", "mu")], axis=-1)


@pytest.fixture(scope="session")  # (session: built once in the worker of the group "faults")
def reference(tmp_path_factory, tiny_mesh):
    """``(root, mesh file, reference run directory)``: the uninterrupted run (on the
    session's tiny mesh)."""
    root = tmp_path_factory.mktemp("faults")
    mesh = Path(tiny_mesh)
    ref = root / "reference"
    assert main(_args(mesh, ref)) == 0
    return root, mesh, ref


def _same_run(a, b) -> None:
    for name in OUTPUTS[1:]:
        assert (Path(a) / name).read_bytes() == (Path(b) / name).read_bytes(), name


def _interrupt_at(monkeypatch, stage: str) -> None:
    """Raise KeyboardInterrupt (Ctrl-C) in ``stage`` of the next run."""
    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    if stage == "mesh":
        monkeypatch.setattr(bayesreg.model.problem, "read_mesh", stop)
    elif stage == "warm-up":
        monkeypatch.setattr(bayesreg.sampling.driver, "run_warmup", stop)
    elif stage == "sampling":
        original = Checkpoint.on_chunk

        def after_chunk_1(self, ckpt, out):
            original(self, ckpt, out)
            if ckpt.chunks_done == 1:
                raise KeyboardInterrupt

        monkeypatch.setattr(Checkpoint, "on_chunk", after_chunk_1)
    else:
        monkeypatch.setattr(bayesreg.outputs.write, "plot_parameters", stop)


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["mesh", "warm-up", "sampling", "outputs"])
def test_an_interrupted_overwrite_puts_the_finished_run_back(reference, tmp_path, monkeypatch,
                                                             capsys, stage):
    """Ctrl-C during an ``--overwrite`` (another seed) at any stage puts the finished run it
    was replacing back, byte for byte, says so in one line, and leaves nothing aside."""
    root, mesh, ref = reference
    finished = tmp_path / "run"
    shutil.copytree(ref, finished)
    _interrupt_at(monkeypatch, stage)
    assert main(_args(mesh, finished, "--overwrite", "--set", "seed=5")) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (f"bayesreg: interrupted during the {stage}: the run that was in {finished} "
                       "is back in place (this run's partial results were discarded)")
    _same_run(finished, ref)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["mesh", "sampling", "outputs"])
def test_an_interrupted_new_run_keeps_what_a_resume_needs(reference, tmp_path, monkeypatch, capsys,
                                                         stage):
    """Ctrl-C before anything resumable was saved leaves nothing; later the checkpoint stays,
    one line says how to continue, and the resume gives the uninterrupted run's draws.  A
    checkpoint whose config was edited meanwhile is refused (a mixture of two configs)."""
    root, mesh, ref = reference
    out = tmp_path / "run"
    with monkeypatch.context() as mp:
        _interrupt_at(mp, stage)
        assert main(_args(mesh, out)) == 130
    err = capsys.readouterr().err
    line = err.strip().splitlines()[-1]
    # with output.progress false (no bars) the stage lines still say how far it came
    assert "bayesreg: data done" in err and ("bayesreg: starts done" in err) == (stage != "mesh")
    if stage == "mesh":
        assert line == "bayesreg: interrupted during the mesh: nothing was kept"
        assert not out.exists() and not list(tmp_path.iterdir())
        return
    where = "after chunk 1" if stage == "sampling" else "during the outputs"
    assert line == f"bayesreg: interrupted {where}; continue with `bayesreg run --resume {out}`"
    config = out / "checkpoint" / "config.json"
    original = config.read_text()
    config.write_text(original.replace('"seed": 0', '"seed": 7'))
    assert main(["run", "--resume", str(out)]) == 2
    assert "config.json was changed after the run started" in capsys.readouterr().err
    config.write_text(original)
    if stage != "sampling":
        assert main(["run", "--resume", str(out)]) == 0
        np.testing.assert_array_equal(_draws(out), _draws(ref))
        return
    # a resume may take the run further (the stop rule, the draw bounds), nothing else
    assert main(["run", "--resume", str(out), "--set", "model.t_s=1"]) == 2
    assert "cannot change 'model.t_s'" in capsys.readouterr().err
    assert main(["run", "--resume", str(out), "--set", "sampler.max_draws=40",
                 "--set", "sampler.min_draws=40"]) == 0
    longer = _draws(out, 40)
    np.testing.assert_array_equal(longer[:, :30], _draws(ref))
    assert np.all(np.isfinite(longer[:, 30:])) and not np.array_equal(longer[:, 30:], longer[:, 20:30])
    saved = json.loads(config.read_text())["sampler"]
    assert saved["max_draws"] == saved["min_draws"] == 40


#: ``python -c`` program that runs the CLI with Python's Ctrl-C handler, as a terminal's shell
#: starts it: a test run itself launched in the background by a non-interactive shell has
#: SIGINT ignored, which its children would inherit (and Python then installs no handler).
AS_FROM_A_TERMINAL = ("import runpy, signal, sys; "
                      "signal.signal(signal.SIGINT, signal.default_int_handler); "
                      "sys.argv[0] = 'bayesreg'; runpy.run_module('bayesreg.cli', run_name='__main__')")


def _start(mesh, out, *extra) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bayesreg.cli", *_args(mesh, out, *extra)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 240.0) -> None:
    t = time.monotonic()
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t < timeout, f"{path} did not appear"
        time.sleep(0.02)


@pytest.mark.slow
def test_a_killed_overwrite_is_refused_to_others_resumes_and_leaves_the_old_run_found(
        reference, tmp_path, capsys):
    """While a run samples, a second process into its directory is refused, naming the
    holder's PID (an overwrite, a resume).  Killed outright (SIGKILL) during its overwrite,
    the run it was replacing waits aside: every later opening of the directory says where,
    none deletes it, and the killed run's resume gives the uninterrupted draws."""
    root, mesh, ref = reference
    finished = tmp_path / "run"
    shutil.copytree(ref, finished)
    proc = _start(mesh, finished, "--overwrite")
    lock = tmp_path / ".run.lock"
    _wait_for(lock, proc)
    while lock.read_text().strip() != str(proc.pid):
        time.sleep(0.02)
    for attempt in (_args(mesh, finished, "--overwrite", "--set", "seed=5"),
                    ["run", "--resume", str(finished)]):
        assert main(attempt) == 2
        assert f"is in use by process {proc.pid}" in capsys.readouterr().err
    _wait_for(finished / "checkpoint" / "state.npz", proc)  # the warm-up is done
    proc.kill()
    proc.wait()
    aside = list(tmp_path.glob(".run.replaced-*"))
    assert len(aside) == 1
    # a new run into the directory is refused, naming the run left aside and what to do
    assert main(_args(mesh, finished)) == 2
    err = capsys.readouterr().err
    assert "continue it with --resume" in err and f"waits in {aside[0]}" in err
    assert f"mv {aside[0]} {finished}" in err and "never deletes it" in err
    with pytest.warns(UserWarning, match=rf"waits in {aside[0]}"):
        assert main(["run", "--resume", str(finished)]) == 0
    np.testing.assert_array_equal(_draws(finished), _draws(ref))
    _same_run(aside[0], ref)  # the old run, untouched


def _stage_line(proc: subprocess.Popen, text: str, timeout: float = 240.0) -> list[str]:
    """Read ``proc``'s stderr until a line holds ``text``; the lines read."""
    lines, t = [], time.monotonic()
    while time.monotonic() - t < timeout:
        line = proc.stderr.readline()
        assert line, f"the run ended before {text!r}: {lines}"
        lines.append(line)
        if text in line:
            return lines
    raise AssertionError(f"no {text!r} in {timeout} s: {lines}")


def _wait_for_child(proc: subprocess.Popen, name: str, timeout: float = 120.0) -> None:
    """Wait until ``proc`` has a child process whose command line names ``name``."""
    import psutil

    t = time.monotonic()
    while time.monotonic() - t < timeout:
        assert proc.poll() is None, proc.communicate()
        for child in psutil.Process(proc.pid).children():
            try:
                if name in " ".join(child.cmdline()):
                    return
            except psutil.Error:  # (gone meanwhile)
                pass
        time.sleep(0.01)
    raise AssertionError(f"no child process {name!r} in {timeout} s")


@pytest.mark.slow
def test_ctrl_c_in_a_terminal_after_or_during_meshing_puts_the_finished_run_back(reference, tmp_path):
    """Ctrl-C as a terminal sends it (SIGINT to the foreground process group) while fTetWild
    meshes, and again in the warm-up after it meshed: each ends with the one line, exit
    status 130, and the finished run that ``--overwrite`` was replacing back in place.  (The
    mesher's native library replaces the process's signal handlers; it runs in a child
    process so that the run's own stay.)"""
    root, mesh, ref = reference
    finished = tmp_path / "run"
    shutil.copytree(ref, finished)
    args = ["run", CONFIG, "--out", str(finished), "--overwrite", "--set", "seed=5"]
    for s in TINY:
        args += ["--set", s]
    for stage, after in (("mesh", "bayesreg: data done"), ("warm-up", "bayesreg: starts done")):
        # a warm-up of 30 chunks, the signal after the first is saved: inside it, whatever
        # the machine's load and the compilation cache (a fixed sleep was not)
        extra = ["--set", "sampler.warmup_steps=3000"] if stage == "warm-up" else []
        proc = subprocess.Popen([sys.executable, "-c", AS_FROM_A_TERMINAL, *args, *extra], text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                start_new_session=True)
        lines = _stage_line(proc, after)
        if stage == "mesh":  # while fTetWild runs (its process a child of the run's)
            _wait_for_child(proc, "_tetwild_worker")
        else:
            assert any("bayesreg: mesh done" in line for line in lines), lines
            _wait_for(finished / "checkpoint" / "warmup.npz", proc)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 130, err
        assert err.strip().splitlines()[-1] == (
            f"bayesreg: interrupted during the {stage}: the run that was in {finished} is back "
            "in place (this run's partial results were discarded)"), err
        _same_run(finished, ref)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


@pytest.mark.slow
def test_sigterm_interrupts_as_ctrl_c_does(reference, tmp_path):
    """``kill PID`` (SIGTERM) stops a run as Ctrl-C does: status 130, one line, the
    checkpoint kept for a resume that gives the uninterrupted draws."""
    root, mesh, ref = reference
    out = tmp_path / "run"
    proc = _start(mesh, out)
    _wait_for(out / "checkpoint" / "state.npz", proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    line = err.strip().splitlines()[-1]
    assert line.startswith("bayesreg: interrupted ") and f"`bayesreg run --resume {out}`" in line
    assert "Traceback" not in err
    assert main(["run", "--resume", str(out)]) == 0
    np.testing.assert_array_equal(_draws(out), _draws(ref))


@pytest.mark.slow
def test_stuck_chains_are_a_loud_warning_a_status_of_their_own_and_strict_json(
        reference, tmp_path, capsys):
    """Chains that never move (every proposal rejected) are named in a warning, in the
    printed report and in ``run.json``; ``--strict`` makes them exit status 3; every JSON
    written parses strictly (no ``NaN`` or ``Infinity`` tokens: ``null`` with a note)."""
    root, mesh, ref = reference
    out = tmp_path / "stuck"
    huge = ["--set", "sampler.sigma_u=500", "--set", "sampler.sigma_lam=500", "--set",
            "sampler.sigma_mu=500", "--set", "sampler.warmup_steps=0"]
    with pytest.warns(RuntimeWarning, match=r"chains \[0, 1\] never moved"):
        assert main(_args(mesh, out, *huge, "--strict")) == 3
    assert "verdict: NOT converged: chains [0, 1] never moved" in capsys.readouterr().out

    def strict(token):
        raise ValueError(f"non-standard JSON token {token}")

    run = json.loads((out / "run.json").read_text(), parse_constant=strict)
    assert run["sampler"]["stuck_chains"] == [0, 1]
    assert run["non_finite"]["paths"] and run["sampler"]["rhat_classic_max"] is None
    for path in (out / "errors.json", out / "checkpoint" / "config.json"):
        json.loads(path.read_text(), parse_constant=strict)


def test_a_tangled_or_misplaced_mesh_file_is_refused(reference, tmp_path, capsys):
    """A folded mesh (an element turned inside out) and a mesh in voxel units are refused in
    the mesh stage with what is wrong named, before anything runs."""
    root, mesh, ref = reference
    m = meshio.read(mesh)
    nodes, tets = np.asarray(m.points), m.cells_dict["tetra"]
    counts = np.bincount(tets.ravel(), minlength=len(nodes))
    surface = np.unique(np.sort(tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), 1),
                        axis=0, return_counts=True)
    on_surface = np.unique(surface[0][surface[1] == 1])
    inner = next(n for n in np.argsort(-counts) if n not in on_surface)
    folded = nodes.copy()
    neighbours = np.unique(tets[np.any(tets == inner, axis=1)])
    far = neighbours[np.argmax(np.linalg.norm(nodes[neighbours] - nodes[inner], axis=1))]
    folded[inner] = nodes[far] + 1.5 * (nodes[far] - nodes[inner])  # across its neighbour
    for name, points, match in (
            ("folded.vtu", folded, r"mesh: mesh file .*folded\.vtu is tangled \(folded elements\)"),
            ("voxels.vtu", nodes / 3.0, r"mesh: mesh file .*voxels\.vtu does not match the brain "
                                        r"of the label map: the mesh holds \d+ ml")):
        meshio.write(tmp_path / name, meshio.Mesh(points, [("tetra", tets)]))
        assert main(_args(tmp_path / name, tmp_path / "run")) == 2
        err = capsys.readouterr().err
        assert re.search(match, err), err
        assert not (tmp_path / "run").exists()


def test_a_library_failure_names_its_stage_and_what_to_change(reference, tmp_path, monkeypatch,
                                                              capsys):
    """A LAPACK failure deep in the truth's solve reaches the user as the stage and what to
    change, not as the library's code alone."""
    root, mesh, ref = reference

    def potrf(*args, **kwargs):
        raise np.linalg.LinAlgError("Internal potrf return info = [312] for slices [0].")

    monkeypatch.setattr(bayesreg.model.problem, "brain_shift", potrf)
    assert main(_args(mesh, tmp_path / "run")) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    # The stages finished before the truth print their lines first; the error is the last one.
    assert [line.split(" done ")[0] for line in lines[:-1]] == ["bayesreg: data", "bayesreg: mesh"]
    err = lines[-1]
    assert err.startswith("bayesreg: error: truth: a dense factorisation failed (LAPACK: "
                          "Internal potrf return info = [312] for slices [0].)")
    assert "synthetic.shift_mm" in err and "synthetic.truth: smooth" in err


def test_a_full_disk_names_the_file_and_leaves_nothing_half_written(reference, tmp_path, capsys):
    """On a full disk (a 1 MB tmpfs) the run stops with the file it could not write named and
    the directory as it was."""
    root, mesh, ref = reference
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({mounted.stderr.strip() or 'not root'})")
    try:
        assert main(_args(mesh, disk / "run")) == 2
        err = capsys.readouterr().err
        assert re.search(rf"cannot write {re.escape(str(disk))}/run/checkpoint/\S+: No space left "
                         "on device", err), err
        assert not list(disk.iterdir())
    finally:
        subprocess.run(["umount", str(disk)], check=False)


def test_messages_name_what_they_reject(reference, tmp_path, capsys):
    """``report --out`` a file says so in the CLI's words; ``--set =3`` shows the item."""
    root, mesh, ref = reference
    assert main(["report", str(ref), "--out", str(mesh)]) == 2
    assert f"report directory {mesh} is a file: choose a folder for --out" in capsys.readouterr().err
    (tmp_path / "report").mkdir()
    (tmp_path / "report" / "x").write_text("x")
    assert main(["report", str(ref), "--out", str(tmp_path / "report")]) == 2
    assert "pass --overwrite" in capsys.readouterr().err
    assert main(["run", CONFIG, "--set", "=3"]) == 2
    assert "--set '=3': the key must be dotted names" in capsys.readouterr().err
