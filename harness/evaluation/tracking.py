"""Closed-loop reference tracking (paper section VI): a controller drives the plant at 10 ms.

:func:`track` runs one reference and returns its metrics (SI):

- ``rmse``: {vx, vy, yaw_rate}, root-mean-square of state - reference over the run;
- ``solve_time_ms``: {median, p99, max} of the time from the measurement to the input: the
  controller's ``act`` call up to ``StepInfo.input_ready_s`` where it says when its input was
  ready (lift, QP, input recovery), the whole call where not; with a real-time-iteration
  controller the feedback phase;
- ``prepare_time_ms``: {median, p99, max} of the rest of a step's work: its ``prepare`` call, run
  before each measurement (:class:`~harness.core.contracts.RealTimeIteration`), and what ``act``
  did after the input was ready (the record of its horizon);
- ``step_time_ms``: {median, p99, max} of both, step by step: what must fit in the control
  period;
- ``deadline_misses``: steps whose whole work (preparation, feedback, bookkeeping) took longer
  than the control period;
- ``solver_failures``: steps where the controller fell back (``StepInfo.fallback``);
- ``steps``: control steps run;
- ``solve_paths``: how many steps each solve path answered (DE-MPC: unconstrained,
  active_set, piqp, failed);
- ``horizon``: {Np, Nc}, the lengths of the controller's predicted states and planned inputs;
- ``compute_delay``: the clock in the loop (``controller.compute_delay``): ``none``, each input
  applied at the instant of its measurement, or ``one_step``, one control period later;
- ``quality``: how smoothly it drove: steering-wheel rate and reversals, throttle-brake changes
  and time on the brake, jerk and peak lateral acceleration (``harness/evaluation/quality.py``).

The controller is seen only through :class:`~harness.core.contracts.Controller`: every number above
comes from timing ``act`` and reading the :class:`~harness.core.contracts.StepInfo` it returns.

Everything is recorded: the rollout (states, inputs, pose) under ``name``, each state's plot
drawing the reference, the actual state and the model's prediction ``Np`` steps ahead at the
time it predicts (``{name}/state/<state>``, ``…/reference``, ``…/predicted_<Np>_ahead``), and
actual - reference on one error plot (``{name}/error/<state>``); the whole predicted horizon at
every step is logged columnar under ``{name}/horizon/<state>`` ((T, Np): column i is the
prediction i + 1 steps ahead), and drawn as a path ahead of the car in the 3D view
(``{name}/predicted_path``, :func:`predicted_path`). Tracking runs come first in the recording's
tabs: they are the result.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from harness.core.contracts import (
    COMPUTE_DELAYS,
    INPUT_NAMES,
    STATE_NAMES,
    Controller,
    Plant,
    RateLimited,
    RealTimeIteration,
    StepInfo,
)
from harness.core.reference_path import ReferencePath
from harness.evaluation.quality import control_quality, quality_series
from harness.output import load_arrays, save_arrays, save_figure
from harness.plant.rollout import Trajectory, closed_loop
from harness.recorder import Recorder

FINAL_ERROR_S = 0.5  # the end of a run over which ``final_error`` averages (s)


@dataclass
class TrackingTrajectory(Trajectory):
    """A rollout plus what tracking adds: the reference, predictions and solve times."""

    reference: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    predicted: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))  # (T, Np, 3)
    solve_time_s: np.ndarray = field(default_factory=lambda: np.zeros(0))


def track(
    plant: Plant,
    controller: Controller,
    reference: np.ndarray,
    *,
    name: str,
    recorder: Recorder,
    figure_path: Path | None = None,
    arrays_path: Path | None = None,
    tab_priority: int = 1,
    path: ReferencePath | None = None,
    compute_delay: str = "none",
) -> tuple[dict[str, Any], TrackingTrajectory]:
    """Track ``reference`` ((T, 3) states at plant.dt) from rest-or-rolling at its first speed.

    ``figure_path``: the tracking figure; ``arrays_path``: the run as ``.npz`` (see
    :func:`save_run`), which a sweep's report overlays across learners; ``tab_priority``: where
    its tab goes in the recording (see :meth:`Recorder.rollout`; tracking comes before data);
    ``path``: the line the reference drives along, given to the controller with the car's pose
    every step (a path-following controller steers by them); ``compute_delay``: how long the
    loop holds each input before the plant receives it (``COMPUTE_DELAYS``), the controller's
    own setting, which it compensates for if it knows how (DE-MPC does).
    """
    if compute_delay not in COMPUTE_DELAYS:
        raise ValueError(
            f"controller.compute_delay must be one of {', '.join(COMPUTE_DELAYS)} "
            f"(got {compute_delay!r})"
        )
    reference = np.asarray(reference, dtype=float)
    if reference.ndim != 2 or reference.shape[1] != 3 or len(reference) < 2:
        raise ValueError(f"reference must be (T >= 2, 3) states, got {reference.shape}")
    controller.reset(reference, path=path)
    timed = _Timed(controller, plant, follows=path is not None)
    loop = closed_loop(
        plant,
        timed,
        len(reference),
        speed_mps=float(reference[0, 0]),
        keep_infos=True,
        delay_steps=COMPUTE_DELAYS[compute_delay],
    )
    infos = loop.infos
    # The last sample has no step after it, hence no prediction (a NaN row) and no solve time.
    run = TrackingTrajectory(
        loop.time_s,
        loop.states,
        loop.inputs,
        loop.poses,
        reference,
        loop.predicted(),
        np.array(timed.feedback_s[: len(loop.time_s) - 1]),
    )
    metrics = tracking_metrics(run, plant.dt, sum(info.fallback for info in infos))
    # A period holds the step's feedback and the rest of its work: the preparation before the
    # measurement, the bookkeeping after the input.
    other = np.array(timed.other_s[: len(run.solve_time_s)])
    metrics["deadline_misses"] = int(np.sum(run.solve_time_s + other > plant.dt))
    metrics["step_time_ms"] = _statistics((run.solve_time_s + other) * 1e3)
    metrics["prepare_time_ms"] = _statistics(other * 1e3)
    metrics["solve_paths"] = dict(Counter(info.solve_path for info in infos))
    metrics["follows_path"] = bool(infos[0].follows_path)
    metrics["horizon"] = {"Np": len(infos[0].predicted_states), "Nc": len(infos[0].planned_inputs)}
    metrics["compute_delay"] = compute_delay
    shares = (
        controller.increment_shares(run.inputs) if isinstance(controller, RateLimited) else None
    )
    metrics["quality"] = control_quality(run.states, run.inputs, plant.dt, shares)
    record_run(recorder, name, run, plant.dt, tab_priority)
    if figure_path is not None:
        plot_tracking({name: run}, figure_path)
    if arrays_path is not None:
        save_run(run, arrays_path)
    return metrics, run


def save_run(run: TrackingTrajectory, path: Path) -> Path:
    """The run's arrays (no predicted horizons: they are large and in the recording)."""
    return save_arrays(
        path,
        time_s=run.time_s,
        states=run.states,
        inputs=run.inputs,
        poses=run.poses,
        reference=run.reference,
        solve_time_s=run.solve_time_s,
    )


