"""A least-squares lifted-linear model: EDMD with hand-picked observables, for the controller.

Not a learner (those live in ``learners/``): a fixed polynomial lift and one least-squares
solve give, in under a second, a :class:`~harness.core.contracts.LiftedModel` good enough to close a
loop on the plant; the solve-time benchmark and the controller's tests drive DE-MPC with it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from harness.core.contracts import Dynamics
from harness.core.episode import Episode, MinMaxNormalizer


def polynomial_features(x_norm: np.ndarray) -> np.ndarray:
    """(..., 10): 1, the six quadratic and three cubic monomials of the centred state.

    The products carry what a linear model misses: vx·r (centripetal), lateral terms growing
    with speed.
    """
    centred = np.asarray(x_norm, dtype=float) - 0.5
    vx, vy, r = centred[..., 0], centred[..., 1], centred[..., 2]
    terms = [np.ones_like(vx), vx * vy, vx * r, vy * r, vx * vx, vy * vy, r * r]
    return np.stack([*terms, vx * vx * vy, vx * vx * r, vx**3], axis=-1)


@dataclass
class LiftedLinearModel:
    """z = [x_norm; features(x_norm)], z⁺ = A_ z + B_ v, x_norm = C_ z: a ``LiftedModel``."""

    A_: np.ndarray
    B_: np.ndarray
    dynamics: ClassVar[Dynamics] = "linear"
    normalizer_: MinMaxNormalizer
    features: Callable[[np.ndarray], np.ndarray] = field(default=polynomial_features)
    C_: np.ndarray = field(init=False)  # the state is the lift's first three coordinates

    def __post_init__(self) -> None:
        size = self.A_.shape[0]
        self.C_ = np.hstack([np.eye(3), np.zeros((3, size - 3))])

    def lift(self, x: np.ndarray) -> np.ndarray:
        x_norm = self.normalizer_.states(x)
        return np.concatenate([x_norm, self.features(x_norm)], axis=-1)


def fit_lifted_linear(
    episodes: Sequence[Episode],
    features: Callable[[np.ndarray], np.ndarray] = polynomial_features,
    normalizer: MinMaxNormalizer | None = None,
) -> LiftedLinearModel:
    """Least squares [A B] = argmin Σ ||z_{k+1} - A z_k - B v_k||² over all one-step pairs."""
    normalizer = normalizer or MinMaxNormalizer.fit(episodes)
    before, after, inputs = [], [], []
    for episode in episodes:
        x_norm = normalizer.states(episode.states)
        z = np.concatenate([x_norm, features(x_norm)], axis=-1)
        before.append(z[:-1])
        after.append(z[1:])
        inputs.append(normalizer.inputs(episode.inputs[:-1]))
    regressors = np.hstack([np.concatenate(before), np.concatenate(inputs)])
    solution, *_ = np.linalg.lstsq(regressors, np.concatenate(after), rcond=None)
    size = before[0].shape[1]
    return LiftedLinearModel(solution[:size].T, solution[size:].T, normalizer, features)
