"""Any learner fitted on the pedal as two inputs, throttle and brake, and read back as a model of
the pedal (ours; the paper's u has one throttle/brake input).

Why: the sedan's brake decelerates 7.3-7.6 m/s² per unit of pedal at every speed, its throttle
accelerates 1.5 per unit at low speed and 0.56 above 25 m/s (``python -m bench.pedal_structure
--slopes``). A model affine in u has one column of B for the pedal: one slope for both sides. Fed
throttle = max(p, 0) and brake = max(-p, 0) (the pedal's feature, each in [0, 1]) as two columns,
the same model has a slope for each, and Deep EDMD's whole-drive vx fell 1.4-2.6x
(docs/findings/deep_edmd_vx.md,
"The pedal's two slopes").

To everything outside, :class:`SplitPedal` is a learner of the dataset's own inputs
(``normalizer_`` is the caller's, with the signed pedal): ``predict`` takes the pedal, and for
DE-MPC it is a :class:`~harness.core.contracts.LinearizableModel` (``dynamics = "nonlinear"``)
whose step is piecewise linear in the pedal, kinked at zero. The controller's pedal secant
(``controller.input_secant_span``) reads the slope across the kink. The wrapped learner (``inner``)
is fitted, saved and loaded with its own normalizer, derived from the caller's exactly (the
throttle's range is [max(p_min, 0), max(p_max, 0)] of the pedal's feature, the brake's likewise).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self, cast

import numpy as np
import torch

from harness.core.contracts import Dynamics, LinearizableModel
from harness.core.episode import Episode, InputChannel, MinMaxNormalizer
from learners.base import (
    INPUT_DIM,
    STATE_DIM,
    check_rollout_args,
)
from learners.settings import settle
from learners.wrapping import WrappingLearner, inner_learner

__all__ = [
    "SplitPedal",
    "pedal_column",
    "split_inputs",
    "split_normalizer",
    "split_pedal",
]

SPLIT_NAMES = ("throttle", "brake")
SPLIT_ROLES = ("drive", "brake")


def pedal_column(names: Sequence[str], pedal: str, source: str) -> int:
    """The index of input ``pedal`` in ``names``; refused in one line naming ``source``."""
    if pedal not in names:
        raise ValueError(
            f"{source} has no '{pedal}' input ({', '.join(names)}): the pedal split needs a signed "
            "throttle/brake input (learner.pedal names it)"
        )
    return list(names).index(pedal)


def split_inputs(inputs: np.ndarray, channels: Sequence[InputChannel], column: int) -> np.ndarray:
    """Physical inputs (..., m) with column ``column`` as two, its feature's positive part
    (throttle) and negative part (brake), last: (..., m + 1), in the split channels' units."""
    inputs = np.array(inputs, dtype=float)
    inputs[..., column] = channels[column].feature(inputs[..., column])
    return _split_column(inputs, column)


def _split_column(values: np.ndarray, column: int) -> np.ndarray:
    """``values`` (..., m) with column ``column`` as its positive and negative parts, last."""
    signed = values[..., column]
    kept = np.delete(values, column, axis=-1)
    return np.concatenate(
        [kept, np.maximum(signed, 0.0)[..., None], np.maximum(-signed, 0.0)[..., None]], axis=-1
    )


def split_channels(channels: Sequence[InputChannel], column: int) -> tuple[InputChannel, ...]:
    kept = [c for i, c in enumerate(channels) if i != column]
    # The pedal's positive part drives and its negative part brakes, each >= 0 (the sedan's
    # in [0, 1] of its side's range).
    return (
        *kept,
        *(InputChannel(n, role=r) for n, r in zip(SPLIT_NAMES, SPLIT_ROLES, strict=True)),
    )


def split_pedal(episode: Episode, pedal: str = "pedal") -> Episode:
    """The episode with its pedal column as two, throttle and brake, each >= 0 (in [0, 1] for the
    sedan's pedal), after the other inputs."""
    column = pedal_column(episode.input_names, pedal, f"episode {episode.name}")
    return dataclasses.replace(
        episode,
        inputs=split_inputs(episode.inputs, episode.channels, column),
        channels=split_channels(episode.channels, column),
    )


