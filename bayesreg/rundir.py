"""A run directory: written in place while the run goes, never overwritten silently.

Final outputs are staged in ``.outputs-partial`` and moved in by
:meth:`RunDirectory.commit`, ``run.json`` last (its presence marks a finished run).  A run in
progress keeps its draws in ``checkpoint/`` (:mod:`bayesreg.checkpoint`).
"""

from __future__ import annotations

import glob
import os
import shutil
import uuid
from pathlib import Path

from bayesreg._files import fsync_dir, fsync_file

__all__ = ["RunDirectory"]


class RunDirectory:
    """A run directory, written in place while the run goes and never overwritten silently.

    The run's checkpoint (:class:`bayesreg.checkpoint.Checkpoint`) lives in
    ``path/checkpoint``; final outputs are staged in ``path/.outputs-partial`` and moved in
    by :meth:`commit`, ``run.json`` last (its presence marks a finished run).

    Parameters
    ----------
    path : str or Path
    overwrite : bool
        Replace an existing non-empty directory that holds one of ``marks`` (a folder of
        other files is never replaced): it is moved aside to a hidden sibling
        (``.NAME.replaced-PID-XXXXXXXX``, unique per call) at once and deleted only when the new run commits;
        :meth:`rollback` puts it back.  A run interrupted after its sampling started keeps
        the sibling; the next run into ``path`` that commits (its ``--resume``, or another
        ``overwrite``) deletes it.
    resume : bool
        Continue the unfinished run in ``path`` (it must hold ``checkpoint/config.json`` and
        no ``run.json``).
    marks : tuple of str
        Names whose presence in ``path`` makes it a directory ``overwrite`` may replace
        (default: a run's ``run.json`` and ``checkpoint``, and the staging folder
        ``.outputs-partial`` that a run without checkpoints killed while writing its
        outputs leaves).
    inputs : dict, optional
        ``{name: path}`` of files the run still has to read (data, a given mesh): none may
        lie inside a directory that ``overwrite`` replaces (it moves aside at once).

    Raises
    ------
    FileExistsError
        If ``path`` exists, is not empty and neither ``overwrite`` nor ``resume`` is set;
        with ``overwrite``, if it holds none of ``marks``; with ``resume``, if the run there
        is already finished.
    NotADirectoryError
        If ``path`` or one of its parents is a file.
    ValueError
        With ``overwrite``, if one of ``inputs`` lies inside the directory to replace (named).
    FileNotFoundError
        With ``resume``, if ``path`` holds no checkpoint.
    """

    def __init__(self, path, *, overwrite=False, resume=False,
                 marks=("run.json", "checkpoint", ".outputs-partial"), inputs=None):
        self.path = Path(path)
        self.overwrite = overwrite
        self._old: Path | None = None
        # directories replaced by earlier --overwrite runs into this path that were
        # interrupted after their sampling started: deleted when this run commits
        self._stale = sorted(self.path.parent.glob(f".{glob.escape(self.path.name)}.replaced-*"))
        for p in (self.path, *self.path.parents):
            if p.exists() and not p.is_dir():
                raise NotADirectoryError(f"run directory {self.path}: {p} is a file")
        self._created = not self.path.exists()
        if resume:
            if (self.path / "run.json").is_file():
                raise FileExistsError(f"run {self.path} is finished (run.json exists): nothing to resume")
            if not (self.path / "checkpoint" / "config.json").is_file():
                raise FileNotFoundError(f"{self.path} holds no checkpoint/config.json: nothing to resume")
        elif self.path.exists() and any(self.path.iterdir()):
            if not overwrite:
                hint = (" (an unfinished run: continue it with --resume)"
                        if (self.path / "checkpoint").is_dir() and not (self.path / "run.json").exists()
                        else "")
                raise FileExistsError(
                    f"run directory {self.path} exists and is not empty{hint}; pass --out to "
                    "choose another or --overwrite to replace it"
                )
            if not any((self.path / m).exists() for m in marks):
                raise FileExistsError(
                    f"{self.path} is not empty and holds none of {', '.join(marks)}: not a "
                    "directory bayesreg wrote, so --overwrite does not replace it; choose "
                    "another --out"
                )
            if self.path.resolve() in (Path.cwd().resolve(), *Path.cwd().resolve().parents):
                raise FileExistsError(f"{self.path} is the working directory or holds it: "
                                      "--overwrite does not replace it; choose another --out")
            here = self.path.resolve()
            inside = [f"{key} ({p})" for key, p in (inputs or {}).items()
                      if here in Path(p).resolve().parents]
            if inside:
                raise ValueError(
                    f"{', '.join(inside)} {'lies' if len(inside) == 1 else 'lie'} inside the "
                    f"run directory {self.path} that --overwrite replaces: copy "
                    f"{'it' if len(inside) == 1 else 'them'} elsewhere first, or choose another "
                    "--out")
            # unique per call: an interrupted --overwrite leaves its aside folder (deleted by
            # the next commit), and a notebook may overwrite the same path again in one process
            self._old = self.path.with_name(
                f".{self.path.name}.replaced-{os.getpid()}-{uuid.uuid4().hex[:8]}")
            os.replace(self.path, self._old)
        self.path.mkdir(parents=True, exist_ok=True)
        self._staging = self.path / ".outputs-partial"

    @property
    def replaced(self) -> Path | None:
        """Where the directory this one replaces waits until :meth:`commit` (else ``None``)."""
        return self._old

    @property
    def staging(self) -> Path:
        """Hidden folder for the final outputs, created on first use."""
        self._staging.mkdir(exist_ok=True)
        return self._staging

    def file(self, name) -> Path:
        return self.staging / name

    def commit(self) -> Path:
        """Move the staged outputs in (each file atomically, ``run.json`` last)."""
        names = sorted(p.name for p in self.staging.iterdir())
        for name in names:  # every file on disk before any rename (a power loss: old or new)
            if (self.staging / name).is_file():
                fsync_file(self.staging / name)
        for name in [n for n in names if n != "run.json"] + [n for n in names if n == "run.json"]:
            os.replace(self.staging / name, self.path / name)
        fsync_dir(self.path)
        self.staging.rmdir()
        if self._old is not None:
            shutil.rmtree(self._old)
            self._old = None
        for p in self._stale:
            shutil.rmtree(p, ignore_errors=True)
        self._stale = []
        return self.path

    def rollback(self) -> None:
        """Undo the directory of a run that failed before it wrote anything to resume.

        Deletes what this run wrote and puts back what was there before: the replaced
        directory (``overwrite``), an empty directory, or nothing.  Not for resumed runs.
        """
        shutil.rmtree(self.path, ignore_errors=True)
        if self._old is not None:
            os.replace(self._old, self.path)
            self._old = None
        elif not self._created:
            self.path.mkdir(parents=True, exist_ok=True)
