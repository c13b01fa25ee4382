"""The physics baseline: the single-track model's identification recovers a known model, its
linearisation is its step's derivative, and it is a learner and a linearizable model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from harness.core.contracts import LinearizableModel
from harness.core.episode import Episode, MinMaxNormalizer
from learners.base import load
from learners.single_track import NAMES, SingleTrack

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


def known_model() -> SingleTrack:
    model = SingleTrack()
    model.coefficients_ = np.array([TRUE[k] for k in NAMES])
    model.dt_ = 0.01
    return model


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
    assert fitted.dt_ == pytest.approx(0.01)
    physics = fitted.parameters
    assert physics["steering_ratio"] == pytest.approx(16.0, rel=1e-6)
    assert physics["cornering_stiffness_front_n_per_rad"] == pytest.approx(75.0 * 1500, rel=1e-6)
    assert physics["yaw_inertia_kg_m2"] == pytest.approx(1500 / 0.62, rel=1e-6)


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
