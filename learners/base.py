"""The base class every learner shares (its file format: :mod:`learners.model_file`).

Every learner models x_{k+1} = f(x_k, u_k) for x = (vx, vy, yaw_rate) [m/s, m/s, rad/s] and
u = (steer_wheel_deg, pedal). Learners train in the min-max normalized coordinates of
:class:`~harness.core.episode.MinMaxNormalizer` (fitted on the training episodes only) and speak
physical units at their interface.

Koopman learners additionally expose a lifted linear model for the MPC::

    z_0     = lift(x_0)                                  (N,)
    z_{k+1} = A_ @ z_k + B_ @ normalizer_.inputs(u_k)
    x_hat_k = normalizer_.states_inverse(C_ @ z_k)

In every Koopman learner of this package the lifted state starts with the normalized state
itself, z = [normalizer_.states(x); ...], so ``C_ = [I 0]`` exactly (EDMD's "the lifted state
includes x"); Deep EDMD with ``lifted_includes_state=false`` is the one exception and fits
``C_`` by least squares (the paper's eq. for C).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import is_dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, ClassVar, Self

import numpy as np
import torch

from harness.core import contracts
from harness.core.contracts import STATE_NAMES
from harness.core.episode import Episode, InputChannel, MinMaxNormalizer
from learners.model_file import INPUT_DIM, STATE_DIM, Dim, Shape, load, write
from learners.settings import NoSettings, plain

__all__ = [
    "INPUT_DIM",
    "STATE_DIM",
    "Dim",
    "KoopmanLearner",
    "Learner",
    "Shape",
    "check_fit_data",
    "check_rollout_args",
]


class Learner(contracts.RunLearner, ABC):
    """The ABC that implements :class:`harness.core.contracts.RunLearner`: a model of
    x_{k+1} = f(x_k, u_k) learned from episodes, saved to and loaded from one file format.

    Subclasses set ``name`` (their config-group name, used in messages and file names) and
    ``config_class``, the frozen dataclass of their settings (:mod:`learners.settings`; none by
    default): the learner takes its fields as keywords (or in order), so that a config maps 1:1
    to the code, and keeps them, checked, as ``config``.
    """

    name: ClassVar[str]
    config_class: ClassVar[type] = NoSettings
    config: Any

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        abstract = any(
            getattr(getattr(cls, attr, None), "__isabstractmethod__", False) for attr in dir(cls)
        )
        if not abstract and not isinstance(getattr(cls, "name", None), str):
            raise TypeError(f"{cls.__qualname__} must set the class attribute `name`")
        if not is_dataclass(cls.config_class):
            raise TypeError(f"{cls.__qualname__}.config_class must be its settings dataclass")

    def __init__(self, *args: Any, **settings: Any) -> None:
        self.config = self.config_class(*args, **settings)

    @abstractmethod
    def fit(
        self,
        train: Sequence[Episode],
        validation: Sequence[Episode],
        normalizer: MinMaxNormalizer,
    ) -> Self:
        """As :meth:`harness.core.contracts.Learner.fit`."""

    @abstractmethod
    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """As :meth:`harness.core.contracts.Learner.predict`."""

    def save(self, path: str | Path, provenance: Mapping[str, Any] | None = None) -> Path:
        """As :meth:`harness.core.contracts.Learner.save`; the file is read back by
        :func:`learners.model_file.load`.

        ``provenance``: plain values in the caller's words (plant, dataset); None keeps what
        the file it was loaded from said.

        Raises:
            ValueError: (one line) when a fitted array is NaN, infinite or mis-shaped: a
                diverged fit is reported, never saved as a model.
        """
        return write(self, path, provenance)

    @classmethod
    def load(cls, path: str | Path) -> Learner:
        """Read a file written by :meth:`save` (of this class or, from ``Learner``, any class)."""
        learner = load(path)
        if not isinstance(learner, cls):
            raise ValueError(f"{path} holds a {type(learner).__name__}, not a {cls.__name__}")
        return learner

    @classmethod
    def from_hyperparameters(cls, hyperparameters: Mapping[str, Any]) -> Self:
        """The learner a model file's ``hyperparameters`` describe (unfitted)."""
        return cls(**hyperparameters)

    def check_size(self, episode_frames: int, n: int = STATE_DIM, m: int = INPUT_DIM) -> None:
        """Refuse, in one line naming the key, sizes whose fit on episodes of up to
        ``episode_frames`` frames cannot fit in this machine's memory (see
        :mod:`harness.core.budget`); called before any data is collected. The default checks
        nothing: a learner that can be configured too big overrides it."""
        del episode_frames, n, m

    def check_inputs(self, channels: Sequence[InputChannel]) -> None:
        """Refuse, in one line, inputs this learner cannot be fitted on (``channels``, in order,
        as the data config gives them: names, and roles where declared); called before any
        data is collected. The default takes any inputs: a learner that needs a particular one
        overrides it."""
        del channels

    @property
    def redraws_random_layer(self) -> bool:
        """Whether ``predict(..., random_layer_seed=s)`` draws a fresh random layer each call (the
        paper's robustness experiment): only such learners get repeated predictions."""
        return False

    @property
    def core(self) -> Learner:
        """The learner that trains and holds the state matrices: itself, or the one a wrapper
        fits (:class:`learners.split_pedal.SplitPedal`); a run reports its loss curves and
        spectrum."""
        return self

    @property
    def hyperparameters(self) -> dict[str, Any]:
        """The settings this learner was built with, as plain data (what its config holds and
        its model file keeps)."""
        return plain(self.config)

    @property
    def fit_summary(self) -> dict[str, Any]:
        """Empty unless a learner chooses something, as input EDMD its ridge."""
        return {}

    # -- for subclasses -------------------------------------------------------------------------

    # What the model was trained on, as its file said (plant, dataset; empty for a model fitted
    # here, or a file from before it was recorded): the caller compares it with its own run.
    provenance_: Mapping[str, Any] = MappingProxyType({})

    @abstractmethod
    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        """The fitted arrays that, with the hyperparameters and normalizer, define the model."""

    @abstractmethod
    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        """The shape of every array of :meth:`_state`, from the hyperparameters alone (n states,
        m inputs): what a model file is checked against before :meth:`_set_state` reads it."""

    @abstractmethod
    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        """Restore what :meth:`_state` returned (called on a freshly constructed learner)."""


