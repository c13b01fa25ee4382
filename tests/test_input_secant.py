"""The pedal's flat tangent: a linearising DE-MPC must not hold a pedal whose tangent is flat.

A learned step can be flat in the pedal at one point (a fitted smooth map overshoots where the
true one bends, at the throttle-brake kink) although braking or throttle act a little further
on. A QP linearised there sees no use in moving the pedal and holds it while its reference
brakes. ``input_secant_span`` takes the input Jacobian as a secant over a part of each input's
range instead. On a toy car whose pedal acts as its cube (flat at the released pedal), both
behaviours are shown; the secant itself is checked against closed forms.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pytest

from controllers import DEMPC, DEMPCConfig
from controllers.linearization import BilinearLinearization, SecantInputs
from harness.core.contracts import Dynamics, LinearizableModel
from harness.core.episode import MinMaxNormalizer
from harness.evaluation.tracking import track
from harness.recorder import Recorder
from tests.toy_models import OwnModelPlant, toy_bilinear_model

DT = 0.01
GAIN = 8.0  # m/s²: the pedal's feature f in [-1, 1] accelerates the car by GAIN · f³
SPEED_SPAN = 40.0  # vx from 0 to 40 m/s, normalized to [0, 1]


@dataclass
class CubicPedalCar:
    """vx⁺ = vx + dt · 8 f³ (f = 2 v_pedal − 1, the pedal's feature): monotone in the pedal, its
    tangent zero at the released pedal; vy and the yaw rate decay, steering turns the car by
    0.02 sin(v_wheel − 0.5)."""

    dynamics: ClassVar[Dynamics] = "nonlinear"
    normalizer_: MinMaxNormalizer = field(
        default_factory=lambda: MinMaxNormalizer(
            np.array([0.0, -2.0, -1.0]),
            np.array([SPEED_SPAN, 2.0, 1.0]),
            np.array([-450.0, -1.0]),
            np.array([450.0, 1.0]),
        )
    )
    C_: np.ndarray = field(default_factory=lambda: np.eye(3))

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.normalizer_.states(np.asarray(x, dtype=float)), dtype=float)

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        feature = 2.0 * v[..., 1] - 1.0
        out = np.array(z, dtype=float, copy=True)
        out[..., 0] = z[..., 0] + DT * GAIN * feature**3 / SPEED_SPAN
        out[..., 1] = 0.5 + 0.95 * (z[..., 1] - 0.5)
        out[..., 2] = 0.5 + 0.95 * (z[..., 2] - 0.5) + 0.02 * np.sin(v[..., 0] - 0.5)
        return out

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        feature = 2.0 * v[:, 1] - 1.0
        A = np.zeros((len(z), 3, 3))
        A[:, 0, 0] = 1.0
        A[:, 1, 1] = A[:, 2, 2] = 0.95
        B = np.zeros((len(z), 3, 2))
        B[:, 0, 1] = DT * GAIN * 3.0 * feature**2 * 2.0 / SPEED_SPAN  # the tangent
        B[:, 2, 0] = 0.02 * np.cos(v[:, 0] - 0.5)
        d = self.step(z, v) - np.einsum("kab,kb->ka", A, z) - np.einsum("kaj,kj->ka", B, v)
        return A, B, d


def secant(model: Any, span: float = 0.2, wheel_span: float | None = None) -> SecantInputs:
    """Secants over ``span`` of each input's range (``wheel_span`` of the wheel's, if given)."""
    spans = np.array([span if wheel_span is None else wheel_span, span])
    return SecantInputs(model, spans, np.zeros(2), np.ones(2))


def test_the_toy_car_has_a_flat_tangent_where_the_pedal_is_released() -> None:
    model = CubicPedalCar()
    assert isinstance(model, LinearizableModel)
    z = model.lift(np.array([[10.0, 0.0, 0.0]]))
    released = np.array([[0.5, 0.5]])
    _, B, _ = model.linearize(z, released)
    assert B[0, 0, 1] == 0.0
    braked = model.step(z, np.array([[0.5, 0.3]]))
    assert braked[0, 0] < z[0, 0]  # yet braking slows it


def test_the_secant_of_a_cubic_pedal_is_its_closed_form() -> None:
    model = CubicPedalCar()
    z = model.lift(np.array([[10.0, 0.1, -0.2], [25.0, 0.0, 0.1]]))
    v = np.array([[0.5, 0.5], [0.3, 0.7]])
    A, B, d = secant(model, span=0.2).linearize(z, v)
    own_a, _, _ = model.linearize(z, v)
    h = 0.1  # half the span, normalized; the feature moves twice as far
    f = 2.0 * v[:, 1] - 1.0
    expected = DT * GAIN * ((f + 2 * h) ** 3 - (f - 2 * h) ** 3) / (2 * h) / SPEED_SPAN
    np.testing.assert_allclose(B[:, 0, 1], expected, rtol=1e-9)
    assert B[0, 0, 1] > 0.0  # the released pedal brakes and drives after all
    wheel = v[:, 0] - 0.5
    np.testing.assert_allclose(B[:, 2, 0], 0.02 * np.cos(wheel) * np.sin(h) / h, rtol=1e-9)
    np.testing.assert_array_equal(A, own_a)
    np.testing.assert_allclose(
        np.einsum("kab,kb->ka", A, z) + np.einsum("kaj,kj->ka", B, v) + d,
        model.step(z, v),
        rtol=1e-12,
        atol=1e-15,
    )  # exact at the point it linearises at


def test_a_span_of_zero_keeps_that_inputs_tangent() -> None:
    model = CubicPedalCar()
    z = model.lift(np.array([[10.0, 0.0, 0.0]]))
    v = np.array([[0.8, 0.5]])
    _, tangent, _ = model.linearize(z, v)
    _, mixed, _ = secant(model, span=0.2, wheel_span=0.0).linearize(z, v)
    _, both, _ = secant(model, span=0.2).linearize(z, v)
    assert mixed[0, 2, 0] == tangent[0, 2, 0] != both[0, 2, 0]  # the wheel: its own tangent
    assert mixed[0, 0, 1] == both[0, 0, 1] > tangent[0, 0, 1] == 0.0  # the pedal: the secant


def test_the_secant_stays_inside_the_input_limits() -> None:
    model = CubicPedalCar()
    z = model.lift(np.array([[10.0, 0.0, 0.0]]))
    at_full_brake = np.array([[0.5, 0.0]])
    _, B, _ = secant(model, span=0.2).linearize(z, at_full_brake)
    f_low, f_high = -1.0, 2.0 * 0.1 - 1.0  # the interval [0, 0.1], one-sided at the limit
    expected = DT * GAIN * (f_high**3 - f_low**3) / 0.1 / SPEED_SPAN
    np.testing.assert_allclose(B[0, 0, 1], expected, rtol=1e-9)


def test_the_secant_of_a_model_linear_in_its_inputs_is_its_tangent() -> None:
    model = BilinearLinearization(toy_bilinear_model())
    rng = np.random.default_rng(0)
    z = model.lift(np.array([[20.0, 0.1, 0.05], [5.0, -0.2, 0.0]]))
    v = rng.uniform(0.2, 0.8, size=(2, 2))
    _, tangent, _ = model.linearize(z, v)
    _, chord, _ = secant(model, span=0.3).linearize(z, v)
    np.testing.assert_allclose(chord, tangent, rtol=1e-9, atol=1e-12)


def braking_from_speed() -> np.ndarray:
    """10 m/s held for 0.5 s, then braked at 1 m/s² for 3 s (to 7 m/s)."""
    t = np.arange(350) * DT
    vx = np.where(t < 0.5, 10.0, 10.0 - (t - 0.5))
    return np.stack([vx, np.zeros_like(t), np.zeros_like(t)], axis=1)


@pytest.mark.parametrize("horizons", [{"Np": 10, "Nc": 7}, {"Np": 60, "Nc": 50}])
def test_a_flat_tangent_holds_the_pedal_and_the_secant_brakes(horizons: dict) -> None:
    reference = braking_from_speed()
    model = CubicPedalCar()
    errors = {}
    for span in (0.0, 0.2):
        config = DEMPCConfig(**horizons, release_brake=False, input_secant_span=span)
        controller = DEMPC(model, config)
        plant = OwnModelPlant(model, x0=reference[0])
        _, run = track(plant, controller, reference, name="x", recorder=Recorder())
        states, inputs = np.asarray(run.states), np.asarray(run.inputs)
        errors[span] = (abs(states[-1, 0] - reference[-1, 0]), inputs[-1, 1])
    held_error, held_pedal = errors[0.0]
    assert held_error > 2.0 and held_pedal == 0.0  # coasted at 10 m/s: the pedal never moved
    braked_error, braked_pedal = errors[0.2]
    assert braked_error < 0.3 and braked_pedal < -1.0  # braked (MPa) with its reference


@pytest.mark.parametrize("span", [-0.1, 1.5, float("nan"), "0.2", [0.1, 0.2, 0.3], [0.1, -0.2]])
def test_the_secant_span_is_a_fraction_of_the_range(span: Any) -> None:
    with pytest.raises(ValueError, match=r"controller\.input_secant_span"):
        DEMPCConfig(input_secant_span=span)


def test_a_span_per_input_is_accepted() -> None:
    np.testing.assert_array_equal(
        DEMPCConfig(input_secant_span=[0.0, 0.2]).secant_spans(), [0, 0.2]
    )
    np.testing.assert_array_equal(DEMPCConfig(input_secant_span=0.1).secant_spans(), [0.1, 0.1])
