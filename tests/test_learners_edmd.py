"""EDMD with each dictionary against analytic truth: exact A, B on linear systems; MPC contract."""

from __future__ import annotations

import numpy as np
import pytest

from harness.core.episode import Episode, MinMaxNormalizer
from learners import EDMD, DeepEDMD, RandomFeatures, ThinPlateRBF
from learners.dictionaries import ACTIVATIONS, dictionary_from
from learners.linalg import ridge_lstsq
from tests.helpers import synthetic_episodes
from tests.toydata import drive_episodes

# A lightly damped, coupled 3-state system in normalized coordinates, driven by 2 inputs.
A_TRUE = np.array([[0.95, 0.10, 0.00], [-0.10, 0.90, 0.05], [0.02, 0.00, 0.80]])
B_TRUE = np.array([[0.05, 0.00], [0.00, 0.10], [0.03, -0.02]])
NORMALIZER = MinMaxNormalizer(
    state_min=np.array([0.0, -2.0, -1.0]),
    state_max=np.array([30.0, 2.0, 1.0]),
    input_min=np.array([-450.0, -1.0]),
    input_max=np.array([450.0, 1.0]),
)


def linear_episodes(count: int = 4, steps: int = 400, seed: int = 0) -> list[Episode]:
    """z_{k+1} = A z_k + B v_k in normalized coordinates, written out in physical units:
    exactly linear in what the learners see (the pedal's two slopes included)."""
    return synthetic_episodes(
        lambda z, v: A_TRUE @ z + B_TRUE @ v,
        NORMALIZER,
        count=count,
        steps=steps,
        seed=seed,
        name="linear",
    )


def test_edmd_with_the_identity_lift_recovers_a_and_b_exactly() -> None:
    model = EDMD(ThinPlateRBF(num_centers=0), include_constant=False, ridge=0.0)
    model.fit(linear_episodes(), [], NORMALIZER)
    np.testing.assert_allclose(model.A_, A_TRUE, atol=1e-9)
    np.testing.assert_allclose(model.B_, B_TRUE, atol=1e-9)
    np.testing.assert_array_equal(model.C_, np.eye(3))


# ReLU units active on every sample are affine in x: with them [A B] is not unique, so the
# minimum-norm solution need not be the true one (and is not); every other dictionary is.
SMOOTH = [name for name in ACTIVATIONS if name != "relu"]


@pytest.mark.parametrize(
    "dictionary",
    [
        ThinPlateRBF(num_centers=20),
        *(RandomFeatures(num_features=20, activation=name) for name in SMOOTH),
    ],
    ids=["thin_plate_rbf", *(f"random_{name}" for name in SMOOTH)],
)
def test_with_x_in_the_lift_the_state_rows_are_exact_and_ignore_the_observables(
    dictionary,
) -> None:
    """z = [x; 1; phi(x)] with any dictionary: x's own rows of [A B] are the true ones, zero on
    1 and phi."""
    model = EDMD(dictionary, ridge=0.0).fit(linear_episodes(), [], NORMALIZER)
    size = model.A_.shape[0]
    assert size == 3 + 1 + 20
    np.testing.assert_allclose(model.A_[:3, :3], A_TRUE, atol=1e-6)
    np.testing.assert_allclose(model.A_[:3, 3:], 0.0, atol=1e-6)
    np.testing.assert_allclose(model.B_[:3], B_TRUE, atol=1e-6)
    np.testing.assert_array_equal(model.C_, np.eye(3, size))
    # the constant observable is propagated exactly
    np.testing.assert_allclose(model.A_[3], np.eye(size)[3], atol=1e-8)


