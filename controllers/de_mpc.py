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
- the slack ε is relative to each limit: |Δv| <= Δv_max·(1 + ε) (see ``condensed_qp``).
"""

from __future__ import annotations

import logging
import time
from typing import Protocol

import numpy as np

from controllers.condensed_qp import CondensedQP, QPSolution
from harness.data.episode import MinMaxNormalizer
from harness.plant.sedan import BRAKE_MAX_MPA, STEER_WHEEL_LIMIT_DEG, THROTTLE_MAX

log = logging.getLogger(__name__)

STATES, INPUTS = 3, 2


class KoopmanModel(Protocol):
    """What DE-MPC needs from a learner: z⁺ = A_ z + B_ v, x_norm = C_ z, and the lift."""

    A_: np.ndarray  # (N, N)
    B_: np.ndarray  # (N, m)
    C_: np.ndarray  # (n, N), to normalized physical state
    normalizer_: MinMaxNormalizer

    def lift(self, x_physical: np.ndarray) -> np.ndarray: ...


class DEMPC:
    """Koopman MPC with PIQP; ``reset(reference)`` then ``act(x, t) -> u`` every 10 ms.

    Keys are ``conf/controller/de_mpc.yaml``; the fitted model is given at run time. Limits are
    physical: steering-wheel angle in degrees, pedal >= 0 throttle, pedal < 0 brake in -MPa;
    increments are per control step.
    """

    def __init__(
        self,
        model: KoopmanModel,
        *,
        Np: int = 10,  # noqa: N803
        Nc: int = 7,  # noqa: N803
        Q: float | list = 1000.0,  # noqa: N803
        R: float | list = 5.0,  # noqa: N803
        rho: float = 10.0,
        steer_wheel_min_deg: float = -STEER_WHEEL_LIMIT_DEG,
        steer_wheel_max_deg: float = STEER_WHEEL_LIMIT_DEG,
        pedal_min: float = -BRAKE_MAX_MPA,
        pedal_max: float = THROTTLE_MAX,
        steer_wheel_increment_deg: float = 2.25,
        throttle_increment: float = 0.004,
        brake_increment_mpa: float = 0.18,
        dt: float = 0.01,
        tol: float = 1e-6,
        max_iter: int = 100,
        active_set: bool = True,
    ) -> None:
        _check_horizons(Np, Nc)
        weights = {"Q": _weight("Q", Q, STATES), "R": _weight("R", R, INPUTS)}
        _check_positive(
            rho=rho,
            steer_wheel_increment_deg=steer_wheel_increment_deg,
            throttle_increment=throttle_increment,
            brake_increment_mpa=brake_increment_mpa,
            dt=dt,
            tol=tol,
            max_iter=max_iter,
        )
        _check_range("steer_wheel", steer_wheel_min_deg, steer_wheel_max_deg, "_deg")
        _check_range("pedal", pedal_min, pedal_max, "")
        self.model = model
        self.Np, self.Nc, self.dt = int(Np), int(Nc), float(dt)
        A, B, C = _check_model(model)  # noqa: N806
        self.normalizer: MinMaxNormalizer = model.normalizer_
        to_v = self.normalizer.inputs
        self.u_min = np.array([steer_wheel_min_deg, pedal_min])
        self.u_max = np.array([steer_wheel_max_deg, pedal_max])
        origin = to_v(np.zeros(INPUTS))
        pedal_step = min(throttle_increment / THROTTLE_MAX, brake_increment_mpa / BRAKE_MAX_MPA)
        dv_max = np.array(
            [
                to_v(np.array([steer_wheel_increment_deg, 0.0]))[0] - origin[0],
                to_v(np.array([0.0, pedal_step * THROTTLE_MAX]))[1] - origin[1],
            ]
        )
        self.qp = CondensedQP(
            A,
            B,
            C,
            Np=self.Np,
            Nc=self.Nc,
            Q=weights["Q"],
            R=weights["R"],
            rho=rho,
            v_min=to_v(self.u_min),
            v_max=to_v(self.u_max),
            dv_max=dv_max,
            tol=tol,
            max_iter=max_iter,
            active_set=active_set,
        )
        self.solver_failures = 0
        self.solve_time_s = float("nan")
        self.last: QPSolution | None = None
        self._reference: np.ndarray | None = None
        self.reset()

    def reset(self, reference: np.ndarray | None = None, u_prev: np.ndarray | None = None) -> None:
        """Start a run tracking ``reference`` ((T, 3) physical states at ``dt``) from u_prev.

        The paper starts from u = 0 (wheel straight, no pedal); ``reference`` is kept when None.
        """
        if reference is not None:
            reference = np.asarray(reference, dtype=float)
            if reference.ndim != 2 or reference.shape[1] != STATES or len(reference) < 2:
                raise ValueError(f"reference must be (T >= 2, 3) states, got {reference.shape}")
            normalized = self.normalizer.states(reference)
            # Beyond its end the reference holds its last sample.
            tail = np.repeat(normalized[-1:], self.Np + 1, axis=0)
            self._reference = np.ascontiguousarray(np.vstack([normalized, tail]))
            self._reference_steps = len(reference)
        u = np.zeros(INPUTS) if u_prev is None else np.asarray(u_prev, dtype=float)
        self._v_prev = self.normalizer.inputs(np.clip(u, self.u_min, self.u_max))
        self._plan: np.ndarray | None = None
        self._plan_step = 0
        self._z = None
        self._dv = np.zeros((self.Nc, INPUTS))
        self._v_before = self._v_prev
        self.solver_failures = 0
        self.last = None
        self.qp.reset()

    def act(self, x: np.ndarray, t: float) -> np.ndarray:
        """Input (steer_wheel_deg, pedal) for measured state ``x`` at time ``t`` (s)."""
        if self._reference is None:
            raise ValueError("DEMPC.reset(reference) must be called before act()")
        start = time.perf_counter()
        k = min(round(t / self.dt), self._reference_steps - 1)
        z = np.asarray(self.model.lift(np.asarray(x, dtype=float)), dtype=float)
        y_ref = self._reference[k + 1 : k + 1 + self.Np].ravel()
        v_prev = self._v_prev
        solution = self.qp.solve(z, v_prev, y_ref)
        if solution.ok:
            self._plan = v_prev + np.cumsum(solution.dv, axis=0)
            self._plan_step = 1
            v = self._plan[0]
            self._dv = solution.dv
        else:
            v = self._fallback(v_prev)
            log.warning(
                "DE-MPC solve failed at t = %.2f s (%s); applying the previous plan's next move",
                t,
                solution.status,
            )
        u = np.clip(self.normalizer.inputs_inverse(v), self.u_min, self.u_max)
        self._z, self._v_before, self._v_prev, self.last = z, v_prev, v, solution
        self.solve_time_s = time.perf_counter() - start
        return u

    def _fallback(self, v_prev: np.ndarray) -> np.ndarray:
        """The previous plan's next move (held at its end); the last input if there is none."""
        self.solver_failures += 1
        if self._plan is None:
            self._dv = np.zeros((self.Nc, INPUTS))
            return v_prev
        rest = self._plan[min(self._plan_step, self.Nc - 1) :]
        rest = np.vstack([rest, np.repeat(rest[-1:], self.Nc - len(rest), axis=0)])
        self._plan_step += 1
        self._dv = np.diff(np.vstack([v_prev, rest]), axis=0)
        return rest[0]

    @property
    def predicted_states(self) -> np.ndarray:
        """(Np, 3) physical states the model predicts over the horizon of the last ``act``."""
        if self._z is None:
            return np.full((self.Np, STATES), np.nan)
        y = self.qp.predict(self._z, self._v_before, self._dv)
        return self.normalizer.states_inverse(y)


