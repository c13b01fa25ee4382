"""DE-MPC (paper section V, Algorithm 2): Koopman MPC on a learned lifted-linear model.

Each step the measured state x is lifted, z_t = lift(x) (the nonlinear part initializes, the
linear part predicts: eq. 17), the condensed QP of eq. (20) is solved for the increments, and
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
- ``compute_delay: one_step``: the input computed from the measurement at t_k reaches the plant
  at t_{k+1} (the loop holds it, ``harness.plant.rollout.closed_loop``), while over [t_k, t_{k+1})
  the plant still gets the input returned last step. The controller predicts z_{k+1} =
  f(lift(x_k), v_{k-1}) (+ w, offset-free) with its own model and plans from there, against
  the reference from k + 1 on: standard delay compensation, exact for an exact model.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any, cast

import numpy as np

from controllers.blas import single_threaded
from controllers.condensed_qp import QP_SOLVERS, CondensedQP, QPSolution, TimeVaryingQP
from controllers.disturbance import DisturbanceEstimator
from controllers.linearization import (
    BilinearLinearization,
    SecantInputs,
    check_lifted_model,
    check_linearizable,
    linearization_of,
)
from controllers.path_following import ERRORS, OUTPUTS, FrenetOutputs
from controllers.pedal_sides import PEDAL, PedalSides
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
from harness.core.contracts import (
    COMPUTE_DELAYS,
    LiftedModel,
    LinearizableModel,
    Model,
    StepInfo,
)
from harness.core.episode import MinMaxNormalizer
from harness.core.limits import BRAKE_MAX_MPA, STEER_WHEEL_LIMIT_DEG, THROTTLE_MAX
from harness.core.reference_path import ReferencePath

log = logging.getLogger(__name__)
# QPSolution.status of a step whose model gave a non-finite linearisation (no QP was solved).
MODEL_NOT_FINITE = "model_not_finite"

STATES, INPUTS = 3, 2
# The brake's release (DEMPCConfig.release_brake): below what speed a plan that brakes may be
# released (a brake acts at speed, and a linearisation there is right: only near a stop does its
# effect vanish), and how far the reference's speed must lie above the car's (m/s).
RELEASE_BELOW_MPS = 1.0
RELEASE_MARGIN_MPS = 0.1
# Where a time-varying model is linearised: at every point of the previous plan (exact along
# the horizon), or at the current state and next input only, held over the horizon (frozen:
# Θ from one step response: far cheaper for a large lift at 60/50, see docs/findings/real_time.md).
LINEARIZATIONS = ("plan", "frozen", "predicted")
# What the cost follows: the reference's states (the paper's), or a run's path when it has one
# (lateral and heading error, controllers/path_following.py; state tracking where it has none).
REFERENCES = ("states", "path")
# Path following: the speed in the error kinematics, to this band (m/s): 1 % at 80 km/h.
SPEED_BAND_MPS = 0.25
# A band is kept until the speed is this many bands from it (the nearest band's half, 0.5, plus
# hysteresis): v̄ is within 0.19 m/s of the speed, 0.8 % at 80 km/h.
BAND_HOLD = 0.75
# Path QPs a lifted-linear DE-MPC keeps, one per speed band (about 0.7 MB each at 60/50).
BAND_QPS = 8
# The longest prediction horizon, Np·dt (s): 1000 steps at 10 ms, 17 times the paper's longest
# (60 steps) and the span of the pipeline's prediction windows (task.prediction_window_s). Θ holds
# C·Aᵏ·B for k <= Np, so a learned model's mode outside the unit circle (spectrum.unstable_modes;
# bilinear EDMD's fastest on data=default doubles in 2.5 s, docs/findings/input_models.md) grows as
# 2^(Np·dt / 2.5 s) in Θ and squared in the Hessian ΘᵀQΘ: 16-fold over 10 s, 2^400 over
# Np = 100000 (1000 s), where the Hessian overflows float64 (2^1024) after the whole run's
# training. Every tracking step also keeps and records its predicted horizon: (T, Np, 3) floats.
MAX_HORIZON_S = 10.0
# Where the car stands for the path QP: lateral error (m), heading error (rad), the banded speed
# v̄ (m/s) and the curvature at the Np steps ahead (1/m).
_Where = tuple[float, float, float, np.ndarray]


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
        pedal's is the tighter of the throttle's and the brake's on the signed scale."""
        to_v = normalizer.inputs
        origin = to_v(np.zeros(INPUTS))
        pedal_step = min(
            self.throttle_increment / THROTTLE_MAX, self.brake_increment_mpa / BRAKE_MAX_MPA
        )
        return np.array(
            [
                to_v(np.array([self.steer_wheel_increment_deg, 0.0]))[0] - origin[0],
                to_v(np.array([0.0, pedal_step * THROTTLE_MAX]))[1] - origin[1],
            ]
        )

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