def test_a_linear_plant_in_physical_units_is_recovered_through_the_constant_observable() -> None:
    """x_{k+1} = A x_k + B u_k (physical) is affine after min-max scaling: the 1 absorbs it."""
    rng = np.random.default_rng(1)
    a = np.array([[0.99, 0.0, 0.0], [0.0, 0.9, 0.05], [0.0, -0.05, 0.9]])
    b = np.array([[0.0, 0.5], [0.002, 0.0], [0.001, 0.0]])
    episodes = []
    for k in range(3):
        u = np.c_[rng.uniform(-90, 90, 300), rng.uniform(0.0, 0.2, 300)]  # throttle: one slope
        x = np.zeros((300, 3))
        x[0] = rng.uniform(-1, 1, 3)
        for t in range(299):
            x[t + 1] = a @ x[t] + b @ u[t]
        episodes.append(Episode(f"plant_{k}", np.arange(300) * 0.01, x, u, np.zeros((300, 3))))
    normalizer = MinMaxNormalizer.fit(episodes)
    model = EDMD(ThinPlateRBF(num_centers=0), ridge=0.0).fit(episodes, [], normalizer)
    x0, inputs = episodes[0].states[0], episodes[0].inputs[:-1]
    np.testing.assert_allclose(model.predict(x0, inputs), episodes[0].states, atol=1e-8)


def test_the_thin_plate_spline_observable_is_r2_log_r() -> None:
    rbf = ThinPlateRBF(num_centers=1)
    rbf.centers_ = np.array([[0.2, 0.3, 0.4]])
    r = np.array([0.0, 0.5, 1.0, np.exp(0.5)])
    x = rbf.centers_ + r[:, None] * np.array([0.0, 0.6, 0.8])  # unit direction
    expected = np.where(r > 0, r**2 * np.log(np.where(r > 0, r, 1.0)), 0.0)
    np.testing.assert_allclose(rbf(x)[:, 0], expected, atol=1e-12)


def test_random_features_are_the_activation_of_an_affine_map_drawn_in_its_scales() -> None:
    features = RandomFeatures(num_features=500, activation="relu", weight_scale=3.0, bias_scale=0.5)
    features.fit(np.zeros((10, 3)), np.random.default_rng(0))
    assert features.weights_.shape == (500, 3) and features.biases_.shape == (500,)
    assert np.abs(features.weights_).max() <= 3.0 and np.abs(features.weights_).max() > 2.9
    assert np.abs(features.biases_).max() <= 0.5 and np.abs(features.biases_).max() > 0.49
    x = np.array([[0.1, 0.5, 0.9]])
    expected = np.maximum(x @ features.weights_.T + features.biases_, 0.0)
    np.testing.assert_array_equal(features(x), expected)


def test_the_seed_draws_the_dictionary_and_nothing_else() -> None:
    """One seed, one draw: refits agree exactly, another seed draws other features (each
    learner draws into its own copy of a dictionary given to several)."""
    episodes = linear_episodes(count=2, steps=200)
    shared = RandomFeatures(num_features=10)

    def fit(seed: int) -> EDMD:
        return EDMD(shared, seed=seed).fit(episodes, [], NORMALIZER)

    first, again, other = fit(0), fit(0), fit(1)
    np.testing.assert_array_equal(first.A_, again.A_)
    np.testing.assert_array_equal(first.dictionary.weights_, again.dictionary.weights_)
    assert not np.allclose(first.dictionary.weights_, other.dictionary.weights_)


@pytest.mark.parametrize(
    ("target", "message"),
    [
        ("os.system", "outside the learners package"),
        ("learners.edmd.EDMD", "not a dictionary class"),
        ("learners.dictionaries.NoSuchThing", "not a dictionary class"),
    ],
)
def test_a_dictionary_is_built_only_from_a_dictionary_class_of_this_package(
    target: str, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        dictionary_from({"_target_": target, "num_centers": 3})
    built = dictionary_from({"_target_": "learners.dictionaries.ThinPlateRBF", "num_centers": 3})
    assert isinstance(built, ThinPlateRBF) and built.num_centers == 3


def test_ridge_lstsq_in_chunks_equals_lstsq_and_the_closed_form_ridge() -> None:
    rng = np.random.default_rng(0)
    w, y = rng.standard_normal((1000, 8)), rng.standard_normal((1000, 3))
    chunks = [(w[i : i + 128], y[i : i + 128]) for i in range(0, 1000, 128)]
    np.testing.assert_allclose(
        ridge_lstsq(chunks, 0.0), np.linalg.lstsq(w, y, rcond=None)[0], atol=1e-10
    )
    ridge = 0.1
    closed = np.linalg.solve(w.T @ w + ridge * 1000 * np.eye(8), w.T @ y)
    np.testing.assert_allclose(ridge_lstsq(chunks, ridge), closed, atol=1e-10)


def test_ridge_lstsq_stays_exact_where_the_normal_equations_square_the_conditioning() -> None:
    """cond(W) = 1e7, so cond(W^T W) = 1e14: noise-free data still gives the exact answer."""
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.standard_normal((500, 6)))
    w = q @ np.diag(np.logspace(0, -7, 6)) @ np.linalg.qr(rng.standard_normal((6, 6)))[0]
    theta = rng.standard_normal((6, 2))
    np.testing.assert_allclose(ridge_lstsq([(w, w @ theta)]), theta, rtol=1e-6, atol=1e-6)


