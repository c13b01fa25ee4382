"""Persistence, the bar every model must clear: the state is held, x_{k+1} = x_k.

It needs no data and has nothing to fit, yet over a few seconds of steady driving it is hard to
beat on vx; a model worse than it has learnt nothing that a prediction can use. Its RMSE over a
window of p steps is the RMS change of the state from each window's start (a closed form the
tests check). Every prediction table has its row (``prediction.persistence`` in metrics.json).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import ClassVar, Self

import numpy as np
import torch

from harness.core.episode import Episode, MinMaxNormalizer
from learners.base import Learner, Shape, check_rollout_args

__all__ = ["Persistence"]


class Persistence(Learner):
    """x_{k+1} = x_k under any inputs (module docstring)."""

    name: ClassVar[str] = "persistence"

    def fit(
        self, train: Sequence[Episode], validation: Sequence[Episode], normalizer: MinMaxNormalizer
    ) -> Self:
        """Nothing to learn: keeps the normalizer (the inputs' names and count) only."""
        del train, validation
        self.normalizer_ = normalizer
        return self

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        x0, inputs = check_rollout_args(
            x0, inputs, len(self.normalizer_.state_min), len(self.normalizer_.input_min)
        )
        steps = inputs.shape[-2] + 1
        return np.repeat(x0[..., None, :], steps, axis=-2)

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {}

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        return {}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        del state
