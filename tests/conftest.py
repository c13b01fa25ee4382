"""Shared fixtures: plants and their characterization are built once per test run."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from harness.config import register_configs
from harness.core.paths import REPO_ROOT
from harness.plant import Sedan, SedanParams
from harness.plant.params import TireParams
from harness.recorder import Recorder
from harness.tasks.characterize import Characterize

# `python -m harness` in a subprocess imports this checkout, not the one pip installed editable.
os.environ["PYTHONPATH"] = os.pathsep.join(
    filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")])
)

register_configs()  # tests compose with hydra.compose: the YAML files extend these schemas


@pytest.fixture(scope="session")
def sedan() -> Sedan:
    return Sedan()


@pytest.fixture(scope="session")
def characterized(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """Characterization metrics of the dry and the wet sedan (about 3 s each)."""
    plants = {
        "sedan": SedanParams(),
        "sedan_wet": SedanParams(name="sedan_wet", tire=TireParams(road_friction=0.5)),
    }
    results = {}
    for name, params in plants.items():
        out = Path(tmp_path_factory.mktemp(name))
        results[name] = Characterize()(Sedan(params), Recorder(), out)["characterize"]
    return results
