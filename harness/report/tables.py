"""The paper's tables from a sweep's runs: one row per learner (and plant, controller, variant),
numbers as mean ± std over the runs that differ only by seed.

Each table is also written as a CSV by :func:`harness.report.report`.
"""

from __future__ import annotations

import math
import re
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from harness.evaluation.prediction import window_name
from harness.report.jobs import Run, common_overrides, variant

STATES = ("vx", "vy", "yaw_rate")
# Entries of a job's ``prediction`` section that are not test episodes.
_NOT_EPISODES = frozenset({"step_response", "persistence"})


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[str]] = field(default_factory=list)

    def markdown(self) -> str:
        lines = [f"### {self.title}", "", "| " + " | ".join(self.columns) + " |"]
        lines.append("|" + "---|" * len(self.columns))
        lines += ["| " + " | ".join(row) + " |" for row in self.rows]
        return "\n".join(lines) + "\n"


def _mean_std(values: Iterable[float | None]) -> str:
    numbers = [v for v in values if v is not None and math.isfinite(v)]
    if not numbers:
        return "—"
    mean = sum(numbers) / len(numbers)
    if len(numbers) == 1:
        return f"{mean:.4g}"
    std = math.sqrt(sum((v - mean) ** 2 for v in numbers) / (len(numbers) - 1))
    return f"{mean:.4g} ± {std:.2g}"


def _mean(values: Iterable[float | None]) -> str:
    """The mean to 3 significant digits; "—" when no job has the value (older runs)."""
    present = [float(v) for v in values if v is not None and math.isfinite(v)]
    return f"{sum(present) / len(present):.3g}" if present else "—"


def _get(tree: Mapping[str, Any] | None, *keys: str) -> Any:
    for key in keys:
        if not isinstance(tree, Mapping) or key not in tree:
            return None
        tree = tree[key]
    return tree


def _group(runs: Iterable[Run], *keys: Callable[[Run], str]) -> dict[tuple[str, ...], list[Run]]:
    """Runs that differ only by seed share a group (mean ± std); the last key is the variant."""
    runs = list(runs)
    common = common_overrides(runs)
    groups: dict[tuple[str, ...], list[Run]] = defaultdict(list)
    for run in runs:
        groups[(*(key(run) for key in keys), variant(run, common))].append(run)
    return dict(sorted(groups.items()))


def _learner(run: Run) -> str:
    return run.learner


def _plant(run: Run) -> str:
    return run.plant


def prediction_table(jobs: list[Run], metric: str = "rmse") -> Table:
    table = Table(
        f"Prediction RMSE ({metric}; vx, vy in m/s, yaw rate in rad/s; mean ± std over jobs)",
        ["learner", "plant", "variant", "test episode", "jobs", *STATES],
    )
    for (learner, plant, varied), members in _group(jobs, _learner, _plant).items():
        episodes = sorted(
            {e for j in members for e in (_get(j.metrics, "prediction") or {})} - _NOT_EPISODES
        )
        for episode in episodes:
            runs = [_get(j.metrics, "prediction", episode) or {} for j in members]
            # A whole-drive rollout that ran away is named, not averaged (nor dropped silently).
            gone = sum(1 for r in runs if metric == "rmse" and r.get("diverged"))
            present = [
                r[metric]
                for r in runs
                if r.get(metric) and not (metric == "rmse" and r.get("diverged"))
            ]
            note = f" ({gone} of {len(runs)} diverged)" if gone else ""
            cells = [
                _mean_std(v.get(s) for v in present) + note + _worse(runs, metric, s)
                for s in STATES
            ]
            if gone and not present:
                cells = [f"diverged ({gone} of {len(runs)})"] * len(STATES)
            table.rows.append([learner, plant, varied or "—", episode, str(len(present)), *cells])
    # Persistence (the state held) on the same drives: the bar beside every learner's rows. It
    # has no fit, so every job of a plant and data reports the same numbers: one row each.
    held: dict[tuple[str, str], Mapping[str, Any]] = {}
    as_learner = {
        (j.plant, e)
        for j in jobs
        if j.learner == "persistence"
        for e in (_get(j.metrics, "prediction") or {})
    }  # learner=persistence has its own rows
    for job in jobs:
        for episode, metrics in (_get(job.metrics, "prediction", "persistence") or {}).items():
            if _get(metrics, metric) is not None:
                held.setdefault((job.plant, episode), metrics[metric])
    for (plant, episode), values in sorted(held.items()):
        if (plant, episode) in as_learner:
            continue
        table.rows.append(
            ["persistence", plant, "—", episode, "—"] + [_mean_std([values.get(s)]) for s in STATES]
        )
    return table


