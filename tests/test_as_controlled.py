"""A model as DE-MPC reads it: lift, its own step, the linear read-out C z."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.as_controlled import AsControlled
from controllers.linearization import BilinearLinearization
from harness.core.episode import MinMaxNormalizer
from learners import DeepEDMD
from learners.persistence import Persistence
from tests.toy_models import toy_bilinear_model, toy_linear_model
from tests.toydata import drive_episodes

INPUTS = np.column_stack([np.linspace(-90.0, 90.0, 40), np.linspace(-0.5, 0.8, 40)])


def test_a_lifted_linear_model_steps_through_a_and_b() -> None:
    model = toy_linear_model()
    x0 = np.array([18.0, 0.2, -0.05])
    normalizer = model.normalizer_
    z, by_hand = model.lift(x0), [x0]
    for v in normalizer.inputs(INPUTS):
        z = model.A_ @ z + model.B_ @ v
        by_hand.append(normalizer.states_inverse(model.C_ @ z))
    np.testing.assert_allclose(AsControlled(model).predict(x0, INPUTS), np.array(by_hand))


def test_a_bilinear_model_steps_as_its_linearisation_does() -> None:
    model = toy_bilinear_model()
    x0 = np.array([18.0, 0.2, -0.05])
    stepper, normalizer = BilinearLinearization(model), model.normalizer_
    z, by_hand = model.lift(x0), [x0]
    for v in normalizer.inputs(INPUTS):
        z = stepper.step(z, v)
        by_hand.append(normalizer.states_inverse(model.C_ @ z))
    np.testing.assert_allclose(AsControlled(model).predict(x0, INPUTS), np.array(by_hand))


def test_deep_edmd_is_read_through_c_not_through_its_decoder() -> None:
    """DE-MPC predicts x = C z; Deep EDMD's own predict goes through its decoder network."""
    episodes = drive_episodes(3, 10.0, first_seed=3)
    learner = DeepEDMD(
        lifted_dim=4,
        encoder_hidden=[8],
        decoder_hidden=[8],
        horizon=8,
        training={"max_steps": 20, "batch_size": 8, "progress": False},
    )
    learner.fit(episodes[:2], episodes[2:], MinMaxNormalizer.fit(episodes[:2]))
    x0 = episodes[2].states[100]
    z, by_hand = learner.lift(x0), [x0]
    for v in learner.normalizer_.inputs(INPUTS):
        z = learner.A_ @ z + learner.B_ @ v
        by_hand.append(learner.normalizer_.states_inverse(learner.C_ @ z))
    controlled = AsControlled(learner).predict(x0, INPUTS)
    np.testing.assert_allclose(controlled, np.array(by_hand), rtol=1e-12)
    assert np.abs(controlled - learner.predict(x0, INPUTS)).max() > 1e-6  # the decoder differs


def test_a_model_without_dynamics_has_no_controlled_reading() -> None:
    episodes = drive_episodes(2, 5.0, first_seed=3)
    held = Persistence()
    held.fit(episodes[:1], episodes[1:], MinMaxNormalizer.fit(episodes[:1]))
    with pytest.raises(ValueError, match="declares no dynamics"):
        AsControlled(held)  # type: ignore[arg-type]
