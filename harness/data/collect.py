"""The data stage of ``task=collect`` and ``task=pipeline``: make (or reuse) the dataset, then
record and summarise its coverage (the tasks themselves are in ``harness/tasks/``)."""

from __future__ import annotations

from pathlib import Path

from harness.data import coverage
from harness.data.driver import DriverKnowledge
from harness.data.store import DataConfig, Dataset, collect_counted, load
from harness.plant import Sedan
from harness.recorder import Recorder


def prepare(
    plant: Sedan, data: DataConfig, recorder: Recorder, output_dir: Path
) -> tuple[Dataset, dict]:
    """Collect or reuse; write the coverage figure; record every episode; return the summary."""
    directory, collected = collect_counted(plant, data, DriverKnowledge.of(plant.params))
    dataset = load(directory)
    splits = {"train": dataset.train, "validation": dataset.validation, "test": dataset.test}
    coverage.plot(splits, plant.params.tire.road_friction, output_dir / "data_coverage.png")
    step = data.record_every
    for split, episodes in splits.items():
        for e in episodes:
            recorder.rollout(
                f"data/{split}/{e.name}",
                e.time_s[::step],
                e.states[::step],
                e.inputs[::step],
                e.poses[::step],
                extra={"lateral_accel_mps2": coverage.lateral_accel(e)[::step]},
            )
    metrics = {
        "key": dataset.key,
        "path": str(dataset.path),
        "split": {s: [e.name for e in episodes] for s, episodes in splits.items()},
        "spun_episodes": sorted(n for n, v in dataset.manifest["episodes"].items() if v["spun"]),
        # Episodes this job drove; 0: stored already (or by another job of the sweep).
        "episodes_collected": collected,
        "coverage": coverage.summary(dataset.episodes(), plant.params.tire.road_friction),
        "normalizer": dataset.normalizer.to_dict(),
    }
    return dataset, metrics
