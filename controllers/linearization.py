"""How DE-MPC reads a model: lifted-linear, or linearised each step (the time-varying DE-MPC).

:func:`linearization_of` says which, by the dynamics a model declares, and the checks of each
kind (``check_lifted_model``, ``check_linearizable``) run once when a controller is built.

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

from typing import ClassVar, cast

import numpy as np

from harness.core.contracts import (
    INPUT_NAMES,
    STATE_NAMES,
    BilinearModel,
    Dynamics,
    LiftedModel,
    LinearizableModel,
    Model,
    dynamics_of,
)
from harness.core.episode import MinMaxNormalizer

STATES, INPUTS = len(STATE_NAMES), len(INPUT_NAMES)


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


class SecantInputs:
    """A linearisable model whose input Jacobian is, column by column, a secant over ``spans``
    of each input's normalized range (a span of 0 keeps that input's tangent); its A and its
    step are the model's own.

    Why: a learned step's tangent in the pedal can be flat, or of the wrong sign, near the
    throttle-brake kink (a fitted smooth map overshoots where the true one bends), and a QP
    linearised there sees no use in moving the pedal and holds it: seed 1 of input EDMD at paper
    scale coasted at 0.05 throttle for four seconds while its reference braked from 19 to 10 m/s
    (docs/findings/smooth_driving.md, "The pedal's flat tangent"). The secant, (step(v + h) −
    step(v − h)) / 2h
    with h = span / 2 kept inside [v_min, v_max], sees past such a wiggle to the slope that
    braking or throttle has over a usable pedal move."""

    dynamics: ClassVar[Dynamics] = "nonlinear"

    def __init__(
        self, model: LinearizableModel, spans: np.ndarray, v_min: np.ndarray, v_max: np.ndarray
    ) -> None:
        spans = np.asarray(spans, dtype=float)  # checked where they are read: DEMPCConfig
        self.model = model
        self.half = 0.5 * spans
        self.columns = np.flatnonzero(spans > 0)  # the inputs taken as secants
        self.v_min = np.asarray(v_min, dtype=float)
        self.v_max = np.asarray(v_max, dtype=float)
        self.C_ = model.C_
        self.normalizer_: MinMaxNormalizer = model.normalizer_

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.model.lift(x), dtype=float)

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.asarray(self.model.step(z, v), dtype=float)

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        A, tangent, tangent_d = self.model.linearize(z, v)
        B = np.array(tangent, dtype=float)  # the tangent's columns stay where the span is 0
        points, size = z.shape
        columns = self.columns
        low = np.maximum(v - self.half, self.v_min)[:, columns]  # (K, c): in the input box
        high = np.minimum(v + self.half, self.v_max)[:, columns]
        # Row (k, i, end): point k with input columns[i] at its interval's low or high end.
        moved = np.repeat(v[:, None, None, :], len(columns), axis=1).repeat(2, axis=2)
        picks = np.arange(len(columns))
        moved[:, picks, 0, columns] = low
        moved[:, picks, 1, columns] = high
        repeated = np.broadcast_to(z[:, None, None, :], (points, len(columns), 2, size))
        ends = self.step(repeated.reshape(-1, size), moved.reshape(-1, v.shape[1]))
        ends = ends.reshape(points, len(columns), 2, size)
        width = np.maximum(high - low, np.finfo(float).tiny)  # (K, c)
        B[:, :, columns] = np.transpose(
            (ends[:, :, 1] - ends[:, :, 0]) / width[..., None], (0, 2, 1)
        )
        # Exact at the point as the model's own: step(z, v) = A z + B v + d for either B.
        d = tangent_d + np.einsum("kaj,kj->ka", tangent - B, v)
        return A, np.ascontiguousarray(B), d


# -- how DE-MPC reads a model ---------------------------------------------------------------


def linearization_of(model: Model) -> LinearizableModel | None:
    """How DE-MPC reads ``model``, by the dynamics it declares: None for lifted-linear (one QP for
    the whole run), else the model to linearise each step."""
    dynamics = dynamics_of(model)
    if dynamics is None:
        raise ValueError(
            f"{type(model).__name__} declares no dynamics (linear, bilinear or nonlinear): "
            "DE-MPC reads only a fitted model of harness.core.contracts"
        )
    if dynamics == "bilinear":
        return BilinearLinearization(cast(BilinearModel, model))
    if dynamics == "nonlinear":
        return cast(LinearizableModel, model)
    return None


def check_linearizable(model: LinearizableModel) -> np.ndarray:
    """C_ of a model to linearise, checked against its lift and its linearisation's shapes."""
    C = np.asarray(model.C_, dtype=float)
    z = np.asarray(model.lift(np.asarray(model.normalizer_.state_min, dtype=float)), dtype=float)
    size = z.shape[0] if z.ndim == 1 else -1
    if C.shape != (STATES, size) or not np.all(np.isfinite(C)):
        raise ValueError(f"model.C_ must be finite with shape ({STATES}, {size}), got {C.shape}")
    v = np.asarray(model.normalizer_.inputs(np.zeros(INPUTS)), dtype=float)
    A, B, d = model.linearize(z[None], v[None])
    for name, array, shape in (
        ("A", A, (1, size, size)),
        ("B", B, (1, size, INPUTS)),
        ("d", d, (1, size)),
    ):
        if np.shape(array) != shape:
            raise ValueError(f"model.linearize must return {name} of shape {shape}")
    return C


def check_lifted_model(model: LiftedModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The contract, checked once: shapes agree and lift returns the lifted dimension."""
    A, B, C = (np.asarray(m, dtype=float) for m in (model.A_, model.B_, model.C_))
    size = A.shape[0] if A.ndim == 2 else -1
    for name, array, shape in (
        ("A_", A, (size, size)),
        ("B_", B, (size, INPUTS)),
        ("C_", C, (STATES, size)),
    ):
        if array.shape != shape or not np.all(np.isfinite(array)):
            raise ValueError(f"model.{name} must be finite with shape {shape}, got {array.shape}")
    lifted = np.asarray(model.lift(np.asarray(model.normalizer_.state_min, dtype=float)))
    if lifted.shape != (size,):
        raise ValueError(f"model.lift(x) must return shape ({size},), got {lifted.shape}")
    return A, B, C
