"""A sweep's jobs, read into one list of :class:`Run` records: what every table and figure reads.

Each job directory is recognised by Hydra's ``.hydra/hydra.yaml``. A run's learner, plant and
controller are the config-group options Hydra chose for it (``hydra.runtime.choices``), its seed
is the one its composed config ran with (``.hydra/config.yaml``), and its command-line overrides
(``hydra.overrides.task``) are parsed with Hydra's own override grammar. The overrides that differ
within a sweep, besides the ones naming a row, make a run's ``variant``.

A sweep's ``multirun.yaml`` says which jobs it launches (the product of its choices, as Hydra's
``BasicSweeper`` builds it): a job that never started (the sweep was stopped before it) is a run
with an error, so is a job whose files cannot be read; none is dropped, none stops the report.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra._internal.config_loader_impl import ConfigLoaderImpl, get_overrides_dirname
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra._internal.utils import create_config_search_path
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

from harness.core.paths import CONF_DIR

log = logging.getLogger(__name__)

HYDRA_FILE = Path(".hydra") / "hydra.yaml"
MULTIRUN_FILE = "multirun.yaml"  # Hydra's record of a sweep, in its directory
NEVER_STARTED = "never started (no job directory: the sweep stopped before it)"
JOB_DIRNAME_BYTES = 200  # file names may have 255 bytes; Hydra adds nothing to the sweep subdir

# Overrides that name a row (or a line of a figure) of their own; never part of a variant.
NAMED = frozenset({"learner", "plant", "controller", "seed"})
# Overrides that change where or how a job runs, never its numbers: no row of their own.
NEUTRAL = frozenset(
    {
        "recorder",
        "threads",
        "task.reuse_baseline_runs",
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
    config: Any = None  # its composed config as Hydra saved it (.hydra/config.yaml), unresolved

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def learner(self) -> str:
        return self._choice("learner")

    @property
    def plant(self) -> str:
        """The plant the job drove; for a job on a user's logs (``data.source: logs``) the
        logs' config: the configured plant never ran."""
        data = (self.metrics or {}).get("data")
        if isinstance(data, dict) and data.get("source") == "logs":
            return f"logs: {self._choice('data')}"
        return self._choice("plant")

    @property
    def controller(self) -> str:
        return self._choice("controller")

    def _choice(self, group: str) -> str:
        """Hydra's choice for ``group``; for a job that never started, its override."""
        return str(self.choices.get(group) or self.overrides.get(group) or "—")


# What a finished job leaves beside metrics.json: the digest of the config it ran. A sweep rerun
# into the same directory skips a job whose digest matches (and whose metrics.json is there),
# so a sweep of hours can be stopped and started again; anything else runs (again). The report
# counts a job's metrics only where the digest is its config's.
FINISHED = "finished.json"


