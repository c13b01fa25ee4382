"""``task=pipeline`` (the main job): data -> training -> prediction tables -> closed-loop tracking.

Sections written to ``metrics.json``:

- ``data``: the dataset used (see ``harness/data/collect.py``);
- ``training``: the learner, its fit time (a resumed training's runs before it included:
  ``fit_time_before_resume_s``) and where the model file is; ``training.provenance``
  what the model was trained on against this run (a ``task.model_path`` of another plant,
  dataset or normalizer is named in a warning; see ``harness/tasks/provenance.py``);
- ``prediction``: per test episode, RMSE of the open-loop prediction over the whole episode
  and over re-initialised windows (see ``harness/evaluation/prediction.py``);
- ``robustness`` (learners trained with ``random_layer.enabled``): per test episode the RMSE's
  mean, std, min and max over ``robustness_repeats`` predictions;
- ``prediction.step_response``: steering and throttle steps from straight driving, the model
  against the plant at 0.3 s and 1.5 s (see ``harness/evaluation/step_response.py``);
- ``spectrum``: the eigenvalues of a Koopman model's state matrices and the modes outside the
  unit circle, named (see ``harness/evaluation/spectrum.py``); a bilinear model is not tracked
  (below);
- ``tracking``: DE-MPC on the plant (lifted-linear, bilinear and linearizable learners; the
  others report ``tracking.skipped``). The top-level keys
  (``rmse``, ``solve_time_ms``, ``deadline_misses``, ``solver_failures``) are the paper's
  experiment, tracking the first reference (the first test episode); ``tracking.references``
  holds every reference of ``task.references`` (``conf/reference/``), e.g. the ISO 3888 double
  lane change; ``tracking.controllers.<name>`` the same for every controller (``controller``
  first, then ``task.extra_controllers``, e.g. both of the paper's horizons);
- ``generalization.<plant>`` (``task.other_plants``, ``experiment=generalization``): the model
  of this run's plant evaluated on the test drives driven again on another plant, with the
  same ``prediction`` and ``tracking`` sections.

Beside ``metrics.json`` it leaves the arrays behind its figures (``prediction_<episode>.npz``,
``tracking_<controller>_<reference>.npz``, ``training_history.json``) for a sweep's report.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, cast

from controllers.config import ControllerFactory
from harness.core.checks import choice, integer, is_number
from harness.core.contracts import (
    COMPUTE_DELAYS,
    INPUT_NAMES,
    RunLearner,
)
from harness.core.episode import Episode
from harness.core.phases import Phase, seconds
from harness.data.collect import data_config, prepare, reference_speeds
from harness.data.driver import DriverKnowledge
from harness.data.store import DataConfig, Dataset, drive_again
from harness.evaluation import training_report
from harness.evaluation.prediction import (
    ENVELOPE_SPANS,
    beats_persistence,
    evaluate,
    robustness,
)
from harness.plant import Sedan
from harness.recorder import Recorder
from harness.references import Reference
from harness.tasks import provenance
from harness.tasks.closed_loops import ClosedLoops, ModelOrWhy
from harness.tasks.model_checks import spectrum_section, step_responses
from learners.model_file import check_inputs, check_same_learner
from learners.model_file import load as load_learner
from learners.persistence import Persistence

log = logging.getLogger(__name__)


# Below about 1 m/s the tyres are in their slip-limited low-speed regime and nothing of the
# handling the learners are for (cornering, load transfer, drag) shows; every working plant
# passes it within the first seconds of every drive. Training data that never reaches it means
# a plant that does not move (``plant.chassis.sprung_mass_kg=1e12``), not a dataset to fit.
MIN_TRAIN_SPEED_MPS = 1.0


class Pipeline:
    """The whole experiment of one learner on one plant; keys are ``conf/task/pipeline.yaml``."""

    def __init__(
        self,
        data: Mapping[str, Any],
        learner: RunLearner,
        learner_name: str,
        controller: ControllerFactory | None = None,
        *,
        controller_name: str = "de_mpc",
        extra_controllers: Mapping[str, ControllerFactory] | None = None,
        other_plants: Mapping[str, Sedan] | None = None,
        model_path: str | None = None,
        prediction_window_steps: int = 41,
        prediction_window_s: float | Sequence[float] = 10.0,
        prediction_envelope_spans: float = ENVELOPE_SPANS,
        references: Mapping[str, Reference] | None = None,
        robustness_repeats: int = 100,
        logs_from_plant: bool = False,
        reuse_baseline_runs: bool = True,
        compute_delay: str | None = None,
    ) -> None:
        self.data = data_config(data)
        self.learner, self.learner_name = learner, learner_name
        controllers = {controller_name: controller} if controller is not None else {}
        for name, make in (extra_controllers or {}).items():
            if name in controllers:  # controller=de_mpc beside the default extra de_mpc
                log.info("task.extra_controllers.%s is the run's controller: run once", name)
                continue
            if not isinstance(make, ControllerFactory):
                raise ValueError(
                    f"task.extra_controllers.{name} must be a controller config (conf/controller/)"
                )
            controllers[name] = make
        if compute_delay is not None:  # one clock for every controller the run drives
            choice("task.compute_delay", compute_delay, COMPUTE_DELAYS)
            controllers = {
                name: _with_delay(make, compute_delay, name) for name, make in controllers.items()
            }
        self.other_plants = dict(other_plants or {})
        self.model_path = model_path
        # All before any data: a model file of another learner, inputs the learner cannot take,
        # a size beyond this machine.
        self.loaded = self._load(model_path, learner, learner_name)
        if self.loaded is None:
            learner.check_inputs(self.data.channels)  # the sedan's, or the logs' column map
            if isinstance(self.data, DataConfig):
                learner.check_size(self.data.max_steps)  # logs: once read, before the fit
        self.window_steps, self.windows_s, self.envelope_spans = _prediction_settings(
            prediction_window_steps, prediction_window_s, prediction_envelope_spans
        )
        # null leaves a reference out (an experiment replacing the default's lane change)
        references = {k: v for k, v in (references or {}).items() if v is not None}
        for name, reference in references.items():
            if not isinstance(reference, Reference):
                raise ValueError(f"task.references.{name} must be a reference config (_target_)")
        integer("task.robustness_repeats", robustness_repeats)
        self.robustness_repeats = int(robustness_repeats)
        if not isinstance(logs_from_plant, bool):
            raise ValueError(f"task.logs_from_plant must be true or false (got {logs_from_plant})")
        self.logs_from_plant = logs_from_plant
        if not isinstance(reuse_baseline_runs, bool):
            raise ValueError(
                f"task.reuse_baseline_runs must be true or false (got {reuse_baseline_runs})"
            )
        self.closed_loops = ClosedLoops(controllers, references, learner_name, reuse_baseline_runs)

    @staticmethod
    def _load(path: str | None, learner: RunLearner, learner_name: str) -> RunLearner | None:
        """The model file of ``task.model_path``, refused unless it is the configured learner."""
        if not path:
            return None
        loaded = load_learner(path)
        check_same_learner(loaded, learner, str(path), learner_name)
        return loaded

    def __call__(self, plant: Sedan, recorder: Recorder, output_dir: Path) -> dict[str, Any]:
        """Data, fit, predictions and spectrum; then, on drives of ``plant``, step responses,
        tracking and other plants. On a user's logs those need the car that made the logs and
        are skipped, each named in one line saying why, unless the user says ``plant`` made
        them (``task.logs_from_plant``); the spectrum is at the logs' period."""
        with Phase("data") as phase:
            dataset, data_metrics = prepare(plant, self.data, recorder, output_dir)
            phase.done = data_done(self.data.name, data_metrics)
        logs = dataset.from_logs
        check_windows(self.windows_s, dataset.period_s, dataset.test)
        on_plant = not logs or self.logs_from_plant
        if logs and self.logs_from_plant:
            check_logs_drive(plant, dataset, self.data.name)
        if on_plant:
            data_metrics |= reference_speeds(self.closed_loops.references, plant.dt, dataset)
        if self.loaded is None:
            if logs:  # sized by the logs once they are read, still before the fit
                self.learner.check_size(max(len(e) for e in dataset.episodes()))
            check_training_data(dataset)
        sections: dict[str, Any] = {"data": data_metrics}
        this_run = provenance.of_logs(dataset) if logs else provenance.of_run(plant, dataset)
        with Phase("training") as phase:
            learner, training = self._learner(dataset, this_run, recorder, output_dir)
            phase.done = training_done(learner, training)
        sections["training"] = training
        with Phase("prediction") as phase:
            prediction = self._predict(learner, dataset.test, recorder, output_dir)
            sections["prediction"] = prediction
            drives = len(dataset.test)
            done = [f"{drives} test drive{'s' * (drives != 1)} open loop"]
            if on_plant:
                prediction["step_response"] = step_responses(
                    learner, self.learner_name, plant, recorder, output_dir
                )
                done.append("step responses")
            period = dataset.period_s if logs else plant.dt
            sections["spectrum"] = spectrum_section(
                learner, self.learner_name, period, recorder, output_dir
            )
            if learner.redraws_random_layer:
                repeated = robustness(
                    {self.learner_name: learner},
                    dataset.test,
                    self.robustness_repeats,
                    recorder=recorder,
                    output_dir=output_dir,
                )
                sections["robustness"] = _one_learner(repeated, self.learner_name)
                done.append(f"{self.robustness_repeats} redrawn random layers")
            phase.done = ", ".join(done)
        if not on_plant:
            return sections | self._skipped_on_logs(prediction)
        models = self.closed_loops.models(learner, dataset)
        tracking = self.closed_loops.track(
            models, plant, dataset.test, recorder, output_dir, data_key=dataset.key
        )
        if tracking is not None:
            sections["tracking"] = tracking
        if self.other_plants:
            sections["generalization"] = {
                name: self._generalize(name, other, models, learner, dataset, recorder, output_dir)
                for name, other in self.other_plants.items()
            }
        return sections

    def _skipped_on_logs(self, prediction: dict[str, Any]) -> dict[str, Any]:
        """What a run on logs leaves out, each section's ``skipped`` saying why (one line)."""
        why = (
            f"data={self.data.name} are logs, not drives of this harness's plant; this needs "
            "the car that made them (task.logs_from_plant=true if plant= is that car)"
        )
        prediction["step_response"] = {"skipped": why}
        skipped: dict[str, Any] = {}
        if self.closed_loops.controllers and self.closed_loops.references:
            skipped["tracking"] = {"skipped": why}
        if self.other_plants:
            skipped["generalization"] = {"skipped": why}
        log.info("%s skipped: %s", ", ".join(["prediction.step_response", *skipped]), why)
        return skipped

    def _learner(
        self,
        dataset: Dataset,
        this_run: Mapping[str, Any],
        recorder: Recorder,
        output_dir: Path,
    ) -> tuple[RunLearner, dict[str, Any]]:
        """Fit (or load ``model_path``), save the model (with what it was trained on: this run,
        or what the loaded file said) and its loss curves."""
        start = time.perf_counter()
        if self.loaded is not None:
            learner = self.loaded
            source = str(Path(str(self.model_path)).resolve())
            check_inputs(learner, dataset.normalizer.input_names, f"task.model_path {source}")
            provenance.check_period(source, learner.provenance_, dataset.period_s)
        else:
            learner = training_report.fit(
                self.learner,
                dataset.train,
                dataset.validation,
                dataset.normalizer,
                recorder=recorder,
                output_dir=output_dir,
            )
            source = "trained"
        fit_time = time.perf_counter() - start
        # A training resumed from its checkpoint: the runs before this one count too.
        history = getattr(learner.core, "history_", None) if self.loaded is None else None
        before_resume = float(getattr(history, "resumed_s", 0.0))
        recorded = learner.provenance_ if self.loaded is not None else this_run
        trained_on = provenance.compare(
            source, recorded, learner.normalizer_, this_run, dataset.normalizer
        )
        model_file = learner.save(output_dir / f"model_{self.learner_name}.pt", recorded)
        summary = {
            "learner": self.learner_name,
            "source": source,
            "fit_time_s": fit_time + before_resume,
            "fit_time_before_resume_s": before_resume,
            "model_path": str(model_file),
            "train_frames": sum(len(e) for e in dataset.train),
            "provenance": trained_on,
        }
        if learner.fit_summary:
            summary["fit"] = learner.fit_summary
        return learner, summary

    def _predict(
        self,
        learner: RunLearner,
        episodes: Sequence[Episode],
        recorder: Recorder,
        output_dir: Path,
        prefix: str = "",
    ) -> dict[str, Any]:
        predictions = evaluate(
            {self.learner_name: learner},
            episodes,
            window_steps=self.window_steps,
            window_seconds=self.windows_s,
            envelope_spans=self.envelope_spans,
            recorder=recorder,
            output_dir=output_dir,
            prefix=prefix,
        )
        section = _one_learner(predictions, self.learner_name)
        # The bar every model must clear, on the same drives (``prediction.persistence``), and
        # the verdict against it per window and state (``<episode>.beats_persistence``).
        held = Persistence().fit([], [], learner.normalizer_)
        bars = evaluate(
            {"persistence": held},
            episodes,
            window_steps=self.window_steps,
            window_seconds=self.windows_s,
        )["persistence"]
        if not isinstance(learner, Persistence):
            for episode, bar in bars.items():
                section[episode]["beats_persistence"] = beats_persistence(section[episode], bar)
        section["persistence"] = bars
        return section

    def _generalize(
        self,
        name: str,
        plant: Sedan,
        models: Mapping[str, ModelOrWhy],
        learner: RunLearner,
        dataset: Dataset,
        recorder: Recorder,
        output_dir: Path,
    ) -> dict[str, Any]:
        """The model of this run's plant, on the test drives driven again on ``plant``."""
        assert isinstance(self.data, DataConfig)  # logs never get here (``_on_logs``)
        episodes = drive_again(plant, self.data, DriverKnowledge.of(plant.params), dataset.test)
        directory = output_dir / "generalization" / name
        directory.mkdir(parents=True, exist_ok=True)
        prefix = f"generalization/{name}/"
        result = {"prediction": self._predict(learner, episodes, recorder, directory, prefix)}
        tracking = self.closed_loops.track(
            models, plant, episodes, recorder, directory, prefix, data_key=dataset.key
        )
        if tracking is not None:
            result["tracking"] = tracking
        return result