def split_normalizer(normalizer: MinMaxNormalizer, column: int) -> MinMaxNormalizer:
    """What :meth:`MinMaxNormalizer.fit` gives on the split drives, from the signed one alone."""
    low, high = float(normalizer.input_min[column]), float(normalizer.input_max[column])
    keep = np.delete(np.arange(len(normalizer.input_min)), column)
    return MinMaxNormalizer(
        normalizer.state_min,
        normalizer.state_max,
        np.concatenate([normalizer.input_min[keep], [max(low, 0.0), max(-high, 0.0)]]),
        np.concatenate([normalizer.input_max[keep], [max(high, 0.0), max(-low, 0.0)]]),
        split_channels(normalizer.channels, column),
    )


@dataclass(frozen=True)
class SplitPedalConfig:
    """The pedal split's settings (``conf/learner/*_split.yaml``): the learner fitted on the
    two inputs, and the input to split."""

    inner: Any = None  # a learner, or its config with _target_ (deep_edmd@inner)
    pedal: str = "pedal"  # the signed throttle/brake input to split

    def __post_init__(self) -> None:
        inner = inner_learner(self.inner)
        if isinstance(inner, SplitPedal):
            raise ValueError("learner.inner is a split_pedal learner already: split the pedal once")
        if not isinstance(self.pedal, str) or not self.pedal:
            raise ValueError(f"learner.pedal must name the signed pedal input (got {self.pedal!r})")
        settle(self, inner=inner)


