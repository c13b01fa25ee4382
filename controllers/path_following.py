"""Path following for any DE-MPC model: its predicted states and the errors they drive to a path.

``controller.reference: path`` adds two outputs to the model's (vx, vy, yaw rate): the lateral
error e_y (m, left of the line) and heading error e_ψ (rad) to the path, with the small-angle
kinematics of a car at the measured speed v̄::

    e_y,k+1 = e_y,k + dt (vy_k + v̄ e_ψ,k)        vy_k, r_k: the model's physical states
    e_ψ,k+1 = e_ψ,k + dt (r_k − v̄ κ_k)           κ_k: the path's curvature where the car will be

Both are linear in the model's predicted states for a given v̄, and the curvature ahead is a
known input, so the errors over the horizon are running sums of the model's own prediction
Y = free + Θ ΔV: whatever the model (lifted-linear, bilinear, linearisable), the path QP's
prediction is a few cumulative sums of the states QP's, O(Np·Nc·m) a step, and its Hessian is
built from it (:meth:`~controllers.time_varying_qp.TimeVaryingQP.set_prediction_matrix`; the free
response by ``set_free_response``). The outputs per step are (vx, vy, yaw rate) normalized as
the model's, then e_y and e_ψ; ``controller.Q_path`` weighs them.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.condensed_qp import CondensedQP, QPSolution
from controllers.time_varying_qp import TimeVaryingQP
from harness.core.episode import MinMaxNormalizer
from harness.core.reference_path import ReferencePath

STATES, INPUTS = 3, 2
ERRORS = 2  # lateral error (m), heading error (rad)
OUTPUTS = STATES + ERRORS
# The speed in the error kinematics, to this band (m/s): 1 % at 80 km/h.
SPEED_BAND_MPS = 0.25
# A band is kept until the speed is this many bands from it (the nearest band's half, 0.5, plus
# hysteresis): v̄ is within 0.19 m/s of the speed, 0.8 % at 80 km/h.
BAND_HOLD = 0.75
# Path QPs a lifted-linear DE-MPC keeps, one per speed band (about 0.7 MB each at 60/50).
BAND_QPS = 8


@dataclass(frozen=True)
class Where:
    """Where the car stands for the path QP: the errors now, the banded speed v̄ (m/s) and the
    curvature (1/m) at the Np steps ahead."""

    lateral_error_m: float
    heading_error_rad: float
    speed_mps: float
    curvature_per_m: np.ndarray


class FrenetOutputs:
    """The path QP's prediction from a model's (module docstring).

    Args:
        normalizer: the model's min-max map (physical vy, r = span · y + low).
        dt: control period (s).
    """

    def __init__(self, normalizer: MinMaxNormalizer, dt: float) -> None:
        low = np.asarray(normalizer.states_inverse(np.zeros(STATES)), dtype=float)
        self.span = np.asarray(normalizer.states_inverse(np.ones(STATES)), dtype=float) - low
        self.low = low
        self.dt = float(dt)

    def extend(
        self,
        theta: np.ndarray,
        free: np.ndarray,
        y0: np.ndarray,
        lateral_error_m: float,
        heading_error_rad: float,
        speed_mps: float,
        curvature_per_m: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(Θ (5 Np, M), free (5 Np,)) of the outputs (y_k, e_y,k, e_ψ,k), k = 1..Np, from the
        model's prediction of y_1..y_Np (Θ (3 Np, M), free (3 Np,)), its current outputs y0
        (normalized C z_0), the errors now, v̄ and the curvature at steps 0..Np-1 ahead."""
        return self.extend_theta(theta, speed_mps), self.extend_free(
            free, y0, lateral_error_m, heading_error_rad, speed_mps, curvature_per_m
        )

    def extend_theta(self, theta: np.ndarray, speed_mps: float) -> np.ndarray:
        """Θ (5 Np, M) of :meth:`extend`: it depends on the model's Θ and v̄ only, so it is
        built before the measurement (the real-time iteration's preparation) and kept while v̄
        stays in its band."""
        dt, v = self.dt, float(speed_mps)
        Np = theta.shape[0] // STATES
        theta = theta.reshape(Np, STATES, -1)
        theta_states = _before(np.zeros_like(theta[0]), theta * self.span[:, None])
        heading_theta = dt * np.cumsum(theta_states[:, 2], axis=0)
        lateral_theta = dt * np.cumsum(
            theta_states[:, 1] + v * _before(np.zeros_like(heading_theta[0]), heading_theta),
            axis=0,
        )
        return np.concatenate(
            [theta, lateral_theta[:, None], heading_theta[:, None]], axis=1
        ).reshape(Np * OUTPUTS, -1)

    def extend_free(
        self,
        free: np.ndarray,
        y0: np.ndarray,
        lateral_error_m: float,
        heading_error_rad: float,
        speed_mps: float,
        curvature_per_m: np.ndarray,
    ) -> np.ndarray:
        """free (5 Np,) of :meth:`extend`: what the measurement moves. Written into one array
        (no stacking): it runs in the feedback phase, every step."""
        dt, v = self.dt, float(speed_mps)
        Np = len(curvature_per_m)
        free = free.reshape(Np, STATES)
        span, low = self.span, self.low
        out = np.empty((Np, OUTPUTS))
        out[:, :STATES] = free
        # Step j's physical vy and r, j = 0..Np-1: j = 0 measured (no input effect), then
        # predicted; the two error columns hold them until they are summed.
        lateral, heading = out[:, STATES], out[:, STATES + 1]
        lateral[0], heading[0] = span[1:] * np.asarray(y0, dtype=float)[1:] + low[1:]
        lateral[1:] = span[1] * free[:-1, 1] + low[1]
        heading[1:] = span[2] * free[:-1, 2] + low[2]
        # e_ψ,k = e_ψ,0 + dt Σ_{j<k} (r_j − v̄ κ_j)
        heading -= v * curvature_per_m
        heading_before = heading_error_rad + dt * np.cumsum(heading)
        # e_y,k = e_y,0 + dt Σ_{j<k} (vy_j + v̄ e_ψ,j), e_ψ,0 the measured one
        lateral[0] += v * heading_error_rad
        lateral[1:] += v * heading_before[:-1]
        np.cumsum(lateral, out=lateral)
        lateral *= dt
        lateral += lateral_error_m
        heading[:] = heading_before
        return out.ravel()


