"""Closed-loop rollouts of a plant under a policy, kept as arrays for metrics and recording.

:func:`closed_loop` is the one loop that steps a plant under feedback: data collection
(:func:`harness.data.store.drive_episode`), closed-loop tracking
(:func:`harness.evaluation.tracking.track`) and the characterization tests (:func:`simulate`)
are each a call of it with their options:

- ``stop`` ends the run early (a spin, a test's end condition), keeping or dropping the frame
  where it fired (``keep_stop_frame``);
- ``act_on_last``: the last frame gets its own input from the policy (recorded data) instead
  of repeating the previous one (tracking, tests: the run ends there);
- ``timed``: the wall time of every policy call (a controller's solve time);
- ``keep_infos``: the :class:`~harness.core.contracts.StepInfo` of every call (solve paths,
  fallbacks, predicted horizons: :meth:`Rollout.predicted`);
- ``delay_steps``: the clock in the loop (``controller.compute_delay``): each input reaches the
  plant that many control periods after the measurement it was computed from.

Recording stays with the callers: each records other things, and a stored dataset is recorded
from its files (a reused dataset is never driven).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from harness.core.contracts import Plant, StepInfo
from harness.plant import Sedan

Policy = Callable[[float, np.ndarray], np.ndarray | tuple[float, float]]
# What the loop calls each frame, ``Controller.act``'s signature: the input for state x at time t
# (s), and what the policy did.
Act = Callable[[np.ndarray, float], tuple[np.ndarray | tuple[float, float], StepInfo]]
StopCondition = Callable[[float, np.ndarray], bool]
NO_INFO = StepInfo()  # what a policy without a model reports (shared: it is frozen)


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


@dataclass
class Rollout(Trajectory):
    """What :func:`closed_loop` returns: the trajectory and the extras its options asked for.

    The last row's input is the policy's own where it was asked (``act_on_last``), else it
    repeats the previous one."""

    stopped: bool = False  # ``stop`` fired
    acted: int = 0  # policy calls among the kept frames (the first ``acted`` rows)
    solve_time_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,), NaN untimed
    infos: list[StepInfo] = field(default_factory=list)  # one per call, with ``keep_infos``

    def predicted(self) -> np.ndarray:
        """(T, Np, n): the horizon each call predicted, NaN rows where no call was made."""
        if not self.infos:
            raise ValueError("the rollout kept no StepInfo (closed_loop(..., keep_infos=True))")
        horizons = np.stack([info.predicted_states for info in self.infos])
        missing = np.full((len(self.time_s) - len(horizons), *horizons.shape[1:]), np.nan)
        return np.concatenate([horizons, missing])


def closed_loop(
    plant: Plant,
    act: Act,
    frames: int,
    *,
    seed: int | None = None,
    speed_mps: float = 0.0,
    stop: StopCondition | None = None,
    keep_stop_frame: bool = True,
    act_on_last: bool = False,
    timed: bool = False,
    keep_infos: bool = False,
    delay_steps: int = 0,
) -> Rollout:
    """Reset ``plant`` (``seed``; at rest, or rolling at ``speed_mps``) and run ``frames`` frames.

    Each frame k records x_k and the pose, asks ``act(x_k, t_k)`` for u_k (a
    :class:`~harness.core.contracts.Controller`'s ``act`` as it is) and steps the plant. ``stop(t,
    x)`` is checked from frame 2 on (every rollout keeps a start and one step): where it fires the
    run ends, with that frame (``keep_stop_frame``) or without it (a spin the data should not hold).
    A non-finite state stops the run with an error.

    With ``delay_steps`` d, u_k is applied over [t_{k+d}, t_{k+d+1}): the policy's answer
    arrives when its computation has used up d periods. Until the first one arrives the plant
    gets u = 0 (wheel straight, no pedal: where every controller starts, ``DEMPC.reset``).
    ``inputs[k]`` is what the plant received from t_k on, as without delay.
    """
    if frames < 2:
        raise ValueError(f"a rollout needs at least 2 frames (got {frames})")
    if delay_steps < 0:
        raise ValueError(f"a rollout's delay_steps must be >= 0 (got {delay_steps})")
    pending = [np.zeros(2)] * delay_steps  # computed, not yet at the plant: oldest first
    states, inputs, poses = np.empty((frames, 3)), np.zeros((frames, 2)), np.empty((frames, 3))
    solve_time = np.full(frames, np.nan)
    infos: list[StepInfo] = []
    x = plant.reset(seed=seed, speed_mps=speed_mps)
    n, acted, stopped = frames, 0, False
    for k in range(frames):
        t = k * plant.dt
        states[k], poses[k] = x, plant.pose
        if stop is not None and k >= 2 and stop(t, x):
            n, stopped = (k + 1 if keep_stop_frame else k), True
            break
        if k == frames - 1 and not act_on_last:
            break
        start = time.perf_counter() if timed else 0.0
        u, info = act(x, t)
        if timed:
            solve_time[k] = time.perf_counter() - start
        pending.append(np.asarray(u, dtype=float))
        inputs[k] = pending.pop(0)
        acted = k + 1
        if keep_infos:
            infos.append(info)
        if k == frames - 1:
            break
        x = plant.step(inputs[k])
        if not np.all(np.isfinite(x)):
            raise RuntimeError(f"plant state became non-finite at t = {t:.2f} s")
    acted = min(acted, n)
    if acted < n:  # the last kept frame was not acted on: it holds the previous input
        inputs[n - 1] = inputs[n - 2]
    return Rollout(
        np.arange(n) * plant.dt,
        states[:n],
        inputs[:n],
        poses[:n],
        stopped=stopped,
        acted=acted,
        solve_time_s=solve_time[:n],
        infos=infos[:acted],
    )


def simulate(
    plant: Plant,
    policy: Policy,
    duration_s: float,
    *,
    speed_mps: float = 0.0,
    stop: StopCondition | None = None,
) -> Rollout:
    """Reset ``plant`` (at rest, or rolling at ``speed_mps``) and drive it with ``policy``
    for ``duration_s`` (one frame more than steps: the state after the last step is kept)."""
    return closed_loop(
        plant,
        lambda x, t: (policy(t, x), NO_INFO),
        round(duration_s / plant.dt) + 1,
        speed_mps=speed_mps,
        stop=stop,
    )


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
