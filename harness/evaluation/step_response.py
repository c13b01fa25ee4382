"""Local response checks: steering and throttle steps from straight driving, model against plant.

What a vehicle engineer looks at first. The whole-drive RMSE of :mod:`harness.evaluation.prediction`
mixes every regime of a drive; a step from straight driving isolates one thing: does the model's
input gain, and its change with speed, match the car's? (A lifted-linear model has one input matrix
for every speed, while the car's steering gain falls with speed.)

Every :class:`StepCase` drives the plant straight at ``speed_mps``: reset rolling
(``plant.reset(speed_mps=...)``), then :class:`~harness.plant.rollout.SpeedHold` for ``settle_s`` to
find the pedal that holds the speed. At t0 that pedal is frozen and the step is applied (the
steering wheel to ``step`` degrees, or the pedal raised by ``step``); from the state at t0 the
model predicts the response open loop under exactly the inputs the plant got. Compared at
0.3 s (the transient) and 1.5 s (close to steady state) after the step: the yaw rate for
steering steps, vx for the throttle step. ``relative_error`` is model / plant - 1 of the
*response*, the change of the output since t0 (for the yaw rate from straight driving that is
the yaw rate itself; vx's response is its increase): 0 is exact, -1 a model that does not
respond, below -1 one that responds the wrong way, whatever the step's direction. A diverged
prediction gives inf (null in ``metrics.json``).

The model's response mixes its input gain with its own drift under the held inputs (the plant,
settled, has none). ``model_input_effect`` is the model's prediction with the step minus its
prediction without it: the input's effect alone; ``input_sign_agrees`` says whether it has the
sign of the plant's response at every time compared. A model whose gain has the wrong sign is
one no controller can use (seed 1 of the main job's Deep EDMD, read out as DE-MPC reads it: more
throttle, 0.8 m/s less speed after 0.3 s).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from matplotlib.figure import Figure

from harness.core.checks import choice, positive
from harness.core.contracts import INPUT_NAMES, STATE_NAMES, Plant
from harness.output import save_arrays, save_figure
from harness.plant.rollout import SpeedHold
from harness.recorder import Recorder

__all__ = [
    "DEFAULT_CASES",
    "TIMES_S",
    "PlantResponse",
    "StepCase",
    "evaluate",
    "plot_step_responses",
    "respond",
]


class Predictor(Protocol):
    """What a step response needs of a model: an open-loop prediction in physical units (a
    learner; or ``controllers.as_controlled.AsControlled``, the model as DE-MPC reads it)."""

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray: ...


TIMES_S = (0.3, 1.5)
_BEFORE_S = 0.5  # of straight driving shown before the step in the figure and the recording


@dataclass(frozen=True)
class StepCase:
    """A step of one input from straight driving at ``speed_mps``, judged on ``output``.

    ``step`` is the steering-wheel angle in degrees (input ``steer_wheel_deg``) or the increase
    of the pedal over the pedal that holds the speed (input ``pedal``).
    """

    speed_mps: float
    input_name: str
    step: float
    output: str

    def __post_init__(self) -> None:
        choice("step input", self.input_name, INPUT_NAMES)
        choice("step output", self.output, STATE_NAMES)
        positive("step speed", self.speed_mps)

    @property
    def name(self) -> str:
        """``steer+20deg_22mps``, ``throttle+0.1_10mps``: the case's key in ``metrics.json``."""
        speed = f"{self.speed_mps:g}mps"
        if self.input_name == "steer_wheel_deg":
            return f"steer{self.step:+g}deg_{speed}"
        return f"throttle{self.step:+g}_{speed}"


