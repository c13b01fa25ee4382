"""DE-MPC's settings (paper section V, Algorithm 2): Koopman MPC on a learned lifted-linear model.

:class:`DEMPCConfig` is what ``conf/controller/*.yaml`` builds, checked before any data or
training; called with the fitted model it builds :class:`~controllers.receding_horizon.DEMPC`,
whose step is composed of parts (the QP, what it tracks, the disturbance, the clock). Each step
the measured state x is lifted, z_t = lift(x) (the nonlinear part initializes, the linear part
predicts: eq. 17), the condensed QP of eq. (20) is solved for the increments, and
u_t = u_{t-1} + Δu_{t|t} is applied (eq. 21). Everything runs in the model's normalized units:

- outputs: y = C_ z is the normalized physical state, and the reference is normalized with the
  same min-max map. The paper tracks the whole lifted reference φ(x_ref) with Q on all N
  coordinates; tracking the three physical states only keeps Q's meaning independent of the
  learner's lifting (its extra observables are free to be whatever predicts best);
- Q (n×n) weighs normalized state errors, R (m×m) normalized input increments, as the paper's
  Q = 1000·I, R = 5·I on its normalized data;
- inputs: v = min-max((steer_wheel_deg, signed pedal scale)), see ``MinMaxNormalizer``. The
  limits map exactly (both maps are monotone): steering ±450° and pedal [-9.1 MPa, 0.2] become
  box bounds on v. The increments ±2.25°, ±0.004 throttle and ±0.18 MPa per step become
  2.25°/span and min(0.004/0.2, 0.18/9.1) = 0.0198 of the signed pedal scale per step (one
  limit for one pedal: the tighter of the two, brake 0.18 MPa, throttle 0.00396);
- the slack ε is relative to each limit: |Δv| <= Δv_max·(1 + ε) (see ``condensed_qp``);
- ``compute_delay: one_step``: each input reaches the plant one period after its measurement,
  and the controller plans from its model's prediction of the state then
  (``controllers/clock.py``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from controllers.condensed_qp import QP_SOLVERS
from controllers.disturbance import DisturbanceEstimator
from controllers.path_following import ERRORS
from controllers.receding_horizon import DEMPC
from controllers.time_varying import LINEARIZATIONS
from harness.core.budget import check_memory
from harness.core.checks import (
    boolean,
    choice,
    finite,
    integer,
    is_number,
    positive,
    require,
)
from harness.core.contracts import COMPUTE_DELAYS, Model
from harness.core.episode import SEDAN_INPUTS, MinMaxNormalizer, is_sedan
from harness.core.limits import BRAKE_MAX_MPA, STEER_WHEEL_LIMIT_DEG, THROTTLE_MAX

__all__ = ["DEMPC", "MAX_HORIZON_S", "DEMPCConfig"]

STATES, INPUTS = 3, 2
# What the cost follows: the reference's states (the paper's), or a run's path when it has one
# (lateral and heading error, controllers/path_following.py; state tracking where it has none).
REFERENCES = ("states", "path")
# The longest prediction horizon, Np·dt (s): 1000 steps at 10 ms, 17 times the paper's longest
# (60 steps) and the span of the pipeline's prediction windows (task.prediction_window_s). Θ holds
# C·Aᵏ·B for k <= Np, so a learned model's mode outside the unit circle (spectrum.unstable_modes;
# bilinear EDMD's fastest on data=default doubles in 2.5 s, docs/findings/input_models.md) grows as
# 2^(Np·dt / 2.5 s) in Θ and squared in the Hessian ΘᵀQΘ: 16-fold over 10 s, 2^400 over
# Np = 100000 (1000 s), where the Hessian overflows float64 (2^1024) after the whole run's
# training. Every tracking step also keeps and records its predicted horizon: (T, Np, 3) floats.
MAX_HORIZON_S = 10.0


@dataclass(frozen=True)
class DEMPCConfig:
    """DE-MPC's settings (``conf/controller/de_mpc.yaml``), checked when built: no model needed.

    The YAML's ``_target_`` is this class, so a wrong value (``controller.Nc=60`` with Np = 10,
    ``controller.Q=-5``) fails while Hydra builds the task, before any data is collected or any
    model trained. Calling it with the fitted model builds the controller:
    ``instantiate(cfg.controller)(model)``. Limits are physical: steering-wheel angle in degrees,
    pedal >= 0 throttle, pedal < 0 brake in -MPa; increments are per control step.
    """

    Np: int = 10  # prediction horizon, steps of dt; Np·dt <= MAX_HORIZON_S
    Nc: int = 7  # control horizon; increments are zero from Nc to Np
    # Normalized state-error weight (vx, vy, r): scalar, n diagonal entries or n x n (OmegaConf
    # has no float | list). vy at 1 % (ours; the paper's is 1000·I): a reference's vy is the
    # steady-state sideslip, opposite to r at speed, but within a 0.1 s horizon steering moves vy
    # with r, so at 1000·I the QP trades the two errors and barely steers
    # (docs/findings/lane_change.md, "The physics baseline").
    Q: Any = (1000.0, 10.0, 1000.0)
    R: Any = 5.0  # normalized input-increment weight: scalar, m diagonal entries or m x m
    rho: float = 10.0  # slack weight; the slack is relative to each increment limit
    steer_wheel_min_deg: float = -STEER_WHEEL_LIMIT_DEG
    steer_wheel_max_deg: float = STEER_WHEEL_LIMIT_DEG
    pedal_min: float = -BRAKE_MAX_MPA  # pedal < 0 is brake pressure in -MPa
    pedal_max: float = THROTTLE_MAX  # pedal >= 0 is throttle
    steer_wheel_increment_deg: float = 2.25  # per step
    throttle_increment: float = 0.004  # per step
    brake_increment_mpa: float = 0.18  # per step
    dt: float = 0.01  # control period = the model's sampling period = the plant's (s)
    tol: float = 1e-6  # feasibility and optimality tolerance of every solve
    max_iter: int = 100  # PIQP iterations: the time limit of one solve
    active_set: bool = True  # hot-start from the last step's active set before PIQP
    # The active-set solver tried before PIQP: DAQP (the bounded worst case:
    # docs/findings/real_time.md, "DAQP") or ours (controllers/condensed_qp.py).
    qp_solver: str = "daqp"
    sqp_iterations: int = 1  # time-varying models (bilinear, nonlinear): linearisations a step
    # Time-varying models (LINEARIZATIONS): frozen at the current point and held over the
    # horizon (Θ from one step response: at 60/50 bilinear EDMD's step 2.4-2.9x faster and
    # inside the period, the same lane changes passed, 3 seeds: findings/real_time.md); predicted
    # (acados's RTI shift: at the states the last step's QP predicted, lifted, no simulation);
    # plan (along the previous plan, rolled out: Np model steps in sequence).
    linearization: str = "frozen"
    # What the cost follows: the reference's states (the paper's), or ``path``: on a course, the
    # lateral and heading error to its centre line and the yaw rate its curvature asks for where
    # the car is (controllers/path_following.py); runs without a course track states either way.
    reference: str = "states"
    # reference=path: diagonal weights on (vx, vy, yaw rate) errors, normalized as Q's, then on
    # the lateral error (per m²) and heading error (per rad²) to the path.
    Q_path: Any = (1000.0, 0.0, 300.0, 30.0, 300.0)
    # A disturbance w in the model's step, z⁺ = f(z, v) + w, estimated from each step's one-step
    # prediction error (controllers/disturbance.py): null, none (the paper's); a _target_ block
    # such as {_target_: controllers.disturbance.OffsetFree, gain: 1.0} (offset-free tracking:
    # w += gain · (z − ẑ)) or controllers.disturbance.KalmanDisturbance.
    disturbance: Any = None
    # One side of the pedal at a time (controllers/pedal_sides.py; ours): the plan keeps to
    # the throttle (and coasting) or to the brake (and releasing) until its best on that side
    # still misses the reference's speed within the horizon by more than this (m/s); null:
    # the pedal crosses between them freely (the paper's).
    pedal_side_margin_mps: float | None = None
    # The clock in the loop (COMPUTE_DELAYS): none, or one_step, each input applied one control
    # period after its measurement and the state predicted that far before planning.
    compute_delay: str = "none"
    # The real-time iteration (acados's RTI): prepare() builds the next step's linearisation,
    # prediction matrices, Hessian and factor before its measurement, along the state the model
    # predicts; act() is then the feedback phase (tracking.solve_time_ms). False: act() does it
    # all from the measurement.
    real_time_iteration: bool = True
    # Linearised models with the real-time iteration: prepare() also solves the step's new QP
    # at the state it predicts (and throws the answer away), so that the feedback's active-set
    # solver starts from the working set the measurement most likely needs: the same answer,
    # fewer iterations after the measurement (at 60/50 the feedback's p99: input EDMD 3.0 ->
    # 0.8 ms, the DNN 2.4 -> 1.0 ms; docs/findings/real_time.md). A lifted-linear model's QP never
    # changes, so its last working set is warm already: no presolve (it doubled its step).
    presolve: bool = True
    # Linearised models: where the plan brakes while the car is nearly stopped (< 1 m/s) and the
    # reference asks for more speed than it has, linearise at the pedal released (zero) (ours).
    # At a stop under brake a model rightly says the pedal does nothing (braking cannot push a
    # stopped car backwards), so a QP linearised there never leaves the brake: the main job's
    # controller waited at every stop of a paper-scale test drive (docs/findings/smooth_driving.md,
    # "The standstill trap").
    release_brake: bool = True
    # Linearised models: each input's column of B_k as a secant over this fraction of its range
    # (normalized units), centred on the point and kept inside the input limits; one number for
    # every input or one per input (steering wheel, pedal); 0 takes the model's tangent. Ours:
    # the pedal's over 0.4 of its range (±0.08 throttle or ±3.6 MPa about the point), the wheel's
    # tangent. A learned step's tangent in the pedal can be flat near the throttle-brake kink,
    # and a QP linearised there held the pedal while its reference braked: at paper scale the
    # main controller's test drive went from 0.12-1.83 to 0.063-0.088 m/s vx RMSE over input
    # EDMD and the DNN, 2 seeds each, the baseline's unchanged (docs/findings/smooth_driving.md,
    # "The pedal's flat tangent"). OmegaConf has no float | list.
    input_secant_span: Any = (0.0, 0.4)

    def __post_init__(self) -> None:
        key = "controller."
        Np, Nc = integer(key + "Np", self.Np), integer(key + "Nc", self.Nc)
        require(Nc <= Np, key + "Nc", f"<= controller.Np ({Np})", Nc)
        require(
            self.sqp_iterations in (1, 2, 3),
            key + "sqp_iterations",
            "1, 2 or 3",
            self.sqp_iterations,
        )
        integer(key + "max_iter", self.max_iter)
        if isinstance(self.disturbance, Mapping) and "_target_" in self.disturbance:
            # The block as a schema check reads it (not yet built): build it, checking it.
            from hydra.utils import instantiate

            object.__setattr__(self, "disturbance", instantiate(self.disturbance))
        if self.disturbance is not None and not isinstance(self.disturbance, DisturbanceEstimator):
            raise ValueError(
                "controller.disturbance must be null or an estimator block with a _target_ "
                "(controllers/disturbance.py: OffsetFree, KalmanDisturbance), got "
                f"{self.disturbance!r:.80}"
            )
        for flag in (
            "active_set",
            "real_time_iteration",
            "presolve",
            "release_brake",
        ):
            boolean(key + flag, getattr(self, flag))
        choice(key + "compute_delay", self.compute_delay, COMPUTE_DELAYS)
        choice(key + "linearization", self.linearization, LINEARIZATIONS)
        choice(key + "qp_solver", self.qp_solver, QP_SOLVERS)
        choice(key + "reference", self.reference, REFERENCES)
        if self.pedal_side_margin_mps is not None:
            positive(key + "pedal_side_margin_mps", self.pedal_side_margin_mps)
        self.secant_spans()
        for name in (
            "rho",
            "steer_wheel_increment_deg",
            "throttle_increment",
            "brake_increment_mpa",
            "dt",
            "tol",
        ):
            positive(key + name, getattr(self, name))
        for name in ("steer_wheel_min_deg", "steer_wheel_max_deg", "pedal_min", "pedal_max"):
            finite(key + name, getattr(self, name))
        _check_qp_size(Np, Nc)
        self.weights()
        self.path_weights()
        _check_range("steer_wheel", self.steer_wheel_min_deg, self.steer_wheel_max_deg, "_deg")
        _check_range("pedal", self.pedal_min, self.pedal_max, "")
        _check_horizon_span(Np, float(self.dt))

    def weights(self) -> tuple[np.ndarray, np.ndarray]:
        """(Q (n, n), R (m, m)) as matrices, each checked symmetric positive definite."""
        return _weight("Q", self.Q, STATES), _weight("R", self.R, INPUTS)

    def increment_limits(self, normalizer: MinMaxNormalizer) -> np.ndarray:
        """(m,) each input's increment limit per step in the model's normalized units; the
        pedal's is the tighter of the throttle's and the brake's on the signed scale (they
        differ by 1 %). With the sedan's pedal in other units (``data.pedal_gains``) they differ
        more (in acceleration units at 80 km/h the brake's is 11x the throttle's): the looser,
        so that braking is not slowed below its own limit."""
        to_v = normalizer.inputs
        origin = to_v(np.zeros(INPUTS))
        steering = to_v(np.array([self.steer_wheel_increment_deg, 0.0]))[0] - origin[0]
        channels = normalizer.channels
        if is_sedan(channels) and channels[1] != SEDAN_INPUTS[1]:
            throttle = to_v(np.array([0.0, self.throttle_increment]))[1] - origin[1]
            brake = origin[1] - to_v(np.array([0.0, -self.brake_increment_mpa]))[1]
            return np.array([steering, max(throttle, brake)])
        pedal_step = min(
            self.throttle_increment / THROTTLE_MAX, self.brake_increment_mpa / BRAKE_MAX_MPA
        )
        return np.array([steering, to_v(np.array([0.0, pedal_step * THROTTLE_MAX]))[1] - origin[1]])

    def qp_settings(self, normalizer: MinMaxNormalizer) -> dict[str, Any]:
        """The states QP's keywords (CondensedQP's) in the model's normalized units."""
        Q, R = self.weights()
        low, high = self.input_bounds(normalizer)
        return {
            "Np": int(self.Np),
            "Nc": int(self.Nc),
            "Q": Q,
            "R": R,
            "v_min": low,
            "v_max": high,
            "dv_max": self.increment_limits(normalizer),
            **self.solver_settings(),
        }

    def input_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high): the inputs' bounds, physical (steering-wheel degrees, signed pedal)."""
        return (
            np.array([self.steer_wheel_min_deg, self.pedal_min]),
            np.array([self.steer_wheel_max_deg, self.pedal_max]),
        )

    def input_bounds(self, normalizer: MinMaxNormalizer) -> tuple[np.ndarray, np.ndarray]:
        """(low, high): the inputs' bounds, normalized."""
        low, high = self.input_limits()
        return normalizer.inputs(low), normalizer.inputs(high)

    def solver_settings(self) -> dict[str, Any]:
        """What every QP of the controller is solved with (CondensedQP's keywords)."""
        return {
            "rho": self.rho,
            "tol": self.tol,
            "max_iter": self.max_iter,
            "active_set": self.active_set,
            "qp_solver": self.qp_solver,
        }

    def secant_spans(self) -> np.ndarray:
        """input_secant_span as one span per input, each a fraction of its range in [0, 1]."""
        value = self.input_secant_span
        values = [value] * INPUTS if is_number(value) else value
        numbers = isinstance(values, Sequence) and not isinstance(values, str | bytes)
        numbers = numbers and len(values) == INPUTS and all(is_number(s) for s in values)
        spans = np.array(values if numbers else [np.nan] * INPUTS, dtype=float)
        if not (np.all(np.isfinite(spans)) and np.all((spans >= 0) & (spans <= 1))):
            raise ValueError(
                "controller.input_secant_span must be a fraction of each input's range in "
                "[0, 1]: one number, or one per input [steering wheel, pedal] (got "
                f"{self.input_secant_span!r})"
            )
        return spans

    def without_path(self) -> DEMPCConfig:
        """These settings as they drive a reference with no path: a path follower tracks its
        states there, bit for bit as the same settings with ``reference: states`` would (the
        pipeline runs such twins once)."""
        default_q_path = next(f.default for f in fields(DEMPCConfig) if f.name == "Q_path")
        return replace(self, reference="states", Q_path=default_q_path)

    def path_weights(self) -> np.ndarray:
        """Q_path as a (5, 5) diagonal: non-negative, and the path's errors weighed at all."""
        try:
            diagonal = np.asarray(self.Q_path, dtype=float)
        except (TypeError, ValueError):
            diagonal = np.full(0, np.nan)
        if (
            diagonal.shape != (STATES + ERRORS,)
            or not np.all(np.isfinite(diagonal))
            or np.any(diagonal < 0)
            or not np.any(diagonal[STATES:] > 0)
        ):
            raise ValueError(
                "controller.Q_path must be 5 weights >= 0 on (vx, vy, yaw rate, lateral error, "
                f"heading error), the last two not both 0 (got {self.Q_path!r})"
            )
        return np.diag(diagonal)

    def __call__(self, model: Model, control_period_s: float | None = None) -> DEMPC:
        """DE-MPC on ``model``; ``control_period_s`` (the plant's, when known) must equal dt.

        The model predicts one step per dt and the reference is indexed by t / dt: on a plant
        stepping at another period both would silently be wrong.
        """
        if control_period_s is not None and not np.isclose(self.dt, control_period_s):
            raise ValueError(
                f"controller.dt ({self.dt}) must equal plant.control_period_s "
                f"({control_period_s}): the model steps once per control period"
            )
        return DEMPC(model, self)


