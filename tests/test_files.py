"""Durable atomic writes: checkpoints, NIfTI files and a run's commit flush each file before
its rename and the folder after it."""

import os

import numpy as np

from bayesreg.checkpoint import savez_atomic
from bayesreg.data.images import Image, save_nifti
from bayesreg.rundir import RunDirectory


def test_writes_are_flushed_to_disk_before_their_rename(tmp_path, monkeypatch):
    """Checkpoints, NIfTI files and a run's commit flush each file's data before
    the rename and the folder's entry after it (a power loss leaves the old file or the new
    one, never an empty one under the final name)."""
    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (events.append(("fsync", os.readlink(
        f"/proc/self/fd/{fd}"))), real_fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda a, b: (events.append(("replace", str(b))),
                                                            real_replace(a, b))[1])

    savez_atomic(tmp_path / "a.npz", x=np.arange(3))
    np.testing.assert_array_equal(np.load(tmp_path / "a.npz")["x"], np.arange(3))
    assert [e[0] for e in events] == ["fsync", "replace", "fsync"]
    assert events[0][1].endswith("a.npz.tmp.npz") and events[2][1] == str(tmp_path)
    events.clear()
    save_nifti(Image(np.zeros((2, 2, 2), np.float32), np.eye(4)), tmp_path / "b.nii.gz")
    assert [e[0] for e in events] == ["fsync", "replace", "fsync"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.nii.gz"]  # no temporaries

    events.clear()
    rd = RunDirectory(tmp_path / "run")
    rd.file("summary.csv").write_text("x\n")
    rd.file("run.json").write_text("{}")
    events.clear()
    rd.commit()
    synced = [e[1] for e in events if e[0] == "fsync"]
    staged = tmp_path / "run" / ".outputs-partial"
    assert synced == [str(staged / "run.json"), str(staged / "summary.csv"), str(tmp_path / "run")]
    assert (tmp_path / "run" / "run.json").read_text() == "{}" and not staged.exists()
