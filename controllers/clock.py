"""How DE-MPC meets the clock: where each step plans from, and when its input reaches the plant.

``compute_delay: one_step``: the input computed from the measurement at t_k reaches the plant at
t_{k+1} (the loop holds it, ``harness.plant.rollout.closed_loop``), while over [t_k, t_{k+1}) the
plant still gets the input returned last step. The controller predicts z_{k+1} =
f(lift(x_k), v_{k-1}) (+ w, offset-free) with its own model and plans from there, against the
reference from k + 1 on: standard delay compensation, exact for an exact model.

The real-time iteration prepares the next step before its measurement, from the state the model
predicts it will start at (:meth:`Clock.next_start`), along the rest of the last plan
(:class:`Plan`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from harness.core.episode import MinMaxNormalizer

# The model's own step in lifted coordinates, z⁺ = f(z, v) (no disturbance).
ModelStep = Callable[[np.ndarray, np.ndarray], np.ndarray]


class Clock:
    """Where a DE-MPC step plans from (module docstring).

    Args:
        delay_steps: control periods between a measurement and its input at the plant.
        dt: control period (s).
        step: the model's step, lifted.
        C: the lifted state's readout, y = C z (normalized states).
        normalizer: the model's min-max map.
    """

    def __init__(
        self,
        delay_steps: int,
        dt: float,
        step: ModelStep,
        C: np.ndarray,
        normalizer: MinMaxNormalizer,
    ) -> None:
        self.delay_steps, self.dt = delay_steps, dt
        self.step, self.C, self.normalizer = step, C, normalizer
        self.last: Planned | None = None

    def index(self, t: float, reference_steps: int) -> int:
        """The reference's sample the step at ``t`` plans from: t's, one period on under delay."""
        return min(round(t / self.dt) + self.delay_steps, reference_steps - 1)

    def ahead(
        self,
        z: np.ndarray,
        x: np.ndarray,
        pose: np.ndarray | None,
        v: np.ndarray,
        w: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(z, x, pose) one period on, as the model predicts them under the input v the plant
        gets meanwhile (+ w), the pose moved on by the step's kinematics."""
        z = self.step(z, v)
        if w is not None:
            z = z + w
        if pose is not None:
            pose = pose_ahead(np.asarray(pose, dtype=float), x, self.dt)
        return z, self.normalizer.states_inverse(self.C @ z), pose

    def next_start(
        self, z0: np.ndarray | None, v_prev: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float]:
        """(z, x, pose, t) the next step will plan from, as the model predicts them: the last
        step's planning state under its first move (+ w), its pose moved on by that step's
        kinematics; before the first step, ``z0`` (the reference's first sample, lifted; no
        pose), under v_prev for a period where the input is delayed."""
        last = self.last
        if last is None:
            assert z0 is not None, "the first step starts from the reference's first sample"
            z = self.step(z0, v_prev) if self.delay_steps else z0
            return z, self.normalizer.states_inverse(self.C @ z), None, 0.0
        z, x, pose = self.ahead(last.z, last.x, last.pose, last.v, last.w)
        return z, x, pose, last.t + self.dt


class Plan:
    """The inputs the last solve planned (normalized), as the loop moves along them: one move
    is applied a period; the rest guides the next linearisation, or stands in for a failed
    solve."""

    def __init__(self, Np: int, Nc: int) -> None:
        self.Np, self.Nc = Np, Nc
        self.moves: np.ndarray | None = None
        self.step = 0

    def clear(self) -> None:
        """No plan (a run's start)."""
        self.moves, self.step = None, 0

    def adopt(self, v_prev: np.ndarray, dv: np.ndarray) -> np.ndarray:
        """The solved increments from v_prev as the plan, its first move applied now."""
        self.moves, self.step = v_prev + np.cumsum(dv, axis=0), 1
        return self.moves

    def guess(self, v_prev: np.ndarray) -> np.ndarray:
        """(Np, m) inputs to linearise along: the rest of the plan held at its end (v_prev held
        before the first plan)."""
        if self.moves is None:
            return np.repeat(v_prev[None], self.Np, axis=0)
        return held(self.moves[min(self.step, self.Nc - 1) :], self.Np)

    def fallback(self, v_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(plan, increments): the rest of the plan, held at its end, as the new plan (its first
        row is the move applied); the last input held if there is no plan."""
        if self.moves is None:
            return np.repeat(v_prev[None], self.Nc, axis=0), np.zeros((self.Nc, v_prev.shape[0]))
        rest = self.moves[min(self.step, self.Nc - 1) :]
        rest = np.vstack([rest, np.repeat(rest[-1:], self.Nc - len(rest), axis=0)])
        self.step += 1
        return rest, np.diff(np.vstack([v_prev, rest]), axis=0)


@dataclass(frozen=True)
class Planned:
    """A step's planning state (lifted, physical), first move, disturbance, pose and time: the
    next one's prediction starts from them."""

    z: np.ndarray
    v: np.ndarray
    w: np.ndarray | None
    x: np.ndarray
    pose: np.ndarray | None
    t: float


def pose_ahead(pose: np.ndarray, x: np.ndarray, dt: float) -> np.ndarray:
    """(X, Y, yaw) one step on: planar kinematics under the state x at the step's start (the
    plant's pose to first order, as ``harness.evaluation.tracking.predicted_path`` draws it)."""
    vx, vy, yaw_rate = x
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return pose + dt * np.array([vx * c - vy * s, vx * s + vy * c, yaw_rate])


def held(plan: np.ndarray, steps: int) -> np.ndarray:
    """The first ``steps`` rows of ``plan``, its last row repeated beyond its end."""
    if len(plan) >= steps:
        return plan[:steps]
    return np.vstack([plan, np.repeat(plan[-1:], steps - len(plan), axis=0)])
