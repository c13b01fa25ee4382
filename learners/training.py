"""Mini-batch training shared by the DNN and Deep EDMD: Adam, early stopping, checkpoints.

What the loop guarantees:

- **Deterministic on CPU for a seed.** Initial weights come from ``seed``; the windows of epoch
  e from ``numpy.random.default_rng([seed, e])``; the random layer of step s from
  ``torch.Generator().manual_seed(seed * 1_000_003 + s)``. Nothing depends on global RNG state.
- **Resumable.** Every ``checkpoint_every_steps`` the parameters, Adam's state, the position in
  the epoch and the early-stopping state go to the checkpoint file (atomically). A new
  ``fit`` with the same hyperparameters and data continues from it and ends exactly where an
  uninterrupted run ends; ``max_steps``, ``max_epochs``, ``patience`` may be raised to extend a
  finished run. Other data or hyperparameters refuse the checkpoint in one line (it may be
  another run's: it is left alone). The file ends with a SHA-256 of its content; a checkpoint
  that is truncated, altered or unreadable is damaged: a one-line warning names it, it is
  moved aside to ``<name>.ckpt.damaged`` and training starts afresh (a damaged file cannot be
  resumed from, and the run it belongs to is this one).
- **Never a silent NaN model.** A non-finite loss stops training with a one-line RuntimeError.
- **Early stopping** every ``eval_every_steps`` on what ``selection`` names: the validation
  windows' loss (``window_loss``, the paper's) or the open-loop rollout of the whole validation
  drives, scored in physical units (``rollout``, what the tables and the controller use; the
  learner supplies the score). The returned model is the best one seen by that measure (the
  last one when there is no validation data); the window loss stays in the history either way.
- **Schedules are functions of the step**, so a resumed run sees the same ones: the learning
  rate (``lr_schedule``: constant, or linear warm-up then cosine decay to ``lr_final``), the
  window length (``curriculum``: [[p, steps], ...] phases before the learner's own p), and the
  noise drawn onto each window's initial state (``initial_state_noise``, from
  ``numpy.random.default_rng([seed, step, 1])``).
- **Averaged weights, where asked** (``average_decay``): an exponential moving average of the
  parameters over the batches (Polyak averaging) is what is validated, kept and returned; Adam
  steps the raw parameters, and both are in the checkpoint.

The loss curves (:class:`History`) are returned, not drawn: figures and recordings are the
caller's (``harness/evaluation/training_report.py``).
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import io
import json
import logging
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from tqdm import tqdm

from harness.core.checks import (
    boolean,
    choice,
    integer,
    is_number,
    non_negative,
    positive,
    require,
)
from harness.core.files import write_atomic
from learners.nets import FlatParameters
from learners.settings import block
from learners.windows import WindowData

__all__ = [
    "RUN_SETTINGS",
    "History",
    "Objective",
    "RandomLayerConfig",
    "TrainingConfig",
    "batch_mean_terms",
    "block",
    "train",
]

VALIDATION_CHUNK = 1024  # windows per validation forward pass
SELECTIONS = ("window_loss", "rollout")  # what early stopping and the kept checkpoint go by
LR_SCHEDULES = ("constant", "cosine")
# A batch's fixed cost (gather, optimizer step, encoder) in window steps: Deep EDMD at batch 64
# took 4.3 ms at p = 10 and 22 ms at p = 100 (Intel Xeon, one thread), a + b p with a / b = 12.
BATCH_FIXED_STEPS = 10
_BAR = "{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}{postfix}"
ROLLOUT_SCORE = "rollout_score"  # the key of the rollout measure in History.validation
# A checkpoint is torch.save's bytes, then this marker, the hex SHA-256 of those bytes and "\n".
_CHECKSUM_MARKER = b"\nkoopman-harness checkpoint sha256 "
_TRAILER_BYTES = len(_CHECKSUM_MARKER) + 64 + 1

log = logging.getLogger(__name__)


# The mark of a training setting that says how long or how a model was trained, not which model
# it is (RUN_SETTINGS).
_RUN = {"run": True}


@dataclass(frozen=True)
class TrainingConfig:
    """Optimizer and budget of a trained learner: the schema of ``learner.training``.

    Paper values: Adam, lr 1e-4, batch 64, ~1e5 batches, and (the defaults here) a constant
    rate, no clipping, no curriculum, no noise, checkpoints chosen by the window loss.
    ``max_epochs`` None means no epoch limit; at least one of ``max_steps`` / ``max_epochs``
    must be set. ``num_threads`` None trains on the threads in force (the job's ``threads``,
    ``harness/core/threads.py``); a number sets PyTorch's intra-op threads for training alone.

    Ours (not in the paper): ``selection: rollout`` keeps the checkpoint whose open-loop
    rollout of the validation drives has the lowest mean over drives and states of
    RMSE / ``rollout_scales`` (physical units: m/s, m/s, rad/s for vx, vy, r); ``lr_schedule:
    cosine`` warms up linearly over ``warmup_steps`` and decays to ``lr_final`` at ``max_steps``;
    ``grad_clip_norm`` clips the gradient's 2-norm; ``curriculum`` trains on shorter windows
    first (checkpoints are chosen, and patience counted, only after it);
    ``initial_state_noise`` (normalized units) perturbs each window's first state;
    ``average_decay`` (None: off) validates, keeps and returns the exponential moving average
    of the weights, a ← d·a + (1 − d)·w after every batch, instead of the weights themselves:
    the average of the last ~1/(1 − d) batches is a model the optimizer's noise moves less.
    """

    batch_size: int = 64
    lr: float = 1e-4  # Adam's, constant (the paper's)
    max_steps: int | None = field(default=100_000, metadata=_RUN)  # the paper trains ~1e5 batches
    max_epochs: int | None = field(default=None, metadata=_RUN)
    # Validations without improvement before early stopping.
    patience: int = field(default=20, metadata=_RUN)
    eval_every_steps: int = 1000
    checkpoint_every_steps: int = field(default=1000, metadata=_RUN)
    seed: int = 0
    # null: the job's threads (conf/config.yaml: 1); a number: for training alone.
    num_threads: int | None = field(default=None, metadata=_RUN)
    progress: bool = field(default=True, metadata=_RUN)
    # window_loss (the paper's) | rollout: checkpoint by whole-drive validation rollouts (ours).
    selection: str = "window_loss"
    # m/s, m/s, rad/s: what an RMSE of vx, vy, r counts in the rollout score.
    rollout_scales: Sequence[float] = (1.0, 0.1, 0.05)
    # constant (the paper's) | cosine: linear warm-up, then cosine decay to lr_final (ours).
    lr_schedule: str = "constant"
    warmup_steps: int = 0
    lr_final: float = 0.0
    grad_clip_norm: float | None = None  # clip the gradient's 2-norm (null: no clipping, the paper)
    # [[p, batches], ...]: shorter windows first, then learner.horizon (null: none, the paper).
    curriculum: Sequence[Sequence[int]] | None = None
    initial_state_noise: float = 0.0  # std (normalized units) added to each window's first state
    # Ours, off: validate, keep, return the weights' moving average (d per batch); no gain on
    # data=default (docs/findings/training_recipe.md).
    average_decay: float | None = None

    def __post_init__(self) -> None:
        key = "learner.training."
        integer(key + "batch_size", self.batch_size, 1)
        positive(key + "lr", self.lr)
        if self.max_steps is not None:
            integer(key + "max_steps", self.max_steps, 1)
        if self.max_epochs is not None:
            integer(key + "max_epochs", self.max_epochs, 1)
        require(
            self.max_steps is not None or self.max_epochs is not None,
            key + "max_steps",
            "set when training.max_epochs is null",
            self.max_steps,
        )
        integer(key + "patience", self.patience, 1)
        integer(key + "eval_every_steps", self.eval_every_steps, 1)
        integer(key + "checkpoint_every_steps", self.checkpoint_every_steps, 1)
        integer(key + "seed", self.seed, 0)
        if self.num_threads is not None:
            integer(key + "num_threads", self.num_threads, 1)
        boolean(key + "progress", self.progress)
        choice(key + "selection", self.selection, SELECTIONS)
        scales = self.rollout_scales
        require(
            isinstance(scales, Sequence) and not isinstance(scales, str) and len(scales) > 0,
            key + "rollout_scales",
            "a list of positive numbers, one per state",
            scales,
        )
        for scale in scales:
            positive(key + "rollout_scales", scale)
        object.__setattr__(self, "rollout_scales", tuple(float(x) for x in scales))
        choice(key + "lr_schedule", self.lr_schedule, LR_SCHEDULES)
        integer(key + "warmup_steps", self.warmup_steps, 0)
        non_negative(key + "lr_final", self.lr_final)
        require(
            self.lr_schedule == "constant" or self.max_steps is not None,
            key + "max_steps",
            "set when training.lr_schedule is cosine (the decay ends there)",
            self.max_steps,
        )
        if self.grad_clip_norm is not None:
            positive(key + "grad_clip_norm", self.grad_clip_norm)
        non_negative(key + "initial_state_noise", self.initial_state_noise)
        if self.average_decay is not None:
            require(
                is_number(self.average_decay) and 0.0 < self.average_decay < 1.0,
                key + "average_decay",
                "a number in (0, 1), e.g. 0.99 for an average over about 100 batches, or null",
                self.average_decay,
            )
        if self.curriculum is not None:
            phases = []
            for phase in self.curriculum:
                require(
                    isinstance(phase, Sequence) and not isinstance(phase, str) and len(phase) == 2,
                    key + "curriculum",
                    "a list of [p, steps] pairs",
                    self.curriculum,
                )
                phases.append(
                    (
                        integer(key + "curriculum p", phase[0], 1),
                        integer(key + "curriculum steps", phase[1], 1),
                    )
                )
            object.__setattr__(self, "curriculum", tuple(phases))

    def lr_at(self, step: int) -> float:
        """The learning rate of training step ``step`` (0-based)."""
        if self.lr_schedule == "constant":
            return self.lr
        if step < self.warmup_steps:
            return self.lr * (step + 1) / self.warmup_steps
        assert self.max_steps is not None  # checked in __post_init__
        span = max(1, self.max_steps - self.warmup_steps)
        progress = min(1.0, (step - self.warmup_steps) / span)
        return self.lr_final + 0.5 * (self.lr - self.lr_final) * (
            1.0 + math.cos(math.pi * progress)
        )

    @property
    def curriculum_steps(self) -> int:
        """Training steps on the curriculum's shorter windows. Checkpoints are chosen, and
        patience counted, only after them: a model trained on short windows so far is no
        candidate for long rollouts (the main job's Deep EDMD kept a step-500 checkpoint by a
        lucky validation rollout and stopped at step 2500 before this rule)."""
        return sum(steps for _, steps in self.curriculum or ())

    def work_until(self, step: int, horizon: int) -> int:
        """The cost of training steps 0 .. step-1 in window steps, a batch counted as its window
        plus ``BATCH_FIXED_STEPS``: what the progress bar counts, so that its estimate holds
        across the curriculum's phases (a batch of 100 steps costs about 5x one of 10)."""
        done, end = 0, 0
        for p, steps in self.curriculum or ():
            done += min(steps, max(0, step - end)) * (p + BATCH_FIXED_STEPS)
            end += steps
        return done + max(0, step - end) * (horizon + BATCH_FIXED_STEPS)

    def horizon_at(self, step: int, horizon: int) -> int:
        """The window length of training step ``step``: the curriculum's phase, then ``horizon``."""
        end = 0
        for p, steps in self.curriculum or ():
            end += steps
            if step < end:
                return p
        return horizon


