"""The time-varying condensed QP: prediction matrices of a model that changes along the horizon,
the same answers as the time-invariant QP when it does not change, the bilinear linearisation,
and DE-MPC closing the loop on bilinear models."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pytest

from controllers import DEMPC, DEMPCConfig
from controllers.active_set import dense_dual, structured_dual
from controllers.condensed_qp import PREDICTION_NOT_FINITE, CondensedQP
from controllers.lifted_linear import LiftedLinearModel
from controllers.linearization import BilinearLinearization
from controllers.time_varying_qp import TimeVaryingQP
from harness.core.episode import MinMaxNormalizer
from harness.evaluation.tracking import track
from harness.recorder import Recorder
from harness.references import DoubleLaneChange
from tests.qp_truth import PIQP_KKT_TOL, assert_optimal, solution_kkt
from tests.toy_models import (
    ModelPlant,
    constant_feature,
    feasible_reference,
    toy_bilinear_model,
    toy_linear_model,
)
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
    frozen = TimeVaryingQP(model.C_, 2, **{**SETTINGS, **box})
    frozen.set_model(model.A_[None], model.B_[None])  # one model held over the horizon
    np.testing.assert_allclose(frozen.theta, lti.theta, atol=1e-12)
    np.testing.assert_allclose(
        frozen.predict(
            z := model.lift(np.array([20.0, 0.0, 0.0])), np.full(2, 0.5), np.ones((10, 2))
        ),
        lti.predict(z, np.full(2, 0.5), np.ones((10, 2))),
        atol=1e-12,
    )
    expected, got = lti.solve(z, v_prev, y_ref), tv.solve(z, v_prev, y_ref)
    assert got.path == expected.path
    assert_optimal(lti, z, v_prev, y_ref, expected)
    assert_optimal(lti, z, v_prev, y_ref, got)  # the time-invariant QP's optimum, by its KKT
    # The optimum is unique (P > 0) and both answers are exact: they agree to rounding.
    np.testing.assert_allclose(got.dv, expected.dv, atol=1e-8)
    assert got.slack == pytest.approx(expected.slack, abs=1e-8)
    assert solution_kkt(lti, z, v_prev, y_ref, tv.solve_piqp(z, v_prev, y_ref)).holds(PIQP_KKT_TOL)
    # A second step with another model: PIQP is given the new Hessian.
    tv.set_model(np.repeat(model.A_[None], Np, 0), 2 * np.repeat(model.B_[None], Np, 0))
    lti2 = CondensedQP(model.A_, 2 * model.B_, model.C_, **{**SETTINGS, **box})
    assert solution_kkt(lti2, z, v_prev, y_ref, tv.solve_piqp(z, v_prev, y_ref)).holds(PIQP_KKT_TOL)


def test_daqp_follows_a_model_that_changes_every_step() -> None:
    """A new Hessian each step (DAQP's rows G L⁻ᵀ rebuilt, its working set kept): every answer
    meets that step's KKT conditions, and PIQP at its everyday tolerance finds the same cost."""
    C = random_time_varying(0)[3]
    qp, second = TimeVaryingQP(C, 2, **SETTINGS), TimeVaryingQP(C, 2, **SETTINGS)
    rng = np.random.default_rng(5)
    paths = []
    for seed in range(12):
        A, B, d, _ = random_time_varying(seed)
        qp.set_model(A, B, d)
        second.set_model(A, B, d)
        z, v_prev = rng.normal(size=5), rng.uniform(0.3, 0.7, size=2)
        y_ref = qp.free_response(z, v_prev) + rng.normal(scale=0.05, size=3 * SETTINGS["Np"])
        solution, other = qp.solve(z, v_prev, y_ref), second.solve_piqp(z, v_prev, y_ref)
        assert_optimal(qp, z, v_prev, y_ref, solution)
        assert solution_kkt(qp, z, v_prev, y_ref, other).holds(PIQP_KKT_TOL)
        assert qp.cost(z, v_prev, y_ref, solution.dv, solution.slack) == pytest.approx(
            qp.cost(z, v_prev, y_ref, other.dv, other.slack), rel=1e-5
        )
        paths.append(solution.path)
    assert set(paths) <= {"unconstrained", "daqp"} and paths.count("daqp") >= 8


def test_a_wrongly_shaped_model_is_refused() -> None:
    tv = TimeVaryingQP(np.eye(3), 2, **SETTINGS)
    with pytest.raises(ValueError, match="time-varying model must be"):
        tv.set_model(np.zeros((19, 3, 3)), np.zeros((20, 3, 2)))


def test_the_bilinear_linearisation_equals_finite_differences_of_the_bilinear_step() -> None:
    rng = np.random.default_rng(3)
    N, m, K = 6, 2, 4
    model = ToyBilinear(
        A_=np.eye(N) + rng.normal(scale=0.05, size=(N, N)),
        B_=rng.normal(scale=0.1, size=(N, m)),
        H_=rng.normal(scale=0.1, size=(m, N, N)),
        v0=rng.uniform(0.3, 0.6, size=m),
    )
    linear = BilinearLinearization(model)
    z, v = rng.normal(size=(K, N)), rng.uniform(0, 1, size=(K, m))
    A, B, d = linear.linearize(z, v)
    h = 1e-6
    for k in range(K):
        for i in range(N):
            e = np.eye(N)[i] * h
            column = (linear.step(z[k] + e, v[k]) - linear.step(z[k] - e, v[k])) / (2 * h)
            np.testing.assert_allclose(A[k][:, i], column, atol=1e-8)
        for j in range(m):
            e = np.eye(m)[j] * h
            column = (linear.step(z[k], v[k] + e) - linear.step(z[k], v[k] - e)) / (2 * h)
            np.testing.assert_allclose(B[k][:, j], column, atol=1e-8)
    # The linearisation is exact at the point itself, and batched steps are the single steps.
    np.testing.assert_allclose(
        np.einsum("kab,kb->ka", A, z) + np.einsum("kaj,kj->ka", B, v) + d,
        linear.step(z, v),
        atol=1e-12,
    )
    np.testing.assert_allclose(linear.step(z, v)[1], linear.step(z[1], v[1]), atol=1e-14)
    expected = model.A_ @ z[0] + model.B_ @ v[0]
    expected += np.einsum("j,jab,b->a", v[0] - model.v0_, model.H_, z[0])
    np.testing.assert_allclose(linear.step(z[0], v[0]), expected, atol=1e-12)


@pytest.mark.parametrize(
    ("horizons", "linearization"),
    [
        ({"Np": 10, "Nc": 7}, "plan"),
        ({"Np": 60, "Nc": 50}, "plan"),
        ({"Np": 10, "Nc": 7}, "frozen"),
    ],
)
def test_the_exact_bilinear_model_tracks_a_feasible_reference_on_its_own_plant(
    horizons, linearization
) -> None:
    model = toy_bilinear_model()
    reference = feasible_reference(model)
    plant = ModelPlant(model, x0=reference[0])
    controller = DEMPC(model, DEMPCConfig(**horizons, linearization=linearization))
    assert isinstance(controller.qp, TimeVaryingQP)  # read as bilinear, not as A_, B_ alone
    metrics, _ = track(plant, controller, reference, name="exact", recorder=Recorder())
    assert metrics["rmse"]["vx"] < 0.05  # of a 40 m/s range
    assert metrics["rmse"]["vy"] < 1e-3 and metrics["rmse"]["yaw_rate"] < 1e-3
    assert metrics["solver_failures"] == 0
    # Read as lifted-linear (H_ dropped), the same loop tracks worse.
    dropped = LiftedLinearModel(model.A_, model.B_, model.normalizer_, constant_feature)
    linear, _ = track(
        plant, DEMPC(dropped, DEMPCConfig(**horizons)), reference, name="h", recorder=Recorder()
    )
    assert linear["rmse"]["yaw_rate"] > 3 * metrics["rmse"]["yaw_rate"]


def test_more_sqp_iterations_plan_along_their_own_plan() -> None:
    model = toy_bilinear_model()
    reference = feasible_reference(model, steps=80)
    x = np.array([20.0, 0.3, -0.1])
    infos = []
    for iterations in (1, 3):
        controller = DEMPC(
            model, DEMPCConfig(Np=12, Nc=5, sqp_iterations=iterations, linearization="plan")
        )
        controller.reset(reference)
        _, info = controller.act(x, 0.0)
        infos.append(info)
    # After re-linearising along its own plan, the prediction is the bilinear model's own
    # rollout of that plan to within the second-order term left out.
    plan = np.vstack([infos[1].planned_inputs, np.repeat(infos[1].planned_inputs[-1:], 7, 0)])
    plant = ModelPlant(model, x0=x)
    stepped = np.array([plant.step(move) for move in plan])
    first = infos[0]
    plan0 = np.vstack([first.planned_inputs, np.repeat(first.planned_inputs[-1:], 7, 0)])
    plant0 = ModelPlant(model, x0=x)
    stepped0 = np.array([plant0.step(move) for move in plan0])
    error3 = np.abs(infos[1].predicted_states - stepped).max()
    error1 = np.abs(first.predicted_states - stepped0).max()
    assert error3 < 1e-6 and error3 < error1


@pytest.mark.parametrize("value", [0, 4, 1.5])
def test_sqp_iterations_must_be_one_to_three(value: float) -> None:
    with pytest.raises(ValueError, match=r"controller\.sqp_iterations must be 1, 2 or 3"):
        DEMPCConfig(sqp_iterations=value)  # type: ignore[arg-type]


def test_the_linearization_must_be_plan_or_frozen() -> None:
    with pytest.raises(ValueError, match=r"controller\.linearization must be one of plan, frozen"):
        DEMPCConfig(linearization="everywhere")


@dataclass
class ToyBilinear:
    A_: np.ndarray
    B_: np.ndarray
    H_: np.ndarray
    v0: np.ndarray

    @property
    def v0_(self) -> np.ndarray:
        return self.v0

    @property
    def C_(self) -> np.ndarray:
        return np.eye(3, self.A_.shape[0])

    @property
    def normalizer_(self) -> MinMaxNormalizer:
        return toy_linear_model().normalizer_

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=float)


