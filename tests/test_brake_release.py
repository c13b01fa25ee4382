"""The standstill trap: a linearising DE-MPC must not hold the brake of a stopped car for good.

A stopped car under brake stays where it is: its model rightly says the pedal does nothing
there, so a QP linearised at the brake sees no gain in releasing it. ``release_brake``
linearises at the pedal released wherever the plan brakes while the reference asks for more
speed than the car has. On a toy car that stops and goes no further, both behaviours are shown.
"""

from __future__ import annotations

import numpy as np
import pytest

from controllers import DEMPC, DEMPCConfig
from harness.core.contracts import LinearizableModel
from harness.evaluation.tracking import track
from harness.recorder import Recorder
from tests.toy_models import DT, OwnModelPlant, StoppingCar


def stop_and_go() -> np.ndarray:
    """3 m/s braked to a stop in 1 s, held for 1 s, then 1 m/s² for 3 s (to 3 m/s)."""
    t = np.arange(500) * DT
    vx = np.where(t < 1.0, 3.0 - 3.0 * t, np.where(t < 2.0, 0.0, t - 2.0))
    return np.stack([vx, np.zeros_like(t), np.zeros_like(t)], axis=1)


def test_the_toy_car_is_a_model_whose_brake_does_nothing_at_standstill() -> None:
    model = StoppingCar()
    assert isinstance(model, LinearizableModel)
    z = model.lift(np.array([[0.0, 0.0, 0.0]]))
    brake = model.normalizer_.inputs(np.array([[0.0, -0.5]]))
    throttle = model.normalizer_.inputs(np.array([[0.0, 0.5]]))
    assert np.array_equal(model.step(z, brake), z)  # braking cannot push it backwards
    _, gain_braked, _ = model.linearize(z, brake)
    _, gain_throttled, _ = model.linearize(z, throttle)
    assert gain_braked[0, 0, 1] == 0.0 and gain_throttled[0, 0, 1] > 0.0


@pytest.mark.parametrize("horizons", [{"Np": 10, "Nc": 7}, {"Np": 60, "Nc": 50}])
def test_a_stopped_car_starts_again_only_when_the_brake_is_released(horizons: dict) -> None:
    reference = stop_and_go()
    model = StoppingCar()
    final = {}
    for release in (False, True):
        controller = DEMPC(model, DEMPCConfig(**horizons, release_brake=release))
        plant = OwnModelPlant(model, x0=reference[0])
        _, run = track(plant, controller, reference, name="x", recorder=Recorder())
        states, inputs = np.asarray(run.states), np.asarray(run.inputs)
        assert states[:, 0].min() >= 0.0
        assert states[150:200, 0].max() < 0.05  # both stop where the reference stops
        final[release] = (states[-1, 0], inputs[-1, 1])
    held_speed, held_pedal = final[False]
    assert held_speed < 0.05 and held_pedal < 0.0  # trapped: braked at a stop for good
    released_speed, released_pedal = final[True]
    assert released_speed > 2.0 and released_pedal > 0.0  # drives off after the reference
