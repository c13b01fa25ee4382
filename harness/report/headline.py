"""The README's result tables, generated from committed studies (``results/<study>/``).

- ``headline`` (from ``lane_change_paper``): one row per learner (and persistence, the state
  held): its open-loop prediction of the held-out test drives (the whole drive and 3 s windows,
  mean over drives and seeds) and its 80 km/h ISO 3888 lane change on the dry and the wet road
  with the main job's controller and with the paper's, as seeds passed and the mean largest
  deviation from the centre line.
- ``main job`` (from ``main_job``): what ``python -m harness`` gives per learner and controller
  over seeds: the test drives open loop, the 80 km/h lane change, the test drive tracked, and
  the time of a control step; ``main job output``: what its seed-0 run printed at its end.
- ``logs`` (from ``ddk_carsim``, in docs/findings/authors_carsim.md): a study on driving logs, per
learner: each
  seed's mean over the test runs, then mean ± std over seeds, in 3 s and 1.5 s windows and over
  whole runs, a seed whose run diverged counted and not averaged.

All are queries of :func:`harness.report.load` anyone can rerun. A document (:data:`BLOCKS`
names which) holds each between its ``<!-- NAME: generated ... -->`` line and ``<!-- NAME end
-->``; :func:`update_readme` rewrites them (``python -m harness.report.studies`` does, after the
studies), and ``tests/test_studies.py`` fails when a committed block differs from its data.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from harness.core.files import write_text_atomic
from harness.evaluation.prediction import window_name
from harness.report.frame import frame, load, read_jobs
from harness.report.jobs import read_runs
from harness.report.summary import summary, title

__all__ = [
    "BLOCKS",
    "begin",
    "end",
    "headline",
    "logs",
    "main_job",
    "paper_model",
    "paper_reported",
    "replace_blocks",
    "update_readme",
]

MAIN = "de_mpc_path_long_offset_free"  # the main job's controller (conf/config.yaml)
MAIN_LEARNER = "deep_edmd"  # the main job's learner
MAIN_BASELINE = "bicycle_mpc_path_long_offset_free"  # the same on the single-track model
PAPER = "de_mpc"  # the paper's DE-MPC as written: 10/7, tracking the reference's states
PAPER_BASELINE = "bicycle_mpc"
LANE_CHANGE = "lane_change_80kph"  # experiment=lane_change's 80 km/h run
MAIN_LANE_CHANGE = "double_lane_change"  # the main job's (80 km/h)
DRY, WET = "sedan", "sedan_wet"
BASELINE = "single_track"  # the identified single-track model: the bar with persistence
STATES = ("vx", "vy", "yaw_rate")

# The paper's reported prediction RMSE (vx m/s, vy m/s, yaw rate rad/s) on its two CarSim test
# episodes (its Tables of the predicted states' RMSE, with and without the random layer): the
# bars of the paper-scale target. Its drives are its own; the comparison is of orders.
PAPER_REPORTED: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "EDMD": ((1.99, 0.36, 0.20), (1.42, 0.25, 0.66)),
    "ELM-EDMD": ((4.88, 0.55, 0.37), (5.61, 0.27, 0.44)),
    "DNN": ((1.78, 0.14, 0.08), (2.80, 0.16, 0.12)),
    "Deep EDMD": ((0.75, 0.04, 0.02), (1.15, 0.08, 0.05)),
    "Deep EDMD, random layer": ((0.4, 0.01, 0.01), (0.35, 0.05, 0.01)),
    "DNN, random layer": ((3.86, 0.01, 0.01), (15.56, 0.06, 0.04)),
}
# The paper's models as the code builds them: the learner's class (with EDMD's dictionary, which
# makes it ELM-EDMD), so that every preset of one, with our recipe or the paper's, is set beside
# the paper's numbers; a preset with the random layer on is the paper's random-layer model.
PAPER_MODELS: dict[tuple[str, str | None], str] = {
    ("learners.edmd.EDMD", "learners.dictionaries.ThinPlateRBF"): "EDMD",
    ("learners.edmd.EDMD", "learners.dictionaries.RandomFeatures"): "ELM-EDMD",
    ("learners.dnn.DNN", None): "DNN",
    ("learners.deep_edmd.DeepEDMD", None): "Deep EDMD",
}


def paper_model(learner: Any) -> str | None:
    """The paper's name for the model a job's ``learner`` config builds (its Tables' rows), None
    for a model that is not the paper's (ours, the baselines, a wrapped or extended one)."""
    target = OmegaConf.select(learner, "_target_", default=None)
    dictionary = OmegaConf.select(learner, "dictionary._target_", default=None)
    model = PAPER_MODELS.get((target, dictionary))
    if model is not None and OmegaConf.select(learner, "random_layer.enabled", default=False):
        model = f"{model}, random layer"
    return model


def paper_reported(model: str | None) -> str:
    """The paper's own whole-drive RMSE for ``model`` (:func:`paper_model`), the mean of its two
    test episodes as our cells are of ours; "—" for a model that is not the paper's."""
    if model is None:
        return "—"
    first, second = PAPER_REPORTED[model]
    return " / ".join(_number((a + b) / 2) for a, b in zip(first, second, strict=True))


def headline(study: Path) -> str:
    """The headline table of ``study`` (see the module docstring), with its source line."""
    read = read_jobs(study)
    runs = frame(read)
    jobs = runs.drop_duplicates("job")
    learners = sorted(set(jobs.learner) - {"persistence"}, key=_order)
    models = {
        run.learner: paper_model(OmegaConf.select(run.config, "learner"))
        for run in read
        if run.config is not None
    }
    lines = [
        "| learner | jobs | whole test drive: vx / vy / r | the paper's, its model | "
        "3 s windows: vx / vy / r | "
        f"lane change 80 km/h, {MAIN} (60/50): dry / wet | {PAPER} (10/7): dry / wet |",
        "|---|---|---|---|---|---|---|",
    ]
    for learner in learners:
        own = jobs[jobs.learner == learner]
        closed = runs[(runs.learner == learner) & (runs.reference == LANE_CHANGE)]
        whole, windows = _prediction(own, "rmse"), _prediction(own, "rmse_window_3s")
        paper = paper_reported(models.get(learner))
        lines.append(
            f"| {_name(learner)} | {_jobs(own)} | {whole} | {paper} | {windows} | "
            f"{_lane(closed, MAIN, DRY)} / {_lane(closed, MAIN, WET)} | "
            f"{_lane(closed, PAPER, DRY)} / {_lane(closed, PAPER, WET)} |"
        )
    lines.append(
        f"| persistence (the state held) | — | {_prediction(jobs, 'rmse', held=True)} | — | "
        f"{_prediction(jobs, 'rmse_window_3s', held=True)} | — | — |"
    )
    return "\n".join(lines) + (
        f"\n\nRMSE in m/s, m/s, rad/s: mean over the test drives and seeds {_seeds(jobs)}; "
        "the paper's: its Table for the same model, mean of its two test episodes (CarSim, its "
        "own drives); "
        "jobs: finished of those the study's sweeps launched (the rest are named in its "
        "report); a lane-change cell is the seeds that passed (reached the exit, no cone hit) of "
        "those run, and their mean largest deviation from the centre line. "
        f"{_worse_note(lines)}From [results/{study.name}](docs/results/{study.name}.md)."
    )


def main_job(study: Path) -> str:
    """The main job's table of ``study``: per learner and controller over its seeds."""
    runs = load(study)
    jobs = runs.drop_duplicates("job")
    lines = [
        "| model | controller | test drives open loop: vx / vy / r | lane change 80 km/h | "
        "test drive tracked: vx / vy / r | step ms: median / p99 |",
        "|---|---|---|---|---|---|",
    ]
    for learner in sorted(set(jobs.learner)):
        own = runs[runs.learner == learner]
        for controller in (MAIN, PAPER):
            lines.append(_main_row(learner, own, controller, jobs[jobs.learner == learner]))
    # The baselines are fitted on the same drives whatever the learner: one row each, from the
    # main learner's jobs where the study has them (another learner added leaves the row as is).
    learners = sorted(set(jobs.learner))
    first = runs[runs.learner == (MAIN_LEARNER if MAIN_LEARNER in learners else learners[0])]
    for controller in (MAIN_BASELINE, PAPER_BASELINE):
        lines.append(_main_row(f"{BASELINE} (the physics baseline)", first, controller, None))
    lines.append(
        f"| persistence (the state held) | — | {_prediction(jobs, 'rmse', held=True)} | — | — | — |"
    )
    return "\n".join(lines) + (
        f"\n\nMean over seeds {_seeds(jobs)} (RMSE in m/s, m/s, rad/s); the lane change as seeds "
        "passed (reached the exit, no cone hit) and mean largest deviation from the centre line; "
        "a step is the whole control step (preparation and feedback). "
        f"{_worse_note(lines)}From [results/{study.name}](docs/results/{study.name}.md)."
    )


def _main_row(name: str, runs: pd.DataFrame, controller: str, jobs: pd.DataFrame | None) -> str:
    mine = runs[runs.controller == controller]
    lane = mine[mine.reference == MAIN_LANE_CHANGE]
    tracked = mine[mine.reference.astype(str).str.startswith("test_episode/")]
    first_drive = tracked[tracked.reference == tracked.reference.min()] if len(tracked) else tracked
    open_loop = _prediction(jobs, "rmse") if jobs is not None else "—"
    rmse = " / ".join(_number(float(first_drive[f"rmse.{s}"].mean())) for s in STATES)
    steps = " / ".join(_number(float(mine[f"step_time_ms.{q}"].mean())) for q in ("median", "p99"))
    return (
        f"| {name} | {controller} | {open_loop} | {_lane(lane, controller, DRY)} | "
        f"{rmse if len(first_drive) else '—'} | {steps if len(mine) else '—'} |"
    )


def main_job_output(study: Path) -> str:
    """What the main job printed at its end, for its default learner and seed 0: the summary
    of that job's ``metrics.json`` (``harness/report/summary.py``, as the run prints it)."""
    run = next(
        (r for r in read_runs(study) if r.learner == MAIN_LEARNER and r.seed == 0 and r.metrics),
        None,
    )
    if run is None or run.metrics is None:
        raise ValueError(f"{study} holds no finished {MAIN_LEARNER} job of seed 0")
    return f"```\n{summary(run.metrics, title(run.learner, run.seed, run.plant))}\n```"


WORSE = "†"  # a state's RMSE not below persistence's on some drive (``beats_persistence``)
LOGS_WINDOWS = (("rmse_window_3s", "3 s windows"), ("rmse_window_1.5s", "1.5 s windows"))


def logs(study: Path) -> str:
    """The summary of a study on driving logs: per learner and variant (persistence and the
    baseline first; a variant is the overrides its jobs add), each seed's mean over the test
    runs, then mean ± std over seeds; a seed with a diverged run is counted, not averaged. One
    table per measure, and the mean fit time."""
    runs = load(study)
    jobs = runs[runs["data.split.test"].apply(lambda v: isinstance(v, list))]
    jobs = jobs.drop_duplicates("job")
    rows = sorted(
        set(zip(jobs.learner, jobs.variant, strict=True)),
        key=lambda row: (row[0] != "persistence", *_order(row[0]), row[1] != "—", row[1]),
    )
    tables = []
    for metric, label in (*LOGS_WINDOWS, ("rmse", "whole runs")):
        lines = [
            f"**{label}** (`prediction.<run>.{metric}`)",
            "",
            "| learner | seeds | vx (m/s) | vy (m/s) | yaw rate (rad/s) | fit (s) |",
            "|---|---|---|---|---|---|",
        ]
        for learner, variant in rows:
            own = jobs[(jobs.learner == learner) & (jobs.variant == variant)]
            per_seed, diverged = [], 0
            for _, job in own.iterrows():
                episodes = job["data.split.test"]
                if any(job.get(f"prediction.{e}.diverged") is True for e in episodes) and (
                    metric == "rmse"
                ):
                    diverged += 1
                    continue
                per_seed.append(
                    [
                        sum(float(job[f"prediction.{e}.{metric}.{s}"]) for e in episodes)
                        / len(episodes)
                        for s in STATES
                    ]
                )
            cells = [
                _spread([row[i] for row in per_seed], diverged, len(own))
                + _worse_runs(own, metric, state)
                for i, state in enumerate(STATES)
            ]
            fit = own["training.fit_time_s"].astype(float).mean()
            name = learner if variant == "—" else f"{learner} ({variant})"
            lines.append(f"| {name} | {len(own)} | {' | '.join(cells)} | {fit:.0f} |")
        tables.append("\n".join(lines))
    return "\n\n".join(tables) + (
        f"\n\nRMSE per seed: the mean over the test runs; then mean ± std (n − 1) over seeds "
        f"{_seeds(jobs)}; fit: the fit alone, mean over seeds. From "
        f"[results/{study.name}](../results/{study.name}.md)."
    )


def _worse_runs(jobs: pd.DataFrame, metric: str, state: str) -> str:
    """`` (worse than persistence on k of n runs)``: the test runs, over every seed, whose
    verdict (``beats_persistence``) says the RMSE is not below the state held; empty where none
    says so (or the jobs predate the verdict)."""
    window = window_name(metric)
    worse = total = 0
    for _, job in jobs.iterrows():
        for episode in job["data.split.test"]:
            total += 1
            verdict = job.get(f"prediction.{episode}.beats_persistence.{window}.{state}")
            worse += isinstance(verdict, bool | np.bool_) and not verdict  # a frame's bool
    return f" (worse than persistence on {worse} of {total} runs)" if worse else ""


def _spread(values: list[float], diverged: int, seeds: int) -> str:
    """``mean ± std`` over seeds (no ± for one value or none to speak of), and how many of the
    seeds diverged."""
    if not values:
        return f"diverged ({diverged} of {seeds} seeds)"
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / max(len(values) - 1, 1))
    # Seeds that give the same model (no randomness) differ by the order of a float sum only.
    cell = f"{_number(mean)} ± {std:.2g}" if std > 1e-12 * abs(mean) else _number(mean)
    return cell + (f" ({diverged} of {seeds} seeds diverged)" if diverged else "")