# Training settings that say how long or how a model was trained, not which model it is (the
# fields marked _RUN): a model file trained with another budget still is the configured learner,
# and a training may resume from its checkpoint with them changed (learners/trained.py).
RUN_SETTINGS = tuple(f.name for f in fields(TrainingConfig) if f.metadata.get("run"))


@dataclass(frozen=True)
class RandomLayerConfig:
    """The paper's robustness experiment: an extra hidden layer redrawn at every training step.

    W ~ I + N(0, std^2), b ~ N(0, std^2), then a ReLU (see :func:`learners.nets.random_layer`).
    The schema of ``learner.random_layer``.
    """

    enabled: bool = False
    std: float = 0.1

    def __post_init__(self) -> None:
        boolean("learner.random_layer.enabled", self.enabled)
        non_negative("learner.random_layer.std", self.std)


class Objective(Protocol):
    """What a trained learner gives the loop: parameters, a gradient step, a validation loss."""

    params: FlatParameters

    def train_step(self, x: torch.Tensor, v: torch.Tensor, step: int) -> float:
        """Loss of windows x (B, p+1, n), v (B, p, m); its gradient ADDED to ``params.grad``."""
        ...

    def validate(self, x: torch.Tensor, v: torch.Tensor) -> dict[str, float]:
        """Batch-mean loss terms of windows (nominal random layer); key ``loss`` is monitored."""
        ...


