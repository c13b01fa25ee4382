"""Our active-set path (``qp_solver: active_set``): Lawson-Hanson on the condensed QP's dual.

The dual of min ½xᵀPx + cᵀx s.t. Gx <= b is min_{λ>=0} ½λᵀKλ - rᵀλ with K = G P⁻¹ Gᵀ and
r = G x_u - b (x_u the unconstrained optimum); x = x_u - P⁻¹Gᵀλ. :class:`HotActiveSet` solves it
started from the rows active one step ago (a hot start), and its answer is accepted only at a
KKT point to ``tol``. K and P⁻¹Gᵀ come from :func:`dense_dual` (a QP whose P never changes) or
:func:`structured_dual` (a time-varying QP: from the structure of G, every step it is needed).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.linalg.lapack import dpotrf, dpotrs, dtrtrs


class HotActiveSet:
    """The dual operator of one QP and the rows active at its last solve.

    Args:
        rows: the rows of G x <= b.
        tol: the KKT tolerance an answer must meet.
        max_iter: factorizations before it hands over to PIQP (100 bounds a solve at about 4
            ms + PIQP, inside the 10 ms period).
    """

    def __init__(self, rows: int, tol: float, max_iter: int) -> None:
        self.tol, self.max_iter = tol, max_iter
        self.guess = np.zeros(rows, dtype=bool)  # the rows active at the last solve

    def set_dual(self, g_p_inv: np.ndarray, K: np.ndarray) -> None:
        """The rows of P⁻¹Gᵀ and K = G P⁻¹ Gᵀ of the QP's current P."""
        self._g_p_inv, self._K = g_p_inv, K
        # A whisper of regularization keeps K_WW factorable when active rows are dependent
        # (more rows than unknowns); the result is checked against tol all the same.
        self._delta = 1e-13 * float(np.abs(np.diag(self._K)).max())

    def solve(
        self,
        x_u: np.ndarray,
        r: np.ndarray,
        residual: Callable[[np.ndarray], np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray, int] | None:
        """Lawson-Hanson on the dual min_{λ>=0} ½λᵀKλ - rᵀλ, started from the last active set
        (``residual(x)``: G x - b).

        Rows enter one at a time (the most violated; the factor of K_WW grows by one row) and
        leave when their multiplier reaches zero (refactored). Returns (x, rows, factorizations)
        at a KKT point, or None when it is degenerate or takes longer than PIQP would.
        """
        tol, limit = self.tol, self.max_iter
        rows = np.flatnonzero(self.guess)
        factor, lam, iterations = None, np.zeros(0), 0
        while rows.size:  # warm start: keep the guessed rows whose multipliers are positive
            factor = self._factor(rows)
            iterations += 1
            if factor is None:
                rows = rows[:0]
                break
            lam = dpotrs(factor, r[rows], lower=1)[0]
            if (lam > 0).all():
                break
            rows = rows[lam > 0]
        while iterations < limit:
            x = x_u - lam @ self._g_p_inv[rows] if rows.size else x_u
            s = residual(x)
            if rows.size and np.abs(s[rows]).max() > tol:
                return None  # the regularization shows: leave it to PIQP
            s[rows] = -np.inf
            worst = int(np.argmax(s))
            if s[worst] <= tol:
                return x, rows, iterations
            factor = self._extend(factor, rows, worst)
            if factor is None:
                return None
            rows, current = np.append(rows, worst), np.append(lam, 0.0)
            while True:  # move towards the block solution, dropping rows whose λ reaches 0
                iterations += 1
                mu = dpotrs(factor, r[rows], lower=1)[0]
                if (mu > 0).all():
                    lam = mu
                    break
                if (mu[-1] <= 0 and current[-1] == 0) or iterations >= limit:
                    return None  # the most violated row cannot enter: degenerate
                blocking = mu <= 0
                ratios = current[blocking] / (current[blocking] - mu[blocking])
                current = current + ratios.min() * (mu - current)
                keep = current > 0
                keep[np.flatnonzero(blocking)[np.argmin(ratios)]] = False
                rows, current = rows[keep], current[keep]
                if rows.size == 0:
                    lam = current
                    break
                factor = self._factor(rows)
                if factor is None:
                    return None
        return None

    def _factor(self, rows: np.ndarray) -> np.ndarray | None:
        """Lower Cholesky factor of K[rows, rows] + δI; None when not numerically definite."""
        block = self._K.take(rows, 0).take(rows, 1)
        block.flat[:: rows.size + 1] += self._delta
        factor, info = dpotrf(block, lower=1)
        return factor if info == 0 else None

    def _extend(self, factor: np.ndarray | None, rows: np.ndarray, new: int) -> np.ndarray | None:
        """The factor of K_WW + δI with row ``new`` appended, in O(|W|²)."""
        k = rows.size
        diagonal = self._K[new, new] + self._delta
        extended = np.zeros((k + 1, k + 1), order="F")
        if k:
            column = dtrtrs(factor, self._K[new].take(rows), lower=1)[0]
            diagonal -= column @ column
            extended[:k, :k] = factor
            extended[k, :k] = column
        if diagonal <= self._delta:
            return None
        extended[k, k] = np.sqrt(diagonal)
        return extended


def dense_dual(G: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows of P⁻¹Gᵀ, K = G P⁻¹ Gᵀ) by dense products: built once for a fixed P."""
    p_inv = cho_solve(cho_factor(P), np.eye(P.shape[0]))
    g_p_inv = np.ascontiguousarray((p_inv @ G.T).T)  # rows of P⁻¹Gᵀ, one per constraint
    return g_p_inv, np.ascontiguousarray(G @ p_inv @ G.T)


def structured_dual(
    P: np.ndarray, inv_rate: np.ndarray, inputs: int, rows: int
) -> tuple[np.ndarray, np.ndarray]:
    """(rows of G P⁻¹, K = G P⁻¹ Gᵀ) from the structure of G, every step it is needed.

    Every row of G is a signed sum of three kinds: a = [diag(1/Δv_max), 0] (rates),
    b = [0, 1] (slack) and c = [L, 0] (cumulative inputs, L block lower-triangular ones):
    the rows are a − b, −a − b, c, −c, −b. So G P⁻¹ needs only a P⁻¹ (row scaling), b P⁻¹
    (a row) and c P⁻¹ (block cumulative sums), and K only their products with a, b, c
    (column scaling, a column, block cumulative sums): no product with G itself, about
    10x fewer operations than the dense G P⁻¹ Gᵀ at Nc = 50.
    """
    M, m = P.shape[0] - 1, inputs
    Nc = M // m
    factor, info = dpotrf(P, lower=1)
    p_inv = dpotrs(factor, np.eye(M + 1), lower=1)[0] if info == 0 else np.linalg.inv(P)
    rate = inv_rate
    a_p = rate[:, None] * p_inv[:M]  # (M, M+1)
    b_p = p_inv[M:]  # (1, M+1)
    c_p = p_inv[:M].reshape(Nc, m, M + 1).cumsum(axis=0).reshape(M, M + 1)
    g_p_inv = np.ascontiguousarray(np.vstack([a_p - b_p, -a_p - b_p, c_p, -c_p, -b_p]))
    basis = np.vstack([a_p, b_p, c_p])  # (2M+1, M+1) rows of [a; b; c] P⁻¹
    with_a = basis[:, :M] * rate  # (·)aᵀ
    with_b = basis[:, M:]  # (·)bᵀ
    with_c = basis[:, :M].reshape(-1, Nc, m).cumsum(axis=1).reshape(-1, M)
    pa, pb, pc = slice(0, M), slice(M, M + 1), slice(M + 1, 2 * M + 1)
    aa, ab, ac = with_a[pa], with_b[pa], with_c[pa]
    ba, bb, bc = with_a[pb], with_b[pb], with_c[pb]
    ca, cb, cc = with_a[pc], with_b[pc], with_c[pc]
    # Row kinds (a - b, -a - b, c, -c, -b) against the same column kinds.
    upper = [aa - ab - ba + bb, -aa - ab + ba + bb, ac - bc, -ac + bc, -ab + bb]
    lower = [-aa + ab - ba + bb, aa + ab + ba + bb, -ac - bc, ac + bc, ab + bb]
    cumulative = [ca - cb, -ca - cb, cc, -cc, -cb]
    slack = [-ba + bb, ba + bb, -bc, bc, bb]
    K = np.empty((rows, rows))
    edges = [0, M, 2 * M, 3 * M, 4 * M, 4 * M + 1]
    kinds = [upper, lower, cumulative, [-x for x in cumulative], slack]
    for i, row in enumerate(kinds):
        for j, block in enumerate(row):
            K[edges[i] : edges[i + 1], edges[j] : edges[j + 1]] = block
    return g_p_inv, K
