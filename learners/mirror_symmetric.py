"""Any lifted-linear learner made exactly left-right symmetric: the model averaged with its mirror
image (ours; the paper's models are not).

Why: a car is its own mirror image. Reflect a drive (vy, yaw rate and the steering change sign;
vx and the pedal do not) and it is another drive of the same car, so the speed a steering input
costs is even in the steering: cornering drag, about as much left as right. A lifted-linear model
z⁺ = A z + B v answers an input linearly: the speed change its steering causes is odd, a left
turn gaining what a right turn loses. The best such answer to an even effect is none, and a
fitted model is not the best: Deep EDMD on ``data=default`` swings vx by 0.20-0.41 m/s RMS
through a 0.6 Hz slalom at constant brake where the sedan swings 0.009, and DE-MPC pulses the
pedal at every turn of the wheel to cancel swings that never come
(docs/findings/smooth_driving.md, "Deep EDMD's speed in a slalom").

The mirror image of a lifted-linear model is another (the lift of the reflected state, the
reflected inputs), and so is their average: two copies side by side and a constant, N → 2N + 1.
In it the steering's effect on vx cancels exactly, the effects on vy and r are the mean of both
copies', and vx's response to the pedal is the inner model's. ``predict`` averages the inner
model's prediction with its mirror image's likewise (the decoder's, where it has one).

Needs the data's steering to be known: inputs with a steering role (``steering_wheel`` or
``road_wheel``) are reflected, every other input is kept, and an input without a role is refused
before any data is read.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self, cast

import numpy as np
import torch

from harness.core.contracts import Dynamics
from harness.core.episode import STEERING_ROLES, Episode, InputChannel, MinMaxNormalizer
from learners.base import INPUT_DIM, STATE_DIM, check_rollout_args
from learners.settings import settle
from learners.wrapping import WrappingLearner, inner_learner

__all__ = ["STATE_MIRROR", "MirrorSymmetric", "input_mirror"]

# The reflection of x = (vx, vy, yaw rate): the car's lateral velocity and yaw rate change sign.
STATE_MIRROR = np.array([1.0, -1.0, -1.0])


def input_mirror(channels: Sequence[InputChannel], source: str) -> np.ndarray:
    """The reflection of the inputs, −1 for a steering input and +1 for the others; refused in
    one line where an input has no role or a steering input's two signs have other gains."""
    signs = []
    for channel in channels:
        if channel.role is None:
            raise ValueError(
                f"{source}: input {channel.name!r} has no role, so the mirror image cannot tell "
                "whether it steers: give every input a role (data.inputs), or use another learner"
            )
        steers = channel.role in STEERING_ROLES
        if steers and channel.gain_positive != channel.gain_negative:
            raise ValueError(
                f"{source}: steering input {channel.name!r} has other gains left and right: "
                "a mirror image needs one gain for both"
            )
        signs.append(-1.0 if steers else 1.0)
    return np.array(signs)


@dataclass(frozen=True)
class MirrorSymmetricConfig:
    """The settings of ``conf/learner/*_mirror.yaml``: the lifted-linear learner to symmetrize."""

    inner: Any = None  # a learner, or its config with _target_ (deep_edmd@inner)

    def __post_init__(self) -> None:
        inner = inner_learner(self.inner)
        dynamics = getattr(type(inner), "dynamics", None)
        if dynamics != "linear":
            raise ValueError(
                f"learner.inner ({inner.name}) has {dynamics or 'no lifted'} dynamics: the mirror "
                "average is built for lifted-linear models (z+ = A z + B v): edmd, deep_edmd"
            )
        settle(self, inner=inner)


class MirrorSymmetric(WrappingLearner):
    """``inner`` averaged with its mirror image: a lifted-linear model, symmetric by
    construction (module docstring)."""

    name: ClassVar[str] = "mirror_symmetric"
    config_class: ClassVar[type] = MirrorSymmetricConfig
    config: MirrorSymmetricConfig
    dynamics: ClassVar[Dynamics] = "linear"

    # -- the learner contract ---------------------------------------------------------------------

    def fit(
        self, train: Sequence[Episode], validation: Sequence[Episode], normalizer: MinMaxNormalizer
    ) -> Self:
        self.check_inputs(normalizer.channels)
        self.normalizer_ = normalizer
        self.inner.fit(train, validation, normalizer)
        self._read_inner()
        return self

    def predict(self, x0: np.ndarray, inputs: np.ndarray, **options: Any) -> np.ndarray:
        """The mean of the inner model's prediction and its mirror image's (``options`` as the
        inner learner's ``predict`` takes them)."""
        x0, inputs = check_rollout_args(
            x0, inputs, len(self.normalizer_.state_min), len(self.normalizer_.input_min)
        )
        direct = self.inner.predict(x0, inputs, **options)
        mirrored = self.inner.predict(x0 * STATE_MIRROR, inputs * self._input_signs, **options)
        return 0.5 * (direct + mirrored * STATE_MIRROR)

    def check_size(self, episode_frames: int, n: int = STATE_DIM, m: int = INPUT_DIM) -> None:
        self.inner.check_size(episode_frames, n, m)

    def check_inputs(self, channels: Sequence[InputChannel]) -> None:
        """Every input's role known (which of them steer), before any data."""
        input_mirror(channels, "the data")
        self.inner.check_inputs(channels)

    # -- the model DE-MPC reads -------------------------------------------------------------------

    def _read_inner(self) -> None:
        """A_, B_, C_ of the average, in the normalized units of the data.

        Min-max normalization makes the reflection affine there: x̃ ↦ S x̃ + c_x with
        c_x = (S min − min) / span (likewise the inputs), so the mirror copy steps under
        S_u v + c_u, the constant part through the last state, held at 1."""
        normalizer, inner = self.normalizer_, cast(Any, self.inner)
        self._input_signs = input_mirror(normalizer.channels, "the model's data")
        A, B, C = (np.asarray(m, dtype=float) for m in (inner.A_, inner.B_, inner.C_))
        state_offset = (
            STATE_MIRROR * normalizer.state_min - normalizer.state_min
        ) / normalizer.state_span
        input_offset = (
            self._input_signs * normalizer.input_min - normalizer.input_min
        ) / normalizer.input_span
        size = A.shape[0]
        direct, mirror, constant = slice(0, size), slice(size, 2 * size), 2 * size
        self.A_ = np.zeros((2 * size + 1, 2 * size + 1))
        self.A_[direct, direct] = A
        self.A_[mirror, mirror] = A
        self.A_[mirror, constant] = B @ input_offset
        self.A_[constant, constant] = 1.0
        self.B_ = np.zeros((2 * size + 1, B.shape[1]))
        self.B_[direct] = B
        self.B_[mirror] = B * self._input_signs
        self.C_ = np.zeros((C.shape[0], 2 * size + 1))
        self.C_[:, direct] = 0.5 * C
        self.C_[:, mirror] = 0.5 * STATE_MIRROR[:, None] * C
        self.C_[:, constant] = 0.5 * state_offset

    def lift(self, x: np.ndarray) -> np.ndarray:
        """[lift(x), lift of x's mirror image, 1]."""
        x = np.asarray(x, dtype=float)
        inner = cast(Any, self.inner)
        return np.concatenate(
            [inner.lift(x), inner.lift(x * STATE_MIRROR), np.ones((*x.shape[:-1], 1))], axis=-1
        )

    # -- the file ---------------------------------------------------------------------------------

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        self._set_inner_state(state, self.normalizer_)
