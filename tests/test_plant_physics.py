"""The plant obeys vehicle-dynamics facts a sedan engineer would check first."""

from __future__ import annotations

import numpy as np
import pytest

from harness.plant import Sedan, SedanParams
from harness.plant.params import TireParams
from harness.plant.rollout import SpeedHold, simulate

G = 9.81


def test_understeer_gradient_is_a_sedans(characterized: dict) -> None:
    assert 1.0 <= characterized["sedan"]["understeer_gradient_deg_per_g"] <= 4.0


@pytest.mark.parametrize("name", ["sedan", "sedan_wet"])
def test_the_ramp_and_the_held_angles_measure_the_same_understeer_gradient(
    characterized: dict, name: str
) -> None:
    """ISO 4138's two constant-speed methods: a slow ramp and steering angles held until steady."""
    metrics = characterized[name]
    ramp = metrics["understeer_gradient_deg_per_g"]
    held = metrics["understeer_gradient_steady_state_deg_per_g"]
    assert held == pytest.approx(ramp, rel=0.10)


def test_the_steady_state_yaw_rate_gain_falls_with_speed_as_an_understeering_car(
    characterized: dict,
) -> None:
    """r / (v delta / L) = 1 / (1 + K v^2 / L): at small steering angles one K explains the gain
    at every speed; it is below the K fitted up to 4 m/s^2, as K grows with a_y (load transfer)."""
    by_speed = characterized["sedan"]["steady_state"]["by_speed_mps"]
    speeds = sorted(by_speed, key=float)
    gains = np.array([by_speed[v]["yaw_rate_gain_ratio"] for v in speeds])
    assert np.all(np.diff(gains) < 0)
    wheelbase = 2.7
    small_angle_k = (1 / gains - 1) * wheelbase / np.array(speeds, dtype=float) ** 2
    assert small_angle_k.std() < 0.05 * small_angle_k.mean()
    fitted = np.deg2rad([by_speed[v]["understeer_gradient_deg_per_g"] for v in speeds]) / 9.81
    assert np.all(small_angle_k < fitted)


def test_max_lateral_acceleration_sits_just_below_the_friction_limit(characterized: dict) -> None:
    for name, mu in (("sedan", 0.9), ("sedan_wet", 0.5)):
        a_max = characterized[name]["max_lateral_accel_mps2"]
        assert 0.8 * mu * G <= a_max <= mu * G, name


def test_step_steer_response_is_quick_and_well_damped(characterized: dict) -> None:
    metrics = characterized["sedan"]
    assert 0.1 <= metrics["yaw_rate_rise_time_s"] <= 0.35
    assert 1.0 <= metrics["yaw_rate_overshoot"] <= 1.2
    assert metrics["step_steer_lateral_accel_mps2"] == pytest.approx(4.0, abs=0.3)


def test_braking_from_100_kph_stops_in_40_to_50_m_when_dry(characterized: dict) -> None:
    assert 40.0 <= characterized["sedan"]["braking_distance_100kph_m"] <= 50.0


def test_wet_road_brakes_longer_and_corners_lower(characterized: dict) -> None:
    dry, wet = characterized["sedan"], characterized["sedan_wet"]
    assert wet["braking_distance_100kph_m"] > 1.3 * dry["braking_distance_100kph_m"]
    assert wet["max_lateral_accel_mps2"] < 0.7 * dry["max_lateral_accel_mps2"]


def test_low_speed_yaw_rate_is_kinematic(characterized: dict) -> None:
    assert characterized["sedan"]["kinematic_yaw_rate_error"] < 0.05


def test_coast_down_recovers_drag_and_rolling_resistance(characterized: dict) -> None:
    metrics = characterized["sedan"]
    assert metrics["drag_coefficient_fit"] == pytest.approx(
        metrics["drag_coefficient_true"], rel=0.05
    )
    assert metrics["rolling_resistance_fit"] == pytest.approx(
        metrics["rolling_resistance_true"], rel=0.1
    )


