"""Plumbing shared by the learners trained by gradient descent (DNN, Deep EDMD)."""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Self

import numpy as np
import torch

from harness.core.budget import check_memory
from harness.core.checks import integer, positive
from harness.core.episode import Episode, MinMaxNormalizer
from learners import training as loop
from learners.base import (
    INPUT_DIM,
    STATE_DIM,
    Dim,
    Learner,
    Shape,
    check_fit_data,
    check_rollout_args,
)
from learners.nets import Dense, FlatParameters, LayerSpec, random_layer
from learners.settings import block, settle
from learners.training import (
    RUN_SETTINGS,
    History,
    Objective,
    RandomLayerConfig,
    TrainingConfig,
)
from learners.windows import WindowData

__all__ = [
    "TrainedLearner",
    "check_loss_scales",
    "check_per_state",
    "settle_trained",
    "state_loss_weights",
]


def check_loss_scales(scales: Sequence[float] | None) -> tuple[float, ...] | None:
    """``learner.loss_scales``: None (the paper: errors in normalized units) or one positive
    scale per state in its physical unit."""
    if scales is None:
        return None
    if isinstance(scales, str) or not isinstance(scales, Sequence) or not scales:
        raise ValueError(
            f"learner.loss_scales must be null or a list of positive numbers, one per state "
            f"(got {scales!r})"
        )
    return tuple(positive("learner.loss_scales", value) for value in scales)


def check_per_state(key: str, scales: Sequence[float], n: int) -> None:
    """``key`` (a list of scales) has one entry per state of data with ``n`` states."""
    if len(scales) != n:
        raise ValueError(
            f"{key} has {len(scales)} entries; the data has {n} states "
            f"(give one scale per state, in its unit)"
        )


def state_loss_weights(
    normalizer: MinMaxNormalizer, scales: Sequence[float] | None
) -> torch.Tensor | None:
    """Per-state weights w of squared normalized errors so that the loss weighs each state's
    error in units of its scale: w_s proportional to (span_s / scale_s)^2, mean 1 (so the
    other loss terms keep their balance). None without scales."""
    if scales is None:
        return None
    span = normalizer.state_max - normalizer.state_min
    check_per_state("learner.loss_scales", scales, len(span))
    w = (np.where(span > 1e-12, span, 1.0) / np.asarray(scales, float)) ** 2
    return torch.from_numpy((w / w.mean()).astype(np.float32))


def settle_trained(settings: Any) -> None:
    """Check and keep the settings every trained learner has: ``horizon``, ``loss_scales``,
    ``random_layer`` and ``training`` (from its settings' ``__post_init__``)."""
    settle(
        settings,
        horizon=integer("learner.horizon", settings.horizon, 1),
        loss_scales=check_loss_scales(settings.loss_scales),
        random_layer=block(RandomLayerConfig, settings.random_layer, "random_layer"),
        training=block(TrainingConfig, settings.training, "training"),
    )


def _is_size(value: Any) -> bool:
    """An int, or a list of ints (widths): a size a user can make smaller (not a flag, not a
    list of scales)."""
    if isinstance(value, list):
        return bool(value) and all(_is_size(item) for item in value)
    return isinstance(value, int) and not isinstance(value, bool)


