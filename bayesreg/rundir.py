"""A run directory: written in place while the run goes, never overwritten silently, one
process at a time.

Final outputs are staged in ``.outputs-partial`` and moved in by
:meth:`RunDirectory.commit`, ``run.json`` last (its presence marks a finished run).  A run in
progress keeps its draws in ``checkpoint/`` (:mod:`bayesreg.checkpoint`).  While a
:class:`RunDirectory` is open its process holds an advisory lock on the directory
(``fcntl.flock`` on a hidden sibling file ``.NAME.lock`` holding the holder's PID, removed
when the lock is released): a second
process, or a second :class:`RunDirectory` in the same process, is refused with the holder
named (:class:`RunDirectoryInUse`).
"""

from __future__ import annotations

import errno
import fcntl
import os
import shutil
import uuid
import warnings
from pathlib import Path

from bayesreg._files import fsync_dir, fsync_file

__all__ = ["RunDirectory", "RunDirectoryInUse"]


class RunDirectoryInUse(FileExistsError):
    """Another process (or another open :class:`RunDirectory`) holds the run directory."""


def _lock_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.lock")


def _lock(path: Path):
    """Take the advisory lock of run directory ``path``: an open file descriptor, or
    :class:`RunDirectoryInUse` naming the holder's PID.

    The lock file is removed on release (:func:`_unlock`), so a lock taken on a file that
    was removed meanwhile is not a lock: it is taken again on the file now at the path.
    """
    lock = _lock_path(path)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                os.close(fd)
                raise
            try:
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            finally:
                os.close(fd)
            raise RunDirectoryInUse(
                f"run directory {path} is in use by process {holder} (it holds {lock}): one "
                "run per directory; wait for that run to end, stop it, or choose another "
                "--out") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # released and removed by its holder in between: take the new one
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def _unlock(path: Path, fd) -> None:
    """Release the lock of :func:`_lock`, removing its file while still holding it."""
    try:
        os.unlink(_lock_path(path))
    except FileNotFoundError:  # pragma: no cover - removed by hand
        pass
    fcntl.flock(fd, fcntl.LOCK_UN)
    os.close(fd)


def replaced_leftovers(path) -> list[Path]:
    """The hidden siblings ``.NAME.replaced-PID-XXXXXXXX`` of the run directory ``path`` that
    an ``--overwrite`` moved aside and that its process, killed outright, never put back or
    deleted (sorted; none while that process still runs and holds the directory's lock)."""
    path = Path(path)
    prefix = f".{path.name}.replaced-"
    if not path.parent.is_dir():
        return []
    return sorted(p for p in path.parent.iterdir() if p.name.startswith(prefix) and p.is_dir())


def leftover_note(path, leftovers) -> str:
    """What to do with :func:`replaced_leftovers` of ``path``: one sentence naming each."""
    path = Path(path)
    where = ", ".join(str(p) for p in leftovers)
    one = len(leftovers) == 1
    back = (f"`rm -r {path} && mv {leftovers[0]} {path}` (this discards what is in {path} now)"
            if one else f"`mv` the one to keep to {path} after removing what is there")
    return (f"the run that an interrupted --overwrite replaced {'waits' if one else 'wait'} in "
            f"{where} (its process was killed before it could put it back); put "
            f"{'it' if one else 'one'} back with {back}, or delete "
            f"{'it' if one else 'them'}: bayesreg never deletes {'it' if one else 'them'}")


