"""Bilinear EDMD against analytic truth: exact A, B, H of a bilinear system; its rollout; its
file; and that nothing treats it as lifted-linear."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hydra.utils import instantiate

import learners
from controllers import DEMPC, DEMPCConfig, TimeVaryingQP
from controllers.linearization import BilinearLinearization
from harness.core.contracts import BilinearModel, LiftedModel
from harness.core.episode import Episode, MinMaxNormalizer
from harness.evaluation.prediction import open_loop, rmse
from harness.tasks.closed_loops import not_lifted_linear
from learners import EDMD, ThinPlateRBF
from learners.bilinear import BilinearEDMD, bilinear_rollout
from tests.helpers import compose, synthetic_episodes
from tests.test_learners_edmd import NORMALIZER
from tests.toydata import drive_episodes

# x_n+ = A x_n + c + B v + sum_j (v_j - v0_j) H_j x_n in normalized coordinates: the input's
# effect depends on the state, as a car's steering gain depends on its speed.
A_TRUE = np.array([[0.95, 0.10, 0.00], [-0.10, 0.90, 0.05], [0.02, 0.00, 0.80]])
C_TRUE = np.array([0.02, -0.01, 0.03])  # affine part: the constant observable's column of A
B_TRUE = np.array([[0.05, 0.00], [0.00, 0.10], [0.03, -0.02]])
H_TRUE = np.array(
    [
        [[0.00, 0.04, 0.00], [0.10, 0.00, -0.05], [0.00, 0.03, 0.02]],
        [[-0.06, 0.00, 0.01], [0.00, 0.02, 0.00], [0.04, 0.00, -0.03]],
    ]
)
V0 = NORMALIZER.inputs(np.zeros(2))  # (0.5, 0.1): min-max puts "no input" inside the box


def bilinear_episodes(count: int = 4, steps: int = 400, seed: int = 0) -> list[Episode]:
    """The system above, driven by random normalized inputs, written out in physical units."""

    def step(x: np.ndarray, v: np.ndarray) -> np.ndarray:
        return A_TRUE @ x + C_TRUE + B_TRUE @ v + np.einsum("j,jnk,k", v - V0, H_TRUE, x)

    return synthetic_episodes(
        step, NORMALIZER, count=count, steps=steps, seed=seed, name="bilinear"
    )


@pytest.mark.parametrize("ridge_prior", ["identity", "zero"])
def test_bilinear_edmd_recovers_a_b_and_h_of_a_bilinear_system_exactly(ridge_prior: str) -> None:
    """z = [x_n; 1]: A = [[A, c], [0, 1]], B = [B; 0], H_j = [[H_j, 0], [0, 0]] (the input
    never multiplies the constant: v_j * 1 is B's)."""
    model = BilinearEDMD(ThinPlateRBF(num_centers=0), ridge=0.0, ridge_prior=ridge_prior)
    model.fit(bilinear_episodes(), [], NORMALIZER)
    a = np.eye(4)
    a[:3, :3], a[:3, 3] = A_TRUE, C_TRUE
    h = np.zeros((2, 4, 4))
    h[:, :3, :3] = H_TRUE
    np.testing.assert_allclose(model.A_, a, atol=1e-8)
    np.testing.assert_allclose(model.B_, np.vstack([B_TRUE, np.zeros((1, 2))]), atol=1e-8)
    np.testing.assert_allclose(model.H_, h, atol=1e-8)
    np.testing.assert_allclose(model.v0_, V0)
    np.testing.assert_array_equal(model.C_, np.eye(3, 4))


def test_a_linear_model_misses_what_the_bilinear_one_predicts_exactly() -> None:
    """The same data through EDMD: the input-times-state term is lost, the rollout is off."""
    episodes = bilinear_episodes()
    episode = episodes[0]
    bilinear = BilinearEDMD(ThinPlateRBF(num_centers=0), ridge=0.0).fit(episodes, [], NORMALIZER)
    linear = EDMD(ThinPlateRBF(num_centers=0), ridge=0.0).fit(episodes, [], NORMALIZER)
    x0, inputs = episode.states[0], episode.inputs[:-1]
    np.testing.assert_allclose(bilinear.predict(x0, inputs), episode.states, rtol=1e-7, atol=1e-7)
    span = NORMALIZER.state_max - NORMALIZER.state_min
    assert np.max(np.abs(linear.predict(x0, inputs) - episode.states) / span) > 0.02


def test_predict_iterates_the_bilinear_model_and_is_batched() -> None:
    """predict == z+ = A z + B v + sum_j (v_j - v0_j) H_j z from lift(x0), x = C z, per row."""
    episodes = bilinear_episodes(count=2)
    model = BilinearEDMD(ThinPlateRBF(num_centers=10), ridge=1e-6).fit(episodes, [], NORMALIZER)
    rng = np.random.default_rng(3)
    x0 = NORMALIZER.states_inverse(rng.uniform(0.2, 0.8, (2, 3)))
    inputs = NORMALIZER.inputs_inverse(rng.uniform(0.0, 1.0, (2, 25, 2)))
    batch = model.predict(x0, inputs)
    assert batch.shape == (2, 26, 3)
    for row in range(2):
        z, expected = model.lift(x0[row]), [x0[row]]
        for u in inputs[row]:
            v = NORMALIZER.inputs(u)
            z = model.A_ @ z + model.B_ @ v + np.einsum("j,jnk,k", v - model.v0_, model.H_, z)
            expected.append(NORMALIZER.states_inverse(model.C_ @ z))
        np.testing.assert_allclose(batch[row], expected, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(model.predict(x0[1], inputs[1]), batch[1], rtol=1e-12)
    held = model.transition(np.full(2, 0.7))
    np.testing.assert_allclose(held, model.A_ + np.einsum("j,jnk->nk", 0.7 - model.v0_, model.H_))


def test_bilinear_rollout_without_h_is_the_linear_rollout() -> None:
    from learners.edmd import linear_rollout

    rng = np.random.default_rng(0)
    a, b = 0.3 * rng.standard_normal((5, 5)), rng.standard_normal((5, 2))
    z0, v = rng.standard_normal((4, 5)), rng.standard_normal((4, 10, 2))
    zero = np.zeros((2, 5, 5))
    np.testing.assert_allclose(
        bilinear_rollout(a, b, zero, z0, v, np.full(2, 0.4)), linear_rollout(a, b, z0, v)
    )


def test_save_then_load_keeps_h_and_the_predictions(tmp_path: Path) -> None:
    episodes = bilinear_episodes(count=2)
    model = BilinearEDMD(ThinPlateRBF(num_centers=10), ridge=1e-6, ridge_prior="zero")
    model.fit(episodes, [], NORMALIZER)
    loaded = learners.load(model.save(tmp_path / "bilinear.pt"))
    assert isinstance(loaded, BilinearEDMD) and loaded.hyperparameters == model.hyperparameters
    np.testing.assert_array_equal(loaded.H_, model.H_)
    episode = episodes[1]
    np.testing.assert_array_equal(
        loaded.predict(episode.states[0], episode.inputs[:-1]),
        model.predict(episode.states[0], episode.inputs[:-1]),
    )


def test_a_bilinear_model_is_never_taken_for_a_lifted_linear_one() -> None:
    """It has A_, B_, C_, lift and normalizer_ (so LiftedModel's runtime check passes), and
    a DE-MPC reading only A_, B_ would drop H_: the controller asks the model what it is and
    linearises a bilinear one along its plan (the pipeline tracks both)."""
    episodes = bilinear_episodes(count=2)
    bilinear = BilinearEDMD(ThinPlateRBF(num_centers=0)).fit(episodes, [], NORMALIZER)
    linear = EDMD(ThinPlateRBF(num_centers=0)).fit(episodes, [], NORMALIZER)
    assert isinstance(bilinear, LiftedModel) and isinstance(bilinear, BilinearModel)
    assert isinstance(linear, LiftedModel) and not isinstance(linear, BilinearModel)
    assert not_lifted_linear(bilinear) is None and not_lifted_linear(linear) is None
    controller = DEMPC(bilinear, DEMPCConfig())
    assert isinstance(controller.qp, TimeVaryingQP)
    assert isinstance(controller.linearization, BilinearLinearization)
    np.testing.assert_array_equal(controller.linearization.H, bilinear.H_)  # H_ is read
    assert not isinstance(DEMPC(linear, DEMPCConfig()).qp, TimeVaryingQP)


def test_the_config_builds_it_and_bad_values_fail_in_one_line() -> None:
    config = compose("learner=bilinear_edmd").learner
    bad = compose("learner=bilinear_edmd", "learner.ridge_prior=ones").learner
    model = instantiate(config)
    assert isinstance(model, BilinearEDMD) and model.name == "bilinear_edmd"
    assert model.ridge_prior == "identity" and model.ridges == [1e-4]
    assert model.hyperparameters["dictionary"]["num_centers"] == 100
    with pytest.raises(Exception) as info:
        instantiate(bad)
    error = info.value.__cause__ or info.value  # Hydra wraps what the constructor raised
    assert isinstance(error, ValueError)
    assert "learner.ridge_prior must be one of" in str(error) and "\n" not in str(error)


def test_its_normalizer_puts_no_input_inside_the_box() -> None:
    """Why the bilinear term is centred: min-max puts zero steering near the middle."""
    normalizer = MinMaxNormalizer.fit(bilinear_episodes(count=1))
    v0 = normalizer.inputs(np.zeros(2))
    assert 0.3 < v0[0] < 0.7


def test_on_the_plant_it_predicts_a_held_out_drive_better_than_holding_its_start() -> None:
    """The contract every learner meets (tests/test_learners.py), with the config's ridge:
    a bounded open-loop minute, better than no model."""
    episodes = drive_episodes(6, 60.0)
    train, validation, episode = episodes[:4], episodes[4:5], episodes[5]
    normalizer = MinMaxNormalizer.fit(train)
    model = BilinearEDMD(ThinPlateRBF(num_centers=50)).fit(train, validation, normalizer)
    held = np.repeat(episode.states[:1], len(episode), 0)
    learned = open_loop(model, episode)
    assert np.all(np.isfinite(learned))
    for state, error in rmse(learned, episode.states).items():
        assert error < 0.9 * rmse(held, episode.states)[state], state