class SplitPedal(WrappingLearner):
    """``inner`` fitted on throttle and brake, used as a model of the pedal (module docstring)."""

    name: ClassVar[str] = "split_pedal"
    config_class: ClassVar[type] = SplitPedalConfig
    config: SplitPedalConfig
    dynamics: ClassVar[Dynamics] = "nonlinear"  # piecewise linear in the pedal: DE-MPC linearises

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        self.pedal = self.config.pedal

    # -- the learner contract ---------------------------------------------------------------------

    def fit(
        self, train: Sequence[Episode], validation: Sequence[Episode], normalizer: MinMaxNormalizer
    ) -> Self:
        column = pedal_column(normalizer.input_names, self.pedal, "the data")
        self.normalizer_ = normalizer
        self._column = column
        split = split_normalizer(normalizer, column)
        self.inner.fit(
            [split_pedal(e, self.pedal) for e in train],
            [split_pedal(e, self.pedal) for e in validation],
            split,
        )
        self._read_inner()
        return self

    def predict(self, x0: np.ndarray, inputs: np.ndarray, **options: Any) -> np.ndarray:
        """As the inner learner's ``predict`` (``options`` too), the pedal split first."""
        x0, inputs = check_rollout_args(
            x0, inputs, len(self.normalizer_.state_min), len(self.normalizer_.input_min)
        )
        split = split_inputs(inputs, self.normalizer_.channels, self._column)
        return self.inner.predict(x0, split, **options)

    def check_size(self, episode_frames: int, n: int = STATE_DIM, m: int = INPUT_DIM) -> None:
        self.inner.check_size(episode_frames, n, m + 1)

    def check_inputs(self, channels: Sequence[InputChannel]) -> None:
        """The pedal named in ``learner.pedal`` among the data's inputs, before any data."""
        pedal_column([c.name for c in channels], self.pedal, "the data config")

    # -- the model DE-MPC reads -------------------------------------------------------------------

    def _read_inner(self) -> None:
        """The affine map from this model's normalized inputs v to the inner's w, each side of
        the kink: w = w_zero + J_side (v - v_zero) on the throttle (feature >= 0) or brake side."""
        outer, inner = self.normalizer_, self.inner.normalizer_
        column, m = self._column, len(outer.input_min)
        self._inner_dynamics: Dynamics = getattr(self.inner, "dynamics", "nonlinear")
        if self._inner_dynamics not in ("linear", "bilinear") and not isinstance(
            self.inner, LinearizableModel
        ):
            return  # predict only: the inner model cannot be linearised for a controller
        self.C_ = np.asarray(cast(Any, self.inner).C_, dtype=float)
        span, inner_span = outer.input_span, inner.input_span
        # d(feature)/dv for every input; the pedal's feature moves throttle up or brake down.
        jacobians = []
        for sign, target in ((1.0, m - 1), (-1.0, m)):
            jacobian = np.zeros((m + 1, m))
            kept = [j for j in range(m) if j != column]
            for i, j in enumerate(kept):
                jacobian[i, j] = span[j] / inner_span[i]
            jacobian[target, column] = sign * span[column] / inner_span[target]
            jacobians.append(jacobian)
        self._jacobian_throttle, self._jacobian_brake = jacobians

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(cast(Any, self.inner).lift(x), dtype=float)

    def _to_inner(self, v: np.ndarray) -> np.ndarray:
        """This model's normalized inputs (..., m) as the inner model's (..., m + 1)."""
        outer, inner = self.normalizer_, self.inner.normalizer_
        features = np.asarray(v, dtype=float) * outer.input_span + outer.input_min
        return (_split_column(features, self._column) - inner.input_min) / inner.input_span

    def _inner_step(self, z: np.ndarray, w: np.ndarray) -> np.ndarray:
        inner: Any = self.inner
        if self._inner_dynamics == "nonlinear":
            return np.asarray(inner.step(z, w), dtype=float)
        step = z @ np.asarray(inner.A_).T + w @ np.asarray(inner.B_).T
        if self._inner_dynamics == "bilinear":
            offsets = w - np.asarray(inner.v0_)
            step = step + np.einsum("...j,jab,...b->...a", offsets, np.asarray(inner.H_), z)
        return np.asarray(step, dtype=float)

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self._inner_step(np.asarray(z, dtype=float), self._to_inner(v))

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A_k, B_k, d_k at every (z̄_k, v̄_k): the inner model's Jacobians in its inputs, times
        the split's (exactly at the pedal released: the mean of both sides); d_k makes the
        linearisation exact at the point."""
        z, v = np.asarray(z, dtype=float), np.asarray(v, dtype=float)
        w = self._to_inner(v)
        inner: Any = self.inner
        if self._inner_dynamics == "nonlinear":
            A, b_inner, _ = inner.linearize(z, w)
        else:
            A = np.broadcast_to(np.asarray(inner.A_, dtype=float), (len(z), *inner.A_.shape))
            b_inner = np.broadcast_to(np.asarray(inner.B_, dtype=float), (len(z), *inner.B_.shape))
            if self._inner_dynamics == "bilinear":
                H = np.asarray(inner.H_, dtype=float)
                A = A + np.tensordot(w - np.asarray(inner.v0_), H, axes=1)
                b_inner = b_inner + np.transpose(H @ z.T, (2, 1, 0))
        outer, column = self.normalizer_, self._column
        features = v[:, column] * outer.input_span[column] + outer.input_min[column]
        released = np.abs(features) <= 1e-9  # to rounding: v of the pedal at zero
        side = np.where(released, 0.0, np.sign(features))[:, None, None]  # -1 brake, 0: the mean
        jacobian = (
            0.5 * (1 + side) * self._jacobian_throttle + 0.5 * (1 - side) * self._jacobian_brake
        )
        B = b_inner @ jacobian
        d = self.step(z, v) - np.einsum("kab,kb->ka", A, z) - np.einsum("kab,kb->ka", B, v)
        return np.ascontiguousarray(A), np.ascontiguousarray(B), d

    # -- the file ---------------------------------------------------------------------------------

    def _inner_input_count(self, m: int) -> int:
        return m + 1  # the pedal as two

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        self._column = pedal_column(self.normalizer_.input_names, self.pedal, "the model file")
        self._set_inner_state(state, split_normalizer(self.normalizer_, self._column))