def load_run(path: Path) -> TrackingTrajectory:
    """A run written by :func:`save_run`."""
    arrays = load_arrays(path)
    try:
        return TrackingTrajectory(
            arrays["time_s"],
            arrays["states"],
            arrays["inputs"],
            arrays["poses"],
            arrays["reference"],
            solve_time_s=arrays["solve_time_s"],
        )
    except KeyError as error:
        raise ValueError(f"{path} lacks {error}; it was not written by save_run") from error


class _Timed:
    """A controller's ``act`` as the loop calls it, timed: the feedback (measurement to input
    ready) and the period's other work (the preparation before the measurement, the record of
    the horizon after the input)."""

    def __init__(self, controller: Controller, plant: Plant, *, follows: bool) -> None:
        self.controller, self.plant, self.follows = controller, plant, follows
        self.preparing = controller if isinstance(controller, RealTimeIteration) else None
        self.feedback_s: list[float] = []
        self.other_s: list[float] = []

    def __call__(self, x: np.ndarray, t: float) -> tuple[np.ndarray, StepInfo]:
        other = 0.0
        if self.preparing is not None:  # the preparation belongs to the period before
            start = time.perf_counter()
            self.preparing.prepare()
            other = time.perf_counter() - start
        start = time.perf_counter()
        answer = self.controller.act(x, t, pose=self.plant.pose if self.follows else None)
        end = time.perf_counter()
        # The latency ends when the input is ready; what act did after it (the record of its
        # horizon) is the period's other work, like the preparation.
        ready = answer[1].input_ready_s
        ready = end if ready is None or not start <= ready <= end else ready
        self.feedback_s.append(ready - start)
        self.other_s.append(other + end - ready)
        return answer


