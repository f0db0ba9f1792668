"""Atomic file writes: a crash or kill leaves the old file (or none), never half a file.

Every result, record, picture and checkpoint file of the project is written through here:
the bytes go to a temporary file beside the target, are flushed to disk, and the temporary
file is renamed over the target (`os.replace` is atomic on POSIX).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def file_mode(path: Path) -> int:
    """The permissions a rewritten `path` should keep: its own, or those of a new file (0666
    less the umask; `mkstemp` would otherwise leave 0600)."""
    if path.exists():
        return path.stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def check_writable(path: str | os.PathLike, what: str = "output file") -> Path:
    """`ValueError` now, before any work, unless `atomic_write(path, ...)` could write `path`:
    it must not be a directory, and its nearest existing folder must be a writable folder (the
    temporary file is made beside the target, then renamed over it)."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{what} {path} is a directory; give a file name")
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"{what} {path} cannot be created: {folder} is not a directory")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{what} {path} cannot be written: no permission to write in {folder}")
    return path


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], object]) -> Path:
    """Run `write(file)` on a temporary binary file beside `path`, then rename it over `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write(path, lambda f: f.write(text.encode()))


def atomic_write_json(path: str | os.PathLike, payload: object) -> Path:
    return atomic_write_text(path, json.dumps(payload, indent=2) + "\n")
