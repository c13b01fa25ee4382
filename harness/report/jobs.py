"""A sweep's jobs, read into one list of :class:`Run` records: what every table and figure reads.

Each job directory is recognised by Hydra's ``.hydra/hydra.yaml``. A run's learner, plant and
controller are the config-group options Hydra chose for it (``hydra.runtime.choices``), its seed
is the one its composed config ran with (``.hydra/config.yaml``), and its command-line overrides
(``hydra.overrides.task``) are parsed with Hydra's own override grammar. The overrides that differ
within a sweep, besides the ones naming a row, make a run's ``variant``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

HYDRA_FILE = Path(".hydra") / "hydra.yaml"

# Overrides that name a row (or a line of a figure) of their own; never part of a variant.
NAMED = frozenset({"learner", "plant", "controller", "seed"})
# Overrides that change where or how a job runs, never its numbers: no row of their own.
NEUTRAL = frozenset(
    {
        "recorder",
        "data.root",
        "data.workers",
        "learner.training.progress",
        "learner.training.num_threads",
    }
)


@dataclass
class Run:
    """One job of a sweep: what Hydra recorded of it, and what it left behind."""

    path: Path
    choices: dict[str, str | None] = field(default_factory=dict)
    overrides: dict[str, str] = field(default_factory=dict)
    seed: int = 0
    metrics: dict[str, Any] | None = None
    error: str | None = None

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def learner(self) -> str:
        return self._choice("learner")

    @property
    def plant(self) -> str:
        return self._choice("plant")

    @property
    def controller(self) -> str:
        return self._choice("controller")

    def _choice(self, group: str) -> str:
        return str(self.choices.get(group) or "—")


def parse_overrides(lines: Iterable[str]) -> dict[str, str]:
    """``key`` (``group@package`` for a group) -> value, as Hydra writes it in job directory
    names; a deleted entry (``~key``) has the value ``null``."""
    overrides = {}
    for override in OverridesParser.create().parse_overrides(list(lines)):
        key = override.key_or_group
        if override.package is not None:
            key += f"@{override.package}"
        overrides[key] = override.get_value_element_as_str()
    return overrides


def read_run(directory: Path) -> Run:
    """The run of one job directory; its metrics or error when it left them."""
    hydra = OmegaConf.load(directory / HYDRA_FILE).hydra
    config = OmegaConf.load(directory / ".hydra" / "config.yaml")
    choices = OmegaConf.to_container(hydra.runtime.choices)
    run = Run(
        directory,
        choices={str(k): None if v is None else str(v) for k, v in choices.items()},
        overrides=parse_overrides(OmegaConf.to_container(hydra.overrides.task)),
        seed=int(config.get("seed", 0)),
    )
    if (directory / "metrics.json").exists():
        run.metrics = json.loads((directory / "metrics.json").read_text())
    if (directory / "error.json").exists():
        run.error = json.loads((directory / "error.json").read_text()).get("error", "failed")
    return run


def read_runs(sweep_dir: Path) -> list[Run]:
    """Every job below ``sweep_dir``, in the order of their directories."""
    return [read_run(path.parent.parent) for path in sorted(sweep_dir.rglob(str(HYDRA_FILE)))]


def common_overrides(runs: Iterable[Run]) -> dict[str, str]:
    """The overrides every run shares."""
    runs = list(runs)
    if not runs:
        return {}
    shared = dict(runs[0].overrides)
    for run in runs[1:]:
        shared = {k: v for k, v in shared.items() if run.overrides.get(k) == v}
    return shared


def variant(
    run: Run, common: Mapping[str, str], named: Callable[[str], bool] = NAMED.__contains__
) -> str:
    """The run's overrides that differ within the sweep, besides the ``named`` ones (which
    name a row or a line of their own) and those that never change a number."""
    return ",".join(
        f"{k}={v}"
        for k, v in sorted(run.overrides.items())
        if not named(k) and k not in NEUTRAL and not k.startswith("hydra") and common.get(k) != v
    )
