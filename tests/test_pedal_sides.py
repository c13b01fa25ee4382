"""One side of the pedal at a time: the plan keeps to throttle or brake until it needs the other."""

from __future__ import annotations

import numpy as np
import pytest

from controllers import DEMPC, DEMPCConfig
from controllers.pedal_sides import PedalSides
from harness.evaluation.tracking import track
from harness.recorder import Recorder
from tests.toy_models import ModelPlant, toy_linear_model

V_MIN, V_MAX = np.array([0.0, 0.0]), np.array([1.0, 1.0])  # normalized; released pedal at 0.4
RELEASED = 0.4


def test_on_the_throttle_the_pedal_may_release_but_not_brake_and_on_the_brake_the_reverse() -> None:
    sides = PedalSides(margin_mps=0.5, released=RELEASED, vx_span=50.0)
    sides.reset(np.array([0.5, 0.6]))  # on the throttle
    low, high = sides.bounds(V_MIN, V_MAX, np.array([0.5, 0.6]))
    np.testing.assert_array_equal(low, [0.0, RELEASED])  # the wheel's bounds are untouched
    np.testing.assert_array_equal(high, V_MAX)
    sides.reset(np.array([0.5, 0.1]))  # on the brake
    low, high = sides.bounds(V_MIN, V_MAX, np.array([0.5, 0.1]))
    np.testing.assert_array_equal(low, V_MIN)
    np.testing.assert_array_equal(high, [1.0, RELEASED])


def test_a_pedal_left_on_the_other_side_comes_back_at_its_own_pace() -> None:
    """The step after the side changed, the pedal is still past released: its bound is where it
    is, so the increments' limits, not a bound, decide how fast it comes back."""
    sides = PedalSides(margin_mps=0.5, released=RELEASED, vx_span=50.0)
    sides.reset(np.array([0.5, 0.6]))
    low, _ = sides.bounds(V_MIN, V_MAX, np.array([0.5, 0.3]))  # still braking at 0.3
    assert low[1] == pytest.approx(0.3)


def test_the_other_side_opens_only_when_this_sides_plan_misses_by_more_than_the_margin() -> None:
    sides = PedalSides(margin_mps=0.5, released=RELEASED, vx_span=50.0)  # 0.01 normalized
    sides.reset(np.array([0.5, 0.6]))
    reference = np.full(10, 0.4)
    sides.update(reference + 0.009, reference)  # 0.45 m/s too fast: coasting will do
    assert not sides.braking
    sides.update(reference - 0.5, reference)  # far too slow: the throttle's problem, stays
    assert not sides.braking
    sides.update(np.r_[reference[:9], 0.411], reference)  # 0.55 m/s too fast at the horizon
    assert sides.braking
    sides.update(reference + 0.3, reference)  # too fast on the brake: stays
    sides.update(reference - 0.009, reference)
    assert sides.braking
    sides.update(reference - 0.011, reference)
    assert not sides.braking


def drive(reference: np.ndarray, margin: float | None) -> dict:
    model = toy_linear_model()
    plant = ModelPlant(model, x0=reference[0])
    config = DEMPCConfig(Np=20, Nc=10, pedal_side_margin_mps=margin)
    metrics, run = track(plant, DEMPC(model, config), reference, name="t", recorder=Recorder())
    return {**metrics["quality"], "rmse_vx": metrics["rmse"]["vx"], "pedal": run.inputs[:, 1]}


def test_on_its_exact_model_it_brakes_when_asked_and_tracks_as_well() -> None:
    """A reference that slows from 20 to 15 m/s faster than coasting: with the sides the
    controller still brakes (the plan on the throttle misses by more than the margin), and
    tracks the speed about as well as without them; it holds constant speed off the brake."""
    t = np.arange(800) * 0.01
    vx = np.clip(20.0 - 4.0 * np.clip(t - 1.0, 0.0, None), 15.0, None)
    reference = np.c_[vx, np.zeros_like(t), np.zeros_like(t)]
    free, sides = drive(reference, None), drive(reference, 0.3)
    assert np.min(sides["pedal"]) < -0.05  # it braked
    assert sides["rmse_vx"] < 1.5 * free["rmse_vx"] + 0.05
    assert sides["pedal_changes_per_min"] <= free["pedal_changes_per_min"]
    steady = drive(np.tile([20.0, 0.0, 0.0], (400, 1)), 0.3)
    assert steady["brake_time_share"] == 0
