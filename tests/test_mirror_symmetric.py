"""The mirror average (learners/mirror_symmetric.py): a lifted-linear model made exactly left-right
symmetric, in what it predicts and in the A, B, C that DE-MPC reads; its file; its refusals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from harness.core.episode import SEDAN_INPUTS, Episode, InputChannel, MinMaxNormalizer
from learners import DNN, EDMD, ThinPlateRBF
from learners import load as load_learner
from learners.mirror_symmetric import STATE_MIRROR, MirrorSymmetric, input_mirror

# x⁺ = A x + B u + c with a steering that speeds the car up (B[vx, steer] > 0): a linear fit's
# kind of error, which no car has. Steering drawn from [-90, 60] deg: ranges that are not
# symmetric, so the reflection is affine in the normalized units the model lives in.
A = np.array([[0.99, 0.0, 0.0], [0.0, 0.9, 0.05], [0.0, -0.05, 0.9]])
B = np.array([[0.001, 0.02], [0.002, 0.0], [0.001, 0.0]])  # columns: steer (deg), pedal
OFFSET = np.array([0.1, 0.0, 0.0])
INPUT_SIGNS = np.array([-1.0, 1.0])


def asymmetric_episodes(count: int = 3, steps: int = 300) -> list[Episode]:
    rng = np.random.default_rng(4)
    episodes = []
    for k in range(count):
        u = np.c_[rng.uniform(-90, 60, steps), rng.uniform(-2.0, 0.15, steps)]
        x = np.zeros((steps, 3))
        x[0] = np.array([10.0, 0.3, -0.1]) + rng.uniform(-1, 1, 3)
        for t in range(steps - 1):
            x[t + 1] = A @ x[t] + B @ u[t] + OFFSET
        times = np.arange(steps) * 0.01
        episodes.append(Episode(f"plant_{k}", times, x, u, np.zeros((steps, 3))))
    return episodes


def linear_edmd() -> EDMD:
    return EDMD(ThinPlateRBF(num_centers=0), ridge=0.0)


@pytest.fixture(scope="module")
def fitted() -> tuple[MirrorSymmetric, list[Episode]]:
    episodes = asymmetric_episodes()
    model = MirrorSymmetric(linear_edmd()).fit(episodes, [], MinMaxNormalizer.fit(episodes))
    return model, episodes


def linear_rollout(model: MirrorSymmetric, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """What DE-MPC predicts: z = lift(x0), z⁺ = A z + B v, x = C z in physical units."""
    normalizer = model.normalizer_
    z, states = model.lift(x0), [x0]
    for v in normalizer.inputs(u):
        z = model.A_ @ z + model.B_ @ v
        states.append(normalizer.states_inverse(model.C_ @ z))
    return np.array(states)


def test_a_mirrored_drive_is_predicted_as_the_mirror_image_of_the_drive(
    fitted: tuple[MirrorSymmetric, list[Episode]],
) -> None:
    model, episodes = fitted
    drive = episodes[1]
    x0, u = drive.states[0], drive.inputs[:-1]
    direct = model.predict(x0, u)
    mirrored = model.predict(x0 * STATE_MIRROR, u * INPUT_SIGNS)
    np.testing.assert_allclose(mirrored, direct * STATE_MIRROR, atol=1e-9)
    inner = model.inner.predict(x0 * STATE_MIRROR, u * INPUT_SIGNS)  # the fit alone is not
    assert np.abs(inner - direct * STATE_MIRROR).max() > 0.1


def test_its_steering_moves_the_speed_that_dempc_predicts_not_at_all(
    fitted: tuple[MirrorSymmetric, list[Episode]],
) -> None:
    model, _ = fitted
    vx_row = model.C_[0]
    effects = [vx_row @ np.linalg.matrix_power(model.A_, k) @ model.B_ for k in range(60)]
    steer, pedal = np.abs(np.array(effects)).max(axis=0)
    assert steer < 1e-12 < 1e-4 < pedal
    inner = model.inner
    inner_steer = [
        inner.C_[0] @ np.linalg.matrix_power(inner.A_, k) @ inner.B_[:, 0] for k in (0, 5)
    ]
    assert np.abs(inner_steer).max() > 1e-4  # the fitted model's steering did move vx


def test_a_controller_reads_the_same_model_as_predict(
    fitted: tuple[MirrorSymmetric, list[Episode]],
) -> None:
    model, episodes = fitted
    drive = episodes[2]
    x0, u = drive.states[0], drive.inputs[:200]
    assert model.A_.shape == (2 * model.inner.A_.shape[0] + 1,) * 2
    np.testing.assert_allclose(linear_rollout(model, x0, u), model.predict(x0, u), atol=1e-8)


def test_a_saved_mirror_average_loads_as_itself(
    fitted: tuple[MirrorSymmetric, list[Episode]], tmp_path: Path
) -> None:
    model, episodes = fitted
    loaded = load_learner(model.save(tmp_path / "mirror.pt"))
    assert isinstance(loaded, MirrorSymmetric) and isinstance(loaded.inner, EDMD)
    drive = episodes[0]
    np.testing.assert_array_equal(
        loaded.predict(drive.states[0], drive.inputs[:50]),
        model.predict(drive.states[0], drive.inputs[:50]),
    )
    np.testing.assert_array_equal(loaded.A_, model.A_)


def test_what_it_cannot_mirror_is_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match="nonlinear dynamics: the mirror average is built for"):
        MirrorSymmetric(DNN(hidden=[4], training={"max_steps": 1}))
    unknown = (InputChannel("steer_wheel_deg"), SEDAN_INPUTS[1])
    with pytest.raises(ValueError, match="input 'steer_wheel_deg' has no role"):
        MirrorSymmetric(linear_edmd()).check_inputs(unknown)
    lopsided = (InputChannel("steer", 1.0, 2.0, role="road_wheel", unit="rad"),)
    with pytest.raises(ValueError, match="other gains left and right"):
        input_mirror(lopsided, "the data")
    np.testing.assert_array_equal(input_mirror(SEDAN_INPUTS, "the data"), INPUT_SIGNS)