# The cases: steering-wheel steps of +-20 and 60 deg, and a throttle step, at 10 and
# 22 m/s (22.2 m/s = 80 km/h is where the main job tracks the ISO 3888 lane change).
DEFAULT_CASES: tuple[StepCase, ...] = tuple(
    case
    for speed in (10.0, 22.0)
    for case in (
        StepCase(speed, "steer_wheel_deg", 20.0, "yaw_rate"),
        StepCase(speed, "steer_wheel_deg", -20.0, "yaw_rate"),
        StepCase(speed, "steer_wheel_deg", 60.0, "yaw_rate"),
        StepCase(speed, "pedal", 0.1, "vx"),
    )
)


@dataclass
class PlantResponse:
    """The plant's run of one case: ``time_s`` 0 at the step; row k of ``inputs`` is applied
    from ``time_s[k]``; ``first`` is the row of the step (t0)."""

    case: StepCase
    time_s: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    poses: np.ndarray
    first: int
    hold_pedal: float


def respond(
    plant: Plant, case: StepCase, *, settle_s: float = 10.0, duration_s: float = 1.5
) -> PlantResponse:
    """Drive ``plant`` through ``case``: straight at its speed, then the step for ``duration_s``."""
    dt = plant.dt
    x = plant.reset(speed_mps=case.speed_mps)
    hold = SpeedHold(case.speed_mps, dt)
    pedal = 0.0
    for _ in range(round(settle_s / dt)):
        pedal = hold(float(x[0]))
        x = plant.step(np.array([0.0, pedal]))
    before, after = round(_BEFORE_S / dt), round(duration_s / dt)
    steady = np.array([0.0, pedal])
    stepped = steady.copy()
    if case.input_name == "steer_wheel_deg":
        stepped[0] = case.step
    else:
        stepped[1] = pedal + case.step
    inputs = np.vstack([np.tile(steady, (before, 1)), np.tile(stepped, (after + 1, 1))])
    states, poses = [x], [plant.pose]
    for u in inputs[:-1]:
        states.append(plant.step(u))
        poses.append(plant.pose)
    time_s = (np.arange(before + after + 1) - before) * dt
    return PlantResponse(
        case, time_s, np.array(states), inputs, np.array(poses), before, float(pedal)
    )


def _compare(response: PlantResponse, predicted: np.ndarray, held: np.ndarray) -> dict[str, Any]:
    """The case's metrics: plant, model and relative error of the response at each time; the
    model's input effect (``predicted`` with the step minus ``held`` without it) and whether its
    sign is the plant's."""
    case, first = response.case, response.first
    column = STATE_NAMES.index(case.output)
    start = response.states[first, column]
    result: dict[str, Any] = {
        "output": case.output,
        "input": case.input_name,
        "step": case.step,
        "speed_mps": float(response.states[first, 0]),
        "hold_pedal": response.hold_pedal,
    }
    dt = float(response.time_s[1] - response.time_s[0])
    agrees = []
    for t in TIMES_S:
        row = round(t / dt)
        plant_value = float(response.states[first + row, column])
        model_value = float(predicted[row, column])
        plant_change, model_change = plant_value - start, model_value - start
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            error = model_change / plant_change - 1.0
        effect = model_value - float(held[row, column])
        result[f"at_{round(t * 1000)}ms"] = {
            "plant": plant_value,
            "model": model_value if np.isfinite(model_value) else np.inf,
            "relative_error": float(error) if np.isfinite(error) else np.inf,
            "model_input_effect": effect if np.isfinite(effect) else np.inf,
        }
        agrees.append(bool(np.isfinite(effect) and effect * plant_change > 0))
    # The input's effect alone has the sign of the plant's response at every time compared.
    result["input_sign_agrees"] = all(agrees)
    return result


