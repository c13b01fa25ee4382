"""PIQP on the condensed QP written in absolute inputs: the solver of record and the last resort.

With ΔV = D V - E v_{t-1} (D the block difference matrix) the decision variables become
x_V = [V; ε]: the hard input bounds are then PIQP's box bounds and only the increment rows
stay general rows (two-sided, in fractions of each rate limit), the fastest layout measured.
Every answer of the faster paths is the optimum PIQP finds, to ``tol``.
"""

from __future__ import annotations

import numpy as np
import piqp


class PIQPSolver:
    """PIQP's dense workspace for one condensed QP.

    Args:
        inputs, Nc: m inputs per step and the control horizon (x = [ΔV; ε], M = m Nc + 1).
        inv_rate: (M,) 1/Δv_max of each increment.
        v_min, v_max: (m,) hard input bounds.
        tol: PIQP's absolute and duality-gap tolerance.
        max_iter: its iteration limit, the time limit of a solve.
        P: the QP's Hessian when it never changes (P_V built now); None for a time-varying QP,
            whose P_V is built when PIQP is first asked after each :meth:`new_hessian`.
    """

    def __init__(
        self,
        inputs: int,
        Nc: int,
        inv_rate: np.ndarray,
        v_min: np.ndarray,
        v_max: np.ndarray,
        tol: float,
        max_iter: int,
        P: np.ndarray | None,
    ) -> None:
        m, M = inputs, inputs * Nc
        self.m, self.Nc, self.inv_rate = m, Nc, inv_rate
        difference = np.eye(M) - np.eye(M, k=-m)
        T = np.zeros((M + 1, M + 1))
        T[:M, :M], T[M, M] = difference, 1.0
        self.T = T
        self._hessian_ready = P is not None
        if P is not None:
            self.P_V = np.asfortranarray(T.T @ P @ T)
        rate = inv_rate[:, None] * difference
        ones = np.ones((M, 1))
        # Upper rows  ΔV/Δv_max - ε <= 1, lower rows  ΔV/Δv_max + ε >= -1 (one-sided each).
        self.G_V = np.asfortranarray(np.vstack([np.hstack([rate, -ones]), np.hstack([rate, ones])]))
        self.x_l = np.concatenate([np.tile(v_min, Nc), [0.0]])
        self.x_u = np.concatenate([np.tile(v_max, Nc), [np.inf]])
        self.h_l = np.concatenate([np.full(M, -np.inf), -np.ones(M)])
        self.h_u = np.concatenate([np.ones(M), np.full(M, np.inf)])
        solver = piqp.DenseSolver()
        settings = solver.settings
        settings.eps_abs = tol
        settings.eps_duality_gap_abs = tol
        settings.max_iter = max_iter
        settings.preconditioner_reuse_on_update = P is not None  # P changes every step if not
        self._solver = solver
        self._ready = False
        self._new_hessian = False  # a time-varying model's P changes every step
        self._bounds_new = False  # set_input_bounds moved the box since PIQP's last solve

    def new_hessian(self) -> None:
        """The QP's P changed: P_V is built again when PIQP is next asked."""
        self._hessian_ready = False

    def set_input_bounds(self, v_min: np.ndarray, v_max: np.ndarray) -> None:
        """This step's hard input bounds (m,): only PIQP's box moves."""
        M = self.m * self.Nc
        self.x_l[:M] = np.tile(v_min, self.Nc)
        self.x_u[:M] = np.tile(v_max, self.Nc)
        self._bounds_new = True

    def solve(
        self, c: np.ndarray, P: np.ndarray, v_prev: np.ndarray
    ) -> tuple[np.ndarray | None, int, piqp.Status]:
        """(x in the condensed QP's variables [ΔV; ε] or None, iterations, PIQP's status) of
        min ½xᵀPx + cᵀx under the QP's rows, with the last input ``v_prev``."""
        M = self.m * self.Nc
        # x = T x_V + t0 with t0 = [-E v_prev; 0]: c_V = Tᵀ (c + P t0).
        c_v = self.T.T @ (c - P[:, : self.m] @ v_prev)
        shift = np.zeros(M)
        shift[: self.m] = v_prev * self.inv_rate[: self.m]
        h_l = self.h_l.copy()
        h_u = self.h_u.copy()
        h_u[:M] += shift
        h_l[M:] += shift
        if not self._hessian_ready:
            self.P_V = np.asfortranarray(self.T.T @ P @ self.T)
            self._new_hessian = True
            self._hessian_ready = True
        solver = self._solver
        check_shapes(self.P_V, c_v, self.G_V, h_l, h_u, self.x_l, self.x_u)
        if not self._ready:
            self._bounds_new = False
            solver.setup(
                P=self.P_V, c=c_v, G=self.G_V, h_l=h_l, h_u=h_u, x_l=self.x_l, x_u=self.x_u
            )
            self._ready = True
        elif self._new_hessian:
            solver.update(P=self.P_V, c=c_v, h_l=h_l, h_u=h_u, **self._box())
        else:
            solver.update(c=c_v, h_l=h_l, h_u=h_u, **self._box())
        self._new_hessian = False
        status = solver.solve()
        iterations = int(solver.result.info.iter)
        if status != piqp.PIQP_SOLVED:
            return None, iterations, status
        x = self.T @ solver.result.x
        x[: self.m] -= v_prev
        return x, iterations, status

    def _box(self) -> dict[str, np.ndarray]:
        """PIQP's input box for ``update`` when set_input_bounds moved it, else nothing (an
        unchanged problem stays bit for bit the one set up)."""
        if not self._bounds_new:
            return {}
        self._bounds_new = False
        return {"x_l": self.x_l, "x_u": self.x_u}


def check_shapes(
    P: np.ndarray,
    c: np.ndarray,
    G: np.ndarray,
    h_l: np.ndarray,
    h_u: np.ndarray,
    x_l: np.ndarray,
    x_u: np.ndarray,
) -> None:
    """PIQP 0.7 warns and then segfaults in solve() on mismatched sizes: refuse them here."""
    n = c.shape[0]
    expected = {
        "P": (P.shape, (n, n)),
        "G": (G.shape, (h_l.shape[0], n)),
        "h_u": (h_u.shape, h_l.shape),
        "x_l": (x_l.shape, (n,)),
        "x_u": (x_u.shape, (n,)),
    }
    for name, (got, want) in expected.items():
        if got != want:
            raise RuntimeError(f"PIQP problem data {name} has shape {got}, expected {want}")
    if not (P.flags.f_contiguous and G.flags.f_contiguous):
        raise RuntimeError("PIQP dense problem matrices must be Fortran-ordered")
