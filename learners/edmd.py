"""EDMD with thin-plate-spline radial basis observables (the paper's baseline, Sec. VI).

Lifted state (normalized coordinates, x_n = normalizer.states(x))::

    z = [x_n (3); 1 (if include_constant); phi_1(x_n) .. phi_K(x_n)],
    phi_i(x) = ||x - c_i||^2 log ||x - c_i||                       (paper's eq. for the TPS RBF)

with K = ``num_centers`` centres drawn from N(mean, std^2) of the normalized training states,
per dimension, seeded. [A B] minimize the one-step residual of the paper's EDMD eq. over all
pairs (z_k, v_k) -> z_{k+1} of the training episodes, by ridge least squares
(:func:`learners.linalg.ridge_lstsq`). Because x_n is part of z, C = [I 0] exactly (the paper's
least-squares C gives the same matrix). The constant observable lets the lifted model represent
the affine terms that min-max normalization introduces (a linear plant is affine in x_n).
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Self

import numpy as np
import torch

from harness.data.episode import Episode, MinMaxNormalizer
from harness.recorder import Recorder
from learners.base import (
    KoopmanLearner,
    check_episodes,
    check_int,
    check_nonnegative,
    check_rollout_args,
)
from learners.linalg import ridge_lstsq, row_chunks

__all__ = ["EDMD", "LiftedLinearLearner", "linear_rollout"]

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


class LiftedLinearLearner(KoopmanLearner):
    """EDMD on a fixed dictionary of observables; subclasses define the observables only."""

    def __init__(self, *, ridge: float, include_constant: bool, seed: int) -> None:
        self.ridge = check_nonnegative("ridge", ridge)
        self.include_constant = bool(include_constant)
        self.seed = check_int("seed", seed, 0)

    # -- subclass hooks ------------------------------------------------------------------------

    @abstractmethod
    def _init_observables(self, states_n: np.ndarray, rng: np.random.Generator) -> None:
        """Draw the dictionary's parameters from the normalized training states."""

    @abstractmethod
    def _observables(self, x_n: np.ndarray) -> np.ndarray:
        """phi(x_n): (..., n) -> (..., K)."""

    # -- the contract ----------------------------------------------------------------------------

    def fit(
        self,
        train: Sequence[Episode],
        validation: Sequence[Episode],
        normalizer: MinMaxNormalizer,
        *,
        recorder: Recorder | None = None,
        output_dir: Path | None = None,
    ) -> Self:
        """Least squares on all one-step pairs of ``train``; ``validation`` is only checked."""
        del recorder, output_dir  # nothing iterative to record
        check_episodes(train, "train", normalizer)
        if validation:
            check_episodes(validation, "validation", normalizer)
        self.normalizer_ = normalizer
        states_n = np.concatenate([normalizer.states(e.states) for e in train])
        self._init_observables(states_n, np.random.default_rng(self.seed))

        def pairs() -> Iterator[tuple[np.ndarray, np.ndarray]]:
            for e in train:
                z = self._lift_n(normalizer.states(e.states))
                v = normalizer.inputs(e.inputs)
                for rows in row_chunks(z[:-1], _CHUNK_ROWS):
                    w = np.hstack([z[:-1][rows], v[:-1][rows]])
                    yield w, z[1:][rows]

        theta = ridge_lstsq(pairs(), self.ridge)  # (N + m, N)
        n_lift = theta.shape[1]
        self.A_ = np.ascontiguousarray(theta[:n_lift].T)
        self.B_ = np.ascontiguousarray(theta[n_lift:].T)
        n = normalizer.state_min.shape[0]
        self.C_ = np.eye(n, n_lift)
        return self

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
        parts.append(self._observables(x_n))
        return np.concatenate(parts, axis=-1)

    def _state(self) -> dict[str, np.ndarray]:
        return {"A": self.A_, "B": self.B_, "C": self.C_, **self._observable_state()}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        self.A_, self.B_, self.C_ = (state[k].numpy().astype(np.float64) for k in "ABC")
        self._set_observable_state({k: v.numpy() for k, v in state.items() if k not in "ABC"})

    @abstractmethod
    def _observable_state(self) -> dict[str, np.ndarray]:
        """The dictionary's parameters, to save."""

    @abstractmethod
    def _set_observable_state(self, state: Mapping[str, np.ndarray]) -> None:
        """Restore what :meth:`_observable_state` returned."""


class EDMD(LiftedLinearLearner):
    """EDMD with ``num_centers`` thin-plate-spline RBF observables (see the module docstring).

    Args:
        num_centers: K, the number of RBF centres (0 gives DMD with inputs on x_n).
        ridge: Tikhonov weight relative to the mean squared one-step residual.
        include_constant: Add the observable 1 to the lifted state.
        seed: Seed of the centres.
    """

    name: ClassVar[str] = "edmd"

    def __init__(
        self,
        num_centers: int = 100,
        ridge: float = 1e-10,
        include_constant: bool = True,
        seed: int = 0,
    ) -> None:
        super().__init__(ridge=ridge, include_constant=include_constant, seed=seed)
        self.num_centers = check_int("num_centers", num_centers, 0)
        self._hyperparameters: dict[str, Any] = {
            "num_centers": self.num_centers,
            "ridge": self.ridge,
            "include_constant": self.include_constant,
            "seed": self.seed,
        }

    def _init_observables(self, states_n: np.ndarray, rng: np.random.Generator) -> None:
        mean, std = states_n.mean(0), states_n.std(0)
        self.centers_ = rng.normal(mean, std, size=(self.num_centers, states_n.shape[1]))

    def _observables(self, x_n: np.ndarray) -> np.ndarray:
        r2 = np.sum((x_n[..., None, :] - self.centers_) ** 2, axis=-1)
        # r^2 log r = r^2 log(r^2) / 2, continuous with value 0 at r = 0
        return 0.5 * r2 * np.log(np.where(r2 > 0, r2, 1.0))

    def _observable_state(self) -> dict[str, np.ndarray]:
        return {"centers": self.centers_}

    def _set_observable_state(self, state: Mapping[str, np.ndarray]) -> None:
        self.centers_ = state["centers"].astype(np.float64)