def test_koopman_learners_honour_the_mpc_contract() -> None:
    """predict == iterating z+ = A z + B inputs(u) from lift(x0), x = states_inverse(C z)."""
    episodes = drive_episodes(3, 20.0)
    normalizer = MinMaxNormalizer.fit(episodes)
    models = [
        EDMD(ThinPlateRBF(num_centers=20)).fit(episodes, [], normalizer),
        EDMD(RandomFeatures(num_features=20), ridge=1e-8).fit(episodes, [], normalizer),
        DeepEDMD(
            horizon=5, prediction_output="linear", training={"max_steps": 20, "progress": False}
        ).fit(episodes, [], normalizer),
        DeepEDMD(
            horizon=5,
            lifted_includes_state=False,
            prediction_output="linear",
            training={"max_steps": 20, "progress": False},
        ).fit(episodes, [], normalizer),
    ]
    x0, inputs = episodes[0].states[300], episodes[0].inputs[300:400]
    for model in models:
        z = model.lift(x0)
        assert z.shape == (model.A_.shape[0],) and model.B_.shape == (z.size, 2)
        if model.C_.shape[1] > 3 and np.array_equal(model.C_, np.eye(3, z.size)):
            np.testing.assert_allclose(z[:3], normalizer.states(x0), atol=1e-6)
        expected = [x0]
        for u in inputs:
            z = model.A_ @ z + model.B_ @ normalizer.inputs(u)
            expected.append(normalizer.states_inverse(model.C_ @ z))
        np.testing.assert_allclose(model.predict(x0, inputs), expected, rtol=1e-6, atol=1e-6)


def test_several_ridges_are_chosen_between_on_the_validation_drives() -> None:
    """Each candidate is fitted and scored by its open-loop rollouts of the validation drives
    (mean over drives of the normalized squared RMSE summed over states); the least wins, and
    its fit is the one single ridge would give."""
    episodes = drive_episodes(5, 20.0, first_seed=30)
    normalizer = MinMaxNormalizer.fit(episodes[:3])
    ridges = [1e-10, 1e-2, 10.0]
    chosen = EDMD(ThinPlateRBF(30), ridge=ridges).fit(episodes[:3], episodes[3:], normalizer)
    scores = chosen.fit_summary["validation_scores"]
    assert set(scores) == {"1e-10", "0.01", "10"}
    best = min(ridges, key=lambda r: scores[f"{r:g}"] if scores[f"{r:g}"] is not None else np.inf)
    assert chosen.fit_summary["ridge"] == best == chosen.ridge_
    alone = EDMD(ThinPlateRBF(30), ridge=best).fit(episodes[:3], episodes[3:], normalizer)
    np.testing.assert_array_equal(chosen.A_, alone.A_)
    # The score is what it says: recomputed here for the winner.
    total = 0.0
    for e in episodes[3:]:
        error = normalizer.states(alone.predict(e.states[0], e.inputs[:-1]))[1:]
        error -= normalizer.states(e.states)[1:]
        total += float(np.sum(np.mean(error**2, axis=0)))
    assert scores[f"{best:g}"] == pytest.approx(total / 2, rel=1e-12)
    assert alone.fit_summary == {} and alone.hyperparameters["ridge"] == best


def test_several_ridges_without_validation_drives_are_refused_in_one_line() -> None:
    episodes = drive_episodes(2, 10.0, first_seed=40)
    with pytest.raises(ValueError, match=r"learner\.ridge lists 2 weights to choose from"):
        EDMD(ThinPlateRBF(5), ridge=[1e-6, 1e-2]).fit(episodes, [], MinMaxNormalizer.fit(episodes))
    with pytest.raises(ValueError, match=r"learner\.ridge must be a number >= 0 or a non-empty"):
        EDMD(ridge=[])
