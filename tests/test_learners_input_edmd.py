"""Input EDMD: observables of state and input, re-lifted every step. What it recovers, what it
learns that input-affine models cannot, how it chooses its ridge, and what DE-MPC reads."""

from __future__ import annotations

import numpy as np
import pytest
from hydra.utils import instantiate

from controllers import DEMPC, DEMPCConfig, TimeVaryingQP
from harness.core.contracts import LiftedModel, LinearizableModel
from harness.core.episode import Episode, MinMaxNormalizer
from harness.evaluation.prediction import open_loop, rmse
from learners import RandomFeatures, ThinPlateRBF
from learners.bilinear import BilinearEDMD
from learners.edmd import EDMD
from learners.input_edmd import InputEDMD
from tests.helpers import learner_config, synthetic_episodes
from tests.test_learners_edmd import NORMALIZER
from tests.toy_models import OwnModelPlant

DT = 0.01


def episodes_of(step, count: int = 4, steps: int = 600, seed: int = 0) -> list[Episode]:
    """Drives of x_n+ = step(x_n, v) under smooth random normalized inputs, in physical units."""
    return synthetic_episodes(
        step,
        NORMALIZER,
        count=count,
        steps=steps,
        seed=seed,
        inputs="smooth",
        start=(0.3, 0.7),
    )