@dataclass
class History:
    """Loss curves: one entry per evaluation (every ``eval_every_steps`` and at the end).

    ``resumed_s``: the seconds of training this fit resumed from (its checkpoint's runs; 0
    for a fresh fit), so that a run killed and resumed reports the whole training time. A
    measurement, not part of the result: two histories are equal without it."""

    step: list[int]
    epoch: list[int]
    train: list[float]
    validation: list[dict[str, float]]
    stopped: str = ""
    resumed_s: float = field(default=0.0, compare=False)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def train(
    name: str,
    objective: Objective,
    train_data: WindowData,
    validation_data: WindowData | None,
    horizon: int,
    config: TrainingConfig,
    *,
    fingerprint: Mapping[str, Any],
    checkpoint_path: Path | None = None,
    rollout_score: Callable[[], dict[str, float]] | None = None,
) -> History:
    """Train ``objective.params`` in place with Adam; leaves the best parameters in them.

    With ``checkpoint_path``, resumes from it when it exists and keeps it current.
    ``rollout_score`` (needed by ``selection: rollout``) scores the current parameters by
    open-loop rollouts of the validation drives: a dict with :data:`ROLLOUT_SCORE` (lower is
    better; inf where a rollout diverged) and any per-state terms to keep in the history.
    """
    _check_windows(name, train_data, validation_data, horizon, config, rollout_score)
    validation = _Validation(objective, validation_data, horizon, config, rollout_score)
    params = objective.params
    flat = torch.nn.Parameter(params.data)  # shares storage with params.data and its views
    flat.grad = params.grad
    optimizer = torch.optim.Adam([flat], lr=config.lr, fused=True)
    fingerprint = {
        "learner": name,
        **fingerprint,
        "train": train_data.fingerprint(),
        "validation": validation_data.fingerprint() if validation_data is not None else None,
    }
    state = _State.fresh(params.data.clone() if config.average_decay is not None else None)
    if checkpoint_path is not None and checkpoint_path.exists():
        state = _resume(name, checkpoint_path, fingerprint, params, optimizer, state)
    resumed_s, clock = state.trained_s, time.perf_counter()

    def save_checkpoint() -> None:
        if checkpoint_path is not None:
            state.trained_s = resumed_s + time.perf_counter() - clock
            state.save(checkpoint_path, fingerprint, params, optimizer)

    with _torch_threads(config.num_threads), _progress(name, config, state, horizon) as bar:
        step = _Step(name, objective, flat, optimizer, config, state)
        while _budget_left(config, state) and not state.stopped:
            # An epoch's windows have the length of its first step (resumed: step - batches).
            p = config.horizon_at(state.step - state.batch_in_epoch, horizon)
            batches = _epoch_batches(train_data, config, state.epoch, p)
            for b in range(state.batch_in_epoch, len(batches)):
                step(*train_data.gather(batches[b], p))
                state.batch_in_epoch = b + 1
                bar.set_description_str(step.description(), refresh=False)
                bar.update(p + BATCH_FIXED_STEPS)
                if state.step % config.eval_every_steps == 0:
                    with _averaged(params, state.average):
                        state.evaluate(validation(), params, config)
                    bar.set_postfix(state.postfix(), refresh=False)
                if state.step % config.checkpoint_every_steps == 0:
                    save_checkpoint()
                if state.stopped or not _budget_left(config, state):
                    break
                if config.horizon_at(state.step, horizon) != p:  # the next phase: a new epoch
                    state.epoch += 1
                    state.batch_in_epoch = 0
                    break
            else:
                state.epoch += 1
                state.batch_in_epoch = 0
        history, best = _finish(state, params, config, validation)
        save_checkpoint()
    history.resumed_s = resumed_s
    if best is not None and len(validation.windows):
        params.data.copy_(best)
    elif state.average is not None:  # nothing to choose by: the average is the model
        params.data.copy_(state.average)
    return history


