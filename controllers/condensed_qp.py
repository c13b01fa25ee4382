"""The condensed DE-MPC quadratic program (paper eq. 19-20) and the order of its solve paths.

Decision variables x = [ΔV; ε]: the input increments over the control horizon (Nc·m, in
normalized input units; ΔV = 0 from Nc to Np) and one slack ε. With y_i = C z_{t+i},

    Y = Φz z_t + Φv v_{t-1} + Θ ΔV                                          (eq. 18)
    J = ||Y - Y_ref||²_Q + ||ΔV||²_R + ρ ε²  =  ½ xᵀPx + cᵀx + eᵀQe          (eq. 20)

with P = 2·diag(ΘᵀQΘ + R, ρ), c = 2[ΘᵀQe; 0], e = Φz z + Φv v - Y_ref. Constraints, as rows
Gx <= b of this module (scaled so every rate row reads in fractions of its limit):

    ±Δv_k / Δv_max - ε <= 1            increments, softened by ε (paper: 1_m ε, see below)
    ±(v_{t-1} + Σ_{j<=k} Δv_j) <= ±v_max/min   hard input bounds
    -ε <= 0

The paper adds ε·1_m to the increment bounds. Its inputs have mixed units (deg, throttle, MPa),
so one unit of ε means very different things per channel; here ε is relative to each channel's
own limit (|Δv_k| <= Δv_max·(1 + ε)), so ρ prices "exceed every rate limit by 100 %" the same
for steering and pedal. ε = 0 exactly when no rate limit binds.

Everything that does not depend on (z_t, v_{t-1}, Y_ref) is built once per model. Per step,
:meth:`CondensedQP.solve` tries, fastest first, each path returning the QP's exact optimum:

1. the unconstrained optimum x_u = -P⁻¹c (one matrix-vector product); it is the QP's solution
   whenever it satisfies every row;
2. an active-set solver, started from the last step's active set (``qp_solver``):
   ``daqp`` (DAQP, a dual active-set solver in C, on the QP's least-distance form:
   ``controllers/daqp_solver.py``) or ``active_set`` (ours, Lawson-Hanson on the dual:
   ``controllers/active_set.py``). Either answer is accepted only at a KKT point to ``tol``:
   every row satisfied, multipliers >= 0 and their rows active, i.e. the optimum;
3. PIQP (dense), on the same problem written in absolute inputs (``controllers/piqp_solver.py``),
   whenever 2 gives up. PIQP is the solver of record: every answer above is the optimum PIQP
   finds, to ``tol``.

This module holds the QP itself (its matrices, built once per model or per step for a
time-varying one) and the order of the paths; each solver keeps its own workspace.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NotRequired, TypedDict, Unpack

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from controllers.active_set import HotActiveSet, dense_dual
from controllers.condensing import (
    block_cumulative,
    block_diagonal,
)
from controllers.daqp_solver import DAQPSolver
from controllers.piqp_solver import PIQPSolver

PATHS = ("unconstrained", "active_set", "daqp", "piqp", "failed")
# The active-set solver tried before PIQP: DAQP (default: the bounded worst case, measured in
# docs/findings/real_time.md) or ours (Lawson-Hanson on the dual, hot-started).
QP_SOLVERS = ("daqp", "active_set")
# Lifts this small (the three-state models) get their free response as one product with maps
# built with the model (``free_response_maps``), not a loop over the horizon at every solve.
SMALL_LIFT = 16
# The status of a solve whose prediction (free response) is not finite: a model that diverges
# from this state. Nothing is optimised; the controller falls back.
PREDICTION_NOT_FINITE = "prediction_not_finite"


@dataclass(frozen=True)
class QPSolution:
    """One solve: the increments, the slack, how it was found and whether to trust it."""

    dv: np.ndarray  # (Nc, m) optimal increments, normalized input units
    slack: float  # ε, relative to the rate limits
    path: str  # one of PATHS
    iterations: int  # active-set factorizations or PIQP iterations (0 for unconstrained)
    status: str  # "solved", or PIQP's status name when it did not solve

    @property
    def ok(self) -> bool:
        return self.status == "solved"


class QPSettings(TypedDict):
    """The keywords of :class:`CondensedQP` (and :class:`TimeVaryingQP`), written once; see
    :class:`CondensedQP` for each."""

    Np: int
    Nc: int
    Q: np.ndarray
    R: np.ndarray
    rho: float
    v_min: np.ndarray
    v_max: np.ndarray
    dv_max: np.ndarray
    tol: NotRequired[float]  # 1e-6
    max_iter: NotRequired[int]  # 100
    active_set: NotRequired[bool]  # True
    active_set_max_iter: NotRequired[int]  # 100
    qp_solver: NotRequired[str]  # "daqp"


class CondensedQP:
    """Prediction matrices, Hessian and dual operator of one model, and the per-step solve.

    Args:
        A, B, C: the lifted model z⁺ = Az + Bv, y = Cz (normalized units).
        Np, Nc: prediction and control horizon (Nc <= Np).
        Q: (n, n) output weight; R: (m, m) increment weight; rho: slack weight.
        v_min, v_max: (m,) hard input bounds; dv_max: (m,) increment limits (> 0).
        tol: feasibility / optimality tolerance of every path.
        max_iter: PIQP iteration limit, the time limit of a solve.
        active_set: try an active-set solver before PIQP.
        active_set_max_iter: factorizations before our active set hands over to PIQP; 100
            bounds a solve at about 4 ms + PIQP, inside the 10 ms period.
        qp_solver: which active-set solver, one of QP_SOLVERS.
    """

    def __init__(
        self, A: np.ndarray, B: np.ndarray, C: np.ndarray, **settings: Unpack[QPSettings]
    ) -> None:
        self._configure(C, B.shape[1], settings)
        self._build_prediction(A, B, C)
        self._build_cost(settings["Q"], settings["R"])
        self._build_constraints()
        self._build_dual()
        self._dual_ready = True  # P never changes
        self._build_piqp(self._max_iter)
        self._daqp.new_hessian(block=self.P[: self._M, : self._M])  # factored when first needed
        self.reset()

    def _configure(self, C: np.ndarray, m: int, settings: QPSettings) -> None:
        """Sizes, limits and solver settings (the defaults of :class:`QPSettings`' optional
        keys): what does not depend on the model's matrices."""
        unknown = sorted(set(settings) - set(QPSettings.__annotations__))
        if unknown:
            raise TypeError(f"{type(self).__name__} got unknown settings {', '.join(unknown)}")
        qp_solver = settings.get("qp_solver", "daqp")
        if qp_solver not in QP_SOLVERS:
            raise ValueError(
                f"qp_solver must be one of {', '.join(QP_SOLVERS)} (got {qp_solver!r})"
            )
        self.n, self.N = C.shape
        self.m = m
        self.Np, self.Nc = settings["Np"], settings["Nc"]
        self.rho, self.tol = float(settings["rho"]), settings.get("tol", 1e-6)
        self.active_set, self.qp_solver = settings.get("active_set", True), qp_solver
        self.active_set_max_iter = settings.get("active_set_max_iter", 100)
        self._max_iter = settings.get("max_iter", 100)
        self.v_min = np.asarray(settings["v_min"], float)
        self.v_max = np.asarray(settings["v_max"], float)
        self.dv_max = np.asarray(settings["dv_max"], float)

    # ---- built once per model -------------------------------------------------------------

    def _build_prediction(self, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> None:
        """Φz, Φv, Θ of eq. (18) from the step responses S_l = Σ_{q<l} A^q B; and Φw, the
        outputs' response to a constant disturbance w added to every step (offset-free)."""
        n, m, N, Np, Nc = self.n, self.m, self.N, self.Np, self.Nc
        power = np.eye(N)
        step = np.zeros((N, m))
        powers = np.zeros((N, N))
        phi_z, phi_w, step_out = [], [], [np.zeros((n, m))]  # C S_0 = 0
        for _ in range(Np):
            step = step + power @ B
            powers = powers + power
            power = A @ power
            phi_z.append(C @ power)
            phi_w.append(C @ powers)
            step_out.append(C @ step)
        self.phi_z = np.vstack(phi_z)  # (n Np, N): y_i from z_t
        self.phi_w = np.vstack(phi_w)  # (n Np, N): y_i from w in z_{k+1} = A z_k + B v_k + w
        self.phi_v = np.vstack(step_out[1:])  # (n Np, m): y_i from holding v_{t-1}
        theta = np.zeros((Np, n, Nc, m))
        for i in range(1, Np + 1):  # y_i depends on Δv_j for j < i through C S_{i-j}
            for j in range(min(i, Nc)):
                theta[i - 1, :, j, :] = step_out[i - j]
        self.theta = theta.reshape(n * Np, m * Nc)

    def _build_cost(self, Q: np.ndarray, R: np.ndarray) -> None:
        n, Np, Nc, M = self.n, self.Np, self.Nc, self.m * self.Nc
        self.Q, self._R = np.asarray(Q, float), np.asarray(R, float)
        q_theta = np.einsum("ab,ibm->iam", self.Q, self.theta.reshape(Np, n, M)).reshape(n * Np, M)
        self._theta_q = np.ascontiguousarray(q_theta.T)  # ΘᵀQ, (M, n Np)
        hessian = self.theta.T @ q_theta + block_diagonal(self._R, Nc)
        self.P = np.zeros((M + 1, M + 1))
        self.P[:M, :M] = 2 * hessian
        self.P[M, M] = 2 * self.rho
        self.P = np.asfortranarray((self.P + self.P.T) / 2)
        # Unconstrained optimum x_u = -P⁻¹c = F [z; v; Y_ref] (ε_u = 0): one product per step.
        gain = cho_solve(cho_factor(self.P[:M, :M]), 2 * q_theta.T)  # P⁻¹·2ΘᵀQ
        self._x_u = np.hstack([-gain @ self.phi_z, -gain @ self.phi_v, gain])

    def _build_constraints(self) -> None:
        """Rows G x <= b (b moves with v_{t-1}): they depend on the limits, never on the model."""
        m, Nc, M = self.m, self.Nc, self.m * self.Nc
        inv_rate = np.tile(1.0 / self.dv_max, Nc)
        cumulative = block_cumulative(Nc, m)
        G = np.zeros((4 * M + 1, M + 1))
        G[:M, :M], G[:M, M] = np.diag(inv_rate), -1.0
        G[M : 2 * M, :M], G[M : 2 * M, M] = -np.diag(inv_rate), -1.0
        G[2 * M : 3 * M, :M] = cumulative
        G[3 * M : 4 * M, :M] = -cumulative
        G[4 * M, M] = -1.0
        self.G, self.rows, self._M = G, G.shape[0], M
        self._inv_rate, self._cumulative = inv_rate, cumulative
        # b = b_0 + S v_{t-1}: only the input rows move with v_{t-1} (-v_{t-1} and +v_{t-1}).
        self._b_upper = np.concatenate(
            [np.ones(2 * M), np.tile(self.v_max, Nc), -np.tile(self.v_min, Nc), [0.0]]
        )
        held = np.tile(np.eye(m), (Nc, 1))  # row k·m + j picks v_{t-1}[j]
        self._b_shift = np.zeros((self.rows, m))
        self._b_shift[2 * M : 3 * M], self._b_shift[3 * M : 4 * M] = -held, held
        self._daqp = DAQPSolver(M, m, self.rows, self._inv_rate, self.rho, self.tol)
        self._active = HotActiveSet(self.rows, self.tol, self.active_set_max_iter)

    def _build_dual(self) -> None:
        """The active set's dual operator K = G P⁻¹ Gᵀ and the rows of P⁻¹Gᵀ (P never changes)."""
        self._active.set_dual(*dense_dual(self.G, self.P))

    def _build_piqp(self, max_iter: int, hessian: bool = True) -> None:
        """PIQP's workspace (``hessian``: P_V now; a time-varying QP builds it when PIQP is
        first asked after each new P)."""
        self._piqp = PIQPSolver(
            self.m,
            self.Nc,
            self._inv_rate,
            self.v_min,
            self.v_max,
            self.tol,
            max_iter,
            self.P if hessian else None,
        )

    # ---- per step ---------------------------------------------------------------------------

    def set_input_bounds(self, v_min: np.ndarray, v_max: np.ndarray) -> None:
        """This step's hard input bounds (m,) (the pedal kept to one side): only b and PIQP's
        box move; the Hessian, G and every factor stay."""
        v_min, v_max = np.asarray(v_min, float), np.asarray(v_max, float)
        if np.array_equal(v_min, self.v_min) and np.array_equal(v_max, self.v_max):
            return
        M = self.m * self.Nc
        self.v_min, self.v_max = v_min, v_max
        self._b_upper[2 * M : 3 * M] = np.tile(v_max, self.Nc)
        self._b_upper[3 * M : 4 * M] = -np.tile(v_min, self.Nc)
        self._piqp.set_input_bounds(v_min, v_max)

    def reset(self) -> None:
        """Forget the previous active set (a new run starts cold)."""
        self._active.guess[:] = False
        self._daqp.reset(build=self.active_set and self.qp_solver == "daqp" and self.has_model())

    def prepare_solvers(self) -> None:
        """Build now what the active-set solver would build at its first constrained solve
        (DAQP's rows G L⁻ᵀ, its workspace): the real-time iteration's preparation, before the
        measurement."""
        if self.active_set and self.qp_solver == "daqp":
            self._daqp.prepare()

    def has_model(self) -> bool:
        """Whether a model's matrices are set: :meth:`predict` needs them, and a time-varying
        QP's placeholder P (none before its first preparation succeeds) is not worth DAQP's
        workspace, since every Θ replaces its rows."""
        return True

    def unconstrained(self, z: np.ndarray, v_prev: np.ndarray, y_ref: np.ndarray) -> np.ndarray:
        """x_u = [ΔV; 0], the minimizer of J without constraints."""
        dv = self._x_u @ np.concatenate([z, v_prev, y_ref])
        return np.append(dv, 0.0)

    def bounds(self, v_prev: np.ndarray) -> np.ndarray:
        """b of the rows G x <= b, which move with the last input v_{t-1}."""
        return self._b_upper + self._b_shift @ v_prev

    def residual(self, x: np.ndarray, v_prev: np.ndarray) -> np.ndarray:
        """G x - b: positive entries are violated rows (one dense product: at 60/50 faster
        than a dozen NumPy calls on G's structure)."""
        return self.G @ x - self.bounds(v_prev)

    def solve(self, z: np.ndarray, v_prev: np.ndarray, y_ref: np.ndarray) -> QPSolution:
        """The QP's optimum for lifted state z, previous input v_prev, references y_ref (n Np,)."""
        x_u = self.unconstrained(z, v_prev, y_ref)
        if not np.isfinite(x_u).all():  # every comparison with NaN is False: refuse it here
            return QPSolution(np.zeros((self.Nc, self.m)), 0.0, "failed", 0, PREDICTION_NOT_FINITE)
        b = self.bounds(v_prev)
        r = self.G @ x_u - b  # the residual, with b kept for DAQP
        if not (r > self.tol).any():
            self._active.guess[:] = False
            return self._solution(x_u, "unconstrained", 0, "solved")
        if self.active_set and self.qp_solver == "daqp":
            answer = self._daqp.solve(x_u, b)
            if answer is not None:
                x, iterations = answer
                return self._solution(x, "daqp", iterations, "solved")
        elif self.active_set:
            if not self._dual_ready:  # a time-varying QP's, built when first needed
                self._build_dual()
                self._dual_ready = True
            found = self._active.solve(x_u, r, lambda x: self.residual(x, v_prev))
            if found is not None:
                x, rows, iterations = found
                self._active.guess[:] = False
                self._active.guess[rows] = True
                return self._solution(x, "active_set", iterations, "solved")
        solution = self.solve_piqp(z, v_prev, y_ref)
        if solution.ok:
            x = np.append(solution.dv.ravel(), solution.slack)
            self._active.guess = self.residual(x, v_prev) > -10 * self.tol
        return solution

    def _solution(self, x: np.ndarray, path: str, iterations: int, status: str) -> QPSolution:
        M = self.m * self.Nc
        return QPSolution(x[:M].reshape(self.Nc, self.m), float(x[M]), path, iterations, status)

    def solve_piqp(self, z: np.ndarray, v_prev: np.ndarray, y_ref: np.ndarray) -> QPSolution:
        """PIQP alone (dense), in absolute inputs: the reference path and the last resort."""
        M = self.m * self.Nc
        e = self.free_response(z, v_prev) - y_ref
        c = np.zeros(M + 1)
        c[:M] = 2 * self._theta_q @ e
        x, iterations, status = self._piqp.solve(c, self.P, v_prev)
        if x is None:
            zeros = np.zeros((self.Nc, self.m))
            return QPSolution(zeros, 0.0, "failed", iterations, status.name)
        return self._solution(x, "piqp", iterations, "solved")

    def free_response(self, z: np.ndarray, v_prev: np.ndarray) -> np.ndarray:
        """(n Np,) outputs y_{t+1..t+Np} with the input held at v_prev (ΔV = 0)."""
        return self.phi_z @ z + self.phi_v @ v_prev

    def predict(self, z: np.ndarray, v_prev: np.ndarray, dv: np.ndarray) -> np.ndarray:
        """(Np, n) predicted outputs y_{t+1..t+Np} under the increments dv (Nc, m)."""
        y = self.phi_z @ z + self.phi_v @ v_prev + self.theta @ np.ravel(dv)
        return y.reshape(self.Np, self.n)

    def cost(
        self, z: np.ndarray, v_prev: np.ndarray, y_ref: np.ndarray, dv: np.ndarray, slack: float
    ) -> float:
        """J of eq. (20), constant included: ||Y - Y_ref||²_Q + ||ΔV||²_R + ρε²."""
        error = (self.predict(z, v_prev, dv).ravel() - y_ref).reshape(self.Np, self.n)
        dv = np.reshape(dv, (self.Nc, self.m))
        tracking = np.einsum("ia,ab,ib->", error, self.Q, error)
        return float(tracking + np.einsum("ia,ab,ib->", dv, self._R, dv) + self.rho * slack**2)
