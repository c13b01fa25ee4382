"""The learner contract, for every learner config: fit, predict, save/load, configs, bad values."""

from __future__ import annotations

import subprocess
import sys
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
from learners import (
    DNN,
    EDMD,
    DeepEDMD,
    KoopmanLearner,
    Learner,
    RandomFeatures,
    ThinPlateRBF,
)
from learners.base import FORMAT_VERSION
from learners.input_edmd import InputEDMD
from tests.toydata import drive_episodes

NAMES = ("edmd", "elm_edmd", "dnn", "deep_edmd", "input_edmd")

# Budgets small enough for a unit test (seconds), large enough to learn something.
TINY = {
    "edmd": lambda: EDMD(ThinPlateRBF(num_centers=50)),
    "elm_edmd": lambda: EDMD(RandomFeatures(num_features=50), ridge=1e-8),
    "input_edmd": lambda: InputEDMD(ThinPlateRBF(num_centers=100, center_draw="samples")),
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
    model = EDMD(ThinPlateRBF(num_centers=5)).fit([episode], [], MinMaxNormalizer.fit([episode]))
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


@pytest.mark.parametrize(
    ("legacy_class", "legacy_keys", "dictionary"),
    [
        ("learners.edmd.EDMD", {"num_centers": 50}, ThinPlateRBF(num_centers=50)),
        (
            "learners.elm_edmd.ELMEDMD",
            {"num_features": 50, "activation": "tanh", "weight_scale": 4.0, "bias_scale": 2.0},
            RandomFeatures(num_features=50),
        ),
    ],
    ids=["edmd", "elm_edmd"],
)
def test_a_file_from_before_dictionaries_loads_as_edmd_and_predicts_the_same(
    legacy_class: str, legacy_keys: dict, dictionary, data: dict, tmp_path: Path
) -> None:
    """Format-1 files name EDMD's or ELM-EDMD's own class with flat dictionary keywords."""
    model = EDMD(dictionary, ridge=1e-8).fit(data["train"], [], data["normalizer"])
    payload = torch.load(model.save(tmp_path / "new.pt"), weights_only=True)
    assert payload["version"] == FORMAT_VERSION
    payload["class"] = legacy_class
    payload["hyperparameters"] = {**legacy_keys, "ridge": 1e-8, "include_constant": True, "seed": 0}
    torch.save(payload, tmp_path / "old.pt")
    loaded = learners.load(tmp_path / "old.pt")
    assert type(loaded) is EDMD and loaded.hyperparameters == model.hyperparameters
    np.testing.assert_array_equal(open_loop(loaded, data["test"]), open_loop(model, data["test"]))


@pytest.mark.parametrize("name", [*NAMES, "deep_edmd_lstsq", "deep_edmd_random_layer"])
def test_every_learner_config_builds_a_learner_its_saved_hyperparameters_rebuild(
    name: str,
) -> None:
    """What a model file stores (plain values) builds the same learner as the config did."""
    learner = instantiate(compose_learner(name))
    assert isinstance(learner, Learner)
    saved = learner.hyperparameters
    assert type(learner).from_hyperparameters(saved).hyperparameters == saved


@pytest.mark.parametrize(
    ("name", "dictionary", "size"),
    [("edmd", ThinPlateRBF, 100), ("elm_edmd", RandomFeatures, 100)],
)
def test_edmd_and_elm_edmd_are_one_class_whose_dictionary_the_config_chooses(
    name: str, dictionary: type, size: int, data: dict
) -> None:
    learner = instantiate(compose_learner(name))
    assert type(learner) is EDMD and type(learner.dictionary) is dictionary
    learner.fit(data["train"], [], data["normalizer"])
    assert learner.A_.shape == (3 + 1 + size, 3 + 1 + size)  # [x; 1; phi(x)]
    sin = instantiate(compose_learner("elm_edmd", "learner.dictionary.activation=sin"))
    assert sin.dictionary.activation == "sin"
    swapped = instantiate(
        compose_learner(
            "edmd",
            "~learner.dictionary.num_centers",
            "learner.dictionary._target_=learners.dictionaries.RandomFeatures",
            "+learner.dictionary.num_features=7",
        )
    )
    assert type(swapped.dictionary) is RandomFeatures and swapped.dictionary.num_features == 7


def test_the_learners_package_imports_no_recorder_figures_or_config_system() -> None:
    """Estimators take data: recording, figures and configs are the caller's."""
    code = (
        "import sys, learners, learners.training, learners.dictionaries; "
        "print(sorted(m for m in ('rerun', 'matplotlib', 'hydra', 'harness.recorder') "
        "if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize(
    ("name", "override", "key"),
    [
        ("edmd", "learner.dictionary.num_centers=-1", "learner.dictionary.num_centers"),
        ("edmd", "learner.ridge=-1e-3", "learner.ridge"),
        ("elm_edmd", "learner.dictionary.activation=softsign", "learner.dictionary.activation"),
        ("elm_edmd", "learner.dictionary.num_features=0", "learner.dictionary.num_features"),
        ("dnn", "learner.horizon=0", "learner.horizon"),
        ("dnn", "learner.training.lr=-1e-4", "learner.training.lr"),
        ("dnn", "learner.beta.inf=-1", "learner.beta.inf"),
        ("deep_edmd", "learner.lifted_dim=0", "learner.lifted_dim"),
        ("deep_edmd", "learner.horizon=0", "learner.horizon"),
        ("deep_edmd", "learner.training.batch_size=0", "learner.training.batch_size"),
        ("deep_edmd", "learner.alpha.xo=-0.3", "learner.alpha.xo"),
        ("deep_edmd", "learner.prediction_output=both", "learner.prediction_output"),
        ("deep_edmd", "learner.random_layer.std=-1", "learner.random_layer.std"),
        ("input_edmd", "learner.dictionary.center_draw=grid", "learner.dictionary.center_draw"),
        ("input_edmd", "learner.ridge=[1e-6,-1]", "learner.ridge"),
        ("input_edmd", "learner.ridge=[]", "learner.ridge"),
    ],
)
def test_a_wrong_learner_value_names_its_key(name: str, override: str, key: str) -> None:
    with pytest.raises(Exception) as info:
        instantiate(compose_learner(name, override))
    error = info.value.__cause__ or info.value
    assert isinstance(error, ValueError)
    assert key in str(error) and "\n" not in str(error)


@pytest.mark.parametrize(
    ("name", "override"),
    [
        ("dnn", "+learner.training.epochs=3"),
        ("deep_edmd", "+learner.alpha.beta=1"),
        ("elm_edmd", "+learner.dictionary.num_centers=3"),
    ],
)
def test_an_unknown_key_in_a_nested_block_is_refused_naming_it(name: str, override: str) -> None:
    """The block's dataclass is its schema: a key it lacks fails where Hydra builds it."""
    unknown = override.rpartition(".")[2].partition("=")[0]
    with pytest.raises(Exception) as info:
        instantiate(compose_learner(name, override))
    error = info.value.__cause__ or info.value
    assert isinstance(error, TypeError)
    assert f"'{unknown}'" in str(error) and "\n" not in str(error)


def test_an_unknown_key_in_a_plain_block_is_refused_naming_it() -> None:
    """Plain mappings (model files, code) get the same schema as the configs."""
    with pytest.raises(ValueError, match=r"learner\.training\.epochs is not a key") as info:
        DNN(training={"epochs": 3})
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=r"learner\.training\.lr must be > 0 \(got -1\)"):
        DNN(training={"lr": -1})
