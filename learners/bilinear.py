"""Bilinear EDMD: EDMD whose input enters multiplied by the lifted state (Bruder et al., RA-L 2021).

Lifted state z = [x_n; 1; phi(x_n)] as in :class:`learners.edmd.EDMD`; the model is::

    z_{k+1} = A z_k + B v_k + sum_j vbar_{k,j} H_j z_k,     vbar_k = v_k - v0

with v = normalizer.inputs(u) and v0 = normalizer.inputs(0) the normalized "no input" (no
steering, no pedal). Why bilinear: a car's steering gain falls with speed (0.9 -> 0.47 of
kinematic between 10 and 30 m/s) and the throttle's force falls as 1/v above the torque limit,
so the input's effect depends on the state; a lifted-linear model has one B for every speed,
while every control-affine system has a bilinear realization. Why vbar and not v: min-max
normalization puts "no steering" at v ~ 0.45, so v_j z would be nearly collinear with z itself
and the fit ill-posed (rollouts diverged everywhere without the shift); vbar_j z is zero when
nothing is applied, and H_j is then the change of the dynamics per unit of input j.

[A B H_1 .. H_m] minimize the one-step residual over all training pairs by the same ridge least
squares as EDMD, on the regressors [z; v; vbar_1 z'; ...; vbar_m z'] where z' is z without the
constant observable: vbar_j * 1 = v_j - v0_j is already in [z; v], so H_j's column on the
constant is zero by construction (the regression stays full rank, and A, B, H are unique).

The ridge shrinks toward ``ridge_prior``: ``zero`` is EDMD's Tikhonov term (A, B, H -> 0), while
``identity`` (the default) regresses z_{k+1} - z_k and so shrinks A toward the identity, the
model "nothing changes in one step". At the plant's 100 Hz a step barely moves the state, every
mode of A lies near 1, and shrinking toward zero pulls them inside the unit circle (the model
decays to rest) while too little ridge leaves the input-multiplied modes outside it. Measured
on ``data=default``'s two validation drives (20-40 s, open loop from rest), thin-plate RBFs:
toward zero (20 and 50 centres), every ridge from 1e-10 to 1e-3 diverged on a drive; 1e-2, bounded,
lost vx (RMSE 3.8-4.7 m/s); toward the identity, ridge 1e-6 drifted far (vx 2-35 m/s), and 1e-4
stayed bounded for every dictionary size tried (20, 50, 100, 200 centres; vx 1.2-1.7 m/s, yaw
rate 0.05-0.11 rad/s). The config's 100 centres and ridge 1e-4 come from that grid.

The model is not lifted-linear: an MPC that reads only ``A_`` and ``B_`` (the harness's
:class:`~harness.core.contracts.LiftedModel`) would ignore ``H_``. It satisfies
:class:`~harness.core.contracts.BilinearModel` instead, which DE-MPC linearises along its plan
(``controllers/linearization.py``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch

from harness.core.checks import choice
from harness.core.contracts import Dynamics
from harness.core.episode import MinMaxNormalizer
from learners.base import INPUT_DIM, STATE_DIM, Shape, check_rollout_args
from learners.edmd import EDMD, EDMDConfig
from learners.settings import settle

__all__ = [
    "BilinearEDMD",
    "BilinearEDMDConfig",
    "BilinearOperator",
    "bilinear_matrices",
    "bilinear_regression_rows",
    "bilinear_rollout",
]


def bilinear_rollout(
    a: np.ndarray,
    b: np.ndarray,
    h: np.ndarray,
    z0: np.ndarray,
    v: np.ndarray,
    v0: np.ndarray,
) -> np.ndarray:
    """z_{k+1} = A z_k + B v_k + sum_j (v_kj - v0_j) H_j z_k: z0 (..., N), v (..., T, m).

    Returns (..., T + 1, N); the batch dimensions are rolled out together.
    """
    m, size = h.shape[0], a.shape[0]
    z = np.empty((*v.shape[:-2], v.shape[-2] + 1, size))
    z[..., 0, :] = z0
    bv = v @ b.T
    vbar = v - v0
    # One product per step for A and every H_j: z @ [A^T H_1^T .. H_m^T] -> (..., 1 + m, N)
    stacked = np.concatenate([a.T, *(h_j.T for h_j in h)], axis=1)
    with np.errstate(over="ignore", invalid="ignore"):  # a diverging model yields inf, not noise
        for k in range(v.shape[-2]):
            products = (z[..., k, :] @ stacked).reshape(*z.shape[:-2], 1 + m, size)
            z[..., k + 1, :] = (
                products[..., 0, :]
                + np.einsum("...j,...jn->...n", vbar[..., k, :], products[..., 1:, :])
                + bv[..., k, :]
            )
    return z


RIDGE_PRIORS = ("identity", "zero")


def bilinear_regression_rows(
    z: np.ndarray,
    v: np.ndarray,
    z_next: np.ndarray,
    v0: np.ndarray,
    varying: np.ndarray,
    ridge_prior: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Regressors [z; v; vbar_1 z[varying]; ..; vbar_m z[varying]] and targets z_{k+1} (or
    z_{k+1} - z_k when the ridge shrinks toward the identity) of one-step pairs."""
    vbar = v - v0
    moving = z[:, varying]
    w = np.hstack([z, v, *(vbar[:, j : j + 1] * moving for j in range(v.shape[1]))])
    return w, z_next - z if ridge_prior == "identity" else z_next


