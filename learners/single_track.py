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
from scipy.optimize import lsq_linear, minimize, minimize_scalar

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
    is_sedan,
)
from learners.base import Learner, Shape, check_fit_data, check_rollout_args
from learners.settings import settle

__all__ = ["SingleTrack", "SingleTrackConfig", "coefficient_names", "form_of"]

LATERAL = ("front_per_mass", "rear_per_mass", "steer_per_mass")  # C_f/m, C_r/m, C_f/(m i_s)
YAW = ("mass_per_inertia",)  # m / I_z
FORM = ("vy_steer", "vy_vy", "vy_r", "r_steer", "r_vy", "r_r")  # θ_1 .. θ_6
LONGITUDINAL = ("rolling", "drag", "throttle", "throttle_power", "brake")  # the sedan's c_0 .. b
MAX_SUBSTEPS = 50
# a and b of any road car: from a city car's 0.8 m to a long van's 3 m, with margin.
GEOMETRY_BOUNDS_M = (0.5, 3.5)
SEDAN_GEOMETRY = {"cg_to_front_m": 1.15, "cg_to_rear_m": 1.55, "mass_kg": 1500.0}
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
class _LateralSamples:
    """The samples the lateral and yaw equations are fitted on: states, road-wheel angle
    (rad), lateral and yaw acceleration."""

    x: np.ndarray
    delta: np.ndarray
    lateral_accel: np.ndarray
    yaw_accel: np.ndarray

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return self.x, self.delta, self.lateral_accel, self.yaw_accel


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


