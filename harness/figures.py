"""Figures are written like every other artifact: atomically, so a killed run leaves no half PNG.

Figures are built with matplotlib's object API (``Figure``, no pyplot): no backend to select, no
global figure registry to leak, safe in worker processes and on machines with a display.
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure

from harness.files import write_atomic


def save_figure(fig: Figure, path: Path, dpi: int = 110) -> Path:
    """Save ``fig`` to ``path`` (its suffix names the format) through a temporary file."""
    path = Path(path)
    return write_atomic(path, lambda handle: fig.savefig(handle, format=path.suffix[1:], dpi=dpi))
