"""``python -m harness.report SWEEP_DIR``: the paper's tables and figures from a sweep.

Every job directory of a Hydra multirun (one with ``.hydra/overrides.yaml``) is read; its
overrides name the row (learner, controller, plant, seed, and a ``variant`` for any other
override that changes numbers). Numbers are mean ± std over the jobs that differ only by seed.
Writes ``report.md``, one CSV per table and the figures (``harness/report_figures.py``) into
``SWEEP_DIR/report/``; failed jobs (an ``error.json``) and unfinished ones (no
``metrics.json``) are listed by name, never dropped silently. Every sweep runs it at its end
(:class:`WriteReport`, a Hydra callback); rerun it by hand on a sweep still in progress.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import sys
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

STATES = ("vx", "vy", "yaw_rate")
log = logging.getLogger(__name__)


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
# Overrides that change where or how a job runs, never its numbers: no row of their own.
NEUTRAL = {
    "recorder",
    "data.root",
    "data.workers",
    "learner.training.progress",
    "learner.training.num_threads",
}


def variant(
    job: Job, common: Mapping[str, str], named: Callable[[str], bool] = _NAMED.__contains__
) -> str:
    """The job's overrides that differ within the sweep, besides the ``named`` ones (which
    name a row or a line of their own) and those that never change a number."""
    return ",".join(
        f"{k}={v}"
        for k, v in sorted(job.overrides.items())
        if not named(k) and k not in NEUTRAL and not k.startswith("hydra") and common.get(k) != v
    )


def common_overrides(jobs: Iterable[Job]) -> dict[str, str]:
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
    common = common_overrides(jobs)
    groups: dict[tuple[str, ...], list[Job]] = defaultdict(list)
    for job in jobs:
        key = (*(job.choice(k, default) for k, default in keys), variant(job, common))
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


def _tracking_runs(
    tracking: Mapping[str, Any], controller: str
) -> Iterable[tuple[str, str, dict[str, Any]]]:
    """(controller, reference, metrics) of every closed-loop run of a ``tracking`` section,
    first controller first; older sections without ``controllers`` are ``controller``'s."""
    by_controller = tracking.get("controllers")
    if not by_controller:
        references = tracking.get("references") or (
            {tracking.get("reference", "test_episode"): tracking} if "rmse" in tracking else {}
        )
        by_controller = {controller: references}
    for controller, runs in by_controller.items():
        for label, metrics in runs.items():
            if isinstance(metrics, Mapping) and "rmse" in metrics:
                yield controller, label.split("/", 1)[0], metrics


def tracking_table(jobs: list[Job]) -> Table:
    table = Table(
        "DE-MPC tracking RMSE on the plant (SI) and solve time of one control step (ms)",
        [
            "learner",
            "controller",
            "Np/Nc",
            "reference",
            "variant",
            "jobs",
            *STATES,
            "solve median",
            "solve p99",
            "solve max",
            "deadline misses",
            "solver failures",
        ],
    )
    common = common_overrides(jobs)
    runs: dict[tuple[str, ...], list[dict[str, Any]]] = defaultdict(list)
    for job in jobs:
        tracking = _get(job.metrics, "tracking") or {}
        for controller, reference, metrics in _tracking_runs(
            tracking, job.choice("controller", "de_mpc")
        ):
            horizon = metrics.get("horizon") or {}
            key = (
                job.choice("learner", "deep_edmd"),
                controller,
                f"{horizon.get('Np', '?')}/{horizon.get('Nc', '?')}",
                reference,
                variant(job, common) or "—",
            )
            runs[key].append(metrics)
    order = {"test_episode": 0}
    for key, members in sorted(
        runs.items(), key=lambda kv: (kv[0][0], kv[0][1], order.get(kv[0][3], 1), kv[0][3:])
    ):
        table.rows.append(
            [*key, str(len(members))]
            + [_mean_std(_get(m, "rmse", s) for m in members) for s in STATES]
            + [
                _mean_std(_get(m, "solve_time_ms", q) for m in members)
                for q in ("median", "p99", "max")
            ]
            + [_mean_std(m.get(k) for m in members) for k in ("deadline_misses", "solver_failures")]
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
        "Random-layer robustness: RMSE over 100 predictions with the layer redrawn, mean "
        "(spread) per job, then mean ± std over jobs",
        ["learner", "variant", "test episode", "jobs", *STATES],
    )
    for (learner, variant), members in _group(jobs, ("learner", "deep_edmd")).items():
        episodes = sorted({e for j in members for e in (_get(j.metrics, "robustness") or {})})
        for episode in episodes:
            values = [_get(j.metrics, "robustness", episode) for j in members]
            present = [v for v in values if isinstance(v, Mapping)]
            table.rows.append(
                [learner, variant or "—", episode, str(len(present))]
                + [
                    f"{_mean_std(_get(v, 'rmse_mean', s) for v in present)} "
                    f"({_mean_std(_get(v, 'rmse_std', s) for v in present)})"
                    for s in STATES
                ]
            )
    return table


