"""What a run ends by printing: the model's test drives, then one line per controller.

``summary(metrics)`` reads only the run's ``metrics.json`` sections (the public contract), so the
lines say what the file says:

- the open-loop prediction of each test drive (RMSE vx m/s / vy m/s / yaw rate rad/s), with
  persistence (the state held) beside it, the bar every model must clear, and the states and
  windows where the model does not clear it (``beats_persistence``); a diverged prediction with
  the time it left the data's envelope and its RMSE until then;
- per controller, the run's first: every course (the lane change): passed or failed, the largest
  lateral deviation from the centre line and the cones hit; every test-drive reference: the
  tracking RMSE; how smoothly each run drove where its metrics say (``quality``: steering
  reversals and throttle-brake changes a minute, longitudinal jerk RMS); the step's time on its
  first reference (median / p99, ms), deadline misses and failed solves. A value the run could
  not compute (null in metrics.json) is printed n/a.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

STATES = ("vx", "vy", "yaw_rate")


def title(learner: object, seed: object, plant: object) -> str:
    """The summary's first line: which model, seed and plant the run was."""
    return f"{learner}, seed {seed}, on {plant}:"


def summary(metrics: Mapping[str, Any], title: str = "") -> str:
    """The lines to print at the end of a pipeline run (empty without prediction or tracking)."""
    lines = [title] if title else []
    lines += _prediction_lines(metrics.get("prediction") or {})
    tracking = metrics.get("tracking") or {}
    controllers = tracking.get("controllers") or {}
    if tracking.get("skipped") and not controllers:
        lines.append(f"  tracking skipped: {tracking['skipped']}")
    for index, (name, runs) in enumerate(controllers.items()):
        first = next(iter(runs.values()), None) if "skipped" not in runs else None
        horizon = first.get("horizon") if isinstance(first, Mapping) else None
        label = name if horizon is None else f"{name} {horizon['Np']}/{horizon['Nc']}"
        label += ", the run's controller" if index == 0 else ""
        lines.append(f"  {label}: {_controller_line(runs)}")
    return "\n".join(lines)


def _rmse(values: Mapping[str, Any]) -> str:
    """vx / vy / r; a value the run could not compute (null: an overflow, no window) as n/a."""
    return " / ".join(_number(values.get(state)) for state in STATES)


def _number(value: Any, form: str = ".3g") -> str:
    return "n/a" if value is None else f"{float(value):{form}}"


def _prediction_lines(prediction: Mapping[str, Any]) -> list[str]:
    persistence = prediction.get("persistence") or {}
    lines = []
    for episode, result in prediction.items():
        if not isinstance(result, Mapping) or "rmse" not in result:
            continue
        line = f"  test drive {episode}, open loop RMSE vx / vy / r: {_rmse(result['rmse'])}"
        if result.get("diverged"):
            at = result.get("diverged_at_s")
            line += " (diverged" if at is None else f" (diverged at t = {float(at):.1f} s"
            until = result.get("rmse_until_diverged")
            line += f"; until then {_rmse(until)})" if isinstance(until, Mapping) else ")"
        held = persistence.get(episode)
        if isinstance(held, Mapping) and "rmse" in held:
            line += f"; persistence {_rmse(held['rmse'])}"
        lines.append(line)
        worse = _worse_than_persistence(result.get("beats_persistence") or {})
        if worse:
            lines.append(f"    not better than persistence on {worse}")
    return lines


def _worse_than_persistence(verdicts: Mapping[str, Mapping[str, Any]]) -> str:
    """``vx (41 steps, 1.5 s windows), vy (open loop)``: the states and windows where the
    model's RMSE is not below the state held; empty where it beats it everywhere."""
    parts = []
    for state in STATES:
        windows = [_window(w) for w, by_state in verdicts.items() if by_state.get(state) is False]
        if windows:
            parts.append(f"{state} ({', '.join(windows)})")
    return ", ".join(parts)


def _window(name: str) -> str:
    if name == "open_loop":
        return "open loop"
    if name.endswith("_steps"):
        return f"{name.removesuffix('_steps')}-step windows"
    return f"{name.removesuffix('s')} s windows"


def _controller_line(runs: Mapping[str, Any]) -> str:
    if "skipped" in runs:
        return f"skipped ({runs['skipped']})"
    parts = []
    step = None
    for label, run in runs.items():
        path = run.get("path")
        if path is not None:
            verdict = "passed" if path["passed"] else "FAILED"
            if not path.get("reached_exit", True):
                verdict += " (never reached the exit)"
            speed_kph = 3.6 * float(path.get("reference_speed_mps", float("nan")))
            parts.append(
                f"{label} at {speed_kph:.0f} km/h {verdict}, "
                f"{path['max_lateral_deviation_m']:.2f} m, {path['cones_hit']} cones"
            )
        else:
            parts.append(f"{label} tracked, RMSE {_rmse(run['rmse'])}")
        quality = run.get("quality")
        if quality:
            parts[-1] += (
                f" (steering {quality['steering_reversals_per_min']:.0f} reversals/min, pedal "
                f"{quality['pedal_changes_per_min']:.0f} throttle-brake changes/min, jerk "
                f"{quality['long_jerk_rms_mps3']:.2g} m/s³)"
            )
        step = step or run.get("step_time_ms")
        misses = run.get("deadline_misses", 0)
        if misses:
            parts[-1] += f", {misses} deadline misses"
        failures = run.get("solver_failures", 0)
        if failures:  # each fell back to its last plan's next move: the loop ran open meanwhile
            parts[-1] += f", {failures} of {run.get('steps', '?')} solves failed"
    if step:
        parts.append(f"step {step['median']:.2f} / {step['p99']:.2f} ms (median / p99)")
    return "; ".join(parts)
