"""The paper's figures from a sweep's runs: every learner on one plot, redrawn from their arrays.

Runs that differ only by learner (and its ``learner.*`` settings) and seed share a figure;
each learner is drawn from its lowest seed (the figures show one run each, the tables show the
spread over seeds):

- ``prediction_<episode>.png``: the measured test drive and every learner's open-loop
  prediction (from ``prediction_<episode>.npz``);
- ``tracking_<controller>_<reference>.png``: the reference and every Koopman learner's
  closed-loop run on the plant (from ``tracking_<controller>_<reference>.npz``);
- ``loss_curves.png``: training and validation loss of every trained network, one line per
  seed (from ``training_history.json``).

A group of jobs that differ in something else (a plant, a horizon) gets a suffix naming it.
"""

from __future__ import annotations

import json
import logging
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from harness.core.episode import SEDAN_INPUTS, Episode, InputChannel
from harness.evaluation.prediction import plot_prediction
from harness.evaluation.tracking import load_run, plot_tracking
from harness.output import load_arrays, save_figure
from harness.references.course import Course, plot_course
from harness.report.jobs import Run, common_overrides, variant

log = logging.getLogger(__name__)

_ACROSS = {"learner", "seed"}


def _groups(jobs: Iterable[Run]) -> dict[str, list[Run]]:
    """Runs by what they share besides learner and seed; the key is a filename suffix naming
    what differs within the sweep (empty when nothing does)."""
    jobs = list(jobs)
    common = common_overrides(jobs)
    groups: dict[str, list[Run]] = defaultdict(list)
    for job in jobs:
        groups[_suffix(variant(job, common, named=_describes_learner))].append(job)
    return dict(groups)


def _describes_learner(key: str) -> bool:
    """The learner, its settings (or model file) and the seed are drawn within one figure."""
    return key in _ACROSS or key.startswith("learner.") or key == "task.model_path"


def _suffix(text: str) -> str:
    safe = "".join(c if c.isalnum() or c in "-_.=" else "_" for c in text)
    return f"__{safe}" if safe else ""


def _lowest_seed_per_learner(jobs: Iterable[Run]) -> dict[str, Run]:
    chosen: dict[str, Run] = {}
    for job in sorted(jobs, key=lambda job: job.seed):
        chosen.setdefault(job.learner, job)
    return dict(sorted(chosen.items()))


def prediction_figures(jobs: list[Run], out: Path, subdir: str = "") -> list[Path]:
    """One figure per test episode (per group): the drive and every learner's prediction."""
    written = []
    for suffix, members in _groups(jobs).items():
        per_episode: dict[str, dict[str, object]] = defaultdict(dict)
        episodes: dict[str, Episode] = {}
        for learner, job in _lowest_seed_per_learner(members).items():
            for path in sorted((job.path / subdir).glob("prediction_*.npz")):
                name = path.stem.removeprefix("prediction_")
                try:
                    arrays = load_arrays(path)
                except ValueError as error:
                    log.warning("%s", error)
                    continue
                episodes.setdefault(
                    name,
                    Episode(
                        name,
                        arrays["time_s"],
                        arrays["states"],
                        arrays["inputs"],
                        arrays["poses"],
                        _channels(job),
                    ),
                )
                predicted = [k for k in arrays if k.startswith("predicted_")]
                if predicted:
                    per_episode[name][learner] = arrays[predicted[0]]
        for name, predictions in sorted(per_episode.items()):
            path = out / subdir / f"prediction_{name}{suffix}.png"
            written.append(plot_prediction(episodes[name], predictions, path))
    return written


def _channels(job: Run) -> tuple[InputChannel, ...]:
    """The inputs a job's data had (``data.inputs``; the sedan's where a job does not say)."""
    names = (job.metrics or {}).get("data", {}).get("inputs")
    if not names or tuple(names) == tuple(c.name for c in SEDAN_INPUTS):
        return SEDAN_INPUTS
    return tuple(InputChannel(str(n)) for n in names)