def _prediction_settings(
    window_steps: int, windows_s: float | Sequence[float], envelope_spans: float
) -> tuple[int, list[float], float]:
    """The prediction task's windows (steps; seconds, as a list) and envelope, checked."""
    # A window of one step is its measured first state only: no prediction to score.
    integer("task.prediction_window_steps", window_steps, 2)
    windows = [windows_s] if isinstance(windows_s, int | float) else list(windows_s)
    for window in windows:
        if not (is_number(window) and math.isfinite(window) and window > 0):
            raise ValueError(
                f"task.prediction_window_s must be a number > 0 or a list of them (got {windows_s})"
            )
    if not (is_number(envelope_spans) and 0 < envelope_spans < math.inf):
        raise ValueError(
            "task.prediction_envelope_spans must be a number > 0: how many training spans "
            f"beyond the data's range a prediction counts as diverged (got {envelope_spans})"
        )
    return int(window_steps), windows, float(envelope_spans)


def _with_delay(make: ControllerFactory, compute_delay: str, name: str) -> ControllerFactory:
    """The controller's settings with ``compute_delay`` (checked again, as any settings are)."""
    if not (dataclasses.is_dataclass(make) and hasattr(make, "compute_delay")):
        raise ValueError(
            f"task.compute_delay: controller {name} ({type(make).__name__}) has no "
            "compute_delay setting to apply it to"
        )
    return cast(ControllerFactory, dataclasses.replace(make, compute_delay=compute_delay))


