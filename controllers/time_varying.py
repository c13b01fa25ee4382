"""The time-varying DE-MPC's step: a model linearised along a guess of the plan, its QP built.

A bilinear or linearisable model (``controllers/linearization.py``) has a new A_k, B_k, d_k
along every plan, so each step builds its QP again: linearise along the input guess (the
previous plan, shifted and held; or, ``frozen``, at the current point only), Θ from the
step responses, the Hessian and its factor (:meth:`LinearisedStep.prepare`, the real-time
iteration's preparation when it runs before the measurement); then, with the measured state,
the free response and the solve (:meth:`LinearisedStep.feedback`). ``sqp_iterations`` > 1
linearises again along the plan each solve finds.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from controllers.clock import held
from controllers.condensed_qp import QPSolution
from controllers.linearization import BilinearLinearization, SecantInputs
from controllers.path_following import PathTracking, Where
from controllers.pedal_sides import PEDAL, pedal_frame
from controllers.time_varying_qp import TimeVaryingQP
from harness.core.contracts import LinearizableModel
from harness.core.episode import MinMaxNormalizer

log = logging.getLogger(__name__)
INPUTS = 2
# QPSolution.status of a step whose model gave a non-finite linearisation (no QP was solved).
MODEL_NOT_FINITE = "model_not_finite"
# Where a time-varying model is linearised: at every point of the previous plan (exact along
# the horizon), or at the current state and next input only, held over the horizon (frozen:
# Θ from one step response: far cheaper for a large lift at 60/50, see docs/findings/real_time.md).
LINEARIZATIONS = ("plan", "frozen", "predicted")
# The brake's release: below what speed a plan that brakes may be released (a brake acts at
# speed, and a linearisation there is right: only near a stop does its effect vanish), and how
# far the reference's speed must lie above the car's (m/s).
RELEASE_BELOW_MPS = 1.0
RELEASE_MARGIN_MPS = 0.1


class BrakeRelease:
    """An input guess with the pedal released (zero) on every step where it brakes while the car
    is slower than RELEASE_BELOW_MPS and the reference's speed lies more than
    RELEASE_MARGIN_MPS above it (``controller.release_brake``).

    Why: at a stop under brake a model rightly says the pedal does nothing, so a QP linearised
    there never leaves the brake (docs/findings/smooth_driving.md, "The standstill trap").
    """

    def __init__(self, normalizer: MinMaxNormalizer, C: np.ndarray) -> None:
        self.C = C
        self.pedal_zero, vx_min, vx_span = pedal_frame(normalizer)
        self.below = (RELEASE_BELOW_MPS - vx_min) / vx_span  # normalized throughout
        self.margin = RELEASE_MARGIN_MPS / vx_span

    def __call__(self, guess: np.ndarray, z: np.ndarray, y_ref: np.ndarray) -> np.ndarray:
        braking = guess[:, PEDAL] < self.pedal_zero
        if not braking.any():
            return guess
        speed = float((self.C @ z)[0])
        if speed >= self.below:
            return guess
        wanted = y_ref.reshape(len(guess), -1)[:, 0]
        release = braking & (wanted > speed + self.margin)
        if not release.any():
            return guess
        released = guess.copy()
        released[release, PEDAL] = self.pedal_zero
        return released


@dataclass(frozen=True)
class Prepared:
    """What a step's preparation built into the QPs, and what the feedback phase needs of it:
    a path's model Θ and the speed band its path Θ is for; or the failure to report."""

    theta: np.ndarray | None
    failed: QPSolution | None
    band: float | None = None


