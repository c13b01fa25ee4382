"""EDMD: the one exact-least-squares lifted-linear learner; its observables are a dictionary.

Lifted state (normalized coordinates, x_n = normalizer.states(x))::

    z = [x_n (n); 1 (if include_constant); phi_1(x_n) .. phi_K(x_n)]

where phi is the ``dictionary`` (:mod:`learners.dictionaries`): thin-plate-spline RBFs give the
paper's EDMD baseline (Sec. VI, ``conf/learner/edmd.yaml``), random ELM units give ELM-EDMD
(``conf/learner/elm_edmd.yaml``). [A B] minimize the one-step residual of the paper's EDMD eq.
over all pairs (z_k, v_k) -> z_{k+1} of the training episodes, by ridge least squares
(:func:`learners.linalg.ridge_lstsq`). Because x_n is part of z, C = [I 0] exactly (the paper's
least-squares C gives the same matrix). The constant observable lets the lifted model represent
the affine terms that min-max normalization introduces (a linear plant is affine in x_n).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self

import numpy as np
import torch

from harness.core.budget import check_memory
from harness.core.checks import boolean, integer
from harness.core.episode import Episode, MinMaxNormalizer
from learners.base import (
    INPUT_DIM,
    STATE_DIM,
    Dim,
    KoopmanLearner,
    Shape,
    check_fit_data,
    check_rollout_args,
)
from learners.dictionaries import RandomFeatures, ThinPlateRBF, dictionary_from
from learners.linalg import Triangle, ridge_weights, row_chunks
from learners.settings import settle

log = logging.getLogger(__name__)

__all__ = ["EDMD", "EDMDConfig", "linear_rollout"]

_CHUNK_ROWS = 20_000


def linear_rollout(a: np.ndarray, b: np.ndarray, z0: np.ndarray, v: np.ndarray) -> np.ndarray:
    """z_{k+1} = A z_k + B v_k for k < T: z0 (..., N), v (..., T, m) -> (..., T + 1, N)."""
    z = np.empty((*v.shape[:-1][:-1], v.shape[-2] + 1, a.shape[0]))
    z[..., 0, :] = z0
    bv = v @ b.T
    at = a.T
    with np.errstate(over="ignore", invalid="ignore"):  # a diverging model yields inf, not noise
        for k in range(v.shape[-2]):
            z[..., k + 1, :] = z[..., k, :] @ at + bv[..., k, :]
    return z


@dataclass(frozen=True)
class EDMDConfig:
    """EDMD's settings (``conf/learner/edmd.yaml``, ``elm_edmd.yaml``), checked when built."""

    # The observables phi(x) (learners/dictionaries.py): a Dictionary, or its block with
    # ``_target_``; null: 100 thin-plate RBFs, centres ~ N(mean, std^2) of the training states.
    dictionary: Any = None
    # Tikhonov weight relative to the mean squared one-step residual: one number, or a list
    # to choose from by the validation drives' rollouts (OmegaConf has no float | list).
    ridge: Any = 1e-10
    # The observable 1 (min-max normalization makes a linear plant affine).
    include_constant: bool = True
    seed: int = 0  # of the dictionary's draw

    def __post_init__(self) -> None:
        ridges = ridge_weights(self.ridge)
        settle(
            self,
            dictionary=dictionary_from(self.dictionary),
            ridge=tuple(ridges) if len(ridges) > 1 else ridges[0],
            include_constant=boolean("learner.include_constant", self.include_constant),
            seed=integer("learner.seed", self.seed, 0),
        )


