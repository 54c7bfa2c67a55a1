"""Durable atomic replacement of files (shared by checkpoints, outputs and NIfTI writes).

A file is written under a temporary name in its final folder, flushed to disk
(``os.fsync``), renamed over the final name (``os.replace``, atomic on POSIX and Windows),
and the folder's entry is flushed too.  A kill at any point leaves either the old file or
the new one; so does a power loss, which without the two flushes could leave an empty or
partial file under the final name (the rename reaching the disk before the data).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path

import numpy as np

__all__ = ["fsync_file", "fsync_dir", "replace_durably", "write_text_atomic", "writing",
           "strict_json", "dumps_json"]


@contextlib.contextmanager
def writing(path):
    """Name ``path`` in an :class:`OSError` raised while writing it (a full disk, a
    permission): ``[Errno 28] No space left on device`` alone does not say which file."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None and exc.errno is not None:
            raise OSError(exc.errno, f"cannot write {path}: {exc.strerror}", str(path)) from exc
        raise


def fsync_file(path) -> None:
    """Flush a written file's data to disk."""
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def fsync_dir(path) -> None:
    """Flush a folder's entries (renames, new files) to disk; a no-op where the platform
    cannot open a folder (Windows)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - Windows
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - file systems that refuse fsync on a folder
        pass
    finally:
        os.close(fd)


def replace_durably(tmp, path) -> None:
    """``os.replace(tmp, path)`` with ``tmp``'s data flushed before and the folder's entry
    after (module docstring)."""
    fsync_file(tmp)
    os.replace(tmp, path)
    fsync_dir(Path(path).parent)


def write_text_atomic(path, text: str) -> None:
    """Write ``text`` to ``path`` under a temporary name, then :func:`replace_durably`.

    Raises
    ------
    OSError
        The file could not be written (named in the message, e.g. a full disk).
    """
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with writing(path):
        tmp.write_text(text)
        replace_durably(tmp, path)


def strict_json(obj, _path: str = "") -> tuple[object, list[str]]:
    """``obj`` with every non-finite number (NaN, inf) replaced by ``None``, and the dotted
    paths of those replaced: strict JSON has no token for them (``json.dumps`` writes
    ``NaN`` and ``Infinity`` by default, which strict parsers reject)."""
    found: list[str] = []

    def clean(x, path):
        if isinstance(x, dict):
            return {str(k): clean(v, f"{path}.{k}" if path else str(k)) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v, f"{path}[{i}]") for i, v in enumerate(x)]
        if isinstance(x, np.ndarray):
            return clean(x.tolist(), path)
        if isinstance(x, (np.bool_,)):
            return bool(x)
        if isinstance(x, (np.integer,)):
            return int(x)
        if isinstance(x, (float, np.floating)):
            if not math.isfinite(float(x)):
                found.append(path or "(value)")
                return None
            return float(x)
        return x

    return clean(obj, _path), found


def dumps_json(obj, *, note_key: str | None = "non_finite", **kwargs) -> str:
    """Strict JSON text of ``obj`` (:func:`strict_json`).  Where a mapping had non-finite
    numbers, written as ``null``, its key ``note_key`` lists their paths (``None``: no note).

    Raises
    ------
    ValueError
        ``obj`` holds something JSON cannot represent.
    """
    clean, found = strict_json(obj)
    if found and note_key is not None and isinstance(clean, dict):
        clean[note_key] = {"note": "non-finite numbers (NaN, inf) written as null", "paths": found}
    return json.dumps(clean, allow_nan=False, **kwargs)