def config_digest(cfg: Any) -> str:
    """SHA-256 of the job's config as composed (interpolations unresolved), without Hydra's own
    node and the settings that change no number (``harness.report.jobs.NEUTRAL``)."""
    values = OmegaConf.to_container(cfg, resolve=False)
    assert isinstance(values, dict)
    values.pop("hydra", None)
    for key in NEUTRAL:
        *parents, leaf = key.split(".")
        node: Any = values
        for parent in parents:
            node = node.get(parent, {}) if isinstance(node, dict) else {}
        if isinstance(node, dict):
            node.pop(leaf, None)
    text = json.dumps(values, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def job_dirname(overrides: str, limit: int = JOB_DIRNAME_BYTES) -> str:
    """A sweep job's directory (``hydra.sweep.subdir``): its overrides with ``/`` (a path in a
    value) as ``_``, cut to ``limit`` bytes plus a hash when longer (the full list is in
    ``.hydra/overrides.yaml``)."""
    raw = overrides.replace("/", "_").encode()
    if len(raw) <= limit:
        return raw.decode()
    digest = hashlib.sha256(raw).hexdigest()[:10]
    return raw[: limit - len(digest) - 1].decode(errors="ignore") + "~" + digest


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
    """The run of one job directory; its metrics or error when it left them. A file that
    cannot be read makes the error, naming the file."""
    try:
        hydra = OmegaConf.load(directory / HYDRA_FILE).hydra
        config = OmegaConf.load(directory / ".hydra" / "config.yaml")
        choices = OmegaConf.to_container(hydra.runtime.choices)
        run = Run(
            directory,
            choices={str(k): None if v is None else str(v) for k, v in choices.items()},
            overrides=parse_overrides(OmegaConf.to_container(hydra.overrides.task)),
            seed=int(config.get("seed", 0)),
            config=config,
        )
    except Exception as error:  # YAML, OmegaConf or override syntax: any damage to .hydra/
        message = f"{type(error).__name__}: {error}".splitlines()[0]
        return Run(directory, error=f"{directory / '.hydra'} is unreadable ({message})")
    metrics, metrics_error = _read_json(directory / "metrics.json")
    finished, _ = _read_json(directory / FINISHED)
    if finished is not None and finished.get("config_sha256") != config_digest(config):
        # A run of another config ended here (a reused directory): its numbers are not this
        # config's, whatever metrics.json holds.
        metrics, metrics_error = (
            None,
            (
                f"{directory / FINISHED} is of another config than {directory / '.hydra'}: its "
                "metrics.json is another run's; rerun the job"
            ),
        )
    if metrics_error is None:
        run.metrics = metrics
    failure, failure_error = _read_json(directory / "error.json")
    if failure is not None:
        run.error = str(failure.get("error", "failed"))
    run.error = run.error or failure_error or metrics_error
    return run


def _read_json(path: Path) -> tuple[dict[str, Any] | None, str | None]:
    """A JSON object file and ``None``, or ``None`` and why it cannot be read (``None`` and
    ``None`` when there is no such file)."""
    if not path.exists():
        return None, None
    try:
        document = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        return None, f"{path} is unreadable ({error}); rerun the job"
    if not isinstance(document, dict):
        return None, f"{path} holds no JSON object; rerun the job"
    return document, None


def sweep_jobs(multirun: Path) -> list[tuple[str, dict[str, str]]] | None:
    """Every job a sweep launches: its directory's name and its overrides as
    :func:`parse_overrides` gives them. ``None`` where that cannot be known from ``multirun``
    (another sweeper, a damaged file). A sweep over a glob of a config group
    (``experiment=paper``'s ``learner: glob(*)``) is resolved against the files of ``conf/``, as
    Hydra did: the schemas that the app stores beside them (``edmd_schema``) are no options."""
    try:
        hydra = OmegaConf.load(multirun).hydra
        if hydra.sweeper._target_.rsplit(".", 1)[-1] != BasicSweeper.__name__:
            return None
        params = hydra.sweeper.get("params") or {}
        lines = [f"{k}={v}" for k, v in params.items()] + list(hydra.overrides.task)
        search_path = create_config_search_path(str(CONF_DIR))
        search_path.config_search_path = [  # type: ignore[attr-defined]
            element for element in search_path.get_path() if element.provider != "schema"
        ]
        loader = ConfigLoaderImpl(config_search_path=search_path)
        parser = OverridesParser.create(config_loader=loader)
        (batch,) = BasicSweeper.split_arguments(parser.parse_overrides(lines), None)
        naming = hydra.job.config.override_dirname
        jobs = []
        for job in batch:
            overrides = parser.parse_overrides(job)
            name = get_overrides_dirname(
                overrides, list(naming.exclude_keys), naming.item_sep, naming.kv_sep
            )
            jobs.append((job_dirname(name), parse_overrides(job)))
        return jobs
    except Exception as error:  # the jobs found still make the report
        message = f"{type(error).__name__}: {error}".splitlines()[0]
        log.warning(
            "%s: the sweep's jobs are unknown (%s); counting those found", multirun, message
        )
        return None


def read_runs(sweep_dir: Path) -> list[Run]:
    """Every job below ``sweep_dir``, in the order of their directories, then every job a
    sweep's ``multirun.yaml`` names that left no directory (with :data:`NEVER_STARTED`)."""
    runs = [read_run(path.parent.parent) for path in sorted(sweep_dir.rglob(str(HYDRA_FILE)))]
    for multirun in sorted(sweep_dir.rglob(MULTIRUN_FILE)):
        jobs = sweep_jobs(multirun)
        if jobs is None:
            continue
        started = [r.overrides for r in runs if _sweep_of(r.path) == multirun.parent]
        runs += [
            Run(
                multirun.parent / name,
                overrides=overrides,
                seed=int(overrides.get("seed", "0")),
                error=_never_read(multirun.parent / name),
            )
            for name, overrides in jobs
            if overrides not in started and not (multirun.parent / name / HYDRA_FILE).exists()
        ]
    return runs


def _never_read(job: Path) -> str:
    """Why a job of the sweep has no run to read: it never started, or its directory lost
    ``.hydra/`` (the config its results belong to) while it holds them."""
    if job.is_dir() and any((job / name).exists() for name in (FINISHED, "metrics.json")):
        return (
            f"{job / '.hydra'} is missing: its results cannot be matched to a config; restore "
            "it or rerun the job"
        )
    return NEVER_STARTED


def _sweep_of(job: Path) -> Path | None:
    """The sweep directory a job directory belongs to: the nearest with a ``multirun.yaml``."""
    return next((p for p in job.parents if (p / MULTIRUN_FILE).is_file()), None)


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
