"""The pedal split (learners/split_pedal.py): a model affine in throttle and brake, read as a
model of the signed pedal, exactly; its file; its linearisation for DE-MPC."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controllers.de_mpc import DEMPC, DEMPCConfig
from harness.core.episode import SEDAN_INPUTS, Episode, MinMaxNormalizer
from learners import EDMD, ThinPlateRBF
from learners import load as load_learner
from learners.split_pedal import SplitPedal, split_normalizer, split_pedal

# x⁺ = a x + b_steer steer + b_throttle max(p, 0) - b_brake max(-p, 0) + c, in the pedal's
# feature p in [-1, 1]: braking five times as strong per unit as throttle, as the sedan's.
A = np.array([[0.99, 0.0, 0.0], [0.0, 0.9, 0.05], [0.0, -0.05, 0.9]])
B_STEER = np.array([0.0, 0.002, 0.001])
B_THROTTLE = np.array([0.015, 0.0, 0.0])
B_BRAKE = np.array([0.075, 0.0, 0.0])
OFFSET = np.array([0.1, 0.0, 0.0])


def two_slope_episodes(count: int = 3, steps: int = 300) -> list[Episode]:
    rng = np.random.default_rng(2)
    episodes = []
    for k in range(count):
        feature = rng.uniform(-1.0, 1.0, steps)
        u = np.c_[rng.uniform(-90, 90, steps), SEDAN_INPUTS[1].value(feature)]
        x = np.zeros((steps, 3))
        x[0] = np.array([10.0, 0.0, 0.0]) + rng.uniform(-1, 1, 3)
        for t in range(steps - 1):
            pedal = B_THROTTLE * max(feature[t], 0.0) - B_BRAKE * max(-feature[t], 0.0)
            x[t + 1] = A @ x[t] + B_STEER * u[t, 0] + pedal + OFFSET
        times = np.arange(steps) * 0.01
        episodes.append(Episode(f"plant_{k}", times, x, u, np.zeros((steps, 3))))
    return episodes


def linear_edmd() -> EDMD:
    return EDMD(ThinPlateRBF(num_centers=0), ridge=0.0)


@pytest.fixture(scope="module")
def fitted() -> tuple[SplitPedal, list[Episode]]:
    episodes = two_slope_episodes()
    model = SplitPedal(linear_edmd()).fit(episodes, [], MinMaxNormalizer.fit(episodes))
    return model, episodes


def test_the_split_normalizer_is_the_one_fitted_on_the_split_drives() -> None:
    episodes = two_slope_episodes()
    derived = split_normalizer(MinMaxNormalizer.fit(episodes), column=1)
    assert derived.same_as(MinMaxNormalizer.fit([split_pedal(e) for e in episodes]))
    assert derived.input_names == ("steer_wheel_deg", "throttle", "brake")


def test_a_plant_with_two_pedal_slopes_is_recovered_exactly_only_with_the_split(
    fitted: tuple[SplitPedal, list[Episode]],
) -> None:
    model, episodes = fitted
    drive = episodes[0]
    np.testing.assert_allclose(
        model.predict(drive.states[0], drive.inputs[:-1]), drive.states, atol=1e-8
    )
    one_slope = linear_edmd().fit(episodes, [], MinMaxNormalizer.fit(episodes))
    error = one_slope.predict(drive.states[0], drive.inputs[:-1]) - drive.states
    assert np.sqrt(np.mean(error[:, 0] ** 2)) > 0.01  # m/s: one slope cannot be both


def test_its_step_is_the_inner_models_on_throttle_and_brake_and_its_file_round_trips(
    fitted: tuple[SplitPedal, list[Episode]], tmp_path: Path
) -> None:
    model, episodes = fitted
    drive = split_pedal(episodes[1])
    z = model.lift(episodes[1].states[:50])
    v = model.normalizer_.inputs(episodes[1].inputs[:50])
    w = model.inner.normalizer_.inputs(drive.inputs[:50])
    inner = model.inner
    np.testing.assert_allclose(model.step(z, v), z @ inner.A_.T + w @ inner.B_.T, atol=1e-12)
    loaded = load_learner(model.save(tmp_path / "model.pt"))
    assert isinstance(loaded, SplitPedal) and isinstance(loaded.inner, EDMD)
    np.testing.assert_allclose(loaded.step(z, v), model.step(z, v), atol=1e-12)
    assert loaded.hyperparameters == model.hyperparameters
    assert loaded.core is loaded.inner and loaded.inner.core is loaded.inner  # curves, spectrum


def test_its_linearisation_has_each_sides_slope_and_their_mean_at_the_released_pedal(
    fitted: tuple[SplitPedal, list[Episode]],
) -> None:
    model, _ = fitted
    state = np.array([[12.0, 0.1, 0.05]] * 3)
    z = model.lift(state)
    v = model.normalizer_.inputs(np.array([[10.0, 0.1], [10.0, -3.0], [10.0, 0.0]]))
    A, B, d = model.linearize(z, v)
    h = 1e-4  # within each side: the slope of its own step
    up, down = v.copy(), v.copy()
    up[:, 1] += h
    down[:, 1] -= h
    slopes = (model.step(z, up) - model.step(z, down)) / (2 * h)
    np.testing.assert_allclose(B[:2, :, 1], slopes[:2], atol=1e-9)
    np.testing.assert_allclose(B[2, :, 1], slopes[2], atol=1e-9)  # the central difference: mean
    one_sided = (model.step(z, up) - model.step(z, v)) / h
    assert abs(B[2, 0, 1] - one_sided[2, 0]) > 1e-3  # the kink: not the throttle side's
    exact = np.einsum("kab,kb->ka", A, z) + np.einsum("kab,kb->ka", B, v) + d
    np.testing.assert_allclose(exact, model.step(z, v), atol=1e-12)


def test_de_mpc_drives_a_split_model_as_a_model_it_linearises(
    fitted: tuple[SplitPedal, list[Episode]],
) -> None:
    model, _ = fitted
    controller = DEMPC(model, DEMPCConfig(Np=10, Nc=7))
    reference = np.tile([12.0, 0.0, 0.0], (200, 1))
    controller.reset(reference)
    u, info = controller.act(np.array([10.0, 0.0, 0.0]), 0.0)
    assert np.all(np.isfinite(u)) and u[1] > 0  # 2 m/s slow: throttle
    del info


def test_data_without_the_pedal_named_is_refused_in_one_line() -> None:
    episodes = two_slope_episodes(count=1)
    with pytest.raises(ValueError, match="the data has no 'brake_mpa' input"):
        SplitPedal(linear_edmd(), pedal="brake_mpa").fit(
            episodes, [], MinMaxNormalizer.fit(episodes)
        )
    with pytest.raises(ValueError, match="split the pedal once"):
        SplitPedal(SplitPedal(linear_edmd()))


def test_a_model_file_is_the_configured_learner_whatever_its_inner_training_budget() -> None:
    from learners import DeepEDMD
    from learners.model_file import check_same_learner

    def split(**training: float) -> SplitPedal:
        return SplitPedal(DeepEDMD(training={"max_steps": 100, **training}))

    check_same_learner(split(max_steps=50), split(), "m.pt", "deep_edmd_split")
    with pytest.raises(ValueError, match=r"learner\.inner\.training\.lr=0\.5"):
        check_same_learner(split(lr=0.5), split(), "m.pt", "deep_edmd_split")
