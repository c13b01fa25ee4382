"""controller.offset_free: a constant model error leaves no steady offset.

The plant is the controller's own model with a constant input disturbance the model does not
know (the steering wheel 15° off centre, the throttle 0.02 stronger): plain DE-MPC settles with
a steady error; with the disturbance estimate it settles on the reference.
"""

from __future__ import annotations

import numpy as np
import pytest

from controllers import DEMPCConfig
from harness.core.contracts import LiftedModel
from tests.toy_models import ModelPlant, toy_bilinear_model, toy_linear_model

OFFSET = np.array([15.0, 0.02])  # steering wheel (deg), throttle


def _settled_error(model: LiftedModel, offset_free: bool, steps: int = 1500) -> np.ndarray:
    """|x − reference| at the end of a run holding a steady turn under the disturbance; the
    turn is one the plant holds without it (30° of steering: feasible, vy and r together)."""
    plant = ModelPlant(model, x0=np.array([20.0, 0.0, 0.0]))
    start = plant.reset()
    for _ in range(3000):
        target = plant.step(np.array([30.0, 0.0]))
    reference = np.vstack([plant.reset(), np.tile(target, (steps, 1))])
    assert np.abs(target - start).max() > 0.05  # a turn, not the start
    controller = DEMPCConfig(offset_free=offset_free, Q=1000.0)(model, plant.dt)
    controller.reset(reference)
    x = reference[0]
    for k in range(steps):
        u, _ = controller.act(x, k * plant.dt)
        x = plant.step(u + OFFSET)
    return np.abs(x - target)


@pytest.mark.parametrize("model", [toy_linear_model(), toy_bilinear_model()], ids=type)
def test_the_disturbance_estimate_removes_the_steady_offset(model: LiftedModel) -> None:
    plain = _settled_error(model, offset_free=False)
    offset_free = _settled_error(model, offset_free=True)
    assert plain.max() > 3e-3  # the plain MPC settles off the reference
    assert offset_free.max() < 1e-9  # the estimate removes it


def test_the_gain_must_be_a_share() -> None:
    with pytest.raises(ValueError, match=r"controller\.offset_free_gain"):
        DEMPCConfig(offset_free=True, offset_free_gain=1.5)