def _check_horizon_span(Np: int, dt: float) -> None:
    """Refuse a horizon longer than ``MAX_HORIZON_S``: its prediction matrices lose all
    precision, then overflow, on a learned model's unstable modes (see ``MAX_HORIZON_S``)."""
    if Np * dt > MAX_HORIZON_S * (1 + 1e-9):
        raise ValueError(
            f"controller.Np ({Np}) spans {Np * dt:g} s at controller.dt = {dt:g} s; at most "
            f"{MAX_HORIZON_S:g} s ({math.floor(MAX_HORIZON_S / dt + 1e-9)} steps): over a longer "
            "horizon a learned model's unstable modes overflow the QP's prediction matrices"
        )


def _check_qp_size(Np: int, Nc: int) -> None:
    """Refuse horizons whose condensed QP cannot fit in memory (``Np = Nc = 100000``: TiB).

    Counted, in float64 and without the lifted dimension (unknown before training, so this is
    a lower bound): Θ (Np·n × Nc·m), the Hessian P and the dual operator K = G P⁻¹ Gᵀ over the
    4·Nc·m + 1 constraint rows, and G itself (``controllers/condensed_qp.py``).
    """
    variables = Nc * INPUTS + 1
    rows = 4 * Nc * INPUTS + 1
    doubles = Np * STATES * Nc * INPUTS + variables**2 + rows**2 + rows * variables
    what = f"the condensed QP of Np = {Np}, Nc = {Nc}"
    check_memory("controller.Np and controller.Nc", what, 8 * doubles)


