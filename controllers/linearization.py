"""Linearisations of models that are not lifted-linear, for the time-varying DE-MPC.

A :class:`~harness.core.contracts.BilinearModel` (z⁺ = A z + B v + Σⱼ (vⱼ − v0ⱼ) Hⱼ z) is
linear in z for a fixed input and linear in v for a fixed state, so along a plan (z̄_k, v̄_k) it
is exactly

    z⁺ = A_k z + B_k v + d_k + Σⱼ (vⱼ − v̄ⱼ) Hⱼ (z − z̄)     (second-order term dropped)

with A_k = A + Σⱼ (v̄_kj − v0ⱼ) Hⱼ, B_k = B + [H₁ z̄_k … H_m z̄_k], d_k = −Σⱼ v̄_kj Hⱼ z̄_k.
:class:`BilinearLinearization` wraps any such model as a
:class:`~harness.core.contracts.LinearizableModel`; every point of the horizon is done in one
``einsum`` (no loop over the horizon).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from harness.core.contracts import BilinearModel, Dynamics
from harness.core.episode import MinMaxNormalizer


class BilinearLinearization:
    """A bilinear model read as a :class:`~harness.core.contracts.LinearizableModel`."""

    dynamics: ClassVar[Dynamics] = "nonlinear"

    def __init__(self, model: BilinearModel) -> None:
        self.model = model
        self.A = np.asarray(model.A_, dtype=float)
        self.B = np.asarray(model.B_, dtype=float)
        self.H = np.asarray(model.H_, dtype=float)
        self.v0 = np.asarray(model.v0_, dtype=float)
        self.C_ = np.asarray(model.C_, dtype=float)
        self.normalizer_: MinMaxNormalizer = model.normalizer_
        size, m = self.A.shape[0], self.B.shape[1]
        if self.H.shape != (m, size, size) or self.v0.shape != (m,):
            raise ValueError(
                f"bilinear model.H_ must be ({m}, {size}, {size}) and v0_ ({m},); "
                f"got {self.H.shape} and {self.v0.shape}"
            )
        # z @ [Aᵀ H₁ᵀ … H_mᵀ]: the state's products with A and every Hⱼ in one product.
        self._stacked = np.concatenate([self.A.T, *(h.T for h in self.H)], axis=1)

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.model.lift(x), dtype=float)

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        size, m = self.A.shape[0], self.B.shape[1]
        products = (z @ self._stacked).reshape(*np.shape(z)[:-1], 1 + m, size)
        vbar = (v - self.v0)[..., None, :]  # (..., 1, m)
        bilinear = (vbar @ products[..., 1:, :])[..., 0, :]
        return products[..., 0, :] + bilinear + v @ self.B.T

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        hz = np.transpose(self.H @ z.T, (2, 1, 0))  # (K, N, m): column j is H_j z̄_k
        A = self.A + np.tensordot(v - self.v0, self.H, axes=1)
        B = self.B + hz
        d = -(hz @ v[:, :, None])[:, :, 0]
        return A, B, d
