"""DEMPC, the controller DE-MPC's settings build: each control period, measure, lift, solve the
step's QP, apply the first move (paper section V, Algorithm 2; the settings and their units are
``controllers/de_mpc.py``).

The step is composed of parts, each chosen by the settings:

- **the QP** (``controllers/condensed_qp.py``): built once for a lifted-linear model
  (:class:`CondensedQP`), or each step for a linearised one (:class:`TimeVaryingQP`, prepared by
  ``controllers/time_varying.py``: the real-time iteration, the brake's release);
- **what it tracks**: the reference's states, or a course's path
  (:class:`~controllers.path_following.PathTracking`);
- **the disturbance** (``controllers/disturbance.py``): none, offset-free or a Kalman filter;
- **the pedal's side** (``controllers/pedal_sides.py``), when it is kept to one;
- **the clock** (``controllers/clock.py``): ``compute_delay: one_step`` plans from the model's
  prediction one period ahead; ``real_time_iteration`` prepares the next step's QP before its
  measurement (:meth:`DEMPC.prepare`).
"""

from __future__ import annotations

import copy
import logging
import time
from typing import TYPE_CHECKING, cast

import numpy as np

from controllers.blas import single_threaded
from controllers.clock import Clock, Plan, Planned
from controllers.condensed_qp import CondensedQP, QPSolution
from controllers.disturbance import DisturbanceEstimator, learned, without_lateral
from controllers.linearization import check_lifted_model, check_linearizable, linearization_of
from controllers.path_following import PathTracking, Where
from controllers.pedal_sides import PedalSides
from controllers.time_varying import LinearisedStep, Prepared, linearised_step
from controllers.time_varying_qp import TimeVaryingQP
from harness.core.contracts import (
    COMPUTE_DELAYS,
    LiftedModel,
    LinearizableModel,
    Model,
    StepInfo,
)
from harness.core.episode import MinMaxNormalizer
from harness.core.reference_path import ReferencePath

if TYPE_CHECKING:  # the settings build this controller: it reads them, it does not import them
    from controllers.de_mpc import DEMPCConfig

log = logging.getLogger(__name__)
STATES, INPUTS = 3, 2