def _worse(runs: list[Mapping[str, Any]], metric: str, state: str) -> str:
    """`` (worse than persistence)``, or ``… in k of n`` jobs, where a job's verdict
    (``beats_persistence``) says its RMSE is not below the state held on that drive; empty
    where none says so (or no job has the verdict: runs before it existed)."""
    window = window_name(metric)
    worse = sum(1 for r in runs if _get(r, "beats_persistence", window, state) is False)
    if not worse:
        return ""
    return (
        " (worse than persistence"
        + ("" if worse == len(runs) else f" in {worse} of {len(runs)}")
        + ")"
    )


def _tracking_runs(
    tracking: Mapping[str, Any], controller: str
) -> Iterable[tuple[str, str, dict[str, Any]]]:
    """(controller, reference, metrics) of every closed-loop run of a ``tracking`` section,
    first controller first; older sections without ``controllers`` are ``controller``'s."""
    by_controller = tracking.get("controllers")
    if not by_controller:
        references = tracking.get("references") or (
            {tracking.get("reference", "test_episode"): tracking} if "rmse" in tracking else {}
        )
        by_controller = {controller: references}
    for controller, runs in by_controller.items():
        for label, metrics in runs.items():
            if isinstance(metrics, Mapping) and "rmse" in metrics:
                yield controller, label.split("/", 1)[0], metrics


CLOSED_LOOP_COLUMNS = ("learner", "controller", "Np/Nc", "reference", "variant", "jobs")


def _tracking_row(
    job: Run, controller: str, reference: str, metrics: Mapping[str, Any], common: Mapping
) -> tuple[str, ...]:
    """A closed loop's row of the tracking and quality tables: learner, controller, Np/Nc,
    reference, variant."""
    horizon = metrics.get("horizon") or {}
    return (
        job.learner,
        controller,
        f"{horizon.get('Np', '?')}/{horizon.get('Nc', '?')}",
        reference,
        variant(job, common) or "—",
    )


def tracking_table(jobs: list[Run]) -> Table:
    table = Table(
        "DE-MPC tracking RMSE on the plant (SI) and solve time of one control step (ms)",
        [
            *CLOSED_LOOP_COLUMNS,
            *STATES,
            "final error vx / vy / r",
            "solve median",
            "solve p99",
            "solve max",
            "deadline misses",
            "solver failures",
        ],
    )
    common = common_overrides(jobs)
    runs: dict[tuple[str, ...], list[dict[str, Any]]] = defaultdict(list)
    firsts: set[str] = set()  # the references a job tracked first: the paper's, listed first
    for job in jobs:
        tracking = _get(job.metrics, "tracking") or {}
        first = _first_reference(tracking)
        for controller, reference, metrics in _tracking_runs(tracking, job.controller):
            runs[_tracking_row(job, controller, reference, metrics, common)].append(metrics)
        if first is not None:
            firsts.add(first)
    for key, members in sorted(
        runs.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][3] not in firsts, kv[0][3:])
    ):
        table.rows.append(
            [*key, str(len(members))]
            + [_mean_std(_get(m, "rmse", s) for m in members) for s in STATES]
            + [" / ".join(_mean(_get(m, "final_error", s) for m in members) for s in STATES)]
            + [
                _mean_std(_get(m, "solve_time_ms", q) for m in members)
                for q in ("median", "p99", "max")
            ]
            + [_mean_std(m.get(k) for m in members) for k in ("deadline_misses", "solver_failures")]
        )
    return table


QUALITY = (  # tracking…quality's keys, in the table's order (harness/evaluation/quality.py)
    "steering_reversals_per_min",
    "steer_rate_rms_deg_s",
    "pedal_changes_per_min",
    "brake_time_share",
    "long_jerk_rms_mps3",
    "lat_jerk_rms_mps3",
    "lat_accel_peak_mps2",
    "steer_increment_limit_share",
    "pedal_increment_limit_share",
)


