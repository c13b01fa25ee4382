"""SINDy with control (Brunton, Proctor & Kutz 2016; Kaiser et al. 2018): a sparse polynomial
model of the step, x_n⁺ = x_n + Ξᵀ θ(x_n, v), from every one-step pair of the training drives.

θ holds every monomial of y = [x_n; v] (normalized state and input, centred on the training
box: 2y − 1) up to ``degree``, the constant included: at degree 2 with three states and two
inputs, 21 terms, the vx·r and steering·vx products of the single-track equations among them.
Degree 3 (56 terms) fits the one-step pairs better but its whole-drive rollouts diverge on
``data=default`` (every threshold; degree 2 does not: docs/guide/learners.md). Ξ is fitted by
sequentially thresholded ridge least squares (STLSQ): fit, drop every term whose coefficient is
small (relative to its column's and its state's RMS), refit on the rest, until the terms stop
changing. The threshold is chosen from a list by the validation drives' open-loop rollouts, as
input EDMD chooses its ridge; 0 keeps every term (plain polynomial regression).

Polynomials extrapolate badly, so θ sees y clipped to the training box widened by
``observable_margin`` (normalized units), as input EDMD's observables do. Fitted, the model is a
:class:`~harness.core.contracts.LinearizableModel` in the normalized state (z = x_n, C = I):
its Jacobians are the monomials' derivatives, in closed form, so DE-MPC linearises it along its
plan with no other configuration.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self

import numpy as np
import torch

from harness.core.checks import integer, non_negative, positive, require
from harness.core.contracts import STATE_NAMES, Dynamics
from harness.core.episode import Episode, MinMaxNormalizer
from learners.base import Dim, Learner, Shape, check_fit_data, check_rollout_args
from learners.settings import settle

__all__ = ["SINDyC", "SINDyConfig", "monomial_exponents"]


def monomial_exponents(variables: int, degree: int) -> np.ndarray:
    """(F, variables) exponents of every monomial of total degree <= ``degree``, the constant
    (all zeros) first, then by degree."""
    rows = [np.zeros(variables, dtype=int)]
    for d in range(1, degree + 1):
        for combination in itertools.combinations_with_replacement(range(variables), d):
            row = np.zeros(variables, dtype=int)
            np.add.at(row, list(combination), 1)
            rows.append(row)
    return np.array(rows)


@dataclass(frozen=True)
class SINDyConfig:
    """SINDy's settings (``conf/learner/sindy.yaml``), checked when built."""

    degree: int = 2  # 21 terms for 3 states and 2 inputs (3: 56, its rollouts diverge)
    # In units of its state's RMS one-step change per unit RMS of its term: one number, or a
    # list chosen on the validation rollouts; 0 keeps every term (OmegaConf has no float | list).
    threshold: Any = (0.0, 0.03, 0.1, 0.3)
    ridge: float = 1e-8  # on unit-RMS columns
    iterations: int = 10  # threshold-and-refit rounds at most
    # theta sees (x, u) clipped to the training box widened by this (normalized); null:
    # unclipped.
    observable_margin: float | None = 0.0

    def __post_init__(self) -> None:
        threshold, margin = self.threshold, self.observable_margin
        thresholds = [threshold] if not isinstance(threshold, Sequence) else list(threshold)
        require(len(thresholds) > 0, "learner.threshold", "a number or a non-empty list", threshold)
        checked = tuple(non_negative("learner.threshold", value) for value in thresholds)
        settle(
            self,
            degree=integer("learner.degree", self.degree),
            threshold=checked if len(checked) > 1 else checked[0],
            ridge=positive("learner.ridge", self.ridge),
            iterations=integer("learner.iterations", self.iterations),
            observable_margin=(
                None if margin is None else non_negative("learner.observable_margin", margin)
            ),
        )