def affine_step(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A linear system with an offset: inside input EDMD's span for any centres."""
    a = np.array([[-0.02, 0.01, 0.0], [0.0, -0.05, 0.02], [0.01, 0.0, -0.04]])
    b = np.array([[0.01, 0.0], [0.0, 0.02], [0.03, -0.01]])
    return x + a @ x + b @ v + np.array([0.005, -0.002, 0.001])


def saturating_step(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A yaw rate that follows tanh of the steering: its gain falls as the input grows, what a
    tyre's lateral force does in its slip angle, and no model affine in v can represent."""
    steer = np.tanh(6.0 * (v[0] - 0.5))
    return x + np.array(
        [0.05 * (v[1] - x[0]), 0.1 * (0.5 + 0.4 * steer - x[1]), 0.1 * (0.5 + 0.4 * steer - x[2])]
    )


def test_input_edmd_recovers_a_system_inside_its_span_exactly() -> None:
    model = InputEDMD(ThinPlateRBF(20, center_draw="samples"), ridge=0.0)
    model.fit(episodes_of(affine_step), [], NORMALIZER)
    held_out = episodes_of(affine_step, count=1, seed=1)[0]
    np.testing.assert_allclose(open_loop(model, held_out), held_out.states, rtol=0, atol=1e-6)
    np.testing.assert_allclose(model.theta_[5 + 1 :], 0.0, atol=1e-8)  # no RBF needed


def test_input_edmd_learns_a_saturating_input_that_bilinear_edmd_cannot() -> None:
    train, validation = episodes_of(saturating_step), episodes_of(saturating_step, 2, seed=2)
    held_out = episodes_of(saturating_step, count=1, seed=3)[0]
    errors = {}
    for name, model in (
        ("input", InputEDMD(ThinPlateRBF(150, center_draw="samples"))),
        ("bilinear", BilinearEDMD(ThinPlateRBF(150))),
    ):
        model.fit(train, validation, NORMALIZER)
        errors[name] = rmse(open_loop(model, held_out), held_out.states)["yaw_rate"]
    assert errors["input"] < 0.3 * errors["bilinear"]


def test_the_ridge_is_the_one_whose_validation_rollouts_are_best() -> None:
    train, validation = episodes_of(saturating_step), episodes_of(saturating_step, 2, seed=2)
    grid = [1e-9, 1e-6, 1e-3, 1e-1]
    model = InputEDMD(ThinPlateRBF(60, center_draw="samples"), ridge=grid)
    model.fit(train, validation, NORMALIZER)
    assert list(model.validation_scores_) == grid
    assert model.ridge_ == min(model.validation_scores_, key=model.validation_scores_.__getitem__)
    alone = InputEDMD(ThinPlateRBF(60, center_draw="samples"), ridge=model.ridge_)
    np.testing.assert_allclose(alone.fit(train, [], NORMALIZER).theta_, model.theta_)


def test_several_ridges_without_validation_drives_are_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match=r"learner\.ridge lists 2 weights") as info:
        InputEDMD(ridge=[1e-6, 1e-4]).fit(episodes_of(affine_step), [], NORMALIZER)
    assert "\n" not in str(info.value)


def test_a_fit_whose_every_ridge_diverges_is_refused_in_one_line(monkeypatch) -> None:
    monkeypatch.setattr(
        InputEDMD, "_scores", lambda self, thetas, episodes: np.full(len(thetas), np.inf)
    )
    with pytest.raises(ValueError, match="diverged on the validation drives") as info:
        InputEDMD(ThinPlateRBF(20, center_draw="samples"), ridge=[1e-6, 1e-4]).fit(
            episodes_of(affine_step), episodes_of(affine_step, 1, seed=1), NORMALIZER
        )
    assert "\n" not in str(info.value)


def held_steering(episodes: list[Episode], wander_deg: float) -> list[Episode]:
    """The drives with the wheel held at 10 deg, give or take ``wander_deg``."""
    rng = np.random.default_rng(0)
    held = []
    for e in episodes:
        inputs = e.inputs.copy()
        inputs[:, 0] = 10.0 + wander_deg * rng.uniform(size=len(e))
        held.append(Episode(e.name, e.time_s, e.states, inputs, e.poses))
    return held


@pytest.mark.parametrize("wander_deg", [0.0, 1e-9])
def test_drives_that_never_turn_the_wheel_are_refused_naming_the_learner(wander_deg) -> None:
    """Such a fit went through; its prediction of a drive that steers was NaN from the first
    steps (min-max scaling by a 1e-9 deg range), and DE-MPC failed on its QP."""
    train = held_steering(episodes_of(saturating_step), wander_deg)
    validation = held_steering(episodes_of(saturating_step, 2, seed=2), wander_deg)
    with pytest.raises(ValueError) as info:
        InputEDMD(ThinPlateRBF(60, center_draw="samples")).fit(
            train, validation, MinMaxNormalizer.fit(train)
        )
    message = str(info.value)
    assert message.startswith("input_edmd cannot learn from the training drives (")
    assert "): steer_wheel_deg stays at 10 " in message
    assert "train on drives that vary steer_wheel_deg" in message and "\n" not in message


@pytest.mark.parametrize("ridge", ["1e-4", [1e-6, "1e-4"], [], None, True])
def test_a_ridge_that_is_not_a_number_or_a_list_of_numbers_says_so(ridge) -> None:
    """A quoted ``learner.ridge='1e-4'`` is a string: it once read as '1', 'e', '-', '4'."""
    with pytest.raises(ValueError) as info:
        InputEDMD(ridge=ridge)
    assert str(info.value) == (
        f"learner.ridge must be a number >= 0 or a non-empty list of them (got {ridge!r})"
    )
    with pytest.raises(ValueError) as info:  # EDMD's ridge takes the same forms
        EDMD(ridge=ridge)
    assert str(info.value).startswith("learner.ridge must be a number >= 0 or a non-empty list")


def test_a_quoted_ridge_on_the_command_line_is_refused_in_one_line() -> None:
    with pytest.raises(Exception) as info:
        instantiate(learner_config("input_edmd", "learner.ridge='1e-4'"))
    error = info.value.__cause__ or info.value
    assert isinstance(error, ValueError)
    assert (
        str(error) == "learner.ridge must be a number >= 0 or a non-empty list of them (got '1e-4')"
    )
    assert instantiate(learner_config("input_edmd", "learner.ridge=1e-4")).ridges == [1e-4]


def test_centres_drawn_as_samples_are_distinct_data_points() -> None:
    points = np.random.default_rng(0).uniform(size=(200, 5))
    rbf = ThinPlateRBF(50, center_draw="samples").fit(points, np.random.default_rng(1))
    matches = (rbf.centers_[:, None, :] == points[None]).all(-1)
    assert matches.any(1).all() and len(np.unique(rbf.centers_, axis=0)) == 50
    with pytest.raises(ValueError, match=r"dictionary\.num_centers=300"):
        ThinPlateRBF(300, center_draw="samples").fit(points, np.random.default_rng(1))


@pytest.mark.parametrize(
    "dictionary",
    [ThinPlateRBF(30), *(RandomFeatures(30, activation=a) for a in ("tanh", "sigmoid", "sin"))],
    ids=lambda d: getattr(d, "activation", "thin_plate"),
)
def test_dictionary_jacobians_equal_finite_differences(dictionary) -> None:
    rng = np.random.default_rng(0)
    dictionary.fit(rng.uniform(size=(100, 5)), rng)
    y, h = rng.uniform(size=(4, 5)), 1e-6
    numeric = np.stack(
        [(dictionary(y + h * e) - dictionary(y - h * e)) / (2 * h) for e in np.eye(5)], axis=-1
    )
    np.testing.assert_allclose(dictionary.jacobian(y), numeric, rtol=1e-5, atol=1e-7)


@pytest.fixture(scope="module")
def fitted() -> InputEDMD:
    return InputEDMD(ThinPlateRBF(60, center_draw="samples")).fit(
        episodes_of(saturating_step), episodes_of(saturating_step, 2, seed=2), NORMALIZER
    )


def test_it_is_a_linearizable_model_and_not_a_lifted_linear_one(fitted: InputEDMD) -> None:
    assert isinstance(fitted, LinearizableModel) and not isinstance(fitted, LiftedModel)
    x = NORMALIZER.states_inverse(np.array([0.4, 0.5, 0.6]))
    np.testing.assert_allclose(fitted.lift(x), [0.4, 0.5, 0.6])
    np.testing.assert_array_equal(fitted.C_, np.eye(3))
    u = NORMALIZER.inputs_inverse(np.array([[0.7, 0.3]] * 5))
    stepped = [fitted.lift(x)]
    for v in NORMALIZER.inputs(u):
        stepped.append(fitted.step(stepped[-1], v))
    np.testing.assert_allclose(
        NORMALIZER.states_inverse(np.array(stepped)), fitted.predict(x, u), atol=1e-9
    )


def test_its_linearisation_equals_finite_differences_of_its_step(fitted: InputEDMD) -> None:
    rng = np.random.default_rng(1)
    z, v, h = rng.uniform(0.2, 0.8, (6, 3)), rng.uniform(0.2, 0.8, (6, 2)), 1e-6
    A, B, d = fitted.linearize(z, v)
    for k in range(6):
        dz = [
            (fitted.step(z[k] + h * e, v[k]) - fitted.step(z[k] - h * e, v[k])) / (2 * h)
            for e in np.eye(3)
        ]
        dv = [
            (fitted.step(z[k], v[k] + h * e) - fitted.step(z[k], v[k] - h * e)) / (2 * h)
            for e in np.eye(2)
        ]
        np.testing.assert_allclose(A[k], np.array(dz).T, atol=1e-6)
        np.testing.assert_allclose(B[k], np.array(dv).T, atol=1e-6)
    np.testing.assert_allclose(
        A @ z[..., None] + B @ v[..., None] + d[..., None], fitted.step(z, v)[..., None]
    )


def test_de_mpc_tracks_it_on_itself_through_the_time_varying_qp(fitted: InputEDMD) -> None:
    """On its own model as the plant, a steering sweep it drives itself is tracked closely."""
    x0 = NORMALIZER.states_inverse(np.array([0.5, 0.5, 0.5]))
    plant = OwnModelPlant(fitted, x0)
    u0 = NORMALIZER.inputs_inverse(np.array([0.5, 0.5]))
    steer = u0[0] + 90.0 * np.sin(2 * np.pi * 0.5 * np.arange(120) * DT)  # degrees
    reference = np.array([x0, *(plant.step(np.array([s, u0[1]])) for s in steer[:-1])])
    controller = DEMPC(fitted, DEMPCConfig(sqp_iterations=2))
    assert isinstance(controller.qp, TimeVaryingQP)
    controller.reset(reference, u_prev=u0)
    states = [plant.reset()]
    for k in range(len(reference) - 1):
        u, info = controller.act(states[-1], k * DT)
        assert not info.fallback and np.all(np.isfinite(u))
        states.append(plant.step(u))
    error = np.sqrt(np.mean((np.array(states) - reference) ** 2, axis=0))
    swing = np.ptp(reference, axis=0)  # vy and yaw rate swing with the steering, vx holds
    assert error[0] < 0.01 * (NORMALIZER.state_max - NORMALIZER.state_min)[0], error
    assert np.all(error[1:] < 0.05 * swing[1:]), (error, swing)