def _before(first: np.ndarray, later: np.ndarray) -> np.ndarray:
    """Values at steps 0..Np-1 from step 0's and those of steps 1..Np (the last one unused)."""
    return np.concatenate([first[None], later[:-1]])


class PathTracking:
    """DE-MPC's cost on a course (``controller.reference: path``): the path QP, built from the
    states QP's prediction each step (it has outputs, no model of its own: N = 0).

    A lifted-linear model's Θ is constant, so its path Θ depends on v̄ alone: one path QP per
    speed band, built once and kept warm (the most recently used last). A linearised model's
    path QP is rebuilt from the step's Θ (:meth:`build`, :meth:`feedback`).
    """

    def __init__(
        self, normalizer: MinMaxNormalizer, dt: float, Np: int, settings: dict[str, Any]
    ) -> None:
        self.frenet = FrenetOutputs(normalizer, dt)
        self.dt = float(dt)
        self._settings = settings  # the path QP's (Q: the path weights)
        self.qp = TimeVaryingQP(np.zeros((OUTPUTS, 0)), INPUTS, **settings)
        # The path's yaw-rate reference, normalized as the model's states, and the steps ahead.
        self._yaw_rate_scale = (float(normalizer.state_min[2]), float(normalizer.state_span[2]))
        self._steps_ahead = np.arange(Np + 1, dtype=float)
        self._band_qps: OrderedDict[float, TimeVaryingQP] = OrderedDict()
        self.path: ReferencePath | None = None
        self._band: float | None = None  # the v̄ whose Θ a lifted-linear path QP holds
        self._hint: int | None = None
        self._band_held: float | None = None
        self._step_bounds: tuple[np.ndarray, np.ndarray] | None = None

    def follow(self, path: ReferencePath | None) -> None:
        """Follow ``path`` from the next step on (None: the run tracks states)."""
        self.path, self._hint = path, None

    def restart(self) -> None:
        """Forget the hot starts and the held band (the band's QPs stay built)."""
        self._band_held = None
        self.qp.reset()
        for band_qp in self._band_qps.values():
            band_qp.reset()

    def qps(self) -> list[CondensedQP]:
        """Every path QP a step may solve: the current one and each speed band's."""
        return [self.qp, *self._band_qps.values()]

    def set_input_bounds(self, v_min: np.ndarray, v_max: np.ndarray) -> None:
        """The step's input bounds on every path QP (and on those built later in the step)."""
        self._step_bounds = (v_min, v_max)
        for each in self.qps():
            each.set_input_bounds(v_min, v_max)

    def reference(
        self, x: np.ndarray, pose: np.ndarray, y_ref: np.ndarray
    ) -> tuple[np.ndarray, Where]:
        """Locate the car on the path; the path QP's references (5 Np,): the reference's speed
        (and vy, normally unweighted) by time, the yaw rate the path asks for where the car
        will be (v̄ κ: by place, not time), zero lateral and heading error; and where it is."""
        assert self.path is not None
        frenet = self.path.locate(pose, self._hint)
        self._hint = frenet.index
        speed = float(x[0])
        Np = len(self._steps_ahead) - 1
        ahead = frenet.station_m + (speed * self.dt) * self._steps_ahead
        curvature = self.path.curvature_at(ahead)
        # The kinematics' v̄ by band: Θ depends on nothing else for a lifted-linear model, so
        # its path QP (Hessian, dual) is rebuilt only when the speed leaves its band.
        banded = self.speed_band(speed)
        where = Where(frenet.lateral_error_m, frenet.heading_error_rad, banded, curvature[:-1])
        references = np.zeros((Np, OUTPUTS))  # errors' references: 0
        references[:, :STATES] = y_ref.reshape(Np, STATES)
        low, span = self._yaw_rate_scale
        references[:, 2] = (speed * curvature[1:] - low) / span
        return references.ravel(), where

    def speed_band(self, speed: float) -> float:
        """The path kinematics' v̄: the speed to SPEED_BAND_MPS, held while the speed stays
        within BAND_HOLD of it, so that a speed at a band's edge does not rebuild the path QP
        (2-3 ms at 60/50, in the feedback phase) every few steps."""
        held = self._band_held
        if held is None or abs(speed - held) > BAND_HOLD * SPEED_BAND_MPS:
            held = self._band_held = SPEED_BAND_MPS * round(speed / SPEED_BAND_MPS)
        return held

    def _extend_free(self, free: np.ndarray, y0: np.ndarray, where: Where) -> np.ndarray:
        return self.frenet.extend_free(
            free,
            y0,
            where.lateral_error_m,
            where.heading_error_rad,
            where.speed_mps,
            where.curvature_per_m,
        )

    # A lifted-linear model: one path QP per speed band.

    def solve_lifted(
        self,
        states_qp: CondensedQP,
        z: np.ndarray,
        v_prev: np.ndarray,
        y_ref: np.ndarray,
        w: np.ndarray | None,
        where: Where,
        y0: np.ndarray,
    ) -> QPSolution:
        """The path QP of a lifted-linear model: the errors to the path extend its prediction,
        with the disturbance w where offset-free; y0 = C z, normalized."""
        free = states_qp.free_response(z, v_prev)
        if w is not None:
            free = free + states_qp.phi_w @ w
        self.use_band(where.speed_mps, states_qp.theta)
        self.qp.set_free_response(self._extend_free(free, y0, where))
        return self.qp.solve(z, v_prev, y_ref)

    def prepare_lifted(self, speed: float, theta: np.ndarray) -> None:
        """Before the measurement: the path QP of the band of ``speed``, and the one a speed
        change would switch to next (one band away, the nearer side first), so that the switch,
        which happens in the feedback, finds it built."""
        band = self.speed_band(speed)
        self.use_band(band, theta)
        for side in sorted((-1.0, 1.0), key=lambda s: s * (band - speed)):
            if self._band_qp(band + side * SPEED_BAND_MPS, theta):
                break

    def use_band(self, band: float, theta: np.ndarray) -> None:
        """Make the path QP the one of speed band ``band`` (built once and kept, warm, for the
        run and the next ones: BAND_QPS of them, the least recently used dropped)."""
        if band != self._band:
            self._band_qp(band, theta)
            self.qp = self._band_qps[band]
            self._band_qps.move_to_end(band)
            self._band = band

    def _band_qp(self, band: float, theta: np.ndarray) -> bool:
        """Build the path QP of speed band ``band`` unless it is kept: whether it was built."""
        if band in self._band_qps:
            return False
        qp = TimeVaryingQP(np.zeros((OUTPUTS, 0)), INPUTS, **self._settings)
        qp.set_prediction_matrix(self.frenet.extend_theta(theta, band))
        qp.prepare_solvers()
        if self._step_bounds is not None:  # built mid-step: the step's bounds
            qp.set_input_bounds(*self._step_bounds)
        self._band_qps[band] = qp  # the most recently used end
        while len(self._band_qps) > BAND_QPS:
            self._band_qps.popitem(last=False)
        return True

    # A linearised model: the path QP from the step's Θ.

    def build(self, theta: np.ndarray, band: float) -> None:
        """The path QP from the model's Θ at v̄ = ``band`` (Hessian, factor, solver rows)."""
        self.qp.set_prediction_matrix(self.frenet.extend_theta(theta, band))
        self.qp.prepare_solvers()

    def feedback(
        self,
        states_qp: TimeVaryingQP,
        theta: np.ndarray,
        band: float,
        z: np.ndarray,
        v_prev: np.ndarray,
        y_ref: np.ndarray,
        where: Where,
        y0: np.ndarray,
    ) -> QPSolution:
        """The feedback phase on the path QP prepared at v̄ = ``band`` from Θ ``theta``."""
        if where.speed_mps != band:  # the speed left the band it was prepared for
            self.qp.set_prediction_matrix(self.frenet.extend_theta(theta, where.speed_mps))
        free = states_qp.free_response(z, v_prev)
        self.qp.set_free_response(self._extend_free(free, y0, where))
        return self.qp.solve(z, v_prev, y_ref)
