"""The pipeline's closed loops: every controller of a run on every reference (``tracking``).

Each controller runs on the run's learner, or, for a controller that brings its own model (the
physics baseline), on that model fitted on the same training drives. A run that another
controller of the job drove bit for bit (a path follower on a reference without a path, beside
its state-tracking twin) is copied, not driven again; a baseline run another job drove with the
same code, plant, data and settings is reused (``harness/evaluation/reuse.py``).
"""

from __future__ import annotations

import json
import logging
import shutil
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from controllers.config import ControllerFactory, OwnModelFactory
from harness.core.contracts import Model, RunLearner, dynamics_of
from harness.core.episode import Episode
from harness.core.phases import Phase
from harness.data.store import Dataset
from harness.evaluation import reuse
from harness.evaluation.tracking import TrackingTrajectory, load_run, record_run, track
from harness.output import save_arrays
from harness.plant import Sedan
from harness.recorder import Recorder
from harness.references import CourseReference, Reference, ReferencePath
from harness.references.course import Course, path_metrics, plot_course, record_course

# A controller's model, or the one line that says why it has none (``tracking…skipped``).
ModelOrWhy = RunLearner | str
# (reference, model, settings without a path): what makes two controllers' runs the same run.
TwinKey = tuple[str, int, str]
log = logging.getLogger(__name__)