class KoopmanLearner(Learner, contracts.LiftedModel):
    """A learner whose model is linear in a lifted state (see the module docstring): fitted, it
    is a :class:`~harness.core.contracts.LiftedModel` (``A_``, ``B_``, ``C_`` as float64 arrays,
    ``normalizer_``, ``lift``)."""

    dynamics: ClassVar[contracts.Dynamics] = "linear"


def check_episodes(
    episodes: Sequence[Episode], role: str, normalizer: MinMaxNormalizer, min_length: int = 2
) -> None:
    """Refuse empty, too short, mis-shaped or non-finite episodes in one line naming the episode."""
    if not episodes:
        raise ValueError(f"no {role} episodes")
    n, m = normalizer.state_min.shape[0], normalizer.input_min.shape[0]
    for e in episodes:
        if e.states.ndim != 2 or e.states.shape[1] != n or e.inputs.shape[1:] != (m,):
            raise ValueError(
                f"{role} episode {e.name!r}: states {e.states.shape} / inputs {e.inputs.shape} "
                f"do not match the normalizer's {n} states and {m} inputs"
            )
        if len(e) < min_length:
            raise ValueError(f"{role} episode {e.name!r} has {len(e)} samples, need {min_length}")
        for field in ("states", "inputs"):
            if not np.all(np.isfinite(getattr(e, field))):
                raise ValueError(f"{role} episode {e.name!r}: {field} contain NaN or inf")


def check_fit_data(
    train: Sequence[Episode],
    validation: Sequence[Episode],
    normalizer: MinMaxNormalizer,
    learner: str,
) -> None:
    """What every ``fit`` checks first: the training episodes, and the validation ones if any;
    and that every state and input varies in the training ones (``learner`` names the fit)."""
    check_episodes(train, "train", normalizer)
    if validation:
        check_episodes(validation, "validation", normalizer)
    check_varied(train, learner)


# A training column whose range is below this, in its unit (relative to its size where that is
# above 1), never varied: no model learns what it does, and min-max scaling by that range sends
# any other value a million spans and more away (a steering wheel held within 1e-9 deg gave input
# EDMD NaN predictions, and DE-MPC a QP that failed, far from the cause).
MIN_TRAINING_RANGE = 1e-6


def check_varied(train: Sequence[Episode], learner: str) -> None:
    """Refuse, in one line naming the learner and the column, training drives in which a state or
    an input stays (all but) constant (see ``MIN_TRAINING_RANGE``)."""
    for field, names in (("states", STATE_NAMES), ("inputs", train[0].input_names)):
        values = np.concatenate([getattr(e, field) for e in train])
        low, high = values.min(0), values.max(0)
        size = np.maximum(np.maximum(np.abs(low), np.abs(high)), 1.0)
        constant = np.flatnonzero(high - low < MIN_TRAINING_RANGE * size)
        if constant.size:
            column = int(constant[0])
            name = names[column] if values.shape[1] == len(names) else f"{field}[{column}]"
            drives = ", ".join(e.name for e in train[:3]) + (", ..." if len(train) > 3 else "")
            raise ValueError(
                f"{learner} cannot learn from the training drives ({drives}): {name} stays at "
                f"{low[column]:.6g} (range {high[column] - low[column]:.1e} over {len(values)} "
                f"frames), so what it does is not in the data; train on drives that vary {name} "
                "(collected: data.driver.*; logs: the files of data.split.train)"
            )


def check_rollout_args(x0: np.ndarray, inputs: np.ndarray, n: int, m: int) -> tuple:
    """Validate predict() arguments; returns float64 arrays (x0 (..., n), inputs (..., T, m))."""
    x0 = np.asarray(x0, dtype=np.float64)
    inputs = np.asarray(inputs, dtype=np.float64)
    if x0.shape[-1:] != (n,) or inputs.ndim < 2 or inputs.shape[-1] != m:
        raise ValueError(
            f"predict needs x0 (..., {n}) and inputs (..., T, {m}); "
            f"got {x0.shape} and {inputs.shape}"
        )
    if inputs.shape[:-2] != x0.shape[:-1]:
        raise ValueError(f"predict: batch shapes differ, x0 {x0.shape} vs inputs {inputs.shape}")
    return x0, inputs
