"""DAQP on the condensed QP's least-distance form: the active-set path tried before PIQP.

With P = LLᵀ and y = Lᵀx the QP min ½xᵀPx + cᵀx s.t. Gx <= b becomes

    min ½‖y‖² + fᵀy  s.t.  (G L⁻ᵀ) y <= b,   f = L⁻¹c = -Lᵀx_u,

so DAQP's own factorization of the Hessian is trivial (the identity), and a new P (a
time-varying model, every step) costs one triangular inverse and the rows G L⁻ᵀ, built from
G's structure (:meth:`DAQPSolver._build_rows`), not DAQP's O(rows·n²) refactorization
(``update(H=...)``: 1 ms at 60/50, against 0.3 ms here). An answer is accepted only at a KKT
point to ``tol``; otherwise :meth:`DAQPSolver.solve` says None and the QP's next path runs.
"""

from __future__ import annotations

import daqp
import numpy as np
from scipy.linalg.blas import dtrmv
from scipy.linalg.lapack import dpotrf, dtrtri, dtrtrs

# DAQP's exit flag for an optimum (1); 2 (soft optimum) cannot happen without soft rows.
DAQP_OPTIMAL = 1


class DAQPSolver:
    """One QP's DAQP workspace, warm from its last working set.

    Args:
        increments: M = m·Nc, the increments in x = [ΔV; ε].
        inputs: m, the inputs per step.
        rows: the rows of G x <= b (rate rows, input rows, ε's row, in the QP's order).
        inv_rate: (M,) 1/Δv_max of each increment (the rate rows' scale).
        rho: the slack's weight (ε's entry of P is 2ρ).
        tol: the KKT tolerance an answer must meet.
    """

    def __init__(
        self,
        increments: int,
        inputs: int,
        rows: int,
        inv_rate: np.ndarray,
        rho: float,
        tol: float,
    ) -> None:
        self.M, self.m, self.rows = increments, inputs, rows
        self.inv_rate, self.rho, self.tol = inv_rate, rho, tol
        self.model: daqp.Model | None = None  # set up at its first solve, warm from then on
        self.factor: np.ndarray | None = None  # L of P's first M rows
        self._hessian: np.ndarray | None = None  # P's first M rows, factored when first needed
        self._rows_ready = False
        self._rows_new = False  # rows built that DAQP has not received yet

    def new_hessian(
        self, block: np.ndarray | None = None, factor: np.ndarray | None = None
    ) -> None:
        """A new P: its first M rows (factored when first needed) or their factor L."""
        self._hessian, self.factor = block, factor
        self._rows_ready = False

    def reset(self, build: bool) -> None:
        """Forget the working set; ``build``: set up a cold workspace now (before a run's first
        measurement, so that its first step does not pay for it: 1-3 ms at 60/50)."""
        self.model = self._cold() if build else None

    def prepare(self) -> None:
        """Build now what the first constrained solve would (the rows G L⁻ᵀ, the workspace): the
        real-time iteration's preparation, before the measurement."""
        self._ensure()
        if self.model is None:  # a new QP, or one whose last DAQP solve failed: cold
            self.model = self._cold()
        elif self._rows_new:
            # DAQP takes the new rows now (its LDP form, its working set refactored: 0.2-0.3
            # ms at 60/50), so that the feedback phase only updates f and b.
            self.model.update(A=self._rows)
            self._rows_new = False

    def solve(self, x_u: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, int] | None:
        """x (and DAQP's iterations) at a KKT point to ``tol`` of the QP whose unconstrained
        optimum is ``x_u`` and whose rows' bounds are ``b``, warm-started from the last
        working set; None otherwise (the next path's turn; the next solve then starts cold)."""
        self._ensure()
        f = self._cost(x_u)
        if self.model is None:
            self.model = self._setup(f, b)
            if self.model is None:
                return None
        elif self._rows_new:
            self.model.update(A=self._rows, f=f, bupper=b)
            self._rows_new = False
        else:
            self.model.update(f=f, bupper=b)
        _, _, flag, info = self.model.solve()
        # y from DAQP's multipliers, as ours computes it from its own: stationarity holds by
        # construction, and the checks below are the rest of the KKT conditions, on the rows
        # in y (G x - b = G L⁻ᵀ y - b: one product instead of the structured residual).
        multipliers = np.asarray(info["lam"], dtype=float)
        y = -f - multipliers @ self._rows
        s = self._rows @ y - b
        active = multipliers > 0
        # Written so that a NaN anywhere fails: every comparison with NaN is False.
        if not (
            flag == DAQP_OPTIMAL
            and s.max() <= self.tol
            and multipliers.min() >= 0
            and np.abs(s[active]).max(initial=0.0) <= self.tol
        ):
            self.model = None  # its working set is suspect: the next solve starts cold
            return None
        return self._primal(y), int(info["iterations"])

    def _cold(self) -> daqp.Model | None:
        """A workspace with placeholder f = 0, b = 1 (y = 0 feasible): every solve updates
        both, so building it before the first measurement costs the feedback nothing."""
        return self._setup(np.zeros(self.M + 1), np.ones(self.rows))

    def _setup(self, f: np.ndarray, b: np.ndarray) -> daqp.Model | None:
        """A workspace for this QP's rows, cold (no active row); None if DAQP refuses."""
        self._ensure()
        model = daqp.Model()
        model.settings = {"primal_tol": self.tol, "dual_tol": self.tol, "eps_prox": 0.0}
        flag, _ = model.setup(self._identity, f, self._rows, b, self._lower)
        self._rows_new = False
        return model if flag >= 0 else None

    def _cost(self, x_u: np.ndarray) -> np.ndarray:
        """f = L⁻¹c = -Lᵀx_u of DAQP's form (ε's entry 0)."""
        M = self.M
        assert self.factor is not None  # _ensure built it
        f = np.zeros(M + 1)
        f[:M] = -dtrmv(self.factor, x_u[:M], lower=1, trans=1)
        return f

    def _primal(self, y: np.ndarray) -> np.ndarray:
        """x = L⁻ᵀ y (one triangular solve; ε's row of L is √(2ρ))."""
        M, factor = self.M, self.factor
        x = np.empty(M + 1)
        x[:M] = dtrtrs(factor, y[:M], lower=1, trans=1)[0]
        x[M] = y[M] / np.sqrt(2 * self.rho)
        return x

    def _ensure(self) -> None:
        """L (P = LLᵀ) and the rows G L⁻ᵀ are current (built once per P)."""
        if self._rows_ready:
            return
        M = self.M
        if self.factor is None:
            assert self._hessian is not None, "DAQPSolver.new_hessian was never called"
            factor, info = dpotrf(self._hessian, lower=1)
            if info != 0:
                raise np.linalg.LinAlgError(f"QP Hessian not positive definite ({info})")
            self.factor = factor
        self._rows = self._build_rows(self.factor)
        self._identity = np.eye(M + 1)
        self._lower = np.full(self.rows, -np.inf)  # one-sided rows G x <= b
        self._rows_new = True
        self._rows_ready = True

    def _build_rows(self, factor: np.ndarray) -> np.ndarray:
        """G L⁻ᵀ from the structure of G (rows a - b, -a - b, c, -c, -b as in
        :meth:`controllers.time_varying_qp.TimeVaryingQP._build_dual`): with W = L⁻ᵀ (upper
        triangular), the rate rows are W's rows scaled by 1/Δv_max, the input rows W's block
        cumulative sums, and ε's column is 1/√(2ρ): one triangular inverse (M³/3) and
        O(rows·M), no product with G."""
        M, m = self.M, self.m
        Nc = M // m
        inverse, info = dtrtri(factor, lower=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"QP Hessian factor singular ({info})")
        W = np.tril(inverse).T  # L⁻ᵀ; dtrtri leaves the upper triangle as it found it
        rate = self.inv_rate[:, None] * W
        cumulative = W.reshape(Nc, m, M).cumsum(axis=0).reshape(M, M)
        slack = 1.0 / np.sqrt(2 * self.rho)
        rows = np.zeros((self.rows, M + 1))
        rows[:M, :M], rows[:M, M] = rate, -slack
        rows[M : 2 * M, :M], rows[M : 2 * M, M] = -rate, -slack
        rows[2 * M : 3 * M, :M] = cumulative
        rows[3 * M : 4 * M, :M] = -cumulative
        rows[4 * M, M] = -slack
        return rows
