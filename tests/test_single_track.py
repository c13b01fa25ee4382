"""The physics baseline: the single-track model's identification recovers a known model, its
linearisation is its step's derivative, and it is a learner and a linearizable model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from harness.core.contracts import LinearizableModel
from harness.core.episode import SEDAN_INPUTS, Episode, InputChannel, MinMaxNormalizer
from learners.base import load
from learners.single_track import SingleTrack

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


def test_any_number_of_inputs_with_the_steering_first() -> None:
    """Logs with steering in radians and separate throttle and brake columns: the same car
    (one radian of road wheel = 16 x 57.3 degrees of steering wheel) is identified again."""
    truth = known_model()
    episodes = drives(truth)
    channels = (
        InputChannel("front_wheel_angle_rad"),
        InputChannel("throttle"),
        InputChannel("brake_mpa"),
    )
    logs = []
    for e in episodes:
        pedal = SEDAN_INPUTS[1].feature(e.inputs[:, 1])
        inputs = np.column_stack(
            [np.deg2rad(e.inputs[:, 0]) / 16.0, np.maximum(pedal, 0), np.maximum(-pedal, 0)]
        )
        logs.append(Episode(e.name, e.time_s, e.states, inputs, e.poses, channels))
    fitted = SingleTrack(max_lateral_accel_mps2=100.0).fit(logs, [], MinMaxNormalizer.fit(logs))
    assert fitted.parameters["steering_ratio"] == pytest.approx(1.0, rel=1e-6)  # per wheel rad
    np.testing.assert_allclose(fitted.coefficients_[1:3], truth.coefficients_[1:3], rtol=1e-6)
    x0, u = logs[0].states[0], logs[0].inputs[:300]
    np.testing.assert_allclose(
        fitted.predict(x0, u), truth.predict(x0, episodes[0].inputs[:300]), rtol=1e-6, atol=1e-9
    )


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