def _check_horizons(Np: int, Nc: int) -> None:  # noqa: N803
    for key, value in (("Np", Np), ("Nc", Nc)):
        if int(value) != value or value < 1:
            raise ValueError(f"controller.{key} must be a positive integer (got {value})")
    if Nc > Np:
        raise ValueError(f"controller.Nc ({Nc}) must be <= controller.Np ({Np})")


def _weight(key: str, value: float | list, size: int) -> np.ndarray:
    """A scalar (times I), a diagonal or a full symmetric positive-definite matrix."""
    array = np.asarray(value, dtype=float)
    if array.ndim == 0:
        array = array * np.eye(size)
    elif array.ndim == 1 and array.shape == (size,):
        array = np.diag(array)
    if array.shape != (size, size):
        raise ValueError(
            f"controller.{key} must be a scalar, {size} diagonal entries or a {size}x{size} "
            f"matrix (got shape {np.shape(value)})"
        )
    if not np.allclose(array, array.T) or not np.all(np.isfinite(array)):
        raise ValueError(f"controller.{key} must be symmetric and finite")
    smallest = float(np.linalg.eigvalsh(array).min())
    if smallest <= 0:
        raise ValueError(
            f"controller.{key} must be positive definite (smallest eigenvalue {smallest:g})"
        )
    return array


def _check_positive(**values: float) -> None:
    for key, value in values.items():
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"controller.{key} must be > 0 (got {value})")


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


def _check_model(model: KoopmanModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The contract, checked once: shapes agree and lift returns the lifted dimension."""
    for name in ("A_", "B_", "C_", "normalizer_"):
        if not hasattr(model, name):
            raise ValueError(f"model has no {name}: is it fitted, and a lifted-linear learner?")
    A, B, C = (np.asarray(getattr(model, k), dtype=float) for k in ("A_", "B_", "C_"))  # noqa: N806
    size = A.shape[0] if A.ndim == 2 else -1
    for name, array, shape in (
        ("A_", A, (size, size)),
        ("B_", B, (size, INPUTS)),
        ("C_", C, (STATES, size)),
    ):
        if array.shape != shape or not np.all(np.isfinite(array)):
            raise ValueError(f"model.{name} must be finite with shape {shape}, got {array.shape}")
    lifted = np.asarray(model.lift(np.asarray(model.normalizer_.state_min, dtype=float)))
    if lifted.shape != (size,):
        raise ValueError(f"model.lift(x) must return shape ({size},), got {lifted.shape}")
    return A, B, C