# name: (study, how its block is made, the document that holds it, from the repository root)
Block = tuple[str, Callable[[Path], str], str]

BLOCKS: dict[str, Block] = {
    "headline": ("lane_change_paper", headline, "README.md"),
    "main job": ("main_job", main_job, "README.md"),
    "main job output": ("main_job", main_job_output, "docs/guide/main_job.md"),
    "logs": ("ddk_carsim", logs, "docs/findings/authors_carsim.md"),
}


def begin(name: str, study: str) -> str:
    return f"<!-- {name}: generated by python -m harness.report.studies from results/{study}/ -->"


def end(name: str) -> str:
    return f"<!-- {name} end -->"


def update_readme(readme: Path, results: Path) -> bool:
    """Rewrite every generated block of ``readme`` from its study under ``results``; whether
    anything changed.

    Raises:
        ValueError: (one line) when ``readme`` has no block to rewrite.
    """
    text = readme.read_text()
    new = replace_blocks(text, results)
    if new != text:
        write_text_atomic(readme, new)
    return new != text


def replace_blocks(text: str, results: Path) -> str:
    """``text`` with each block of :data:`BLOCKS` it holds regenerated from its study."""
    found = False
    for name, (study, make, _) in BLOCKS.items():
        pattern = re.compile(
            re.escape(begin(name, study)) + r"\n.*?" + re.escape(end(name)), re.DOTALL
        )
        match = pattern.search(text)
        if match is not None:
            found = True
            block = f"{begin(name, study)}\n{make(results / study)}\n{end(name)}"
            text = text[: match.start()] + block + text[match.end() :]
    if not found:
        raise ValueError(f"no generated block ({', '.join(BLOCKS)}) to rewrite")
    return text