def evaluate(
    learners: Mapping[str, Predictor],
    plant: Plant,
    cases: Sequence[StepCase] = DEFAULT_CASES,
    *,
    recorder: Recorder | None = None,
    output_dir: Path | None = None,
    prefix: str = "",
) -> dict[str, dict[str, dict[str, Any]]]:
    """Every case for every learner: ``{learner: {case name: metrics}}`` (see the module).

    The plant runs each case once; each learner predicts from the plant's state at the step.
    Writes ``step_response.png`` and ``step_response.npz`` into ``output_dir`` and one recording
    per case (``<prefix>step_response/<case>``, predictions as ``extra/predicted_<learner>``).
    """
    recorder = recorder or Recorder()
    results: dict[str, dict[str, dict[str, Any]]] = {name: {} for name in learners}
    responses = [respond(plant, case) for case in cases]
    predictions: dict[str, dict[str, np.ndarray]] = {}
    for response in responses:
        first, name = response.first, response.case.name
        predictions[name] = {}
        steady = np.repeat(response.inputs[first - 1 : first], len(response.inputs) - first - 1, 0)
        for learner_name, learner in learners.items():
            predicted = learner.predict(response.states[first], response.inputs[first:-1])
            held = learner.predict(response.states[first], steady)
            predictions[name][learner_name] = predicted
            results[learner_name][name] = _compare(response, predicted, held)
        recorder.rollout(
            f"{prefix}step_response/{name}",
            response.time_s,
            response.states,
            response.inputs,
            poses=response.poses,
            overlays={f"predicted_{k}": _padded(response, p) for k, p in predictions[name].items()},
        )
    if output_dir is not None:
        plot_step_responses(responses, predictions, Path(output_dir) / "step_response.png")
        save_arrays(
            Path(output_dir) / "step_response.npz",
            **{
                f"{r.case.name}__{key}": value
                for r in responses
                for key, value in (
                    ("time_s", r.time_s),
                    ("states", r.states),
                    ("inputs", r.inputs),
                    *((f"predicted_{k}", p) for k, p in predictions[r.case.name].items()),
                )
            },
        )
    return results


def _padded(response: PlantResponse, predicted: np.ndarray) -> np.ndarray:
    """The prediction on the plant run's rows: NaN before the step and where it diverged."""
    out = np.full(response.states.shape, np.nan)
    out[response.first :] = np.where(np.isfinite(predicted), predicted, np.nan)
    return out


def plot_step_responses(
    responses: Sequence[PlantResponse],
    predictions: Mapping[str, Mapping[str, np.ndarray]],
    path: Path,
) -> Path:
    """A panel per case: the plant's output (black) and every model's prediction from t0."""
    speeds = sorted({r.case.speed_mps for r in responses})
    per_speed = max(sum(r.case.speed_mps == s for r in responses) for s in speeds)
    fig = Figure(figsize=(3.4 * per_speed, 2.8 * len(speeds)))
    axes = fig.subplots(len(speeds), per_speed, squeeze=False)
    counts = dict.fromkeys(speeds, 0)
    for response in responses:
        case, first = response.case, response.first
        ax = axes[speeds.index(case.speed_mps), counts[case.speed_mps]]
        counts[case.speed_mps] += 1
        column = STATE_NAMES.index(case.output)
        plant_output = response.states[:, column]
        ax.plot(response.time_s, plant_output, "k-", lw=1.6, label="plant")
        for k, (name, predicted) in enumerate(predictions[case.name].items()):
            ax.plot(
                response.time_s[first:], predicted[:, column], color=f"C{k}", lw=1.0, label=name
            )
        for t in TIMES_S:
            ax.axvline(t, color="0.6", lw=0.6, ls=":")
        span = np.ptp(plant_output) + 1e-3
        ax.set_ylim(plant_output.min() - span, plant_output.max() + span)
        unit = "rad/s" if case.output == "yaw_rate" else "m/s"
        ax.set_title(case.name, fontsize=9)
        ax.set_ylabel(f"{case.output} [{unit}]", fontsize=8)
        ax.grid(True, alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time after the step [s]")
    for row, speed in enumerate(speeds):
        for ax in axes[row, counts[speed] :]:
            ax.set_visible(False)
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle("step responses from straight driving (axes clipped to 3x the plant's range)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, path)
