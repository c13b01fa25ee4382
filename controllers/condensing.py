"""The condensed prediction of a lifted model over the horizon, as matrices (paper eq. 18).

With ΔV the input increments over the control horizon, the outputs over the prediction horizon
are Y = Φz z + Φv v + Θ ΔV (+ the disturbance's and a time-varying model's affine terms). These
functions build Θ and the free response's maps, for a time-invariant model (its step
responses) and a time-varying one (A_k, B_k, d_k along the horizon), and the block matrices
the cost and the constraints are made of. :mod:`controllers.condensed_qp` builds its QP from
them; they hold no state.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "block_cumulative",
    "block_diagonal",
    "free_response_maps",
    "time_invariant_theta",
    "time_varying_theta",
]


def block_diagonal(block: np.ndarray, count: int) -> np.ndarray:
    """kron(I_count, block) without kron's (count·m)² products of zeros (a fifth of a band
    QP's construction at 60/50)."""
    m = block.shape[0]
    blocks = np.zeros((count, m, count, m))
    index = np.arange(count)
    blocks[index, :, index, :] = block
    return blocks.reshape(count * m, count * m)


def block_cumulative(count: int, m: int) -> np.ndarray:
    """kron(tril(ones(count)), I_m): v_{t-1} + this · ΔV are the inputs over the horizon."""
    cumulative = np.zeros((count, m, count, m))
    lower = np.tril(np.ones((count, count)))
    for channel in range(m):
        cumulative[:, channel, :, channel] = lower
    return cumulative.reshape(count * m, count * m)


def time_varying_theta(A: np.ndarray, B: np.ndarray, C: np.ndarray, Nc: int) -> np.ndarray:
    """Θ (n Np, m Nc): y_i's response to the increment Δv_j of a time-varying model.

    Δv_j holds from step j on, so the state's response S_j obeys S_j(k+1) = A_k S_j(k) + B_k
    for k >= j (S_j(j) = 0). All Nc responses advance together, one product per step over the
    increments already applied (a loop over Np of BLAS-3 products: each step needs the last).
    """
    Np, N, m = B.shape
    M = m * Nc
    response = np.zeros((N, M))
    history = np.empty((Np, N, M))
    blocks = response.reshape(N, Nc, m)  # a view: block j is S_j
    for k in range(Np):
        active = min(k + 1, Nc)
        response[:, : m * active] = A[k] @ response[:, : m * active]
        blocks[:, :active] += B[k][:, None, :]
        history[k] = response
    return (C @ history).reshape(Np * C.shape[0], M)


def free_response_maps(A: np.ndarray, B: np.ndarray, d: np.ndarray, C: np.ndarray) -> np.ndarray:
    """(n Np, 2N + m + 1): the outputs y_1..y_Np of z_{k+1} = A_k z_k + B_k v + d_k + w as one
    matrix on [z_0; v; w; 1] (v and w held over the horizon).

    X_k = [Φ_k | Γ_k | Ω_k | δ_k] (the state's response to z_0, v, w and the d's) obeys
    X_{k+1} = A_k X_k + [0 | B_k | I | d_k], X_0 = [I | 0 | 0 | 0]: one N×N by N×(2N+m+1)
    product a step, worth it for a small lift (``SMALL_LIFT``), where it replaces a loop of
    matrix-vector products at every solve by one product.
    """
    Np, N, m = B.shape
    width = 2 * N + m + 1
    drive = np.zeros((Np, N, width))
    drive[:, :, N : N + m] = B
    drive[:, :, N + m : 2 * N + m] = np.eye(N)
    drive[:, :, -1] = d
    history = np.empty((Np, N, width))
    response = np.zeros((N, width))
    response[:, :N] = np.eye(N)
    for k in range(Np):  # each step needs the last
        response = A[k] @ response + drive[k]
        history[k] = response
    return (C @ history).reshape(Np * C.shape[0], width)


def time_invariant_theta(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, Np: int, Nc: int
) -> np.ndarray:
    """Θ (n Np, m Nc) of a time-invariant model: block (i, j) is C S_{i+1-j} for j <= i, with
    the step responses S_l = Σ_{q<l} A^q B (one N×N by N×m product per step)."""
    N, m = B.shape
    steps = np.zeros((Np + 1, C.shape[0], m))  # C S_0 = 0
    power_b, step = B.copy(), np.zeros((N, m))
    for length in range(1, Np + 1):
        step += power_b
        power_b = A @ power_b
        steps[length] = C @ step
    rows, columns = np.arange(Np)[:, None], np.arange(Nc)[None, :]
    index = np.where(columns <= rows, rows + 1 - columns, 0)  # (Np, Nc) into steps
    blocks = steps[index]  # (Np, Nc, n, m)
    return blocks.transpose(0, 2, 1, 3).reshape(Np * C.shape[0], Nc * m)