class DEMPC:
    """Koopman MPC with PIQP; ``reset(reference)`` then ``act(x, t)`` every control period.

    Settings are a :class:`DEMPCConfig` (checked there); the fitted model is given at run time.
    What the model is decides the QP: a lifted-linear model's prediction matrices are built once
    (:class:`CondensedQP`); a bilinear model (:class:`~harness.core.contracts.BilinearModel`) or
    any :class:`~harness.core.contracts.LinearizableModel` is linearised each step along the
    previous plan, shifted by one step and rolled out from the measured state, and solved as a
    :class:`TimeVaryingQP` (``sqp_iterations`` times, re-linearising along the new plan).
    """

    def __init__(self, model: Model, config: DEMPCConfig | None = None) -> None:
        config = DEMPCConfig() if config is None else config
        self.config = config
        self.model = model
        self.Np, self.Nc, self.dt = int(config.Np), int(config.Nc), float(config.dt)
        self.sqp_iterations = int(config.sqp_iterations)
        Q, R = config.weights()
        self.linearization = linearization_of(model)
        if self.linearization is None:
            A, B, C = check_lifted_model(cast(LiftedModel, model))
        else:
            C = check_linearizable(self.linearization)
        self.normalizer: MinMaxNormalizer = model.normalizer_
        to_v = self.normalizer.inputs
        self.u_min = np.array([config.steer_wheel_min_deg, config.pedal_min])
        self.u_max = np.array([config.steer_wheel_max_deg, config.pedal_max])
        origin = to_v(np.zeros(INPUTS))
        dv_max = config.increment_limits(self.normalizer)
        settings: dict[str, Any] = {
            "Np": self.Np,
            "Nc": self.Nc,
            "Q": Q,
            "R": R,
            "v_min": to_v(self.u_min),
            "v_max": to_v(self.u_max),
            "dv_max": dv_max,
            **config.solver_settings(),
        }
        self.qp: CondensedQP
        if self.linearization is None:
            self.qp = CondensedQP(A, B, C, **settings)
            self._linear_step = (A, B)
        else:
            self.qp = TimeVaryingQP(C, INPUTS, **settings)
            spans = config.secant_spans()
            # A bilinear step is linear in v at a fixed state: its secant is its tangent.
            if np.any(spans > 0) and not isinstance(self.linearization, BilinearLinearization):
                self.linearization = SecantInputs(
                    self.linearization, spans, settings["v_min"], settings["v_max"]
                )
        self.C = C
        self._dv_max = dv_max  # normalized: the pedal's is a share of each side's range
        self._pedal_zero = float(origin[PEDAL])  # the released pedal, normalized
        vx_min = float(self.normalizer.state_min[0])
        vx_span = max(float(self.normalizer.state_max[0]) - vx_min, 1e-9)
        self._release_below = (RELEASE_BELOW_MPS - vx_min) / vx_span
        self._release_margin = RELEASE_MARGIN_MPS / vx_span
        # Its own estimator: the config's is a template, shared by every run it builds.
        self.disturbance: DisturbanceEstimator | None = copy.deepcopy(config.disturbance)
        self._input_bounds = (settings["v_min"], settings["v_max"])
        margin = config.pedal_side_margin_mps
        self.pedal_sides = None if margin is None else PedalSides(margin, self._pedal_zero, vx_span)
        self._step_bounds: tuple[np.ndarray, np.ndarray] | None = None
        self.delay_steps = COMPUTE_DELAYS[config.compute_delay]
        self.frenet: FrenetOutputs | None = None
        self.path_qp: TimeVaryingQP | None = None
        if config.reference == "path":
            # Its prediction is built from the states QP's every step (set_prediction_matrix,
            # set_free_response): it has outputs, no model of its own (no lifted state: N = 0).
            self.frenet = FrenetOutputs(self.normalizer, self.dt)
            settings["Q"] = config.path_weights()
            self.path_qp = TimeVaryingQP(np.zeros((OUTPUTS, 0)), INPUTS, **settings)
        self._path_settings = settings
        # The path's yaw-rate reference, normalized as the model's states, and the steps ahead.
        self._yaw_rate_scale = (
            float(self.normalizer.state_min[2]),
            float(self.normalizer.state_span[2]),
        )
        self._steps_ahead = np.arange(self.Np + 1, dtype=float)
        # A lifted-linear model's path QPs, one per speed band met (see _path_theta), the most
        # recently used last.
        self._band_qps: OrderedDict[float, TimeVaryingQP] = OrderedDict()
        self._path: ReferencePath | None = None
        self._path_band: float | None = None  # the v̄ whose Θ a lifted-linear path QP holds
        self._path_hint: int | None = None
        self._reference: np.ndarray | None = None
        self._reference_steps = 0
        self._start(None)

    def reset(
        self,
        reference: np.ndarray,
        *,
        path: ReferencePath | None = None,
        u_prev: np.ndarray | None = None,
    ) -> None:
        """Start a run tracking ``reference`` ((T, 3) physical states at ``dt``) from u_prev.

        The paper starts from u = 0 (wheel straight, no pedal). With ``reference: path`` and a
        ``path``, the run follows the path (and the reference's speed); without one it tracks
        the states.
        """
        reference = np.asarray(reference, dtype=float)
        if reference.ndim != 2 or reference.shape[1] != STATES or len(reference) < 2:
            raise ValueError(f"reference must be (T >= 2, 3) states, got {reference.shape}")
        normalized = self.normalizer.states(reference)
        # Beyond its end the reference holds its last sample.
        tail = np.repeat(normalized[-1:], self.Np + 1, axis=0)
        self._reference = np.ascontiguousarray(np.vstack([normalized, tail]))
        self._reference_steps = len(reference)
        self._path = path if self.path_qp is not None else None
        self._path_hint = None
        if self.path_qp is not None and path is None:
            log.debug("controller.reference=path: this run has no path, tracking its states")
        self._start(u_prev)

    def _start(self, u_prev: np.ndarray | None) -> None:
        """No plan, the hot start forgotten, the last input u_prev (default 0)."""
        u = np.zeros(INPUTS) if u_prev is None else np.asarray(u_prev, dtype=float)
        self._v_prev = self.normalizer.inputs(np.clip(u, self.u_min, self.u_max))
        self._plan: np.ndarray | None = None
        self._plan_step = 0
        if self.disturbance is not None:
            self.disturbance.start(self.C.shape[1])
        if self.pedal_sides is not None:
            self.pedal_sides.reset(self._v_prev)
        self._z_expected: np.ndarray | None = None
        self._prepared: _Prepared | None = None
        self._last: _Last | None = None
        self._predicted_rows: np.ndarray | None = None  # the last plan's states, normalized
        self._band_held: float | None = None  # the path kinematics' v̄ (see _speed_band)
        self.qp.reset()
        if self.path_qp is not None:
            self.path_qp.reset()
        for band_qp in self._band_qps.values():
            band_qp.reset()

    def increment_shares(self, inputs: np.ndarray) -> np.ndarray:
        """(T - 1, m) each step's change of each physical input in ``inputs`` (T, m), as a share
        of its bound (the QP's, normalized: the pedal's on the throttle's or the brake's side
        as it moved there); above 1 where the slack let it past."""
        v = self.normalizer.inputs(np.asarray(inputs, dtype=float))
        return np.abs(np.diff(v, axis=0)) / self._dv_max

    def _qps(self) -> list[CondensedQP]:
        """Every QP this controller may solve in a step: states, path, each speed band's."""
        path = [self.path_qp] if self.path_qp is not None else []
        return [self.qp, *path, *self._band_qps.values()]

    @property
    def follows_path(self) -> bool:
        """Whether this run follows a path (``reference: path`` and a path at reset)."""
        return self._path is not None

    def act(
        self, x: np.ndarray, t: float, *, pose: np.ndarray | None = None
    ) -> tuple[np.ndarray, StepInfo]:
        """Input (steer_wheel_deg, pedal) for measured state ``x`` at time ``t`` (s), and the
        horizon it plans: the model's predicted states under the plan, the plan itself.
        ``pose`` (X, Y, yaw): needed when the run follows a path.

        With ``compute_delay: one_step`` the input is the one to apply from t + dt: the plan
        starts from the model's prediction of the state then, under the input returned last
        step (which the plant gets meanwhile), and the pose moved on by that step's kinematics;
        the predicted states still start one step after the measurement."""
        if self._reference is None:
            raise ValueError("DEMPC.reset(reference) must be called before act()")
        x = np.asarray(x, dtype=float)
        k = min(round(t / self.dt) + self.delay_steps, self._reference_steps - 1)
        z = np.asarray(self.model.lift(x), dtype=float)
        y_ref = self._reference[k + 1 : k + 1 + self.Np].ravel()
        v_prev = self._v_prev
        w = self._estimate_disturbance(z)
        if self.delay_steps:  # from here on z, x and pose are those at t + dt, predicted
            z = self._model_step(z, v_prev)
            if w is not None:
                z = z + w
            if pose is not None:
                pose = _pose_ahead(np.asarray(pose, dtype=float), x, self.dt)
            x = self.normalizer.states_inverse(self.C @ z)
        qp: CondensedQP = self.qp
        where: _Where | None = None
        if self._path is not None and self.path_qp is not None:
            if pose is None:
                raise ValueError("a DE-MPC run that follows a path needs the car's pose in act()")
            qp = self.path_qp
            y_ref, where = self._path_reference(x, pose, y_ref)
        if self.pedal_sides is not None:
            self._step_bounds = self.pedal_sides.bounds(*self._input_bounds, v_prev)
            for each in self._qps():
                each.set_input_bounds(*self._step_bounds)
        # Small products: one BLAS thread is fastest, for every model (blas.py; the main job's
        # lifted-linear path follower at 60/50: p99 7.8-7.9 ms on two threads, 1.9-4.8 on one).
        with single_threaded():
            solution, shift = self._solve(z, v_prev, y_ref, w, where)
        if where is not None and self.path_qp is not None:
            qp = self.path_qp  # a lifted-linear model's may be another band's now
        self._prepared = None
        if solution.ok:  # the first move only: the plan's rest waits until the input is out
            first = v_prev + solution.dv[0]
        else:
            plan, dv = self._fallback(v_prev)
            first = plan[0]
        u = np.clip(self.normalizer.inputs_inverse(first), self.u_min, self.u_max)
        # The input is ready: the rest is bookkeeping for the next step and the record, work of
        # the period after the input is sent (the harness times the feedback phase to here).
        ready = time.perf_counter()
        if solution.ok:
            self._plan = v_prev + np.cumsum(solution.dv, axis=0)
            self._plan_step = 1
            plan, dv = self._plan, solution.dv
        else:
            log.warning(
                "DE-MPC solve failed at t = %.2f s (%s); applying the previous plan's next move",
                t,
                solution.status,
            )
        self._v_prev = plan[0]
        if w is not None:
            # The next measurement's prediction: under delay, the state the plan started from.
            self._z_expected = z if self.delay_steps else self._model_step(z, plan[0]) + w
        self._last = _Last(z, plan[0], w, x, pose, t)
        planned_inputs = self.normalizer.inputs_inverse(plan)  # elementwise: row 0 is u's bits
        if qp.has_model():
            predicted = qp.predict(z, v_prev, dv)[:, :STATES]
            predicted = predicted + shift.reshape(self.Np, -1)[:, :STATES]
        else:  # the run's first preparation failed: no model to predict with yet (NaN rows)
            predicted = np.full((self.Np, STATES), np.nan)
        self._predicted_rows = predicted if solution.ok else None
        if self.pedal_sides is not None and solution.ok:
            self.pedal_sides.update(predicted[:, 0], self._reference[k + 1 : k + 1 + self.Np, 0])
        if self.delay_steps:  # row i is i + 1 steps after the measurement, with or without delay
            predicted = np.vstack([(self.C @ z)[None], predicted[:-1]])
        info = StepInfo(
            predicted_states=self.normalizer.states_inverse(predicted),
            planned_inputs=planned_inputs,
            solve_path=solution.path,
            fallback=not solution.ok,
            follows_path=self.follows_path,
            input_ready_s=ready,
        )
        return u, info

    def _solve(
        self,
        z: np.ndarray,
        v_prev: np.ndarray,
        y_ref: np.ndarray,
        w: np.ndarray | None,
        where: _Where | None,
    ) -> tuple[QPSolution, np.ndarray]:
        """The step's QP from z (the prepared one, or prepared here in one phase), and the
        shift of the predicted outputs by w that a lifted-linear states QP leaves out."""
        shift = np.zeros_like(y_ref)
        if self.linearization is None and where is not None:
            return self._solve_path_linear(z, v_prev, y_ref, w, where), shift
        if self.linearization is None:
            if w is not None:  # Y = Φz z + Φv v + Φw w + Θ ΔV: shifting Y_ref by Φw w is exact
                shift = self.qp.phi_w @ w
            return self.qp.solve(z, v_prev, y_ref - shift), shift
        if self._prepared is None:  # one phase: prepared along the measurement
            self._prepared = self._prepare_at(z, v_prev, y_ref, w, where)
        return self._feedback(self._prepared, z, v_prev, y_ref, w, where), shift

    def _estimate_disturbance(self, z: np.ndarray) -> np.ndarray | None:
        """The estimator's w after the last step's one-step prediction error z − ẑ (ẑ with w),
        so a constant model error is learned and predicted away; None without an estimator."""
        if self.disturbance is None:
            return None
        error = None if self._z_expected is None else z - self._z_expected
        return self.disturbance.update(error)

    def _model_step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The model's own next lifted state (no disturbance)."""
        if self.linearization is None:
            A, B = self._linear_step
            return A @ z + B @ v
        return np.asarray(self.linearization.step(z, v), dtype=float)

    def _path_reference(
        self, x: np.ndarray, pose: np.ndarray, y_ref: np.ndarray
    ) -> tuple[np.ndarray, _Where]:
        """Locate the car on the path; the path QP's references (5 Np,): the reference's speed
        (and vy, normally unweighted) by time, the yaw rate the path asks for where the car
        will be (v̄ κ: by place, not time), zero lateral and heading error; and what
        :meth:`_solve_path` needs: the errors now, v̄ and the curvature ahead."""
        assert self._path is not None
        frenet = self._path.locate(pose, self._path_hint)
        self._path_hint = frenet.index
        speed = float(x[0])
        ahead = frenet.station_m + (speed * self.dt) * self._steps_ahead
        curvature = self._path.curvature_at(ahead)
        # The kinematics' v̄ by band: Θ depends on nothing else for a lifted-linear model, so
        # its path QP (Hessian, dual) is rebuilt only when the speed leaves its band.
        banded = self._speed_band(speed)
        where = (frenet.lateral_error_m, frenet.heading_error_rad, banded, curvature[:-1])
        references = np.zeros((self.Np, OUTPUTS))  # errors' references: 0
        references[:, :STATES] = y_ref.reshape(self.Np, STATES)
        low, span = self._yaw_rate_scale
        references[:, 2] = (speed * curvature[1:] - low) / span
        return references.ravel(), where

    def prepare(self) -> None:
        """The real-time iteration's preparation of the next step, before its measurement:
        the state it will plan from predicted by the model (from the last step's, under the
        input it returned; from the reference's first sample before the first step), the
        linearisation along the shifted plan rolled out from there, Θ, the Hessian and its
        factor, the active-set solver's rows. :meth:`act` then only measures, builds the free
        response and solves (the feedback phase). With ``presolve`` it then solves the QP at
        the predicted state, for the active-set solver's working set only. A no-op for a
        lifted-linear model (built once) but for a path QP's Θ at a new speed band, and when
        ``real_time_iteration`` is off."""
        if not self.config.real_time_iteration or self._reference is None:
            return
        predicted = self._predicted()
        if predicted is None:
            return
        z, x, pose, t = predicted
        v_prev = self._v_prev
        if self.linearization is None:
            if self._path is not None:  # the path QP's Θ for the speed band expected
                # The last step's speed, not the model's prediction of the next one: a model
                # that predicts speed badly would otherwise flip the band, and rebuild Θ twice,
                # every step (the speed moves far less than a band in one period).
                speed = float((x if self._last is None else self._last.x)[0])
                band = self._speed_band(speed)
                with single_threaded():
                    self._path_theta(band)
                    # The band a speed change would switch to next is one band away: build one
                    # such QP a step (the nearer side first), so that the switch, which happens
                    # in the feedback, finds it built.
                    for side in sorted((-1.0, 1.0), key=lambda s: s * (band - speed)):
                        if self._band_qp(band + side * SPEED_BAND_MPS):
                            break
            return
        k = min(round(t / self.dt) + self.delay_steps, self._reference_steps - 1)
        y_ref = self._reference[k + 1 : k + 1 + self.Np].ravel()
        where: _Where | None = None
        if self._path is not None:
            if pose is None:  # before the first step: no pose to locate the car by
                return
            y_ref, where = self._path_reference(x, pose, y_ref)
        w = self.disturbance.w if self.disturbance is not None else None
        with single_threaded():
            self._prepared = self._prepare_at(z, v_prev, y_ref, w, where)
            if self.config.presolve:  # warms the active-set solver; the answer is not used
                self._solve(z, v_prev, y_ref, w, where)

    def _predicted(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float] | None:
        """(z, x, pose, t) the next step will plan from, as the model predicts them: the last
        step's planning state under its first move (+ w), its pose moved on by that step's
        kinematics; before the first step, the reference's first sample (no pose)."""
        assert self._reference is not None
        last = self._last
        if last is None:
            x0 = self.normalizer.states_inverse(self._reference[0])
            z = np.asarray(self.model.lift(x0), dtype=float)
            if self.delay_steps:
                z = self._model_step(z, self._v_prev)
            return z, self.normalizer.states_inverse(self.C @ z), None, 0.0
        z = self._model_step(last.z, last.v)
        if last.w is not None:
            z = z + last.w
        pose = None if last.pose is None else _pose_ahead(last.pose, last.x, self.dt)
        return z, self.normalizer.states_inverse(self.C @ z), pose, last.t + self.dt

    def _prepare_at(
        self,
        z: np.ndarray,
        v_prev: np.ndarray,
        y_ref: np.ndarray,
        w: np.ndarray | None,
        where: _Where | None,
    ) -> _Prepared:
        """Linearise along the input guess rolled out from z (or, frozen, at z and the next
        input only) and build that model's QP; ``sqp_iterations`` times, each along the plan
        the previous one solves for (from z, against y_ref, where)."""
        model = self.linearization
        assert model is not None
        guess = self._input_guess(v_prev)
        if self.config.release_brake:
            guess = self._brake_released(guess, z, y_ref)
        band = None if where is None else where[2]
        for iteration in range(self.sqp_iterations):
            if self.config.linearization == "frozen":
                A, B, d = model.linearize(z[None], guess[:1])
            else:
                A, B, d = model.linearize(self._points(model, z, guess, iteration), guess)
            states_qp = self.qp
            assert isinstance(states_qp, TimeVaryingQP)
            finite = all(np.isfinite(a).all() for a in (A, B, d) if a is not None)
            theta = states_qp.model_theta(A, B, d) if finite else None
            prepared = None
            if theta is not None and np.isfinite(theta).all():
                try:
                    prepared = self._build(theta, band)
                except np.linalg.LinAlgError:  # finite, but too large for its Hessian
                    prepared = None
            if prepared is None:
                # The model, not the QP, has failed: a diverging rollout along the plan (or a
                # linearisation whose products overflow over the horizon). The step falls back
                # to the previous plan, counted as a failure, and says whose.
                log.warning(
                    "%s's linearisation along the plan is not finite (it diverges from this "
                    "state under the planned inputs): DE-MPC falls back to its previous plan",
                    type(self.model).__name__,
                )
                failed = QPSolution(np.zeros((self.Nc, INPUTS)), 0.0, "failed", 0, MODEL_NOT_FINITE)
                return _Prepared(None, failed)
            if iteration == self.sqp_iterations - 1:
                return prepared
            solution = self._feedback(prepared, z, v_prev, y_ref, w, where)
            if not solution.ok:
                return _Prepared(None, solution)
            guess = _held(v_prev + np.cumsum(solution.dv, axis=0), self.Np)
        raise AssertionError("unreachable: sqp_iterations >= 1")

    def _points(
        self, model: LinearizableModel, z: np.ndarray, guess: np.ndarray, iteration: int
    ) -> np.ndarray:
        """(Np, N) points to linearise at, z̄_0 = z: ``plan``, the model rolled out along the
        guess (exact, Np model steps in sequence); ``predicted`` (acados's RTI shift), the
        states the last step's QP predicted under its plan, one step on and lifted, in one
        batched call (no simulation; the first step and later SQP iterations roll out)."""
        rows = self._predicted_rows
        if self.config.linearization != "predicted" or iteration or rows is None:
            return _rollout(model, z, guess)
        ahead = model.lift(self.normalizer.states_inverse(rows[1:]))
        return np.vstack([z[None], np.asarray(ahead, dtype=float)])

    def _build(self, theta: np.ndarray, band: float | None) -> _Prepared:
        """The QP of the model whose Θ ``theta`` is (its A, B, d set by ``model_theta``):
        Hessian, factor, the solver's rows; for a path (band: v̄), the path QP's, extended
        from the model's Θ."""
        states_qp = self.qp
        assert isinstance(states_qp, TimeVaryingQP)
        if self._path is None:
            states_qp.set_prediction_matrix(theta)
            states_qp.prepare_solvers()
            return _Prepared(None, None)
        assert self.frenet is not None and self.path_qp is not None and band is not None
        self.path_qp.set_prediction_matrix(self.frenet.extend_theta(theta, band))
        self.path_qp.prepare_solvers()
        return _Prepared(theta, None, band)

    def _feedback(
        self,
        prepared: _Prepared,
        z: np.ndarray,
        v_prev: np.ndarray,
        y_ref: np.ndarray,
        w: np.ndarray | None,
        where: _Where | None,
    ) -> QPSolution:
        """The feedback phase on a prepared QP: the measured free response (with w), the solve."""
        if prepared.failed is not None:
            return prepared.failed
        states_qp = self.qp
        assert isinstance(states_qp, TimeVaryingQP)
        states_qp.set_disturbance(w)
        if where is None:
            return states_qp.solve(z, v_prev, y_ref)
        assert self.frenet is not None and self.path_qp is not None
        assert prepared.theta is not None
        if where[2] != prepared.band:  # the speed left the band it was prepared for
            self.path_qp.set_prediction_matrix(self.frenet.extend_theta(prepared.theta, where[2]))
        free = states_qp.free_response(z, v_prev)
        self.path_qp.set_free_response(self.frenet.extend_free(free, self.C @ z, *where))
        return self.path_qp.solve(z, v_prev, y_ref)

    def _speed_band(self, speed: float) -> float:
        """The path kinematics' v̄: the speed to SPEED_BAND_MPS, held while the speed stays
        within BAND_HOLD of it, so that a speed at a band's edge does not rebuild the path QP
        (2-3 ms at 60/50, in the feedback phase) every few steps."""
        held = self._band_held
        if held is None or abs(speed - held) > BAND_HOLD * SPEED_BAND_MPS:
            held = self._band_held = SPEED_BAND_MPS * round(speed / SPEED_BAND_MPS)
        return held

    def _path_theta(self, band: float) -> None:
        """A lifted-linear model's path QP is the one of speed band ``band``: each band's QP
        (Θ, Hessian, factor, the active-set solver's rows) is built once and kept, warm, for
        the run and the next ones (BAND_QPS of them, the least recently used dropped)."""
        if band != self._path_band:
            self._band_qp(band)
            self.path_qp = self._band_qps[band]
            self._band_qps.move_to_end(band)
            self._path_band = band

    def _band_qp(self, band: float) -> bool:
        """Build the path QP of speed band ``band`` unless it is kept: whether it was built."""
        if band in self._band_qps:
            return False
        assert self.frenet is not None
        qp = TimeVaryingQP(np.zeros((OUTPUTS, 0)), INPUTS, **self._path_settings)
        qp.set_prediction_matrix(self.frenet.extend_theta(self.qp.theta, band))
        qp.prepare_solvers()
        if self._step_bounds is not None:  # built mid-step: the step's pedal side
            qp.set_input_bounds(*self._step_bounds)
        self._band_qps[band] = qp  # the most recently used end
        while len(self._band_qps) > BAND_QPS:
            self._band_qps.popitem(last=False)
        return True

    def _solve_path_linear(
        self,
        z: np.ndarray,
        v_prev: np.ndarray,
        y_ref: np.ndarray,
        w: np.ndarray | None,
        where: _Where,
    ) -> QPSolution:
        """The path QP of a lifted-linear model: the errors to the path extend its prediction
        (``controllers/path_following.py``), with the disturbance w where offset-free."""
        assert self.frenet is not None and self.path_qp is not None
        states_qp = self.qp
        free = states_qp.free_response(z, v_prev)
        if w is not None:
            free = free + states_qp.phi_w @ w
        self._path_theta(where[2])
        self.path_qp.set_free_response(self.frenet.extend_free(free, self.C @ z, *where))
        return self.path_qp.solve(z, v_prev, y_ref)

    def _input_guess(self, v_prev: np.ndarray) -> np.ndarray:
        """(Np, m) inputs to linearise along: the rest of the previous plan held at its end
        (v_prev held before the first plan)."""
        if self._plan is None:
            return np.repeat(v_prev[None], self.Np, axis=0)
        return _held(self._plan[min(self._plan_step, self.Nc - 1) :], self.Np)

    def _brake_released(self, guess: np.ndarray, z: np.ndarray, y_ref: np.ndarray) -> np.ndarray:
        """``guess`` with its pedal at zero on every step where it brakes while the car is
        slower than RELEASE_BELOW_MPS and the reference's speed lies more than
        RELEASE_MARGIN_MPS above it (normalized units throughout)."""
        pedal_zero = self._pedal_zero
        braking = guess[:, PEDAL] < pedal_zero
        if not braking.any():
            return guess
        speed = float((self.C @ z)[0])
        if speed >= self._release_below:
            return guess
        wanted = y_ref.reshape(self.Np, -1)[: len(guess), 0]
        release = braking & (wanted > speed + self._release_margin)
        if not release.any():
            return guess
        released = guess.copy()
        released[release, PEDAL] = pedal_zero
        return released

    def _fallback(self, v_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(plan, increments): the rest of the previous plan, held at its end, as the new plan
        (its first row is the move applied); the last input held if there is no plan."""
        if self._plan is None:
            return np.repeat(v_prev[None], self.Nc, axis=0), np.zeros((self.Nc, INPUTS))
        rest = self._plan[min(self._plan_step, self.Nc - 1) :]
        rest = np.vstack([rest, np.repeat(rest[-1:], self.Nc - len(rest), axis=0)])
        self._plan_step += 1
        return rest, np.diff(np.vstack([v_prev, rest]), axis=0)


@dataclass(frozen=True)
class _Prepared:
    """What a step's preparation built into the QPs, and what the feedback phase needs of it:
    a path's model Θ and the speed band its path Θ is for; or the failure to report."""

    theta: np.ndarray | None
    failed: QPSolution | None
    band: float | None = None


@dataclass(frozen=True)
class _Last:
    """The last step's planning state (lifted, physical), first move, disturbance, pose and
    time: the next one's prediction starts from them."""

    z: np.ndarray
    v: np.ndarray
    w: np.ndarray | None
    x: np.ndarray
    pose: np.ndarray | None
    t: float


def _pose_ahead(pose: np.ndarray, x: np.ndarray, dt: float) -> np.ndarray:
    """(X, Y, yaw) one step on: planar kinematics under the state x at the step's start (the
    plant's pose to first order, as ``harness.evaluation.tracking.predicted_path`` draws it)."""
    vx, vy, yaw_rate = x
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return pose + dt * np.array([vx * c - vy * s, vx * s + vy * c, yaw_rate])


def _plus(d: np.ndarray | None, w: np.ndarray | None) -> np.ndarray | None:
    """A model's affine term d (K, N) (or none) with the disturbance w (N,) added."""
    if w is None:
        return d
    return w[None] if d is None else d + w


def _rollout(model: LinearizableModel, z: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """(K, N): z̄_0 = z, z̄_{k+1} = step(z̄_k, v_k), the points a plan of K inputs passes."""
    states = np.empty((len(inputs), z.shape[0]))
    state = z
    for k in range(len(inputs)):  # each point needs the previous one
        states[k] = state
        state = model.step(state, inputs[k])
    return states


def _held(plan: np.ndarray, steps: int) -> np.ndarray:
    """The first ``steps`` rows of ``plan``, its last row repeated beyond its end."""
    if len(plan) >= steps:
        return plan[:steps]
    return np.vstack([plan, np.repeat(plan[-1:], steps - len(plan), axis=0)])


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
