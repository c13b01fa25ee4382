"""ELM-EDMD: EDMD whose observables are an extreme learning machine's random hidden layer.

The paper replaces the RBF kernels of its EDMD baseline by extreme learning machines: the
lifted state is z = [x_n; 1; sigma(W x_n + b)] with W, b drawn once at random (seeded) and never
trained; [A B] then come from the same ridge least squares as EDMD (:mod:`learners.edmd`).
Weights and biases are uniform in [-scale, scale] (Huang's classic ELM); on min-max normalized
states in [0, 1]^3 a scale of a few puts the units' kinks and saturations inside the data.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from learners.base import check_choice, check_int, check_positive
from learners.edmd import LiftedLinearLearner

__all__ = ["ACTIVATIONS", "ELMEDMD"]

ACTIVATIONS = {
    "tanh": np.tanh,
    "sigmoid": lambda a: 0.5 * (1.0 + np.tanh(0.5 * a)),
    "relu": lambda a: np.maximum(a, 0.0),
    "sin": np.sin,
}


class ELMEDMD(LiftedLinearLearner):
    """EDMD on ``num_features`` random ELM units (see the module docstring).

    Args:
        num_features: K, the number of random hidden units.
        activation: One of tanh, sigmoid, relu, sin.
        weight_scale: Half-width of the uniform distribution of the input weights.
        bias_scale: Half-width of the uniform distribution of the biases.
        ridge: Tikhonov weight relative to the mean squared one-step residual.
        include_constant: Add the observable 1 to the lifted state.
        seed: Seed of the random layer.
    """

    name: ClassVar[str] = "elm_edmd"

    def __init__(
        self,
        num_features: int = 100,
        activation: str = "tanh",
        weight_scale: float = 4.0,
        bias_scale: float = 2.0,
        ridge: float = 1e-8,
        include_constant: bool = True,
        seed: int = 0,
    ) -> None:
        super().__init__(ridge=ridge, include_constant=include_constant, seed=seed)
        self.num_features = check_int("num_features", num_features, 1)
        self.activation = check_choice("activation", activation, tuple(ACTIVATIONS))
        self.weight_scale = check_positive("weight_scale", weight_scale)
        self.bias_scale = check_positive("bias_scale", bias_scale)
        self._hyperparameters: dict[str, Any] = {
            "num_features": self.num_features,
            "activation": self.activation,
            "weight_scale": self.weight_scale,
            "bias_scale": self.bias_scale,
            "ridge": self.ridge,
            "include_constant": self.include_constant,
            "seed": self.seed,
        }

    def _init_observables(self, states_n: np.ndarray, rng: np.random.Generator) -> None:
        n = states_n.shape[1]
        self.weights_ = rng.uniform(-self.weight_scale, self.weight_scale, (self.num_features, n))
        self.biases_ = rng.uniform(-self.bias_scale, self.bias_scale, self.num_features)

    def _observables(self, x_n: np.ndarray) -> np.ndarray:
        return ACTIVATIONS[self.activation](x_n @ self.weights_.T + self.biases_)

    def _observable_state(self) -> dict[str, np.ndarray]:
        return {"weights": self.weights_, "biases": self.biases_}

    def _set_observable_state(self, state: Mapping[str, np.ndarray]) -> None:
        self.weights_ = state["weights"].astype(np.float64)
        self.biases_ = state["biases"].astype(np.float64)
