"""A learner that fits another, ``learner.inner``, and reads it as a model of its own: what the
pedal split (``split_pedal.py``) and the mirror average (``mirror_symmetric.py``) share.

The inner learner is built from its config, saved and loaded in the same file under ``inner.``,
and its hyperparameters are the wrapper's, beside the inner class's name; the run's loss curves
and fit summary are the inner learner's (``core``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Self

import numpy as np
import torch

from learners.base import Learner, Shape
from learners.model_file import learner_class
from learners.settings import plain

__all__ = ["WrappingLearner", "inner_learner"]


def inner_learner(value: Any) -> Learner:
    """``learner.inner`` as a learner: built (Hydra's ``_target_``), or its settings with
    ``_target_`` (its schema's node, a mapping), built here."""
    if isinstance(value, Learner):
        return value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if not (isinstance(value, Mapping) and "_target_" in value):
        raise ValueError(
            f"learner.inner must be a learner config (a _target_ in learners), got {value!r:.80}"
        )
    settings = {str(k): v for k, v in value.items() if not str(k).startswith("_")}
    return learner_class(str(value["_target_"]), "learner.inner._target_")(**settings)


class WrappingLearner(Learner):
    """The part of a wrapping learner that is the same for every wrapper: ``config.inner`` (a
    built learner) becomes ``self.inner``; a subclass fits it and reads it (``_read_inner``)."""

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        self.inner: Learner = self.config.inner

    @property
    def hyperparameters(self) -> dict[str, Any]:
        """The inner learner's class and settings, and the wrapper's own."""
        inner = type(self.inner)
        return {"inner_class": f"{inner.__module__}.{inner.__qualname__}", **plain(self.config)}

    @classmethod
    def from_hyperparameters(cls, hyperparameters: Mapping[str, Any]) -> Self:
        inner_class = learner_class(str(hyperparameters.get("inner_class", "")), cls.name)
        inner = inner_class.from_hyperparameters(hyperparameters["inner"])
        own = {k: v for k, v in hyperparameters.items() if k not in ("inner_class", "inner")}
        return cls(inner, **own)

    @property
    def core(self) -> Learner:
        return self.inner

    @property
    def redraws_random_layer(self) -> bool:
        return self.inner.redraws_random_layer

    @property
    def fit_summary(self) -> dict[str, Any]:
        return self.inner.fit_summary

    def _inner_input_count(self, m: int) -> int:
        """How many inputs the inner model has where this one has ``m``."""
        return m

    def _read_inner(self) -> None:
        """What this model reads from its fitted inner model (after ``fit`` and a load)."""

    # -- the file ---------------------------------------------------------------------------------

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {f"inner.{k}": value for k, value in self.inner._state().items()}

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        shapes = self.inner._state_shapes(n, self._inner_input_count(m))
        return {f"inner.{k}": shape for k, shape in shapes.items()}

    def _set_inner_state(self, state: Mapping[str, torch.Tensor], normalizer: Any) -> None:
        """The inner model's arrays from this file, in ``normalizer``'s units, then read."""
        self.inner.normalizer_ = normalizer
        self.inner._set_state({k.removeprefix("inner."): v for k, v in state.items()})
        self._read_inner()