def form_of(
    physics: Mapping[str, float], a: float, b: float
) -> tuple[float, float, float, float, float, float]:
    """θ_1 .. θ_6 of the single-track model with C_f/m, C_r/m, C_f/(m i_s), m/I_z, a and b."""
    front, rear, steer = (physics[k] for k in LATERAL)
    k = physics["mass_per_inertia"]
    moment = a * front - b * rear
    return (
        steer,
        -(front + rear),
        -moment,
        k * a * steer,
        -k * moment,
        -k * (a * a * front + b * b * rear),
    )


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
        model.substeps_ = model._stable_substeps(40.0)
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
        self._warn_sedan_geometry(normalizer.channels)
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
        lateral = _LateralSamples(x[moving], delta, lateral_accel[moving], rate[moving, 2])
        self.identified_geometry_: tuple[float, float] | None = None
        if self.a is not None and self.b is not None:
            form = self._fit_geometry(lateral, self.a, self.b)
        else:
            w = np.maximum(vx[moving], self.min_speed)
            regressors = np.column_stack([delta, vy[moving] / w, r[moving] / w])
            form = (
                *_lstsq(regressors, lateral_accel[moving]),
                *_lstsq(regressors, rate[moving, 2]),
            )
            a, b = _geometry_of(form)
            low, high = GEOMETRY_BOUNDS_M
            if not (low <= a <= high and low <= b <= high):
                a, b = self._bounded_geometry(lateral, a, b)
                form = self._fit_geometry(lateral, a, b)
                self.identified_geometry_ = (a, b)
        rolling_regime = vx > 0.5  # at standstill the brakes hold the car: no dynamics to fit
        longitudinal = self._longitudinal_regressors(x, u)[rolling_regime]
        target = (rate[:, 0] - vy * r)[rolling_regime]
        longitudinal_fit, self.bounded_ = _signed_lstsq(longitudinal, target, layout.bounds())
        if self.bounded_:
            names = coefficient_names(self._internal_names(normalizer))[6:]
            held = ", ".join(names[i] for i in self.bounded_)
            log.warning(
                "single_track: the least-squares fit gave %s the sign physics forbids (an input "
                "that brakes accelerating, a drive that slows); fitted again with the signs as "
                "bounds, %s (training.fit.bounded)",
                held,
                "held at its bound" if len(self.bounded_) == 1 else "each held at its bound",
            )
        self.coefficients_ = np.array([*form, *longitudinal_fit], dtype=np.float64)
        self.dt_ = dt
        self._maps = None  # new coefficients: the cached maps and floats are rebuilt
        self.substeps_ = self._stable_substeps(float(vx.max()))
        return self

    def _fit_geometry(
        self, samples: _LateralSamples, a: float, b: float
    ) -> tuple[float, float, float, float, float, float]:
        """θ_1 .. θ_6 of the physical fit with a and b given."""
        fitted = self._fit_lateral(*samples.arrays(), a, b)
        return form_of(dict(zip(LATERAL + YAW, fitted, strict=True)), a, b)

    def _bounded_geometry(
        self, samples: _LateralSamples, a_free: float, b_free: float
    ) -> tuple[float, float]:
        """a and b within :data:`GEOMETRY_BOUNDS_M` that fit the lateral and yaw equations
        best (a coarse grid, then a bounded local search), with a warning that the free fit's
        were not a road car's."""
        low, high = GEOMETRY_BOUNDS_M

        def residual(ab: np.ndarray) -> float:
            return self._lateral_residual(samples, float(ab[0]), float(ab[1]))

        grid = np.linspace(low, high, 7)
        start = min(((a, b) for a in grid for b in grid), key=lambda ab: residual(np.array(ab)))
        best = minimize(residual, np.array(start), bounds=[(low, high)] * 2, method="L-BFGS-B")
        a, b = (float(v) for v in best.x)
        log.warning(
            "single_track: the data gives a = %.3g m, b = %.3g m, outside [%g, %g] m: it cannot "
            "separate the axles; identified within those bounds instead, a = %.2f m, b = %.2f "
            "m. Measured ones are better: learner.cg_to_front_m, learner.cg_to_rear_m",
            a_free,
            b_free,
            low,
            high,
            a,
            b,
        )
        return a, b

    def _lateral_residual(self, samples: _LateralSamples, a: float, b: float) -> float:
        """Normalized squared residual of both equations with a and b given."""
        form = self._fit_geometry(samples, a, b)
        x, delta, lateral_accel, yaw_accel = samples.arrays()
        vx, vy, r = x[:, 0], x[:, 1], x[:, 2]
        w = np.maximum(vx, self.min_speed)
        regressors = np.column_stack([delta, vy / w, r / w])
        lateral = regressors @ np.array(form[:3]) - lateral_accel
        yaw = regressors @ np.array(form[3:]) - yaw_accel
        return float(np.mean(lateral**2) / lateral_accel.var() + np.mean(yaw**2) / yaw_accel.var())

    def _warn_sedan_geometry(self, channels: Sequence[InputChannel]) -> None:
        """Logs of another car fitted with the sedan's measured geometry and mass: say so."""
        own = {"cg_to_front_m": self.a, "cg_to_rear_m": self.b, "mass_kg": self.mass_kg}
        defaults = [key for key, value in own.items() if value == SEDAN_GEOMETRY[key]]
        if is_sedan(channels) or not defaults:
            return
        log.warning(
            "single_track: these inputs are not the sedan's, but %s %s the sedan's (%s): set "
            "learner.%s to this car's (null a and b: identified from the data)",
            ", ".join(defaults),
            "is" if len(defaults) == 1 else "are",
            ", ".join(f"{SEDAN_GEOMETRY[k]:g}" for k in defaults),
            "=…, learner.".join(defaults) + "=…",
        )

    @staticmethod
    def _fit_lateral(
        x: np.ndarray,
        delta: np.ndarray,
        lateral_accel: np.ndarray,
        yaw_accel: np.ndarray,
        a: float,
        b: float,
    ) -> tuple[float, float, float, float]:
        """(C_f/m, C_r/m, C_f/(m i_s), m/I_z): both equations together, by separable least
        squares (for a given m/I_z both are linear in the rest; the best m/I_z by a bounded
        scalar search). Each equation is scaled by its spread so both count.

        Fitted apart, the lateral equation alone cannot tell C_f from C_r (both multiply
        nearly −vy/vx): on ``data=default`` it gave C_r = 5·C_f and a model that lost the lane
        change; the yaw equation weighs them with +a and −b and separates them.
        """
        vx, vy, r = x[:, 0], x[:, 1], x[:, 2]
        w = np.maximum(vx, 1e-9)
        alpha_f, alpha_r = -(vy + a * r) / w, -(vy - b * r) / w
        lateral = np.column_stack([alpha_f, alpha_r, delta]) / lateral_accel.std()
        yaw = np.column_stack([a * alpha_f, -b * alpha_r, a * delta])
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

    def _stable_substeps(self, fastest_mps: float) -> int:
        """Euler sub-steps per period that keep every lateral eigenvalue λ stable with a factor
        2 margin (h |λ|² <= |Re λ|), from min_speed_mps to ``fastest_mps``."""
        _, t2, t3, _, t5, t6 = self.coefficients_[:6]
        needed = 1
        for vx in np.linspace(self.min_speed, max(fastest_mps, self.min_speed), 50):
            w = max(vx, self.min_speed)
            jacobian = np.array([[t2 / w, t3 / w - vx], [t5 / w, t6 / w]])
            for eigenvalue in np.linalg.eigvals(jacobian):
                if eigenvalue.real >= 0:
                    continue  # not damped: no step size makes Euler follow it more stably
                largest = abs(eigenvalue.real) / abs(eigenvalue) ** 2
                needed = max(needed, math.ceil(self.dt_ / largest - 1e-9))
        return min(needed, MAX_SUBSTEPS)

    def _steer_to_rad(self) -> float:
        """The steering input's unit, as its channel declares it."""
        return self._input_layout().steer_to_rad

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
        """The identified physics, in SI units: C_f, C_r (N/rad per axle), I_z (kg m²), the
        steering ratio (per unit of the steering input), a and b (given or recovered), and the
        longitudinal coefficients (per unit mass)."""
        t1, t2, t3, _, t5, _ = self.coefficients_[:6].tolist()
        mass_per_inertia = t5 / t3 if t3 else float("nan")
        total, moment = -t2, -t3
        if self.a is not None and self.b is not None:
            a, b = self.a, self.b
        else:
            a, b = _geometry_of(self.coefficients_[:6])
        rear = (a * total - moment) / (a + b)
        front = total - rear
        names = (
            coefficient_names(self._internal_names(self.normalizer_))
            if hasattr(self, "normalizer_")
            else coefficient_names(("steer_wheel_deg", "pedal"))
        )
        return {
            "cornering_stiffness_front_n_per_rad": front * self.mass_kg,
            "cornering_stiffness_rear_n_per_rad": rear * self.mass_kg,
            "yaw_inertia_kg_m2": self.mass_kg / mass_per_inertia,
            "steering_ratio": front / t1 if t1 else float("inf"),
            "cg_to_front_m": a,
            "cg_to_rear_m": b,
            **dict(zip(names[6:], self.coefficients_[6:].tolist(), strict=True)),
        }

    # -- the model --------------------------------------------------------------------------

    def _longitudinal_regressors(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        vx = x[..., 0]
        w = np.maximum(vx, self.min_speed)
        on, off = np.maximum(u[..., 1:], 0.0), np.minimum(u[..., 1:], 0.0)
        per_input = np.stack([on, on / w[..., None], off], axis=-1)  # (..., m - 1, 3)
        per_input = per_input.reshape(*per_input.shape[:-2], -1)
        return np.concatenate(
            [np.ones_like(vx)[..., None], (vx * vx)[..., None], per_input], axis=-1
        )

    def derivative(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """ẋ (..., 3) at physical states x (..., 3) and input features u (..., m) (steering,
        then the others; for the sedan the signed pedal scale)."""
        t1, t2, t3, t4, t5, t6 = self.coefficients_[:6]
        vx, vy, r = x[..., 0], x[..., 1], x[..., 2]
        w = np.maximum(vx, self.min_speed)
        delta = u[..., 0] * self._steer_to_rad()
        push = self._longitudinal_regressors(x, u) @ self.coefficients_[6:]
        dvx = vy * r + push
        dvy = t1 * delta + (t2 * vy + t3 * r) / w - vx * r
        dr = t4 * delta + (t5 * vy + t6 * r) / w
        return np.stack([dvx, dvy, dr], axis=-1)

    def _jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(∂ẋ/∂x (K, 3, 3), ∂ẋ/∂u (K, 3, m)) at K points, physical units (u: features)."""
        t1, t2, t3, t4, t5, t6 = self.coefficients_[:6]
        drag = self.coefficients_[7]
        gains = self.coefficients_[8:].reshape(-1, 3)  # (m - 1, 3): g, p, b
        vx, vy, r = x[:, 0], x[:, 1], x[:, 2]
        fast = (vx > self.min_speed).astype(float)  # ∂w/∂vx
        w = np.maximum(vx, self.min_speed)
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
        steer = self._steer_to_rad()
        ju = np.zeros((len(vx), 3, u.shape[1]))
        ju[:, 0, 1:] = slope
        ju[:, 1, 0] = t1 * steer
        ju[:, 2, 0] = t4 * steer
        return jx, ju

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
                rates = self._derivative_point(*point, *u.tolist())
                point = [p + h * d for p, d in zip(point, rates, strict=True)]
            return (np.array(point) - state_min) / state_span
        return (self._euler(x, u) - state_min) / state_span

    def _derivative_point(
        self, vx: float, vy: float, r: float, steer_in: float, pedal: float
    ) -> tuple[float, float, float]:
        """:meth:`derivative` at one point of the sedan's two inputs, in plain floats (10x
        faster than numpy on 3-vectors)."""
        t1, t2, t3, t4, t5, t6, rolling, drag, gain, power, brake = self._floats
        w = max(vx, self.min_speed)
        delta = steer_in * self._steer_float
        throttle = max(pedal, 0.0)
        push = gain * throttle + power * throttle / w + brake * min(pedal, 0.0)
        dvx = vy * r + rolling + drag * vx * vx + push
        dvy = t1 * delta + (t2 * vy + t3 * r) / w - vx * r
        return dvx, dvy, t4 * delta + (t5 * vy + t6 * r) / w

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The derivative of :meth:`step` (every sub-step's Jacobian, chained) at K points."""
        state_span, state_min, input_span, input_min = self._coordinates()
        z, v = np.atleast_2d(z), np.atleast_2d(v)
        x, u = z * state_span + state_min, self._internal(v * input_span + input_min)
        h = self.dt_ / self.substeps_
        jac_x = np.broadcast_to(np.eye(3), (len(x), 3, 3)).copy()
        jac_u = np.zeros((len(x), 3, u.shape[1]))
        for _ in range(self.substeps_):
            jx, ju = self._jacobians(x, u)
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
            self._steer_float = self._steer_to_rad()
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


def _spans(normalizer: MinMaxNormalizer) -> tuple[np.ndarray, np.ndarray]:
    """Physical units per normalized unit: of the states, and of the input features."""
    state_span = normalizer.states_inverse(np.ones(3)) - normalizer.states_inverse(np.zeros(3))
    low, high = np.asarray(normalizer.input_min), np.asarray(normalizer.input_max)
    return state_span, np.where(high - low > 1e-12, high - low, 1.0)


def _geometry_of(form: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """a and b recovered from θ_1 .. θ_6: a = θ_4 / (k θ_1) with k = m / I_z = θ_5 / θ_3; b
    from C_f + C_r, a C_f − b C_r and a² C_f + b² C_r."""
    t1, t2, t3, t4, t5, t6 = (float(v) for v in form)
    mass_per_inertia = t5 / t3 if t3 else float("nan")
    total, moment = -t2, -t3
    with np.errstate(divide="ignore", invalid="ignore"):
        a = t4 / (mass_per_inertia * t1) if t1 else float("nan")
        denominator = a * total - moment
        b = a + (-t6 / mass_per_inertia - a * a * total) / denominator if denominator else a
    return a, b


def _signed_lstsq(
    regressors: np.ndarray, target: np.ndarray, bounds: Sequence[tuple[float, float] | None]
) -> tuple[np.ndarray, list[int]]:
    """Least squares with each coefficient in its bounds (None: held at 0), and the indices of
    those held at a bound. The plain solution where it keeps every sign (the same bits as an
    unbounded fit); else the bounded one. A regressor that is 0 throughout (a brake column
    never negative) has nothing to fit: its coefficient is 0."""
    used = np.any(regressors != 0, axis=0)
    free = [i for i, bound in enumerate(bounds) if bound is not None and used[i]]
    low = np.array([bounds[i][0] for i in free])  # type: ignore[index]
    high = np.array([bounds[i][1] for i in free])  # type: ignore[index]
    solution = np.zeros(len(bounds))
    columns = regressors if len(free) == len(bounds) else regressors[:, free]
    plain = _lstsq(columns, target)
    if np.all((plain >= low) & (plain <= high)):
        solution[free] = plain
        return solution, []
    bounded = lsq_linear(columns, target, bounds=(low, high), method="bvls").x
    solution[free] = bounded
    held = [free[k] for k in np.flatnonzero((bounded == low) | (bounded == high))]
    return solution, held


def _lstsq(regressors: np.ndarray, target: np.ndarray) -> np.ndarray:
    solution, *_ = np.linalg.lstsq(regressors, target, rcond=None)
    return np.asarray(solution, dtype=np.float64)