class RunDirectory:
    """A run directory, written in place while the run goes and never overwritten silently.

    The run's checkpoint (:class:`bayesreg.checkpoint.Checkpoint`) lives in
    ``path/checkpoint``; final outputs are staged in ``path/.outputs-partial`` and moved in
    by :meth:`commit`, ``run.json`` last (its presence marks a finished run).  The directory
    is locked from construction to :meth:`commit`, :meth:`rollback`, :meth:`restore` or
    :meth:`release` (also a context manager).

    Parameters
    ----------
    path : str or Path
    overwrite : bool
        Replace an existing non-empty directory that holds one of ``marks`` (a folder of
        other files is never replaced): it is moved aside to a hidden sibling
        (``.NAME.replaced-PID-XXXXXXXX``, unique per call) at once and deleted only when the
        new run commits; :meth:`rollback` and :meth:`restore` put it back.  A process killed
        outright (SIGKILL) cannot put it back: the sibling stays, and every later
        :class:`RunDirectory` of ``path`` warns where it is (it is never deleted but by the
        run that replaced it).
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
    RunDirectoryInUse
        Another process, or another open :class:`RunDirectory` of this process, holds
        ``path`` (its PID named).
    FileExistsError
        If ``path`` exists, is not empty and neither ``overwrite`` nor ``resume`` is set;
        with ``overwrite``, if it holds none of ``marks``; with ``resume``, if the run there
        is already finished.  The message names any run an interrupted ``overwrite`` left
        aside (:func:`replaced_leftovers`) and what to do with it.
    NotADirectoryError
        If ``path`` or one of its parents is a file.
    ValueError
        With ``overwrite``, if one of ``inputs`` lies inside the directory to replace (named).
    FileNotFoundError
        With ``resume``, if ``path`` holds no checkpoint.

    Warns
    -----
    UserWarning
        A directory replaced by an earlier ``overwrite`` whose process was killed waits in a
        hidden sibling (named, with how to put it back: :func:`leftover_note`).
    """

    def __init__(self, path, *, overwrite=False, resume=False,
                 marks=("run.json", "checkpoint", ".outputs-partial"), inputs=None):
        self.path = Path(path)
        self.overwrite = overwrite
        self._old: Path | None = None
        self._fd = None
        for p in (self.path, *self.path.parents):
            if p.exists() and not p.is_dir():
                raise NotADirectoryError(f"run directory {self.path}: {p} is a file")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = _lock(self.path)
        # directories replaced by earlier --overwrite runs whose process was killed (SIGKILL,
        # a power loss): never deleted here, only reported, in the refusal below too
        self.leftovers = replaced_leftovers(self.path)
        try:
            self._open(resume, marks, inputs)
        except FileExistsError as exc:
            self.release()
            if not self.leftovers:
                raise
            raise FileExistsError(f"{exc}; note: {leftover_note(self.path, self.leftovers)}") from None
        except BaseException:
            self.release()
            raise
        for p in self.leftovers:
            warnings.warn(f"run directory {self.path}: {leftover_note(self.path, [p])}",
                          UserWarning, stacklevel=2)

    def _open(self, resume, marks, inputs) -> None:
        self._created = not self.path.exists()
        if resume:
            if (self.path / "run.json").is_file():
                raise FileExistsError(f"run {self.path} is finished (run.json exists): nothing to resume")
            if not (self.path / "checkpoint" / "config.json").is_file():
                raise FileNotFoundError(f"{self.path} holds no checkpoint/config.json: nothing to resume")
        elif self.path.exists() and any(self.path.iterdir()):
            if not self.overwrite:
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
            # unique per call: a killed --overwrite leaves its aside folder, and a notebook may
            # overwrite the same path again in one process
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
        """Path of the output ``name`` in the staging folder (moved in by :meth:`commit`)."""
        return self.staging / name

    def release(self) -> None:
        """Give up the directory's lock (idempotent; :meth:`commit`, :meth:`rollback` and
        :meth:`restore` release it too)."""
        if self._fd is not None:
            _unlock(self.path, self._fd)
            self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()
        return False

    def commit(self) -> Path:
        """Move the staged outputs in (each file atomically, ``run.json`` last), delete the
        directory this one replaced, and release the lock."""
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
        self.release()
        return self.path

    def rollback(self) -> None:
        """Undo the directory of a run that failed before it wrote anything to resume.

        Deletes what this run wrote and puts back what was there before: the replaced
        directory (``overwrite``), an empty directory, or nothing; releases the lock.  Not
        for resumed runs.
        """
        shutil.rmtree(self.path, ignore_errors=True)
        if self._old is not None:
            os.replace(self._old, self.path)
            self._old = None
        elif not self._created:
            self.path.mkdir(parents=True, exist_ok=True)
        self.release()

    def restore(self) -> Path | None:
        """Put back the directory an ``overwrite`` replaced, discarding this run's unfinished
        one (a run interrupted or failed before its commit); releases the lock.

        Returns
        -------
        Path or None
            The run directory put back, or ``None`` when nothing was replaced (then nothing
            changes but the lock).
        """
        if self._old is None:
            self.release()
            return None
        self.rollback()
        return self.path
