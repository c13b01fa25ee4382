"""The physics baseline: a linear single-track (bicycle) model identified from the driving data.

What a vehicle engineer writes before any learning. Lateral: the linear single-track model with
axle cornering stiffnesses, in the measured speed vx (w = max(vx, min_speed_mps))::

    α_f = δ − (vy + a r) / w,   α_r = −(vy − b r) / w,   δ = steer_wheel / i_s
    vy' = (C_f α_f + C_r α_r) / m − vx r
    r'  = (a C_f α_f − b C_r α_r) / I_z

Longitudinal, first order in vx with the pedal split into throttle p⁺ and brake p⁻ (signed
pedal scale, as the normalizer's)::

    vx' = vy r + c_0 + c_2 vx² + g_1 p⁺ + g_2 p⁺ / w + g_3 p⁻

(rolling resistance, aerodynamic drag, a throttle force between constant torque g_1 and
constant power g_2 / v, brake). One Euler step of dt (the data's sampling period) is the model.

Measured, as a person would with a tape and a set of axle scales: the CG's distances to the
front and rear axles, a and b (``cg_to_front_m``, ``cg_to_rear_m``: wheelbase and axle loads),
and, for reporting only, the mass. Identified by least squares on the training episodes
(samples at vx >= ``min_speed_mps`` and, for the lateral and yaw equations, in the tyres'
linear range |ay| <= ``max_lateral_accel_mps2``; nothing is read from the plant's
configuration): the lateral and yaw equations together, linear in (C_f / m, C_r / m,
C_f / (m i_s)) for a given m / I_z, by separable least squares over m / I_z (this gives the
cornering stiffnesses per unit mass, the steering ratio and the yaw inertia per unit mass);
then the longitudinal equation, linear in (c_0, c_2, g_1, g_2, g_3).
The mass cancels: it only converts the fitted per-mass values into N/rad and kg·m² in
:attr:`SingleTrack.parameters`.

Besides a :class:`~learners.base.Learner` (``fit``/``predict``, so it has rows in the
prediction and step-response tables), the model is a
:class:`~harness.core.contracts.LinearizableModel` in the normalized state (z = x_norm, C = I):
the time-varying DE-MPC linearises it along its plan (``controller=bicycle_mpc``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Self

import numpy as np
import torch
from scipy.optimize import minimize_scalar

from harness.core.episode import Episode, MinMaxNormalizer, pedal_scale
from learners.base import Learner, Shape, check_fit_data, check_positive, check_rollout_args

__all__ = ["NAMES", "SingleTrack"]

LATERAL = ("front_per_mass", "rear_per_mass", "steer_per_mass")  # C_f/m, C_r/m, C_f/(m i_s)
YAW = ("mass_per_inertia",)  # m / I_z
LONGITUDINAL = ("rolling", "drag", "throttle", "throttle_power", "brake")  # c_0 c_2 g_1 g_2 g_3
NAMES = LATERAL + YAW + LONGITUDINAL
_Maps = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class SingleTrack(Learner):
    """The linear single-track model plus a first-order longitudinal channel (module docstring).

    Args:
        cg_to_front_m, cg_to_rear_m: a and b, measured (tape and axle scales).
        mass_kg: measured; used only to report C_f, C_r (N/rad) and I_z (kg m²).
        min_speed_mps: below it the lateral terms use this speed (1/vx stays bounded), and
            samples slower than it do not enter the lateral fit.
        max_lateral_accel_mps2: the lateral and yaw fits use samples below this lateral
            acceleration only (the tyres' linear range, about 0.4 g).

    Fitted attributes: ``coefficients_`` (len(NAMES),), ``dt_`` (s), ``normalizer_``;
    ``C_`` = I and ``lift`` = the normalization (a lifted state of the state itself).
    """

    name: ClassVar[str] = "single_track"

    def __init__(
        self,
        cg_to_front_m: float = 1.15,
        cg_to_rear_m: float = 1.55,
        mass_kg: float = 1500.0,
        min_speed_mps: float = 3.0,
        max_lateral_accel_mps2: float = 4.0,
    ) -> None:
        self.a = check_positive("cg_to_front_m", cg_to_front_m)
        self.b = check_positive("cg_to_rear_m", cg_to_rear_m)
        self.mass_kg = check_positive("mass_kg", mass_kg)
        self.min_speed = check_positive("min_speed_mps", min_speed_mps)
        self.max_lateral_accel = check_positive("max_lateral_accel_mps2", max_lateral_accel_mps2)
        self._hyperparameters: dict[str, Any] = {
            "cg_to_front_m": self.a,
            "cg_to_rear_m": self.b,
            "mass_kg": self.mass_kg,
            "min_speed_mps": self.min_speed,
            "max_lateral_accel_mps2": self.max_lateral_accel,
        }
        self.C_ = np.eye(3)
        self._maps: tuple[MinMaxNormalizer, _Maps] | None = None
        self._floats: tuple[float, ...] = ()

    # -- identification ---------------------------------------------------------------------

    def fit(
        self, train: Sequence[Episode], validation: Sequence[Episode], normalizer: MinMaxNormalizer
    ) -> Self:
        """Least squares on the Euler one-step derivatives of ``train`` (module docstring)."""
        check_fit_data(train, validation, normalizer, self.name)
        steps = np.concatenate([np.diff(e.time_s) for e in train])
        dt = float(np.median(steps))
        x = np.concatenate([e.states[:-1] for e in train])
        u = np.concatenate([_features(e.inputs[:-1]) for e in train])
        rate = np.concatenate([np.diff(e.states, axis=0) for e in train]) / dt
        vx, vy, r = x.T
        lateral_accel = rate[:, 1] + vx * r
        # The linear tyre range: where a linear single-track model is meant to hold.
        moving = (vx >= self.min_speed) & (np.abs(lateral_accel) <= self.max_lateral_accel)
        if moving.sum() < 10 * len(NAMES):
            raise ValueError(
                f"single_track: only {int(moving.sum())} training samples at vx >= "
                f"{self.min_speed} m/s (learner.min_speed_mps) and |ay| <= "
                f"{self.max_lateral_accel} m/s² (learner.max_lateral_accel_mps2); too few to "
                f"identify {len(NAMES)} parameters"
            )
        front, rear, steer, mass_per_inertia = self._fit_lateral(
            x[moving], u[moving], lateral_accel[moving], rate[moving, 2]
        )
        rolling_regime = vx > 0.5  # at standstill the brakes hold the car: no dynamics to fit
        longitudinal = self._longitudinal_regressors(x, u)[rolling_regime]
        target = (rate[:, 0] - vy * r)[rolling_regime]
        longitudinal_fit = _lstsq(longitudinal, target)
        self.coefficients_ = np.array(
            [front, rear, steer, mass_per_inertia, *longitudinal_fit], dtype=np.float64
        )
        self.dt_ = dt
        self.normalizer_ = normalizer
        self._maps = None  # new coefficients: the cached maps and floats are rebuilt
        return self

    def _fit_lateral(
        self, x: np.ndarray, u: np.ndarray, lateral_accel: np.ndarray, yaw_accel: np.ndarray
    ) -> tuple[float, float, float, float]:
        """(C_f/m, C_r/m, C_f/(m i_s), m/I_z): both equations together, by separable least
        squares (for a given m/I_z both are linear in the rest; the best m/I_z by a bounded
        scalar search). Each equation is scaled by its spread so both count.

        Fitted apart, the lateral equation alone cannot tell C_f from C_r (both multiply
        nearly −vy/vx): on ``data=default`` it gave C_r = 5·C_f and a model that lost the lane
        change; the yaw equation weighs them with +a and −b and separates them.
        """
        alpha_f, alpha_r, delta = self._slips(x, u)
        lateral = np.column_stack([alpha_f, alpha_r, delta]) / lateral_accel.std()
        yaw = np.column_stack([self.a * alpha_f, -self.b * alpha_r, self.a * delta])
        yaw /= yaw_accel.std()
        target = np.concatenate([lateral_accel / lateral_accel.std(), yaw_accel / yaw_accel.std()])

        def fit(log_ratio: float) -> tuple[np.ndarray, float]:
            regressors = np.vstack([lateral, np.exp(log_ratio) * yaw])
            solution = _lstsq(regressors, target)
            return solution, float(np.sum((regressors @ solution - target) ** 2))

        # m / I_z = 1 / (yaw radius of gyration)²: radii from 0.3 m to 10 m cover any car.
        best = minimize_scalar(
            lambda log_ratio: fit(log_ratio)[1],
            bounds=(np.log(0.01), np.log(11.0)),
            method="bounded",
            options={"xatol": 1e-10},
        )
        (front, rear, steer), _ = fit(float(best.x))
        return float(front), float(rear), float(steer), float(np.exp(best.x))

    @property
    def parameters(self) -> dict[str, float]:
        """The identified physics, in SI units: C_f, C_r (N/rad per axle), I_z (kg m²), the
        steering ratio, and the longitudinal coefficients (per unit mass)."""
        values = dict(zip(NAMES, self.coefficients_.tolist(), strict=True))
        front, rear, steer = (values[k] for k in LATERAL)
        return {
            "cornering_stiffness_front_n_per_rad": front * self.mass_kg,
            "cornering_stiffness_rear_n_per_rad": rear * self.mass_kg,
            "yaw_inertia_kg_m2": self.mass_kg / values["mass_per_inertia"],
            "steering_ratio": front / steer if steer else float("inf"),
            **{k: values[k] for k in LONGITUDINAL},
        }

    # -- the model --------------------------------------------------------------------------

    def _slips(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(α_f without steering, α_r, steering-wheel angle in rad) at states x, inputs u."""
        vx, vy, r = x[..., 0], x[..., 1], x[..., 2]
        w = np.maximum(vx, self.min_speed)
        return -(vy + self.a * r) / w, -(vy - self.b * r) / w, np.deg2rad(u[..., 0])

    def _longitudinal_regressors(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        vx = x[..., 0]
        w = np.maximum(vx, self.min_speed)
        throttle, brake = np.maximum(u[..., 1], 0.0), np.minimum(u[..., 1], 0.0)
        return np.stack([np.ones_like(vx), vx * vx, throttle, throttle / w, brake], axis=-1)

    def derivative(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """ẋ (..., 3) at physical states x (..., 3) and input features u (..., 2) (steering
        wheel in degrees, signed pedal scale)."""
        front, rear, steer, mass_per_inertia = self.coefficients_[:4]
        rolling, drag, throttle_gain, power, brake_gain = self.coefficients_[4:]
        vx, vy, r = x[..., 0], x[..., 1], x[..., 2]
        alpha_f, alpha_r, delta = self._slips(x, u)
        force_f = front * alpha_f + steer * delta
        force_r = rear * alpha_r
        throttle = np.maximum(u[..., 1], 0.0)
        w = np.maximum(vx, self.min_speed)
        push = (
            throttle_gain * throttle + power * throttle / w + brake_gain * np.minimum(u[..., 1], 0)
        )
        dvx = vy * r + rolling + drag * vx * vx + push  # as _longitudinal_regressors
        dvy = force_f + force_r - vx * r
        dr = mass_per_inertia * (self.a * force_f - self.b * force_r)
        return np.stack([dvx, dvy, dr], axis=-1)

    def _jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(∂ẋ/∂x (K, 3, 3), ∂ẋ/∂u (K, 3, 2)) at K points, physical units (u: features)."""
        front, rear, steer, mass_per_inertia = self.coefficients_[:4]
        _, drag, throttle, power, brake = self.coefficients_[4:]
        vx, vy, r = x[:, 0], x[:, 1], x[:, 2]
        fast = (vx > self.min_speed).astype(float)  # ∂w/∂vx
        w = np.maximum(vx, self.min_speed)
        zero = np.zeros_like(vx)
        # ∂α/∂(vx, vy, r)
        d_alpha_f = np.stack([(vy + self.a * r) / w**2 * fast, -1 / w, -self.a / w], axis=-1)
        d_alpha_r = np.stack([(vy - self.b * r) / w**2 * fast, -1 / w, self.b / w], axis=-1)
        d_force_f, d_force_r = front * d_alpha_f, rear * d_alpha_r
        pedal = u[:, 1]
        pedal_on = np.maximum(pedal, 0.0)
        d_vx = np.stack([2 * drag * vx - power * pedal_on / w**2 * fast, r, vy], axis=-1)
        d_vy = d_force_f + d_force_r - np.stack([r, zero, vx], axis=-1)
        d_r = mass_per_inertia * (self.a * d_force_f - self.b * d_force_r)
        jx = np.stack([d_vx, d_vy, d_r], axis=1)
        # Pedal: the throttle's slope above 0, the brake's below, their mean at exactly 0.
        on_throttle = throttle + power / w
        d_pedal = np.where(
            pedal > 0, on_throttle, np.where(pedal < 0, brake, (on_throttle + brake) / 2)
        )
        d_steer = np.deg2rad(steer)
        ju = np.zeros((len(vx), 3, 2))
        ju[:, 0, 1] = d_pedal
        ju[:, 1, 0] = d_steer
        ju[:, 2, 0] = mass_per_inertia * self.a * d_steer
        return jx, ju

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        x0, inputs = check_rollout_args(x0, inputs, 3, 2)
        u = _features(inputs)
        x = np.empty((*inputs.shape[:-1][:-1], inputs.shape[-2] + 1, 3))
        x[..., 0, :] = x0
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(inputs.shape[-2]):
                state = x[..., k, :] + self.dt_ * self.derivative(x[..., k, :], u[..., k, :])
                state[..., 0] = np.maximum(state[..., 0], 0.0)  # brakes stop the car, no more
                x[..., k + 1, :] = state
        return x

    # -- the LinearizableModel contract (normalized units) ----------------------------------

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.normalizer_.states(x), dtype=float)

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """One Euler step in normalized units (no stop at vx = 0: the smooth model the MPC sees)."""
        state_span, state_min, input_span, input_min = self._coordinates()
        x = z * state_span + state_min
        u = v * input_span + input_min
        if x.ndim == 1:  # the MPC's rollout, one point at a time: floats, not 0-d arrays
            return (
                z
                + self.dt_ * np.array(self._derivative_point(*x.tolist(), *u.tolist())) / state_span
            )
        return z + self.dt_ * self.derivative(x, u) / state_span

    def _derivative_point(
        self, vx: float, vy: float, r: float, steer_deg: float, pedal: float
    ) -> tuple[float, float, float]:
        """:meth:`derivative` at one point in plain floats (10x faster than numpy on 3-vectors)."""
        front, rear, steer, mass_per_inertia, rolling, drag, gain, power, brake = self._floats
        w = max(vx, self.min_speed)
        force_f = -front * (vy + self.a * r) / w + steer * steer_deg * (math.pi / 180.0)
        force_r = -rear * (vy - self.b * r) / w
        throttle = max(pedal, 0.0)
        push = gain * throttle + power * throttle / w + brake * min(pedal, 0.0)
        dvx = vy * r + rolling + drag * vx * vx + push
        dvy = force_f + force_r - vx * r
        return dvx, dvy, mass_per_inertia * (self.a * force_f - self.b * force_r)

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        state_span, state_min, input_span, input_min = self._coordinates()
        jx, ju = self._jacobians(z * state_span + state_min, v * input_span + input_min)
        A = np.eye(3) + self.dt_ * jx * state_span[None, :] / state_span[:, None]
        B = self.dt_ * ju * input_span[None, :] / state_span[:, None]
        d = self.step(z, v) - np.einsum("kab,kb->ka", A, z) - np.einsum("kaj,kj->ka", B, v)
        return A, B, d

    def _coordinates(self) -> _Maps:
        """(state span, state min, input-feature span, input-feature min): x = span z + min and
        features = span v + min, the normalizer's affine maps (cached per normalizer and fit,
        with the coefficients as floats)."""
        if self._maps is None or self._maps[0] is not self.normalizer_:
            normalizer = self.normalizer_
            state_span, input_span = _spans(normalizer)
            state_min = normalizer.states_inverse(np.zeros(3))
            input_min = np.asarray(normalizer.input_min, dtype=float)
            self._maps = (normalizer, (state_span, state_min, input_span, input_min))
            self._floats = tuple(self.coefficients_.tolist())
        return self._maps[1]

    # -- model file ---------------------------------------------------------------------------

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {"coefficients": self.coefficients_, "dt": np.array([self.dt_])}

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        return {"coefficients": (len(NAMES),), "dt": (1,)}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        self.coefficients_ = state["coefficients"].numpy().astype(np.float64)
        self._maps = None
        self.dt_ = float(state["dt"].numpy()[0])


def _features(u: np.ndarray) -> np.ndarray:
    """(steering-wheel degrees, signed pedal scale): the inputs the model is linear in."""
    u = np.asarray(u, dtype=float)
    return np.stack([u[..., 0], pedal_scale(u[..., 1])], axis=-1)


def _spans(normalizer: MinMaxNormalizer) -> tuple[np.ndarray, np.ndarray]:
    """Physical units per normalized unit: of the states, and of the input features."""
    state_span = normalizer.states_inverse(np.ones(3)) - normalizer.states_inverse(np.zeros(3))
    # inputs() is affine in the features: feature 1 (1° of steering, full throttle) minus 0.
    per_feature = normalizer.inputs(np.array([1.0, 0.2])) - normalizer.inputs(np.zeros(2))
    return state_span, 1.0 / per_feature


def _lstsq(regressors: np.ndarray, target: np.ndarray) -> np.ndarray:
    solution, *_ = np.linalg.lstsq(regressors, target, rcond=None)
    return np.asarray(solution, dtype=np.float64)