def bilinear_matrices(
    theta: np.ndarray, m: int, varying: np.ndarray, ridge_prior: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A (N, N), B (N, m), H (m, N, N) from Theta^T (N, regressors) of
    :func:`bilinear_regression_rows` (H_j is zero on the coordinates not in ``varying``)."""
    size = theta.shape[0]
    a = np.ascontiguousarray(theta[:, :size])
    if ridge_prior == "identity":
        a += np.eye(size)
    b = np.ascontiguousarray(theta[:, size : size + m])
    h = np.zeros((m, size, size))
    columns = theta[:, size + m :].reshape(size, m, len(varying))
    for j in range(m):
        h[j][:, varying] = columns[:, j]
    return a, b, h


class BilinearOperator:
    """What every bilinear learner shares: ``v0_`` and the state matrix at a held input.

    Mixed into a fitted learner with ``A_``, ``H_`` and ``normalizer_``, ahead of it: a bilinear
    learner declares ``bilinear`` dynamics (:class:`~harness.core.contracts.BilinearModel`).
    """

    dynamics: ClassVar[Dynamics] = "bilinear"

    A_: np.ndarray
    H_: np.ndarray
    normalizer_: MinMaxNormalizer

    @property
    def v0_(self) -> np.ndarray:
        """Normalized input of no steering and no pedal, where the bilinear term vanishes."""
        return self.normalizer_.inputs(np.zeros(self.normalizer_.input_min.shape[0]))

    def transition(self, v: np.ndarray) -> np.ndarray:
        """A + sum_j (v_j - v0_j) H_j: the state matrix while the normalized input v is held."""
        vbar = np.asarray(v, dtype=np.float64) - self.v0_
        return self.A_ + np.einsum("...j,jnk->...nk", vbar, self.H_)


@dataclass(frozen=True)
class BilinearEDMDConfig(EDMDConfig):
    """Bilinear EDMD's settings (``conf/learner/bilinear_edmd.yaml``): EDMD's, and the prior."""

    ridge: Any = 1e-4  # Tikhonov weight relative to the mean squared one-step residual
    # What the ridge shrinks A toward: identity (z+ = z) or zero.
    ridge_prior: str = "identity"

    def __post_init__(self) -> None:
        super().__post_init__()
        settle(self, ridge_prior=choice("learner.ridge_prior", self.ridge_prior, RIDGE_PRIORS))


class BilinearEDMD(BilinearOperator, EDMD):
    """EDMD with the bilinear input term (see the module docstring).

    Settings (:class:`BilinearEDMDConfig`):
        dictionary, ridge, include_constant, seed: As :class:`~learners.edmd.EDMD`'s.
        ridge_prior: What the ridge shrinks A toward: ``identity`` or ``zero``.

    Fitted attributes: ``A_`` (N, N), ``B_`` (N, m), ``H_`` (m, N, N), ``C_`` (n, N),
    ``normalizer_``; ``v0_`` (m,) is the normalized zero input the bilinear term is centred on.
    """

    name: ClassVar[str] = "bilinear_edmd"
    config_class: ClassVar[type] = BilinearEDMDConfig
    config: BilinearEDMDConfig

    H_: np.ndarray

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        self.ridge_prior = self.config.ridge_prior

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        n, m = self.C_.shape[0], self.B_.shape[1]
        x0, inputs = check_rollout_args(x0, inputs, n, m)
        z = bilinear_rollout(
            self.A_, self.B_, self.H_, self.lift(x0), self.normalizer_.inputs(inputs), self.v0_
        )
        with np.errstate(over="ignore", invalid="ignore"):
            x = self.normalizer_.states_inverse(z @ self.C_.T)
        x[..., 0, :] = x0
        return x

    # -- EDMD's hooks ---------------------------------------------------------------------------

    def regressor_count(self, n: int = STATE_DIM, m: int = INPUT_DIM) -> int:
        """N + m + m (N - 1): [z; v] and each input times z without its constant."""
        size = self.lifted_dim(n)
        return size + m + m * (size - int(self.include_constant))

    def _regression_rows(
        self, z: np.ndarray, v: np.ndarray, z_next: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """[z; v; vbar_1 z'; ..; vbar_m z'] -> z_{k+1} (or z_{k+1} - z_k toward the identity)."""
        varying = self._varying(z.shape[1])
        return bilinear_regression_rows(z, v, z_next, self.v0_, varying, self.ridge_prior)

    def _set_matrices(self, theta: np.ndarray) -> None:
        m = self.normalizer_.input_min.shape[0]
        varying = self._varying(theta.shape[0])
        self.A_, self.B_, self.H_ = bilinear_matrices(theta, m, varying, self.ridge_prior)

    def _varying(self, size: int) -> np.ndarray:
        """Indices of the ``size`` lifted coordinates the input multiplies: all but the 1."""
        n = self.normalizer_.state_min.shape[0]
        return np.array([i for i in range(size) if not (self.include_constant and i == n)])

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        return {**super()._state(), "H": self.H_}

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        shapes = super()._state_shapes(n, m)
        lifted = shapes["A"][0]
        return {**shapes, "H": (m, lifted, lifted)}

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        self.H_ = state["H"].numpy().astype(np.float64)
        super()._set_state({k: v for k, v in state.items() if k != "H"})
