"""A sweep's results as one pandas table: :func:`load`, for queries the report does not make.

One row per job × plant × controller × reference (a job that tracked nothing, on a user's logs,
or that failed: one row, its controller and reference empty); ``experiment=generalization``'s
closed loops on the other plants are rows of their own, ``plant`` naming the one driven. The
columns name the row first (``job``, ``learner``, ``seed``, ``plant``, ``data``, ``variant``,
``controller``, ``reference``, ``Np``, ``Nc``, ``horizon``, ``mode``, ``offset_free``,
``compute_delay``, ``error``), then every number
of the closed-loop run flattened with dots (``rmse.vx``, ``solve_time_ms.p99``,
``path.max_lateral_deviation_m``), then every other section of the job's ``metrics.json``
flattened the same way (``prediction.episode_0000.rmse.vx``, ``training.fit_time_s``),
repeated on each of its rows. SI units, as in ``metrics.json``. A controller the job skipped is
a row too, its reference empty and ``skipped`` saying why.

``mode`` is what the controller's cost followed: ``states`` (the reference's) or ``path`` (the
course's centre line, ``controller.reference: path``); with ``offset_free`` and
``compute_delay``, read from the job's composed config, not from its controller's name.

    >>> runs = load("results/lane_change")  # doctest: +SKIP
    >>> lane = runs[runs.reference == "double_lane_change"]  # doctest: +SKIP
    >>> lane.groupby(["learner", "mode"])["path.max_lateral_deviation_m"].agg(["mean", "std"])
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import DictConfig, OmegaConf

from harness.report.jobs import HYDRA_FILE, Run, common_overrides, read_run, read_runs, variant

__all__ = ["flatten", "frame", "load", "read_jobs"]


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"rmse": {"vx": 1}}`` -> ``{"rmse.vx": 1}``; lists stay values."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def load(path: str | Path) -> pd.DataFrame:
    """The jobs below ``path`` (a sweep, a committed study under ``results/``, or one job
    directory) as one table (see the module docstring).

    Raises:
        ValueError: (one line) when ``path`` holds no job.
    """
    return frame(read_jobs(path))


def read_jobs(path: str | Path) -> list[Run]:
    """The jobs below ``path`` (a sweep, a study, or one job directory), read once.

    Raises:
        ValueError: (one line) when ``path`` holds no job.
    """
    path = Path(path)
    if not path.is_dir():
        state = "is not a directory" if path.exists() else "does not exist"
        raise ValueError(f"{path} {state}; give a sweep's, a study's or a job's directory")
    runs = [read_run(path)] if (path / HYDRA_FILE).is_file() else read_runs(path)
    if not runs:
        raise ValueError(f"{path} holds no Hydra job directories ({HYDRA_FILE})")
    return runs


def frame(runs: list[Run]) -> pd.DataFrame:
    """Jobs already read (:func:`read_jobs`) as :func:`load`'s table."""
    common = common_overrides(runs)
    rows = []
    for run in runs:
        job = {
            "job": run.name,
            "learner": run.learner,
            "seed": run.seed,
            "plant": run.plant,
            "data": str(run.choices.get("data") or "—"),
            "variant": variant(run, common) or "—",
            "error": run.error,
        }
        metrics = dict(run.metrics or {})
        tracking = metrics.pop("tracking", None) or {}
        # experiment=generalization: the same controllers on other plants, a row per plant.
        elsewhere = {
            plant: section["tracking"]
            for plant, section in (metrics.get("generalization") or {}).items()
            if isinstance(section, Mapping) and isinstance(section.get("tracking"), Mapping)
        }
        if elsewhere:
            metrics["generalization"] = {
                plant: {k: v for k, v in section.items() if k != "tracking"}
                for plant, section in metrics["generalization"].items()
            }
        sections = flatten(metrics)
        closed_loops = [(run.plant, *loop) for loop in _closed_loops(run, tracking)]
        for plant, other in elsewhere.items():
            closed_loops += [(plant, *loop) for loop in _closed_loops(run, other)]
        if not closed_loops:
            rows.append({**job, "controller": None, "reference": None, **sections})
        for plant, controller, reference, settings, values in closed_loops:
            horizon = values.get("horizon") or {}
            Np, Nc = horizon.get("Np"), horizon.get("Nc")
            rows.append(
                {
                    **job,
                    "plant": plant,
                    "controller": controller,
                    "reference": reference,
                    "Np": Np,
                    "Nc": Nc,
                    "horizon": f"{Np}/{Nc}" if horizon else None,
                    "mode": "path" if values.get("follows_path") else "states",
                    # an estimator block (a job from before it: the offset_free flag)
                    "offset_free": settings.get("disturbance") is not None
                    or bool(settings.get("offset_free", False)),
                    "compute_delay": values.get("compute_delay", settings.get("compute_delay")),
                    **flatten(values),
                    **sections,
                }
            )
    return pd.DataFrame(rows)


def _closed_loops(
    run: Run, tracking: Mapping[str, Any]
) -> list[tuple[str, str | None, Mapping[str, Any], Mapping[str, Any]]]:
    """(controller, reference, its settings, its metrics) of every closed-loop run of a job; a
    controller the job skipped (its model could not be identified, say) is one row, reference
    None, with its ``skipped`` reason."""
    settings = _controller_settings(run)
    loops: list[tuple[str, str | None, Mapping[str, Any], Mapping[str, Any]]] = []
    for controller, references in (tracking.get("controllers") or {}).items():
        if not isinstance(references, Mapping):
            continue
        if isinstance(references.get("skipped"), str):  # it did not run: say why, on its row
            loops.append((controller, None, {}, {"skipped": references["skipped"]}))
            continue
        for reference, values in references.items():
            if isinstance(values, Mapping) and "rmse" in values:
                loops.append((controller, reference, settings.get(controller, {}), values))
    return loops


def _controller_settings(run: Run) -> dict[str, Mapping[str, Any]]:
    """Each controller's composed settings, by its name in ``tracking.controllers``: the run's
    own (named by its Hydra choice) and every ``task.extra_controllers`` entry."""
    config = run.config
    if not isinstance(config, DictConfig):
        return {}
    found: dict[str, Mapping[str, Any]] = {}
    own = OmegaConf.select(config, "controller")
    if isinstance(own, DictConfig):
        found[run.controller] = _plain(own)
    extra = OmegaConf.select(config, "task.extra_controllers")
    if isinstance(extra, DictConfig):
        for name in extra:
            if isinstance(extra[name], DictConfig):
                found[str(name)] = _plain(extra[name])
    return found


def _plain(node: DictConfig) -> dict[str, Any]:
    """A settings node's literal values (interpolations left as they are written)."""
    values = OmegaConf.to_container(node, resolve=False)
    return {str(key): value for key, value in values.items()} if isinstance(values, dict) else {}
