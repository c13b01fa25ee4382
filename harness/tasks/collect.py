"""``task=collect``: make (or reuse) the dataset, then record and summarise its coverage."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from harness.data.collect import data_config, prepare
from harness.plant import Sedan
from harness.recorder import Recorder


class Collect:
    """The data stage alone: ``python -m harness task=collect data=paper``."""

    def __init__(self, data: Mapping[str, Any]) -> None:
        self.data = data_config(data)

    def __call__(self, plant: Sedan, recorder: Recorder, output_dir: Path) -> dict[str, Any]:
        _, metrics = prepare(plant, self.data, recorder, output_dir)
        return {"data": metrics}
