"""The real-time iteration: DE-MPC prepares each step before its measurement and solves it after.

``prepare()`` linearises the model along the shifted plan rolled out from the state the model
predicts, and builds Θ, the Hessian and its factor; ``act`` adds the measured free response and
solves. On a plant that is the controller's own model the prediction is the measurement (to
rounding), so the two-phase loop gives the inputs of the one-phase step, which prepares along
the measurement: the same QPs to rounding, whose optima agree to the solvers' tolerance. The
free response built as one product for a small lift equals a step-by-step rollout, with and
without a disturbance.
"""

from __future__ import annotations

import numpy as np
import pytest

from controllers import DEMPCConfig
from controllers.condensed_qp import SMALL_LIFT
from controllers.disturbance import OffsetFree
from controllers.linearization import BilinearLinearization
from controllers.time_varying_qp import TimeVaryingQP
from harness.evaluation.tracking import track
from harness.recorder import Recorder
from harness.references import DoubleLaneChange
from tests.test_time_varying import SETTINGS, brute_force_outputs, random_time_varying
from tests.toy_models import ModelPlant, feasible_reference, toy_bilinear_model, toy_linear_model

TOL = DEMPCConfig().tol  # the solvers' tolerance, normalized units


def _inputs(model, states, path=None, **settings):
    """(metrics, normalized inputs) of a run tracking ``states`` on the model's own plant."""
    plant = ModelPlant(model, x0=states[0])
    config = DEMPCConfig(**settings)  # type: ignore[arg-type]
    metrics, run = track(
        plant, config(model, plant.dt), states, name="x", recorder=Recorder(), path=path
    )
    return metrics, model.normalizer_.inputs(run.inputs)


@pytest.mark.parametrize(
    "settings",
    [
        {},
        {"Np": 60, "Nc": 50},
        {"disturbance": OffsetFree()},
        {"sqp_iterations": 2},
        {"compute_delay": "one_step"},
    ],
    ids=["10/7", "60/50", "offset-free", "two SQP iterations", "one_step delay"],
)
def test_the_two_phase_step_gives_the_one_phase_input_on_an_exact_model(settings) -> None:
    model = toy_bilinear_model()
    reference = feasible_reference(model, 300)
    metrics, split = _inputs(model, reference, **settings)
    _, one_phase = _inputs(model, reference, real_time_iteration=False, **settings)
    assert metrics["prepare_time_ms"]["median"] > 0  # the loop ran the preparation
    assert np.ptp(split[:, 0]) > 0.05  # it steers: the QPs are not trivial
    np.testing.assert_allclose(split, one_phase, atol=10 * TOL)


@pytest.mark.parametrize("model", [toy_bilinear_model(), toy_linear_model()], ids=["TV", "LTI"])
def test_the_two_phase_path_follower_gives_the_one_phase_input(model) -> None:
    """Following a path, the preparation predicts the pose a step on as well (the plant's
    planar kinematics under the state) and builds the path QP's Θ for its speed band."""
    path = DoubleLaneChange(speed_mps=20.0).course().path()
    reference = np.tile([20.0, 0.0, 0.0], (300, 1))
    settings = {"reference": "path", "Np": 30, "Nc": 20}
    metrics, split = _inputs(model, reference, path, **settings)
    _, one_phase = _inputs(model, reference, path, real_time_iteration=False, **settings)
    assert metrics["follows_path"] and np.ptp(split[:, 0]) > 0.05
    np.testing.assert_allclose(split, one_phase, atol=10 * TOL)


@pytest.mark.parametrize("N", [5, SMALL_LIFT + 4], ids=["product", "loop"])
def test_the_free_response_with_a_disturbance_equals_a_step_by_step_rollout(N: int) -> None:
    """Both ways of building it (one product for a small lift, a loop for a large one)."""
    A, B, d, C = random_time_varying(3, N=N)
    qp = TimeVaryingQP(C, 2, **SETTINGS)
    qp.set_model(A, B, d)
    rng = np.random.default_rng(4)
    z, v_prev, w = rng.normal(size=N), rng.uniform(0.3, 0.7, size=2), rng.normal(size=N)
    zero = np.zeros((10, 2))
    expected = brute_force_outputs(A, B, d, C, z, v_prev, zero).ravel()
    np.testing.assert_allclose(qp.free_response(z, v_prev), expected, atol=1e-12)
    qp.set_disturbance(w)
    expected = brute_force_outputs(A, B, d + w, C, z, v_prev, zero).ravel()
    np.testing.assert_allclose(qp.free_response(z, v_prev), expected, atol=1e-12)
    qp.set_disturbance(None)
    qp.set_model(A, B, d + w)  # the disturbance as part of d: the same outputs
    np.testing.assert_allclose(qp.free_response(z, v_prev), expected, atol=1e-12)


