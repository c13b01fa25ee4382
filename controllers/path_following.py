"""Path following for any DE-MPC model: its predicted states and the errors they drive to a path.

``controller.reference: path`` adds two outputs to the model's (vx, vy, yaw rate): the lateral
error e_y (m, left of the line) and heading error e_ψ (rad) to the path, with the small-angle
kinematics of a car at the measured speed v̄::

    e_y,k+1 = e_y,k + dt (vy_k + v̄ e_ψ,k)        vy_k, r_k: the model's physical states
    e_ψ,k+1 = e_ψ,k + dt (r_k − v̄ κ_k)           κ_k: the path's curvature where the car will be

Both are linear in the model's predicted states for a given v̄, and the curvature ahead is a
known input, so the errors over the horizon are running sums of the model's own prediction
Y = free + Θ ΔV: whatever the model (lifted-linear, bilinear, linearisable), the path QP's
prediction is a few cumulative sums of the states QP's, O(Np·Nc·m) a step, and its Hessian is
built from it (:meth:`~controllers.condensed_qp.TimeVaryingQP.set_prediction_matrix`; the free
response by ``set_free_response``). The outputs per step are (vx, vy, yaw rate) normalized as
the model's, then e_y and e_ψ; ``controller.Q_path`` weighs them.
"""

from __future__ import annotations

import numpy as np

from harness.core.episode import MinMaxNormalizer

STATES = 3
ERRORS = 2  # lateral error (m), heading error (rad)
OUTPUTS = STATES + ERRORS


class FrenetOutputs:
    """The path QP's prediction from a model's (module docstring).

    Args:
        normalizer: the model's min-max map (physical vy, r = span · y + low).
        dt: control period (s).
    """

    def __init__(self, normalizer: MinMaxNormalizer, dt: float) -> None:
        low = np.asarray(normalizer.states_inverse(np.zeros(STATES)), dtype=float)
        self.span = np.asarray(normalizer.states_inverse(np.ones(STATES)), dtype=float) - low
        self.low = low
        self.dt = float(dt)

    def extend(
        self,
        theta: np.ndarray,
        free: np.ndarray,
        y0: np.ndarray,
        lateral_error_m: float,
        heading_error_rad: float,
        speed_mps: float,
        curvature_per_m: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(Θ (5 Np, M), free (5 Np,)) of the outputs (y_k, e_y,k, e_ψ,k), k = 1..Np, from the
        model's prediction of y_1..y_Np (Θ (3 Np, M), free (3 Np,)), its current outputs y0
        (normalized C z_0), the errors now, v̄ and the curvature at steps 0..Np-1 ahead."""
        return self.extend_theta(theta, speed_mps), self.extend_free(
            free, y0, lateral_error_m, heading_error_rad, speed_mps, curvature_per_m
        )

    def extend_theta(self, theta: np.ndarray, speed_mps: float) -> np.ndarray:
        """Θ (5 Np, M) of :meth:`extend`: it depends on the model's Θ and v̄ only, so it is
        built before the measurement (the real-time iteration's preparation) and kept while v̄
        stays in its band."""
        dt, v = self.dt, float(speed_mps)
        Np = theta.shape[0] // STATES
        theta = theta.reshape(Np, STATES, -1)
        theta_states = _before(np.zeros_like(theta[0]), theta * self.span[:, None])
        heading_theta = dt * np.cumsum(theta_states[:, 2], axis=0)
        lateral_theta = dt * np.cumsum(
            theta_states[:, 1] + v * _before(np.zeros_like(heading_theta[0]), heading_theta),
            axis=0,
        )
        return np.concatenate(
            [theta, lateral_theta[:, None], heading_theta[:, None]], axis=1
        ).reshape(Np * OUTPUTS, -1)

    def extend_free(
        self,
        free: np.ndarray,
        y0: np.ndarray,
        lateral_error_m: float,
        heading_error_rad: float,
        speed_mps: float,
        curvature_per_m: np.ndarray,
    ) -> np.ndarray:
        """free (5 Np,) of :meth:`extend`: what the measurement moves. Written into one array
        (no stacking): it runs in the feedback phase, every step."""
        dt, v = self.dt, float(speed_mps)
        Np = len(curvature_per_m)
        free = free.reshape(Np, STATES)
        span, low = self.span, self.low
        out = np.empty((Np, OUTPUTS))
        out[:, :STATES] = free
        # Step j's physical vy and r, j = 0..Np-1: j = 0 measured (no input effect), then
        # predicted; the two error columns hold them until they are summed.
        lateral, heading = out[:, STATES], out[:, STATES + 1]
        lateral[0], heading[0] = span[1:] * np.asarray(y0, dtype=float)[1:] + low[1:]
        lateral[1:] = span[1] * free[:-1, 1] + low[1]
        heading[1:] = span[2] * free[:-1, 2] + low[2]
        # e_ψ,k = e_ψ,0 + dt Σ_{j<k} (r_j − v̄ κ_j)
        heading -= v * curvature_per_m
        heading_before = heading_error_rad + dt * np.cumsum(heading)
        # e_y,k = e_y,0 + dt Σ_{j<k} (vy_j + v̄ e_ψ,j), e_ψ,0 the measured one
        lateral[0] += v * heading_error_rad
        lateral[1:] += v * heading_before[:-1]
        np.cumsum(lateral, out=lateral)
        lateral *= dt
        lateral += lateral_error_m
        heading[:] = heading_before
        return out.ravel()


def _before(first: np.ndarray, later: np.ndarray) -> np.ndarray:
    """Values at steps 0..Np-1 from step 0's and those of steps 1..Np (the last one unused)."""
    return np.concatenate([first[None], later[:-1]])
