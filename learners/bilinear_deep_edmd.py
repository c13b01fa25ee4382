"""Bilinear Deep EDMD: Deep EDMD's learned observables with a bilinear Koopman operator.

The encoder and decoder are trained exactly as :class:`learners.deep_edmd.DeepEDMD` (the
paper's losses, its linear A and B inside them). After training, the operator is refitted on
the lifted training pairs as bilinear EDMD does on its fixed dictionary
(:mod:`learners.bilinear`)::

    z_{k+1} = A z_k + B v_k + sum_j (v_kj - v0_j) H_j z_k,     z = [x_n; phi_e(x_n)]

by ridge least squares toward the identity (``bilinear_ridge``, ``ridge_prior``): the input
acts multiplied by the learned lifted state, so the steering gain can fall with speed, which
one B cannot do. The encoder is not trained through the bilinear term: its observables are
those that make the *linear* operator predict well. Training through it (the bilinear term in
the multi-step losses) is the open part of the bilinear-learners issue.

``predict`` rolls the bilinear model out and reads it with the decoder or, by default here
(``prediction_output: linear``), with C z, exactly what a bilinear MPC predicts with. The model
satisfies :class:`~harness.interfaces.BilinearModel` (``A_``, ``B_``, ``H_``, ``v0_``, ``C_``,
``lift``, ``normalizer_``).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from harness.data.episode import Episode
from learners.base import check, check_choice, check_nonnegative
from learners.bilinear import (
    RIDGE_PRIORS,
    BilinearOperator,
    bilinear_matrices,
    bilinear_regression_rows,
    bilinear_rollout,
)
from learners.deep_edmd import DeepEDMD
from learners.linalg import ridge_lstsq, row_chunks
from learners.nets import Dense, mlp_apply

__all__ = ["BilinearDeepEDMD"]


class BilinearDeepEDMD(BilinearOperator, DeepEDMD):
    """Deep EDMD with a bilinear operator refitted after training (module docstring).

    Args:
        bilinear_ridge: Ridge of the bilinear least squares, relative to the mean squared
            one-step residual (as EDMD's ``ridge``).
        ridge_prior: What the ridge shrinks A toward: ``identity`` (default) or ``zero``.
        **deep_edmd: Every :class:`~learners.deep_edmd.DeepEDMD` argument.
    """

    name: ClassVar[str] = "bilinear_deep_edmd"

    H_: np.ndarray

    def __init__(
        self, bilinear_ridge: float = 1e-4, ridge_prior: str = "identity", **deep_edmd: Any
    ) -> None:
        deep_edmd.setdefault("prediction_output", "linear")
        super().__init__(**deep_edmd)
        check(
            not self.refit_koopman_lstsq,
            "refit_koopman_lstsq",
            "false (the bilinear operator is refitted after training anyway)",
            True,
        )
        self.bilinear_ridge = check_nonnegative("bilinear_ridge", bilinear_ridge)
        self.ridge_prior = check_choice("ridge_prior", ridge_prior, RIDGE_PRIORS)
        self._hyperparameters.update(bilinear_ridge=self.bilinear_ridge, ridge_prior=ridge_prior)

    def _after_training(self, train: Sequence[Episode]) -> None:
        super()._after_training(train)  # C_ (and the linear A_, B_ the losses trained)
        m = self.normalizer_.input_min.shape[0]
        varying = np.arange(self.A_.shape[0])  # the lift has no constant coordinate
        theta = ridge_lstsq(self._bilinear_pairs(train, varying), self.bilinear_ridge)
        self.A_, self.B_, self.H_ = bilinear_matrices(theta.T, m, varying, self.ridge_prior)

    def _bilinear_pairs(
        self, episodes: Sequence[Episode], varying: np.ndarray
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        for e in episodes:
            z = self.lift(e.states)
            v = self.normalizer_.inputs(e.inputs)
            for rows in row_chunks(z[:-1], 20_000):
                yield bilinear_regression_rows(
                    z[:-1][rows], v[:-1][rows], z[1:][rows], self.v0_, varying, self.ridge_prior
                )

    def _rollout_n(self, x0: torch.Tensor, v: torch.Tensor, layer: Dense | None) -> torch.Tensor:
        z0 = self._lift_n(x0, layer).double().numpy()
        z = bilinear_rollout(self.A_, self.B_, self.H_, z0, v.double().numpy(), self.v0_)
        if self.prediction_output == "linear":
            with np.errstate(over="ignore", invalid="ignore"):
                return torch.from_numpy(z @ self.C_.T)
        decoder = self.params_.layers("decoder")
        with np.errstate(over="ignore", invalid="ignore"):
            return mlp_apply(decoder, torch.from_numpy(z.astype(np.float32)))

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {**super()._state(), "H": self.H_}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        super()._set_state(state)
        self.H_ = state["H"].double().numpy().copy()
