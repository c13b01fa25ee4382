"""The learner contract, for every learner config: fit, predict, save/load, configs, bad values."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

import learners
from harness.core.episode import Episode, MinMaxNormalizer
from harness.evaluation.prediction import open_loop, rmse
from learners import (
    DNN,
    EDMD,
    DeepEDMD,
    KoopmanLearner,
    Learner,
    RandomFeatures,
    ThinPlateRBF,
)
from learners.bilinear import BilinearEDMD
from learners.bilinear_deep_edmd import BilinearDeepEDMD
from learners.input_edmd import InputEDMD
from learners.model_file import FORMAT_VERSION
from learners.single_track import SingleTrack
from learners.trained import TrainedLearner
from tests.helpers import learner_config
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
    foreign = tmp_path / "foreign.pt"
    torch.save({"format": "koopman-harness/learner", "run": Path("x")}, foreign)  # an object
    for path in (text, tensors, tmp_path / "missing.pt", foreign):
        with pytest.raises(ValueError, match="is not a learner file") as info:
            learners.load(path)
        assert "\n" not in str(info.value)
        assert str(info.value).endswith(")")  # the reason whole, or cut at a word with " …"
    with pytest.raises(ValueError, match=r"holds Python objects besides tensors .* not loaded\)"):
        learners.load(foreign)


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
    with pytest.raises(ValueError, match="models 2 states; expected 3 states") as info:
        learners.load(path)
    assert "\n" not in str(info.value)
    assert learners.load(path, state_dim=2).A_.shape == model.A_.shape


def test_a_model_refuses_data_with_other_inputs_in_one_line(
    fitted: dict[str, Learner], tmp_path: Path
) -> None:
    """A model file knows its inputs by name: data of other inputs (a log's throttle and brake
    where the model was fitted on the sedan's pedal) is refused before it is read as them."""
    path = fitted["edmd"].save(tmp_path / "edmd.pt")
    assert learners.load(path, inputs=("steer_wheel_deg", "pedal")).normalizer_.input_names == (
        "steer_wheel_deg",
        "pedal",
    )
    with pytest.raises(
        ValueError, match=r"models inputs \(steer_wheel_deg, pedal\), but the data"
    ) as info:
        learners.load(path, inputs=("wheel_angle_rad", "throttle", "brake"))
    assert "\n" not in str(info.value)


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
    learner = instantiate(learner_config(name))
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
    learner = instantiate(learner_config(name))
    assert type(learner) is EDMD and type(learner.dictionary) is dictionary
    learner.fit(data["train"], data["validation"], data["normalizer"])
    assert learner.A_.shape == (3 + 1 + size, 3 + 1 + size)  # [x; 1; phi(x)]
    if name == "edmd":  # the preset chooses its ridge on the validation drives and says which
        assert len(learner.ridges) > 1 and learner.fit_summary["ridge"] in learner.ridges
    sin = instantiate(learner_config("elm_edmd", "learner.dictionary.activation=sin"))
    assert sin.dictionary.activation == "sin"
    swapped = instantiate(
        learner_config(
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
        instantiate(learner_config(name, override))
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
        instantiate(learner_config(name, override))
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


# -- a model file is checked on load, and a non-finite model is never saved ----------------------

TRAINING = {"max_steps": 5, "batch_size": 8, "eval_every_steps": 5, "progress": False}
NET = {"lifted_dim": 4, "encoder_hidden": [8], "decoder_hidden": [8], "horizon": 4}

# Every kind of learner, as small as it gets (a fit in well under a second): each stores other
# tensors (A, B, C, H, dictionary arrays, theta, coefficients, a flat network buffer).
KINDS = {
    "edmd": lambda: EDMD(ThinPlateRBF(num_centers=5)),
    "elm_edmd": lambda: EDMD(RandomFeatures(num_features=5), ridge=1e-8),
    "bilinear_edmd": lambda: BilinearEDMD(ThinPlateRBF(num_centers=5)),
    "input_edmd": lambda: InputEDMD(ThinPlateRBF(num_centers=10, center_draw="samples"), 1e-6),
    "single_track": SingleTrack,
    "dnn": lambda: DNN(hidden=[8], horizon=4, training=TRAINING),
    "deep_edmd": lambda: DeepEDMD(**NET, training=TRAINING),
    "bilinear_deep_edmd": lambda: BilinearDeepEDMD(**NET, training=TRAINING),
}


@pytest.fixture(scope="module")
def model_files(data: dict, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    directory = tmp_path_factory.mktemp("model_files")
    return {
        kind: make()
        .fit(data["train"][:2], data["validation"], data["normalizer"])
        .save(directory / f"model_{kind}.pt")
        for kind, make in KINDS.items()
    }


def _tensors(path: Path) -> dict:
    return torch.load(path, weights_only=True)["tensors"]


def _corrupt(path: Path, out: Path, change) -> Path:
    """A copy of the model file ``path`` with ``change`` applied to its payload."""
    payload = torch.load(path, weights_only=True)
    change(payload)
    torch.save(payload, out)
    return out


def _load_error(path: Path) -> str:
    with pytest.raises(ValueError) as info:
        learners.load(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{path}: ")
    assert message.endswith("retrain the model, or choose another model file")
    return message


def _expected_shape(message: str) -> tuple[int, ...]:
    """The shape a message says was expected, its names (``N = 9``) resolved to sizes."""
    found = re.search(r"expected \(([^)]*)\)(?: with (.*))?: retrain", message)
    assert found, message
    sizes = dict(re.findall(r"(\w+) = (\d+)", found.group(2) or ""))
    dims = [d.strip() for d in found.group(1).split(",") if d.strip()]
    return tuple(int(sizes.get(d, d)) for d in dims)


@pytest.mark.parametrize("kind", KINDS)
def test_nan_or_inf_in_any_tensor_of_a_model_file_is_refused_naming_file_and_tensor(
    kind: str, model_files: dict[str, Path], tmp_path: Path
) -> None:
    keys = list(_tensors(model_files[kind]))
    assert keys  # every learner stores something to check
    for key in keys:
        for value, word in ((float("nan"), "NaN"), (float("-inf"), "inf")):

            def poison(payload: dict, key: str = key, value: float = value) -> None:
                tensor = payload["tensors"][key].clone()
                tensor.view(-1)[-1] = value  # the last entry: a scan that stops early misses it
                payload["tensors"][key] = tensor

            bad = _corrupt(model_files[kind], tmp_path / f"{key}_{word}.pt", poison)
            index = np.unravel_index(_tensors(bad)[key].numel() - 1, _tensors(bad)[key].shape)
            expected = f"tensor '{key}' has {word} at {tuple(int(i) for i in index)}"
            assert expected in _load_error(bad)


@pytest.mark.parametrize("kind", KINDS)
def test_a_tensor_of_another_shape_is_refused_naming_the_expected_one(
    kind: str, model_files: dict[str, Path], tmp_path: Path
) -> None:
    """One row too many in each tensor in turn: the message names the size the learner's own
    hyperparameters give (``N = 9 (lifted states)``), not only the numbers."""
    for key, tensor in _tensors(model_files[kind]).items():
        wrong = (tensor.shape[0] + 1, *tensor.shape[1:])

        def reshape(payload: dict, key: str = key, wrong: tuple = wrong) -> None:
            payload["tensors"][key] = torch.zeros(wrong, dtype=payload["tensors"][key].dtype)

        message = _load_error(_corrupt(model_files[kind], tmp_path / f"{key}.pt", reshape))
        assert f"tensor '{key}' has shape {wrong}, expected (" in message
        assert _expected_shape(message) == tuple(tensor.shape)


def test_the_lifted_size_is_named_in_the_shape_message(
    model_files: dict[str, Path], tmp_path: Path
) -> None:
    """EDMD with 5 centres lifts to N = 3 + 1 + 5 = 9: a 50 x 50 A is refused as such."""

    def big(payload: dict) -> None:
        payload["tensors"]["A"] = torch.zeros(50, 50, dtype=torch.float64)

    message = _load_error(_corrupt(model_files["edmd"], tmp_path / "a50.pt", big))
    assert "tensor 'A' has shape (50, 50), expected (N, N) with N = 9 (lifted states)" in message

    def network(payload: dict) -> None:
        payload["tensors"]["params"] = payload["tensors"]["params"][:-1]

    message = _load_error(_corrupt(model_files["dnn"], tmp_path / "params.pt", network))
    assert "tensor 'params' has shape" in message and "(P,) with P = " in message


@pytest.mark.parametrize("kind", ["bilinear_edmd", "bilinear_deep_edmd", "elm_edmd"])
def test_a_missing_or_foreign_tensor_is_refused(
    kind: str, model_files: dict[str, Path], tmp_path: Path
) -> None:
    key = "biases" if kind == "elm_edmd" else "H"

    def drop(payload: dict) -> None:
        del payload["tensors"][key]

    assert f"tensor '{key}' is missing" in _load_error(
        _corrupt(model_files[kind], tmp_path / "missing.pt", drop)
    )

    def add(payload: dict) -> None:
        payload["tensors"]["extra"] = torch.zeros(3)

    assert "tensor 'extra' is not one of this learner's" in _load_error(
        _corrupt(model_files[kind], tmp_path / "extra.pt", add)
    )


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("state_max", [float("inf"), 1.0, 1.0], "normalizer 'state_max' has inf at (0,)"),
        ("input_min", [0.0, float("nan")], "normalizer 'input_min' has NaN at (1,)"),
        ("state_min", [0.0] * 4, "normalizer 'state_min' has shape (4,), expected (3,)"),
        ("state_max", [-1e9, -1e9, -1e9], "normalizer 'state_max' is below 'state_min' at (0,)"),
    ],
)
def test_a_broken_normalizer_is_refused_naming_the_array(
    key: str, value: list, expected: str, model_files: dict[str, Path], tmp_path: Path
) -> None:
    """``state_max=inf`` would map every state to 0 and track garbage without a word."""

    def change(payload: dict) -> None:
        payload["normalizer"][key] = value

    for kind in ("edmd", "dnn"):
        assert expected in _load_error(_corrupt(model_files[kind], tmp_path / "n.pt", change))


@pytest.mark.parametrize("kind", ["edmd", "input_edmd", "single_track", "dnn", "deep_edmd"])
def test_a_model_with_non_finite_parameters_is_never_saved(
    kind: str, model_files: dict[str, Path], tmp_path: Path
) -> None:
    """A fit that diverged is reported (one line naming the tensor), not saved as a model."""
    learner = learners.load(model_files[kind])
    if isinstance(learner, TrainedLearner):
        learner.params_.data[3] = float("nan")
        clause = "tensor 'params' has NaN at (3,)"
    else:
        array = {"input_edmd": "theta_", "single_track": "coefficients_"}.get(kind, "A_")
        getattr(learner, array)[0, ...] = float("inf")
        clause = f"tensor '{array.rstrip('_')}' has inf at (0"
    path = tmp_path / "diverged.pt"
    with pytest.raises(ValueError, match=r"the fit diverged or failed, so it is not saved") as info:
        learner.save(path)
    assert clause in str(info.value) and "\n" not in str(info.value)
    assert not path.exists() and not list(tmp_path.iterdir())


def test_a_model_file_records_what_it_was_trained_on_and_old_files_still_load(
    model_files: dict[str, Path], tmp_path: Path
) -> None:
    """``provenance`` is saved as given, kept when a loaded model is saved again, and absent
    (empty) in files written before it existed."""
    learner = learners.load(model_files["edmd"])
    assert learner.provenance_ == {}
    record = {"plant": "sedan_wet", "plant_fingerprint": "0123", "dataset": "abcd"}
    again = learners.load(learner.save(tmp_path / "recorded.pt", record))
    assert again.provenance_ == record
    assert learners.load(again.save(tmp_path / "resaved.pt")).provenance_ == record

    def old(payload: dict) -> None:
        del payload["provenance"]

    assert learners.load(_corrupt(model_files["edmd"], tmp_path / "old.pt", old)).provenance_ == {}


def test_a_long_reason_is_cut_at_a_word_never_inside_one() -> None:
    from learners.model_file import _first_words

    error = ValueError(
        "Weights only load failed. In PyTorch 2.6, we changed the default value of the "
        "weights_only argument\nmore"
    )
    cut = _first_words(error)
    assert cut.endswith(" the …") and len(cut) <= 82
    assert _first_words(ValueError("short\nsecond line")) == "short"
