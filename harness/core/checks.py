"""Checks every layer's settings share, written once."""

from __future__ import annotations

import numbers
from typing import Any


def is_number(value: Any) -> bool:
    """A real number (NumPy's too): not a bool, nor a string that reads as one (``'1e-4'``)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)