def quality_table(jobs: list[Run]) -> Table:
    """How smoothly every closed loop drove (``tracking…quality``), beside the tracking table's
    rows; runs measured before the key existed have no row."""
    table = Table(
        "How smoothly DE-MPC drove: steering reversals and wheel rate (deg/s), throttle-brake "
        "changes a minute and time on the brake, jerk (m/s³), peak lateral acceleration (m/s²), "
        "steps at the increment bound (share)",
        [
            *CLOSED_LOOP_COLUMNS,
            "reversals /min",
            "wheel rate RMS",
            "throttle-brake /min",
            "on the brake",
            "long. jerk RMS",
            "lat. jerk RMS",
            "peak |a_y|",
            "wheel at bound",
            "pedal at bound",
        ],
    )
    common = common_overrides(jobs)
    runs: dict[tuple[str, ...], list[dict[str, Any]]] = defaultdict(list)
    for job in jobs:
        tracking = _get(job.metrics, "tracking") or {}
        for controller, reference, metrics in _tracking_runs(tracking, job.controller):
            quality = metrics.get("quality")
            if isinstance(quality, Mapping):
                runs[_tracking_row(job, controller, reference, metrics, common)].append(quality)
    for key, members in sorted(runs.items()):
        table.rows.append(
            [*key, str(len(members))] + [_mean_std(m.get(k) for m in members) for k in QUALITY]
        )
    return table


def training_table(jobs: list[Run]) -> Table:
    table = Table("Training", ["learner", "variant", "jobs", "fit time (s)", "train frames"])
    for (learner, varied), members in _group(jobs, _learner).items():
        trained = [j for j in members if _get(j.metrics, "training")]
        if trained:
            table.rows.append(
                [
                    learner,
                    varied or "—",
                    str(len(trained)),
                    _mean_std(_get(j.metrics, "training", "fit_time_s") for j in trained),
                    _mean_std(_get(j.metrics, "training", "train_frames") for j in trained),
                ]
            )
    return table


def robustness_table(jobs: list[Run]) -> Table:
    table = Table(
        "Random-layer robustness: RMSE over 100 predictions with the layer redrawn, mean "
        "(spread) per job, then mean ± std over jobs",
        ["learner", "variant", "test episode", "jobs", *STATES],
    )
    for (learner, varied), members in _group(jobs, _learner).items():
        episodes = sorted({e for j in members for e in (_get(j.metrics, "robustness") or {})})
        for episode in episodes:
            values = [_get(j.metrics, "robustness", episode) for j in members]
            present = [v for v in values if isinstance(v, Mapping)]
            table.rows.append(
                [learner, varied or "—", episode, str(len(present))]
                + [
                    f"{_mean_std(_get(v, 'rmse_mean', s) for v in present)} "
                    f"({_mean_std(_get(v, 'rmse_std', s) for v in present)})"
                    for s in STATES
                ]
            )
    return table


def _mean_prediction(section: Mapping[str, Any], state: str) -> float | None:
    """Open-loop RMSE of one state averaged over a section's test episodes (the caller leaves
    out a section whose rollout diverged, :func:`_diverged`: counted, not averaged)."""
    episodes = section.get("prediction") or {}
    per_episode = [_get(v, "rmse", state) for e, v in episodes.items() if e not in _NOT_EPISODES]
    numbers = [v for v in per_episode if v is not None]
    return sum(numbers) / len(numbers) if numbers else None


def _diverged(section: Mapping[str, Any]) -> bool:
    """Whether a whole-drive rollout of the section's test episodes ran away."""
    episodes = section.get("prediction") or {}
    return any(
        isinstance(v, Mapping) and v.get("diverged") is True
        for e, v in episodes.items()
        if e not in _NOT_EPISODES
    )


def _first_reference(tracking: Mapping[str, Any]) -> str | None:
    """The reference a job tracked first (its top-level ``tracking`` keys), without episode."""
    label = tracking.get("reference")
    return label.split("/", 1)[0] if isinstance(label, str) else None


def _first_controller_run(section: Mapping[str, Any], reference: str) -> dict[str, Any] | None:
    """The first controller's run of ``reference`` (a test drive matches by its config name)."""
    runs = _tracking_runs(section.get("tracking") or {}, "")
    return next((metrics for _, name, metrics in runs if name == reference), None)


