"""harness.evaluation.quality: how smoothly a run drove, against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from harness.evaluation.quality import control_quality, pedal_changes

DT = 0.01


def run(seconds: float, steer=None, pedal=None, vx=None, vy=None, r=None):
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