class LinearisedStep:
    """Prepare and solve one step of DE-MPC on a linearised model (module docstring).

    Args:
        model: the linearisable model (a secant or bilinear reading of the learner's).
        qp: the states QP, rebuilt from each linearisation.
        linearization: ``plan``, ``frozen`` or ``predicted`` (LINEARIZATIONS).
        sqp_iterations: linearisations a step.
        release: the brake's release of the input guess, or None.
        path: the path QP, extended from the states QP's Θ when the run follows a path.
        name: the learner's, for the warning when its linearisation is not finite.
    """

    def __init__(
        self,
        model: LinearizableModel,
        qp: TimeVaryingQP,
        linearization: str,
        sqp_iterations: int,
        release: BrakeRelease | None,
        path: PathTracking | None,
        name: str,
    ) -> None:
        self.model = model
        self.qp = qp
        self.linearization = linearization
        self.sqp_iterations = sqp_iterations
        self.release = release
        self.path = path
        self.name = name
        self.C = np.asarray(model.C_, dtype=float)
        self.normalizer: MinMaxNormalizer = model.normalizer_

    def prepare(
        self,
        z: np.ndarray,
        v_prev: np.ndarray,
        y_ref: np.ndarray,
        w: np.ndarray | None,
        where: Where | None,
        guess: np.ndarray,
        predicted_rows: np.ndarray | None,
    ) -> Prepared:
        """Linearise along ``guess`` rolled out from z (or, frozen, at z and the next input
        only) and build that model's QP; ``sqp_iterations`` times, each along the plan the
        previous one solves for (from z, against y_ref, where). ``predicted_rows``: the states
        the last plan predicted (normalized), where ``linearization: predicted``."""
        if self.release is not None:
            guess = self.release(guess, z, y_ref)
        band = None if where is None else where.speed_mps
        for iteration in range(self.sqp_iterations):
            if self.linearization == "frozen":
                A, B, d = self.model.linearize(z[None], guess[:1])
            else:
                points = self._points(z, guess, iteration, predicted_rows)
                A, B, d = self.model.linearize(points, guess)
            finite = all(np.isfinite(a).all() for a in (A, B, d) if a is not None)
            theta = self.qp.model_theta(A, B, d) if finite else None
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
                    self.name,
                )
                failed = QPSolution(
                    np.zeros((self.qp.Nc, INPUTS)), 0.0, "failed", 0, MODEL_NOT_FINITE
                )
                return Prepared(None, failed)
            if iteration == self.sqp_iterations - 1:
                return prepared
            solution = self.feedback(prepared, z, v_prev, y_ref, w, where)
            if not solution.ok:
                return Prepared(None, solution)
            guess = held(v_prev + np.cumsum(solution.dv, axis=0), len(guess))
        raise AssertionError("unreachable: sqp_iterations >= 1")

    def feedback(
        self,
        prepared: Prepared,
        z: np.ndarray,
        v_prev: np.ndarray,
        y_ref: np.ndarray,
        w: np.ndarray | None,
        where: Where | None,
    ) -> QPSolution:
        """The feedback phase on a prepared QP: the measured free response (with w), the solve."""
        if prepared.failed is not None:
            return prepared.failed
        self.qp.set_disturbance(w)
        if where is None:
            return self.qp.solve(z, v_prev, y_ref)
        assert self.path is not None and prepared.theta is not None and prepared.band is not None
        return self.path.feedback(
            self.qp, prepared.theta, prepared.band, z, v_prev, y_ref, where, self.C @ z
        )

    def _points(
        self, z: np.ndarray, guess: np.ndarray, iteration: int, rows: np.ndarray | None
    ) -> np.ndarray:
        """(Np, N) points to linearise at, z̄_0 = z: ``plan``, the model rolled out along the
        guess (exact, Np model steps in sequence); ``predicted`` (acados's RTI shift), the
        states the last step's QP predicted (``rows``, normalized), one step on and lifted, in
        one batched call (no simulation; the first step and later SQP iterations roll out)."""
        if self.linearization != "predicted" or iteration or rows is None:
            return rollout(self.model, z, guess)
        ahead = self.model.lift(self.normalizer.states_inverse(rows[1:]))
        return np.vstack([z[None], np.asarray(ahead, dtype=float)])

    def _build(self, theta: np.ndarray, band: float | None) -> Prepared:
        """The QP of the model whose Θ ``theta`` is (its A, B, d set by ``model_theta``):
        Hessian, factor, the solver's rows; for a path (band: v̄), the path QP's, extended
        from the model's Θ."""
        if band is None:
            self.qp.set_prediction_matrix(theta)
            self.qp.prepare_solvers()
            return Prepared(None, None)
        assert self.path is not None
        self.path.build(theta, band)
        return Prepared(theta, None, band)


def linearised_step(
    model: LinearizableModel,
    qp: TimeVaryingQP,
    secant_spans: np.ndarray,
    release_brake: bool,
    linearization: str,
    sqp_iterations: int,
    path: PathTracking | None,
    name: str,
) -> LinearisedStep:
    """The step of ``model`` with its inputs' secants over ``secant_spans`` (0: the tangent;
    a bilinear step is linear in v at a fixed state: its secant is its tangent) and the brake's
    release of the input guess where ``release_brake``."""
    if np.any(secant_spans > 0) and not isinstance(model, BilinearLinearization):
        model = SecantInputs(model, secant_spans, qp.v_min, qp.v_max)
    release = BrakeRelease(model.normalizer_, qp.C) if release_brake else None
    return LinearisedStep(model, qp, linearization, sqp_iterations, release, path, name)


def rollout(model: LinearizableModel, z: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """(K, N): z̄_0 = z, z̄_{k+1} = step(z̄_k, v_k), the points a plan of K inputs passes."""
    states = np.empty((len(inputs), z.shape[0]))
    state = z
    for k in range(len(inputs)):  # each point needs the previous one
        states[k] = state
        state = model.step(state, inputs[k])
    return states