def generalization_table(jobs: list[Run]) -> Table:
    """Each model on its own plant and on the others (``experiment=generalization``).

    The test drives are driven again on each plant (the driver adapts to its grip), so a
    test-drive reference compares a model with the drives each plant produces; a reference built
    from no drive (the double lane change) is the same on every plant.
    """
    evaluated = [j for j in jobs if _get(j.metrics, "generalization")]
    groups = _group(evaluated, _learner, _plant)
    sections = [
        section
        for members in groups.values()
        for j in members
        for section in [j.metrics or {}, *(_get(j.metrics, "generalization") or {}).values()]
    ]
    references = list(
        dict.fromkeys(
            name for s in sections for _, name, _ in _tracking_runs(s.get("tracking") or {}, "")
        )
    )
    table = Table(
        "Generalization: trained on one plant, evaluated on others — open-loop prediction RMSE "
        "(mean over the test drives, driven again on each plant) and the first controller's "
        "tracking RMSE of every reference (a test drive is each plant's own first one; SI)",
        ["learner", "trained on", "evaluated on", "variant", "jobs"]
        + [f"prediction {s}" for s in STATES]
        + [f"tracking {reference} {s}" for reference in references for s in STATES],
    )
    for (learner, plant, varied), members in groups.items():
        targets = {plant: [(j.metrics or {}) for j in members]}
        for job in members:
            for other, section in (_get(job.metrics, "generalization") or {}).items():
                targets.setdefault(other, []).append(section)
        for target, sections in targets.items():
            runs = {
                reference: [_first_controller_run(s, reference) for s in sections]
                for reference in references
            }
            finite = [s for s in sections if not _diverged(s)]
            gone = len(sections) - len(finite)
            note = f" ({gone} of {len(sections)} diverged)" if gone else ""
            predicted = (
                [_mean_std(_mean_prediction(s, state) for s in finite) + note for state in STATES]
                if finite
                else [f"diverged ({gone} of {gone})"] * len(STATES)
            )
            table.rows.append(
                [learner, plant, target, varied or "—", str(len(sections))]
                + predicted
                + [
                    _mean_std(_get(run, "rmse", state) for run in runs[reference])
                    for reference in references
                    for state in STATES
                ]
            )
    return table


def step_response_table(jobs: list[Run]) -> Table:
    """Every step case of every learner: the plant's and the model's output, and the relative
    error of the model's response, at 0.3 s and 1.5 s after the step (mean ± std over jobs)."""
    times = ("at_300ms", "at_1500ms")
    table = Table(
        "Step responses from straight driving: yaw rate (rad/s) after a steering-wheel step, vx "
        "(m/s) after a throttle step; relative error of the model's response (change since the "
        "step) against the plant's; — where a model diverged",
        ["learner", "variant", "case", "jobs"]
        + [f"{quantity} {t.removeprefix('at_')}" for t in times for quantity in _STEP_QUANTITIES],
    )
    for (learner, varied), members in _group(jobs, _learner).items():
        sections = [_get(j.metrics, "prediction", "step_response") or {} for j in members]
        cases = list(dict.fromkeys(case for section in sections for case in section))
        for case in cases:
            present = [s[case] for s in sections if isinstance(s.get(case), Mapping)]
            table.rows.append(
                [learner, varied or "—", case, str(len(present))]
                + [
                    _mean_std(_get(run, t, quantity) for run in present)
                    for t in times
                    for quantity in _STEP_QUANTITIES
                ]
            )
    return table


_STEP_QUANTITIES = ("plant", "model", "relative_error")


def spectrum_table(jobs: list[Run]) -> Table:
    """The largest eigenvalue modulus of every Koopman model and its modes outside the unit
    circle: how many, and the fastest-growing one of the lowest seed, named (no "|" in a cell:
    it would split a Markdown table)."""
    table = Table(
        "Spectrum: largest |eigenvalue| of the state matrices (a bilinear model's at zero input "
        "and at the corners of the input box), modes outside the unit circle (abs λ > 1 + 1e-6), "
        "and the fastest-growing one (lowest seed)",
        ["learner", "variant", "jobs", "max abs λ", "unstable modes", "fastest unstable mode"],
    )
    for (learner, varied), members in _group(jobs, _learner).items():
        sections = [
            (j.seed, s)
            for j in members
            if isinstance(s := _get(j.metrics, "spectrum"), Mapping) and "max_abs_eigenvalue" in s
        ]
        if not sections:
            continue
        modes = min(sections, key=lambda pair: pair[0])[1].get("unstable_modes") or []
        fastest = min(modes, key=lambda mode: mode.get("doubling_time_s") or math.inf, default=None)
        table.rows.append(
            [
                learner,
                varied or "—",
                str(len(sections)),
                _mean_std(s.get("max_abs_eigenvalue") for _, s in sections),
                _mean_std(len(s.get("unstable_modes") or []) for _, s in sections),
                "—"
                if fastest is None
                else f"abs λ {fastest['abs']:.6f}, doubles in {fastest['doubling_time_s']:.3g} s, "
                f"{fastest['dominant']} at {fastest['matrix']}",
            ]
        )
    return table


def _course_runs(
    jobs: list[Run],
) -> Iterable[tuple[Run, tuple[str, str, str, str, str], Mapping[str, Any]]]:
    """(job, (learner, controller, surface, reference, variant), path metrics) of every run
    judged on a course, on the job's own plant and on every plant it was evaluated on."""
    common = common_overrides(jobs)
    for job in jobs:
        sections = {job.plant: job.metrics or {}, **(_get(job.metrics, "generalization") or {})}
        for surface, section in sections.items():
            runs = _tracking_runs(section.get("tracking") or {}, job.controller)
            for controller, reference, metrics in runs:
                path = metrics.get("path")
                if isinstance(path, Mapping):
                    varied = variant(job, common) or "—"
                    yield job, (job.learner, controller, surface, reference, varied), path


