"""Every file the harness leaves is written atomically: a killed run leaves the old file or the
new one, never half of one, and two jobs writing the same path never share a temporary file.

A run holds its directory (:func:`lock_directory`) so that no second run writes into it, and
half-written files a killed writer left there (``.NAME.XXXX.tmp``) can be told from live ones.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np


def umask() -> int:
    """The process umask, read from /proc where Linux offers it: ``os.umask`` can only read it
    by setting it, and another thread creating a file in between would get the wrong mode."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_atomic(path: Path | str, write: Callable[[IO[bytes]], object]) -> Path:
    """Call ``write(handle)`` on a uniquely named temporary file beside ``path``, then rename it
    over ``path``; on any failure the temporary file is removed and the error raised.

    The file ends with the mode ``open()`` would give it (0o666 less the umask): ``mkstemp``
    creates 0o600, which would hide shared datasets and results from everyone but the owner.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~umask())
        with os.fdopen(fd, "wb") as handle:
            write(handle)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_text_atomic(path: Path | str, text: str) -> Path:
    return write_atomic(path, lambda handle: handle.write(text.encode()))


def plain(value: Any) -> Any:
    """JSON-safe copy: numpy scalars to Python, NaN/inf to null (JSON has no NaN)."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [plain(v) for v in value]
    if isinstance(value, (np.integer, np.bool_)):
        return value.item()
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    return value


def write_json_atomic(path: Path | str, content: Any, indent: int = 2) -> Path:
    return write_text_atomic(path, json.dumps(plain(content), indent=indent) + "\n")


LOCK_FILE = ".lock"  # in a run (or sweep) directory, held by the run writing into it
# Directories this process holds: a second open() + flock of the same file would conflict with
# our own lock (flock locks belong to open file descriptions), so a process holds each once.
_held: dict[Path, int] = {}


class DirectoryInUseError(ValueError):
    """Another process writes into the directory a run was given."""


def try_lock(path: Path) -> int | None:
    """An exclusive, non-blocking ``flock`` on ``path`` (created empty): the descriptor that
    holds it, or ``None`` when another open file holds it. The lock dies with its process, so a
    killed run never blocks the next one; closing the descriptor releases it."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def lock_directory(path: Path | str, key: str) -> bool:
    """Hold ``path`` (created if absent) for this process until :func:`unlock_directory`;
    ``True`` when taken now, ``False`` when this process held it already.

    Raises :class:`DirectoryInUseError` naming the directory and the setting ``key`` to change
    when another process holds it: two runs in one directory would mix their files."""
    path = Path(path).resolve()
    if path in _held:
        return False
    path.mkdir(parents=True, exist_ok=True)
    fd = try_lock(path / LOCK_FILE)
    if fd is None:
        raise DirectoryInUseError(
            f"{path} is in use by another run (it holds {path / LOCK_FILE}); choose another {key}"
        )
    _held[path] = fd
    return True


def unlock_directory(path: Path | str) -> None:
    """Release a directory :func:`lock_directory` took (the lock file stays: deleting it could
    let two runs lock two different files of one name)."""
    fd = _held.pop(Path(path).resolve(), None)
    if fd is not None:
        os.close(fd)


def remove_stale_temporaries(directory: Path, depth: int = 2) -> list[Path] | None:
    """Remove the ``.NAME.XXXX.tmp`` files of :func:`write_atomic` that killed writers left in
    ``directory`` and its subdirectories down to ``depth`` levels: the files removed, or
    ``None`` (nothing touched) while a run holds the directory and may still be writing them."""
    try:
        fd = try_lock(directory / LOCK_FILE)
    except OSError:  # a directory we may not write to: none of its files are ours to remove
        return None
    if fd is None:
        return None
    try:
        patterns = [("*/" * level) + ".*.tmp" for level in range(depth + 1)]
        stale = sorted({p for pattern in patterns for p in directory.glob(pattern) if p.is_file()})
        for path in stale:
            path.unlink(missing_ok=True)
    finally:
        os.close(fd)
    return stale
