"""controller.compute_delay: the clock in the loop.

With ``one_step`` the input computed from the measurement at t_k reaches the plant at t_{k+1};
over [t_k, t_{k+1}) the plant still gets the one computed a step before (u = 0 at first). DE-MPC
compensates: it steps its own model one period from the measured state under that held input
and plans from there against the reference one step on.

On a plant that is the controller's own model the prediction is exact, so the delayed loop is
the undelayed one started a period later: from the state the held u = 0 leaves (the toy's rest
point, where the references here start and stay for a step) on the reference from its second
sample on. Row k + 1 of the delayed run is row k of that one. Each step then solves the same QP
up to rounding (the state and input pass through the min-max map and back, ~1e-16), and its
optimum is Lipschitz in the QP's data, so the two runs agree to the solvers' tolerance
``controller.tol`` (1e-6 in normalized units), far below what the delay itself moves.
"""

from __future__ import annotations

import numpy as np
import pytest

from controllers import DEMPCConfig, check_controller_config
from controllers.disturbance import OffsetFree
from harness.core.contracts import LiftedModel
from harness.core.paths import CONF_DIR
from harness.evaluation.tracking import TrackingTrajectory, track
from harness.plant.rollout import closed_loop
from harness.recorder import Recorder
from harness.references import DoubleLaneChange, ReferencePath
from harness.references.course import path_metrics
from tests.helpers import compose
from tests.test_rollout import Counting, Integrator
from tests.toy_models import ModelPlant, feasible_reference, toy_bilinear_model, toy_linear_model

TOL = DEMPCConfig().tol  # the solvers' tolerance, normalized units
# Steering wheel (deg), pedal. Only the steering: the pedal's signed scale has a kink at 0
# (throttle per 0.2, brake per 9.1 MPa), where a throttle offset stops being constant in v.
OFFSET = np.array([15.0, 0.0])


def _run(
    model: LiftedModel,
    states: np.ndarray,
    loop_delay: str,
    compensated: str,
    path: ReferencePath | None = None,
    **settings: object,
) -> tuple[dict, TrackingTrajectory]:
    """Track the reference ``states`` on the model's own plant: the loop delays by
    ``loop_delay``, the controller (DE-MPC with ``settings``) compensates for ``compensated``."""
    plant = ModelPlant(model, x0=states[0])
    config = DEMPCConfig(compute_delay=compensated, **settings)  # type: ignore[arg-type]
    return track(
        plant,
        config(model, plant.dt),
        states,
        name="x",
        recorder=Recorder(),
        compute_delay=loop_delay,
        path=path,
    )


def _normalized_gap(model: LiftedModel, a: TrackingTrajectory, b: TrackingTrajectory) -> float:
    """The largest difference of two runs' states and inputs, in the model's normalized units."""
    normalizer = model.normalizer_
    states = normalizer.states(a.states) - normalizer.states(b.states)
    inputs = normalizer.inputs(a.inputs) - normalizer.inputs(b.inputs)
    return float(max(np.abs(states).max(), np.abs(inputs).max()))


def test_the_loop_holds_each_input_one_period() -> None:
    """u_k reaches the plant at t_{k+1}; u = 0 before the first arrives; one call per frame."""
    policy = Counting()  # answers (k, -k) at frame k
    run = closed_loop(Integrator(), policy, 5, delay_steps=1)
    np.testing.assert_array_equal(run.inputs[:, 0], [0, 0, 1, 2, 2])  # last row: repeated
    np.testing.assert_array_equal(run.states[:, 0], [0, 0, 0, 1, 3])  # sums of what arrived
    assert policy.calls == [0.0, 0.5, 1.0, 1.5]  # every frame measured and computed once
    undelayed = closed_loop(Integrator(), Counting(), 5)
    np.testing.assert_array_equal(undelayed.inputs[:, 0], [0, 1, 2, 3, 3])


