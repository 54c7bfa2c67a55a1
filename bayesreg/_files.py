"""Durable atomic replacement of files (shared by checkpoints, outputs and NIfTI writes).

A file is written under a temporary name in its final folder, flushed to disk
(``os.fsync``), renamed over the final name (``os.replace``, atomic on POSIX and Windows),
and the folder's entry is flushed too.  A kill at any point leaves either the old file or
the new one; so does a power loss, which without the two flushes could leave an empty or
partial file under the final name (the rename reaching the disk before the data).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["fsync_file", "fsync_dir", "replace_durably", "write_text_atomic"]


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
    """Write ``text`` to ``path`` under a temporary name, then :func:`replace_durably`."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    replace_durably(tmp, path)
