"""A weight on each input increment's change (``controller.R_change``): the cost it adds is the
sum of the squared changes, the first counted from the increment applied last step, and every
solve path minimises the cost with it."""

from __future__ import annotations

import numpy as np
import pytest

from controllers import DEMPCConfig
from controllers.condensed_qp import CondensedQP
from controllers.condensing import increment_weights, last_increment_cost
from controllers.time_varying_qp import TimeVaryingQP
from tests.qp_truth import kkt
from tests.toy_models import toy_linear_model

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
CHANGE = np.diag([400.0, 0.0])  # on the wheel only: semidefinite, as a user would set it


def changes_cost(dv: np.ndarray, last: np.ndarray, change: np.ndarray) -> float:
    """Σ_k ||Δv_k − Δv_{k−1}||² weighted by ``change``, Δv_{−1} = ``last``, by its definition."""
    steps = np.diff(np.vstack([last, dv]), axis=0)
    return float(sum(step @ change @ step for step in steps))


def test_the_added_cost_is_the_sum_of_squared_changes_from_the_last_increment() -> None:
    rng = np.random.default_rng(0)
    Nc, R = 6, np.diag([2.0, 3.0])
    change = np.array([[4.0, 1.0], [1.0, 2.0]])
    for _ in range(5):
        dv, last = rng.normal(size=(Nc, 2)), rng.normal(size=2)
        x = dv.ravel()
        quadratic = x @ increment_weights(R, change, Nc) @ x
        linear = last_increment_cost(change, Nc) @ last @ x
        own = float(np.einsum("ia,ab,ib->", dv, R, dv))
        expected = own + changes_cost(dv, last, change) - last @ change @ last  # less its constant
        assert quadratic + linear == pytest.approx(expected, rel=1e-12)


def test_a_saw_costs_more_than_a_ramp_of_the_same_increments() -> None:
    Nc, limit = 8, 0.0025
    saw = np.c_[limit * (-1.0) ** np.arange(Nc), np.zeros(Nc)]
    ramp = np.c_[np.full(Nc, limit), np.zeros(Nc)]
    weights = increment_weights(np.zeros((2, 2)), CHANGE, Nc)
    # Both cost the same under R; the saw's changes are twice its increments, the ramp's none.
    assert saw.ravel() @ weights @ saw.ravel() == pytest.approx(400 * limit**2 * (1 + 4 * (Nc - 1)))
    assert ramp.ravel() @ weights @ ramp.ravel() == pytest.approx(400 * limit**2)


def truth(qp: CondensedQP, z, v_prev, y_ref, last) -> tuple[np.ndarray, np.ndarray]:
    """(P, c) of J = ||ΘΔV + e||²_Q + ||ΔV||²_R + Σ||Δv_k − Δv_{k−1}||²_{R_change} + ρε², built
    from the prediction matrices and the definition, not from the QP's own Hessian."""
    M, Nc = qp.m * qp.Nc, qp.Nc
    error = (qp.free_response(z, v_prev) - y_ref).reshape(qp.Np, qp.n)
    difference = np.eye(Nc) - np.eye(Nc, k=-1)
    hessian = qp.theta.T @ np.kron(np.eye(qp.Np), qp.Q) @ qp.theta
    hessian += np.kron(np.eye(Nc), SETTINGS["R"]) + np.kron(difference.T @ difference, CHANGE)
    P = np.zeros((M + 1, M + 1))
    P[:M, :M], P[M, M] = 2 * hessian, 2 * qp.rho
    c = np.zeros(M + 1)
    c[:M] = 2 * qp.theta.T @ (error @ qp.Q.T).ravel()
    c[: qp.m] -= 2 * CHANGE @ last
    return P, c


@pytest.mark.parametrize("target", [[0.5, 0.5, 0.5], [0.9, 0.1, 0.8]])  # inside, at the bounds
@pytest.mark.parametrize("kind", ["lifted", "time_varying"])
def test_every_solve_path_minimises_the_cost_with_the_change(target, kind) -> None:
    model = toy_linear_model()
    settings = {**SETTINGS, "R_change": CHANGE}
    if kind == "lifted":
        qp = CondensedQP(model.A_, model.B_, model.C_, **settings)
    else:
        qp = TimeVaryingQP(model.C_, 2, **settings)
        qp.set_model(model.A_[None], model.B_[None])
    z, v_prev = model.lift(np.array([20.0, 0.0, 0.0])), np.full(2, 0.5)
    y_ref = np.tile(target, SETTINGS["Np"])
    last = np.array([-0.0025, 0.004])  # the wheel moved the other way last step
    qp.last_increment = last
    P, c = truth(qp, z, v_prev, y_ref, last)
    G, b = qp.G, -qp.residual(np.zeros(len(c)), v_prev)
    exact = qp.solve(z, v_prev, y_ref)  # unconstrained, or an active set: exact to rounding
    assert exact.ok
    assert kkt(P, c, G, b, np.append(exact.dv.ravel(), exact.slack)).holds(), exact.path
    # PIQP, the fallback, to its tolerance (its slack stops short of zero: compare the moves).
    interior = qp.solve_piqp(z, v_prev, y_ref)
    assert interior.ok
    np.testing.assert_allclose(interior.dv, exact.dv, atol=1e-6)


def test_without_the_change_weight_the_qp_is_the_papers() -> None:
    model = toy_linear_model()
    paper = CondensedQP(model.A_, model.B_, model.C_, **SETTINGS)
    zero = CondensedQP(model.A_, model.B_, model.C_, **SETTINGS, R_change=np.zeros((2, 2)))
    zero.last_increment = np.array([0.002, -0.003])  # ignored without a weight
    z, v_prev = model.lift(np.array([20.0, 0.0, 0.0])), np.full(2, 0.5)
    y_ref = np.tile([0.9, 0.1, 0.8], SETTINGS["Np"])
    np.testing.assert_array_equal(zero.P, paper.P)
    np.testing.assert_array_equal(zero.solve(z, v_prev, y_ref).dv, paper.solve(z, v_prev, y_ref).dv)


@pytest.mark.parametrize("value", [-1.0, [1.0, -2.0], "much"])
def test_a_change_weight_that_is_not_positive_semidefinite_is_refused(value) -> None:
    with pytest.raises(ValueError, match=r"controller\.R_change"):
        DEMPCConfig(R_change=value)
