"""The contracts of the harness, each written down once: a plant, a learner, the models a
controller reads, a controller, a reference.

Everything that steps a car (data collection, characterization, closed-loop tracking) is typed
against :class:`Plant`; every learner implements :class:`Learner`, and what a run asks of it
besides, :class:`RunLearner` (``learners.base.Learner`` is the ABC that does both); every MPC
reads a :class:`Model`, which *declares* its dynamics (``linear``, ``bilinear`` or
``nonlinear``) rather than being told apart by ``isinstance`` order:
:class:`LiftedModel`, :class:`BilinearModel` and :class:`LinearizableModel` are what each kind
adds; every rollout drives a :class:`Controller`, whose ``act`` returns the input *and* a
:class:`StepInfo`, so no caller ever probes a controller for attributes; every tracking target
is a :class:`Reference`.

States and inputs are the paper's, in the harness's units:

- x = (vx, vy, yaw_rate) in m/s, m/s, rad/s (the centre of gravity in the yaw frame);
- u = (steer_wheel_deg, pedal): steering-wheel angle in degrees; pedal >= 0 is throttle in
  [0, 0.2], pedal < 0 is brake master-cylinder pressure in -MPa.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Protocol, Self, runtime_checkable

import numpy as np

from harness.core.names import INPUT_NAMES as INPUT_NAMES  # re-exported: the contracts name them
from harness.core.names import STATE_NAMES as STATE_NAMES

if TYPE_CHECKING:  # episode.py imports the plant's limits; the contracts import nothing heavy
    from harness.core.episode import Episode, InputChannel, MinMaxNormalizer
    from harness.core.reference_path import ReferencePath

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


Dynamics = Literal["linear", "bilinear", "nonlinear"]
DYNAMICS: tuple[Dynamics, ...] = ("linear", "bilinear", "nonlinear")


@runtime_checkable
class Learner(Protocol):
    """A model of x⁺ = f(x, u) fitted on episodes (``learners.base.Learner`` implements it)."""

    normalizer_: MinMaxNormalizer  # the min-max scaling of the data it was fitted on

    def fit(
        self, train: Sequence[Episode], validation: Sequence[Episode], normalizer: MinMaxNormalizer
    ) -> Self:
        """Fit on ``train`` (``validation`` to choose and stop where it applies); return self.
        Data in, fitted attributes out: no files, recordings or figures (the caller's)."""
        ...

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """Open-loop rollout in physical units: x0 (..., n), inputs (..., T, m) -> states
        (..., T + 1, n), row 0 being ``x0``."""
        ...

    def save(self, path: str | Path, provenance: Mapping[str, Any] | None = None) -> Path:
        """Write the fitted model to one file (``learners.load`` reads it back); ``provenance``
        says what it was trained on. A diverged fit is refused in one line, never saved."""
        ...

    @property
    def fit_summary(self) -> dict[str, Any]:
        """What the fit chose that its settings do not say (``training.fit``), JSON-ready."""
        ...


class Refusals(Protocol):
    """What a learner refuses before any data is read, each in one line naming the key."""

    def check_size(self, episode_frames: int, n: int = 3, m: int = 2) -> None:
        """Sizes whose fit on episodes of up to ``episode_frames`` frames (n states, m inputs)
        cannot fit in this machine's memory."""
        ...

    def check_inputs(self, channels: Sequence[InputChannel]) -> None:
        """Inputs (names and declared roles, in order) it cannot be fitted on."""
        ...


class Described(Protocol):
    """What a run reports of its learner besides its predictions."""

    provenance_: Mapping[str, Any]  # what a loaded model was trained on (empty: fitted here)

    @property
    def name(self) -> str:
        """Its config-group name (``learner=<name>``), in messages and file names."""
        ...

    @property
    def hyperparameters(self) -> dict[str, Any]:
        """The settings it was built with, as its config holds them."""
        ...

    @property
    def redraws_random_layer(self) -> bool:
        """Whether each prediction draws a fresh random layer (the paper's robustness test)."""
        ...


class RunLearner(Learner, Refusals, Described, Protocol):
    """The learner a run drives: fitted (or loaded), checked before any data, and reported
    (``learners.base.Learner`` implements it)."""

    @property
    def core(self) -> RunLearner:
        """The learner that trains and holds the state matrices: itself, or a wrapper's inner
        one; a run reports its loss curves and spectrum."""
        ...


@runtime_checkable
class Model(Protocol):
    """What every model a controller reads has, in lifted coordinates z = lift(x): its declared
    dynamics, the output map x_norm = C_ z, and the normalizer of its units.

    v = normalizer_.inputs(u) and x = normalizer_.states_inverse(C_ z): a model lives in the
    min-max normalized units of the data it was fitted on.
    """

    dynamics: ClassVar[Dynamics]  # which of the three below it is: a controller reads this
    C_: np.ndarray  # (n, N)
    normalizer_: MinMaxNormalizer

    def lift(self, x: np.ndarray) -> np.ndarray:
        """z = lift(x) for physical states x (..., n) -> (..., N)."""
        ...


@runtime_checkable
class LiftedModel(Model, Protocol):
    """``dynamics = "linear"``: a fitted Koopman model z⁺ = A_ z + B_ v (paper eqs. 9-12)."""

    A_: np.ndarray  # (N, N)
    B_: np.ndarray  # (N, m)


@runtime_checkable
class BilinearModel(LiftedModel, Protocol):
    """``dynamics = "bilinear"``: the input also multiplies the lifted state::

        z⁺ = A_ z + B_ v + Σⱼ (vⱼ − v0_ⱼ) H_[j] z,   v0_ = normalizer_.inputs(0)

    It has every member of :class:`LiftedModel`, but an MPC that read only ``A_`` and ``B_``
    would silently drop ``H_``: its declared dynamics, not its members, say which it is.
    """

    H_: np.ndarray  # (m, N, N)
    v0_: np.ndarray  # (m,)


@runtime_checkable
class LinearizableModel(Model, Protocol):
    """``dynamics = "nonlinear"``: a step that is nonlinear but differentiable::

        z⁺ = step(z, v),   linearised as  z⁺ ≈ A_k z + B_k v + d_k

    what a time-varying MPC needs: ``linearize`` gives, at each point (z̄_k, v̄_k) of a
    trajectory, the Jacobians A_k = ∂step/∂z, B_k = ∂step/∂v and d_k = step(z̄_k, v̄_k) − A_k z̄_k
    − B_k v̄_k. Units as :class:`Model`'s (normalized v).
    """

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """z⁺ for lifted states z (..., N) under normalized inputs v (..., m)."""
        ...

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A (K, N, N), B (K, N, m), d (K, N)) at the K points z (K, N), v (K, m)."""
        ...


_MEMBERS: dict[str, type] = {
    "linear": LiftedModel,
    "bilinear": BilinearModel,
    "nonlinear": LinearizableModel,
}


def dynamics_of(model: object) -> Dynamics | None:
    """The dynamics ``model`` declares, checked against its members; None when it is no model a
    controller can read (it declares none, e.g. persistence).

    Raises:
        ValueError: (one line) when it declares dynamics it does not have the members of.
    """
    declared = getattr(type(model), "dynamics", None)
    if declared is None:
        return None
    if declared not in _MEMBERS:
        raise ValueError(
            f"{type(model).__name__}.dynamics is {declared!r}; a model declares one of {DYNAMICS}"
        )
    if not isinstance(model, _MEMBERS[declared]):
        raise ValueError(
            f"{type(model).__name__} declares {declared} dynamics but lacks a member of "
            f"{_MEMBERS[declared].__name__} (is it fitted?)"
        )
    return declared


@dataclass(frozen=True)
class StepInfo:
    """What a controller did in one ``act``, beside the input it returns.

    ``predicted_states`` (Np, n): the physical states its model predicts over the horizon under
    the plan (Np = 0 for a controller without a model); ``planned_inputs`` (Nc, m): the plan
    itself in physical units; ``solve_path``: which solver answered (DE-MPC: unconstrained,
    active_set, piqp, failed); ``fallback``: the solve failed and a previous plan's move was
    applied instead; ``follows_path``: the step steered by the run's path (lateral and heading
    error), not by the reference's states; ``input_ready_s``: ``time.perf_counter()`` when the
    input was ready, if the controller says (what ``act`` did after it, such as converting the
    horizon above for the record, is work of the period after the input is sent, not latency
    from the measurement to the input).
    """

    predicted_states: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    planned_inputs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    solve_path: str = "n/a"
    fallback: bool = False
    follows_path: bool = False
    input_ready_s: float | None = None


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


@runtime_checkable
class RateLimited(Protocol):
    """A controller whose input increments are bounded (``tracking…quality``'s share at it)."""

    def increment_shares(self, inputs: np.ndarray) -> np.ndarray:
        """(T - 1, m) each step's change of each of ``inputs`` (T, m) as a share of its bound."""
        ...


@runtime_checkable
class Reference(Protocol):
    """A tracking target (``conf/reference/``): its label in the metrics, and its states."""

    def label(self, name: str, episodes: Sequence[Episode]) -> str:
        """The key of its run under ``tracking.references`` (``name`` is its config key)."""
        ...

    def build(self, dt: float, episodes: Sequence[Episode]) -> np.ndarray:
        """(T, n) physical states at the plant's step ``dt``, from the test drives."""
        ...
