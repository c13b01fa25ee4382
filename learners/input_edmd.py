"""Input EDMD: EDMD whose observables are functions of the state *and* the input, re-lifted
every step (Koopman with inputs and control, Proctor, Brunton & Kutz, SIAM J. Appl. Dyn. Syst.
2018; the "re-lifting" predictor of the bilinear-learners issue).

With y = [x_n; v] (normalized state and input) and the observables w(y) = [y; 1; phi(y)]::

    x_n,{k+1} = x_n,k + Theta^T w([x_n,k; v_k])

Theta is EDMD's exact ridge least squares on the one-step pairs, projected on the state (the
observables of the next input are not predicted: the next input is the controller's). The
prediction lifts the predicted state again at every step, so the model is nonlinear in x and in
u; DE-MPC linearises it along its plan (:class:`~harness.core.contracts.LinearizableModel`: lift is
the normalization, C = I, the Jacobians are the dictionary's, by hand).

Why the input inside the observables: the lateral force of a tyre saturates in its slip angle,
a function of steering *and* state, so the response to the steering wheel is nonlinear in the
input itself, which no model affine in u (linear or bilinear Koopman) represents. Measured on
``data=default`` (open-loop RMSE of the yaw rate over the whole test drives episode_0000 /
episode_0010, seeds 0-2, ``python -m bench.input_structure``): EDMD 0.17-1.9 / 0.11-0.12 rad/s,
bilinear EDMD 0.086-0.10 / 0.060-0.066, this fit and predictor with bilinear observables of x
(affine in u, as many columns) 0.065-0.070 / 0.074 or diverged, input EDMD 0.027-0.031 /
0.015-0.027 (the single-track baseline: 0.118 / 0.041).

Two choices make the fit hold over 20-40 s drives. The centres are data points
(``center_draw: samples``): drawn from N(mean, std²) per coordinate in five dimensions they
land where the data never goes, the r² log r observables grow there unconstrained, and for 6
of 9 draws (seeds 0-2 × 200, 300, 500 centres) every ridge from 1e-8 to 1e-4 diverged on a
validation drive; on data points none of 12 did (150-800 centres). And the ridge is
chosen per fit, on the validation drives' open-loop rollouts, from ``ridge`` (a list): the one
step residual barely depends on it, whether a 30 s rollout stays bounded does.

A third makes it hold over runs of minutes: the observables are evaluated at y clipped to the
box the training data span (min-max normalized: [0, 1] per coordinate, widened by
``observable_margin``). Outside its data a thin-plate RBF r² log r grows without bound, so a
rollout that drifts a little past the data is pushed further by observables fitted where it
never was. On the DDK CarSim runs (450 s each, 50 ms) every ridge from 1e-9 to 1e-2 diverged on
the validation runs unclipped; clipped at the box (margin 0) none did, and the whole test runs
predict at 1.83 / 0.033 / 0.021 (vx m/s, vy m/s, r rad/s; persistence 5.18 / 0.12 / 0.083).
The linear part [x_n; v] still extrapolates, so the model is not frozen outside the box.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self

import numpy as np
import torch

from harness.core.budget import check_memory
from harness.core.checks import boolean, integer, non_negative
from harness.core.contracts import Dynamics
from harness.core.episode import Episode, MinMaxNormalizer
from learners.base import (
    INPUT_DIM,
    STATE_DIM,
    Dim,
    Learner,
    Shape,
    check_fit_data,
    check_rollout_args,
)
from learners.dictionaries import ThinPlateRBF, dictionary_from
from learners.linalg import Triangle, ridge_weights, row_chunks
from learners.settings import settle

__all__ = ["InputEDMD", "InputEDMDConfig"]

log = logging.getLogger(__name__)

_CHUNK_ROWS = 5_000  # rows of observables at a time: K·(n + m) floats of temporaries each


@dataclass(frozen=True)
class InputEDMDConfig:
    """Input EDMD's settings (``conf/learner/input_edmd.yaml``), checked when built."""

    # The observables phi(y) of y = [x_n; v] (a Dictionary with a jacobian, or its block with
    # ``_target_``); null: 500 thin-plate RBFs centred on distinct training points (y).
    dictionary: Any = None
    # Tikhonov weight(s) relative to the mean squared residual; with several, the one whose
    # open-loop rollouts of the validation drives are best (OmegaConf has no float | list).
    ridge: Any = (1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2)
    include_constant: bool = True  # the observable 1
    seed: int = 0  # of the centres' draw
    # The observables see (x, u) clipped to the training box, widened by this much on each
    # side (normalized); null: unclipped.
    observable_margin: float | None = 0.0

    def __post_init__(self) -> None:
        ridges = ridge_weights(self.ridge)
        margin = self.observable_margin
        settle(
            self,
            dictionary=dictionary_from(
                self.dictionary
                if self.dictionary is not None
                else ThinPlateRBF(500, center_draw="samples")
            ),
            ridge=tuple(ridges) if len(ridges) > 1 else ridges[0],
            include_constant=boolean("learner.include_constant", self.include_constant),
            seed=integer("learner.seed", self.seed, 0),
            observable_margin=(
                None if margin is None else non_negative("learner.observable_margin", margin)
            ),
        )


