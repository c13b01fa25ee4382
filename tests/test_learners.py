"""The learner contract, for all four learners: fit, predict, save/load, configs, bad values."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

import learners
from harness.data.episode import Episode, MinMaxNormalizer
from harness.paths import CONF_DIR
from harness.prediction import open_loop, rmse
from learners import DNN, EDMD, ELMEDMD, DeepEDMD, KoopmanLearner, Learner
from tests.toydata import drive_episodes

NAMES = ("edmd", "elm_edmd", "dnn", "deep_edmd")

# Budgets small enough for a unit test (seconds), large enough to learn something.
TINY = {
    "edmd": lambda: EDMD(num_centers=50),
    "elm_edmd": lambda: ELMEDMD(num_features=50),
    "dnn": lambda: DNN(
        hidden=[64, 64],
        horizon=20,
        training={
            "max_steps": 2000,
            "batch_size": 32,
            "lr": 1e-2,
            "eval_every_steps": 100,
            "progress": False,
        },
    ),
    "deep_edmd": lambda: DeepEDMD(
        horizon=10,
        refit_koopman_lstsq=True,
        training={
            "max_steps": 300,
            "batch_size": 32,
            "lr": 3e-3,
            "eval_every_steps": 100,
            "progress": False,
        },
    ),
}


@pytest.fixture(scope="module")
def data() -> dict:
    """Four 60 s training drives, one for validation, one held out; normalizer on training."""
    episodes = drive_episodes(6, 60.0)
    train, validation, test = episodes[:4], episodes[4:5], episodes[5]
    return {
        "train": train,
        "validation": validation,
        "test": test,
        "normalizer": MinMaxNormalizer.fit(train),
    }


@pytest.fixture(scope="module")
def fitted(data: dict) -> dict[str, Learner]:
    return {
        name: make().fit(data["train"], data["validation"], data["normalizer"])
        for name, make in TINY.items()
    }


def compose_learner(name: str, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=[f"learner={name}", *overrides]).learner


@pytest.mark.parametrize("name", NAMES)
def test_a_fitted_learner_predicts_a_held_out_drive_better_than_holding_its_start(
    name: str, fitted: dict[str, Learner], data: dict
) -> None:
    """Open loop over the whole held-out minute from rest, RMSE in normalized units summed."""
    episode, span = data["test"], data["normalizer"].state_max - data["normalizer"].state_min
    held = np.repeat(episode.states[:1], len(episode), 0)
    learned = open_loop(fitted[name], episode)

    def score(prediction: np.ndarray) -> float:
        return float(np.sum(np.array(list(rmse(prediction, episode.states).values())) / span))

    assert score(learned) < 0.9 * score(held)
    assert rmse(learned, episode.states)["vx"] < 0.9 * rmse(held, episode.states)["vx"]


@pytest.mark.parametrize("name", NAMES)
def test_predict_is_batched_and_starts_at_x0(name: str, fitted: dict[str, Learner]) -> None:
    learner, rng = fitted[name], np.random.default_rng(0)
    x0 = np.array([[10.0, 0.1, 0.05], [5.0, -0.1, -0.02]])
    inputs = np.stack([np.c_[rng.uniform(-90, 90, 30), rng.uniform(-2, 0.2, 30)]] * 2)
    batch = learner.predict(x0, inputs)
    assert batch.shape == (2, 31, 3)
    np.testing.assert_array_equal(batch[:, 0], x0)
    one = learner.predict(x0[1], inputs[1])
    np.testing.assert_allclose(one, batch[1], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", NAMES)
def test_save_then_load_gives_identical_predictions(
    name: str, fitted: dict[str, Learner], data: dict, tmp_path: Path
) -> None:
    learner, episode = fitted[name], data["test"]
    path = learner.save(tmp_path / f"{name}.pt")
    loaded = learners.load(path)
    assert type(loaded) is type(learner) and loaded.hyperparameters == learner.hyperparameters
    np.testing.assert_array_equal(open_loop(loaded, episode), open_loop(learner, episode))
    assert type(learner).load(path).hyperparameters == learner.hyperparameters
    if isinstance(learner, KoopmanLearner):
        for attr in ("A_", "B_", "C_"):
            np.testing.assert_array_equal(getattr(loaded, attr), getattr(learner, attr))


def test_loading_anything_but_a_learner_file_fails_in_one_line(tmp_path: Path) -> None:
    text = tmp_path / "notes.pt"
    text.write_text("not a model\n")
    tensors = tmp_path / "weights.pt"
    torch.save({"weight": torch.zeros(3)}, tensors)
    for path in (text, tensors, tmp_path / "missing.pt"):
        with pytest.raises(ValueError, match="is not a learner file") as info:
            learners.load(path)
        assert "\n" not in str(info.value)


def test_loading_a_model_of_other_sizes_fails_in_one_line(tmp_path: Path) -> None:
    """A model of a 2-state system (fitted fine) is refused by a harness of 3 states."""
    rng = np.random.default_rng(0)
    steps = 200
    episode = Episode(
        "two_states",
        np.arange(steps) * 0.01,
        rng.random((steps, 2)),
        rng.random((steps, 2)),
        np.zeros((steps, 3)),
    )
    model = EDMD(num_centers=5).fit([episode], [], MinMaxNormalizer.fit([episode]))
    path = model.save(tmp_path / "small.pt")
    with pytest.raises(ValueError, match="models 2 states and 2 inputs; expected 3 states") as info:
        learners.load(path)
    assert "\n" not in str(info.value)
    assert learners.load(path, state_dim=2).A_.shape == model.A_.shape


def test_loading_with_the_wrong_class_names_the_class(
    fitted: dict[str, Learner], tmp_path: Path
) -> None:
    path = fitted["edmd"].save(tmp_path / "edmd.pt")
    with pytest.raises(ValueError, match="holds a EDMD, not a DNN"):
        DNN.load(path)


@pytest.mark.parametrize("name", NAMES)
def test_nan_in_the_training_data_is_refused_naming_the_episode(name: str, data: dict) -> None:
    bad = data["train"][0]
    states = bad.states.copy()
    states[100, 1] = np.nan
    poisoned = Episode("poisoned", bad.time_s, states, bad.inputs, bad.poses)
    with pytest.raises(ValueError, match="train episode 'poisoned': states contain NaN") as info:
        TINY[name]().fit([poisoned, *data["train"][1:]], data["validation"], data["normalizer"])
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("name", NAMES)
def test_every_learner_config_instantiates_with_the_class_defaults(name: str) -> None:
    """conf/learner/<name>.yaml lists every hyperparameter at the paper's default value."""
    learner = instantiate(compose_learner(name))
    assert isinstance(learner, Learner) and learner.name == name
    assert learner.hyperparameters == type(learner)().hyperparameters


