"""The checks every layer's settings share, written once: each raises the harness's one-line
``ValueError`` naming the full config key (``learner.training.lr must be > 0 (got -1)``), and
returns the value as the type the code uses. Every ``__post_init__`` is built from these."""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable
from typing import Any


def is_number(value: Any) -> bool:
    """A real number (NumPy's too): not a bool, nor a string that reads as one (``'1e-4'``)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def shown(value: Any) -> str:
    """A value as a person typed it: ``-1``, not the ``-1.0`` a float schema turned it into."""
    if is_number(value) and math.isfinite(value) and float(value).is_integer():
        return str(int(value))
    return repr(float(value)) if is_number(value) else repr(value)


def require(condition: bool, key: str, requirement: str, value: Any) -> None:
    """Raise ``<key> must be <requirement> (got <value>)`` unless ``condition`` holds."""
    if not condition:
        raise ValueError(f"{key} must be {requirement} (got {shown(value)})")


def finite(key: str, value: Any) -> float:
    """A finite real number."""
    require(is_number(value) and math.isfinite(value), key, "a finite number", value)
    return float(value)


def positive(key: str, value: Any) -> float:
    """A finite number > 0."""
    require(is_number(value), key, "a number > 0", value)
    require(math.isfinite(value) and value > 0, key, "> 0", value)
    return float(value)


def non_negative(key: str, value: Any) -> float:
    """A finite number >= 0."""
    require(is_number(value), key, "a number >= 0", value)
    require(math.isfinite(value) and value >= 0, key, ">= 0", value)
    return float(value)


def integer(key: str, value: Any, minimum: int = 1) -> int:
    """A whole number >= ``minimum``; a float that is one (``1e3`` from the command line) too."""
    whole = is_number(value) and math.isfinite(value) and float(value).is_integer()
    require(whole and value >= minimum, key, f"an integer >= {minimum}", value)
    return int(value)


def in_range(key: str, value: Any, low: float, high: float, *, open_low: bool = False) -> float:
    """A number in [low, high], or (low, high] with ``open_low``."""
    bracket = "(" if open_low else "["
    require(is_number(value), key, f"a number in {bracket}{shown(low)}, {shown(high)}]", value)
    above = value > low if open_low else value >= low
    require(above and value <= high, key, f"in {bracket}{shown(low)}, {shown(high)}]", value)
    return float(value)


def choice(key: str, value: Any, choices: Iterable[str]) -> str:
    """One of ``choices``."""
    options = tuple(choices)
    require(value in options, key, f"one of {', '.join(options)}", value)
    return str(value)


def boolean(key: str, value: Any) -> bool:
    """True or false (not 1, nor the string 'yes')."""
    require(isinstance(value, bool), key, "true or false", value)
    return bool(value)