class SINDyC(Learner):
    """Sparse polynomial step model (see the module docstring).

    Settings (:class:`SINDyConfig`):
        degree: Highest total degree of the monomials of [x_n; v].
        threshold: A coefficient is dropped below this, in units of its state's RMS one-step
            change per unit RMS of its term; one number or a list to choose from on validation.
        ridge: Ridge weight of every least-squares fit (on unit-RMS columns).
        iterations: Most threshold-and-refit rounds.
        observable_margin: θ sees y clipped to [-margin, 1 + margin]; null: unclipped.

    Fitted attributes: ``coefficients_`` (F, n) = Ξ, ``threshold_``, ``normalizer_``, ``C_``.
    """

    name: ClassVar[str] = "sindy"
    config_class: ClassVar[type] = SINDyConfig
    config: SINDyConfig
    dynamics: ClassVar[Dynamics] = "nonlinear"  # DE-MPC linearises it along its plan

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        threshold = self.config.threshold
        self.degree = self.config.degree
        self.thresholds = list(threshold) if isinstance(threshold, tuple) else [threshold]
        self.ridge = self.config.ridge
        self.iterations = self.config.iterations
        self.margin = self.config.observable_margin

    # -- fitting ----------------------------------------------------------------------------

    def fit(
        self, train: Sequence[Episode], validation: Sequence[Episode], normalizer: MinMaxNormalizer
    ) -> Self:
        """STLSQ on every one-step pair of ``train``; the threshold by ``validation``."""
        check_fit_data(train, validation, normalizer, self.name)
        require(
            bool(validation) or len(self.thresholds) == 1,
            "learner.threshold",
            "one number when there are no validation drives to choose from",
            self.thresholds,
        )
        self.normalizer_ = normalizer
        n, m = len(normalizer.state_min), len(normalizer.input_min)
        self.exponents_ = monomial_exponents(n + m, self.degree)
        self.C_ = np.eye(n)
        # The normal equations of the unit-RMS columns, accumulated drive by drive.
        features = self.exponents_.shape[0]
        gram, cross = np.zeros((features, features)), np.zeros((features, n))
        squares, targets_squared, rows = np.zeros(features), np.zeros(n), 0
        for episode in train:
            z, v = normalizer.states(episode.states), normalizer.inputs(episode.inputs)
            theta = self._features(z[:-1], v[:-1])
            change = z[1:] - z[:-1]
            gram += theta.T @ theta
            cross += theta.T @ change
            squares += np.sum(theta**2, axis=0)
            targets_squared += np.sum(change**2, axis=0)
            rows += len(change)
        column_rms = np.sqrt(np.maximum(squares / rows, 1e-300))
        target_rms = np.sqrt(np.maximum(targets_squared / rows, 1e-300))
        scale = 1.0 / column_rms
        gram, cross = gram * np.outer(scale, scale), cross * scale[:, None]
        candidates = {
            t: self._stlsq(gram, cross, target_rms, t) * scale[:, None] for t in self.thresholds
        }
        self.validation_scores_: dict[float, float] = {}
        if len(candidates) == 1:
            ((self.threshold_, self.coefficients_),) = candidates.items()
            return self
        self.validation_scores_ = {t: self._score(xi, validation) for t, xi in candidates.items()}
        self.threshold_ = min(self.validation_scores_, key=lambda t: self.validation_scores_[t])
        self.coefficients_ = candidates[self.threshold_]
        return self

    def _stlsq(
        self, gram: np.ndarray, cross: np.ndarray, target_rms: np.ndarray, threshold: float
    ) -> np.ndarray:
        """Ξ (F, n) on unit-RMS columns: ridge fit, drop the small, refit the rest."""
        features, n = cross.shape
        xi = np.zeros((features, n))
        for state in range(n):
            keep = np.ones(features, dtype=bool)
            for _ in range(self.iterations):
                sub = gram[np.ix_(keep, keep)] + self.ridge * np.eye(int(keep.sum()))
                xi[:, state] = 0.0
                xi[keep, state] = np.linalg.solve(sub, cross[keep, state])
                small = np.abs(xi[:, state]) < threshold * target_rms[state]
                if not np.any(small & keep):
                    break
                keep &= ~small
                if not keep.any():
                    xi[:, state] = 0.0
                    break
        return xi

    def _score(self, coefficients: np.ndarray, episodes: Sequence[Episode]) -> float:
        """Mean over drives of Σ_i RMSE_i², open loop in normalized units; inf if it diverged."""
        total = 0.0
        for episode in episodes:
            z = self.normalizer_.states(episode.states)
            v = self.normalizer_.inputs(episode.inputs)
            with np.errstate(all="ignore"):
                predicted = self._rollout(coefficients, z[0], v[:-1])
            error = float(np.sum(np.mean((predicted - z) ** 2, axis=0)))
            total += error if np.isfinite(error) else np.inf
        return total / len(episodes)

    @property
    def fit_summary(self) -> dict[str, Any]:
        """The chosen threshold, the terms kept per state, and every candidate's score."""
        kept = {
            name: int(np.count_nonzero(column))
            for name, column in zip(STATE_NAMES, self.coefficients_.T, strict=True)
        }
        summary: dict[str, Any] = {"threshold": self.threshold_, "terms_kept": kept}
        scores = getattr(self, "validation_scores_", None)
        if scores:
            summary["validation_scores"] = {
                f"{t:g}": (s if np.isfinite(s) else None) for t, s in scores.items()
            }
        return summary

    # -- the model --------------------------------------------------------------------------

    def _clipped(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """y clipped to the widened training box, and where it was inside (the clip's slope)."""
        if self.margin is None:
            return y, np.ones_like(y)
        low, high = -self.margin, 1.0 + self.margin
        return np.clip(y, low, high), ((y >= low) & (y <= high)).astype(float)

    def _features(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        y, _ = self._clipped(np.concatenate([z, v], axis=-1))
        return np.prod((2.0 * y[..., None, :] - 1.0) ** self.exponents_, axis=-1)

    def _rollout(self, coefficients: np.ndarray, z0: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(..., T + 1, n) normalized states from z0 (..., n) under v (..., T, m)."""
        states = np.empty((*v.shape[:-1], z0.shape[-1]))
        states = np.concatenate([z0[..., None, :], states], axis=-2)
        for k in range(v.shape[-2]):
            z = states[..., k, :]
            states[..., k + 1, :] = z + self._features(z, v[..., k, :]) @ coefficients
        return states

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        n, m = len(self.normalizer_.state_min), len(self.normalizer_.input_min)
        x0, inputs = check_rollout_args(x0, inputs, n, m)
        z = self._rollout(
            self.coefficients_, self.normalizer_.states(x0), self.normalizer_.inputs(inputs)
        )
        predicted = self.normalizer_.states_inverse(z)
        predicted[..., 0, :] = x0  # row 0 is x0 itself, not its round trip
        return predicted

    # -- the LinearizableModel contract (normalized units) ----------------------------------

    def lift(self, x: np.ndarray) -> np.ndarray:
        return self.normalizer_.states(np.asarray(x, dtype=np.float64))

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        return z + self._features(z, v) @ self.coefficients_

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = z.shape[-1]
        y, inside = self._clipped(np.concatenate([z, v], axis=-1))  # (K, n + m)
        centred = 2.0 * y - 1.0  # the monomials' variable, in [-1, 1] on the training box
        exponents = self.exponents_  # (F, n + m)
        # ∂θ_f/∂y_j = 2 e_fj c^(e_f − δ_j): the power of c_j lowered by one where it appears.
        lowered = exponents[None, :, :] - np.eye(exponents.shape[1], dtype=int)[:, None, :]
        powers = np.where(lowered >= 0, centred[:, None, None, :], 1.0) ** np.maximum(lowered, 0)
        derivative = 2.0 * exponents.T[None] * np.prod(powers, axis=-1)  # (K, n + m, F)
        jacobian = (derivative @ self.coefficients_) * inside[..., None]  # (K, n + m, n)
        A = np.eye(n) + np.swapaxes(jacobian[:, :n], 1, 2)
        B = np.swapaxes(jacobian[:, n:], 1, 2)
        d = self.step(z, v) - (A @ z[..., None])[..., 0] - (B @ v[..., None])[..., 0]
        return A, B, d

    # -- model file -------------------------------------------------------------------------

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {"coefficients": self.coefficients_, "threshold": np.array([self.threshold_])}

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        terms = Dim("F", monomial_exponents(n + m, self.degree).shape[0], "monomials")
        return {"coefficients": (terms, n), "threshold": (1,)}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        self.coefficients_ = state["coefficients"].numpy().astype(np.float64)
        self.threshold_ = float(state["threshold"].numpy()[0])
        n = self.coefficients_.shape[1]
        self.C_ = np.eye(n)
        self.exponents_ = monomial_exponents(n + len(self.normalizer_.input_min), self.degree)