def _order(learner: str) -> tuple[int, str]:
    """The baseline first, then the learners by name."""
    return (0 if learner == BASELINE else 1, learner)


def _name(learner: str) -> str:
    return f"{learner} (the physics baseline)" if learner == BASELINE else learner


def _prediction(jobs: pd.DataFrame, metric: str, held: bool = False) -> str:
    """``vx / vy / r`` of ``metric`` over every job's test drives (persistence's: ``held``);
    a rollout that diverged is counted, not averaged."""
    values: dict[str, list[float]] = {state: [] for state in STATES}
    worse: set[str] = set()
    diverged = total = 0
    for _, job in jobs.iterrows():
        episodes = job.get("data.split.test")
        for episode in episodes if isinstance(episodes, list) else []:
            prefix = f"prediction.{'persistence.' if held else ''}{episode}"
            if _value(job, f"{prefix}.{metric}.vx") is None:
                continue
            total += 1
            for state in STATES:  # the verdict against the state held (jobs that have it)
                verdict = job.get(f"{prefix}.beats_persistence.{window_name(metric)}.{state}")
                if isinstance(verdict, bool | np.bool_) and not verdict:
                    worse.add(state)
            if metric == "rmse" and job.get(f"{prefix}.diverged") is True:
                diverged += 1
                continue
            for state in STATES:
                values[state].append(float(job[f"{prefix}.{metric}.{state}"]))
        if held and total:  # the state held is the same in every job of the same drives
            break
    if not values["vx"]:
        return f"diverged ({diverged} of {total})" if total else "not finished"
    cells = " / ".join(
        _number(sum(v) / len(v)) + (WORSE if state in worse else "") for state, v in values.items()
    )
    return cells + (f" ({diverged} of {total} diverged)" if diverged else "")


