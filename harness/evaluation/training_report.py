"""Fitting a learner inside a run: checkpoints in the run directory, then its loss curves reported.

Learners take data only (``learner.fit(train, validation, normalizer)``); what a run keeps of
their training is the caller's, here: ``training_history.json`` (what a sweep's report plots),
the curves in the recording (``training/<learner>``, on the ``step`` timeline) and the paper's
loss figure ``<learner>_loss.png``. Learners that train iteratively
(:class:`~learners.trained.TrainedLearner`) checkpoint into the run directory, so a killed run
started again with the same directory resumes.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from harness.core.contracts import RunLearner
from harness.core.episode import Episode, MinMaxNormalizer
from harness.core.files import write_json_atomic
from harness.output import save_figure
from harness.recorder import Recorder
from learners.trained import TrainedLearner
from learners.training import History

__all__ = ["fit", "plot_loss_curves", "record_loss_curves"]


def fit(
    learner: RunLearner,
    train: Sequence[Episode],
    validation: Sequence[Episode],
    normalizer: MinMaxNormalizer,
    *,
    recorder: Recorder,
    output_dir: Path,
) -> RunLearner:
    """Fit ``learner`` (resuming from ``output_dir``); leave its loss curves in the run."""
    trained = learner.core  # a wrapper's inner learner trains and has the curves
    if isinstance(trained, TrainedLearner):
        trained.checkpoint_dir = output_dir
    learner = learner.fit(train, validation, normalizer)
    if isinstance(trained, TrainedLearner) and trained.history_.step:
        history = trained.history_
        write_json_atomic(output_dir / "training_history.json", history.to_dict())
        record_loss_curves(recorder, trained.name, history)
        plot_loss_curves(history, output_dir / f"{trained.name}_loss.png", title=trained.name)
    return learner


def record_loss_curves(recorder: Recorder, name: str, history: History) -> None:
    """``training/<name>/{train, validation, validation_<term>}`` per training step."""
    steps = np.asarray(history.step, dtype=np.int64)
    values = {"train": np.asarray(history.train, dtype=float)}
    keys = sorted({k for v in history.validation for k in v})
    for key in keys:
        label = "validation" if key == "loss" else f"validation_{key}"
        values[label] = np.array([v.get(key, np.nan) for v in history.validation])
    recorder.series(f"training/{name}", steps, values, timeline="step")


def plot_loss_curves(history: History, path: Path, title: str = "") -> Path:
    """Training (solid) and validation (dashed) loss per batch, log scale, as in the paper."""
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    ax.plot(history.step, history.train, "-", color="C0", label="training loss")
    if any(history.validation):
        ax.plot(
            history.step,
            [v.get("loss", np.nan) for v in history.validation],
            "--",
            color="C0",
            label="validation loss",
        )
        terms = sorted({k for v in history.validation for k in v} - {"loss"})
        for i, key in enumerate(terms, start=1):
            ax.plot(
                history.step,
                [v.get(key, np.nan) for v in history.validation],
                "--",
                color=f"C{i}",
                lw=0.8,
                label=f"validation {key}",
            )
    ax.set_yscale("log")
    ax.set_xlabel("batches")
    ax.set_ylabel("loss (normalized units)")
    ax.set_title(f"{title} ({history.stopped})" if history.stopped else title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, path, dpi=120)