def _check_windows(
    name: str,
    train_data: WindowData,
    validation_data: WindowData | None,
    horizon: int,
    config: TrainingConfig,
    rollout_score: Callable[[], dict[str, float]] | None,
) -> None:
    """Every window length fits a training episode; rollout selection has its score."""
    for p in {horizon, *(p for p, _ in config.curriculum or ())}:
        if len(train_data.window_starts(p)) == 0:
            raise ValueError(
                f"a training window of {p} steps (learner.horizon or training.curriculum) is "
                f"longer than every training episode (no window fits)"
            )
    if config.selection == "rollout" and validation_data is not None and rollout_score is None:
        raise ValueError(f"{name}: training.selection is rollout but no rollout score was given")


def _resume(
    name: str,
    checkpoint_path: Path,
    fingerprint: Mapping[str, Any],
    params: FlatParameters,
    optimizer: torch.optim.Optimizer,
    fresh: _State,
) -> _State:
    """The checkpoint's state; a damaged one is set aside, named, and training starts afresh."""
    try:
        return _State.load(checkpoint_path, fingerprint, params, optimizer)
    except DamagedCheckpointError as damaged:
        aside = checkpoint_path.with_name(checkpoint_path.name + ".damaged")
        checkpoint_path.replace(aside)
        log.warning(
            "%s: %s is damaged (%s); training starts afresh (the file is kept as %s)",
            name,
            checkpoint_path,
            damaged,
            aside.name,
        )
        return fresh