def course_table(jobs: list[Run]) -> Table:
    """Every closed-loop run judged on a course (``path``): learner × controller × surface ×
    reference, passes out of jobs, cones hit and deviation (``experiment=lane_change``: the
    ISO 3888-1 lane change at 60, 80 and 100 km/h, dry and wet)."""
    table = Table(
        "Lane change judged on its course: passed (no cone hit, exit reached) of jobs; cones "
        "knocked down by the body; lateral deviation of the car from the centre line (m); "
        "heading error (rad) and speed (m/s) at the exit",
        [
            *("learner", "controller", "surface", "reference", "variant", "passed", "cones hit"),
            *("max deviation", "rms deviation", "exit heading error", "exit speed"),
        ],
    )
    runs: dict[tuple[str, ...], list[Mapping[str, Any]]] = defaultdict(list)
    for _, key, path in _course_runs(jobs):
        runs[key].append(path)
    for key, paths in sorted(runs.items(), key=lambda kv: _natural(kv[0])):
        passed = sum(bool(p.get("passed")) for p in paths)
        table.rows.append(
            [*key, f"{passed}/{len(paths)}"]
            + [
                _mean_std(p.get(k) for p in paths)
                for k in (
                    "cones_hit",
                    "max_lateral_deviation_m",
                    "rms_lateral_deviation_m",
                    "exit_heading_error_rad",
                    "exit_speed_mps",
                )
            ]
        )
    return table


def course_speed_table(jobs: list[Run]) -> Table:
    """The headline of the lane-change sweep: per learner, controller and surface, the highest
    reference speed passed by every job, of the speeds tried."""
    table = Table(
        "Highest lane-change speed passed (every job of the row passed it; km/h)",
        ["learner", "controller", "surface", "variant", "jobs", "highest passed", "speeds tried"],
    )
    speeds: dict[tuple[str, ...], dict[float, list[bool]]] = defaultdict(lambda: defaultdict(list))
    jobs_per_key: dict[tuple[str, ...], set[str]] = defaultdict(set)
    for job, (learner, controller, surface, _, varied), path in _course_runs(jobs):
        if path.get("reference_speed_mps") is not None:
            key = (learner, controller, surface, varied)
            kph = round(3.6 * float(path["reference_speed_mps"]))
            speeds[key][kph].append(bool(path.get("passed")))
            jobs_per_key[key].add(job.name)
    for key, by_speed in sorted(speeds.items()):
        passed = [kph for kph, results in by_speed.items() if all(results)]
        highest = str(max(passed)) if passed else "none"
        tried = ", ".join(str(kph) for kph in sorted(by_speed))
        table.rows.append([*key, str(len(jobs_per_key[key])), highest, tried])
    return table


def _natural(key: tuple[str, ...]) -> list[Any]:
    """Sort ``lane_change_60kph`` before ``lane_change_100kph``."""
    return [int(p) if p.isdigit() else p for k in key for p in re.split(r"(\d+)", k)]


def failures_table(jobs: list[Run]) -> Table:
    table = Table("Jobs that did not finish", ["job", "reason"])
    for job in jobs:
        if job.error:
            table.rows.append([job.name, job.error])
        elif job.metrics is None:
            table.rows.append([job.name, "no metrics.json (still running, killed, or crashed)"])
    return table


def tables(runs: list[Run]) -> dict[str, Table]:
    """Every table of a sweep by its CSV name; the finished runs' numbers, every run's failure."""
    finished = [r for r in runs if r.metrics is not None and r.error is None]
    return {
        "prediction": prediction_table(finished),
        "prediction_window_41": prediction_table(finished, "rmse_window_41"),
        "prediction_window_10s": prediction_table(finished, "rmse_window_10s"),
        "prediction_window_3s": prediction_table(finished, "rmse_window_3s"),
        "prediction_window_1.5s": prediction_table(finished, "rmse_window_1.5s"),
        "tracking": tracking_table(finished),
        "quality": quality_table(finished),
        "robustness": robustness_table(finished),
        "generalization": generalization_table(finished),
        "step_response": step_response_table(finished),
        "spectrum": spectrum_table(finished),
        "course": course_table(finished),
        "course_speed": course_speed_table(finished),
        "training": training_table(finished),
        "failures": failures_table(runs),
    }