class EDMD(KoopmanLearner):
    """EDMD on a fixed dictionary of observables (see the module docstring).

    Settings (:class:`EDMDConfig`):
        dictionary: The observables phi (a :class:`~learners.dictionaries.Dictionary`, or its
            ``hyperparameters`` with ``_target_``); None gives 100 thin-plate RBFs.
        ridge: Tikhonov weight relative to the mean squared one-step residual; with several,
            the one whose open-loop rollouts of the validation drives err least (a ridge of
            1e-10, the paper's, is none: its lateral predictions run off the data on logs of
            another car, docs/findings/other_cars.md).
        include_constant: Add the observable 1 to the lifted state.
        seed: Seed of the dictionary's random draw.
    """

    name: ClassVar[str] = "edmd"
    config_class: ClassVar[type] = EDMDConfig
    config: EDMDConfig

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        self.dictionary = dictionary_from(self.config.dictionary)  # its own, to draw and fit
        self.ridges = ridge_weights(self.config.ridge)
        self.ridge_ = self.ridges[0]
        self.include_constant = self.config.include_constant
        self.seed = self.config.seed

    @classmethod
    def from_hyperparameters(cls, hyperparameters: Mapping[str, Any]) -> Self:
        """Also reads the flat hyperparameters of files written before dictionaries existed:
        ``num_centers`` (class ``learners.edmd.EDMD``) or ``num_features``, ``activation``,
        ``weight_scale``, ``bias_scale`` (class ``learners.elm_edmd.ELMEDMD``)."""
        values = dict(hyperparameters)
        if "num_centers" in values:
            values["dictionary"] = ThinPlateRBF(values.pop("num_centers"))
        elif "num_features" in values:
            keys = ("num_features", "activation", "weight_scale", "bias_scale")
            values["dictionary"] = RandomFeatures(**{k: values.pop(k) for k in keys})
        return cls(**values)

    def fit(
        self, train: Sequence[Episode], validation: Sequence[Episode], normalizer: MinMaxNormalizer
    ) -> Self:
        """Least squares on all one-step pairs of ``train``; with several ridges, the one whose
        rollouts of ``validation`` err least (else ``validation`` is only checked)."""
        check_fit_data(train, validation, normalizer, self.name)
        if not validation and len(self.ridges) > 1:
            raise ValueError(
                f"learner.ridge lists {len(self.ridges)} weights to choose from on the "
                "validation drives, and there are none: give one weight or validation drives"
            )
        n, m = normalizer.state_min.shape[0], normalizer.input_min.shape[0]
        self.check_size(max(len(e) for e in train), n, m)
        self._check_enough_pairs(sum(len(e) - 1 for e in train), n, m)
        self.normalizer_ = normalizer
        states_n = np.concatenate([normalizer.states(e.states) for e in train])
        self.dictionary.fit(states_n, np.random.default_rng(self.seed))

        def pairs() -> Iterator[tuple[np.ndarray, np.ndarray]]:
            for e in train:
                z = self._lift_n(normalizer.states(e.states))
                v = normalizer.inputs(e.inputs)
                for rows in row_chunks(z[:-1], _CHUNK_ROWS):
                    yield self._regression_rows(z[:-1][rows], v[:-1][rows], z[1:][rows])

        triangle = Triangle.of(pairs())  # one pass over the data, then one small solve a ridge
        thetas = [triangle.solve(ridge) for ridge in self.ridges]  # (regressors, N) each
        self.C_ = np.eye(normalizer.state_min.shape[0], thetas[0].shape[1])
        best = 0
        if len(thetas) > 1:
            scores = [self._validation_score(theta, validation) for theta in thetas]
            self.validation_scores_ = dict(zip(self.ridges, scores, strict=True))
            if not np.any(np.isfinite(scores)):
                raise ValueError(
                    f"{self.name}: every ridge in learner.ridge={self.ridges} diverged on the "
                    "validation drives; try larger weights"
                )
            best = int(np.argmin(scores))
            log.info("%s: ridge %.0e chosen on the validation drives", self.name, self.ridges[best])
        self.ridge_ = self.ridges[best]
        self._set_matrices(thetas[best].T)
        return self

    def _validation_score(self, theta: np.ndarray, episodes: Sequence[Episode]) -> float:
        """The mean over drives of sum_i (RMSE_i / span_i)² of ``theta``'s open-loop rollout,
        in normalized units (as input EDMD scores its ridges); inf where it diverged."""
        self._set_matrices(theta.T)
        total = 0.0
        with np.errstate(over="ignore", invalid="ignore"):
            for e in episodes:
                predicted = self.normalizer_.states(self.predict(e.states[0], e.inputs[:-1]))
                error = predicted[1:] - self.normalizer_.states(e.states)[1:]
                total += float(np.sum(np.mean(error**2, axis=0)))
        score = total / len(episodes)
        return score if np.isfinite(score) else float("inf")

    @property
    def fit_summary(self) -> dict[str, Any]:
        """With several ridges: the chosen one and each candidate's validation score (null where
        its rollout diverged); empty with one."""
        scores = getattr(self, "validation_scores_", None)
        if len(self.ridges) < 2 or not scores:
            return {}
        return {
            "ridge": self.ridge_,
            "validation_scores": {
                f"{r:g}": (v if np.isfinite(v) else None) for r, v in scores.items()
            },
        }

    def lifted_dim(self, n: int = STATE_DIM) -> int:
        """N = n + 1 (the constant, if any) + K."""
        return n + int(self.include_constant) + self.dictionary.size[1]

    def check_size(self, episode_frames: int, n: int = STATE_DIM, m: int = INPUT_DIM) -> None:
        """Refuse a dictionary too big to fit here (``num_centers=1e9``), before any data.

        Counted in float64 (lower bounds): the dictionary's temporaries and the lifted states of
        the longest episode, and the streamed QR's triangle stacked on one row block, twice
        (numpy's QR copies its input): (2N + m + rows) × (2N + m).
        """
        key, size = self.dictionary.size
        width = self.lifted_dim(n) + self.regressor_count(n, m)
        floats = episode_frames * (self.dictionary.floats_per_row(n) + 2 * self.lifted_dim(n))
        floats += 2 * (width + _CHUNK_ROWS) * width
        what = f"EDMD with {size} observables on drives of {episode_frames} steps (data.max_steps)"
        check_memory(f"learner.{key}", what, 8 * floats)

    def _check_enough_pairs(self, pairs: int, n: int, m: int) -> None:
        """Fewer one-step pairs than the N + m unknowns of each row of [A B] leave the least
        squares underdetermined: it then fits any data exactly, and its errors mean nothing."""
        unknowns = self.regressor_count(n, m)
        if pairs < unknowns:
            key, size = self.dictionary.size
            raise ValueError(
                f"{type(self).__name__} with learner.{key}={size} has {unknowns} unknowns per "
                "row of its least squares but "
                f"the training drives hold only {pairs} one-step pairs: collect longer drives "
                "(data.min_steps) or check that the plant moves"
            )

    def regressor_count(self, n: int = STATE_DIM, m: int = INPUT_DIM) -> int:
        """Columns of the least squares, N + m for [A B] (the size checks count them)."""
        return self.lifted_dim(n) + m

    def _regression_rows(
        self, z: np.ndarray, v: np.ndarray, z_next: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Regressors w_k = [z_k; v_k] and targets z_{k+1} of rows k (a subclass, such as
        :class:`learners.bilinear.BilinearEDMD`, adds columns or changes the target)."""
        return np.hstack([z, v]), z_next

    def _set_matrices(self, theta: np.ndarray) -> None:
        """Read the fitted matrices off Theta^T (N, regressors): here [A B]."""
        n_lift = theta.shape[0]
        self.A_ = np.ascontiguousarray(theta[:, :n_lift])
        self.B_ = np.ascontiguousarray(theta[:, n_lift:])

    def lift(self, x: np.ndarray) -> np.ndarray:
        return self._lift_n(self.normalizer_.states(np.asarray(x, dtype=np.float64)))

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        n, m = self.C_.shape[0], self.B_.shape[1]
        x0, inputs = check_rollout_args(x0, inputs, n, m)
        z = linear_rollout(self.A_, self.B_, self.lift(x0), self.normalizer_.inputs(inputs))
        with np.errstate(over="ignore", invalid="ignore"):
            x = self.normalizer_.states_inverse(z @ self.C_.T)
        x[..., 0, :] = x0
        return x

    def _lift_n(self, x_n: np.ndarray) -> np.ndarray:
        parts = [x_n]
        if self.include_constant:
            parts.append(np.ones((*x_n.shape[:-1], 1)))
        parts.append(self.dictionary(x_n))
        return np.concatenate(parts, axis=-1)

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {"A": self.A_, "B": self.B_, "C": self.C_, **self.dictionary.state()}

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        lifted = Dim("N", self.lifted_dim(n), "lifted states")
        return {
            "A": (lifted, lifted),
            "B": (lifted, m),
            "C": (n, lifted),
            **self.dictionary.state_shapes(n),
        }

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        self.A_, self.B_, self.C_ = (state[k].numpy().astype(np.float64) for k in "ABC")
        self.dictionary.set_state({k: v.numpy() for k, v in state.items() if k not in "ABC"})