class _Validation:
    """The validation measure of the current parameters: the windows' loss, in chunks, and the
    rollout score where the selection is by rollouts."""

    def __init__(
        self,
        objective: Objective,
        data: WindowData | None,
        horizon: int,
        config: TrainingConfig,
        rollout_score: Callable[[], dict[str, float]] | None,
    ) -> None:
        self.objective, self.data, self.horizon = objective, data, horizon
        self.windows = data.window_starts(horizon) if data is not None else np.zeros(0)
        self.rollout_score = rollout_score if config.selection == "rollout" else None

    def __call__(self) -> dict[str, float]:
        if not len(self.windows) or self.data is None:
            return {}
        totals: dict[str, float] = {}
        for i in range(0, len(self.windows), VALIDATION_CHUNK):
            chunk = self.windows[i : i + VALIDATION_CHUNK]
            x, v = self.data.gather(chunk, self.horizon)
            for key, value in self.objective.validate(x, v).items():
                totals[key] = totals.get(key, 0.0) + value * len(chunk)
        out = {k: v / len(self.windows) for k, v in totals.items()}
        if self.rollout_score is not None:
            out.update(self.rollout_score())
        return out


class _Step:
    """One batch: the initial state's noise, the loss and its gradient, the clip, Adam's step
    at the schedule's rate, the average; the loss's running sum in the state."""

    def __init__(
        self,
        name: str,
        objective: Objective,
        flat: torch.nn.Parameter,
        optimizer: torch.optim.Optimizer,
        config: TrainingConfig,
        state: _State,
    ) -> None:
        self.name, self.objective, self.flat, self.optimizer = name, objective, flat, optimizer
        self.config, self.state = config, state
        self.of = "" if config.max_steps is None else f"/{config.max_steps}"

    def __call__(self, x: torch.Tensor, v: torch.Tensor) -> None:
        config, state, params = self.config, self.state, self.objective.params
        if config.initial_state_noise:
            noise = np.random.default_rng([config.seed, state.step, 1]).standard_normal(
                (x.shape[0], x.shape[2])
            )
            x[:, 0] += torch.from_numpy((config.initial_state_noise * noise).astype(np.float32))
        params.grad.zero_()
        loss = self.objective.train_step(x, v, state.step)
        if not math.isfinite(loss):
            raise RuntimeError(
                f"{self.name} training diverged at step {state.step} (loss = {loss}); "
                f"lower learner.training.lr or check the data"
            )
        if config.grad_clip_norm is not None:
            torch.nn.utils.clip_grad_norm_([self.flat], config.grad_clip_norm)
        self.optimizer.param_groups[0]["lr"] = config.lr_at(state.step)
        self.optimizer.step()
        if state.average is not None:
            assert config.average_decay is not None  # the average exists only then
            state.average.lerp_(params.data, 1.0 - config.average_decay)
        state.step += 1
        state.train_sum += loss
        state.train_count += 1

    def description(self) -> str:
        return f"{self.name} batch {self.state.step}{self.of}"