class InputEDMD(Learner):
    """EDMD on observables of (state, input), re-lifted every step (module docstring).

    Settings (:class:`InputEDMDConfig`):
        dictionary: The observables phi of y = [x_n; v] (a
            :class:`~learners.dictionaries.Dictionary` with a ``jacobian``, or its
            hyperparameters); None gives 500 thin-plate RBFs centred on data points.
        ridge: Tikhonov weight(s), relative to the mean squared residual; with several, the
            one whose open-loop rollouts of the validation drives are best.
        include_constant: Add the observable 1.
        seed: Seed of the dictionary's draw.
        observable_margin: The observables see y clipped to the training data's box, [0, 1]
            per normalized coordinate widened by this much on each side; None: unclipped (module
            docstring: why).

    Fitted attributes: ``theta_`` (regressors, n), ``ridge_`` (the chosen weight),
    ``validation_scores_`` (ridge -> mean normalized squared RMSE of the validation rollouts,
    inf where one diverged), ``C_`` = I, ``normalizer_``.
    """

    name: ClassVar[str] = "input_edmd"
    config_class: ClassVar[type] = InputEDMDConfig
    config: InputEDMDConfig
    dynamics: ClassVar[Dynamics] = "nonlinear"  # DE-MPC linearises it along its plan

    C_: np.ndarray

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        self.dictionary = dictionary_from(self.config.dictionary)  # its own, to draw and fit
        self.ridges = ridge_weights(self.config.ridge)
        self.include_constant = self.config.include_constant
        self.seed = self.config.seed
        self.margin = self.config.observable_margin

    @classmethod
    def from_hyperparameters(cls, hyperparameters: Mapping[str, Any]) -> Self:
        """A model file from before ``observable_margin`` evaluated its observables unclipped."""
        return cls(**{"observable_margin": None, **hyperparameters})

    # -- fitting ----------------------------------------------------------------------------

    def fit(
        self, train: Sequence[Episode], validation: Sequence[Episode], normalizer: MinMaxNormalizer
    ) -> Self:
        """Least squares on every one-step pair of ``train``; the ridge by ``validation``."""
        check_fit_data(train, validation, normalizer, self.name)
        if not validation and len(self.ridges) > 1:
            raise ValueError(
                f"learner.ridge lists {len(self.ridges)} weights to choose from on the "
                "validation drives, but there are none: give one weight or a validation split"
            )
        n, m = normalizer.state_min.shape[0], normalizer.input_min.shape[0]
        self.check_size(max(len(e) for e in train), n, m)
        pairs = sum(len(e) - 1 for e in train)
        if pairs < self.regressor_count(n, m):
            key, size = self.dictionary.size
            raise ValueError(
                f"input_edmd with learner.{key}={size} has {self.regressor_count(n, m)} unknowns "
                f"per state but the training drives hold only {pairs} one-step pairs: collect "
                "longer drives (data.min_steps) or use fewer observables"
            )
        self.normalizer_ = normalizer
        self.C_ = np.eye(n)
        points = np.concatenate(
            [
                self._dictionary_points(normalizer.states(e.states), normalizer.inputs(e.inputs))
                for e in train
            ]
        )
        self.dictionary.fit(points, np.random.default_rng(self.seed))

        def rows() -> Iterator[tuple[np.ndarray, np.ndarray]]:
            for e in train:
                x_n, v = normalizer.states(e.states), normalizer.inputs(e.inputs)
                for part in row_chunks(x_n[:-1], _CHUNK_ROWS):
                    w = self._observables(x_n[:-1][part], v[:-1][part])
                    yield w, x_n[1:][part] - x_n[:-1][part]

        # The ridge weighs every observable by its spread: columns scaled to unit RMS (on the
        # reduced triangle, so the observables are evaluated once).
        triangle = Triangle.of(rows())
        scale = triangle.column_rms()
        scale[scale < 1e-12] = 1.0
        triangle = triangle.scaled(scale)
        thetas = np.stack([triangle.solve(ridge) / scale[:, None] for ridge in self.ridges])
        scores = self._scores(thetas, validation) if len(self.ridges) > 1 else np.zeros(1)
        self.validation_scores_ = dict(zip(self.ridges, scores.tolist(), strict=True))
        if not np.isfinite(scores).any():
            raise ValueError(
                f"input_edmd: every ridge in learner.ridge={self.ridges} diverged on the "
                "validation drives' open-loop rollouts: add larger weights or fewer observables"
            )
        best = int(np.argmin(np.where(np.isfinite(scores), scores, np.inf)))
        self.ridge_, self.theta_ = self.ridges[best], thetas[best]
        log.info("input_edmd: ridge %.0e chosen on the validation drives", self.ridge_)
        return self

    @property
    def fit_summary(self) -> dict[str, Any]:
        """The chosen ridge and, after a fit here, every candidate's validation score (null where
        its rollout diverged)."""
        summary: dict[str, Any] = {"ridge": self.ridge_}
        scores = getattr(self, "validation_scores_", None)
        if scores:
            summary["validation_scores"] = {
                f"{ridge:g}": (score if np.isfinite(score) else None)
                for ridge, score in scores.items()
            }
        return summary

    def regressor_count(self, n: int = STATE_DIM, m: int = INPUT_DIM) -> int:
        """Columns of the least squares: y = [x_n; v], the constant, and the observables."""
        return n + m + int(self.include_constant) + self.dictionary.size[1]

    def check_size(self, episode_frames: int, n: int = STATE_DIM, m: int = INPUT_DIM) -> None:
        """Refuse a dictionary too big for this machine, before any data (as EDMD's)."""
        key, size = self.dictionary.size
        width = self.regressor_count(n, m) + n
        rows = min(episode_frames, _CHUNK_ROWS)
        floats = rows * (self.dictionary.floats_per_row(n + m) + width)
        floats += 2 * (width + _CHUNK_ROWS) * width
        what = f"input EDMD with {size} observables on drives of {episode_frames} steps"
        check_memory(f"learner.{key}", what, 8 * floats)

    def _scores(self, thetas: np.ndarray, episodes: Sequence[Episode]) -> np.ndarray:
        """Per candidate Theta (R, regressors, n): the mean over drives of sum_i (RMSE_i /
        span_i)², open loop in normalized units; inf where a rollout diverged. The R rollouts
        of a drive run together, one step for all of them at a time."""
        totals = np.zeros(len(thetas))
        for e in episodes:
            target, v = self.normalizer_.states(e.states), self.normalizer_.inputs(e.inputs)
            x = np.repeat(target[:1], len(thetas), axis=0)
            squared = np.zeros(len(thetas))
            with np.errstate(over="ignore", invalid="ignore"):  # diverging candidates: inf/nan
                for k in range(len(e) - 1):
                    w = self._observables(x, np.broadcast_to(v[k], (len(thetas), v.shape[1])))
                    x = x + np.einsum("rd,rdn->rn", w, thetas)
                    squared += np.sum((x - target[k + 1]) ** 2, axis=1)
            totals += squared / len(e)
        scores = totals / len(episodes)
        return np.where(np.isfinite(scores), scores, np.inf)

    # -- prediction -------------------------------------------------------------------------

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        n, m = self.C_.shape[0], self.normalizer_.input_min.shape[0]
        x0, inputs = check_rollout_args(x0, inputs, n, m)
        x_n = self._rollout(self.normalizer_.states(x0), self.normalizer_.inputs(inputs))
        with np.errstate(over="ignore", invalid="ignore"):
            x = self.normalizer_.states_inverse(x_n)
        x[..., 0, :] = x0
        return x

    def _rollout(self, x0_n: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Normalized states (..., T + 1, n) from x0_n (..., n) under v (..., T, m)."""
        x = np.empty((*v.shape[:-1][:-1], v.shape[-2] + 1, x0_n.shape[-1]))
        x[..., 0, :] = x0_n
        with np.errstate(over="ignore", invalid="ignore"):  # a diverging model yields inf/nan
            for k in range(v.shape[-2]):
                x[..., k + 1, :] = self.step(x[..., k, :], v[..., k, :])
        return x

    def _dictionary_points(self, x_n: np.ndarray, v: np.ndarray) -> np.ndarray:
        """What the dictionary's centres are drawn from: y = [x_n; v]."""
        return np.concatenate([x_n, v], axis=-1)

    def _observables(self, x_n: np.ndarray, v: np.ndarray) -> np.ndarray:
        """w = [x_n; v; 1; phi(clip([x_n; v]))], (..., regressors)."""
        y = np.concatenate([x_n, v], axis=-1)
        parts = [y]
        if self.include_constant:
            parts.append(np.ones((*y.shape[:-1], 1)))
        parts.append(self.dictionary(self._clipped(y)))
        return np.concatenate(parts, axis=-1)

    def _clipped(self, y: np.ndarray) -> np.ndarray:
        """y inside the training data's box (``observable_margin``), where phi was fitted."""
        if self.margin is None:
            return y
        return np.clip(y, -self.margin, 1.0 + self.margin)

    # -- the LinearizableModel contract (normalized units) ----------------------------------

    def lift(self, x: np.ndarray) -> np.ndarray:
        """The lifted state is the normalized state: observables are re-made every step."""
        return np.asarray(self.normalizer_.states(np.asarray(x, dtype=np.float64)), dtype=float)

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        return z + self._observables(z, v) @ self.theta_

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A_k = I + dTheta^T w / dx, B_k = dTheta^T w / dv, d_k the remainder, at K points."""
        z, v = np.atleast_2d(z), np.atleast_2d(v)
        n, width = z.shape[1], z.shape[1] + v.shape[1]
        linear = self.theta_[:width].T  # (n, n + m): the observables y themselves
        dictionary = self.theta_[width + int(self.include_constant) :]  # (K_phi, n)
        y = np.concatenate([z, v], axis=1)
        jacobian = self.dictionary.jacobian(self._clipped(y))  # (K, K_phi, n + m)
        if self.margin is not None:  # clip's derivative: 0 in a coordinate outside the box
            inside = (y >= -self.margin) & (y <= 1.0 + self.margin)
            jacobian = jacobian * inside[:, None, :]
        total = linear + np.einsum("cs,kcd->ksd", dictionary, jacobian)  # (K, n, n + m)
        A = np.eye(n) + total[:, :, :n]
        B = np.ascontiguousarray(total[:, :, n:])
        d = self.step(z, v) - np.einsum("kab,kb->ka", A, z) - np.einsum("kaj,kj->ka", B, v)
        return A, B, d

    # -- model file -------------------------------------------------------------------------

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {"theta": self.theta_, "ridge": np.array([self.ridge_]), **self.dictionary.state()}

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        regressors = Dim("R", self.regressor_count(n, m), "regressors")
        return {"theta": (regressors, n), "ridge": (1,), **self.dictionary.state_shapes(n + m)}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        self.theta_ = state["theta"].numpy().astype(np.float64)
        self.ridge_ = float(state["ridge"].numpy()[0])
        self.C_ = np.eye(self.theta_.shape[1])
        self.dictionary.set_state(
            {k: v.numpy() for k, v in state.items() if k not in ("theta", "ridge")}
        )
