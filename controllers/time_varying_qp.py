"""The condensed DE-MPC QP of a model that changes along the horizon and every step.

A bilinear or nonlinear model linearised along the previous plan (``controllers/time_varying.py``)
has new A_k, B_k, d_k each step, so Θ, the Hessian and the unconstrained gain are rebuilt each
step; the solve paths are :class:`~controllers.condensed_qp.CondensedQP`'s.
"""

from __future__ import annotations

from typing import Unpack

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from controllers.active_set import structured_dual
from controllers.condensed_qp import SMALL_LIFT, CondensedQP, QPSettings
from controllers.condensing import (
    block_diagonal,
    free_response_maps,
    time_invariant_theta,
    time_varying_theta,
)


class TimeVaryingQP(CondensedQP):
    """The same QP and solve paths for a model that changes along the horizon and every step::

        z_{k+1} = A_k z_k + B_k v_k + d_k,   y_k = C z_k,   k = 0 .. Np-1 (from z_0 = z_t)

    e.g. a bilinear or nonlinear model linearised along the previous plan (d_k is what the
    linearisation leaves constant). :meth:`set_model` rebuilds Θ, the Hessian and the
    unconstrained gain each step; DAQP's rows G L⁻ᵀ, the active set's dual operator K and
    PIQP's Hessian are built only when a step needs them (DAQP and PIQP receive them by
    ``update``, keeping their warm start). With A_k = A,
    B_k = B, d_k = 0 it solves the time-invariant QP (up to rounding).

    Args:
        C: (n, N) output map; inputs: m. Everything else as :class:`CondensedQP`'s.
    """

    def __init__(self, C: np.ndarray, inputs: int, **settings: Unpack[QPSettings]) -> None:
        self._configure(C, inputs, settings)
        self.C = np.ascontiguousarray(C, dtype=float)
        self.Q, self._R = np.asarray(settings["Q"], float), np.asarray(settings["R"], float)
        Np, Nc = self.Np, self.Nc
        self._R_blocks = block_diagonal(self._R, Nc)
        M = self.m * Nc
        # Until the first set_model: a model without input effect (P = 2 diag(R, ρ)).
        self.theta = np.zeros((self.n * Np, M))
        self.P = np.zeros((M + 1, M + 1))
        self.P[:M, :M], self.P[M, M] = 2 * self._R_blocks, 2 * self.rho
        self.P = np.asfortranarray(self.P)
        self._build_constraints()
        self._build_piqp(self._max_iter, hessian=False)
        self._theta_set = False  # no Θ yet: P is a placeholder, not worth DAQP's workspace
        self._A = np.zeros((Np, self.N, self.N))
        self._B = np.zeros((Np, self.N, self.m))
        self._d = np.zeros((Np, self.N))
        self._gain = np.zeros((M, self.n * Np))
        self._dual_ready = False
        self._free_key: tuple[bytes, bytes] | None = None
        self._free = np.zeros(self.n * Np)
        self._given_free: np.ndarray | None = None
        self._w: np.ndarray | None = None  # a constant drive added to every step's d
        self._free_maps: np.ndarray | None = None  # small lifts: free response as products
        self.reset()

    def set_model(self, A: np.ndarray, B: np.ndarray, d: np.ndarray | None = None) -> None:
        """The model of this step: A (Np, N, N), B (Np, N, m), d (Np, N) (default 0); or one
        (A (1, N, N), B (1, N, m)) held over the whole horizon (a frozen linearisation: Θ from
        one step response, far cheaper for a large N and Np), with d (1, N) or (Np, N) (a known
        input that changes along the horizon)."""
        self._set_theta(self._model_theta(A, B, d))

    def model_prediction(
        self,
        A: np.ndarray,
        B: np.ndarray,
        d: np.ndarray | None,
        z: np.ndarray,
        v_prev: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(Θ, free response) of the model (A, B, d) as :meth:`set_model` takes it, from z and
        v_prev, without building this QP's cost: the prediction another QP builds on."""
        theta = self._model_theta(A, B, d)
        return theta, self.free_response(z, v_prev)

    def model_theta(self, A: np.ndarray, B: np.ndarray, d: np.ndarray | None) -> np.ndarray:
        """Θ of the model (A, B, d) as :meth:`set_model` takes it, which then drives
        :meth:`free_response`, without building this QP's cost (another QP builds on it)."""
        return self._model_theta(A, B, d)

    def _model_theta(self, A: np.ndarray, B: np.ndarray, d: np.ndarray | None) -> np.ndarray:
        """Θ of the model (A, B, d), which then drives :meth:`free_response`."""
        Np, N, m, Nc = self.Np, self.N, self.m, self.Nc
        A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
        K = A.shape[0] if A.ndim == 3 and A.shape[0] == 1 else Np
        d = np.zeros((K, N)) if d is None else np.asarray(d, dtype=float)
        if A.shape != (K, N, N) or B.shape != (K, N, m) or d.shape not in ((K, N), (Np, N)):
            raise ValueError(
                f"time-varying model must be A ({Np} or 1, {N}, {N}), B ({K}, {N}, {m}), "
                f"d ({K} or {Np}, {N}); got {A.shape}, {B.shape}, {d.shape}"
            )
        self._free_key = None
        self._given_free = None
        self._w = None
        if K == 1:
            theta = time_invariant_theta(A[0], B[0], self.C, Np, Nc)
            A, B, d = (np.broadcast_to(a, (Np, *a.shape[1:])) for a in (A, B, d))
        else:
            theta = time_varying_theta(A, B, self.C, Nc)
        self._A, self._B, self._d = A, B, d
        self._free_maps = free_response_maps(A, B, d, self.C) if N <= SMALL_LIFT else None
        return theta

    def has_model(self) -> bool:
        return self._theta_set  # set with the first Θ (set_model, ...)

    def set_disturbance(self, w: np.ndarray | None) -> None:
        """A constant w (N,) added to every step of the model set last (z⁺ = A_k z + B_k v +
        d_k + w: offset-free), which moves the free response only: Θ and the Hessian stay."""
        self._w = None if w is None else np.asarray(w, dtype=float)
        self._free_key = None

    def set_prediction_matrix(self, theta: np.ndarray) -> None:
        """The step's Θ (n Np, m Nc) given directly, for outputs that are not C z of one model
        (path following: a model's outputs and the errors to a path they drive), with its
        Hessian and factor: the preparation of a step whose free response
        :meth:`set_free_response` gives when it is measured."""
        shape = (self.n * self.Np, self.m * self.Nc)
        if theta.shape != shape:
            raise ValueError(f"prediction must be Θ {shape}, got {theta.shape}")
        self._set_theta(np.asarray(theta, dtype=float))

    def set_free_response(self, free: np.ndarray) -> None:
        """The free response (n Np,) of a step whose Θ is already set."""
        if free.shape != (self.n * self.Np,):
            raise ValueError(f"free response must be ({self.n * self.Np},), got {free.shape}")
        self._given_free = free

    def _set_theta(self, theta: np.ndarray) -> None:
        """Θ, and what follows from it: the Hessian, its factor and the unconstrained gain."""
        self.theta = theta
        Np, M = self.Np, self.m * self.Nc
        q_theta = np.einsum("ab,ibm->iam", self.Q, self.theta.reshape(Np, self.n, M)).reshape(
            self.n * Np, M
        )
        self._theta_q = np.ascontiguousarray(q_theta.T)
        with np.errstate(over="ignore", invalid="ignore"):  # a diverging model's Θ: see below
            curvature = self.theta.T @ q_theta
        if not np.all(np.isfinite(curvature)):
            raise np.linalg.LinAlgError(
                "time-varying QP Hessian not finite: the model's prediction overflows"
            )
        P = np.zeros((M + 1, M + 1))
        P[:M, :M] = 2 * (curvature + self._R_blocks)
        P[M, M] = 2 * self.rho
        self.P = np.asfortranarray((P + P.T) / 2)
        factor, info = dpotrf(self.P[:M, :M], lower=1)
        if info != 0:  # R > 0 makes the block definite; only a non-finite model gets here
            raise np.linalg.LinAlgError(f"time-varying QP Hessian not positive definite ({info})")
        self._gain = dpotrs(factor, 2 * q_theta.T, lower=1)[0]
        self._daqp.new_hessian(factor=factor)  # its rows G L⁻ᵀ built when first needed
        self._theta_set = True
        self._piqp.new_hessian()  # P_V built when PIQP is asked (most steps it is not)
        self._dual_ready = False

    def free_response(self, z: np.ndarray, v_prev: np.ndarray) -> np.ndarray:
        """(n Np,) outputs of the step's model with the input held at v_prev (the given one
        after :meth:`set_free_response`, whatever z and v_prev)."""
        if self._given_free is not None:
            return self._given_free
        key = (np.asarray(z, dtype=float).tobytes(), np.asarray(v_prev, dtype=float).tobytes())
        if key != self._free_key:  # solve and its PIQP fallback ask for the same one
            if self._free_maps is not None:  # outputs from [z; v; w; 1]: one product
                w = np.zeros(self.N) if self._w is None else self._w
                self._free = self._free_maps @ np.concatenate([z, v_prev, w, [1.0]])
            else:
                drive = self._B @ v_prev + self._d  # (Np, N)
                if self._w is not None:
                    drive = drive + self._w
                states = np.empty((self.Np, self.N))
                state = np.asarray(z, dtype=float)
                for k in range(self.Np):  # each step needs the previous: a loop of products
                    state = self._A[k] @ state + drive[k]
                    states[k] = state
                self._free = (states @ self.C.T).ravel()
            self._free_key = key
        return self._free

    def unconstrained(self, z: np.ndarray, v_prev: np.ndarray, y_ref: np.ndarray) -> np.ndarray:
        dv = self._gain @ (y_ref - self.free_response(z, v_prev))
        return np.append(dv, 0.0)

    def predict(self, z: np.ndarray, v_prev: np.ndarray, dv: np.ndarray) -> np.ndarray:
        y = self.free_response(z, v_prev) + self.theta @ np.ravel(dv)
        return y.reshape(self.Np, self.n)

    def _build_dual(self) -> None:
        """K = G P⁻¹ Gᵀ and the rows of G P⁻¹ of this step's P, from the structure of G."""
        self._active.set_dual(*structured_dual(self.P, self._inv_rate, self.m, self.rows))