def check_windows(windows_s: Sequence[float], period_s: float, test: Sequence[Episode]) -> None:
    """Every window of task.prediction_window_s at least two of the data's periods (one step
    is the measured state only: its RMSE would be empty), checked before training; a window as
    long as a test drive is said in a warning (its RMSE is the whole drive's under a window's
    name)."""
    shortest = min(test, key=len, default=None)
    for window in windows_s:
        if round(window / period_s) < 2:
            raise ValueError(
                f"task.prediction_window_s {window:g} s is under two of the data's periods "
                f"({period_s:g} s): no step to predict; make it >= {2 * period_s:g} s"
            )
        if shortest is not None and round(window / period_s) >= len(shortest):
            log.warning(
                "task.prediction_window_s %g s is as long as the test drive %s (%g s) or longer: "
                "its rmse_window_%gs is the whole drive's; shorten the window or test on longer "
                "drives",
                window,
                shortest.name,
                (len(shortest) - 1) * period_s,
                window,
            )


def check_training_data(dataset: Dataset) -> None:
    """Refuse to fit a dataset in which the car never moved (see ``MIN_TRAIN_SPEED_MPS``):
    a fit on it scores perfectly (nothing to predict) and means nothing."""
    fastest = max(float(abs(e.states[:, 0]).max()) for e in dataset.train)
    if fastest < MIN_TRAIN_SPEED_MPS:
        frames = sum(len(e) for e in dataset.train)
        check = (
            "check the logs' vx column and its scale (data.states.vx) and the files of "
            f"data.split.train ({', '.join(e.name for e in dataset.train[:3])}"
            f"{', ...' if len(dataset.train) > 3 else ''})"
            if dataset.from_logs
            else "check the plant's keys (plant.chassis.sprung_mass_kg, plant.powertrain.*, "
            "plant.brakes.*) and data.min_steps"
        )
        raise ValueError(
            f"data: the car never reached {MIN_TRAIN_SPEED_MPS} m/s in the {frames} training "
            f"frames of {dataset.path} (fastest {fastest:.3g} m/s): {check}"
        )


