"""The run directory (bayesreg.rundir): overwrite, rollback, resume and commit."""

import os

import pytest

from bayesreg.rundir import RunDirectory


def test_run_directory_overwrite_replaces_only_a_run_and_rollback_puts_it_back(tmp_path, monkeypatch):
    """``overwrite`` never hides a folder bayesreg did not write; a failed start undoes itself."""
    monkeypatch.chdir(tmp_path)
    data = tmp_path / "data"
    data.mkdir()
    (data / "f.nii.gz").write_text("the user's input")
    with pytest.raises(FileExistsError, match="not empty"):
        RunDirectory(data)
    with pytest.raises(FileExistsError, match="holds none of run.json, checkpoint"):
        RunDirectory(data, overwrite=True)
    assert (data / "f.nii.gz").read_text() == "the user's input"
    with pytest.raises(NotADirectoryError, match="is a file"):
        RunDirectory(data / "f.nii.gz" / "run")
    with pytest.raises(FileExistsError, match="working directory"):
        (tmp_path / "run.json").write_text("{}")
        RunDirectory(tmp_path, overwrite=True)
    (tmp_path / "run.json").unlink()

    old = tmp_path / "run"
    old.mkdir()
    (old / "run.json").write_text('{"old": true}')
    rd = RunDirectory(old, overwrite=True)  # the old run moves aside at once
    hidden = rd.replaced
    assert hidden.is_dir() and hidden.name.startswith(f".run.replaced-{os.getpid()}-")
    assert not any(old.iterdir())
    (old / "checkpoint").mkdir()
    rd.rollback()  # a start that failed: the old run is back, nothing of the new one
    assert (old / "run.json").read_text() == '{"old": true}' and not hidden.exists()
    assert sorted(p.name for p in old.iterdir()) == ["run.json"]

    rd = RunDirectory(old, overwrite=True)
    rd.file("run.json").write_text('{"new": true}')
    rd.commit()  # a run that finished: the old one is gone
    assert (old / "run.json").read_text() == '{"new": true}' and not rd.replaced
    assert not list(tmp_path.glob(".run.replaced-*"))

    # a run interrupted after its sampling started keeps the run it replaced aside, and so
    # does a second one in the same process (a notebook), under a name of its own; the
    # resumed run's commit deletes them
    for _ in range(2):
        RunDirectory(old, overwrite=True)
        (old / "checkpoint").mkdir()
        (old / "checkpoint" / "config.json").write_text("{}")
    assert len(list(tmp_path.glob(".run.replaced-*"))) == 2
    resumed = RunDirectory(old, resume=True)
    resumed.file("run.json").write_text('{"resumed": true}')
    resumed.commit()
    assert not list(tmp_path.glob(".run.replaced-*"))
    assert (old / "run.json").read_text() == '{"resumed": true}'

    # the aside folders of another run are not this one's, whatever its name's glob says
    (tmp_path / ".exp1.replaced-1-0").mkdir()
    odd = RunDirectory(tmp_path / "exp[1]")
    odd.file("run.json").write_text("{}")
    odd.commit()
    assert (tmp_path / ".exp1.replaced-1-0").is_dir()

    # a run without checkpoints killed while writing its outputs leaves only its staging
    # folder: that is a directory bayesreg wrote, which --overwrite may replace
    partial = tmp_path / "partial"
    (partial / ".outputs-partial").mkdir(parents=True)
    RunDirectory(partial, overwrite=True).rollback()
    assert (partial / ".outputs-partial").is_dir()

    fresh = tmp_path / "fresh"
    RunDirectory(fresh).rollback()
    assert not fresh.exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    RunDirectory(empty).rollback()
    assert empty.is_dir() and not any(empty.iterdir())