def tracking_metrics(run: TrackingTrajectory, dt: float, solver_failures: int) -> dict[str, Any]:
    """RMSE per state (SI), the error the run ends with (mean |x − reference| over its last
    ``FINAL_ERROR_S``: the offset a model error leaves), solve-time statistics (ms), deadline
    misses and failures."""
    error = run.states - run.reference
    rmse = np.sqrt(np.mean(error**2, axis=0))
    final = np.mean(np.abs(error[-max(1, round(FINAL_ERROR_S / dt)) :]), axis=0)
    solve_ms = run.solve_time_s * 1e3
    return {
        "rmse": dict(zip(STATE_NAMES, rmse.tolist(), strict=True)),
        "final_error": dict(zip(STATE_NAMES, final.tolist(), strict=True)),
        "solve_time_ms": _statistics(solve_ms),
        "deadline_misses": int(np.sum(run.solve_time_s > dt)),
        "solver_failures": int(solver_failures),
        "steps": len(run.solve_time_s),
    }


def _statistics(times_ms: np.ndarray) -> dict[str, float]:
    """{median, p99, max} of step times (ms)."""
    return {
        "median": float(np.median(times_ms)),
        "p99": float(np.percentile(times_ms, 99)),
        "max": float(np.max(times_ms)),
    }


def record_run(
    recorder: Recorder, name: str, run: TrackingTrajectory, dt: float, priority: int
) -> None:
    """A tracking run in the recording under ``name`` (what :func:`track` records of it)."""
    poses = run.poses if np.all(np.isfinite(run.poses)) else None
    solve_ms = np.append(run.solve_time_s, np.nan) * 1e3
    horizon = run.predicted.shape[1]
    overlays: dict[str, np.ndarray] = {}
    if horizon:
        # The prediction Np steps ahead, drawn at the time it is a prediction of.
        ahead = np.full_like(run.states, np.nan)
        ahead[horizon:] = run.predicted[: max(len(ahead) - horizon, 0), -1]
        overlays[f"model's prediction from {horizon * dt:.2f} s before"] = ahead
    recorder.rollout(
        name,
        run.time_s,
        run.states,
        run.inputs,
        poses,
        extra={"solve_time_ms": solve_ms, **quality_series(run.states, run.inputs, dt)},
        priority=priority,
        reference=run.reference,
        overlays=overlays,
    )
    if poses is not None and horizon:
        recorder.path_ahead(name, run.time_s, predicted_path(run, dt))
    for i, state in enumerate(STATE_NAMES if horizon else ()):
        recorder.series(f"{name}/horizon/{state}", run.time_s, {"ahead": run.predicted[..., i]})


def predicted_path(run: TrackingTrajectory, dt: float) -> np.ndarray:
    """(T, Np + 1, 2) world X, Y of the path the controller predicted at each step: its
    predicted (vx, vy, yaw rate) integrated from the car's pose then (NaN after the last step).

    Step i moves with the state at its start (the measured one first, then the predictions),
    as the plant's pose does to first order.
    """
    start = run.states[:, None, :]
    moving = np.concatenate([start, run.predicted[:, :-1]], axis=1)  # (T, Np, 3)
    vx, vy, rate = moving[..., 0], moving[..., 1], moving[..., 2]
    heading = run.poses[:, 2:3] + dt * np.concatenate(
        [np.zeros_like(rate[:, :1]), np.cumsum(rate[:, :-1], axis=1)], axis=1
    )
    step_x = dt * (vx * np.cos(heading) - vy * np.sin(heading))
    step_y = dt * (vx * np.sin(heading) + vy * np.cos(heading))
    x = run.poses[:, 0:1] + np.concatenate([np.zeros_like(vx[:, :1]), np.cumsum(step_x, 1)], 1)
    y = run.poses[:, 1:2] + np.concatenate([np.zeros_like(vy[:, :1]), np.cumsum(step_y, 1)], 1)
    return np.stack([x, y], axis=-1)


_UNITS = {"vx": "m/s", "vy": "m/s", "yaw_rate": "rad/s", "steer_wheel_deg": "deg"}


def plot_tracking(runs: Mapping[str, TrackingTrajectory], path: Path) -> None:
    """The paper's tracking figure: reference vs actual for vx, vy, r; then the inputs."""
    fig = Figure(figsize=(8, 11))
    axes = fig.subplots(5, 1, sharex=True)
    first = next(iter(runs.values()))
    for i, state in enumerate(STATE_NAMES):
        axes[i].plot(first.time_s, first.reference[:, i], "k--", lw=1.2, label="reference")
        for label, run in runs.items():
            axes[i].plot(run.time_s, run.states[:, i], lw=1.0, label=label)
        axes[i].set_ylabel(f"{state} [{_UNITS[state]}]")
    for j, name in enumerate(INPUT_NAMES):
        ax = axes[3 + j]
        for label, run in runs.items():
            ax.plot(run.time_s, run.inputs[:, j], lw=1.0, label=label)
        ax.set_ylabel("pedal [throttle / -MPa]" if name == "pedal" else f"{name} [deg]")
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path)
