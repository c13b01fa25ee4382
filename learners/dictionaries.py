"""Dictionaries of observables phi(x_n) for EDMD and its variants (:class:`learners.edmd.EDMD`).

A dictionary is the one thing that distinguishes the paper's EDMD baseline from ELM-EDMD: the
regression on z = [x_n; 1; phi(x_n)] is the same. Each dictionary is a small class built from
its config (``learner.dictionary`` with its own ``_target_``), drawn once from the normalized
training states by :meth:`Dictionary.fit` and then fixed. A new dictionary is one subclass here
(or anywhere under ``learners``) plus a ``dictionary:`` block in a learner config.

- :class:`ThinPlateRBF`: phi_i(x) = ||x - c_i||^2 log ||x - c_i|| (the paper's EDMD, Sec. VI),
  centres c_i ~ N(mean, std^2) of the normalized training states, per dimension, or drawn among
  the data points (input EDMD's observables of state and input).
- :class:`RandomFeatures`: phi(x) = sigma(W x + b), W and b uniform and never trained (the
  paper's ELM-EDMD, an extreme learning machine's hidden layer, Huang's classic ELM). On min-max
  normalized states in [0, 1]^3 a scale of a few puts the units' kinks and saturations inside
  the data.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Any, Self

import numpy as np

from harness.core.checks import choice, integer, positive
from learners.base import Dim, Shape
from learners.model_file import package_class

__all__ = ["ACTIVATIONS", "Dictionary", "RandomFeatures", "ThinPlateRBF", "dictionary_from"]

ACTIVATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "tanh": np.tanh,
    "sigmoid": lambda a: 0.5 * (1.0 + np.tanh(0.5 * a)),
    "relu": lambda a: np.maximum(a, 0.0),
    "sin": np.sin,
}

DERIVATIVES: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "tanh": lambda a: 1.0 - np.tanh(a) ** 2,
    "sigmoid": lambda a: 0.25 * (1.0 - np.tanh(0.5 * a) ** 2),
    "relu": lambda a: (a > 0).astype(np.float64),
    "sin": np.cos,
}

CENTER_DRAWS = ("normal", "samples")


class Dictionary(ABC):
    """Observables phi: (..., n) -> (..., K) of normalized states, drawn once from data.

    Subclasses are dataclasses: their fields are the hyperparameters (the config's keys, saved
    in the model file; ``__post_init__`` checks them); the drawn arrays are attributes ending in
    ``_`` (what ``state`` returns, saved as tensors).
    """

    @property
    @abstractmethod
    def size(self) -> tuple[str, int]:
        """(its config key, K): how many observables it adds, for size checks and messages."""

    def floats_per_row(self, n: int) -> int:
        """The largest temporary of evaluating phi on one state row (float64 count): K."""
        return self.size[1]

    @abstractmethod
    def fit(self, states_n: np.ndarray, rng: np.random.Generator) -> Self:
        """Draw the parameters from the normalized training states (M, n) with ``rng``."""

    @abstractmethod
    def __call__(self, x_n: np.ndarray) -> np.ndarray:
        """phi(x_n): (..., n) -> (..., K)."""

    def jacobian(self, x_n: np.ndarray) -> np.ndarray:
        """d phi / d x_n: (..., n) -> (..., K, n), for models an MPC linearises."""
        raise NotImplementedError(f"{type(self).__name__} has no jacobian")

    @property
    def hyperparameters(self) -> dict[str, Any]:
        """The fields, with ``_target_`` naming the class: a config block and a file entry."""
        target = f"{type(self).__module__}.{type(self).__qualname__}"
        values = {f.name: getattr(self, f.name) for f in fields(self)}  # type: ignore[arg-type]
        return {"_target_": target, **values}

    @abstractmethod
    def state(self) -> dict[str, np.ndarray]:
        """The drawn arrays, to save (keys must not be A, B or C)."""

    @abstractmethod
    def set_state(self, state: Mapping[str, np.ndarray]) -> None:
        """Restore what :meth:`state` returned."""

    @abstractmethod
    def state_shapes(self, width: int) -> dict[str, Shape]:
        """The shape of every array of :meth:`state` on points of ``width`` coordinates."""

    def _count(self) -> Dim:
        """K, named by its config key (for a model file's shape messages)."""
        key, size = self.size
        return Dim("K", size, f"learner.{key}")


def dictionary_from(value: Dictionary | Mapping[str, Any] | None) -> Dictionary:
    """A fresh, unfitted dictionary like ``value``: a built one (its copy, so that two learners
    never share drawn arrays), its ``hyperparameters`` (a model file) or None (thin-plate RBFs).

    Only classes under ``learners`` are built, as :func:`learners.model_file.load` does for
    learners.
    """
    if value is None:
        return ThinPlateRBF()
    values = dict(value.hyperparameters if isinstance(value, Dictionary) else value)
    target = str(values.pop("_target_", ""))
    cls = package_class(target, Dictionary, "a dictionary class", "learner.dictionary._target_")
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(map(str, values)) - set(names))
    if unknown:
        raise ValueError(
            f"unknown key learner.dictionary.{unknown[0]}; known keys: {', '.join(names)}"
        )
    return cls(**values)