def tracking_figures(jobs: list[Run], out: Path, subdir: str = "") -> list[Path]:
    """One figure per controller and reference (per group): every learner's closed loop."""
    written = []
    for suffix, members in _groups(jobs).items():
        runs: dict[str, dict[str, object]] = defaultdict(dict)
        for learner, job in _lowest_seed_per_learner(members).items():
            for path in sorted((job.path / subdir).glob("tracking_*.npz")):
                try:
                    runs[path.stem][learner] = load_run(path)
                except ValueError as error:
                    log.warning("%s", error)
        for stem, by_learner in sorted(runs.items()):
            path = out / subdir / f"{stem}{suffix}.png"
            plot_tracking(by_learner, path)
            written.append(path)
    return written


def course_figures(jobs: list[Run], out: Path, subdir: str = "") -> list[Path]:
    """One top view per course reference (per group): every learner's and controller's path."""
    written = []
    for suffix, members in _groups(jobs).items():
        courses: dict[str, Course] = {}
        paths: dict[str, dict[str, np.ndarray]] = defaultdict(dict)
        for learner, job in _lowest_seed_per_learner(members).items():
            for course_file in sorted((job.path / subdir).glob("course_*.npz")):
                reference = course_file.stem.removeprefix("course_")
                try:
                    courses.setdefault(reference, Course.from_arrays(load_arrays(course_file)))
                    for run_file in sorted((job.path / subdir).glob(f"tracking_*_{reference}.npz")):
                        controller = run_file.stem.removeprefix("tracking_")
                        controller = controller.removesuffix(f"_{reference}")
                        paths[reference][f"{learner} {controller}"] = load_run(run_file).poses
                except (ValueError, KeyError) as error:
                    log.warning("%s: %s; left out of the course figure", course_file, error)
        for reference, course in sorted(courses.items()):
            path = out / subdir / f"course_{reference}{suffix}.png"
            plot_course(course, paths[reference], path, title=f"{reference}{suffix} (top view)")
            written.append(path)
    return written


def loss_figure(jobs: list[Run], out: Path) -> Path | None:
    """Loss curves of every trained network, a panel per learner, a colour per seed."""
    histories: dict[str, list[tuple[int, dict]]] = defaultdict(list)
    for suffix, members in _groups(jobs).items():
        for job in sorted(members, key=lambda job: job.seed):
            path = job.path / "training_history.json"
            if not path.exists():
                continue
            try:
                history = json.loads(path.read_text())
            except json.JSONDecodeError:
                log.warning("%s is not valid JSON; its loss curve is left out", path)
                continue
            label = job.learner
            if suffix:
                label += f" ({suffix.removeprefix('__')})"
            histories[label].append((job.seed, history))
    if not histories:
        return None
    fig = Figure(figsize=(8, 2.6 * len(histories)))
    axes = fig.subplots(len(histories), 1, squeeze=False, sharex=True)
    for ax, (label, runs) in zip(axes[:, 0], sorted(histories.items()), strict=True):
        for k, (seed, history) in enumerate(runs):
            steps = history["step"]
            validation = [v.get("loss") if v else None for v in history["validation"]]
            ax.semilogy(steps, history["train"], "--", color=f"C{k}", lw=0.9)
            ax.semilogy(steps, validation, color=f"C{k}", lw=1.2, label=f"seed {seed}")
        ax.set_title(f"{label}: validation (solid) and training (dashed) loss", fontsize=9)
        ax.set_ylabel("loss")
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("training step (batches)")
    fig.tight_layout()
    return save_figure(fig, out / "loss_curves.png")


def figures(jobs: list[Run], out: Path) -> list[Path]:
    """Every figure of the sweep's finished ``jobs`` into ``out``; returns the files written.

    Runs evaluated on other plants (``generalization/<plant>/``) get the same figures under
    ``out/generalization/<plant>/``.
    """
    subdirs = {""} | {
        str(path.relative_to(job.path))
        for job in jobs
        for path in (job.path / "generalization").glob("*")
        if path.is_dir()
    }
    written = []
    for subdir in sorted(subdirs):
        written += prediction_figures(jobs, out, subdir) + tracking_figures(jobs, out, subdir)
        written += course_figures(jobs, out, subdir)
    loss = loss_figure(jobs, out)
    return [*written, loss] if loss else written
