"""The three contracts of the harness, written down once: a plant, a lifted model, a controller.

(:class:`BilinearModel` refines the lifted model: what sets a bilinear one apart from a linear one;
:class:`LinearizableModel` is a nonlinear model a time-varying MPC linearises along its plan.)

Everything that steps a car (data collection, characterization, closed-loop tracking) is typed
against :class:`Plant`; every MPC reads a learner through :class:`LiftedModel`; every rollout
drives a :class:`Controller`, whose ``act`` returns the input *and* a :class:`StepInfo`, so no
caller ever probes a controller for attributes.

States and inputs are the paper's, in the harness's units:

- x = (vx, vy, yaw_rate) in m/s, m/s, rad/s (the centre of gravity in the yaw frame);
- u = (steer_wheel_deg, pedal): steering-wheel angle in degrees; pedal >= 0 is throttle in
  [0, 0.2], pedal < 0 is brake master-cylinder pressure in -MPa.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:  # episode.py imports the plant's limits; the contracts import nothing heavy
    from harness.core.episode import MinMaxNormalizer
    from harness.core.reference_path import ReferencePath

STATE_NAMES: tuple[str, ...] = ("vx", "vy", "yaw_rate")
INPUT_NAMES: tuple[str, ...] = ("steer_wheel_deg", "pedal")
# ``controller.compute_delay``: control periods between a measurement and the plant receiving
# the input computed from it. The loop holds each input that long
# (:func:`harness.plant.rollout.closed_loop`); a controller that knows it predicts its model forward
# as far (DE-MPC's delay compensation).
COMPUTE_DELAYS: dict[str, int] = {"none": 0, "one_step": 1}


@runtime_checkable
class Plant(Protocol):
    """A car that steps at ``dt`` under u and reports x (mujoco_playground's ``reset``/``step``)."""

    dt: float

    def reset(self, seed: int | None = None, speed_mps: float = 0.0) -> np.ndarray:
        """Start at rest (the paper's x0 = 0), or rolling straight at ``speed_mps``; return x."""
        ...

    def step(self, u: np.ndarray) -> np.ndarray:
        """Hold u for one control period; return the new x."""
        ...

    @property
    def pose(self) -> np.ndarray:
        """(X, Y, yaw) in the world frame (m, m, rad): where the car is, for display and paths."""
        ...

    @property
    def fingerprint(self) -> dict[str, Any]:
        """Everything that determines the plant's behaviour (JSON-able): what a dataset keys on."""
        ...


@runtime_checkable
class LiftedModel(Protocol):
    """A fitted Koopman model: z⁺ = A_ z + B_ v, x_norm = C_ z, z = lift(x) (paper eqs. 9-12).

    v = normalizer_.inputs(u) and x = normalizer_.states_inverse(C_ z): the model lives in the
    min-max normalized units of the data it was fitted on.
    """

    A_: np.ndarray  # (N, N)
    B_: np.ndarray  # (N, m)
    C_: np.ndarray  # (n, N)
    normalizer_: MinMaxNormalizer

    def lift(self, x: np.ndarray) -> np.ndarray:
        """z = lift(x) for physical states x (..., n) -> (..., N)."""
        ...


@runtime_checkable
class BilinearModel(LiftedModel, Protocol):
    """A lifted model whose input also multiplies the lifted state (bilinear Koopman)::

        z⁺ = A_ z + B_ v + Σⱼ (vⱼ − v0_ⱼ) H_[j] z,   v0_ = normalizer_.inputs(0)

    It has every member of :class:`LiftedModel`, but is not one: an MPC that reads only
    ``A_`` and ``B_`` would silently drop ``H_``. Check for it before treating a model as linear.
    """

    H_: np.ndarray  # (m, N, N)
    v0_: np.ndarray  # (m,)


@runtime_checkable
class LinearizableModel(Protocol):
    """A model in lifted coordinates z = lift(x) whose step is nonlinear but differentiable::

        z⁺ = step(z, v),   x_norm = C_ z,   linearised as  z⁺ ≈ A_k z + B_k v + d_k

    what a time-varying MPC needs: ``linearize`` gives, at each point (z̄_k, v̄_k) of a
    trajectory, the Jacobians A_k = ∂step/∂z, B_k = ∂step/∂v and d_k = step(z̄_k, v̄_k) − A_k z̄_k
    − B_k v̄_k. Units as :class:`LiftedModel`'s (normalized v).
    """

    C_: np.ndarray  # (n, N)
    normalizer_: MinMaxNormalizer

    def lift(self, x: np.ndarray) -> np.ndarray:
        """z = lift(x) for physical states x (..., n) -> (..., N)."""
        ...

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """z⁺ for lifted states z (..., N) under normalized inputs v (..., m)."""
        ...

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A (K, N, N), B (K, N, m), d (K, N)) at the K points z (K, N), v (K, m)."""
        ...


@dataclass(frozen=True)
class StepInfo:
    """What a controller did in one ``act``, beside the input it returns.

    ``predicted_states`` (Np, n): the physical states its model predicts over the horizon under
    the plan (Np = 0 for a controller without a model); ``planned_inputs`` (Nc, m): the plan
    itself in physical units; ``solve_path``: which solver answered (DE-MPC: unconstrained,
    active_set, piqp, failed); ``fallback``: the solve failed and a previous plan's move was
    applied instead; ``follows_path``: the step steered by the run's path (lateral and heading
    error), not by the reference's states.
    """

    predicted_states: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    planned_inputs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    solve_path: str = "n/a"
    fallback: bool = False
    follows_path: bool = False


@runtime_checkable
class Controller(Protocol):
    """A feedback law on the plant: ``reset(reference)`` before a run, then ``act`` every step.

    A run on a course also hands the controller the path to follow and, every step, the car's
    pose: a path-following controller steers by them, a state-tracking one ignores them.
    """

    def reset(self, reference: np.ndarray, *, path: ReferencePath | None = None) -> None:
        """Start a run tracking ``reference``: (T, n) physical states at the control period;
        ``path``: the line those states drive along, where the run has one."""
        ...

    def act(
        self, x: np.ndarray, t: float, *, pose: np.ndarray | None = None
    ) -> tuple[np.ndarray, StepInfo]:
        """The input u for measured state x at time t (s), and what the controller did;
        ``pose``: (X, Y, yaw) in the world frame (m, m, rad), where the run has a path."""
        ...


@runtime_checkable
class RealTimeIteration(Protocol):
    """A controller whose step has two phases (acados's real-time iteration): ``prepare()``,
    everything that does not need the next measurement, run before it arrives; then ``act``,
    the feedback phase from the measurement to the input (``tracking.solve_time_ms``)."""

    def prepare(self) -> None:
        """Build the next step's problem before its measurement."""
        ...
