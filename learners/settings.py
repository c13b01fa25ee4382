"""A learner's settings: one frozen dataclass per learner, the schema of its config.

Each learner names its settings class (``settings``): the fields, their defaults and why are
written there once, ``__post_init__`` checks every range in one line naming the config key
(:mod:`harness.core.checks`) and keeps each value as the type the code uses (:func:`settle`).
``harness/config.py`` stores the class as the Hydra schema of ``conf/learner/*.yaml``, whose
``_target_`` is the learner: Hydra calls the learner with the settings as keywords, and the
learner builds its settings dataclass from them. A learner's ``hyperparameters`` (what a model
file holds) are its settings as plain data (:func:`plain`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, is_dataclass
from typing import Any, TypeVar

__all__ = ["NoSettings", "block", "plain", "settle"]

_Block = TypeVar("_Block")


@dataclass(frozen=True)
class NoSettings:
    """The settings of a learner that has none (persistence)."""


def settle(settings: Any, **values: Any) -> None:
    """Set checked values on a frozen settings dataclass (from its ``__post_init__``)."""
    for name, value in values.items():
        object.__setattr__(settings, name, value)


def block(cls: type[_Block], value: Any, key: str) -> _Block:
    """``learner.<key>`` as a ``cls``: built already (Hydra's ``_target_``), its schema's node
    (a dataclass of the same fields), a plain mapping (a model file's hyperparameters, a test)
    or None (the defaults). Unknown keys fail in one line."""
    if isinstance(value, cls):
        return value
    if value is None:
        return cls()
    if is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in fields(value)}
    if not isinstance(value, Mapping):
        raise ValueError(f"learner.{key} must be a mapping of settings (got {value!r})")
    values = {k: v for k, v in value.items() if k != "_target_"}
    names = [f.name for f in fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ValueError(
            f"learner.{key}.{unknown[0]} is not a key of {cls.__name__} ({', '.join(names)})"
        )
    return cls(**values)


def plain(settings: Any) -> dict[str, Any]:
    """The settings as a model file holds them: a nested block as its fields (``asdict``), a
    part with its own ``hyperparameters`` (a dictionary, a wrapped learner) as those, and a
    sequence as a list."""
    values: dict[str, Any] = {}
    for f in fields(settings):
        value = getattr(settings, f.name)
        if hasattr(value, "hyperparameters"):
            value = value.hyperparameters
        elif is_dataclass(value) and not isinstance(value, type):
            value = asdict(value)
        elif isinstance(value, tuple | list):
            value = list(value)
        values[f.name] = value
    return values
