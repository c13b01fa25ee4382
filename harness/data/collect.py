"""The data stage of ``task=collect`` and ``task=pipeline``: make (or reuse) the dataset, then
record and summarise its coverage (the tasks themselves are in ``harness/tasks/``)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from harness.core.contracts import Reference
from harness.data import coverage
from harness.data.driver import DriverKnowledge
from harness.data.logs import LogsConfig, import_logs
from harness.data.store import DataConfig, Dataset, collect_counted, load
from harness.plant import Sedan
from harness.recorder import Recorder

log = logging.getLogger(__name__)


def prepare(
    plant: Sedan, data: DataConfig | LogsConfig, recorder: Recorder, output_dir: Path
) -> tuple[Dataset, dict]:
    """Collect or reuse (a user's logs: check and store them); write the coverage figure; record
    every episode; return the summary."""
    friction: float | None
    if isinstance(data, LogsConfig):
        directory, collected, friction = import_logs(data), 0, None
    else:
        directory, collected = collect_counted(plant, data, DriverKnowledge.of(plant.params))
        friction = plant.params.tire.road_friction
    dataset = load(directory)
    splits = {"train": dataset.train, "validation": dataset.validation, "test": dataset.test}
    coverage.plot(splits, friction, output_dir / "data_coverage.png")
    step = data.record_every
    for split, episodes in splits.items():
        for e in episodes:
            recorder.rollout(
                f"data/{split}/{e.name}",
                e.time_s[::step],
                e.states[::step],
                e.inputs[::step],
                e.poses[::step],
                input_names=e.input_names,
                extra={"lateral_accel_mps2": coverage.lateral_accel(e)[::step]},
                priority=-1,  # the run's inputs: the layout's last tabs (it has a view budget)
            )
    metrics = {
        "key": dataset.key,
        "path": str(dataset.path),
        "split": {s: [e.name for e in episodes] for s, episodes in splits.items()},
        "spun_episodes": sorted(n for n, v in dataset.manifest["episodes"].items() if v["spun"]),
        # Episodes this job drove; 0: stored already (or by another job of the sweep).
        "episodes_collected": collected,
        "source": "logs" if dataset.from_logs else "plant",
        "period_s": dataset.period_s,
        "inputs": list(dataset.normalizer.input_names),
        "coverage": coverage.summary(dataset.episodes(), friction),
        "normalizer": dataset.normalizer.to_dict(),
    }
    return dataset, metrics


def reference_speeds(
    references: Mapping[str, Reference], dt: float, dataset: Dataset
) -> dict[str, Any]:
    """The speed range of every reference the pipeline tracks against the training drives'.

    A model is judged outside its data where a reference leaves the training speed range (the
    lane change at 22.2 m/s on drives that never passed 20.7 m/s did): each such reference is
    named in a warning and in ``data.outside_training_speed``.
    """
    vx = np.concatenate([e.states[:, 0] for e in dataset.train])
    low, high = float(vx.min()), float(vx.max())
    ranges: dict[str, list[float]] = {}
    for name, reference in references.items():
        label = reference.label(name, dataset.test)
        speeds = reference.build(dt, dataset.test)[:, 0]
        ranges[label] = [float(speeds.min()), float(speeds.max())]
    outside = sorted(label for label, (a, b) in ranges.items() if a < low or b > high)
    for label in outside:
        a, b = ranges[label]
        log.warning(
            "data: the reference %s runs at %.1f to %.1f m/s, outside the training drives' "
            "%.1f to %.1f m/s: its tracking judges the model outside its data",
            label,
            a,
            b,
            low,
            high,
        )
    return {
        "training_speed_range_mps": [low, high],
        "reference_speed_range_mps": ranges,
        "outside_training_speed": outside,
    }


def data_config(node: Any) -> DataConfig | LogsConfig:
    """The ``data`` block as its schema's object: drives to collect, or a user's logs."""
    value = node if isinstance(node, DataConfig | LogsConfig) else OmegaConf.to_object(node)
    if not isinstance(value, DataConfig | LogsConfig):
        raise ValueError(f"data must be a data or logs config, got {type(value).__name__}")
    return value
