"""The physics baseline: the single-track model's identification recovers a known model, its
linearisation is its step's derivative, and it is a learner and a linearizable model."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from harness.core.contracts import LinearizableModel
from harness.core.episode import SEDAN_INPUTS, Episode, InputChannel, MinMaxNormalizer
from learners.model_file import load
from learners.single_track import InputLayout, SingleTrack
from learners.single_track_fit import GEOMETRY_BOUNDS_M

TRUE = {
    "front_per_mass": 75.0,  # C_f / m: 112 kN/rad on 1500 kg
    "rear_per_mass": 85.0,
    "steer_per_mass": 75.0 / 16.0,  # steering ratio 16
    "mass_per_inertia": 0.62,  # I_z = 2420 kg m²
    "rolling": -0.12,
    "drag": -4e-4,
    "throttle": 4.0,
    "throttle_power": 25.0,
    "brake": 9.0,
}


def known_model(dt: float = 0.01) -> SingleTrack:
    return SingleTrack.of_physics(TRUE, dt)


def drives(model: SingleTrack, count: int = 3, steps: int = 3000, seed: int = 0) -> list[Episode]:
    """Drives of the known model under smooth random steering and pedal, from 8-25 m/s."""
    rng = np.random.default_rng(seed)
    episodes = []
    for index in range(count):
        t = np.arange(steps) * model.dt_
        steer = sum(
            rng.uniform(20, 60) * np.sin(2 * np.pi * rng.uniform(0.1, 1.0) * t + rng.uniform(0, 6))
            for _ in range(3)
        )
        pedal = 0.08 * np.sin(2 * np.pi * rng.uniform(0.05, 0.3) * t) + rng.uniform(0.0, 0.06)
        pedal = np.where(pedal >= 0, pedal, pedal * 9.1 / 0.2 * 0.3)  # some braking, in -MPa
        inputs = np.column_stack([steer, pedal])
        x0 = np.array([rng.uniform(8, 25), 0.0, 0.0])
        states = model.predict(x0, inputs[:-1])
        poses = np.zeros((steps, 3))
        episodes.append(Episode(f"drive_{index}", t, states, inputs, poses))
    return episodes


def test_the_identification_recovers_a_known_single_track_model() -> None:
    truth = known_model()
    episodes = drives(truth)
    assert min(e.states[:, 0].min() for e in episodes) > 3.0  # every sample in the fit
    fitted = SingleTrack(max_lateral_accel_mps2=100.0).fit(
        episodes, [], MinMaxNormalizer.fit(episodes)
    )
    np.testing.assert_allclose(fitted.coefficients_, truth.coefficients_, rtol=1e-6)
    assert fitted.dt_ == pytest.approx(0.01) and fitted.substeps_ == 1
    physics = fitted.parameters
    assert physics["steering_ratio"] == pytest.approx(16.0, rel=1e-6)
    assert physics["cornering_stiffness_front_n_per_rad"] == pytest.approx(75.0 * 1500, rel=1e-6)
    assert physics["yaw_inertia_kg_m2"] == pytest.approx(1500 / 0.62, rel=1e-6)


def test_without_a_and_b_the_same_model_is_identified_and_a_and_b_recovered() -> None:
    """A user's logs of a car nobody measured: the six lateral coefficients directly, then a, b,
    C_f, C_r and I_z from them (the known model has a = 1.15 m, b = 1.55 m)."""
    truth = known_model()
    episodes = drives(truth)
    fitted = SingleTrack(cg_to_front_m=None, cg_to_rear_m=None, max_lateral_accel_mps2=100.0).fit(
        episodes, [], MinMaxNormalizer.fit(episodes)
    )
    np.testing.assert_allclose(fitted.coefficients_, truth.coefficients_, rtol=1e-6)
    physics = fitted.parameters
    assert physics["cg_to_front_m"] == pytest.approx(1.15, rel=1e-5)
    assert physics["cg_to_rear_m"] == pytest.approx(1.55, rel=1e-5)
    assert physics["cornering_stiffness_rear_n_per_rad"] == pytest.approx(85.0 * 1500, rel=1e-5)
    assert physics["yaw_inertia_kg_m2"] == pytest.approx(1500 / 0.62, rel=1e-5)


@pytest.mark.parametrize("dt", [0.01, 0.05, 0.1])
def test_the_discrete_model_is_stable_at_every_period_up_to_100_ms(dt: float) -> None:
    """At min_speed_mps the lateral dynamics are fastest: one Euler step of 50 ms there has
    |1 + h λ| > 1. The sub-stepped model decays as the continuous one does: from a skid at
    3 m/s, steering held straight, vy and r fall below 1 % within 2 s at every period."""
    model = known_model(dt)
    one_step = SingleTrack.of_physics(TRUE, dt)
    one_step.substeps_ = 1
    x0 = np.array([3.0, 0.5, 0.3])
    inputs = np.zeros((round(2.0 / dt), 2))
    held = model.predict(x0, inputs)
    assert np.all(np.isfinite(held))
    assert np.all(np.abs(held[-1, 1:]) < 0.01 * np.abs(x0[1:]))
    if dt > 0.01:  # what the sub-steps are for
        assert model.substeps_ > 1
        with np.errstate(over="ignore", invalid="ignore"):
            plain = one_step.predict(x0, inputs)
        assert not np.all(np.abs(plain[-1, 1:]) < 0.01 * np.abs(x0[1:]))
    else:
        assert model.substeps_ == 1  # the sedan's 10 ms: the plain Euler step, as before


ROAD_CAR = (
    InputChannel("throttle", role="drive", unit="fraction"),
    InputChannel("front_wheel_angle_rad", role="road_wheel", unit="rad"),
    InputChannel("brake_mpa", role="brake", unit="MPa"),
)


def as_logs(
    episodes: list[Episode], channels: tuple[InputChannel, ...] = ROAD_CAR
) -> list[Episode]:
    """The sedan's drives as another car's logs: throttle, road-wheel angle in radians (one
    radian of road wheel = 16 x 57.3 degrees of steering wheel) and brake pressure, in that
    order: the steering is not the first input."""
    logs = []
    for e in episodes:
        pedal = SEDAN_INPUTS[1].feature(e.inputs[:, 1])
        inputs = np.column_stack(
            [np.maximum(pedal, 0), np.deg2rad(e.inputs[:, 0]) / 16.0, np.maximum(-pedal, 0)]
        )
        logs.append(Episode(e.name, e.time_s, e.states, inputs, e.poses, channels))
    return logs


def test_any_number_of_inputs_in_any_order_by_their_roles() -> None:
    """The same car is identified again from its roles, whatever the columns' order."""
    truth = known_model()
    episodes = drives(truth)
    logs = as_logs(episodes)
    fitted = SingleTrack(max_lateral_accel_mps2=100.0).fit(logs, [], MinMaxNormalizer.fit(logs))
    assert fitted.parameters["steering_ratio"] == pytest.approx(1.0, rel=1e-6)  # per wheel rad
    np.testing.assert_allclose(fitted.coefficients_[1:3], truth.coefficients_[1:3], rtol=1e-6)
    assert fitted.parameters["brake_mpa_on"] < 0 < fitted.parameters["throttle_on"]
    assert fitted.parameters["brake_mpa_on_power"] == 0.0  # a brake does no work per speed
    assert fitted.fit_summary["bounded"] == []  # the physics' signs held without bounds
    x0, u = logs[0].states[0], logs[0].inputs[:300]
    np.testing.assert_allclose(
        fitted.predict(x0, u), truth.predict(x0, episodes[0].inputs[:300]), rtol=1e-6, atol=1e-9
    )
    # The linearisation takes the data's column order too: B's columns are the data's.
    z, v = fitted.lift(logs[0].states[100]), fitted.normalizer_.inputs(logs[0].inputs[100])
    _, B, _ = fitted.linearize(z, v)
    h = 1e-6
    for j in range(3):
        e = np.eye(3)[j] * h
        column = (fitted.step(z, v + e) - fitted.step(z, v - e)) / (2 * h)
        np.testing.assert_allclose(B[0][:, j], column, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize(
    ("channels", "message"),
    [
        (
            (InputChannel("throttle"), *ROAD_CAR[1:]),
            r"input 'throttle' declares no role, .* set data\.inputs\.throttle\.role to one of",
        ),
        (
            (ROAD_CAR[0], ROAD_CAR[1], InputChannel("rear_angle", role="road_wheel", unit="rad")),
            r"exactly one steering input .* declares 2 \(front_wheel_angle_rad, rear_angle\)",
        ),
    ],
)
def test_inputs_whose_roles_do_not_say_what_steers_are_refused_in_one_line(
    channels: tuple[InputChannel, ...], message: str
) -> None:
    logs = as_logs(drives(known_model(), count=1, steps=400), channels)
    with pytest.raises(ValueError, match=message):
        SingleTrack().check_inputs(channels)
    with pytest.raises(ValueError, match=message):
        SingleTrack().fit(logs, [], MinMaxNormalizer.fit(logs))


def test_a_brake_that_would_accelerate_is_held_at_zero_and_named(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Drives in which pressing the brake speeds the car up (a logger's columns swapped, or
    braking that coincides with downhill): least squares would say so; physics does not."""
    truth = known_model()
    bent = []
    for e in as_logs(drives(truth)):  # vx gains 15 m/s² per unit of "brake": net, it speeds up
        states = e.states.copy()
        states[1:, 0] += np.cumsum(15.0 * e.inputs[:-1, 2] * truth.dt_)
        bent.append(dataclasses.replace(e, states=states))
    fitted = SingleTrack(max_lateral_accel_mps2=100.0).fit(bent, [], MinMaxNormalizer.fit(bent))
    assert fitted.fit_summary["bounded"] == ["brake_mpa_on"]
    assert fitted.parameters["brake_mpa_on"] == 0.0 and fitted.parameters["throttle_on"] >= 0
    (said,) = [r.getMessage() for r in caplog.records if "sign physics forbids" in r.getMessage()]
    assert said.startswith("single_track: the least-squares fit gave brake_mpa_on the sign")


def test_a_model_file_from_before_roles_keeps_its_layout() -> None:
    """No role anywhere in a fitted model's inputs: the first input steered, as it was fitted."""
    layout = InputLayout.of(
        (InputChannel("delta_deg"), InputChannel("a"), InputChannel("b")), fitting=False
    )
    assert layout.order == (0, 1, 2) and layout.steer_to_rad == pytest.approx(np.pi / 180)
    with pytest.raises(ValueError, match="declares no role"):
        InputLayout.of((InputChannel("delta_deg"), InputChannel("a")))


def test_logs_of_another_car_with_the_sedans_geometry_say_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    logs = as_logs(drives(known_model(), count=1, steps=600))
    SingleTrack(mass_kg=2000.0).fit(logs, [], MinMaxNormalizer.fit(logs))
    (said,) = [r.getMessage() for r in caplog.records if "sedan's" in r.getMessage()]
    assert said.startswith("single_track: these inputs are not the sedan's, but cg_to_front_m, ")
    assert "mass_kg" not in said  # given: not the default
    caplog.clear()
    episodes = drives(known_model(), count=1, steps=600)  # the sedan's own drives: silent
    SingleTrack().fit(episodes, [], MinMaxNormalizer.fit(episodes))
    assert not [r for r in caplog.records if "sedan's" in r.getMessage()]


def test_axles_the_data_cannot_separate_are_identified_within_a_road_cars_bounds(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A model whose a and b are a bus's (5 m, 6 m): the free fit's a and b are outside what the
    baseline takes for a road car, so a and b are fitted within the bounds and it says so."""
    bus = SingleTrack.of_physics(TRUE, 0.01, a=5.0, b=6.0)
    episodes = drives(bus, count=2, steps=1500)
    fitted = SingleTrack(cg_to_front_m=None, cg_to_rear_m=None, max_lateral_accel_mps2=100.0).fit(
        episodes, [], MinMaxNormalizer.fit(episodes)
    )
    low, high = GEOMETRY_BOUNDS_M
    physics = fitted.parameters
    for key in ("cg_to_front_m", "cg_to_rear_m"):  # recovered from θ: to a float's rounding
        assert low - 1e-9 <= physics[key] <= high + 1e-9
    assert fitted.fit_summary["geometry_bounded"] is True
    (said,) = [r.getMessage() for r in caplog.records if "cannot separate" in r.getMessage()]
    assert said.startswith("single_track: the data gives a = ")
    assert "outside [0.5, 3.5] m: it cannot separate the axles" in said


def test_the_linearisation_is_the_derivative_of_the_normalized_step() -> None:
    truth = known_model()
    episodes = drives(truth, count=1, steps=400)
    truth.normalizer_ = MinMaxNormalizer.fit(episodes)
    assert isinstance(truth, LinearizableModel)
    rng = np.random.default_rng(1)
    z = truth.lift(
        np.column_stack([rng.uniform(5, 30, 6), rng.normal(0, 0.5, 6), rng.normal(0, 0.3, 6)])
    )
    pedal = np.array([0.1, -3.0, 0.05, -1.0, 0.15, -0.5])
    v = truth.normalizer_.inputs(np.column_stack([rng.uniform(-90, 90, 6), pedal]))
    A, B, d = truth.linearize(z, v)
    h = 1e-6
    assert truth.substeps_ == 1
    for k in range(len(z)):
        for i in range(3):
            e = np.eye(3)[i] * h
            column = (truth.step(z[k] + e, v[k]) - truth.step(z[k] - e, v[k])) / (2 * h)
            np.testing.assert_allclose(A[k][:, i], column, rtol=1e-6, atol=1e-8)
        for j in range(2):
            e = np.eye(2)[j] * h
            column = (truth.step(z[k], v[k] + e) - truth.step(z[k], v[k] - e)) / (2 * h)
            np.testing.assert_allclose(B[k][:, j], column, rtol=1e-6, atol=1e-8)
    exact = np.einsum("kab,kb->ka", A, z) + np.einsum("kaj,kj->ka", B, v) + d
    np.testing.assert_allclose(exact, truth.step(z, v), atol=1e-12)
    # The normalized step is the physical Euler step.
    x = truth.normalizer_.states_inverse(z[0])
    u = truth.normalizer_.inputs_inverse(v[0])
    np.testing.assert_allclose(
        truth.normalizer_.states_inverse(truth.step(z[0], v[0])),
        truth.predict(x, u[None])[1],
        atol=1e-10,
    )


def test_the_model_file_round_trips(tmp_path: Path) -> None:
    truth = known_model()
    episodes = drives(truth, count=1, steps=400)
    fitted = SingleTrack(cg_to_front_m=1.2).fit(episodes, [], MinMaxNormalizer.fit(episodes))
    loaded = load(fitted.save(tmp_path / "model.pt"))
    assert isinstance(loaded, SingleTrack) and loaded.hyperparameters == fitted.hyperparameters
    x0, inputs = episodes[0].states[0], episodes[0].inputs[:50]
    np.testing.assert_array_equal(loaded.predict(x0, inputs), fitted.predict(x0, inputs))


def test_too_little_moving_data_is_refused_in_one_line() -> None:
    episodes = drives(known_model(), count=1, steps=400)
    with pytest.raises(ValueError, match=r"learner\.min_speed_mps"):
        SingleTrack(min_speed_mps=100.0).fit(episodes, [], MinMaxNormalizer.fit(episodes))
