"""An exact lifted-linear system and a plant made of it, so a controller meets its own model.

With the plant equal to the controller's model, tracking errors are the controller's alone: a
feasible reference must be tracked almost exactly, and the QP's answers can be checked against
closed forms.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from controllers.lifted_linear import LiftedLinearModel
from harness.core.contracts import (
    STATE_NAMES,
    BilinearModel,
    Dynamics,
    LiftedModel,
    LinearizableModel,
)
from harness.core.episode import MinMaxNormalizer


def constant_feature(x_norm: np.ndarray) -> np.ndarray:
    """(..., 1): the constant observable, enough for an affine (linear in SI units) system."""
    return np.ones((*np.shape(x_norm)[:-1], 1))


def toy_linear_model() -> LiftedLinearModel:
    """An exact lifted-linear system, z = [x_norm; 1], at rest at (20 m/s, 0, 0) under u = 0.

    Pedal drives vx, steering drives the coupled (vy, yaw_rate) pair; stable, well damped.
    """
    normalizer = MinMaxNormalizer(
        np.array([0.0, -2.0, -1.0]),
        np.array([40.0, 2.0, 1.0]),
        np.array([-450.0, -1.0]),
        np.array([450.0, 1.0]),
    )
    a = np.array([[0.995, 0.0, 0.0], [0.0, 0.90, 0.04], [0.0, 0.03, 0.93]])
    b = np.array([[0.0, 0.004], [0.02, 0.0], [0.03, 0.0]])
    x_rest, v_rest = np.full(3, 0.5), np.full(2, 0.5)
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = a, x_rest - a @ x_rest - b @ v_rest
    B = np.vstack([b, np.zeros((1, 2))])
    return LiftedLinearModel(A, B, normalizer, constant_feature)


@dataclass
class ToyBilinearModel:
    """The toy linear system plus a steering gain that grows with speed: a ``BilinearModel``.

    z⁺ = A z + B v + Σⱼ (vⱼ − v0ⱼ) Hⱼ z with H₀ feeding vx_norm · steering into vy and the yaw
    rate (the lateral gain doubles from standstill to 40 m/s); H₁ = 0.
    """

    A_: np.ndarray
    B_: np.ndarray
    H_: np.ndarray
    dynamics: ClassVar[Dynamics] = "bilinear"
    normalizer_: MinMaxNormalizer
    C_: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.C_ = np.hstack([np.eye(3), np.zeros((3, self.A_.shape[0] - 3))])

    @property
    def v0_(self) -> np.ndarray:
        return self.normalizer_.inputs(np.zeros(2))

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([self.normalizer_.states(x), constant_feature(x)], axis=-1)


def toy_bilinear_model() -> ToyBilinearModel:
    linear = toy_linear_model()
    H = np.zeros((2, 4, 4))
    H[0, 1, 0], H[0, 2, 0] = 0.02, 0.03  # ∂(vy, r)⁺/∂steer grows with vx_norm
    return ToyBilinearModel(linear.A_, linear.B_, H, linear.normalizer_)


def lifted_step(model: LiftedModel, z: np.ndarray, v: np.ndarray) -> np.ndarray:
    """One step of a lifted-linear or bilinear model."""
    z_next = model.A_ @ z + model.B_ @ v
    if isinstance(model, BilinearModel):
        z_next = z_next + np.einsum("j,jab,b->a", v - model.v0_, model.H_, z)
    return z_next


def feasible_reference(model: LiftedModel, steps: int = 600) -> np.ndarray:
    """(steps, 3) states the model itself reaches from (20 m/s, 0, 0) under slow inputs."""
    plant = ModelPlant(model, x0=np.array([20.0, 0.0, 0.0]))
    t = np.arange(steps) * plant.dt
    inputs = np.stack([60 * np.sin(2 * np.pi * 0.4 * t), 0.05 * np.sin(2 * np.pi * 0.2 * t)], 1)
    states = [plant.reset()]
    states += [plant.step(u) for u in inputs[:-1]]
    return np.array(states)


class ModelPlant:
    """A :class:`~harness.core.contracts.Plant` whose dynamics are a lifted-linear model.

    Only consistent when the lift is closed under the dynamics (e.g. ``constant_feature``): the
    state is x = normalizer⁻¹(C z) and the next z is A z + B v.
    """

    dt = 0.01

    def __init__(self, model: LiftedModel, x0: np.ndarray | None = None) -> None:
        self.model = model
        self.x0 = np.zeros(3) if x0 is None else np.asarray(x0, dtype=float)
        self.reset()

    def reset(self, seed: int | None = None, speed_mps: float = 0.0) -> np.ndarray:
        del seed  # deterministic: nothing to seed
        x = self.x0.copy()
        if speed_mps:
            x[0] = speed_mps
        self._z = self.model.lift(x)
        self._pose = np.zeros(3)
        return self._state()

    def step(self, u: np.ndarray) -> np.ndarray:
        vx, vy, yaw_rate = self._state()
        self._z = lifted_step(self.model, self._z, self.model.normalizer_.inputs(u))
        # Pose (X, Y, yaw) by planar kinematics, for display only.
        yaw = self._pose[2]
        self._pose = self._pose + self.dt * np.array(
            [vx * np.cos(yaw) - vy * np.sin(yaw), vx * np.sin(yaw) + vy * np.cos(yaw), yaw_rate]
        )
        return self._state()

    @property
    def pose(self) -> np.ndarray:
        return self._pose.copy()

    @property
    def fingerprint(self) -> dict[str, Any]:
        normalizer = self.model.normalizer_
        return {
            "plant": "model_plant",
            "dt": self.dt,
            "x0": dict(zip(STATE_NAMES, self.x0.tolist(), strict=True)),
            "A": self.model.A_.tolist(),
            "B": self.model.B_.tolist(),
            "normalizer": [
                np.asarray(limit).tolist()
                for limit in (
                    normalizer.state_min,
                    normalizer.state_max,
                    normalizer.input_min,
                    normalizer.input_max,
                )
            ],
        }

    def _state(self) -> np.ndarray:
        return self.model.normalizer_.states_inverse(self.model.C_ @ self._z)


class OwnModelPlant:
    """A plant that is a linearisable model itself (a DNN, an input EDMD, a toy car), its lifted
    state the normalized state: the controller meets its own model."""

    dt = 0.01

    def __init__(self, model: LinearizableModel, x0: np.ndarray) -> None:
        self.model, self.x0 = model, x0
        self.reset()

    def reset(self, seed: int | None = None, speed_mps: float = 0.0) -> np.ndarray:
        del seed, speed_mps  # starts at x0, the reference's first state
        self._z = self.model.lift(self.x0)
        return self.x0.copy()

    def step(self, u: np.ndarray) -> np.ndarray:
        self._z = self.model.step(self._z, self.model.normalizer_.inputs(u))
        return self.model.normalizer_.states_inverse(self._z)

    @property
    def pose(self) -> np.ndarray:
        return np.zeros(3)

    @property
    def fingerprint(self) -> dict[str, Any]:
        return {"plant": "own_model", "model": type(self.model).__name__}


DT = 0.01
THROTTLE_ACCEL = 3.0  # m/s² at full throttle (pedal feature +1)
BRAKE_ACCEL = 8.0  # m/s² at full brake (feature -1), fading to nothing at standstill
FADE_MPS = 0.5  # the brake's force ~ tanh(vx / FADE_MPS): it cannot push a stopped car back


@dataclass
class StoppingCar:
    """vx⁺ = vx + dt·a(f, vx): throttle a = 3 f (f >= 0), brake a = 8 f tanh(vx / 0.5) (f < 0),
    f the pedal's feature in [-1, 1]; vy and the yaw rate decay, steering turns the car."""

    dynamics: ClassVar[Dynamics] = "nonlinear"
    normalizer_: MinMaxNormalizer = field(
        default_factory=lambda: MinMaxNormalizer(
            np.array([0.0, -2.0, -1.0]),
            np.array([20.0, 2.0, 1.0]),
            np.array([-450.0, -1.0]),
            np.array([450.0, 1.0]),
        )
    )
    C_: np.ndarray = field(default_factory=lambda: np.eye(3))

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.normalizer_.states(np.asarray(x, dtype=float)), dtype=float)

    def _parts(self, z: np.ndarray, v: np.ndarray) -> tuple[Any, ...]:
        span_x = self.normalizer_.state_max - self.normalizer_.state_min
        vx = z[..., 0] * span_x[0] + self.normalizer_.state_min[0]
        feature = 2.0 * v[..., 1] - 1.0  # input_min -1, input_max 1: v = (f + 1) / 2
        fade = np.tanh(vx / FADE_MPS)
        throttle = feature >= 0
        accel = np.where(throttle, THROTTLE_ACCEL * feature, BRAKE_ACCEL * feature * fade)
        d_accel_d_f = np.where(throttle, THROTTLE_ACCEL, BRAKE_ACCEL * fade)
        d_accel_d_vx = np.where(throttle, 0.0, BRAKE_ACCEL * feature * (1 - fade**2) / FADE_MPS)
        return span_x, accel, d_accel_d_f, d_accel_d_vx

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        span_x, accel, _, _ = self._parts(z, v)
        out = np.array(z, dtype=float, copy=True)
        out[..., 0] = z[..., 0] + DT * accel / span_x[0]
        out[..., 1] = 0.5 + 0.95 * (z[..., 1] - 0.5)
        out[..., 2] = 0.5 + 0.95 * (z[..., 2] - 0.5) + 0.02 * (v[..., 0] - 0.5)
        return out

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        span_x, _, d_accel_d_f, d_accel_d_vx = self._parts(z, v)
        K = z.shape[0]
        A = np.zeros((K, 3, 3))
        A[:, 0, 0] = 1.0 + DT * d_accel_d_vx
        A[:, 1, 1] = A[:, 2, 2] = 0.95
        B = np.zeros((K, 3, 2))
        B[:, 0, 1] = DT * d_accel_d_f * 2.0 / span_x[0]
        B[:, 2, 0] = 0.02
        d = self.step(z, v) - np.einsum("kab,kb->ka", A, z) - np.einsum("kaj,kj->ka", B, v)
        return A, B, d
