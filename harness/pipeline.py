"""``task=pipeline`` (the main job): data -> training -> prediction tables -> closed-loop tracking.

Sections written to ``metrics.json``:

- ``data``: the dataset used (see ``harness/data/collect.py``);
- ``training``: the learner, its fit time and where the model file is;
- ``prediction``: per test episode, RMSE of the open-loop prediction over the whole episode
  and over re-initialised windows (see ``harness/prediction.py``);
- ``robustness`` (learners trained with ``random_layer.enabled``): per test episode the RMSE's
  mean, std, min and max over ``robustness_repeats`` predictions;
- ``tracking``: DE-MPC on the plant (Koopman learners only). The top-level keys
  (``rmse``, ``solve_time_ms``, ``deadline_misses``, ``solver_failures``) are the paper's
  experiment, tracking the first test episode; ``tracking.references.<name>`` holds every
  reference tracked, e.g. the ISO 3888 double lane change.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from harness import references
from harness.data.collect import prepare
from harness.data.store import DataConfig
from harness.plant import Sedan
from harness.prediction import evaluate, robustness
from harness.recorder import Recorder
from harness.tracking import track
from learners.base import KoopmanLearner, Learner
from learners.base import load as load_learner

log = logging.getLogger(__name__)

REFERENCES = ("test_episode", "double_lane_change")


class Pipeline:
    """The whole experiment of one learner on one plant; keys are ``conf/task/pipeline.yaml``."""

    def __init__(
        self,
        data: Mapping[str, Any],
        learner: Learner,
        learner_name: str,
        controller: Callable[..., Any] | None = None,
        *,
        model_path: str | None = None,
        prediction_window_steps: int = 41,
        prediction_window_s: float = 10.0,
        tracking_references: Sequence[str] = REFERENCES,
        double_lane_change_speed_mps: float = 80 / 3.6,
        robustness_repeats: int = 100,
    ) -> None:
        self.data = DataConfig.from_config(data)
        self.learner, self.learner_name = learner, learner_name
        self.make_controller = controller
        self.model_path = model_path
        if prediction_window_steps < 1 or prediction_window_s <= 0:
            raise ValueError(
                "task.prediction_window_steps and task.prediction_window_s must be > 0"
            )
        unknown = set(tracking_references) - set(REFERENCES)
        if unknown:
            raise ValueError(
                f"task.tracking_references: unknown {sorted(unknown)}; choose from {REFERENCES}"
            )
        self.window_steps, self.window_s = prediction_window_steps, prediction_window_s
        self.references = list(tracking_references)
        self.lane_change_speed = double_lane_change_speed_mps
        if robustness_repeats < 1:
            raise ValueError(f"task.robustness_repeats must be >= 1 (got {robustness_repeats})")
        self.robustness_repeats = robustness_repeats

    def __call__(self, plant: Sedan, recorder: Recorder, output_dir: Path) -> dict[str, Any]:
        dataset, data_metrics = prepare(plant, self.data, recorder, output_dir)
        sections: dict[str, Any] = {"data": data_metrics}

        start = time.perf_counter()
        if self.model_path:
            learner = load_learner(self.model_path)
            source = str(Path(self.model_path).resolve())
        else:
            learner = self.learner.fit(
                dataset.train,
                dataset.validation,
                dataset.normalizer,
                recorder=recorder,
                output_dir=output_dir,
            )
            source = "trained"
        fit_time = time.perf_counter() - start
        model_file = learner.save(output_dir / f"model_{self.learner_name}.pt")
        sections["training"] = {
            "learner": self.learner_name,
            "source": source,
            "fit_time_s": fit_time,
            "model_path": str(model_file),
            "train_frames": sum(len(e) for e in dataset.train),
        }

        predictions = evaluate(
            {self.learner_name: learner},
            dataset.test,
            window_steps=self.window_steps,
            window_seconds=self.window_s,
            recorder=recorder,
            output_dir=output_dir,
        )
        sections["prediction"] = _one_learner(predictions, self.learner_name)
        if getattr(getattr(learner, "random_layer", None), "enabled", False):
            repeated = robustness(
                {self.learner_name: learner},
                dataset.test,
                self.robustness_repeats,
                recorder=recorder,
                output_dir=output_dir,
            )
            sections["robustness"] = _one_learner(repeated, self.learner_name)

        if self.make_controller is None or not self.references:
            return sections
        if not isinstance(learner, KoopmanLearner):
            sections["tracking"] = {"skipped": f"{self.learner_name} is not a lifted-linear model"}
            return sections
        runs: dict[str, Any] = {}
        for name in self.references:
            if name == "test_episode":
                episode = dataset.test[0]
                label, reference = f"test_episode/{episode.name}", references.from_episode(episode)
            else:
                label = name
                reference = references.double_lane_change(self.lane_change_speed, dt=plant.dt)
            controller = self.make_controller(learner)
            metrics, _ = track(
                plant,
                controller,
                reference,
                name=f"tracking/{label}",
                recorder=recorder,
                figure_path=output_dir / f"tracking_{name}.png",
            )
            metrics["horizon"] = {"Np": controller.Np, "Nc": controller.Nc}
            runs[label] = metrics
            log.info("tracked %s: rmse %s", label, metrics["rmse"])
        first = next(iter(runs.values()))
        sections["tracking"] = {**first, "reference": next(iter(runs)), "references": runs}
        return sections


def _one_learner(predictions: Mapping[str, Any], learner_name: str) -> dict[str, Any]:
    """``prediction.<episode>.rmse…`` for the run's one learner (the public contract)."""
    if learner_name in predictions:
        return dict(predictions[learner_name])
    return {
        episode: dict(values[learner_name]) if learner_name in values else dict(values)
        for episode, values in predictions.items()
    }