def test_throttle_range_launches_the_car_to_highway_speed(characterized: dict) -> None:
    metrics = characterized["sedan"]
    assert metrics["accel_0_100kph_s"] is not None and metrics["accel_0_100kph_s"] < 60.0
    assert 28.0 < metrics["top_speed_mps"] < 45.0


@pytest.mark.parametrize("mu", [0.9, 0.5])
def test_lateral_acceleration_never_exceeds_friction_in_a_violent_slalom(mu: float) -> None:
    plant = Sedan(SedanParams(tire=TireParams(road_friction=mu)))
    hold = SpeedHold(25.0, plant.dt)
    run = simulate(
        plant,
        lambda t, x: (450.0 * np.sin(2 * np.pi * 0.5 * t), hold(x[0])),
        8.0,
        speed_mps=25.0,
    )
    lateral = run.lateral_accel_mps2[5:]  # skip the finite-difference start
    assert np.max(np.abs(lateral)) <= 1.05 * mu * G
    assert np.max(np.abs(lateral)) >= 0.7 * mu * G  # the slalom really reached the limit


def test_understeer_grows_with_speed(sedan: Sedan) -> None:
    """Yaw-rate gain falls below the kinematic v delta / L as speed rises (r/r_kin < 1)."""
    ratios = []
    for speed in (10.0, 20.0, 30.0):
        hold = SpeedHold(speed, sedan.dt)
        run = simulate(sedan, lambda t, x, hold=hold: (20.0, hold(x[0])), 5.0, speed_mps=speed)
        vx, _, yaw_rate = run.states[-1]
        kinematic = vx * np.deg2rad(20.0 / 16.0) / 2.7
        ratios.append(yaw_rate / kinematic)
    assert ratios[0] > ratios[1] > ratios[2]
    assert 0.8 < ratios[0] < 1.0 and 0.35 < ratios[2] < 0.75


def test_car_at_rest_stays_at_rest(sedan: Sedan) -> None:
    sedan.reset()
    for _ in range(300):
        x = sedan.step((0.0, 0.0))
    assert np.max(np.abs(x)) < 1e-6
    assert np.max(np.abs(sedan.pose[:2])) < 0.01


def test_reset_repeats_a_drive_exactly_whatever_the_plant_did_before(sedan: Sedan) -> None:
    """The plant is deterministic and has no random state: ``reset`` (any seed) restores all of
    it, wheel spin, suspension and steering servo included, so a drive repeats bit for bit."""
    rng = np.random.default_rng(7)
    inputs = np.column_stack([rng.uniform(-200, 200, 300), rng.uniform(-3, 0.2, 300)])

    def drive(seed: int) -> np.ndarray:
        sedan.reset(seed=seed)
        return np.array([sedan.step(u) for u in inputs])

    first = drive(seed=3)
    sedan.reset(speed_mps=25.0)  # leave the plant far from rest: fast, steered, braking
    for _ in range(200):
        sedan.step((300.0, -5.0))
    np.testing.assert_array_equal(first, drive(seed=3))
    np.testing.assert_array_equal(first, drive(seed=11))


def test_out_of_range_inputs_are_clipped_and_counted(sedan: Sedan) -> None:
    sedan.reset()
    sedan.step((900.0, 0.5))
    sedan.step((0.0, -20.0))
    sedan.step((10.0, 0.1))
    assert sedan.clipped_inputs == 2
    np.testing.assert_array_equal(sedan.data.ctrl, [10.0, 0.1])


@pytest.mark.parametrize("bad", [(np.nan, 0.0), (0.0, np.inf)])
def test_non_finite_input_is_refused(sedan: Sedan, bad: tuple[float, float]) -> None:
    sedan.reset()
    with pytest.raises(ValueError, match="finite"):
        sedan.step(bad)