@pytest.mark.parametrize("model", [toy_linear_model(), toy_bilinear_model()], ids=type)
def test_with_one_step_the_loop_is_the_undelayed_loop_one_period_later(model) -> None:
    reference = feasible_reference(model, steps=300)
    np.testing.assert_array_equal(reference[0], reference[1])  # at rest for the held step
    metrics, delayed = _run(model, reference, "one_step", "one_step")
    _, later = _run(model, reference[1:], "none", "none")
    assert metrics["compute_delay"] == "one_step"
    assert metrics["solver_failures"] == 0
    np.testing.assert_array_equal(delayed.inputs[0], [0.0, 0.0])  # nothing computed arrived yet
    delayed_on = TrackingTrajectory(
        delayed.time_s[1:], delayed.states[1:], delayed.inputs[1:], delayed.poses[1:]
    )
    assert _normalized_gap(model, delayed_on, later) < TOL
    # Step k's horizon starts with the state the held input leads to, exactly the next one,
    # then plans as the undelayed run does at its step k, which measured that state.
    states = model.normalizer_.states
    np.testing.assert_allclose(
        states(delayed.predicted[:-1, 0]), states(delayed.states[1:]), atol=TOL
    )
    np.testing.assert_allclose(
        states(delayed.predicted[:-2, 1:]), states(later.predicted[:-1, :-1]), atol=TOL
    )


@pytest.mark.parametrize("model", [toy_linear_model(), toy_bilinear_model()], ids=type)
def test_the_compensation_removes_the_error_an_uncompensated_delay_leaves(model) -> None:
    """The same delay, the controller unaware (compute_delay none): it plans from a state that
    is already a period old, and tracks worse than the undelayed loop; compensated, it does not
    (the previous test: the same run, a period later)."""
    reference = feasible_reference(model, steps=300)
    compensated_metrics, compensated = _run(model, reference, "one_step", "one_step")
    plain_metrics, plain = _run(model, reference, "one_step", "none")
    _, later = _run(model, reference[1:], "none", "none")

    def on(run: TrackingTrajectory) -> TrackingTrajectory:
        return TrackingTrajectory(run.time_s[1:], run.states[1:], run.inputs[1:], run.poses[1:])

    assert _normalized_gap(model, on(plain), later) > 1000 * TOL
    assert _normalized_gap(model, on(compensated), later) < TOL
    for state in ("vy", "yaw_rate"):  # steering, which the delay lags
        assert plain_metrics["rmse"][state] > 1.5 * compensated_metrics["rmse"][state]


def test_following_a_path_under_delay_predicts_the_pose_a_step_on() -> None:
    """The pose is stepped by the plant's planar kinematics under the measured state, so on
    the model's own plant the delayed path follower is the undelayed one a period later too:
    from the pose 0.2 m on (20 m/s for 10 ms), i.e. on the path moved 0.2 m back."""
    model = toy_linear_model()
    course = DoubleLaneChange(speed_mps=20.0).course()
    path = course.path()
    moved = ReferencePath.from_points(path.x_m - 0.2, path.y_m)
    reference = np.tile([20.0, 0.0, 0.0], (450, 1))  # the states say: straight on
    settings = {"reference": "path", "Np": 30, "Nc": 20}
    metrics, delayed = _run(model, reference, "one_step", "one_step", path, **settings)
    _, later = _run(model, reference[1:], "none", "none", moved, **settings)
    _, plain = _run(model, reference, "one_step", "none", path, **settings)
    assert metrics["follows_path"] and metrics["compute_delay"] == "one_step"
    np.testing.assert_allclose(delayed.poses[1:] - [0.2, 0.0, 0.0], later.poses, atol=1e-6)
    delayed_on = TrackingTrajectory(
        delayed.time_s[1:], delayed.states[1:], delayed.inputs[1:], delayed.poses[1:]
    )
    assert _normalized_gap(model, delayed_on, later) < TOL
    deviation = path_metrics(course, delayed.poses, delayed.states)["max_lateral_deviation_m"]
    uncompensated = path_metrics(course, plain.poses, plain.states)["max_lateral_deviation_m"]
    assert uncompensated > deviation + 0.05  # unaware of the delay, it strays further


