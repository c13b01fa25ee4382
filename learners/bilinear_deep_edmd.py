"""Bilinear Deep EDMD: Deep EDMD's learned observables with a bilinear Koopman operator::

    z_{k+1} = A z_k + B v_k + sum_j (v_kj - v0_j) H_j z_k,     z = [x_n; phi_e(x_n)]

The input acts multiplied by the learned lifted state, so the steering gain can fall with
speed, which one B cannot do (v0 and why vbar = v - v0: :mod:`learners.bilinear`).

Training (``bilinear_training: true``): the paper's Deep EDMD losses (:mod:`learners.deep_edmd`)
with this operator inside them: K^[i] z_0 of L_xx and L_xo is the bilinear rollout, and H
(m, N, N) is trained with the encoder, decoder, A and B. H starts at zero, so training starts
as Deep EDMD's, and the encoder learns observables for the bilinear operator. With
``bilinear_training: false`` the network is trained exactly as Deep EDMD (linear A, B in the
losses, bit for bit) and only the refit below adds H.

Refit (``bilinear_refit: lstsq``): after training, A, B, H are replaced by the ridge least
squares of the bilinear regression on the lifted training pairs, as bilinear EDMD fits its fixed
dictionary (``bilinear_ridge``, ``ridge_prior``); ``none`` keeps the trained operator.

Stability penalty (``stability``, :class:`StabilityPenalty`, off by default): MDK-Net's idea
(Abtahi et al., arXiv 2503.03002) of penalising eigenvalues of A outside the unit circle, here
``weight * sum_i max(0, |lambda_i| - radius)`` over the eigenvalues of A and of
A + sum_j (c_j - v0_j) H_j at the 2^m corners c of the normalized input box, added to the
training loss (its gradient by autograd through ``torch.linalg.eigvals``: the matrices are
N x N, tiny beside the network).

``predict`` rolls the bilinear model out and reads it with the decoder or, by default here
(``prediction_output: linear``), with C z, exactly what a bilinear MPC predicts with. The model
satisfies :class:`~harness.core.contracts.BilinearModel` (``A_``, ``B_``, ``H_``, ``v0_``, ``C_``,
``lift``, ``normalizer_``).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

import numpy as np
import torch

from harness.core.checks import boolean, choice, non_negative, positive, require
from harness.core.episode import Episode
from learners.base import Shape
from learners.bilinear import (
    RIDGE_PRIORS,
    BilinearOperator,
    bilinear_matrices,
    bilinear_regression_rows,
    bilinear_rollout,
)
from learners.deep_edmd import BilinearTerm, DeepEDMD, DeepEDMDConfig, _Objective
from learners.linalg import ridge_lstsq, row_chunks
from learners.nets import Dense, LayerSpec
from learners.settings import block, settle

__all__ = [
    "BilinearDeepEDMD",
    "BilinearDeepEDMDConfig",
    "StabilityPenalty",
    "stability_penalty",
]

REFITS = ("lstsq", "none")


@dataclass(frozen=True)
class StabilityPenalty:
    """The schema of ``learner.stability`` (module docstring).

    ``weight``: loss per unit of eigenvalue magnitude above ``radius``, in the units of the data
    terms (squared normalized state); 0 switches the penalty off. ``radius``: the magnitude
    eigenvalues are allowed up to (dimensionless, per 10 ms step; 1 is the unit circle).
    """

    # Loss per unit of |eigenvalue| above radius (data-loss units); 0: off.
    weight: float = 0.0
    # Allowed |eigenvalue| per model period (1.0: per second too; r per step = r_per_s ** period_s).
    radius: float = 1.0

    def __post_init__(self) -> None:
        non_negative("learner.stability.weight", self.weight)
        positive("learner.stability.radius", self.radius)


def stability_penalty(
    a: torch.Tensor, h: torch.Tensor | None, v0: torch.Tensor, radius: float
) -> torch.Tensor:
    """sum_i max(0, |lambda_i| - radius) over A's eigenvalues and, with ``h`` (m, N, N), those
    of A + sum_j (c_j - v0_j) H_j at every corner c in {0, 1}^m of the normalized input box
    (where the bilinear model's modes move farthest). Differentiable by autograd."""
    matrices = a.unsqueeze(0)
    if h is not None:
        corners = torch.tensor(list(itertools.product((0.0, 1.0), repeat=h.shape[0])))
        held = a + torch.einsum("cj,jnk->cnk", (corners - v0).to(a.dtype), h)
        matrices = torch.cat([matrices, held])
    magnitudes = torch.linalg.eigvals(matrices).abs()
    return torch.relu(magnitudes - radius).sum()


class _BilinearObjective(_Objective):
    """Deep EDMD's objective with the bilinear term in its rollout and the stability penalty."""

    def __init__(self, learner: BilinearDeepEDMD) -> None:
        views, grads = learner.params_.views(), learner.params_.views(learner.params_.grad)
        m = learner.normalizer_.input_min.shape[0]
        v0 = torch.from_numpy(learner.v0_.astype(np.float32))
        term = None
        if learner.bilinear_training:
            size = views["koopman.A.weight"].shape[0]
            h, grad_h = (g["koopman.H.weight"].view(m, size, size) for g in (views, grads))
            term = BilinearTerm(h, v0, grad_h)
        super().__init__(learner, term)
        self.v0 = v0
        self.penalty = learner.stability

    def train_step(self, x: torch.Tensor, v: torch.Tensor, step: int) -> float:
        loss = super().train_step(x, v, step)
        if not self.penalty.weight:
            return loss
        a = self.a.detach().clone().requires_grad_()
        h = None if self.bilinear is None else self.bilinear.h.detach().clone().requires_grad_()
        penalty = self.penalty.weight * stability_penalty(a, h, self.v0, self.penalty.radius)
        if penalty.item() > 0.0:
            grads = torch.autograd.grad(penalty, [a] if h is None else [a, h])
            # nearly repeated eigenvalues can make the eigenvector gradient blow up: skip a step
            # rather than write inf into the parameters (the data terms still train)
            if all(bool(torch.isfinite(g).all()) for g in grads):
                self.grad_a.add_(grads[0])
                if self.bilinear is not None and self.bilinear.grad_h is not None:
                    self.bilinear.grad_h.add_(grads[1])
        return loss + float(penalty.detach())

    def validate(self, x: torch.Tensor, v: torch.Tensor) -> dict[str, float]:
        terms = super().validate(x, v)
        if not self.penalty.weight:
            return terms
        h = None if self.bilinear is None else self.bilinear.h
        with torch.no_grad():
            value = float(stability_penalty(self.a, h, self.v0, self.penalty.radius))
        terms["stability"] = value
        terms["loss"] += self.penalty.weight * value
        return terms


@dataclass(frozen=True)
class BilinearDeepEDMDConfig(DeepEDMDConfig):
    """Bilinear Deep EDMD's settings (``conf/learner/bilinear_deep_edmd.yaml``): Deep EDMD's,
    then the bilinear term's."""

    # C z, what a bilinear MPC predicts with; decoder: the paper's read-out.
    prediction_output: str = "linear"
    # H inside the multi-step losses; false: Deep EDMD's training, bit for bit.
    bilinear_training: bool = True
    # lstsq: A, B, H refitted on the lifted data after training | none.
    bilinear_refit: str = "lstsq"
    # Of the refit, relative to the mean squared one-step residual (as edmd's ridge).
    bilinear_ridge: float = 1e-4
    ridge_prior: str = "identity"  # the refit shrinks A toward the identity (z+ = z), not zero
    # MDK-Net's penalty on eigenvalues outside the circle (arXiv 2503.03002).
    stability: StabilityPenalty = field(default_factory=StabilityPenalty)

    def __post_init__(self) -> None:
        super().__post_init__()
        for key in ("refit_koopman_lstsq", "refit_inputs_lstsq"):
            require(
                not getattr(self, key),
                f"learner.{key}",
                "false (bilinear_refit: lstsq refits the bilinear operator)",
                True,
            )
        settle(
            self,
            bilinear_training=boolean("learner.bilinear_training", self.bilinear_training),
            bilinear_refit=choice("learner.bilinear_refit", self.bilinear_refit, REFITS),
            bilinear_ridge=non_negative("learner.bilinear_ridge", self.bilinear_ridge),
            ridge_prior=choice("learner.ridge_prior", self.ridge_prior, RIDGE_PRIORS),
            stability=block(StabilityPenalty, self.stability, "stability"),
        )


class BilinearDeepEDMD(BilinearOperator, DeepEDMD):
    """Deep EDMD with a bilinear operator, trained through and/or refitted (module docstring).

    Settings (:class:`BilinearDeepEDMDConfig`):
        bilinear_training: Train H with the network, the bilinear term inside the losses
            (false: Deep EDMD's training, bit for bit).
        bilinear_refit: ``lstsq``: replace A, B, H by the bilinear least squares on the lifted
            training data after training; ``none``: keep the trained operator.
        bilinear_ridge: Ridge of that least squares, relative to the mean squared one-step
            residual (as EDMD's ``ridge``).
        ridge_prior: What the ridge shrinks A toward: ``identity`` (default) or ``zero``.
        stability: :class:`StabilityPenalty` keys (``weight`` 0: off).
        Every other: as :class:`~learners.deep_edmd.DeepEDMD`'s (``prediction_output``
        defaults to ``linear`` here).
    """

    name: ClassVar[str] = "bilinear_deep_edmd"
    config_class: ClassVar[type] = BilinearDeepEDMDConfig
    config: BilinearDeepEDMDConfig

    H_: np.ndarray

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        self.bilinear_training = self.config.bilinear_training
        self.bilinear_refit = self.config.bilinear_refit
        self.bilinear_ridge = self.config.bilinear_ridge
        self.ridge_prior = self.config.ridge_prior
        self.stability = self.config.stability

    @classmethod
    def from_hyperparameters(cls, hyperparameters: Mapping[str, Any]) -> Self:
        """A model file's learner; files written before ``bilinear_training`` existed hold a
        network trained as Deep EDMD's (no H among its parameters) and the refit."""
        return cls(**{"bilinear_training": False, **hyperparameters})

    def _specs(self, n: int, m: int) -> list[LayerSpec]:
        specs = super()._specs(n, m)
        if not self.bilinear_training:
            return specs
        size = self.lifted_dim + (n if self.lifted_includes_state else 0)
        # H (m, N, N) stored as an (m N, N) weight; last and zero, so that every other tensor
        # gets Deep EDMD's initial values and training starts from Deep EDMD's model
        return [*specs, LayerSpec("koopman.H", size, m * size, "linear", bias=False, init="zero")]

    def _objective(self) -> _BilinearObjective:
        return _BilinearObjective(self)

    def _sync_for_rollout(self, train: Sequence[Episode]) -> None:
        self._after_training(train)  # the refit reads the parameters; it writes none of them

    def _after_training(self, train: Sequence[Episode]) -> None:
        super()._after_training(train)  # C_ and the trained A_, B_
        m, size = self.normalizer_.input_min.shape[0], self.A_.shape[0]
        if self.bilinear_training:
            trained = self.params_.views()["koopman.H.weight"]
            self.H_ = trained.double().numpy().reshape(m, size, size).copy()
        else:
            self.H_ = np.zeros((m, size, size))
        if self.bilinear_refit == "lstsq":
            varying = np.arange(size)  # the lift has no constant coordinate
            theta = ridge_lstsq(self._bilinear_pairs(train, varying), self.bilinear_ridge)
            self.A_, self.B_, self.H_ = bilinear_matrices(theta.T, m, varying, self.ridge_prior)

    def _bilinear_pairs(
        self, episodes: Sequence[Episode], varying: np.ndarray
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        for e in episodes:
            z = self._network_lift(e.states)
            v = self.normalizer_.inputs(e.inputs)
            for rows in row_chunks(z[:-1], 20_000):
                yield bilinear_regression_rows(
                    z[:-1][rows], v[:-1][rows], z[1:][rows], self.v0_, varying, self.ridge_prior
                )

    def _lifted_rollout(self, x0: torch.Tensor, v: torch.Tensor, layer: Dense | None) -> np.ndarray:
        z0 = self._lift_n(x0, layer).double().numpy()
        return bilinear_rollout(self.A_, self.B_, self.H_, z0, v.double().numpy(), self.v0_)

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {**super()._state(), "H": self.H_}

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        shapes = super()._state_shapes(n, m)
        lifted = shapes["A"][0]
        return {**shapes, "H": (m, lifted, lifted)}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        super()._set_state(state)
        self.H_ = state["H"].double().numpy().copy()