class TrainedLearner(Learner):
    """Windows, training loop, checkpoints and the batched, seeded-random-layer ``predict``.

    Fitted attributes: ``params_`` (:class:`~learners.nets.FlatParameters`), ``history_``
    (:class:`~learners.training.History`, the loss curves), ``normalizer_``.

    ``checkpoint_dir`` (None: no checkpoints) is where ``fit`` keeps ``<name>.ckpt`` so that a
    killed training resumes; it is the caller's (the run directory), not a hyperparameter: it
    is neither saved with the model nor part of the checkpoint's fingerprint.
    """

    params_: FlatParameters
    history_: History
    checkpoint_dir: Path | None
    loss_scales: tuple[float, ...] | None

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        self.horizon: int = self.config.horizon
        self.random_layer: RandomLayerConfig = self.config.random_layer
        self.training: TrainingConfig = self.config.training
        self.loss_scales = self.config.loss_scales
        self.checkpoint_dir = None

    # -- subclass hooks --------------------------------------------------------------------------

    @abstractmethod
    def _specs(self, n: int, m: int) -> list[LayerSpec]:
        """The :class:`~learners.nets.LayerSpec` list of every trained tensor."""

    @abstractmethod
    def _objective(self) -> Objective:
        """The loss the training loop minimizes, bound to ``params_``."""

    def _before_training(self, train: Sequence[Episode]) -> None:
        """Set what the network and its loss need of the data (``normalizer_`` is set)."""

    def _after_training(self, train: Sequence[Episode]) -> None:
        """Set the remaining fitted attributes once ``params_`` hold the trained weights."""

    @abstractmethod
    def _rollout_n(self, x0: torch.Tensor, v: torch.Tensor, layer: Dense | None) -> torch.Tensor:
        """Normalized rollout: x0 (R, n), v (R, T, m) float32 -> (R, T + 1, n)."""

    _random_layer_width: int

    # -- the contract ----------------------------------------------------------------------------

    def fit(
        self,
        train: Sequence[Episode],
        validation: Sequence[Episode],
        normalizer: MinMaxNormalizer,
    ) -> Self:
        """Train on windows of ``train``; early-stop on ``validation``; resume from
        ``checkpoint_dir`` when it holds this run's checkpoint."""
        check_fit_data(train, validation, normalizer, self.name)
        self.normalizer_ = normalizer
        n, m = normalizer.state_min.shape[0], normalizer.input_min.shape[0]
        self._before_training(train)
        self._build(n, m)
        generator = torch.Generator().manual_seed(self.training.seed)
        self.params_.initialize(generator)
        fingerprint = self.hyperparameters
        fingerprint["training"] = {
            k: v for k, v in fingerprint["training"].items() if k not in RUN_SETTINGS
        }
        self.history_ = loop.train(
            self.name,
            self._objective(),
            WindowData.from_episodes(train, normalizer),
            WindowData.from_episodes(validation, normalizer) if validation else None,
            self.horizon,
            self.training,
            fingerprint={"hyperparameters": fingerprint},
            checkpoint_path=self.checkpoint_path,
            rollout_score=self._rollout_scorer(train, validation) if validation else None,
        )
        self._after_training(train)
        return self

    def _state_weights_tensor(self) -> torch.Tensor | None:
        """The loss's per-state weights (:func:`state_loss_weights`), None without scales."""
        if self.loss_scales is None:
            return None
        return state_loss_weights(self.normalizer_, self.loss_scales)

    def _sync_for_rollout(self, train: Sequence[Episode]) -> None:
        """Make ``predict`` use the parameters as they are now (mid-training)."""

    def _rollout_scorer(
        self, train: Sequence[Episode], validation: Sequence[Episode]
    ) -> Callable[[], dict[str, float]]:
        """The score ``selection: rollout`` keeps checkpoints by: each validation drive predicted
        open loop from its first state (what the prediction tables do), RMSE per state in
        physical units over ``training.rollout_scales``, averaged over states and drives.
        ``rollout_rmse_<i>`` is state i's RMSE averaged over the drives; inf where one diverged."""
        n = self.normalizer_.state_min.shape[0]
        check_per_state("learner.training.rollout_scales", self.training.rollout_scales, n)
        scales = np.asarray(self.training.rollout_scales, float)

        def score() -> dict[str, float]:
            self._sync_for_rollout(train)
            rmse = np.zeros((len(validation), n))
            with np.errstate(over="ignore", invalid="ignore"):
                for i, e in enumerate(validation):
                    predicted = self.predict(e.states[0], e.inputs[:-1])
                    # rows 1.. (row 0 is given), as the prediction tables count them
                    rmse[i] = np.sqrt(np.mean((predicted[1:] - e.states[1:]) ** 2, axis=0))
            rmse = np.where(np.isfinite(rmse), rmse, np.inf)
            out = {loop.ROLLOUT_SCORE: float(np.mean(rmse / scales))}
            out.update({f"rollout_rmse_{j}": float(v) for j, v in enumerate(rmse.mean(0))})
            return out

        return score

    @property
    def redraws_random_layer(self) -> bool:
        return self.random_layer.enabled

    def predict(
        self, x0: np.ndarray, inputs: np.ndarray, *, random_layer_seed: int | None = None
    ) -> np.ndarray:
        """Open-loop rollout (see :meth:`Learner.predict`).

        Args:
            x0: (..., 3) initial states.
            inputs: (..., T, 2) inputs.
            random_layer_seed: None uses the nominal random layer (the identity, i.e. the
                network as trained without the noise); an integer draws one random layer per
                batch row from that seed (the paper's repeated predictions).
        """
        norm = self.normalizer_
        n, m = norm.state_min.shape[0], norm.input_min.shape[0]
        x0, inputs = check_rollout_args(x0, inputs, n, m)
        batch, steps = x0.shape[:-1], inputs.shape[-2]
        x0n = torch.from_numpy(norm.states(x0).reshape(-1, n).astype(np.float32))
        vn = torch.from_numpy(norm.inputs(inputs).reshape(-1, steps, m).astype(np.float32))
        layer = None
        if random_layer_seed is not None:
            if not self.random_layer.enabled:
                raise ValueError(
                    f"{self.name} has no random layer (learner.random_layer.enabled is false)"
                )
            layer = random_layer(
                self._random_layer_width,
                self.random_layer.std,
                torch.Generator().manual_seed(int(random_layer_seed)),
                rows=x0n.shape[0],
            )
        with torch.inference_mode():
            xn = self._rollout_n(x0n, vn, layer).double().numpy()
        with np.errstate(over="ignore", invalid="ignore"):
            x = norm.states_inverse(xn).reshape(*batch, steps + 1, n)
        x[..., 0, :] = x0
        return x

    def check_size(self, episode_frames: int, n: int = STATE_DIM, m: int = INPUT_DIM) -> None:
        """Refuse a network too big for this machine (``hidden=[1000000000]``), before any data.

        float32 counts (lower bounds): weights, gradients and Adam's two moments (4 per
        parameter), and one batch of windows' activations through every layer.
        """
        del episode_frames  # windows, not episodes, set the batch
        # Checked here too, so that a wrong length fails before any data, not at fit.
        if self.loss_scales is not None:
            check_per_state("learner.loss_scales", self.loss_scales, n)
        check_per_state("learner.training.rollout_scales", self.training.rollout_scales, n)
        specs = self._specs(n, m)
        parameters = sum(s.fan_out * (s.fan_in + int(s.bias)) for s in specs)
        widths = sum(s.fan_out for s in specs)
        activations = self.training.batch_size * (self.horizon + 1) * widths
        what = f"{self.name} with {parameters} parameters (batch {self.training.batch_size})"
        sizes = [  # the widths and sizes among the hyperparameters: what to make smaller
            f"learner.{key}"
            for key, value in self.hyperparameters.items()
            if key != "horizon" and _is_size(value)
        ]
        sizes.append("learner.training.batch_size")
        check_memory(" / ".join(sizes), what, 4 * (4 * parameters + activations))

    @property
    def checkpoint_path(self) -> Path | None:
        """``<checkpoint_dir>/<name>.ckpt``, or None without a ``checkpoint_dir``."""
        if self.checkpoint_dir is None:
            return None
        return Path(self.checkpoint_dir) / f"{self.name}.ckpt"

    # -- helpers ---------------------------------------------------------------------------------

    def _build(self, n: int, m: int) -> None:
        self.params_ = FlatParameters(self._specs(n, m))

    def _step_layer(self, step: int) -> Dense | None:
        """The random layer of training step ``step`` (None when disabled)."""
        if not self.random_layer.enabled:
            return None
        generator = torch.Generator().manual_seed(self.training.seed * 1_000_003 + step)
        return random_layer(self._random_layer_width, self.random_layer.std, generator)

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {"params": self.params_.data.clone()}

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        """One flat buffer of every layer's weights and biases (``learners.nets``)."""
        count = sum(s.fan_out * (s.fan_in + int(s.bias)) for s in self._specs(n, m))
        return {"params": (Dim("P", count, "the network's parameters"),)}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        norm = self.normalizer_
        self._build(norm.state_min.shape[0], norm.input_min.shape[0])
        self.params_.data.copy_(state["params"])
