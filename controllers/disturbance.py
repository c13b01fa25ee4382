"""What DE-MPC learns of its model's error while it drives: a disturbance w in the model's step.

The controller predicts z⁺ = f(z, v) + w. Each step it measures the last step's one-step
prediction error e = z − ẑ (ẑ with the w it had) and hands it to its estimator, which returns
the w to predict with; a constant model error is then learned and predicted away (offset-free
tracking), so a steady reference leaves no steady offset. A controller config names its
estimator as a ``_target_`` block (``controller.disturbance``; null: no disturbance, the
paper's DE-MPC):

- :class:`OffsetFree`: w += gain · e, a fixed share of each error (gain 1 holds the last
  step's error: the best of 0.02-1 at 10/7, docs/findings/lane_change.md);
- :class:`KalmanDisturbance`: w a random walk observed through e, each coordinate's gain the
  Kalman filter's: large while w is unknown, settling to the steady-state gain that weighs how
  fast w moves against how noisy a step's error is.

Below ``lateral_min_speed_mps``, for a model that steps the state x itself (the DNN, input
EDMD, the single-track model), DE-MPC drops w's vy and r parts. A stopped car has no lateral
motion, and its wheel turns it as no model quite says: with gain 1 w fed the model's answer to
the last wheel move back as the opposite move, a two-step saw of the wheel at a stop. The
speed's part is kept: it tracks the stop itself (dropping the whole estimate there cost every
model's speed tracking). A lifted model's w holds the lateral error in its lifted coordinates
too; dropping only the state's drove Deep EDMD worse, so a lifted w is left whole
(docs/findings/smooth_driving.md, "The saw at a stop").

A new estimator is one class with ``lateral_min_speed_mps``, ``start`` and ``update`` and one
block in a controller's YAML: DE-MPC asks nothing else of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from harness.core.checks import in_range, non_negative, positive

__all__ = ["DisturbanceEstimator", "KalmanDisturbance", "OffsetFree", "learned", "without_lateral"]


@runtime_checkable
class DisturbanceEstimator(Protocol):
    """An estimate of the disturbance w in the model's step, updated once a control step."""

    w: np.ndarray  # the estimate now (what the next step's preparation predicts with)
    lateral_min_speed_mps: float  # below this |vx| w drops vy's and r's parts (z = x models)

    def start(self, size: int) -> None:
        """A new run: w = 0 in a lifted state of ``size`` coordinates."""

    def update(self, error: np.ndarray | None) -> np.ndarray:
        """The w to predict this step with, given the last step's one-step prediction error
        z − ẑ (None on a run's first step: nothing was predicted yet)."""


@dataclass
class OffsetFree:
    """w += gain · (z − ẑ): a fixed share of each step's one-step prediction error."""

    gain: float = 1.0
    lateral_min_speed_mps: float = 0.0  # m/s; 0: the lateral part at any speed
    w: np.ndarray = field(
        default_factory=lambda: np.zeros(0), init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        in_range("controller.disturbance.gain", self.gain, 0.0, 1.0, open_low=True)
        non_negative("controller.disturbance.lateral_min_speed_mps", self.lateral_min_speed_mps)

    def start(self, size: int) -> None:
        self.w = np.zeros(size)

    def update(self, error: np.ndarray | None) -> np.ndarray:
        if error is not None:
            self.w = self.w + self.gain * error
        return self.w


@dataclass
class KalmanDisturbance:
    """w a random walk (each step's change of variance ``process_variance``) observed through
    the one-step prediction error (variance ``measurement_variance``), per lifted coordinate, in
    the model's normalized units. The gain starts near 1 (w is unknown: ``initial_variance``)
    and settles to the steady-state Kalman gain (:meth:`steady_gain`): a slow-moving w measured
    through noisy errors gets a small gain, and the estimate averages the noise away."""

    process_variance: float = 1e-6
    measurement_variance: float = 1e-5
    initial_variance: float = 1.0
    lateral_min_speed_mps: float = 0.0  # m/s; 0: the lateral part at any speed
    w: np.ndarray = field(
        default_factory=lambda: np.zeros(0), init=False, repr=False, compare=False
    )
    variance: np.ndarray = field(
        default_factory=lambda: np.zeros(0), init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        for key in ("process_variance", "measurement_variance", "initial_variance"):
            positive(f"controller.disturbance.{key}", getattr(self, key))
        non_negative("controller.disturbance.lateral_min_speed_mps", self.lateral_min_speed_mps)

    def start(self, size: int) -> None:
        self.w = np.zeros(size)
        self.variance = np.full(size, float(self.initial_variance))

    def update(self, error: np.ndarray | None) -> np.ndarray:
        predicted = self.variance + self.process_variance  # w moved by a step of the walk
        if error is None:
            self.variance = predicted
            return self.w
        gain = predicted / (predicted + self.measurement_variance)
        self.w = self.w + gain * error
        self.variance = (1.0 - gain) * predicted
        return self.w

    def steady_gain(self) -> float:
        """The gain the filter settles to: K = P⁻ / (P⁻ + r) with P⁻ = P + q at its fixed
        point, P⁻ = (q + √(q² + 4 q r)) / 2."""
        q, r = self.process_variance, self.measurement_variance
        settled = (q + math.sqrt(q * q + 4.0 * q * r)) / 2.0
        return settled / (settled + r)


def without_lateral(C: np.ndarray) -> np.ndarray | None:
    """The map that drops w's vy and r parts, for a model that steps the state itself (its
    read-out C = I, z = x, in the states' order vx, vy, r); None for a lifted model, whose w
    holds the lateral error in every lifted coordinate and is left whole."""
    C = np.asarray(C, dtype=float)
    if C.shape != (3, 3) or not np.array_equal(C, np.eye(3)):
        return None
    return np.diag([1.0, 0.0, 0.0])


def learned(
    estimator: DisturbanceEstimator,
    error: np.ndarray | None,
    speed: float,
    drop_lateral: np.ndarray | None,
) -> np.ndarray:
    """The estimator's w after ``error``. Below its ``lateral_min_speed_mps`` (``speed``: the
    measured |vx|, m/s) ``drop_lateral`` (:func:`without_lateral`) removes w's lateral part, in
    the estimator too: a stopped car has no lateral motion to explain."""
    w = estimator.update(error)
    if drop_lateral is not None and speed < estimator.lateral_min_speed_mps:
        w = estimator.w = drop_lateral @ w
    return w