class OffsetPlant(ModelPlant):
    """The model's own plant with the steering wheel 15° off centre: a constant input
    disturbance the model does not know (as test_offset_free's)."""

    def step(self, u: np.ndarray) -> np.ndarray:
        return super().step(np.asarray(u) + OFFSET)


@pytest.mark.parametrize("model", [toy_linear_model(), toy_bilinear_model()], ids=type)
def test_offset_free_under_delay_compares_each_measurement_with_its_prediction(model) -> None:
    """The disturbance estimate learns from z − ẑ, ẑ the state the delayed plan started from:
    from the second step on that prediction is the next measurement (exactly for the linear
    model, whose disturbance B·offset is constant; the bilinear one's, H·offset·z, moves with
    z and is followed a step late: within 1e-6), and the steady offset is removed."""
    plant = OffsetPlant(model, x0=np.array([20.0, 0.0, 0.0]))
    start = plant.reset()
    for _ in range(3000):
        target = ModelPlant.step(plant, np.array([30.0, 0.0]))  # a turn the plant holds
    reference = np.vstack([start, np.tile(target, (1500, 1))])
    runs = {}
    for offset_free in (False, True):
        disturbance = OffsetFree() if offset_free else None
        controller = DEMPCConfig(compute_delay="one_step", disturbance=disturbance, Q=1000.0)
        runs[offset_free] = track(
            plant,
            controller(model, plant.dt),
            reference,
            name="x",
            recorder=Recorder(),
            compute_delay="one_step",
        )
    (plain, _), (estimated, run) = runs[False], runs[True]
    states = model.normalizer_.states
    np.testing.assert_allclose(states(run.predicted[1:-1, 0]), states(run.states[2:]), atol=1e-6)
    assert max(plain["final_error"].values()) > 3e-3  # the disturbance leaves an offset
    assert max(estimated["final_error"].values()) < 1e-9  # the estimate removes it


def test_compute_delay_is_checked_and_named_in_one_line() -> None:
    with pytest.raises(ValueError) as info:
        DEMPCConfig(compute_delay="two_steps")
    message = str(info.value)
    assert "controller.compute_delay must be one of none, one_step" in message
    assert "'two_steps'" in message and "\n" not in message
    model = toy_linear_model()
    reference = feasible_reference(model, steps=10)
    with pytest.raises(ValueError, match=r"controller\.compute_delay must be one of"):
        track(
            ModelPlant(model, x0=reference[0]),
            DEMPCConfig()(model),
            reference,
            name="x",
            recorder=Recorder(),
            compute_delay="late",
        )


@pytest.mark.parametrize("name", sorted(p.stem for p in (CONF_DIR / "controller").glob("*.yaml")))
def test_every_controller_config_takes_compute_delay_from_the_command_line(name: str) -> None:
    default = compose(f"controller={name}")
    delayed = compose(f"controller={name}", "controller.compute_delay=one_step")
    assert check_controller_config(default.controller).compute_delay == "none"
    assert check_controller_config(delayed.controller).compute_delay == "one_step"


def test_one_switch_puts_every_controller_of_the_run_on_the_same_clock() -> None:
    """task.compute_delay=one_step: the run's controller and every extra one (the baseline
    too) apply each input one period after its measurement; null leaves each its own."""
    from hydra import compose, initialize_config_module
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    def controllers(*overrides: str) -> dict:
        with initialize_config_module(config_module="conf", version_base=None):
            cfg = compose(
                "config",
                overrides=["task.learner_name=edmd", "task.controller_name=main", *overrides],
            )
        return instantiate(cfg.task).closed_loops.controllers

    delayed = controllers("task.compute_delay=one_step")
    assert len(delayed) == 8 and {c.compute_delay for c in delayed.values()} == {"one_step"}
    assert {c.compute_delay for c in controllers().values()} == {"none"}
    with pytest.raises(InstantiationException, match=r"task\.compute_delay must be one of"):
        controllers("task.compute_delay=two_steps")
