"""Every file the harness leaves is written atomically: a killed run leaves the old file or the
new one, never half of one, and two jobs writing the same path never share a temporary file."""

from __future__ import annotations

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