class ClosedLoops:
    """Every controller on every reference (``task.extra_controllers``, ``task.references``).

    Args:
        controllers: name -> checked settings, the run's controller first.
        references: name -> what to track (``conf/reference/``).
        learner_name: the run's learner, named in figures and skipped runs.
        reuse_baseline_runs: reuse a baseline run another job drove (``task.reuse_baseline_runs``).
    """

    def __init__(
        self,
        controllers: Mapping[str, ControllerFactory],
        references: Mapping[str, Reference],
        learner_name: str,
        reuse_baseline_runs: bool,
    ) -> None:
        self.controllers = dict(controllers)
        self.references = dict(references)
        self.learner_name = learner_name
        self.reuse_baseline_runs = reuse_baseline_runs

    def models(self, learner: RunLearner, dataset: Dataset) -> dict[str, ModelOrWhy]:
        """The model each controller runs on: the run's learner, or, for a controller that
        brings its own (``OwnModelFactory``: the physics baseline), that model fitted on the
        same training episodes; where that fit refuses the data (a tiny dataset), the reason,
        reported as the controller's ``skipped`` instead of failing the run."""
        models: dict[str, ModelOrWhy] = {}
        reason = not_lifted_linear(learner)
        fitted: dict[str, RunLearner | ValueError] = {}  # one fit per distinct own model
        for name, make in self.controllers.items():
            if not isinstance(make, OwnModelFactory):
                # A model no MPC reads (persistence) skips its controllers, not the baseline.
                models[name] = f"{self.learner_name} {reason}" if reason else learner
                continue
            own = make.learner()
            key = json.dumps([type(own).__name__, own.hyperparameters], sort_keys=True, default=str)
            if key not in fitted:
                with Phase(f"identification {own.name}") as phase:
                    try:
                        fitted[key] = own.fit(dataset.train, dataset.validation, dataset.normalizer)
                        phase.done = f"fitted on the training drives, for {name}"
                    except ValueError as error:
                        fitted[key] = error
                        phase.done = f"refused the training drives: {error}"
            model = fitted[key]
            if isinstance(model, ValueError):
                log.warning("%s not tracked: %s", name, model)
                models[name] = f"{name} could not identify its {own.name} model: {model}"
            else:
                models[name] = model
        return models

    def track(
        self,
        models: Mapping[str, ModelOrWhy],
        plant: Sedan,
        episodes: Sequence[Episode],
        recorder: Recorder,
        output_dir: Path,
        prefix: str = "",
        *,
        data_key: str,
    ) -> dict[str, Any] | None:
        """Every controller on every reference (each built from the test drives ``episodes``);
        the first controller's run of the first reference is the top level. ``data_key``: the
        dataset the models were fitted on (a stored baseline run is reused only on the same)."""
        if not self.controllers or not self.references:
            return None
        targets = {
            name: (reference.label(name, episodes), reference.build(plant.dt, episodes))
            for name, reference in self.references.items()
        }
        courses = self._courses()
        centre_lines = {name: course.path() for name, course in courses.items()}
        paths: dict[str, dict[str, np.ndarray]] = {name: {} for name in courses}
        by_controller: dict[str, dict[str, Any]] = {}
        twin_keys = self._twin_keys(models, list(targets), centre_lines)
        twins = Counter(twin_keys.values())
        # twin key -> the first controller's run, kept where a later one is its twin
        driven: dict[TwinKey, tuple[str, TrackingTrajectory]] = {}
        for controller_name, make_controller in self.controllers.items():
            model = models[controller_name]
            if isinstance(model, str):
                by_controller[controller_name] = {"skipped": model}
                continue
            # The run's learner passed not_lifted_linear; an own model is linearizable.
            assert isinstance(model, Model)
            runs: dict[str, Any] = {}
            with Phase(f"{prefix}tracking {controller_name}") as phase:
                for name, (label, reference) in targets.items():
                    stem = f"tracking_{controller_name}_{name}"
                    twin = twin_keys[controller_name, name]
                    rollout = f"{prefix}tracking/{controller_name}/{label}"
                    if twin in driven:  # the same run, bit for bit: copied, not driven again
                        twin_name, twin_run = driven[twin]
                        runs[label] = {**by_controller[twin_name][label], "same_run_as": twin_name}
                        _copy_run(output_dir, f"tracking_{twin_name}_{name}", stem)
                        record_run(recorder, rollout, twin_run, plant.dt, 1)
                        continue
                    metrics, run = self._drive(
                        plant,
                        make_controller,
                        model,
                        reference,
                        rollout=rollout,
                        recorder=recorder,
                        figure_path=output_dir / f"{stem}.png",
                        arrays_path=output_dir / f"{stem}.npz",
                        tab_priority=2 if name in courses else 1,  # the recording opens on a course
                        course=courses.get(name),
                        path=centre_lines.get(name),
                        data_key=data_key,
                    )
                    if twin is not None and twins[twin] > 1:
                        driven[twin] = (controller_name, run)
                    if name in courses:
                        record_course(recorder, rollout, courses[name])
                        paths[name][controller_name] = run.poses
                    runs[label] = metrics
                    rmse, course = metrics["rmse"], metrics.get("path")
                    log.debug(
                        "%s%s tracked %s: rmse %s, path %s",
                        prefix,
                        controller_name,
                        label,
                        rmse,
                        course,
                    )
                phase.done = tracking_done(runs)
            by_controller[controller_name] = runs
        self._plot_courses(courses, paths, output_dir)
        return _sections(by_controller)

    def _courses(self) -> dict[str, Course]:
        """The course of each reference that has one (the lane change's cones and path)."""
        return {
            name: reference.course()
            for name, reference in self.references.items()
            if isinstance(reference, CourseReference)
        }

    def _twin_keys(
        self,
        models: Mapping[str, ModelOrWhy],
        references: Sequence[str],
        centre_lines: Mapping[str, ReferencePath],
    ) -> dict[tuple[str, str], TwinKey | None]:
        """(controller, reference) -> what makes its run the same as another's (``_twin_key``)."""
        return {
            (c, name): _twin_key(name, model, self.controllers[c], centre_lines.get(name))
            for c, model in models.items()
            if not isinstance(model, str)
            for name in references
        }

    def _plot_courses(
        self,
        courses: Mapping[str, Course],
        paths: Mapping[str, Mapping[str, np.ndarray]],
        output_dir: Path,
    ) -> None:
        """Each course's arrays and its top view with every controller's path."""
        for name, course in courses.items():
            save_arrays(output_dir / f"course_{name}.npz", **course.as_arrays())
            title = f"{self.learner_name}: {name} (top view)"
            plot_course(course, paths[name], output_dir / f"course_{name}.png", title=title)

    def _drive(
        self,
        plant: Sedan,
        make: ControllerFactory,
        model: Model,
        reference: np.ndarray,
        *,
        rollout: str,
        recorder: Recorder,
        figure_path: Path,
        arrays_path: Path,
        tab_priority: int,
        course: Course | None,
        path: ReferencePath | None,
        data_key: str,
    ) -> tuple[dict[str, Any], TrackingTrajectory]:
        """One closed loop of ``make``'s controller on ``model``; for a controller with its own
        model (the physics baseline) in a job that records nothing, the run another job drove
        with the same code, plant, data and settings (``harness/evaluation/reuse.py``).
        ``path``: the course's centre line the controller follows (None off a course)."""
        key = None
        own = isinstance(make, OwnModelFactory)
        if own and self.reuse_baseline_runs and type(recorder) is Recorder:
            parts = {
                "plant": repr(plant.params),
                "dt": plant.dt,
                "data": data_key,
                "model": [type(model).__name__, getattr(model, "hyperparameters", None)],
                "controller": repr(make),
                "course": {k: v.tolist() for k, v in course.as_arrays().items()}
                if course
                else None,
            }
            key = reuse.run_key(parts, reference)
            stored = reuse.load(key)
            if stored is not None:
                reuse.copy_out(key, arrays_path, figure_path)
                reused = {"key": key, "driven_in": stored["driven_in"]}
                return {**stored["metrics"], "reused_from": reused}, load_run(arrays_path)
        metrics, run = track(
            plant,
            make(model, plant.dt),
            reference,
            name=rollout,
            recorder=recorder,
            figure_path=figure_path,
            arrays_path=arrays_path,
            tab_priority=tab_priority,
            path=path,
            compute_delay=make.compute_delay,
        )
        if course is not None:
            metrics["path"] = {
                **path_metrics(course, run.poses, run.states),
                "reference_speed_mps": float(reference[0, 0]),
            }
        if key is not None:
            driven = {"metrics": metrics, "driven_in": str(arrays_path.parent)}
            reuse.store(key, driven, arrays_path, figure_path)
        return metrics, run