def test_the_structured_dual_operator_equals_the_dense_one() -> None:
    A, B, d, C = random_time_varying(4)
    qp = TimeVaryingQP(C, 2, **SETTINGS)
    qp.set_model(A, B, d)
    p_inv = np.linalg.inv(qp.P)
    for rows, K in (structured_dual(qp.P, qp._inv_rate, qp.m, qp.rows), dense_dual(qp.G, qp.P)):
        np.testing.assert_allclose(K, qp.G @ p_inv @ qp.G.T, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(rows, (p_inv @ qp.G.T).T, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    "poison",
    ["nan_at_the_end", "finite_but_overflowing", "too_large_for_the_hessian"],
)
def test_a_model_that_diverges_along_the_plan_is_named_and_the_step_falls_back(
    monkeypatch, caplog, poison: str
) -> None:
    """A NaN linearisation, or a finite one whose products overflow over the horizon (Θ not
    finite) or whose Θ is too large for a Hessian, is the model's failure, not the QP's: the
    controller says whose, applies the previous plan's next move and counts a failure, and the
    run goes on."""
    model = toy_bilinear_model()
    reference = feasible_reference(model, steps=40)
    controller = DEMPC(model, DEMPCConfig(Np=10, Nc=7))
    controller.reset(reference)
    x = reference[0]
    _, first = controller.act(x, 0.0)
    assert not first.fallback
    linearization = controller.linearization
    assert linearization is not None
    exact = linearization.linearize

    def diverged(z: np.ndarray, v: np.ndarray):
        A, B, d = exact(z, v)
        A = A.copy()
        if poison == "nan_at_the_end":  # the rollout left the model's domain at the horizon's end
            A[-1, 0, 0] = np.nan
        elif poison == "finite_but_overflowing":  # 1e30 a step: inf within the horizon
            A[:, 0, 0] = 1e30
        else:  # finite Θ, but ΘᵀQΘ overflows
            A[:, 0, 0] = 1e20
        return A, B, d

    monkeypatch.setattr(linearization, "linearize", diverged)
    with caplog.at_level(logging.WARNING):
        u, info = controller.act(x, 0.01)
    assert info.fallback and info.solve_path == "failed" and np.isfinite(u).all()
    np.testing.assert_allclose(u, first.planned_inputs[1])
    named = f"{type(model).__name__}'s linearisation along the plan is not finite" in caplog.text
    assert named or (poison != "nan_at_the_end" and PREDICTION_NOT_FINITE in caplog.text)
    assert "Hessian" not in caplog.text


def test_a_solve_whose_prediction_is_not_finite_fails_and_optimises_nothing() -> None:
    """NaN compares False with every bound, so an unchecked NaN optimum would pass for an
    unconstrained one: the QP refuses it instead."""
    A, B, d, C = random_time_varying(3, N=4)
    qp = TimeVaryingQP(C, 2, **SETTINGS)
    qp.set_model(A, B, d)
    z = np.full(4, np.nan)
    solution = qp.solve(z, np.full(2, 0.5), np.zeros(3 * SETTINGS["Np"]))
    assert not solution.ok and solution.status == PREDICTION_NOT_FINITE
    assert solution.path == "failed" and np.all(solution.dv == 0)


@pytest.mark.parametrize("reference_kind", ["states", "path"])
def test_a_model_that_diverges_at_the_first_step_falls_back_without_a_prediction(
    monkeypatch, reference_kind: str
) -> None:
    """A run whose very first preparation fails has no model in its QP yet: the step holds the
    start input and reports its horizon as NaN rows (as a step without a call), and the next
    step, with a finite model, plans as usual (a DNN of the paper's recipe did this at rest)."""
    model = toy_bilinear_model()
    reference = feasible_reference(model, steps=40)
    controller = DEMPC(model, DEMPCConfig(Np=10, Nc=7, reference=reference_kind))
    linearization = controller.linearization
    assert linearization is not None
    exact = linearization.linearize

    def not_finite(z: np.ndarray, v: np.ndarray):
        A, B, d = exact(z, v)
        return np.full_like(A, np.nan), B, d

    monkeypatch.setattr(linearization, "linearize", not_finite)
    path = DoubleLaneChange().course().path() if reference_kind == "path" else None
    controller.reset(reference, path=path)
    pose = np.zeros(3) if path is not None else None
    x = reference[0]
    u, info = controller.act(x, 0.0, pose=pose)
    assert info.fallback and info.solve_path == "failed"
    np.testing.assert_allclose(u, np.zeros(2), atol=1e-12)  # the run starts from u = 0
    assert info.predicted_states.shape == (10, 3) and np.isnan(info.predicted_states).all()
    monkeypatch.setattr(linearization, "linearize", exact)
    _, after = controller.act(x, 0.01, pose=pose)
    assert not after.fallback and np.isfinite(after.predicted_states).all()
