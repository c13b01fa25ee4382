"""What a run leaves in its directory, written like every other artifact: atomically, so a killed
run leaves the old file or the new one, never half of one.

- ``metrics.json``: the harness's public result, merged by section (:func:`update_metrics`);
- figures (:func:`save_figure`), built with matplotlib's object API (``Figure``, no pyplot): no
  backend to select, no global figure registry to leak, safe in worker processes;
- arrays beside the figures (:func:`save_arrays`), so a sweep's report can redraw them across
  jobs: ``prediction_<episode>.npz`` (measured and predicted states),
  ``tracking_<controller>_<reference>.npz`` (reference, states, inputs, solve times).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from harness.core.files import plain, write_atomic, write_json_atomic


def update_metrics(path: Path, section: str, values: Mapping[str, Any]) -> dict[str, Any]:
    """Set ``section`` in ``path`` (keeping the other sections) and return the whole document."""
    document: dict[str, Any] = {}
    if path.exists():
        try:
            document = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise ValueError(
                f"{path} is not valid JSON ({error}); move it away and rerun"
            ) from error
    document[section] = plain(values)
    write_json_atomic(path, document)
    return document


def save_figure(fig: Figure, path: Path, dpi: int = 110) -> Path:
    """Save ``fig`` to ``path`` (its suffix names the format) through a temporary file."""
    path = Path(path)
    return write_atomic(path, lambda handle: fig.savefig(handle, format=path.suffix[1:], dpi=dpi))


def save_arrays(path: Path, **arrays: np.ndarray) -> Path:
    """``np.savez_compressed`` through a temporary file in the same directory."""
    contents = {k: np.asarray(v) for k, v in arrays.items()}
    # numpy's stubs type **kwds as allow_pickle (bool); here they are the arrays' names.
    return write_atomic(path, lambda handle: np.savez_compressed(handle, **contents))  # type: ignore[arg-type]


def load_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file; a damaged file raises ``ValueError`` naming it."""
    try:
        with np.load(path) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError) as error:
        raise ValueError(f"{path} is not a readable .npz file ({error}); rerun its job") from error
