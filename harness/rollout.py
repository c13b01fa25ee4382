"""Closed-loop rollouts of a plant under a policy, kept as arrays for metrics and recording."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from harness.plant import Sedan

Policy = Callable[[float, np.ndarray], np.ndarray | tuple[float, float]]
StopCondition = Callable[[float, np.ndarray], bool]


@dataclass
class Trajectory:
    """Samples at the control period: row k is the state at ``time_s[k]`` and the input
    applied from there; the last row repeats the previous input."""

    time_s: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    poses: np.ndarray

    @property
    def lateral_accel_mps2(self) -> np.ndarray:
        """a_y = dvy/dt + vx * r, the acceleration an accelerometer at the CG would read."""
        vx, vy, yaw_rate = self.states.T
        return np.gradient(vy, self.time_s) + vx * yaw_rate

    @property
    def distance_m(self) -> np.ndarray:
        steps = np.linalg.norm(np.diff(self.poses[:, :2], axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(steps)])


def simulate(
    plant: Sedan,
    policy: Policy,
    duration_s: float,
    *,
    speed_mps: float = 0.0,
    stop: StopCondition | None = None,
) -> Trajectory:
    """Reset ``plant`` (at rest, or rolling at ``speed_mps``) and drive it with ``policy``."""
    steps = round(duration_s / plant.dt)
    states = np.empty((steps + 1, 3))
    inputs = np.zeros((steps + 1, 2))
    poses = np.empty((steps + 1, 3))
    x = plant.reset(speed_mps=speed_mps)
    states[0], poses[0] = x, plant.pose
    n = steps
    for k in range(steps):
        t = k * plant.dt
        u = np.asarray(policy(t, x), dtype=float)
        inputs[k] = u
        x = plant.step(u)
        states[k + 1], poses[k + 1] = x, plant.pose
        if not np.all(np.isfinite(x)):
            raise RuntimeError(f"plant state became non-finite at t = {t:.2f} s")
        if stop is not None and stop(t + plant.dt, x):
            n = k + 1
            break
    inputs[n] = inputs[n - 1]
    time_s = np.arange(n + 1) * plant.dt
    return Trajectory(time_s, states[: n + 1], inputs[: n + 1], poses[: n + 1])


class SpeedHold:
    """A PI driver on the pedal that holds vx at a set speed; used by the standard tests."""

    brake_limit_mpa = 2.0  # gentle: the speed hold never brakes hard

    def __init__(self, speed_mps: float, dt: float, kp: float = 0.08, ki: float = 0.04) -> None:
        self.speed_mps, self.dt, self.kp, self.ki = speed_mps, dt, kp, ki
        self.integral = 0.0

    def __call__(self, vx: float) -> float:
        error = self.speed_mps - vx
        pedal = self.kp * error + self.ki * self.integral
        if -self.brake_limit_mpa < pedal < Sedan.input_high[1]:  # integrate only unsaturated
            self.integral += error * self.dt
        return float(np.clip(pedal, -self.brake_limit_mpa, Sedan.input_high[1]))
