"""controller.disturbance: a constant model error leaves no steady offset.

The plant is the controller's own model with a constant input disturbance the model does not
know (the steering wheel 15° off centre, the throttle 0.02 stronger): plain DE-MPC settles with
a steady error; with a disturbance estimator (offset-free, or a Kalman filter) it settles on
the reference.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from controllers import DEMPCConfig
from controllers.disturbance import DisturbanceEstimator, KalmanDisturbance, OffsetFree
from harness.core.contracts import LiftedModel
from tests.toy_models import ModelPlant, StoppingCar, toy_bilinear_model, toy_linear_model

OFFSET = np.array([15.0, 0.02])  # steering wheel (deg), throttle


def _settled_error(
    model: LiftedModel, disturbance: DisturbanceEstimator | None, steps: int = 1500
) -> np.ndarray:
    """|x − reference| at the end of a run holding a steady turn under the disturbance; the
    turn is one the plant holds without it (30° of steering: feasible, vy and r together)."""
    plant = ModelPlant(model, x0=np.array([20.0, 0.0, 0.0]))
    start = plant.reset()
    for _ in range(3000):
        target = plant.step(np.array([30.0, 0.0]))
    reference = np.vstack([plant.reset(), np.tile(target, (steps, 1))])
    assert np.abs(target - start).max() > 0.05  # a turn, not the start
    controller = DEMPCConfig(disturbance=disturbance, Q=1000.0)(model, plant.dt)
    controller.reset(reference)
    x = reference[0]
    for k in range(steps):
        u, _ = controller.act(x, k * plant.dt)
        x = plant.step(u + OFFSET)
    return np.abs(x - target)


@pytest.mark.parametrize("model", [toy_linear_model(), toy_bilinear_model()], ids=type)
def test_a_disturbance_estimate_removes_the_steady_offset(model: LiftedModel) -> None:
    plain = _settled_error(model, None)
    assert plain.max() > 3e-3  # the plain MPC settles off the reference
    assert _settled_error(model, OffsetFree()).max() < 1e-9  # the estimate removes it
    # A Kalman filter's gain settles to a share below 1: the same offset, removed more slowly.
    assert _settled_error(model, KalmanDisturbance(), steps=3000).max() < 1e-6


def _held_at_rest(model: Any, disturbance: DisturbanceEstimator, steps: int = 300) -> np.ndarray:
    """The largest |w| per coordinate the estimator held while a car rolls to a stop at
    0.1 m/s² whatever its inputs (slower than 1 m/s), its model believing its wheel turns it
    (both toys' steering moves the yaw rate at any speed), asked for a small yaw rate."""
    reference = np.tile([0.0, 0.0, 0.02], (steps + 1, 1))
    controller = DEMPCConfig(disturbance=disturbance, Q=1000.0)(model, 0.01)
    controller.reset(reference)
    largest = np.zeros(np.shape(model.C_)[1])
    for k in range(steps):
        controller.act(np.array([0.9 - 0.001 * k, 0.0, 0.0]), k * 0.01)
        largest = np.maximum(largest, np.abs(controller.disturbance.w))
    return largest


@pytest.mark.parametrize("estimator", [OffsetFree, KalmanDisturbance])
def test_a_stopped_car_teaches_a_model_of_x_no_lateral_motion(estimator: type) -> None:
    """Below ``lateral_min_speed_mps`` a model that steps x itself (z = x) gets w without vy's
    and r's parts (a stopped car has no lateral motion: the error there is the model's answer
    to the last wheel move); the speed's part is still learned, for it tracks the stop."""
    vx, _, r = _held_at_rest(StoppingCar(), estimator())
    assert min(vx, r) > 1e-4  # at any speed, the stop's errors are learned
    vx, vy, r = _held_at_rest(StoppingCar(), estimator(lateral_min_speed_mps=1.0))
    assert vy == 0.0 and r == 0.0
    assert vx > 1e-4


def test_a_lifted_models_estimate_is_left_whole_at_a_stop() -> None:
    """Its lateral error lives in every lifted coordinate: w is not cut."""
    model = toy_linear_model()  # z = [x_norm; 1]
    whole = _held_at_rest(model, OffsetFree())
    np.testing.assert_array_equal(
        _held_at_rest(model, OffsetFree(lateral_min_speed_mps=1.0)), whole
    )
    assert whole[2] > 1e-4


def test_the_estimate_still_removes_the_offset_above_its_speed() -> None:
    model = toy_linear_model()
    assert _settled_error(model, OffsetFree(lateral_min_speed_mps=1.0)).max() < 1e-9  # 20 m/s


def test_the_kalman_gain_starts_near_one_and_settles_to_its_steady_state() -> None:
    """Per coordinate, the scalar Riccati recursion: P⁻ = P + q, K = P⁻ / (P⁻ + r)."""
    kalman = KalmanDisturbance(process_variance=1e-4, measurement_variance=1e-2)
    kalman.start(2)
    error = np.array([1.0, -2.0])
    first = kalman.update(error).copy()
    np.testing.assert_allclose(first, error * (1.0001 / (1.0001 + 1e-2)), rtol=1e-12)
    for _ in range(2000):
        before = kalman.w.copy()
        kalman.update(np.zeros(2))
    gain = kalman.steady_gain()
    assert 0 < gain < 0.2  # a slow walk seen through noisy errors: a small gain
    kalman.update(np.ones(2))
    np.testing.assert_allclose(kalman.w - before, gain, rtol=1e-9)
    assert kalman.update(None) is kalman.w  # the first step of a run: nothing to learn from


def test_every_estimator_is_fresh_in_each_controller_and_each_run() -> None:
    """The config's estimator is a template: two controllers built from it share no state."""
    config = DEMPCConfig(disturbance=OffsetFree(gain=0.5))
    first, second = config(toy_linear_model()), config(toy_linear_model())
    assert first.disturbance is not second.disturbance
    assert first.disturbance is not config.disturbance


@pytest.mark.parametrize(
    ("disturbance", "message"),
    [
        (OffsetFree, r"controller\.disturbance\.gain must be"),
        (KalmanDisturbance, r"controller\.disturbance\.process_variance must be"),
    ],
)
def test_an_estimators_settings_are_checked(disturbance: type, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        disturbance(**({"gain": 1.5} if disturbance is OffsetFree else {"process_variance": -1}))
    with pytest.raises(ValueError, match=r"disturbance\.lateral_min_speed_mps must be"):
        disturbance(lateral_min_speed_mps=-1.0)


def test_a_disturbance_that_is_no_estimator_is_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match=r"controller\.disturbance must be null or an estimator"):
        DEMPCConfig(disturbance={"gain": 1.0})


def test_the_presets_compose_their_estimator_and_a_user_swaps_it_by_name() -> None:
    with initialize_config_module(config_module="conf", version_base=None):
        main = compose("config")
        kalman = compose("config", overrides=["disturbance@controller.disturbance=kalman"])
        plain = compose("config", overrides=["controller=de_mpc"])
    assert isinstance(instantiate(main.controller).disturbance, OffsetFree)
    assert isinstance(instantiate(kalman.controller).disturbance, KalmanDisturbance)
    assert instantiate(plain.controller).disturbance is None