def _mean_prediction(section: Mapping[str, Any], state: str) -> float | None:
    """Open-loop RMSE of one state averaged over a section's test episodes."""
    per_episode = [_get(v, "rmse", state) for v in (section.get("prediction") or {}).values()]
    numbers = [v for v in per_episode if v is not None]
    return sum(numbers) / len(numbers) if numbers else None


def _first_controller_run(section: Mapping[str, Any], reference: str) -> dict[str, Any] | None:
    """The first controller's run of ``reference`` (``test_episode`` matches its episode)."""
    runs = _tracking_runs(section.get("tracking") or {}, "")
    return next((metrics for _, name, metrics in runs if name == reference), None)


def generalization_table(jobs: list[Job]) -> Table:
    """Each model on its own plant and on the others (``experiment=generalization``).

    The test drives are driven again on each plant (the driver adapts to its grip), so their
    columns compare a model with the drives each plant produces; the double lane change is the
    same reference on every plant.
    """
    table = Table(
        "Generalization: trained on one plant, evaluated on others — open-loop prediction RMSE "
        "(mean over the test drives, driven again on each plant) and DE-MPC tracking RMSE of the "
        "first test drive and of the double lane change (the same reference on every plant; SI)",
        ["learner", "trained on", "evaluated on", "variant", "jobs"]
        + [f"prediction {s}" for s in STATES]
        + [f"tracking test drive {s}" for s in STATES]
        + [f"tracking lane change {s}" for s in STATES],
    )
    evaluated = [j for j in jobs if _get(j.metrics, "generalization")]
    for (learner, plant, variant), members in _group(
        evaluated, ("learner", "deep_edmd"), ("plant", "sedan")
    ).items():
        targets = {plant: [(j.metrics or {}) for j in members]}
        for job in members:
            for other, section in (_get(job.metrics, "generalization") or {}).items():
                targets.setdefault(other, []).append(section)
        for target, sections in targets.items():
            runs = {
                reference: [_first_controller_run(s, reference) for s in sections]
                for reference in ("test_episode", "double_lane_change")
            }
            table.rows.append(
                [learner, plant, target, variant or "—", str(len(sections))]
                + [_mean_std(_mean_prediction(s, state) for s in sections) for state in STATES]
                + [
                    _mean_std(_get(run, "rmse", state) for run in runs[reference])
                    for reference in ("test_episode", "double_lane_change")
                    for state in STATES
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
        "generalization": generalization_table(finished),
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
    from harness.report_figures import figures  # it builds on this module's Job

    written = figures(finished, out)
    if written:
        sections += ["### Figures", ""]
        sections += [f"![{p.stem}]({p.relative_to(out).as_posix()})" for p in written]
        sections.append("")
    markdown = out / "report.md"
    markdown.write_text("\n".join(sections))
    return markdown


class WriteReport(Callback):
    """Every sweep ends with its report (``hydra.callbacks.report`` in ``conf/config.yaml``)."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            log.info("sweep report: %s", report(sweep_dir))
        except Exception as error:  # the jobs' results stand; the report can be rerun by hand
            log.error("no report (%s); run: python -m harness.report %s", error, sweep_dir)


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