def check_logs_drive(plant: Sedan, dataset: Dataset, name: str) -> None:
    """Logs said to come from ``plant`` can drive it: the model's period is the plant's control
    period and its inputs are the plant's, by name and in its units.

    Raises:
        ValueError: (one line) naming what differs and what to set.
    """
    if not math.isclose(dataset.period_s, plant.dt, rel_tol=1e-9):
        raise ValueError(
            f"task.logs_from_plant: data={name} is at a period of {dataset.period_s:g} s but the "
            f"plant's controllers step every {plant.dt:g} s: set data.model_period_s={plant.dt:g} "
            f"or plant.control_period_s={dataset.period_s:g}"
        )
    names = tuple(channel.name for channel in dataset.train[0].channels)
    if names != INPUT_NAMES:
        raise ValueError(
            f"task.logs_from_plant: data={name}'s inputs are {', '.join(names)}; the plant takes "
            f"{', '.join(INPUT_NAMES)} (in its units): name the log's input columns so"
        )


def _one_learner(predictions: Mapping[str, Any], learner_name: str) -> dict[str, Any]:
    """``prediction.<episode>.rmse…`` for the run's one learner (the public contract)."""
    if learner_name in predictions:
        return dict(predictions[learner_name])
    return {
        episode: dict(values[learner_name]) if learner_name in values else dict(values)
        for episode, values in predictions.items()
    }