def test_linearising_at_the_predicted_states_simulates_nothing_and_tracks_as_the_plan() -> None:
    """``linearization: predicted`` (the RTI shift) takes its points from the last step's QP
    prediction, one step on: after the first step the model is never stepped to linearise,
    and on the model's own plant it tracks as the exact rollout along the plan does."""
    model = toy_bilinear_model()
    reference = feasible_reference(model, 300)
    steps = {"n": 0}
    original = BilinearLinearization.step  # what DE-MPC steps a bilinear model with

    def counted(self, z, v):
        steps["n"] += 1
        return original(self, z, v)

    results = {}
    for linearization in ("plan", "predicted"):
        steps["n"] = 0
        BilinearLinearization.step = counted  # type: ignore[method-assign]
        try:
            metrics, inputs = _inputs(model, reference, Np=30, Nc=20, linearization=linearization)
        finally:
            BilinearLinearization.step = original  # type: ignore[method-assign]
        results[linearization] = (metrics, inputs, steps["n"])
    plan, predicted = results["plan"], results["predicted"]
    control_steps = len(reference) - 1
    assert plan[2] >= 30 * control_steps  # a rollout of Np steps every step (and the plant's)
    assert predicted[2] <= 2 * control_steps + 60  # the plant's and the prepare's own steps
    assert np.ptp(predicted[1][:, 0]) > 0.05
    for state in ("vx", "vy", "yaw_rate"):
        assert predicted[0]["rmse"][state] <= 1.1 * plan[0]["rmse"][state] + 1e-6


def test_the_presolve_gives_the_same_inputs_with_fewer_iterations_after_the_measurement(
    monkeypatch,
) -> None:
    """``presolve``: the preparation solves a linearised model's new QP at the state it
    predicts, so DAQP's working set is the one the measurement needs: on an exact model the
    feedback's solves take fewer active-set iterations (the work moved to the preparation),
    and the inputs are the same."""
    model = toy_bilinear_model()
    reference = feasible_reference(model, 300)
    counted: dict[bool, list[int]] = {True: [], False: []}
    for presolve in (True, False):
        config = DEMPCConfig(Np=30, Nc=20, presolve=presolve)
        controller = config(model, 0.01)
        solve, act = controller.qp.solve, controller.act
        in_feedback = [False]

        def counting_solve(*args, solve=solve, presolve=presolve, in_feedback=in_feedback):
            solution = solve(*args)
            if in_feedback[0]:
                counted[presolve].append(solution.iterations)
            return solution

        def feedback_act(*args, act=act, in_feedback=in_feedback, **kwargs):
            in_feedback[0] = True
            try:
                return act(*args, **kwargs)
            finally:
                in_feedback[0] = False

        monkeypatch.setattr(controller.qp, "solve", counting_solve)
        monkeypatch.setattr(controller, "act", feedback_act)
        plant = ModelPlant(model, x0=reference[0])
        _, run = track(plant, controller, reference, name="x", recorder=Recorder())
        if presolve:
            with_presolve = model.normalizer_.inputs(run.inputs)
        else:
            without = model.normalizer_.inputs(run.inputs)
    assert np.ptp(with_presolve[:, 0]) > 0.05  # it steers: the QPs are constrained at times
    np.testing.assert_allclose(with_presolve, without, atol=10 * TOL)
    assert sum(counted[False]) > 0  # the active set works at all without it
    assert sum(counted[True]) < sum(counted[False])


def test_a_lifted_linear_path_follower_builds_each_speed_bands_qp_before_the_measurement(
    monkeypatch,
) -> None:
    """The speed ramps across several speed bands of the path kinematics: each band's QP is
    built in a preparation (the next band ahead of the switch), none in the feedback, and the
    inputs are the one-phase step's, which builds them when the speed gets there."""
    model = toy_linear_model()
    path = DoubleLaneChange(speed_mps=20.0).course().path()
    reference = np.column_stack([np.linspace(20.0, 21.5, 300), np.zeros(300), np.zeros(300)])
    settings = {"reference": "path", "Np": 30, "Nc": 20}
    controller = DEMPCConfig(**settings)(model, 0.01)  # type: ignore[arg-type]
    built: dict[str, list[float]] = {"act": [], "prepare": []}
    phase = ["prepare"]
    band_qp, act = controller.path._band_qp, controller.act

    def counting_band_qp(band: float, theta: np.ndarray) -> bool:
        fresh = band_qp(band, theta)
        if fresh:
            built[phase[0]].append(band)
        return fresh

    def feedback(*args, **kwargs):
        phase[0] = "act"
        try:
            return act(*args, **kwargs)
        finally:
            phase[0] = "prepare"

    monkeypatch.setattr(controller.path, "_band_qp", counting_band_qp)
    monkeypatch.setattr(controller, "act", feedback)
    plant = ModelPlant(model, x0=reference[0])
    _, run = track(plant, controller, reference, name="x", recorder=Recorder(), path=path)
    _, one_phase = _inputs(model, reference, path, real_time_iteration=False, **settings)
    speeds = run.states[:, 0]
    assert np.ptp(speeds) > 3 * 0.25  # the run crossed several bands
    assert len(built["prepare"]) >= 4 and built["act"] == []
    np.testing.assert_allclose(model.normalizer_.inputs(run.inputs), one_phase, atol=10 * TOL)
