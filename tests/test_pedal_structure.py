"""The pedal benchmark's two tools: the split keeps the pedal, the slopes are the plant's."""

import numpy as np
import pytest

from bench.pedal_structure import pedal_slopes, split_pedal
from harness.core.episode import SEDAN_INPUTS, Episode, InputChannel

DT_S = 0.01


def _pair(
    name: str, vx: float, feature: float, throttle_slope: float, brake_slope: float
) -> Episode:
    """Two samples whose acceleration is 0.2 - 0.03 vx + the pedal's slope on its side."""
    slope = throttle_slope if feature >= 0 else brake_slope
    acceleration = 0.2 - 0.03 * vx + slope * feature
    pedal = SEDAN_INPUTS[1].value(np.array([feature, feature]))
    return Episode(
        name,
        np.array([0.0, DT_S]),
        np.array([[vx, 0.1, 0.02], [vx + DT_S * acceleration, 0.1, 0.02]]),
        np.stack([np.array([5.0, 5.0]), pedal], axis=1),
        np.zeros((2, 3)),
    )


def test_the_split_keeps_the_other_inputs_and_the_pedal_as_throttle_minus_brake() -> None:
    rng = np.random.default_rng(0)
    feature = rng.uniform(-1, 1, 50)
    steer = rng.uniform(-90, 90, 50)
    episode = Episode(
        "e",
        np.arange(50) * DT_S,
        np.zeros((50, 3)),
        np.stack([steer, SEDAN_INPUTS[1].value(feature)], axis=1),
        np.zeros((50, 3)),
    )
    split = split_pedal(episode)
    assert split.input_names == ("steer_wheel_deg", "throttle", "brake")
    np.testing.assert_allclose(split.inputs[:, 0], steer)
    np.testing.assert_allclose(split.inputs[:, 1] - split.inputs[:, 2], feature, atol=1e-12)
    assert (split.inputs[:, 1:] >= 0).all() and (split.inputs[:, 1] * split.inputs[:, 2] == 0).all()


def test_the_slopes_are_the_planted_ones_in_each_speed_band() -> None:
    """Throttle 1.5 m/s² per unit below 10 m/s and 0.6 above, brake 7.5 throughout."""
    rng = np.random.default_rng(1)
    episodes = []
    for k in range(4000):
        vx = rng.uniform(0.5, 20.0)
        throttle = 1.5 if vx < 10.0 else 0.6
        episodes.append(_pair(f"e{k}", vx, rng.uniform(-1, 1), throttle, 7.5))
    slopes = pedal_slopes(episodes)
    assert set(slopes) == {(0.5, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 20.0)}
    for (low, _), (throttle, brake, samples) in slopes.items():
        assert throttle == pytest.approx(1.5 if low < 10.0 else 0.6, rel=1e-6)
        assert brake == pytest.approx(7.5, rel=1e-6)
        assert samples > 100


def test_data_without_a_pedal_is_refused_in_one_line() -> None:
    episode = _pair("e", 10.0, 0.5, 1.5, 7.5)
    logs = Episode(
        "run_1",
        episode.time_s,
        episode.states,
        episode.inputs,
        episode.poses,
        (InputChannel("steer"), InputChannel("throttle")),
    )
    with pytest.raises(ValueError, match="run_1 has no 'pedal' input \\(steer, throttle\\)"):
        split_pedal(logs)
    with pytest.raises(ValueError, match="no 'pedal' input"):
        pedal_slopes([logs])


def test_the_plants_pedal_effects_have_their_sign_from_the_first_step_and_grow() -> None:
    """bench.pedal_effects' reference row: throttle speeds the car up, the brake slows it, from
    the first 10 ms on, and a held pedal's effect grows with time."""
    from bench.pedal_effects import plant_effect

    throttle = plant_effect(22.0, 0.1, 30)
    brake = plant_effect(22.0, -3.0, 30)
    assert (throttle > 0).all() and (brake < 0).all()
    assert (np.diff(throttle) > 0).all() and (np.diff(brake) < 0).all()
    assert abs(brake[0]) > 3 * throttle[0]  # 3 MPa brake outweighs 0.1 throttle
