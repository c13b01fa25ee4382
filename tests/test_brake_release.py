"""The standstill trap: a linearising DE-MPC must not hold the brake of a stopped car for good.

A stopped car under brake stays where it is: its model rightly says the pedal does nothing
there, so a QP linearised at the brake sees no gain in releasing it. ``release_brake``
linearises at the pedal released wherever the plan brakes while the reference asks for more
speed than the car has. On a toy car that stops and goes no further, both behaviours are shown.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pytest

from controllers import DEMPC, DEMPCConfig
from harness.core.contracts import Dynamics, LinearizableModel
from harness.core.episode import MinMaxNormalizer
from harness.evaluation.tracking import track
from harness.recorder import Recorder
from tests.toy_models import OwnModelPlant

DT = 0.01
THROTTLE_ACCEL = 3.0  # m/s² at full throttle (pedal feature +1)
BRAKE_ACCEL = 8.0  # m/s² at full brake (feature -1), fading to nothing at standstill
FADE_MPS = 0.5  # the brake's force ~ tanh(vx / FADE_MPS): it cannot push a stopped car back


@dataclass
class StoppingCar:
    """vx⁺ = vx + dt·a(f, vx): throttle a = 3 f (f >= 0), brake a = 8 f tanh(vx / 0.5) (f < 0),
    f the pedal's feature in [-1, 1]; vy and the yaw rate decay, steering turns the car."""

    dynamics: ClassVar[Dynamics] = "nonlinear"
    normalizer_: MinMaxNormalizer = field(
        default_factory=lambda: MinMaxNormalizer(
            np.array([0.0, -2.0, -1.0]),
            np.array([20.0, 2.0, 1.0]),
            np.array([-450.0, -1.0]),
            np.array([450.0, 1.0]),
        )
    )
    C_: np.ndarray = field(default_factory=lambda: np.eye(3))

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.normalizer_.states(np.asarray(x, dtype=float)), dtype=float)

    def _parts(self, z: np.ndarray, v: np.ndarray) -> tuple[Any, ...]:
        span_x = self.normalizer_.state_max - self.normalizer_.state_min
        vx = z[..., 0] * span_x[0] + self.normalizer_.state_min[0]
        feature = 2.0 * v[..., 1] - 1.0  # input_min -1, input_max 1: v = (f + 1) / 2
        fade = np.tanh(vx / FADE_MPS)
        throttle = feature >= 0
        accel = np.where(throttle, THROTTLE_ACCEL * feature, BRAKE_ACCEL * feature * fade)
        d_accel_d_f = np.where(throttle, THROTTLE_ACCEL, BRAKE_ACCEL * fade)
        d_accel_d_vx = np.where(throttle, 0.0, BRAKE_ACCEL * feature * (1 - fade**2) / FADE_MPS)
        return span_x, accel, d_accel_d_f, d_accel_d_vx

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        span_x, accel, _, _ = self._parts(z, v)
        out = np.array(z, dtype=float, copy=True)
        out[..., 0] = z[..., 0] + DT * accel / span_x[0]
        out[..., 1] = 0.5 + 0.95 * (z[..., 1] - 0.5)
        out[..., 2] = 0.5 + 0.95 * (z[..., 2] - 0.5) + 0.02 * (v[..., 0] - 0.5)
        return out

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        span_x, _, d_accel_d_f, d_accel_d_vx = self._parts(z, v)
        K = z.shape[0]
        A = np.zeros((K, 3, 3))
        A[:, 0, 0] = 1.0 + DT * d_accel_d_vx
        A[:, 1, 1] = A[:, 2, 2] = 0.95
        B = np.zeros((K, 3, 2))
        B[:, 0, 1] = DT * d_accel_d_f * 2.0 / span_x[0]
        B[:, 2, 0] = 0.02
        d = self.step(z, v) - np.einsum("kab,kb->ka", A, z) - np.einsum("kaj,kj->ka", B, v)
        return A, B, d


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