def _epoch_batches(
    data: WindowData, config: TrainingConfig, epoch: int, p: int
) -> list[np.ndarray]:
    """The window starts of each of an epoch's batches (windows of p steps, drawn from
    ``[seed, epoch]``; the last partial batch dropped)."""
    rng = np.random.default_rng([config.seed, epoch])
    offsets = rng.integers(0, p + 1, len(data.episode_lengths))
    starts = data.window_starts(p, offsets)
    order = rng.permutation(len(starts))
    batch = min(config.batch_size, len(starts))
    return [starts[order[b * batch : (b + 1) * batch]] for b in range(len(starts) // batch)]


def _budget_left(config: TrainingConfig, state: _State) -> bool:
    if config.max_steps is not None and state.step >= config.max_steps:
        return False
    return config.max_epochs is None or state.epoch < config.max_epochs


def _progress(name: str, config: TrainingConfig, state: _State, horizon: int) -> tqdm:
    """The bar: work done in window steps (an ETA that holds across the curriculum)."""
    return tqdm(
        total=None if config.max_steps is None else config.work_until(config.max_steps, horizon),
        initial=config.work_until(state.step, horizon),
        desc=name,
        bar_format=None if config.max_steps is None else _BAR,
        disable=not config.progress,
        mininterval=1.0,
        smoothing=0.0,  # the rate over this whole run: work-weighted, it holds
    )


def _finish(
    state: _State, params: FlatParameters, config: TrainingConfig, validation: _Validation
) -> tuple[History, torch.Tensor | None]:
    """The history and the best parameters, the last off-grid steps evaluated too; why the
    training stopped."""
    if state.train_count or not state.history.step:  # evaluate the last, off-grid steps
        final = _State.from_state(state)
        with _averaged(params, state.average):
            final.evaluate(validation(), params, config)
        history, best = final.history, final.best_params
    else:
        history, best = state.history, state.best_params
    if not state.stopped:
        history.stopped = (
            "max_steps"
            if config.max_steps is not None and state.step >= config.max_steps
            else "max_epochs"
        )
    return history, best


@contextlib.contextmanager
def _averaged(params: FlatParameters, average: torch.Tensor | None) -> Iterator[None]:
    """The averaged weights in ``params`` for an evaluation (no-op without an average); the
    optimizer's own weights are put back after it."""
    if average is None:
        yield
        return
    live = params.data.clone()
    params.data.copy_(average)
    try:
        yield
    finally:
        params.data.copy_(live)


@dataclass
class _State:
    """Everything a resumed run needs besides parameters and Adam's moments."""

    step: int
    epoch: int
    batch_in_epoch: int
    train_sum: float
    train_count: int
    best_loss: float
    evals_since_best: int
    best_params: torch.Tensor | None
    history: History
    stopped: str = ""
    average: torch.Tensor | None = None  # the weights' moving average (average_decay)
    trained_s: float = 0.0  # seconds of training up to the last checkpoint, over every run

    @classmethod
    def fresh(cls, average: torch.Tensor | None = None) -> _State:
        """Step 0; ``average`` starts the weights' moving average (None: no average)."""
        return cls(0, 0, 0, 0.0, 0, math.inf, 0, None, History([], [], [], []), "", average)

    @classmethod
    def from_state(cls, other: _State) -> _State:
        """A copy that can be evaluated once more without touching the resumable state (its
        ``average`` is shared: the copy is evaluated, never trained)."""
        h = other.history
        history = History([*h.step], [*h.epoch], [*h.train], [*h.validation], h.stopped)
        best = None if other.best_params is None else other.best_params.clone()
        return cls(**{**other.__dict__, "history": history, "best_params": best})

    def evaluate(
        self, validation: dict[str, float], params: FlatParameters, config: TrainingConfig
    ) -> None:
        train_loss = self.train_sum / self.train_count if self.train_count else math.nan
        self.history.step.append(self.step)
        self.history.epoch.append(self.epoch)
        self.history.train.append(train_loss)
        self.history.validation.append(validation)
        self.train_sum, self.train_count = 0.0, 0
        if not validation:
            return
        loss = validation["loss"]
        if not math.isfinite(loss):
            raise RuntimeError(f"validation loss is {loss} at step {self.step}: training diverged")
        if config.selection == "rollout":  # a diverging rollout is not an improvement
            loss = validation.get(ROLLOUT_SCORE, math.inf)
            loss = loss if math.isfinite(loss) else math.inf
        if self.step <= config.curriculum_steps:  # short windows: not yet a candidate
            self.best_loss, self.evals_since_best = math.inf, 0
            self.best_params = params.data.clone()  # what a run cut short here returns
            return
        if loss < self.best_loss or self.best_params is None:
            self.best_loss, self.evals_since_best = loss, 0
            self.best_params = params.data.clone()
        else:
            self.evals_since_best += 1
            if self.evals_since_best >= config.patience:
                self.stopped = self.history.stopped = "early_stopping"

    def postfix(self) -> dict[str, str]:
        out = {"train": f"{self.history.train[-1]:.3g}"}
        last = self.history.validation[-1]
        if last:
            out["val"] = f"{last['loss']:.3g}"
            if ROLLOUT_SCORE in last:
                out["rollout"] = f"{last[ROLLOUT_SCORE]:.3g}"
        return out

    def save(
        self,
        path: Path,
        fingerprint: Mapping[str, Any],
        params: FlatParameters,
        optimizer: torch.optim.Optimizer,
    ) -> None:
        payload = {
            "fingerprint": _digest(fingerprint),
            "params": params.data.clone(),
            "optimizer": optimizer.state_dict(),
            "state": {
                k: v for k, v in self.__dict__.items() if k not in ("best_params", "average")
            },
            "best_params": self.best_params,
            "average": self.average,
        }
        payload["state"]["history"] = self.history.to_dict()
        buffer = io.BytesIO()
        torch.save(payload, buffer)
        body = buffer.getvalue()
        trailer = _CHECKSUM_MARKER + hashlib.sha256(body).hexdigest().encode() + b"\n"
        write_atomic(path, lambda handle: handle.write(body + trailer))

    @classmethod
    def load(
        cls,
        path: Path,
        fingerprint: Mapping[str, Any],
        params: FlatParameters,
        optimizer: torch.optim.Optimizer,
    ) -> _State:
        """The state saved in ``path``; its parameters and Adam's state go into ``params`` and
        ``optimizer``. :class:`DamagedCheckpointError` (nothing changed) where the file fails its
        checksum or cannot be read; ``ValueError`` where it is of other data or hyperparameters.
        """
        payload = _read_checkpoint(path)
        if payload.get("fingerprint") != _digest(fingerprint):
            raise ValueError(
                f"{path} was written for other data or hyperparameters; "
                f"remove it or use another output directory"
            )
        try:
            values = dict(payload["state"])
            values["history"] = History(**values["history"])
            state = cls(**values, best_params=payload["best_params"], average=payload["average"])
            saved = payload["params"]
            for tensor in (saved, state.average):
                if tensor is not None and (
                    not isinstance(tensor, torch.Tensor) or tensor.shape != params.data.shape
                ):
                    raise ValueError("its parameters have another shape")
            if saved is None:
                raise ValueError("it holds no parameters")
            # Adam checks the saved groups before it changes anything.
            optimizer.load_state_dict(payload["optimizer"])
        except (KeyError, TypeError, ValueError) as error:
            raise DamagedCheckpointError(f"its content does not fit: {error}") from None
        params.data.copy_(saved)
        return state


class DamagedCheckpointError(Exception):
    """A checkpoint file that fails its checksum or cannot be read; the message says why."""


def _read_checkpoint(path: Path) -> dict[str, Any]:
    """The payload of a checkpoint whose trailing SHA-256 matches its content."""
    raw = path.read_bytes()
    body, trailer = raw[:-_TRAILER_BYTES], raw[-_TRAILER_BYTES:]
    if not trailer.startswith(_CHECKSUM_MARKER):
        raise DamagedCheckpointError(f"no checksum at its end ({len(raw)} bytes; truncated?)")
    if hashlib.sha256(body).hexdigest().encode() != trailer[len(_CHECKSUM_MARKER) : -1]:
        raise DamagedCheckpointError("fails its checksum (truncated or modified)")
    try:
        payload = torch.load(io.BytesIO(body), map_location="cpu", weights_only=True)
    except Exception as error:  # whatever torch says of a file it cannot read
        raise DamagedCheckpointError(f"torch cannot read it: {error}".splitlines()[0]) from None
    if not isinstance(payload, dict):
        raise DamagedCheckpointError("it holds no checkpoint")
    return payload


def _digest(fingerprint: Mapping[str, Any]) -> str:
    return hashlib.sha1(json.dumps(fingerprint, sort_keys=True, default=str).encode()).hexdigest()


@contextlib.contextmanager
def _torch_threads(count: int | None) -> Iterator[None]:
    """Run with ``count`` intra-op threads (None: those in force), then restore."""
    before = torch.get_num_threads()
    torch.set_num_threads(count or before)
    _keep_freed_memory()
    try:
        yield
    finally:
        torch.set_num_threads(before)


_MALLOC_TUNED = False


def _keep_freed_memory() -> None:
    """Keep freed blocks in glibc's heap instead of returning them to the OS.

    Each training step allocates and frees the same few-MB activation buffers; by default glibc
    serves them with mmap and unmaps them on free, so every step pays page faults on fresh pages
    (about 25 % of a Deep EDMD step here). Raising the mmap and trim thresholds makes freed
    blocks reusable, as jemalloc/tcmalloc would. Process-wide and permanent; no-op off glibc.
    """
    global _MALLOC_TUNED
    if _MALLOC_TUNED:
        return
    _MALLOC_TUNED = True
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3
        libc.mallopt(m_mmap_threshold, 1 << 30)
        libc.mallopt(m_trim_threshold, (1 << 31) - 1)
        libc.mallopt(m_top_pad, 64 << 20)


def batch_mean_terms(
    terms: Mapping[str, torch.Tensor], weights: Mapping[str, float]
) -> dict[str, float]:
    """Floats of the loss terms plus ``loss``, their weighted sum (what validation monitors)."""
    out = {k: float(v) for k, v in terms.items()}
    out["loss"] = sum(weights[k] * out[k] for k in weights)
    return out
