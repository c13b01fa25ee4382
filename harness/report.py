"""``python -m harness.report SWEEP_DIR``: the paper's tables from a sweep's ``metrics.json`` files.

Every job directory of a Hydra multirun (one with ``.hydra/overrides.yaml``) is read; its
overrides name the row (learner, controller, plant, seed). Numbers are mean ± std over seeds.
Writes ``report.md`` and one CSV per table into ``SWEEP_DIR/report/``; failed jobs (an
``error.json``) and unfinished ones (no ``metrics.json``) are listed by name, never dropped
silently.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

STATES = ("vx", "vy", "yaw_rate")


@dataclass
class Job:
    """One job of a sweep: its directory, overrides, and what it left behind."""

    path: Path
    overrides: dict[str, str]
    metrics: dict[str, Any] | None = None
    error: str | None = None

    @property
    def name(self) -> str:
        return self.path.name

    def choice(self, key: str, default: str) -> str:
        return self.overrides.get(key, default)


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[str]] = field(default_factory=list)

    def markdown(self) -> str:
        lines = [f"### {self.title}", "", "| " + " | ".join(self.columns) + " |"]
        lines.append("|" + "---|" * len(self.columns))
        lines += ["| " + " | ".join(row) + " |" for row in self.rows]
        return "\n".join(lines) + "\n"


def _read_overrides(path: Path) -> dict[str, str]:
    overrides = {}
    for line in path.read_text().splitlines():
        line = line.strip().removeprefix("- ").strip().strip("'\"")
        if "=" in line:
            key, value = line.split("=", 1)
            overrides[key.lstrip("+~")] = value
    return overrides


def find_jobs(sweep_dir: Path) -> list[Job]:
    """Every job directory below ``sweep_dir`` (recognised by Hydra's ``.hydra/overrides.yaml``)."""
    jobs = []
    for overrides in sorted(sweep_dir.rglob(".hydra/overrides.yaml")):
        directory = overrides.parent.parent
        job = Job(directory, _read_overrides(overrides))
        if (directory / "metrics.json").exists():
            job.metrics = json.loads((directory / "metrics.json").read_text())
        if (directory / "error.json").exists():
            job.error = json.loads((directory / "error.json").read_text()).get("error", "failed")
        jobs.append(job)
    return jobs


def _mean_std(values: Iterable[float | None]) -> str:
    numbers = [v for v in values if v is not None and math.isfinite(v)]
    if not numbers:
        return "—"
    mean = sum(numbers) / len(numbers)
    if len(numbers) == 1:
        return f"{mean:.4g}"
    std = math.sqrt(sum((v - mean) ** 2 for v in numbers) / (len(numbers) - 1))
    return f"{mean:.4g} ± {std:.2g}"


def _get(tree: Mapping[str, Any] | None, *keys: str) -> Any:
    for key in keys:
        if not isinstance(tree, Mapping) or key not in tree:
            return None
        tree = tree[key]
    return tree


_NAMED = {"learner", "plant", "controller", "seed"}


def _variant(job: Job, common: Mapping[str, str]) -> str:
    """The job's overrides that differ within the sweep, besides the named ones and the seed."""
    return ",".join(
        f"{k}={v}"
        for k, v in sorted(job.overrides.items())
        if k not in _NAMED and common.get(k) != v
    )


def _common(jobs: Iterable[Job]) -> dict[str, str]:
    jobs = list(jobs)
    if not jobs:
        return {}
    shared = dict(jobs[0].overrides)
    for job in jobs[1:]:
        shared = {k: v for k, v in shared.items() if job.overrides.get(k) == v}
    return shared


def _group(jobs: Iterable[Job], *keys: tuple[str, str]) -> dict[tuple[str, ...], list[Job]]:
    """Jobs that differ only by seed share a group (mean ± std); the last key is the variant."""
    jobs = list(jobs)
    common = _common(jobs)
    groups: dict[tuple[str, ...], list[Job]] = defaultdict(list)
    for job in jobs:
        key = (*(job.choice(k, default) for k, default in keys), _variant(job, common))
        groups[key].append(job)
    return dict(sorted(groups.items()))


def prediction_table(jobs: list[Job], metric: str = "rmse") -> Table:
    table = Table(
        f"Prediction RMSE ({metric}; vx, vy in m/s, yaw rate in rad/s; mean ± std over jobs)",
        ["learner", "plant", "variant", "test episode", "jobs", *STATES],
    )
    for (learner, plant, variant), members in _group(
        jobs, ("learner", "deep_edmd"), ("plant", "sedan")
    ).items():
        episodes = sorted({e for j in members for e in (_get(j.metrics, "prediction") or {})})
        for episode in episodes:
            values = [_get(j.metrics, "prediction", episode, metric) for j in members]
            present = [v for v in values if v]
            table.rows.append(
                [learner, plant, variant or "—", episode, str(len(present))]
                + [_mean_std(v.get(s) for v in present) for s in STATES]
            )
    return table


def tracking_table(jobs: list[Job]) -> Table:
    table = Table(
        "DE-MPC tracking RMSE (first test episode; SI) and solve time (ms)",
        [
            "learner",
            "controller",
            "Np/Nc",
            "variant",
            "jobs",
            *STATES,
            "solve median",
            "solve p99",
            "deadline misses",
            "solver failures",
        ],
    )
    for (learner, controller, variant), members in _group(
        jobs, ("learner", "deep_edmd"), ("controller", "de_mpc")
    ).items():
        tracked = [j for j in members if _get(j.metrics, "tracking", "rmse")]
        if not tracked:
            continue
        horizon = _get(tracked[0].metrics, "tracking", "horizon") or {}
        table.rows.append(
            [
                learner,
                controller,
                f"{horizon.get('Np', '?')}/{horizon.get('Nc', '?')}",
                variant or "—",
                str(len(tracked)),
            ]
            + [_mean_std(_get(j.metrics, "tracking", "rmse", s) for j in tracked) for s in STATES]
            + [
                _mean_std(_get(j.metrics, "tracking", "solve_time_ms", q) for j in tracked)
                for q in ("median", "p99")
            ]
            + [
                _mean_std(_get(j.metrics, "tracking", k) for j in tracked)
                for k in ("deadline_misses", "solver_failures")
            ]
        )
    return table


def training_table(jobs: list[Job]) -> Table:
    table = Table("Training", ["learner", "variant", "jobs", "fit time (s)", "train frames"])
    for (learner, variant), members in _group(jobs, ("learner", "deep_edmd")).items():
        trained = [j for j in members if _get(j.metrics, "training")]
        if trained:
            table.rows.append(
                [
                    learner,
                    variant or "—",
                    str(len(trained)),
                    _mean_std(_get(j.metrics, "training", "fit_time_s") for j in trained),
                    _mean_std(_get(j.metrics, "training", "train_frames") for j in trained),
                ]
            )
    return table


def robustness_table(jobs: list[Job]) -> Table:
    table = Table(
        "Random-layer robustness: RMSE mean (spread) over repeated predictions",
        ["learner", "test episode", *STATES],
    )
    for job in jobs:
        for episode, values in sorted((_get(job.metrics, "robustness") or {}).items()):
            if not isinstance(values, Mapping):
                continue
            mean, spread = values.get("rmse_mean", {}), values.get("rmse_std", {})
            table.rows.append(
                [job.choice("learner", "deep_edmd"), episode]
                + [
                    f"{mean.get(s, float('nan')):.4g} ({spread.get(s, float('nan')):.2g})"
                    for s in STATES
                ]
            )
    return table


def failures_table(jobs: list[Job]) -> Table:
    table = Table("Jobs that did not finish", ["job", "reason"])
    for job in jobs:
        if job.error:
            table.rows.append([job.name, job.error])
        elif job.metrics is None:
            table.rows.append([job.name, "no metrics.json (still running, killed, or crashed)"])
    return table


def report(sweep_dir: Path) -> Path:
    """Write the tables for ``sweep_dir``; return the Markdown file."""
    jobs = find_jobs(sweep_dir)
    if not jobs:
        raise ValueError(f"{sweep_dir} holds no Hydra job directories (.hydra/overrides.yaml)")
    finished = [j for j in jobs if j.metrics is not None and j.error is None]
    tables = {
        "prediction": prediction_table(finished),
        "prediction_window_41": prediction_table(finished, "rmse_window_41"),
        "prediction_window_10s": prediction_table(finished, "rmse_window_10s"),
        "tracking": tracking_table(finished),
        "robustness": robustness_table(finished),
        "training": training_table(finished),
        "failures": failures_table(jobs),
    }
    out = sweep_dir / "report"
    out.mkdir(exist_ok=True)
    sections = [
        f"# Sweep report: {sweep_dir}",
        "",
        f"{len(finished)} of {len(jobs)} jobs finished.",
        "",
    ]
    for name, table in tables.items():
        if not table.rows:
            continue
        sections.append(table.markdown())
        with (out / f"{name}.csv").open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(table.columns)
            writer.writerows(table.rows)
    markdown = out / "report.md"
    markdown.write_text("\n".join(sections))
    return markdown


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep_dir", type=Path)
    args = parser.parse_args(argv)
    try:
        path = report(args.sweep_dir)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(path.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