@dataclass(eq=False)
class ThinPlateRBF(Dictionary):
    """``num_centers`` thin-plate-spline radial basis functions (0 gives DMD with inputs).

    Args:
        num_centers: K.
        center_draw: ``normal``: centres ~ N(mean, std²) of the data, per coordinate (the
            paper's EDMD); ``samples``: K distinct data points. In more than three dimensions
            (state and input) independent normal draws land where the data never goes, and a
            thin-plate RBF grows like r² log r there; centres on the data keep every observable
            anchored where the fit sees it (``learners/input_edmd.py`` measures the difference).
    """

    num_centers: int = 100
    center_draw: str = "normal"

    def __post_init__(self) -> None:
        self.num_centers = integer("learner.dictionary.num_centers", self.num_centers, 0)
        self.center_draw = choice("learner.dictionary.center_draw", self.center_draw, CENTER_DRAWS)

    @property
    def size(self) -> tuple[str, int]:
        return "dictionary.num_centers", self.num_centers

    def floats_per_row(self, n: int) -> int:
        """``x_n[..., None, :] - centers``: K·n per row."""
        return self.num_centers * n

    def fit(self, states_n: np.ndarray, rng: np.random.Generator) -> Self:
        if self.center_draw == "samples":
            if len(states_n) < self.num_centers:
                raise ValueError(
                    f"dictionary.num_centers={self.num_centers} centres drawn from the data need "
                    f"as many samples, the training drives hold {len(states_n)}"
                )
            rows = rng.choice(len(states_n), self.num_centers, replace=False)
            self.centers_ = np.array(states_n[np.sort(rows)], dtype=np.float64)
            return self
        mean, std = states_n.mean(0), states_n.std(0)
        self.centers_ = rng.normal(mean, std, size=(self.num_centers, states_n.shape[1]))
        return self

    def __call__(self, x_n: np.ndarray) -> np.ndarray:
        # ||x - c||² = ||x||² + ||c||² - 2 x·c: one matrix product instead of a (rows, K, n)
        # temporary (5x faster at 500 centres in 5 dimensions); the cancellation error (~1e-16
        # on normalized data) is far below any distance that matters, and r² is clipped at 0.
        c = self.centers_
        r2 = np.sum(x_n * x_n, axis=-1, keepdims=True) + np.sum(c * c, axis=-1) - 2.0 * (x_n @ c.T)
        r2 = np.maximum(r2, 0.0)
        # r^2 log r = r^2 log(r^2) / 2, continuous with value 0 at r = 0
        return 0.5 * r2 * np.log(np.where(r2 > 0, r2, 1.0))

    def jacobian(self, x_n: np.ndarray) -> np.ndarray:
        """(log r² + 1)(x − c) for each centre c: continuous, 0 at r = 0."""
        offset = x_n[..., None, :] - self.centers_
        r2 = np.sum(offset**2, axis=-1, keepdims=True)
        return np.where(r2 > 0, np.log(np.where(r2 > 0, r2, 1.0)) + 1.0, 0.0) * offset

    def state(self) -> dict[str, np.ndarray]:
        return {"centers": self.centers_}

    def set_state(self, state: Mapping[str, np.ndarray]) -> None:
        self.centers_ = np.asarray(state["centers"], dtype=np.float64)

    def state_shapes(self, width: int) -> dict[str, Shape]:
        return {"centers": (self._count(), width)}


@dataclass(eq=False)
class RandomFeatures(Dictionary):
    """``num_features`` random units sigma(w . x + b), w ~ U(+-weight_scale), b ~ U(+-bias_scale).

    Args:
        num_features: K, the number of random hidden units.
        activation: One of tanh, sigmoid, relu, sin.
        weight_scale: Half-width of the uniform distribution of the input weights.
        bias_scale: Half-width of the uniform distribution of the biases.
    """

    num_features: int = 100
    activation: str = "tanh"
    weight_scale: float = 4.0
    bias_scale: float = 2.0

    def __post_init__(self) -> None:
        key = "learner.dictionary."
        self.num_features = integer(key + "num_features", self.num_features, 1)
        self.activation = choice(key + "activation", self.activation, tuple(ACTIVATIONS))
        self.weight_scale = positive(key + "weight_scale", self.weight_scale)
        self.bias_scale = positive(key + "bias_scale", self.bias_scale)

    @property
    def size(self) -> tuple[str, int]:
        return "dictionary.num_features", self.num_features

    def fit(self, states_n: np.ndarray, rng: np.random.Generator) -> Self:
        n = states_n.shape[1]
        self.weights_ = rng.uniform(-self.weight_scale, self.weight_scale, (self.num_features, n))
        self.biases_ = rng.uniform(-self.bias_scale, self.bias_scale, self.num_features)
        return self

    def __call__(self, x_n: np.ndarray) -> np.ndarray:
        return ACTIVATIONS[self.activation](x_n @ self.weights_.T + self.biases_)

    def jacobian(self, x_n: np.ndarray) -> np.ndarray:
        """sigma'(w . x + b) w for each unit (by the activation's derivative)."""
        slope = DERIVATIVES[self.activation](x_n @ self.weights_.T + self.biases_)
        return slope[..., :, None] * self.weights_

    def state(self) -> dict[str, np.ndarray]:
        return {"weights": self.weights_, "biases": self.biases_}

    def set_state(self, state: Mapping[str, np.ndarray]) -> None:
        self.weights_ = np.asarray(state["weights"], dtype=np.float64)
        self.biases_ = np.asarray(state["biases"], dtype=np.float64)

    def state_shapes(self, width: int) -> dict[str, Shape]:
        return {"weights": (self._count(), width), "biases": (self._count(),)}
