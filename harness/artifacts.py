"""Arrays a run leaves beside its figures, so a sweep's report can redraw them across jobs.

``prediction_<episode>.npz`` (measured and predicted states),
``tracking_<controller>_<reference>.npz`` (reference, states, inputs, solve times) and
``training_history.json`` (loss curves) are written atomically, like ``metrics.json``: a killed
run leaves either the old file or the new one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from harness.files import write_atomic


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
