"""Fail before the expensive part, in one line naming the key; never score a broken run.

Each check here failed on an earlier version of the code: controller, reference and extra-controller
values were checked only after data and training (or named the wrong key), a controller period
other than the plant's ran, a diverged MuJoCo simulation scored perfectly, a model file of
another learner was reported as the configured one, absurd sizes grew memory until killed, and
Hydra's own errors (a value of the wrong type) took several lines.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate

import learners
from controllers import DEMPCConfig
from harness.config import validate
from harness.core.episode import Episode, MinMaxNormalizer
from harness.data.store import DataConfig, Dataset
from harness.plant import Sedan, SedanParams
from harness.plant.params import ChassisParams, TireParams
from harness.plant.sedan import PlantUnstableError
from harness.recorder import Recorder
from harness.report.jobs import read_run
from harness.tasks.pipeline import Pipeline, check_training_data
from learners.bilinear import BilinearEDMD
from learners.dictionaries import ThinPlateRBF
from learners.dnn import DNN
from learners.edmd import EDMD
from learners.input_edmd import InputEDMD
from learners.single_track import SingleTrack
from tests.helpers import compose, run_job
from tests.toydata import drive_episodes

TINY = [
    "data.episodes=3",
    "data.min_steps=300",
    "data.max_steps=400",
    "data.split.train=1",
    "data.split.validation=1",
    "data.split.test=1",
    "recorder=none",
]


def build_as_the_app(*overrides: str) -> None:
    """What ``python -m harness`` does before the task runs: compose, validate, build."""
    cfg = compose(*TINY, *overrides, as_app=True)
    validate(cfg)
    instantiate(cfg.plant)
    try:
        instantiate(cfg.task)
    except InstantiationException as error:  # the app prints the task's own error
        raise error.__cause__ from None  # type: ignore[misc]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["controller.Np=3", "controller.Nc=7"],
            "controller.Nc must be <= controller.Np (3) (got 7)",
        ),
        (["controller.Q=-5"], "controller.Q must be positive definite"),
        (
            ["experiment=paper", "task.extra_controllers.de_mpc_long.Np=0"],
            "task.extra_controllers.de_mpc_long.Np must be an integer >= 1 (got 0)",
        ),
        (
            ["task.references.double_lane_change.speed_mps=-1"],
            "task.references.double_lane_change.speed_mps must be >= 1 m/s (got -1)",
        ),
        (  # 1.6 million steps: 11 minutes and 78 MB of recording before
            ["task.references.double_lane_change.speed_mps=0.01"],
            "task.references.double_lane_change.speed_mps must be >= 1 m/s (got 0.01)",
        ),
        (
            ["task.references.double_lane_change.standard=iso9999"],
            "task.references.double_lane_change.standard must be one of",
        ),
        (
            ["+task.references.double_lane_change.lanes=3"],
            "unknown key task.references.double_lane_change.lanes",
        ),
        (["learner.training.lr=-1"], "learner.training.lr must be > 0 (got -1)"),
        (["learner=edmd", "learner.dictionary.num_centers=-3"], "learner.dictionary.num_centers"),
        (
            ["controller.dt=0.02"],
            "controller.dt (0.02) must equal plant.control_period_s (0.01)",
        ),
        (  # the run's controller steps at the plant's period; the paper's beside it at 10 ms
            ["plant.control_period_s=0.02"],
            "task.extra_controllers.de_mpc.dt (0.01) must equal plant.control_period_s (0.02)",
        ),
        (
            ["controller=de_mpc", "plant.control_period_s=0.02"],
            "controller.dt (0.01) must equal plant.control_period_s (0.02)",
        ),
        (
            ["experiment=paper", "task.extra_controllers.de_mpc_long.dt=0.05"],
            "task.extra_controllers.de_mpc_long.dt (0.05) must equal plant.control_period_s",
        ),
        (
            ["experiment=generalization", "task.other_plants.sedan_wet.control_period_s=0.02"],
            "task.other_plants.sedan_wet.control_period_s (0.02) must equal",
        ),
        (
            ["experiment=generalization", "task.other_plants.sedan_wet.tire.road_friction=0"],
            "task.other_plants.sedan_wet.tire.road_friction must be > 0 (got 0)",
        ),
        # One scale per state: a wrong length fails before any data, not at fit.
        (["learner=dnn", "learner.loss_scales=[0.2,0.1]"], "learner.loss_scales has 2 entries"),
        (
            ["learner=deep_edmd", "learner.training.rollout_scales=[1.0]"],
            "learner.training.rollout_scales has 1 entries",
        ),
        # An input the learner needs, named in the learner, not among the data's inputs.
        (
            ["learner=deep_edmd_split", "learner.pedal=gas"],
            "the data config has no 'gas' input (steer_wheel_deg, pedal)",
        ),
        # Sizes no machine has, refused before any data (point 10).
        (
            ["learner=edmd", "learner.dictionary.num_centers=1000000000"],
            "learner.dictionary.num_centers: EDMD with 1000000000 observables on drives of 400",
        ),
        (
            ["learner=dnn", "learner.hidden=[1000000000]"],
            "learner.hidden / learner.training.batch_size: dnn with",
        ),
        (
            ["learner=deep_edmd", "learner.lifted_dim=1000000000"],
            "learner.lifted_dim / learner.encoder_hidden / learner.decoder_hidden",
        ),
        (
            ["controller.Np=100000", "controller.Nc=100000"],
            "controller.Np and controller.Nc: the condensed QP of Np = 100000, Nc = 100000",
        ),
        (  # fits in memory, but its Hessian overflowed after training before
            ["controller.Np=100000", "controller.Nc=7"],
            "controller.Np (100000) spans 1000 s at controller.dt = 0.01 s; at most 10 s",
        ),
        (
            ["experiment=paper", "task.extra_controllers.de_mpc_long.Np=2000"],
            "task.extra_controllers.de_mpc_long.Np (2000) spans 20 s at "
            "task.extra_controllers.de_mpc_long.dt = 0.01 s",
        ),
    ],
)
def test_every_part_of_the_config_is_checked_before_the_first_episode(
    overrides: list[str], message: str
) -> None:
    with pytest.raises(ValueError) as info:
        build_as_the_app(*overrides)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_a_period_check_applies_only_to_what_the_task_uses() -> None:
    build_as_the_app("task=characterize", "plant.control_period_s=0.02")  # no controller used
    # Both agree; the paper's de_mpc is the run's controller, not a second one at 10 ms.
    build_as_the_app("controller=de_mpc", "controller.dt=0.02", "plant.control_period_s=0.02")


def run_harness(tmp: Path, *overrides: str) -> tuple[subprocess.CompletedProcess, float]:
    """``python -m harness`` itself: its one-line errors, exit status and start-up time are
    what the command shows."""
    start = time.perf_counter()
    result = subprocess.run(
        [sys.executable, "-m", "harness", *TINY, f"data.root={tmp}/datasets", *overrides],
        cwd=tmp,
        capture_output=True,
        text=True,
        timeout=300,
    )
    return result, time.perf_counter() - start


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["controller.Np=3", "controller.Nc=7"], "controller.Np"),
        (["plant.tire.road_friction=abc"], "plant.tire.road_friction"),  # Hydra's own error
        (["plant.tire.vertical_stiffness_n_per_m=1e12"], "plant.tire.vertical_stiffness_n_per_m"),
        (["controller.Np=100000", "controller.Nc=7"], "controller.Np"),
        (
            ["task.references.double_lane_change.speed_mps=0.01"],
            "task.references.double_lane_change.speed_mps",
        ),
    ],
)
def test_the_command_line_fails_in_one_line_with_no_data_and_no_training(
    tmp_path: Path, overrides: list[str], key: str
) -> None:
    run_dir = tmp_path / "run"
    result, seconds = run_harness(tmp_path, *overrides, f"hydra.run.dir={run_dir}")
    assert result.returncode == 2, result.stderr[-2000:]
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and key in errors[0], result.stderr[-2000:]
    assert not any(line.startswith(("Traceback", "  File")) for line in result.stderr.splitlines())
    datasets = tmp_path / "datasets"
    assert not datasets.exists() or not any(datasets.iterdir())  # nothing collected
    assert not list(tmp_path.rglob("model_*.pt")) and not list(tmp_path.rglob("*.ckpt"))
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()  # MuJoCo's warning went to the log
    assert seconds < 120  # imports and checks only (a loaded 2-core machine: ~10 s)


def test_a_rerun_of_a_failed_job_leaves_no_stale_error(tmp_path: Path) -> None:
    run_dir = tmp_path / "job"
    tiny = (*TINY, f"data.root={tmp_path}/datasets")
    with pytest.raises(SystemExit) as failed:
        run_job(run_dir, *tiny, "task=collect", "controller.Q=-5", cwd=tmp_path)
    assert failed.value.code == 2 and (run_dir / "error.json").exists()
    assert read_run(run_dir).error is not None
    run_job(
        run_dir, *tiny, "task=collect", "data.min_steps=100", "data.max_steps=150", cwd=tmp_path
    )
    assert not (run_dir / "error.json").exists()
    run = read_run(run_dir)
    assert run.error is None and "data" in json.loads((run_dir / "metrics.json").read_text())


# -- the plant: a diverged simulation is an error, never a quiet reset (point 7) ----------------


@pytest.mark.parametrize(
    ("params", "key"),
    [
        (
            SedanParams(tire=TireParams(vertical_stiffness_n_per_m=1e12)),
            "plant.tire.vertical_stiffness_n_per_m=1000000000000.0",
        ),
        (  # settles, then diverges in the first turn
            SedanParams(chassis=ChassisParams(anti_roll_front_n_per_m=1e10)),
            "plant.chassis.anti_roll_front_n_per_m=10000000000.0",
        ),
    ],
)
def test_a_plant_that_diverges_names_the_keys_to_check(params: SedanParams, key: str) -> None:
    with pytest.raises(PlantUnstableError) as info:
        plant = Sedan(params)
        for _ in range(500):
            plant.step((200.0, 0.2))
    assert key in str(info.value) and "mjWARN_BAD" in str(info.value)
    assert "\n" not in str(info.value)


def test_a_divergence_during_a_drive_is_an_error_not_a_reset(sedan: Sedan) -> None:
    sedan.reset()
    sedan.data.qvel[:] = 1e200  # what a diverging integration reaches
    with pytest.raises(PlantUnstableError, match="in a control step"):
        sedan.step((0.0, 0.0))
    x = sedan.reset()  # and the plant works again after a reset
    assert np.all(np.isfinite(sedan.step((0.0, 0.1)))) and np.all(x == 0)


def test_reset_refuses_a_non_finite_speed(sedan: Sedan) -> None:
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="speed_mps must be finite"):
            sedan.reset(speed_mps=bad)


# -- data too little to learn from -----------------------------------------------------------


def _standing(name: str, frames: int) -> Episode:
    states = np.zeros((frames, 3))
    states[:, 0] = np.linspace(0, 1e-11, frames)
    inputs = np.tile([10.0, 0.2], (frames, 1))
    return Episode(name, np.arange(frames) * 0.01, states, inputs, np.zeros((frames, 3)))


def test_a_dataset_in_which_the_car_never_moved_is_refused(tmp_path: Path) -> None:
    """``plant.chassis.sprung_mass_kg=1e12``: the car stands; a fit on it would score 1e-8."""
    plant = Sedan(SedanParams(chassis=ChassisParams(sprung_mass_kg=1e12)))
    for _ in range(300):
        x = plant.step((0.0, 0.2))
    assert abs(x[0]) < 1e-3  # the plant does not diverge: it does not move
    train = [_standing("episode_0000", 400)]
    dataset = Dataset(tmp_path, {}, train, train, train, MinMaxNormalizer.fit(train))
    with pytest.raises(ValueError, match=r"never reached 1.0 m/s.*plant.chassis.sprung_mass_kg"):
        check_training_data(dataset)
    # Logs of a car that stood: the hint is the logs' column and split, not a plant's keys.
    logs = Dataset(tmp_path, {"source": "logs"}, train, train, train, MinMaxNormalizer.fit(train))
    with pytest.raises(ValueError, match=r"logs' vx column .*data.split.train \(episode_0000\)$"):
        check_training_data(logs)


def test_edmd_refuses_fewer_pairs_than_unknowns() -> None:
    (episode,) = drive_episodes(1, duration_s=0.08)  # 9 frames, 8 pairs
    normalizer = MinMaxNormalizer.fit([episode])
    with pytest.raises(ValueError, match=r"EDMD .* 106 unknowns per row .* only 8 one-step"):
        EDMD().fit([episode], [], normalizer)
    EDMD(ThinPlateRBF(0)).fit([episode], [], normalizer)  # DMD: 6 unknowns, 8 pairs
    # bilinear EDMD counts its input-times-state columns too: 4 + 2 + 2 * 3 = 12 > 8
    with pytest.raises(ValueError, match=r"BilinearEDMD .* 12 unknowns per row"):
        BilinearEDMD(ThinPlateRBF(0)).fit([episode], [], normalizer)


@pytest.mark.parametrize(
    "learner", [EDMD(ThinPlateRBF(5)), InputEDMD(ThinPlateRBF(5), ridge=1e-6), DNN(), SingleTrack()]
)
def test_drives_in_which_an_input_never_varied_are_refused_by_every_learner(learner) -> None:
    """A pedal held at one value: no fit can learn what the pedal does, and min-max scaling by
    its range (~0) throws every other pedal value out of bounds (input EDMD: NaN predictions)."""
    train = []
    for episode in drive_episodes(2, duration_s=2.0):
        inputs = episode.inputs.copy()
        inputs[:, 1] = 0.1 + np.linspace(0.0, 1e-9, len(inputs))
        train.append(Episode(episode.name, episode.time_s, episode.states, inputs, episode.poses))
    with pytest.raises(ValueError) as info:
        learner.fit(train, [], MinMaxNormalizer.fit(train))
    names = ", ".join(e.name for e in train)
    assert str(info.value).startswith(
        f"{learner.name} cannot learn from the training drives ({names}): pedal stays at 0.1 "
        "(range 1.0e-09"
    )
    assert "train on drives that vary pedal (collected: data.driver.*; logs:" in str(info.value)


# -- a model file is the configured learner, or refused (point 8) -----------------------------


@pytest.fixture(scope="module")
def edmd_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    episodes = drive_episodes(2, duration_s=5.0)
    learner = EDMD(ThinPlateRBF(10)).fit(episodes[:1], [], MinMaxNormalizer.fit(episodes[:1]))
    return learner.save(tmp_path_factory.mktemp("models") / "model_edmd.pt")


def _pipeline(learner, name: str, path: Path) -> Pipeline:
    data = DataConfig(episodes=3, split={"train": 1, "validation": 1, "test": 1})
    return Pipeline(data, learner, name, model_path=str(path))


def test_a_model_file_of_another_learner_is_refused_naming_both(edmd_file: Path) -> None:
    with pytest.raises(ValueError) as info:
        _pipeline(DNN(), "dnn", edmd_file)
    message = str(info.value)
    assert "holds a EDMD model" in message and "learner=dnn configures a DNN" in message


def test_a_model_file_with_other_hyperparameters_is_refused(edmd_file: Path) -> None:
    with pytest.raises(ValueError, match=r"learner.seed=0, but learner=edmd sets learner.seed=1"):
        _pipeline(EDMD(ThinPlateRBF(10), seed=1), "edmd", edmd_file)
    with pytest.raises(ValueError, match=r"learner.dictionary.num_centers=10"):
        _pipeline(EDMD(ThinPlateRBF(100)), "edmd", edmd_file)
    assert _pipeline(EDMD(ThinPlateRBF(10)), "edmd", edmd_file).loaded is not None


def test_the_qp_size_check_lets_the_papers_horizons_pass() -> None:
    DEMPCConfig(Np=60, Nc=50)
    with pytest.raises(ValueError, match=r"controller.Np and controller.Nc"):
        DEMPCConfig(Np=10**12, Nc=7)


# -- a model file is checked before any data, and its origin is compared --


def test_a_model_file_with_nan_is_refused_before_any_data(edmd_file: Path, tmp_path: Path) -> None:
    """A NaN in A used to fail deep in the spectrum's eigenvalues, after data collection."""
    payload = torch.load(edmd_file, weights_only=True)
    payload["tensors"]["A"][2, 3] = float("nan")
    torch.save(payload, tmp_path / "model_edmd.pt")
    with pytest.raises(ValueError) as info:
        _pipeline(EDMD(ThinPlateRBF(10)), "edmd", tmp_path / "model_edmd.pt")
    assert str(info.value) == (
        f"{tmp_path / 'model_edmd.pt'}: tensor 'A' has NaN at (2, 3): retrain the model, or "
        "choose another model file"
    )


