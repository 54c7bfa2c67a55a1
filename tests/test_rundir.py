"""The run directory (bayesreg.rundir): overwrite, rollback, resume and commit."""

import os
import re
import shutil

import pytest

from bayesreg.rundir import RunDirectory, RunDirectoryInUse


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

    # an overwrite that stops before its commit (interrupted, failed) puts the old run back
    rd = RunDirectory(old, overwrite=True)
    (old / "checkpoint").mkdir()
    assert rd.restore() == old
    assert (old / "run.json").read_text() == '{"new": true}' and not list(tmp_path.glob(".run.replaced-*"))

    # a process killed during an overwrite (no chance to put the old run back) leaves it
    # aside: every later RunDirectory of the path says where, and none deletes it, not even
    # the commit of the killed run's resume
    killed = RunDirectory(old, overwrite=True)
    (old / "checkpoint").mkdir()
    (old / "checkpoint" / "config.json").write_text("{}")
    killed.release()  # the process is gone, and its lock with it
    aside = list(tmp_path.glob(".run.replaced-*"))
    assert len(aside) == 1
    with pytest.warns(UserWarning, match=rf"waits in {re.escape(str(aside[0]))}.*never deletes it"):
        resumed = RunDirectory(old, resume=True)
    resumed.file("run.json").write_text('{"resumed": true}')
    resumed.commit()
    assert (old / "run.json").read_text() == '{"resumed": true}'
    assert aside[0].is_dir() and (aside[0] / "run.json").read_text() == '{"new": true}'
    shutil.rmtree(aside[0])

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


def test_one_open_run_directory_per_path(tmp_path):
    """A run directory is locked while open: a second opening (another process, or this
    one) is refused naming the holder's PID, whatever it asks (overwrite, resume); the lock
    goes with commit, rollback, restore or release, and leaves no file behind."""
    path = tmp_path / "run"
    first = RunDirectory(path)
    (path / "checkpoint").mkdir()
    (path / "checkpoint" / "config.json").write_text("{}")
    for kwargs in ({}, {"overwrite": True}, {"resume": True}):
        with pytest.raises(RunDirectoryInUse, match=rf"in use by process {os.getpid()}"):
            RunDirectory(path, **kwargs)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".run.lock", "run"]
    first.release()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    with RunDirectory(path, resume=True) as again:
        assert again.path == path
    second = RunDirectory(path, resume=True)
    second.file("run.json").write_text("{}")
    second.commit()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