class DEMPC:
    """Koopman MPC; ``reset(reference)`` then ``act(x, t)`` every control period.

    Settings are a :class:`~controllers.de_mpc.DEMPCConfig` (checked there; ``config(model)``
    builds this); the fitted model is given at run time. What the model is decides the QP: a
    lifted-linear model's prediction matrices are built once (:class:`CondensedQP`); a bilinear
    model or any :class:`~harness.core.contracts.LinearizableModel` is linearised each step
    along the previous plan and solved as a :class:`TimeVaryingQP`.
    """

    def __init__(self, model: Model, config: DEMPCConfig) -> None:
        self.config = config
        self.model = model
        self.Np, self.Nc, self.dt = int(config.Np), int(config.Nc), float(config.dt)
        linearization = linearization_of(model)
        if linearization is None:
            A, B, C = check_lifted_model(cast(LiftedModel, model))
        else:
            C = check_linearizable(linearization)
        self.C = C
        self.normalizer: MinMaxNormalizer = model.normalizer_
        self.u_min, self.u_max = config.input_limits()
        settings = config.qp_settings(self.normalizer)
        self._dv_max = settings["dv_max"]  # normalized
        self._input_bounds = (settings["v_min"], settings["v_max"])
        self.path: PathTracking | None = None
        if config.reference == "path":
            path_settings = {**settings, "Q": config.path_weights()}
            self.path = PathTracking(self.normalizer, self.dt, self.Np, path_settings)
        self.qp: CondensedQP
        self.linearised: LinearisedStep | None = None
        if linearization is None:
            self.qp = CondensedQP(A, B, C, **settings)
            self._linear_step = (A, B)
        else:
            self.qp = TimeVaryingQP(C, INPUTS, **settings)
            self.linearised = linearised_step(
                linearization,
                self.qp,
                config.secant_spans(),
                config.release_brake,
                config.linearization,
                int(config.sqp_iterations),
                self.path,
                type(model).__name__,
            )
        # Its own estimator: the config's is a template, shared by every run it builds.
        self.disturbance: DisturbanceEstimator | None = copy.deepcopy(config.disturbance)
        self._without_lateral = without_lateral(C)
        margin = config.pedal_side_margin_mps
        self.pedal_sides = None if margin is None else PedalSides.of(margin, self.normalizer)
        self.delay_steps = COMPUTE_DELAYS[config.compute_delay]
        self.clock = Clock(self.delay_steps, self.dt, self._model_step, C, self.normalizer)
        self.plan = Plan(self.Np, self.Nc)
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
        if self.path is not None:
            self.path.follow(path)
            if path is None:
                log.debug("controller.reference=path: this run has no path, tracking its states")
        self._start(u_prev)

    def _start(self, u_prev: np.ndarray | None) -> None:
        """No plan, the hot start forgotten, the last input u_prev (default 0)."""
        u = np.zeros(INPUTS) if u_prev is None else np.asarray(u_prev, dtype=float)
        self._v_prev = self.normalizer.inputs(np.clip(u, self.u_min, self.u_max))
        self.plan.clear()
        if self.disturbance is not None:
            self.disturbance.start(self.C.shape[1])
        if self.pedal_sides is not None:
            self.pedal_sides.reset(self._v_prev)
        self._z_expected: np.ndarray | None = None
        self._prepared: Prepared | None = None
        self.clock.last = None
        self._predicted_rows: np.ndarray | None = None  # the last plan's states, normalized
        self.qp.reset()
        if self.path is not None:
            self.path.restart()

    def increment_shares(self, inputs: np.ndarray) -> np.ndarray:
        """(T - 1, m) each step's change of each physical input in ``inputs`` (T, m), as a share
        of its bound (the QP's, normalized: the pedal's on the throttle's or the brake's side
        as it moved there); above 1 where the slack let it past."""
        v = self.normalizer.inputs(np.asarray(inputs, dtype=float))
        return np.abs(np.diff(v, axis=0)) / self._dv_max

    @property
    def linearization(self) -> LinearizableModel | None:
        """How a linearised model is read each step (its secant or bilinear form); None: a
        lifted-linear model, whose QP is built once."""
        return None if self.linearised is None else self.linearised.model

    @property
    def follows_path(self) -> bool:
        """Whether this run follows a path (``reference: path`` and a path at reset)."""
        return self.path is not None and self.path.path is not None

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
        k = self.clock.index(t, self._reference_steps)
        z = np.asarray(self.model.lift(x), dtype=float)
        y_ref = self._reference[k + 1 : k + 1 + self.Np].ravel()
        v_prev = self._v_prev
        w = self._estimate_disturbance(z, abs(float(x[0])))
        if self.delay_steps:  # from here on z, x and pose are those at t + dt, predicted
            z, x, pose = self.clock.ahead(z, x, pose, v_prev, w)
        where: Where | None = None
        if self.follows_path:
            if pose is None:
                raise ValueError("a DE-MPC run that follows a path needs the car's pose in act()")
            assert self.path is not None
            y_ref, where = self.path.reference(x, pose, y_ref)
        if self.pedal_sides is not None:
            bounds = self.pedal_sides.bounds(*self._input_bounds, v_prev)
            self.qp.set_input_bounds(*bounds)
            if self.path is not None:
                self.path.set_input_bounds(*bounds)
        # Small products: one BLAS thread is fastest, for every model (blas.py; the main job's
        # lifted-linear path follower at 60/50: p99 7.8-7.9 ms on two threads, 1.9-4.8 on one).
        with single_threaded():
            solution, shift = self._solve(z, v_prev, y_ref, w, where)
        # The QP solved: a lifted-linear model's path QP may be another band's now.
        qp = self.path.qp if where is not None and self.path is not None else self.qp
        self._prepared = None
        if solution.ok:  # the first move only: the plan's rest waits until the input is out
            first = v_prev + solution.dv[0]
        else:
            plan, dv = self.plan.fallback(v_prev)
            first = plan[0]
        u = np.clip(self.normalizer.inputs_inverse(first), self.u_min, self.u_max)
        # The input is ready: the rest is bookkeeping for the next step and the record, work of
        # the period after the input is sent (the harness times the feedback phase to here).
        ready = time.perf_counter()
        if solution.ok:
            plan, dv = self.plan.adopt(v_prev, solution.dv), solution.dv
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
        self.clock.last = Planned(z, plan[0], w, x, pose, t)
        predicted = self._predicted_states(qp, z, v_prev, dv, shift, solution.ok, k)
        info = StepInfo(
            predicted_states=self.normalizer.states_inverse(predicted),
            planned_inputs=self.normalizer.inputs_inverse(plan),  # elementwise: row 0 is u's bits
            solve_path=solution.path,
            fallback=not solution.ok,
            follows_path=self.follows_path,
            input_ready_s=ready,
        )
        return u, info

    def _predicted_states(
        self,
        qp: CondensedQP,
        z: np.ndarray,
        v_prev: np.ndarray,
        dv: np.ndarray,
        shift: np.ndarray,
        ok: bool,
        k: int,
    ) -> np.ndarray:
        """(Np, 3) normalized states the plan predicts, row i i + 1 steps after the measurement
        (with or without delay); kept for the next linearisation and the pedal's side."""
        assert self._reference is not None
        if qp.has_model():
            predicted = qp.predict(z, v_prev, dv)[:, :STATES]
            predicted = predicted + shift.reshape(self.Np, -1)[:, :STATES]
        else:  # the run's first preparation failed: no model to predict with yet (NaN rows)
            predicted = np.full((self.Np, STATES), np.nan)
        self._predicted_rows = predicted if ok else None
        if self.pedal_sides is not None and ok:
            self.pedal_sides.update(predicted[:, 0], self._reference[k + 1 : k + 1 + self.Np, 0])
        if self.delay_steps:
            predicted = np.vstack([(self.C @ z)[None], predicted[:-1]])
        return predicted

    def _solve(
        self,
        z: np.ndarray,
        v_prev: np.ndarray,
        y_ref: np.ndarray,
        w: np.ndarray | None,
        where: Where | None,
    ) -> tuple[QPSolution, np.ndarray]:
        """The step's QP from z (the prepared one, or prepared here in one phase), and the
        shift of the predicted outputs by w that a lifted-linear states QP leaves out."""
        shift = np.zeros_like(y_ref)
        if self.linearised is None and where is not None:
            assert self.path is not None
            solution = self.path.solve_lifted(self.qp, z, v_prev, y_ref, w, where, self.C @ z)
            return solution, shift
        if self.linearised is None:
            if w is not None:  # Y = Φz z + Φv v + Φw w + Θ ΔV: shifting Y_ref by Φw w is exact
                shift = self.qp.phi_w @ w
            return self.qp.solve(z, v_prev, y_ref - shift), shift
        if self._prepared is None:  # one phase: prepared along the measurement
            guess, rows = self.plan.guess(v_prev), self._predicted_rows
            self._prepared = self.linearised.prepare(z, v_prev, y_ref, w, where, guess, rows)
        return self.linearised.feedback(self._prepared, z, v_prev, y_ref, w, where), shift

    def _estimate_disturbance(self, z: np.ndarray, speed: float) -> np.ndarray | None:
        """The estimator's w after the last step's one-step prediction error z − ẑ (ẑ with w),
        at the measured |vx| ``speed`` (:func:`controllers.disturbance.learned`); None without."""
        if self.disturbance is None:
            return None
        error = None if self._z_expected is None else z - self._z_expected
        return learned(self.disturbance, error, speed, self._without_lateral)

    def _model_step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The model's own next lifted state (no disturbance)."""
        if self.linearised is None:
            A, B = self._linear_step
            return A @ z + B @ v
        return np.asarray(self.linearised.model.step(z, v), dtype=float)

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
        z0 = None  # before the first step: from the reference's first sample, lifted
        if self.clock.last is None:
            x0 = self.normalizer.states_inverse(self._reference[0])
            z0 = np.asarray(self.model.lift(x0), dtype=float)
        z, x, pose, t = self.clock.next_start(z0, self._v_prev)
        if self.linearised is None:
            if self.follows_path:
                assert self.path is not None
                # The last step's speed, not the model's prediction of the next one: a model
                # that predicts speed badly would otherwise flip the band, and rebuild Θ twice,
                # every step (the speed moves far less than a band in one period).
                speed = float((x if self.clock.last is None else self.clock.last.x)[0])
                with single_threaded():
                    self.path.prepare_lifted(speed, self.qp.theta)
            return
        k = self.clock.index(t, self._reference_steps)
        y_ref = self._reference[k + 1 : k + 1 + self.Np].ravel()
        where: Where | None = None
        if self.follows_path:
            if pose is None:  # before the first step: no pose to locate the car by
                return
            assert self.path is not None
            y_ref, where = self.path.reference(x, pose, y_ref)
        w = self.disturbance.w if self.disturbance is not None else None
        v_prev = self._v_prev
        assert self.linearised is not None
        guess, rows = self.plan.guess(v_prev), self._predicted_rows
        with single_threaded():
            self._prepared = self.linearised.prepare(z, v_prev, y_ref, w, where, guess, rows)
            if self.config.presolve:  # warms the active-set solver; the answer is not used
                self._solve(z, v_prev, y_ref, w, where)
