"""harness.evaluation.quality: how smoothly a run drove, against closed forms."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from controllers import DEMPC, DEMPCConfig
from controllers.disturbance import OffsetFree
from harness.core.limits import BRAKE_MAX_MPA, THROTTLE_MAX
from harness.evaluation.quality import control_quality, pedal_changes, reversals
from harness.evaluation.tracking import track
from harness.recorder import Recorder
from tests.toy_models import ModelPlant, toy_linear_model

DT = 0.01


def run(seconds: float, steer=None, pedal=None, vx=None, vy=None, r=None) -> tuple[Any, Any]:
    """(states, inputs) sampled every DT for ``seconds``: the given functions of t, else
    straight ahead at 20 m/s with the pedal released."""
    t = np.arange(round(seconds / DT) + 1) * DT
    zeros = np.zeros_like(t)
    states = np.c_[vx(t) if vx else zeros + 20.0, vy(t) if vy else zeros, r(t) if r else zeros]
    inputs = np.c_[steer(t) if steer else zeros, pedal(t) if pedal else zeros]
    return states, inputs


def test_a_sinusoidal_steering_has_its_rate_rms_and_two_reversals_a_period() -> None:
    amplitude_deg, frequency_hz, seconds = 30.0, 0.5, 60.0
    states, inputs = run(
        seconds, steer=lambda t: amplitude_deg * np.sin(2 * np.pi * frequency_hz * t)
    )
    quality = control_quality(states, inputs, DT)
    rate_amplitude = 2 * np.pi * frequency_hz * amplitude_deg  # 94 deg/s
    assert quality["steer_rate_rms_deg_s"] == pytest.approx(rate_amplitude / np.sqrt(2), rel=1e-3)
    assert quality["steer_rate_peak_deg_s"] == pytest.approx(rate_amplitude, rel=1e-3)
    # 2 reversals a period, 30 periods a minute (the first sign is no reversal)
    assert quality["steering_reversals_per_min"] == pytest.approx(2 * frequency_hz * 60, abs=1)
    slow = control_quality(*run(seconds, steer=lambda t: 5 * np.sin(2 * np.pi * 0.5 * t)), DT)
    assert slow["steering_reversals_per_min"] == 0  # 16 deg/s at most: below the threshold


def test_a_pedal_that_flips_n_times_between_throttle_and_brake_counts_n() -> None:
    # throttle, released, brake, released, throttle, brake: 3 changes; the releases are none
    pedal = np.array([0.1, 0.1, 0.0, -1.0, -1.0, 0.01, 0.2, -0.5])
    assert pedal_changes(pedal) == 3
    assert pedal_changes(np.array([0.1, 0.0, 0.1, 0.0, 0.3])) == 0  # lifting off is no change
    states, inputs = run(60.0, pedal=lambda t: np.where(np.floor(t) % 2 == 0, 0.1, -1.0))
    quality = control_quality(states, inputs, DT)
    assert quality["pedal_changes_per_min"] == pytest.approx(59, abs=1)  # a change a second
    assert quality["brake_time_share"] == pytest.approx(0.5, abs=0.01)


def test_a_parabolic_speed_has_its_constant_second_derivative_as_jerk() -> None:
    c = 0.3  # vx = 10 + c t^2: d2vx/dt2 = 2c everywhere
    quality = control_quality(*run(10.0, vx=lambda t: 10 + c * t**2), DT)
    assert quality["long_jerk_rms_mps3"] == pytest.approx(2 * c, rel=1e-6)


def test_a_steady_circle_has_its_centripetal_acceleration_and_no_lateral_jerk() -> None:
    vx, rate = 20.0, 0.2  # a_y = vx r = 4 m/s^2, constant
    states, inputs = run(
        10.0, vx=lambda t: vx + 0 * t, vy=lambda t: -0.3 + 0 * t, r=lambda t: rate + 0 * t
    )
    quality = control_quality(states, inputs, DT)
    assert quality["lat_accel_peak_mps2"] == pytest.approx(vx * rate)
    assert quality["lat_jerk_rms_mps3"] == pytest.approx(0.0, abs=1e-9)
    assert quality["steering_reversals_per_min"] == 0 and quality["pedal_changes_per_min"] == 0


def test_the_share_of_steps_at_the_increment_bound_counts_those_at_it_or_past_it() -> None:
    # The wheel moves 2.25 deg a step (its bound) for the first quarter, then 1 deg, then holds;
    # the pedal steps past its bound (the slack) once.
    steps = np.r_[np.full(100, 2.25), np.full(100, 1.0), np.zeros(200)]
    steer = np.r_[0.0, np.cumsum(steps)]
    pedal = np.zeros(401)
    pedal[200:] = 0.01
    states = np.tile([20.0, 0.0, 0.0], (401, 1))
    shares = np.abs(np.diff(np.c_[steer, pedal], axis=0)) / np.array([2.25, 0.004])
    quality = control_quality(states, np.c_[steer, pedal], DT, shares)
    assert quality["steer_increment_limit_share"] == pytest.approx(0.25)
    assert quality["pedal_increment_limit_share"] == pytest.approx(1 / 400)
    assert "steer_increment_limit_share" not in control_quality(states, np.c_[steer, pedal], DT)


def test_de_mpc_on_its_exact_model_holds_a_constant_speed_without_touching_the_brake() -> None:
    """The controller's own model as the plant, a lane-change-like steering at constant speed:
    the pedal never changes between throttle and brake, nor lives at its increment bound, and
    the controller measures increments against the bounds it was given."""
    model = toy_linear_model()
    plant = ModelPlant(model, x0=np.array([20.0, 0.0, 0.0]))
    t = np.arange(600) * plant.dt
    steering = 60.0 * np.sin(2 * np.pi * 0.4 * t) * (t < 2.5)
    reference = np.array([plant.reset()] + [plant.step(np.array([s, 0.0])) for s in steering[:-1]])
    config = DEMPCConfig(Np=20, Nc=10, disturbance=OffsetFree())
    controller = DEMPC(model, config)
    # Its bounds per step: the wheel's in degrees; the pedal's a share of each side's range,
    # the tighter of the throttle's and the brake's, on whichever side it moves.
    pedal_share = min(
        config.throttle_increment / THROTTLE_MAX, config.brake_increment_mpa / BRAKE_MAX_MPA
    )
    u = np.array([[0.0, 0.0], [config.steer_wheel_increment_deg, -pedal_share * BRAKE_MAX_MPA]])
    np.testing.assert_allclose(controller.increment_shares(u), [[1.0, 1.0]])
    u[1, 1] = pedal_share * THROTTLE_MAX / 2
    np.testing.assert_allclose(controller.increment_shares(u), [[1.0, 0.5]])
    metrics, run = track(plant, controller, reference, name="t", recorder=Recorder())
    quality = metrics["quality"]
    assert np.ptp(run.states[:, 0]) < 0.1  # constant speed, as asked
    assert quality["pedal_changes_per_min"] == 0 and quality["brake_time_share"] == 0
    assert quality["pedal_increment_limit_share"] == 0
    assert quality["steer_increment_limit_share"] < 0.05  # a feasible reference: off its bound


def test_reversals_can_be_counted_where_a_mask_holds() -> None:
    """Three sign changes of a rate beyond the threshold; the slow one (5) is no sample; the
    mask keeps the changes that land on its samples: at a stop, say."""
    rate = np.array([30.0, -30.0, 5.0, 30.0, -30.0])
    assert reversals(rate, 20.0) == 3
    assert reversals(rate, 20.0, where=np.array([0, 1, 1, 0, 1], dtype=bool)) == 2
