"""The physics baseline: a linear single-track (bicycle) model identified from the driving data.

What a vehicle engineer writes before any learning. Lateral: the linear single-track model with
axle cornering stiffnesses, in the measured speed vx (w = max(vx, min_speed_mps))::

    α_f = δ − (vy + a r) / w,   α_r = −(vy − b r) / w,   δ = steer / i_s
    vy' = (C_f α_f + C_r α_r) / m − vx r
    r'  = (a C_f α_f − b C_r α_r) / I_z

Expanded, both are linear in δ, vy / w and r / w, with six coefficients (the regression form
the model runs in)::

    vy' = θ_1 δ + θ_2 vy / w + θ_3 r / w − vx r,     r' = θ_4 δ + θ_5 vy / w + θ_6 r / w

Longitudinal, first order in vx, with every other input split into its positive and negative
parts f⁺, f⁻ (the sedan's signed pedal scale: throttle and brake; a log's throttle and brake
columns each)::

    vx' = vy r + c_0 + c_2 vx² + Σ_j (g_j f_j⁺ + p_j f_j⁺ / w + b_j f_j⁻)

(rolling resistance, aerodynamic drag, a force between constant torque g and constant power
p / v, brake). Each input's role (:class:`~harness.core.episode.InputChannel`, the data config's
``data.inputs.<name>.role``) says where it goes: the one steering input (``steering_wheel`` or
``road_wheel``, in its unit deg or rad) to the lateral model, every other to the longitudinal
one, with the signs physics requires: resistances and a brake never accelerate, a drive or the
sedan's signed pedal never decelerates above zero, and a brake does no work per speed (p = 0).
A fit that breaks a sign is solved again with the signs as bounds (``training.fit.bounded``
names the coefficients held at their bound). Data whose inputs declare no roles is refused in
one line, before any data is read.

Identified by least squares on the training episodes' one-step derivatives (samples at vx >=
``min_speed_mps`` and, for the lateral and yaw equations, in the tyres' linear range |ay| <=
``max_lateral_accel_mps2``; nothing is read from the plant's configuration). Where a and b are
measured (``cg_to_front_m``, ``cg_to_rear_m``: tape and axle scales), the lateral and yaw
equations are fitted together, linear in (C_f / m, C_r / m, C_f / (m i_s)) for a given m / I_z,
by separable least squares over m / I_z; the physical values follow (:attr:`parameters`).
Where they are not (``null``: a user's logs of a car nobody measured), the six θ are fitted
directly, and a and b are recovered from them; where those are outside what a road car can be
(:data:`GEOMETRY_BOUNDS_M`: the data cannot separate them), a and b are identified within those
bounds instead, by the search above over a and b, and a warning says so. The mass cancels: it
only converts per-mass values into N/rad and kg·m². On logs of another car, the sedan's
geometry and mass (the defaults) are used with a warning that names the settings to give.

Discretized at the data's period h by ``substeps_`` explicit Euler steps of h / n: n is the
smallest that keeps Euler stable, with a factor-2 margin, for every eigenvalue of the lateral
dynamics between min_speed_mps and the fastest training speed. At 10 ms the sedan needs one
(the plain Euler step); one Euler step of 50 ms at 3 m/s has |1 + hλ| > 1, and vy grew to 10⁶
within 3 s on the DDK CarSim runs.

Besides a :class:`~learners.base.Learner` (``fit``/``predict``, so it has rows in the
prediction and step-response tables), the model is a
:class:`~harness.core.contracts.LinearizableModel` in the normalized state (z = x_norm, C = I):
the time-varying DE-MPC linearises it along its plan (``controller=bicycle_mpc``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self

import numpy as np
import torch

from harness.core.checks import positive
from harness.core.contracts import Dynamics
from harness.core.episode import (
    ANGLE_UNITS,
    ROLES,
    SEDAN_INPUTS,
    STEERING_ROLES,
    Episode,
    InputChannel,
    MinMaxNormalizer,
    input_features,
)
from learners.base import Learner, Shape, check_fit_data, check_rollout_args
from learners.settings import settle
from learners.single_track_fit import (
    LateralSamples,
    form_of,
    identify_lateral,
    identify_longitudinal,
    physical_parameters,
    stable_substeps,
    warn_sedan_geometry,
)

__all__ = ["SingleTrack", "SingleTrackConfig", "coefficient_names", "form_of"]

FORM = ("vy_steer", "vy_vy", "vy_r", "r_steer", "r_vy", "r_r")  # θ_1 .. θ_6
LONGITUDINAL = ("rolling", "drag", "throttle", "throttle_power", "brake")  # the sedan's c_0 .. b
# Bounds on (g, p, b) of an input by its role: g multiplies its positive part, p that part per
# speed, b its negative part. None: the coefficient is held at 0.
_INF = math.inf
_SIGNS: dict[str, tuple[tuple[float, float] | None, ...]] = {
    "drive": ((0.0, _INF), (0.0, _INF), (0.0, _INF)),
    "pedal": ((0.0, _INF), (0.0, _INF), (0.0, _INF)),
    "brake": ((-_INF, 0.0), None, (0.0, _INF)),
    "": ((-_INF, _INF), (-_INF, _INF), (-_INF, _INF)),  # a model fitted before roles
}
_RESISTANCES = ((-_INF, 0.0), (-_INF, 0.0))  # c_0 (rolling), c_2 (drag)
log = logging.getLogger(__name__)
_Maps = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class InputLayout:
    """Where each input goes: ``order`` lists the data's columns as the model takes them (the
    steering first, then the others as the data has them), ``steer_to_rad`` converts the
    steering's unit, and ``roles`` are the others' roles, in that order."""

    order: tuple[int, ...]
    steer_to_rad: float
    roles: tuple[str, ...]

    @classmethod
    def of(cls, channels: Sequence[InputChannel], fitting: bool = True) -> InputLayout:
        """The layout the channels' roles declare; refused in one line where they do not say
        which input steers and what the others are. A model file fitted before roles were
        described (``fitting=False``, no role anywhere) keeps the layout it was fitted with:
        the first input steers, in degrees where its name ends in ``_deg``."""
        if not fitting and all(c.role is None for c in channels):
            unit = ANGLE_UNITS["deg" if channels[0].name.endswith("_deg") else "rad"]
            return cls(tuple(range(len(channels))), unit, ("",) * (len(channels) - 1))
        for channel in channels:
            if channel.role is None:
                raise ValueError(
                    f"single_track: input {channel.name!r} declares no role, so the physics "
                    f"baseline cannot tell whether it steers, drives or brakes: set "
                    f"data.inputs.{channel.name}.role to one of {', '.join(ROLES)}"
                )
        steering = [j for j, c in enumerate(channels) if c.role in STEERING_ROLES]
        if len(steering) != 1:
            names = ", ".join(channels[j].name for j in steering) or "none"
            raise ValueError(
                f"single_track: the physics baseline needs exactly one steering input (role "
                f"steering_wheel or road_wheel); the data declares {len(steering)} ({names})"
            )
        first = steering[0]
        order = (first, *(j for j in range(len(channels)) if j != first))
        roles = tuple(str(channels[j].role) for j in order[1:])
        return cls(order, ANGLE_UNITS[str(channels[first].unit)], roles)

    def bounds(self) -> list[tuple[float, float] | None]:
        """Bounds of the longitudinal coefficients (c_0, c_2, then g, p, b of each input)."""
        return [*_RESISTANCES, *(b for role in self.roles for b in _SIGNS[role])]


def coefficient_names(input_names: Sequence[str]) -> tuple[str, ...]:
    """θ_1 .. θ_6, c_0, c_2, then (g, p, b) of every input after the steering."""
    per_input = tuple(
        f"{name}_{part}" for name in input_names[1:] for part in ("on", "on_power", "off")
    )
    return (*FORM, "rolling", "drag", *per_input)


@dataclass(frozen=True)
class SingleTrackConfig:
    """The single-track model's settings (``conf/learner/single_track.yaml``): only what a person
    measures with a tape and axle scales (the default sedan's, models/mjcf/sedan.xml's header);
    both axle distances null: identified from the data."""

    cg_to_front_m: float | None = 1.15  # a: CG to front axle (wheelbase x rear axle load share)
    cg_to_rear_m: float | None = 1.55  # b: CG to rear axle
    mass_kg: float = 1500.0  # only converts the identified per-mass values to N/rad and kg m^2
    # Lateral terms use max(vx, this); slower samples stay out of the fit.
    min_speed_mps: float = 3.0
    max_lateral_accel_mps2: float = 4.0  # lateral and yaw fits in the tyres' linear range (0.4 g)

    def __post_init__(self) -> None:
        front, rear = self.cg_to_front_m, self.cg_to_rear_m
        if (front is None) != (rear is None):
            raise ValueError(
                "learner.cg_to_front_m and learner.cg_to_rear_m must both be given (measured) "
                "or both be null (identified from the data)"
            )
        settle(
            self,
            cg_to_front_m=None if front is None else positive("learner.cg_to_front_m", front),
            cg_to_rear_m=None if rear is None else positive("learner.cg_to_rear_m", rear),
            mass_kg=positive("learner.mass_kg", self.mass_kg),
            min_speed_mps=positive("learner.min_speed_mps", self.min_speed_mps),
            max_lateral_accel_mps2=positive(
                "learner.max_lateral_accel_mps2", self.max_lateral_accel_mps2
            ),
        )


class SingleTrack(Learner):
    """The linear single-track model plus a first-order longitudinal channel (module docstring).

    Settings (:class:`SingleTrackConfig`):
        cg_to_front_m, cg_to_rear_m: a and b, measured (tape and axle scales); both null:
            identified from the data.
        mass_kg: measured; used only to report C_f, C_r (N/rad) and I_z (kg m²).
        min_speed_mps: below it the lateral terms use this speed (1/vx stays bounded), and
            samples slower than it do not enter the lateral fit.
        max_lateral_accel_mps2: the lateral and yaw fits use samples below this lateral
            acceleration only (the tyres' linear range, about 0.4 g).

    Fitted attributes: ``coefficients_`` (:func:`coefficient_names`), ``dt_`` (s),
    ``substeps_``, ``normalizer_``; ``C_`` = I and ``lift`` = the normalization.
    """

    name: ClassVar[str] = "single_track"
    config_class: ClassVar[type] = SingleTrackConfig
    config: SingleTrackConfig
    dynamics: ClassVar[Dynamics] = "nonlinear"  # DE-MPC linearises it along its plan

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        self.a, self.b = self.config.cg_to_front_m, self.config.cg_to_rear_m
        self.mass_kg = self.config.mass_kg
        self.min_speed = self.config.min_speed_mps
        self.max_lateral_accel = self.config.max_lateral_accel_mps2
        self.C_ = np.eye(3)
        self.substeps_ = 1
        self._maps: tuple[MinMaxNormalizer, _Maps] | None = None
        self._floats: tuple[float, ...] = ()
        self._layout: tuple[Any, InputLayout, tuple[int, ...]] | None = None

    @classmethod
    def of_physics(
        cls,
        physics: Mapping[str, float],
        dt: float,
        a: float = 1.15,
        b: float = 1.55,
        **kwargs: Any,
    ) -> SingleTrack:
        """The sedan-input model (steering wheel in degrees, signed pedal) with the given
        C_f/m, C_r/m, C_f/(m i_s), m/I_z and longitudinal coefficients (``LATERAL``, ``YAW``,
        ``LONGITUDINAL``): a known model, as the tests and benches drive it."""
        model = cls(cg_to_front_m=a, cg_to_rear_m=b, **kwargs)
        longitudinal = [physics[k] for k in LONGITUDINAL]
        model.coefficients_ = np.array([*form_of(physics, a, b), *longitudinal], dtype=np.float64)
        model.dt_ = float(dt)
        model.substeps_ = stable_substeps(model.coefficients_, model.dt_, model.min_speed, 40.0)
        return model

    def check_inputs(self, channels: Sequence[InputChannel]) -> None:
        """The roles say which input steers and what the others are (before any data)."""
        InputLayout.of(channels)

    # -- identification ---------------------------------------------------------------------

    def fit(
        self, train: Sequence[Episode], validation: Sequence[Episode], normalizer: MinMaxNormalizer
    ) -> Self:
        """Least squares on the Euler one-step derivatives of ``train`` (module docstring)."""
        check_fit_data(train, validation, normalizer, self.name)
        layout = InputLayout.of(normalizer.channels)
        own = {"cg_to_front_m": self.a, "cg_to_rear_m": self.b, "mass_kg": self.mass_kg}
        warn_sedan_geometry(own, normalizer.channels)
        steps = np.concatenate([np.diff(e.time_s) for e in train])
        dt = float(np.median(steps))
        self.normalizer_ = normalizer  # the inputs' roles say which steers, in which unit
        self._maps = None
        x = np.concatenate([e.states[:-1] for e in train])
        u = np.concatenate([self._features(e.inputs[:-1]) for e in train])
        rate = np.concatenate([np.diff(e.states, axis=0) for e in train]) / dt
        vx, vy, r = x.T
        lateral_accel = rate[:, 1] + vx * r
        # The linear tyre range: where a linear single-track model is meant to hold.
        moving = (vx >= self.min_speed) & (np.abs(lateral_accel) <= self.max_lateral_accel)
        needed = 10 * len(coefficient_names(normalizer.input_names))
        if moving.sum() < needed:
            raise ValueError(
                f"single_track: only {int(moving.sum())} training samples at vx >= "
                f"{self.min_speed} m/s (learner.min_speed_mps) and |ay| <= "
                f"{self.max_lateral_accel} m/s² (learner.max_lateral_accel_mps2); too few to "
                f"identify {needed // 10} parameters"
            )
        delta = u[moving, 0] * layout.steer_to_rad
        lateral = LateralSamples(x[moving], delta, lateral_accel[moving], rate[moving, 2])
        form, self.identified_geometry_ = identify_lateral(lateral, self.a, self.b, self.min_speed)
        rolling_regime = vx > 0.5  # at standstill the brakes hold the car: no dynamics to fit
        longitudinal = longitudinal_regressors(x, u, self.min_speed)[rolling_regime]
        target = (rate[:, 0] - vy * r)[rolling_regime]
        names = coefficient_names(self._internal_names(normalizer))[6:]
        longitudinal_fit, self.bounded_ = identify_longitudinal(
            longitudinal, target, layout.bounds(), names
        )
        self.coefficients_ = np.array([*form, *longitudinal_fit], dtype=np.float64)
        self.dt_ = dt
        self._maps = None  # new coefficients: the cached maps and floats are rebuilt
        self.substeps_ = stable_substeps(self.coefficients_, dt, self.min_speed, float(vx.max()))
        return self

    def _input_layout(self) -> InputLayout:
        """The layout of this model's inputs (before a fit: the sedan's), cached per channels."""
        normalizer = getattr(self, "normalizer_", None)
        channels = normalizer.channels if normalizer is not None else SEDAN_INPUTS
        if self._layout is None or self._layout[0] is not channels:
            layout = InputLayout.of(channels, fitting=False)
            inverse = tuple(int(i) for i in np.argsort(layout.order))
            self._layout = (channels, layout, inverse)
        return self._layout[1]

    def _internal(self, u: np.ndarray) -> np.ndarray:
        """Inputs (..., m) in the data's column order as the model takes them (steering first)."""
        order = self._input_layout().order
        return u if order == tuple(range(len(order))) else u[..., list(order)]

    def _internal_names(self, normalizer: MinMaxNormalizer) -> tuple[str, ...]:
        return tuple(normalizer.input_names[j] for j in self._input_layout().order)

    @property
    def fit_summary(self) -> dict[str, Any]:
        """What the fit identified (``training.fit``): the physics, the Euler sub-steps, the
        longitudinal coefficients held at a sign's bound, and whether a and b were bounded."""
        summary = {"parameters": self.parameters, "substeps": self.substeps_}
        bounded = getattr(self, "bounded_", [])
        names = coefficient_names(self._internal_names(self.normalizer_))[6:]
        summary["bounded"] = [names[i] for i in bounded]
        summary["geometry_bounded"] = getattr(self, "identified_geometry_", None) is not None
        return summary

    @property
    def parameters(self) -> dict[str, float]:
        """The identified physics in SI units (:func:`physical_parameters`)."""
        names = (
            coefficient_names(self._internal_names(self.normalizer_))
            if hasattr(self, "normalizer_")
            else coefficient_names(("steer_wheel_deg", "pedal"))
        )
        return physical_parameters(self.coefficients_, self.a, self.b, self.mass_kg, names)

    # -- the model --------------------------------------------------------------------------

    def derivative(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """ẋ (..., 3) at physical states x (..., 3) and input features u (..., m) (steering,
        then the others; for the sedan the signed pedal scale)."""
        t1, t2, t3, t4, t5, t6 = self.coefficients_[:6]
        vx, vy, r = x[..., 0], x[..., 1], x[..., 2]
        w = np.maximum(vx, self.min_speed)
        delta = u[..., 0] * self._input_layout().steer_to_rad
        push = longitudinal_regressors(x, u, self.min_speed) @ self.coefficients_[6:]
        dvx = vy * r + push
        dvy = t1 * delta + (t2 * vy + t3 * r) / w - vx * r
        dr = t4 * delta + (t5 * vy + t6 * r) / w
        return np.stack([dvx, dvy, dr], axis=-1)

    def _euler(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One period of ``substeps_`` Euler steps, physical units (no stop at vx = 0)."""
        h = self.dt_ / self.substeps_
        for _ in range(self.substeps_):
            x = x + h * self.derivative(x, u)
        return x

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        m = len(self.normalizer_.input_min) if hasattr(self, "normalizer_") else 2
        x0, inputs = check_rollout_args(x0, inputs, 3, m)
        u = self._features(inputs)
        x = np.empty((*inputs.shape[:-1][:-1], inputs.shape[-2] + 1, 3))
        x[..., 0, :] = x0
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(inputs.shape[-2]):
                state = self._euler(x[..., k, :], u[..., k, :])
                state[..., 0] = np.maximum(state[..., 0], 0.0)  # brakes stop the car, no more
                x[..., k + 1, :] = state
        return x

    def _features(self, inputs: np.ndarray) -> np.ndarray:
        """The inputs as the model is linear in them, steering first (before a fit: the
        sedan's)."""
        if hasattr(self, "normalizer_"):
            return self._internal(self.normalizer_.input_features(inputs))
        return input_features(inputs, SEDAN_INPUTS)

    # -- the LinearizableModel contract (normalized units) ----------------------------------

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.normalizer_.states(x), dtype=float)

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """One period in normalized units (no stop at vx = 0: the smooth model the MPC sees)."""
        state_span, state_min, input_span, input_min = self._coordinates()
        x = z * state_span + state_min
        u = self._internal(v * input_span + input_min)
        if x.ndim == 1 and self._floats:  # the MPC's rollout, one point: floats, not 0-d arrays
            point = x.tolist()
            h = self.dt_ / self.substeps_
            for _ in range(self.substeps_):
                rates = derivative_point(
                    self._floats, self._steer_float, self.min_speed, *point, *u.tolist()
                )
                point = [p + h * d for p, d in zip(point, rates, strict=True)]
            return (np.array(point) - state_min) / state_span
        return (self._euler(x, u) - state_min) / state_span

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The derivative of :meth:`step` (every sub-step's Jacobian, chained) at K points."""
        state_span, state_min, input_span, input_min = self._coordinates()
        z, v = np.atleast_2d(z), np.atleast_2d(v)
        x, u = z * state_span + state_min, self._internal(v * input_span + input_min)
        h = self.dt_ / self.substeps_
        steer = self._input_layout().steer_to_rad
        jac_x = np.broadcast_to(np.eye(3), (len(x), 3, 3)).copy()
        jac_u = np.zeros((len(x), 3, u.shape[1]))
        for _ in range(self.substeps_):
            jx, ju = jacobians(self.coefficients_, self.min_speed, steer, x, u)
            step = np.eye(3) + h * jx
            jac_x = step @ jac_x
            jac_u = step @ jac_u + h * ju
            x = x + h * self.derivative(x, u)
        jac_u = jac_u[..., list(self._layout[2])] if self._layout else jac_u  # the data's order
        A = jac_x * state_span[None, :] / state_span[:, None]
        B = jac_u * input_span[None, :] / state_span[:, None]
        d = self.step(z, v) - np.einsum("kab,kb->ka", A, z) - np.einsum("kaj,kj->ka", B, v)
        return A, B, d

    def _coordinates(self) -> _Maps:
        """(state span, state min, input-feature span, input-feature min): x = span z + min and
        features = span v + min, the normalizer's affine maps (cached per normalizer and fit,
        with the coefficients as floats where the inputs are the sedan's two)."""
        if self._maps is None or self._maps[0] is not self.normalizer_:
            normalizer = self.normalizer_
            state_span, input_span = _spans(normalizer)
            state_min = normalizer.states_inverse(np.zeros(3))
            input_min = np.asarray(normalizer.input_min, dtype=float)
            self._maps = (normalizer, (state_span, state_min, input_span, input_min))
            two = len(input_min) == 2
            self._floats = tuple(self.coefficients_.tolist()) if two else ()
            self._steer_float = self._input_layout().steer_to_rad
        return self._maps[1]

    # -- model file ---------------------------------------------------------------------------

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {
            "coefficients": self.coefficients_,
            "dt": np.array([self.dt_]),
            "substeps": np.array([float(self.substeps_)]),  # float: a NaN in it is caught
        }

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        return {"coefficients": (6 + 2 + 3 * (m - 1),), "dt": (1,), "substeps": (1,)}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        self.coefficients_ = state["coefficients"].numpy().astype(np.float64)
        self._maps = None
        self.dt_ = float(state["dt"].numpy()[0])
        self.substeps_ = max(1, round(float(state["substeps"].numpy()[0])))


def longitudinal_regressors(x: np.ndarray, u: np.ndarray, min_speed: float) -> np.ndarray:
    """[1, vx², per other input: its positive part, that part per speed, its negative part]."""
    vx = x[..., 0]
    w = np.maximum(vx, min_speed)
    on, off = np.maximum(u[..., 1:], 0.0), np.minimum(u[..., 1:], 0.0)
    per_input = np.stack([on, on / w[..., None], off], axis=-1)  # (..., m - 1, 3)
    per_input = per_input.reshape(*per_input.shape[:-2], -1)
    return np.concatenate([np.ones_like(vx)[..., None], (vx * vx)[..., None], per_input], axis=-1)


def jacobians(
    coefficients: np.ndarray, min_speed: float, steer: float, x: np.ndarray, u: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(∂ẋ/∂x (K, 3, 3), ∂ẋ/∂u (K, 3, m)) at K points, physical units (u: features; ``steer``:
    the steering input's radians per unit)."""
    t1, t2, t3, t4, t5, t6 = coefficients[:6]
    drag = coefficients[7]
    gains = coefficients[8:].reshape(-1, 3)  # (m - 1, 3): g, p, b
    vx, vy, r = x[:, 0], x[:, 1], x[:, 2]
    fast = (vx > min_speed).astype(float)  # ∂w/∂vx
    w = np.maximum(vx, min_speed)
    others = u[:, 1:]
    on = np.maximum(others, 0.0)
    d_vx = np.stack([2 * drag * vx - (on @ gains[:, 1]) / w**2 * fast, r, vy], axis=-1)
    d_vy = np.stack([-(t2 * vy + t3 * r) / w**2 * fast - r, t2 / w, t3 / w - vx], axis=-1)
    d_r = np.stack([-(t5 * vy + t6 * r) / w**2 * fast, t5 / w, t6 / w], axis=-1)
    jx = np.stack([d_vx, d_vy, d_r], axis=1)
    # Each other input: its positive part's slope above 0, the negative's below, their
    # mean at exactly 0.
    on_slope = gains[:, 0] + gains[:, 1] / w[:, None]
    slope = np.where(
        others > 0, on_slope, np.where(others < 0, gains[:, 2], (on_slope + gains[:, 2]) / 2)
    )
    ju = np.zeros((len(vx), 3, u.shape[1]))
    ju[:, 0, 1:] = slope
    ju[:, 1, 0] = t1 * steer
    ju[:, 2, 0] = t4 * steer
    return jx, ju


def derivative_point(
    coefficients: tuple[float, ...],
    steer: float,
    min_speed: float,
    vx: float,
    vy: float,
    r: float,
    steer_in: float,
    pedal: float,
) -> tuple[float, float, float]:
    """:meth:`SingleTrack.derivative` at one point of the sedan's two inputs, in plain floats
    (10x faster than numpy on 3-vectors)."""
    t1, t2, t3, t4, t5, t6, rolling, drag, gain, power, brake = coefficients
    w = max(vx, min_speed)
    delta = steer_in * steer
    throttle = max(pedal, 0.0)
    push = gain * throttle + power * throttle / w + brake * min(pedal, 0.0)
    dvx = vy * r + rolling + drag * vx * vx + push
    dvy = t1 * delta + (t2 * vy + t3 * r) / w - vx * r
    return dvx, dvy, t4 * delta + (t5 * vy + t6 * r) / w


def _spans(normalizer: MinMaxNormalizer) -> tuple[np.ndarray, np.ndarray]:
    """Physical units per normalized unit: of the states, and of the input features."""
    state_span = normalizer.states_inverse(np.ones(3)) - normalizer.states_inverse(np.zeros(3))
    low, high = np.asarray(normalizer.input_min), np.asarray(normalizer.input_max)
    return state_span, np.where(high - low > 1e-12, high - low, 1.0)