def _worse_note(lines: list[str]) -> str:
    """The footnote of the mark, where a table has one."""
    if not any(WORSE in line for line in lines):
        return ""
    return f"{WORSE}: not better than persistence (the state held) on at least one test drive. "


def _jobs(jobs: pd.DataFrame) -> str:
    """``finished of launched``: a job without metrics (failed, killed, never started) counts
    only in the second."""
    finished = int(jobs["data.split.test"].apply(lambda v: isinstance(v, list)).sum())
    return f"{finished} of {len(jobs)}"


def _lane(closed: pd.DataFrame, controller: str, plant: str) -> str:
    """``passed/jobs, deviation m`` of ``controller``'s lane change on ``plant``."""
    rows = closed[(closed.controller == controller) & (closed.plant == plant)]
    if rows.empty:
        return "—"
    passed = int(rows["path.passed"].fillna(False).astype(bool).sum())
    deviation = rows["path.max_lateral_deviation_m"].astype(float)
    return f"{passed}/{len(rows)}, {_number(float(deviation.mean()))} m"


def _value(job: pd.Series, key: str) -> float | None:
    value = job.get(key)
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return float(value)


def _number(value: float) -> str:
    """Three significant digits."""
    return f"{value:.3g}"


def _seeds(jobs: pd.DataFrame) -> str:
    seeds: list[int] = sorted(int(s) for s in jobs.seed.dropna().unique())
    return f"{seeds[0]}–{seeds[-1]}" if len(seeds) > 1 else str(seeds[0]) if seeds else "—"
