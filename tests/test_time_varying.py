"""The time-varying condensed QP: prediction matrices of a model that changes along the horizon,
the same answers as the time-invariant QP when it does not change, the bilinear linearisation,
and DE-MPC closing the loop on bilinear models."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.condensed_qp import CondensedQP, TimeVaryingQP
from tests.toy_models import toy_linear_model as linear_model

SETTINGS = {
    "Np": 20,
    "Nc": 10,
    "Q": 1000 * np.eye(3),
    "R": 5 * np.eye(2),
    "rho": 10.0,
    "v_min": np.array([0.2, 0.1]),
    "v_max": np.array([0.8, 0.9]),
    "dv_max": np.array([0.0025, 0.01]),
}


def random_time_varying(seed: int, Np: int = 20, N: int = 5, m: int = 2):
    rng = np.random.default_rng(seed)
    A = np.eye(N) + rng.normal(scale=0.05, size=(Np, N, N))
    B = rng.normal(scale=0.1, size=(Np, N, m))
    d = rng.normal(scale=0.01, size=(Np, N))
    C = rng.normal(size=(3, N))
    return A, B, d, C


def brute_force_outputs(A, B, d, C, z, v_prev, dv) -> np.ndarray:
    """y_1..y_Np by stepping z_{k+1} = A_k z_k + B_k v_k + d_k with v_k = v_prev + Σ_{j<=k} Δv_j."""
    Np, Nc = len(A), len(dv)
    v, outputs = v_prev.copy(), []
    for k in range(Np):
        if k < Nc:
            v = v + dv[k]
        z = A[k] @ z + B[k] @ v + d[k]
        outputs.append(C @ z)
    return np.array(outputs)


@pytest.mark.parametrize("seed", [0, 1])
def test_time_varying_prediction_equals_a_step_by_step_rollout(seed: int) -> None:
    A, B, d, C = random_time_varying(seed)
    qp = TimeVaryingQP(C, 2, **SETTINGS)
    qp.set_model(A, B, d)
    rng = np.random.default_rng(10 + seed)
    z, v_prev = rng.normal(size=5), rng.uniform(0.3, 0.7, size=2)
    dv = rng.normal(scale=0.01, size=(10, 2))
    np.testing.assert_allclose(
        qp.predict(z, v_prev, dv), brute_force_outputs(A, B, d, C, z, v_prev, dv), atol=1e-12
    )
    # Every column of Θ is the response to one increment: compare the whole matrix.
    free = brute_force_outputs(A, B, d, C, z, v_prev, np.zeros((10, 2)))
    for j in range(20):
        unit = np.eye(20)[j].reshape(10, 2)
        column = brute_force_outputs(A, B, d, C, z, v_prev, unit) - free
        np.testing.assert_allclose(qp.theta[:, j], column.ravel(), atol=1e-12)


@pytest.mark.parametrize(
    ("target", "input_box"),
    [
        ([0.501, 0.501, 0.501], (0.2, 0.8)),  # unconstrained
        ([0.9, 0.8, 0.2], (0.2, 0.8)),  # rate limits bind
        ([0.1, 0.2, 0.9], (0.495, 0.52)),  # and the input bounds too
    ],
)
def test_a_constant_time_varying_model_solves_the_time_invariant_qp(
    target: list[float], input_box: tuple[float, float]
) -> None:
    model = linear_model()
    box = {"v_min": np.full(2, input_box[0]), "v_max": np.full(2, input_box[1])}
    lti = CondensedQP(model.A_, model.B_, model.C_, **{**SETTINGS, **box})
    tv = TimeVaryingQP(model.C_, 2, **{**SETTINGS, **box})
    Np = SETTINGS["Np"]
    tv.set_model(np.repeat(model.A_[None], Np, 0), np.repeat(model.B_[None], Np, 0))
    z, v_prev = model.lift(np.array([20.0, 0.0, 0.0])), np.full(2, 0.5)
    y_ref = np.tile(target, Np)
    np.testing.assert_allclose(tv.theta, lti.theta, atol=1e-12)
    np.testing.assert_allclose(tv.P, lti.P, rtol=1e-10, atol=1e-9)
    expected, got = lti.solve(z, v_prev, y_ref), tv.solve(z, v_prev, y_ref)
    assert got.path == expected.path
    np.testing.assert_allclose(got.dv, expected.dv, atol=1e-8)
    assert got.slack == pytest.approx(expected.slack, abs=1e-8)
    by_piqp = tv.solve_piqp(z, v_prev, y_ref)
    assert by_piqp.ok
    np.testing.assert_allclose(by_piqp.dv, lti.solve_piqp(z, v_prev, y_ref).dv, atol=1e-7)
    # A second step with another model: PIQP is given the new Hessian.
    tv.set_model(np.repeat(model.A_[None], Np, 0), 2 * np.repeat(model.B_[None], Np, 0))
    lti2 = CondensedQP(model.A_, 2 * model.B_, model.C_, **{**SETTINGS, **box})
    np.testing.assert_allclose(
        tv.solve_piqp(z, v_prev, y_ref).dv, lti2.solve_piqp(z, v_prev, y_ref).dv, atol=1e-7
    )


def test_a_wrongly_shaped_model_is_refused() -> None:
    tv = TimeVaryingQP(np.eye(3), 2, **SETTINGS)
    with pytest.raises(ValueError, match="time-varying model must be"):
        tv.set_model(np.zeros((19, 3, 3)), np.zeros((20, 3, 2)))