def data_done(name: str, metrics: Mapping[str, Any]) -> str:
    """The data phase's line: which drives, and whether this job drove or found them."""
    coverage = metrics.get("coverage", {})
    frames = f"{coverage.get('frames', 0):,} frames"
    drives = f"data={name}, {coverage.get('episodes', '?')} drives ({frames})"
    if metrics.get("source") == "logs":
        return f"{drives} of logs, stored at {metrics['path']}"
    collected = metrics.get("episodes_collected", 0)
    if collected:
        return f"{drives}, {collected} collected now into {metrics['path']}"
    return f"{drives} found in the cache at {metrics['path']}"


def training_done(learner: RunLearner, training: Mapping[str, Any]) -> str:
    """The training phase's line: loaded, fitted, or trained for how many batches."""
    if training["source"] != "trained":
        return f"{training['learner']} loaded from {training['source']}"
    history = getattr(learner.core, "history_", None)
    if history is None or not history.step:
        return f"{training['learner']} fitted on {training['train_frames']:,} frames"
    stopped = history.stopped.replace("_", " ") or "done"
    done = f"{training['learner']}, {history.step[-1]} batches (stopped: {stopped})"
    if training.get("fit_time_before_resume_s"):
        before = seconds(training["fit_time_before_resume_s"])
        done += f", resumed from its checkpoint after {before} of training"
    return done