@pytest.mark.parametrize(
    ("name", "override", "key"),
    [
        ("edmd", "learner.num_centers=-1", "learner.num_centers"),
        ("edmd", "learner.ridge=-1e-3", "learner.ridge"),
        ("elm_edmd", "learner.activation=softsign", "learner.activation"),
        ("elm_edmd", "learner.num_features=0", "learner.num_features"),
        ("dnn", "learner.horizon=0", "learner.horizon"),
        ("dnn", "learner.training.lr=-1e-4", "learner.training.lr"),
        ("dnn", "learner.beta.inf=-1", "learner.beta.inf"),
        ("dnn", "+learner.training.epochs=3", "learner.training.epochs"),
        ("deep_edmd", "learner.lifted_dim=0", "learner.lifted_dim"),
        ("deep_edmd", "learner.horizon=0", "learner.horizon"),
        ("deep_edmd", "learner.training.batch_size=0", "learner.training.batch_size"),
        ("deep_edmd", "learner.alpha.xo=-0.3", "learner.alpha.xo"),
        ("deep_edmd", "learner.prediction_output=both", "learner.prediction_output"),
        ("deep_edmd", "learner.random_layer.std=-1", "learner.random_layer.std"),
    ],
)
def test_a_wrong_learner_value_names_its_key(name: str, override: str, key: str) -> None:
    with pytest.raises(Exception) as info:
        instantiate(compose_learner(name, override))
    error = info.value.__cause__ or info.value
    assert isinstance(error, ValueError)
    assert key in str(error) and "\n" not in str(error)