def _sections(by_controller: Mapping[str, dict[str, Any]]) -> dict[str, Any]:
    """``tracking``: the first controller's first run at the top level (the paper's
    experiment), every reference of it, and every controller's."""
    first = next(iter(by_controller.values()))
    if "skipped" in first:
        return {"skipped": first["skipped"], "controllers": dict(by_controller)}
    return {
        **next(iter(first.values())),
        "reference": next(iter(first)),
        "references": first,
        "controllers": dict(by_controller),
    }


def _copy_run(output_dir: Path, source_stem: str, stem: str) -> None:
    """A twin's arrays and figure under this controller's name."""
    for suffix in (".npz", ".png"):
        source = output_dir / f"{source_stem}{suffix}"
        if source.exists():
            shutil.copyfile(source, output_dir / f"{stem}{suffix}")


def tracking_done(runs: Mapping[str, Mapping[str, Any]]) -> str:
    """A controller's line: each reference it drove, a course with its verdict."""
    done = []
    for label, metrics in runs.items():
        course = metrics.get("path")
        line = label
        if course is not None:
            verdict = "passed" if course.get("passed") else "FAILED"
            line += f" {verdict} ({course.get('cones_hit', 0)} cones)"
        if "same_run_as" in metrics:
            line += f" [{metrics['same_run_as']}'s run]"
        if "reused_from" in metrics:
            line += f" [reused from {metrics['reused_from']['driven_in']}]"
        done.append(line)
    return ", ".join(done)


def not_lifted_linear(learner: RunLearner) -> str | None:
    """Why DE-MPC cannot use ``learner`` (None: it can): the controller reads a
    :class:`~harness.core.contracts.Model` of declared dynamics (linear, bilinear or nonlinear)."""
    try:
        dynamics = dynamics_of(learner)
    except ValueError as error:  # it declares dynamics it lacks the members of (unfitted)
        return f"is not a model a controller reads ({error})"
    return None if dynamics else "is not a model a controller reads (it declares no dynamics)"


def _twin_key(
    reference: str, model: object, make: ControllerFactory, path: object | None
) -> TwinKey | None:
    """What makes two controllers' runs of ``reference`` the same run: a reference without a
    path is driven by a path follower as by its state-tracking twin (``without_path``), so the
    pipeline drives it once (``experiment=paper``'s ``*_path`` controllers on the test drive).
    None: no such settings, or a path to follow."""
    without_path = getattr(make, "without_path", None)
    if path is not None or without_path is None:
        return None
    return reference, id(model), repr(without_path())