def _weight(key: str, value: Any, size: int) -> np.ndarray:
    """A scalar (times I), a diagonal or a full symmetric positive-definite matrix."""
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        array = np.full((0,), np.nan)  # not numbers, or ragged: refused by shape below
    if array.ndim == 0:
        array = array * np.eye(size)
    elif array.ndim == 1 and array.shape == (size,):
        array = np.diag(array)
    if array.shape != (size, size):
        raise ValueError(
            f"controller.{key} must be a scalar, {size} diagonal entries or a {size}x{size} "
            f"matrix (got {value!r})"
        )
    if not np.allclose(array, array.T) or not np.all(np.isfinite(array)):
        raise ValueError(f"controller.{key} must be symmetric and finite")
    smallest = float(np.linalg.eigvalsh(array).min())
    if smallest <= 0:
        raise ValueError(
            f"controller.{key} must be positive definite (smallest eigenvalue {smallest:g})"
        )
    return array


def _check_range(name: str, low: float, high: float, unit: str) -> None:
    low_key, high_key = f"controller.{name}_min{unit}", f"controller.{name}_max{unit}"
    if not low < high:
        raise ValueError(f"{low_key} ({low}) must be < {high_key} ({high})")
    index = 0 if name == "steer_wheel" else 1
    plant_low = (-STEER_WHEEL_LIMIT_DEG, -BRAKE_MAX_MPA)[index]
    plant_high = (STEER_WHEEL_LIMIT_DEG, THROTTLE_MAX)[index]
    if low < plant_low or high > plant_high:
        raise ValueError(
            f"{low_key}..{high_key} ({low}..{high}) must lie within the plant's range "
            f"[{plant_low}, {plant_high}]"
        )