THIS_RUN = {"plant": "sedan", "plant_fingerprint": "f0", "dataset": "d0"}


def _reuse(
    path: Path, out: Path, caplog: pytest.LogCaptureFixture, normalizer: MinMaxNormalizer
) -> dict:
    """The pipeline's model stage with ``path`` as ``task.model_path``, in a run whose plant
    and dataset are ``THIS_RUN`` (the training section of ``metrics.json``)."""
    episodes = drive_episodes(2, duration_s=5.0)
    dataset = Dataset(out, {"key": "d0"}, episodes[:1], [], episodes[1:], normalizer)
    pipeline = _pipeline(EDMD(ThinPlateRBF(10)), "edmd", path)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="harness.tasks.provenance"):
        _, training = pipeline._learner(dataset, THIS_RUN, Recorder(), out)
    return training


def test_a_model_of_another_plant_and_dataset_is_named_in_a_warning_and_the_metrics(
    edmd_file: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """``task.model_path=`` a ``plant=sedan_wet data.seed=7`` model: it runs (a deliberate
    experiment may want that), but never without a word."""
    model = learners.load(edmd_file)
    elsewhere = {"plant": "sedan_wet", "plant_fingerprint": "f1", "dataset": "d7"}
    path = model.save(tmp_path / "wet.pt", elsewhere)
    ours = MinMaxNormalizer.fit(drive_episodes(3, duration_s=5.0)[2:])
    training = _reuse(path, tmp_path, caplog, ours)
    assert training["provenance"] == {
        "trained_on": {**elsewhere, "normalizer": model.normalizer_.to_dict()},
        "this_run": {**THIS_RUN, "normalizer": ours.to_dict()},
        "differs": ["plant", "dataset", "normalizer"],
    }
    (record,) = caplog.records
    assert record.getMessage().startswith(
        f"task.model_path {path.resolve()} was trained on plant sedan_wet, dataset d7; this run "
        "has plant sedan, dataset d0: plant, dataset and normalizer differ (training.provenance)"
    )
    assert "\n" not in record.getMessage()
    # the run's copy of the model still says where it was trained, not where it was used
    assert learners.load(training["model_path"]).provenance_ == elsewhere
    json.dumps(training)  # metrics.json takes it as it is


def test_a_model_of_this_plant_and_dataset_reloads_without_a_warning(
    edmd_file: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    model = learners.load(edmd_file)
    path = model.save(tmp_path / "same.pt", THIS_RUN)
    training = _reuse(path, tmp_path, caplog, model.normalizer_)
    assert training["provenance"]["differs"] == [] and not caplog.records
    assert training["provenance"]["trained_on"] == training["provenance"]["this_run"]


def test_a_model_file_from_before_provenance_compares_its_normalizer_only(
    edmd_file: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """What an old file does not say is null and not compared; its normalizer still is."""
    model = learners.load(edmd_file)
    assert model.provenance_ == {}
    same = _reuse(edmd_file, tmp_path, caplog, model.normalizer_)
    assert same["provenance"]["differs"] == [] and not caplog.records
    assert same["provenance"]["trained_on"]["plant"] is None
    other = MinMaxNormalizer.fit(drive_episodes(3, duration_s=5.0)[2:])
    assert _reuse(edmd_file, tmp_path, caplog, other)["provenance"]["differs"] == ["normalizer"]
    assert "plant (not recorded), dataset (not recorded)" in caplog.records[0].getMessage()


def test_an_extra_controller_named_as_the_runs_controller_runs_once_with_the_runs_settings() -> (
    None
):
    """``controller=de_mpc controller.Np=20`` beside the pipeline's extra ``de_mpc``: one de_mpc,
    the run's, with Np = 20 (not a second one at the defaults, nor the defaults in its place)."""
    cfg = compose(*TINY, "controller=de_mpc", "controller.Np=20", as_app=True)
    assert "de_mpc" in cfg.task.extra_controllers and "bicycle_mpc" in cfg.task.extra_controllers
    validate(cfg)
    assert (
        "de_mpc" not in cfg.task.extra_controllers and "bicycle_mpc" in cfg.task.extra_controllers
    )
    assert cfg.controller.Np == 20
