"""What the mathematics guarantees about a DE-MPC QP's answer, for tests on any CPU.

The condensed QP (eq. 20) is ``min ½ xᵀPx + cᵀx  s.t.  G x <= b`` in ``x = [ΔV; ε]``, with P
positive definite: its optimum is unique, and a point is that optimum if and only if it meets the
KKT conditions. So a solver's answer is checked by its KKT residuals, at a tolerance scaled to
the problem, never by another solver pushed near machine precision: how close a solver gets to
1e-11 depends on BLAS threads, kernels and instruction set, and a test of that tests the CPU.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from controllers.condensed_qp import CondensedQP, QPSolution

# Relative KKT residuals. The solvers promise their tol = 1e-6 (CondensedQP's default): an active
# set's answer (DAQP, ours, the unconstrained optimum) is exact up to rounding (5e-11 measured on
# every QP of the tests), so the promise itself is the bound. An interior point (PIQP) measures
# its tolerance in its own scaled variables and stops strictly inside (2e-8 measured), hence ten
# times looser. A wrong answer, one increment off by 1e-3 of the plan, leaves 1.3e-4 and more.
KKT_TOL = 1e-6
PIQP_KKT_TOL = 1e-5


@dataclass(frozen=True)
class KKT:
    """Relative KKT residuals of a point: all three near zero if and only if it is the optimum."""

    stationarity: (
        float  # ||Px + c + Gᵀλ||∞ / max(1, ||c||∞, ||P||∞||x||∞), λ >= 0 best on active rows
    )
    primal: float  # max(Gx - b)+ / (1 + ||b||∞)
    complementarity: float  # max |λ_i (Gx - b)_i| / scale

    def holds(self, tol: float = KKT_TOL) -> bool:
        return max(self.stationarity, self.primal, self.complementarity) <= tol


def qp_data(
    qp: CondensedQP, z: np.ndarray, v_prev: np.ndarray, y_ref: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(P, c, G, b) of the step's QP, c built from the prediction matrices, not from the solver:
    J = ||Θ ΔV + e||²_Q + ||ΔV||²_R + ρε² with e the free response's error, so c = [2ΘᵀQe; 0]."""
    M = qp.m * qp.Nc
    error = (qp.free_response(z, v_prev) - y_ref).reshape(qp.Np, qp.n)
    c = np.zeros(M + 1)
    c[:M] = 2 * qp.theta.T @ (error @ qp.Q.T).ravel()
    b = -qp.residual(np.zeros(M + 1), v_prev)
    return np.asarray(qp.P), c, qp.G, b


def kkt(P: np.ndarray, c: np.ndarray, G: np.ndarray, b: np.ndarray, x: np.ndarray) -> KKT:
    """The KKT residuals of ``x``: multipliers by non-negative least squares on the rows that are
    active at x, the others' multipliers zero. "Active" reaches 1e-4 inside: an interior point
    stops short of its active rows, and a row given a multiplier it should not have is caught by
    the complementarity residual."""
    residual = G @ x - b
    gradient = P @ x + c
    # The backward-error scale of Px + c: what rounding and a solver's tolerance are relative to.
    scale = max(1.0, float(np.abs(c).max()), float(np.abs(P).sum(1).max() * np.abs(x).max()))
    active = residual > -1e-4 * (1.0 + np.abs(b))
    multipliers = np.zeros(len(b))
    if active.any():
        multipliers[active] = nnls(G[active].T, -gradient, maxiter=50 * len(x))[0]
    return KKT(
        stationarity=float(np.abs(gradient + G.T @ multipliers).max()) / scale,
        primal=max(0.0, float(residual.max())) / (1.0 + float(np.abs(b).max())),
        complementarity=float(np.abs(multipliers * residual).max()) / scale,
    )


def solution_kkt(
    qp: CondensedQP, z: np.ndarray, v_prev: np.ndarray, y_ref: np.ndarray, solution: QPSolution
) -> KKT:
    """KKT residuals of a solve's answer, after checking that the solve says it solved."""
    assert solution.ok, (
        f"the {solution.path} solve ended with status {solution.status!r} after "
        f"{solution.iterations} iterations: there is no answer to check"
    )
    x = np.append(np.ravel(solution.dv), solution.slack)
    return kkt(*qp_data(qp, z, v_prev, y_ref), x)


def assert_optimal(
    qp: CondensedQP, z: np.ndarray, v_prev: np.ndarray, y_ref: np.ndarray, solution: QPSolution
) -> None:
    """The answer solved and meets the KKT conditions of the step's QP."""
    residuals = solution_kkt(qp, z, v_prev, y_ref, solution)
    assert residuals.holds(), f"{solution.path} answer is not optimal: {residuals}"
