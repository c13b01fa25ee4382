"""The main job runs data -> training -> prediction -> tracking and honours its contracts."""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from hydra.errors import InstantiationException

from harness.core.episode import Episode
from harness.output import load_arrays
from learners import load as load_learner
from tests.helpers import run_app

TINY = [
    "data.episodes=3",
    "data.min_steps=300",
    "data.max_steps=400",
    "data.split={train: 1, validation: 1, test: 1}",
    "data.start_speed_mps=[0,0]",  # from rest: the drives barely move (the baseline says so)
    "recorder=none",
    "~reference@task.references.double_lane_change",  # the test drive only
    # The paper's short controller as the run's, with its baseline (the default's 60/50 path
    # follower has its own tests); the extras named like it would be it, run once.
    "controller=de_mpc",
    "~controller@task.extra_controllers.de_mpc",
    "~controller@task.extra_controllers.bicycle_mpc_path_long_offset_free",
    # Path followers track states where there is no course: the same run twice here; offset-free
    # tracking has its own tests.
    "~controller@task.extra_controllers.de_mpc_offset_free",
    "~controller@task.extra_controllers.bicycle_mpc_offset_free",
    "~controller@task.extra_controllers.de_mpc_path",
    "~controller@task.extra_controllers.bicycle_mpc_path",
]


class SteadyCruise:
    """A reference of no standard, added by configuration alone (a test's own config group)."""

    def __init__(self, speed_mps: float, seconds: float) -> None:
        self.speed_mps, self.seconds = speed_mps, seconds

    def label(self, name: str, episodes: Sequence[Episode]) -> str:
        return name

    def build(self, dt: float, episodes: Sequence[Episode]) -> np.ndarray:
        steps = round(self.seconds / dt)
        return np.column_stack([np.full(steps, self.speed_mps), np.zeros(steps), np.zeros(steps)])


def run_main(tmp: Path, run_dir: Path, *overrides: str) -> dict:
    """The app's job on the tiny drives, in this process (the command line has its own tests)."""
    return run_app(run_dir, *TINY, f"data.root={tmp}/datasets", *overrides)


@pytest.fixture(scope="module")
def edmd_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    tmp = tmp_path_factory.mktemp("pipeline")
    run_dir = tmp / "edmd"
    return tmp, run_dir, run_main(tmp, run_dir, "learner=edmd")


def test_metrics_follow_the_public_contract(edmd_run) -> None:
    _, run_dir, metrics = edmd_run
    assert set(metrics) == {"data", "training", "prediction", "spectrum", "tracking", "run"}
    # What the job computed on: its threads, and the kernels that set its last digits.
    assert metrics["run"]["threads"]["torch"] == 1
    assert set(metrics["run"]["kernels"]) == {
        "mkl",
        "numpy",
        "openblas",
        "torch",
        "same_everywhere",
    }
    (test_episode,) = metrics["data"]["split"]["test"]
    rmse = metrics["prediction"][test_episode]["rmse"]
    assert set(rmse) == {"vx", "vy", "yaw_rate"} and all(v >= 0 for v in rmse.values())
    # The verdict against the state held, per window and state, read off the two RMSEs.
    prediction = metrics["prediction"][test_episode]
    held = metrics["prediction"]["persistence"][test_episode]
    verdicts = prediction["beats_persistence"]
    assert set(verdicts) == {"open_loop", "41_steps", "10s", "3s", "1.5s"}
    for state, beats in verdicts["3s"].items():
        assert beats == (prediction["rmse_window_3s"][state] < held["rmse_window_3s"][state])
    assert "diverged_at_s" in prediction
    tracking = metrics["tracking"]
    assert set(tracking["rmse"]) == {"vx", "vy", "yaw_rate"}
    assert set(tracking["solve_time_ms"]) == {"median", "p99", "max"}
    assert tracking["horizon"] == {"Np": 10, "Nc": 7}
    assert {"deadline_misses", "solver_failures"} <= set(tracking)
    # the top level is the first reference's run: the first test drive
    assert tracking["reference"] == f"test_episode/{test_episode}"
    first = tracking["references"][f"test_episode/{test_episode}"]
    assert {k: tracking[k] for k in first} == first
    for figure in (
        "data_coverage.png",
        f"prediction_{test_episode}.png",
        "tracking_de_mpc_test_episode.png",
        "tracking_de_mpc_test_episode.npz",
        f"prediction_{test_episode}.npz",
        "step_response.png",
        "step_response.npz",
        "spectrum.png",
    ):
        assert (run_dir / figure).exists(), figure
    steps = metrics["prediction"]["step_response"]
    assert len(steps) == 8 and set(steps["steer+20deg_22mps"]) >= {"at_300ms", "at_1500ms"}
    throttle = steps["throttle+0.1_10mps"]
    assert set(throttle["at_300ms"]) == {"plant", "model", "relative_error", "model_input_effect"}
    # The same step through the model as DE-MPC reads it (EDMD: its own rollout, C z), and
    # whether each view's input effect has the plant's sign.
    as_controlled = throttle["as_controlled"]
    assert as_controlled["at_1500ms"]["model"] == pytest.approx(throttle["at_1500ms"]["model"])
    assert isinstance(throttle["input_sign_agrees"], bool)
    assert isinstance(as_controlled["input_sign_agrees"], bool)
    assert metrics["spectrum"]["max_abs_eigenvalue"] > 0
    assert isinstance(metrics["spectrum"]["unstable_modes"], list)


def test_a_saved_model_is_reused_by_path_in_another_run(edmd_run) -> None:
    tmp, run_dir, metrics = edmd_run
    again = run_main(tmp, tmp / "reuse", "learner=edmd", f"task.model_path={run_dir}/model_edmd.pt")
    assert again["training"]["source"].endswith("model_edmd.pt")
    assert again["prediction"] == metrics["prediction"]
    # the file says it was trained on this plant and dataset: nothing differs
    provenance = again["training"]["provenance"]
    assert provenance == metrics["training"]["provenance"] and provenance["differs"] == []
    assert provenance["trained_on"] == provenance["this_run"]
    assert provenance["this_run"]["plant"] == "sedan"
    assert provenance["this_run"]["dataset"] == metrics["data"]["key"]
    assert provenance["this_run"]["normalizer"] == metrics["data"]["normalizer"]


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "task.prediction_window_steps=1",
            r"task\.prediction_window_steps must be an integer >= 2",
        ),
        ("task.prediction_window_s=[0.005]", r"task\.prediction_window_s 0\.005 s is under two"),
    ],
)
def test_a_window_too_short_to_predict_anything_is_refused_before_training(
    edmd_run, override: str, message: str
) -> None:
    """A one-step window scores the measured state alone: every window metric would be null."""
    tmp, _, _ = edmd_run
    run_dir = tmp / "short_window"
    with pytest.raises((ValueError, InstantiationException), match=message):
        run_main(tmp, run_dir, "learner=edmd", override)
    assert not (run_dir / "model_edmd.pt").exists()  # refused before the fit


def test_an_envelope_that_flags_every_prediction_is_refused_before_training(edmd_run) -> None:
    tmp, _, _ = edmd_run
    run_dir = tmp / "no_envelope"
    message = r"task\.prediction_envelope_spans must be a number > 0"
    with pytest.raises((ValueError, InstantiationException), match=message):
        run_main(tmp, run_dir, "learner=edmd", "task.prediction_envelope_spans=0")
    assert not (run_dir / "model_edmd.pt").exists()


def test_a_window_as_long_as_a_test_drive_is_said_in_a_warning(
    edmd_run, caplog: pytest.LogCaptureFixture
) -> None:
    """The tiny drives last 3-4 s: the default 10 s window is each whole drive, said so."""
    tmp, _, _ = edmd_run
    with caplog.at_level("WARNING", logger="harness.tasks.pipeline"):
        run_main(tmp, tmp / "long_window", "learner=edmd", "task.prediction_window_s=[10.0,1.0]")
    said = [r.getMessage() for r in caplog.records if "prediction_window_s" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("task.prediction_window_s 10 s is as long as")
    assert "its rmse_window_10s is the whole drive's" in said[0]


def test_a_run_says_what_each_phase_did_and_how_long_it_took(
    edmd_run, caplog: pytest.LogCaptureFixture
) -> None:
    """One INFO line per phase, in order, each ending with its time; the details (each
    controller's RMSE, a path follower without a path) are DEBUG lines, not beside them."""
    tmp, run_dir, _ = edmd_run
    with caplog.at_level(logging.INFO):
        run_main(tmp, tmp / "phases", "learner=edmd", f"task.model_path={run_dir}/model_edmd.pt")
    lines = [r.getMessage() for r in caplog.records if r.name == "harness"]
    assert [line.split(":")[0] for line in lines] == [
        "data",
        "training",
        "prediction",
        "identification single_track",  # refused: the tiny drives barely move
        "tracking de_mpc",
    ]
    assert "found in the cache" in lines[0] and "loaded from" in lines[1]
    assert all(re.search(r"\((\d+ min )?\d+(\.\d)? s\)$", line) for line in lines)
    assert not [r for r in caplog.records if r.levelno == logging.INFO and "rmse" in r.getMessage()]


def test_a_saved_model_used_on_another_dataset_is_named_in_a_warning(
    edmd_run, caplog: pytest.LogCaptureFixture
) -> None:
    """``data.seed=7``: other drives, another normalizer; the run goes on, and says so."""
    tmp, run_dir, metrics = edmd_run
    out = tmp / "seed7"
    with caplog.at_level(logging.WARNING):
        other = run_main(
            tmp, out, "learner=edmd", "data.seed=7", f"task.model_path={run_dir}/model_edmd.pt"
        )
    provenance = other["training"]["provenance"]
    assert provenance["differs"] == ["dataset", "normalizer"]
    assert provenance["trained_on"]["dataset"] == metrics["data"]["key"]
    assert provenance["this_run"]["dataset"] == other["data"]["key"] != metrics["data"]["key"]
    log = caplog.text
    assert f"task.model_path {run_dir / 'model_edmd.pt'} was trained on plant sedan" in log
    assert "dataset and normalizer differ (training.provenance)" in log


def test_a_reference_added_by_config_alone_is_tracked(edmd_run) -> None:
    tmp, run_dir, _ = edmd_run
    group = tmp / "more_conf" / "reference"
    group.mkdir(parents=True)
    (group / "steady.yaml").write_text(
        "_target_: tests.test_pipeline.SteadyCruise\nspeed_mps: 15.0\nseconds: 2.0\n"
    )
    metrics = run_main(
        tmp,
        tmp / "steady",
        "learner=edmd",
        f"task.model_path={run_dir}/model_edmd.pt",
        f"hydra.searchpath=[file://{tmp / 'more_conf'}]",
        "+reference@task.references.steady=steady",
    )
    (episode,) = metrics["data"]["split"]["test"]
    tracking = metrics["tracking"]
    assert list(tracking["references"]) == [f"test_episode/{episode}", "steady"]
    assert tracking["reference"] == f"test_episode/{episode}"  # still the first reference
    data = metrics["data"]
    assert data["reference_speed_range_mps"]["steady"] == [15.0, 15.0]
    low, high = data["training_speed_range_mps"]
    assert ("steady" in data["outside_training_speed"]) == (not low <= 15.0 <= high)
    arrays = load_arrays(tmp / "steady" / "tracking_de_mpc_steady.npz")
    reference = SteadyCruise(15.0, 2.0).build(0.01, [])
    np.testing.assert_array_equal(arrays["reference"], reference)
    assert arrays["states"].shape == reference.shape  # the loop drove the whole reference


def test_the_clock_in_the_loop_is_each_controllers_own_setting(edmd_run) -> None:
    """``controller.compute_delay=one_step`` from the command line reaches the run's loop and
    its metrics; a controller beside it keeps its own setting (none) and its undelayed run."""
    tmp, run_dir, metrics = edmd_run
    delayed = run_main(
        tmp,
        tmp / "delayed",
        "learner=edmd",
        f"task.model_path={run_dir}/model_edmd.pt",
        "controller.compute_delay=one_step",
        "+controller@task.extra_controllers.beside=de_mpc",
    )
    assert metrics["tracking"]["compute_delay"] == "none"
    tracking = delayed["tracking"]
    assert tracking["compute_delay"] == "one_step"
    assert tracking["rmse"] != metrics["tracking"]["rmse"]  # another loop, another run
    (beside,) = tracking["controllers"]["beside"].values()
    assert beside["compute_delay"] == "none" and beside["rmse"] == metrics["tracking"]["rmse"]


def test_deep_edmd_runs_the_whole_pipeline_on_a_tiny_budget(tmp_path: Path) -> None:
    run_dir = tmp_path / "deep"
    metrics = run_main(
        tmp_path,
        run_dir,
        "learner=deep_edmd",
        "learner.training.max_steps=30",
        "learner.training.eval_every_steps=10",
        "controller=de_mpc_long",
    )
    assert metrics["training"]["learner"] == "deep_edmd"
    history = json.loads((run_dir / "training_history.json").read_text())
    assert history["step"] and max(history["step"]) <= 30  # the budget held
    (episode,) = metrics["data"]["split"]["test"]
    assert all(np.isfinite(v) for v in metrics["prediction"][episode]["rmse"].values())
    tracking = metrics["tracking"]
    assert tracking["horizon"] == {"Np": 60, "Nc": 50}  # controller=de_mpc_long reached the MPC
    assert all(np.isfinite(v) for v in tracking["rmse"].values())


def test_deep_edmd_on_the_split_pedal_trains_its_inner_model_and_is_tracked_linearised(
    tmp_path: Path,
) -> None:
    run_dir = tmp_path / "split"
    metrics = run_main(
        tmp_path,
        run_dir,
        "learner=deep_edmd_split",
        "data.driver.longitudinal_weights=[0,0,1]",  # brake after the launch (a brake never
        "data.driver.segment_duration_s=[0.5,1.0]",  # used is refused: nothing to learn)
        "learner.inner.training.max_steps=20",
        "learner.inner.training.eval_every_steps=10",
        "learner.inner.horizon=10",
    )
    history = json.loads((run_dir / "training_history.json").read_text())
    assert history["step"] and max(history["step"]) <= 20  # the inner learner's curves
    assert (run_dir / "deep_edmd_loss.png").exists()
    assert set(metrics["spectrum"]["matrices"]) == {"A"}  # the inner model's state matrix
    tracking = metrics["tracking"]
    assert "skipped" not in tracking and tracking["solver_failures"] == 0
    assert all(np.isfinite(v) for v in tracking["rmse"].values())
    reloaded = load_learner(run_dir / "model_deep_edmd_split.pt")
    assert reloaded.normalizer_.input_names == ("steer_wheel_deg", "pedal")


def test_the_dnn_is_tracked_through_its_linearisation(tmp_path: Path) -> None:
    metrics = run_main(
        tmp_path,
        tmp_path / "dnn",
        "learner=dnn",
        "learner.training.max_steps=20",
        "learner.training.eval_every_steps=10",
        "controller=dnn_mpc",
    )
    tracking = metrics["tracking"]
    assert "skipped" not in tracking and tracking["solver_failures"] == 0
    assert list(tracking["controllers"]) == ["dnn_mpc", "bicycle_mpc"]  # the learner's first
    assert all(np.isfinite(v) for v in tracking["rmse"].values())
    assert set(tracking["solve_time_ms"]) == {"median", "p99", "max"}
    assert tracking["horizon"] == {"Np": 10, "Nc": 7}
    assert "not a lifted model" in metrics["spectrum"]["skipped"]  # no A_ to take eigenvalues of
    assert len(metrics["prediction"]["step_response"]) == 8  # every learner meets the steps


def test_a_bilinear_model_is_tracked_through_its_linearisation_beside_the_baseline(
    edmd_run,
) -> None:
    tmp, _, edmd = edmd_run
    # The tiny drives barely leave standstill: the baseline identifies from 1 m/s up here.
    metrics = run_main(
        tmp,
        tmp / "bilinear",
        "learner=bilinear_edmd",
        "task.extra_controllers.bicycle_mpc.model.min_speed_mps=1.0",
    )
    tracking = metrics["tracking"]
    assert "skipped" not in tracking and tracking["solver_failures"] == 0
    assert all(np.isfinite(v) for v in tracking["rmse"].values())
    assert list(tracking["controllers"]) == ["de_mpc", "bicycle_mpc"]  # the learner's first
    (baseline,) = tracking["controllers"]["bicycle_mpc"].values()
    assert all(np.isfinite(v) for v in baseline["rmse"].values())
    assert baseline["horizon"] == {"Np": 10, "Nc": 7} and baseline["solver_failures"] == 0
    # With too few moving samples the baseline says why instead of failing the run.
    reason = edmd["tracking"]["controllers"]["bicycle_mpc"]["skipped"]
    assert "learner.min_speed_mps" in reason
    assert "zero input" in metrics["spectrum"]["matrices"]  # and the input box's corners
    assert len(metrics["spectrum"]["matrices"]) == 5
    assert len(metrics["prediction"]["step_response"]) == 8


def test_input_edmd_runs_the_pipeline_through_its_linearisation(edmd_run) -> None:
    tmp, _, _ = edmd_run
    metrics = run_main(
        tmp,
        tmp / "input",
        "learner=input_edmd",
        "learner.dictionary.num_centers=30",  # the tiny drives hold 300-400 samples
        "task.extra_controllers.bicycle_mpc.model.min_speed_mps=1.0",
    )
    assert metrics["training"]["learner"] == "input_edmd"
    fit = metrics["training"]["fit"]  # the ridge the validation drive chose, and every score
    assert any(float(ridge) == fit["ridge"] for ridge in fit["validation_scores"])
    tracking = metrics["tracking"]
    assert list(tracking["controllers"]) == ["de_mpc", "bicycle_mpc"]
    assert tracking["solver_failures"] == 0
    assert all(np.isfinite(v) for v in tracking["rmse"].values())
    assert "not a lifted model" in metrics["spectrum"]["skipped"]
    assert len(metrics["prediction"]["step_response"]) == 8


def test_generalization_evaluates_the_model_on_other_plants_at_every_horizon(
    tmp_path: Path,
) -> None:
    metrics = run_main(
        tmp_path,
        tmp_path / "general",
        "learner=edmd",
        "experiment=generalization",
        "+controller@task.extra_controllers.de_mpc_long=de_mpc_long",
    )
    (episode,) = metrics["data"]["split"]["test"]
    assert set(metrics["tracking"]["controllers"]) == {"de_mpc", "de_mpc_long", "bicycle_mpc"}
    long = metrics["tracking"]["controllers"]["de_mpc_long"][f"test_episode/{episode}"]
    assert long["horizon"] == {"Np": 60, "Nc": 50}
    nominal = metrics["prediction"][episode]["rmse"]
    for plant in ("sedan_wet", "sedan_loaded"):
        other = metrics["generalization"][plant]
        assert other["prediction"][episode]["rmse"] != nominal  # another plant, other drives
        assert set(other["tracking"]["controllers"]) == {"de_mpc", "de_mpc_long", "bicycle_mpc"}
        assert (
            tmp_path / "general" / "generalization" / plant / f"prediction_{episode}.npz"
        ).exists()


def test_the_lane_change_is_judged_on_its_course(edmd_run) -> None:
    """``tracking.references.double_lane_change.path``: where the car went, against the cones
    of the ISO 3888-1 course; the top view and the course's arrays beside it."""
    tmp, run_dir, _ = edmd_run
    out = tmp / "course"
    metrics = run_main(
        tmp,
        out,
        "learner=edmd",
        f"task.model_path={run_dir}/model_edmd.pt",
        "+reference@task.references.lane_change=double_lane_change",  # TINY removed the default
        "+controller@task.extra_controllers.follower=de_mpc_path",  # TINY removed de_mpc_path
    )
    run = metrics["tracking"]["references"]["lane_change"]
    assert not run["follows_path"]  # de_mpc tracks the states
    assert set(run["final_error"]) == {"vx", "vy", "yaw_rate"}
    followed = metrics["tracking"]["controllers"]["follower"]
    assert followed["lane_change"]["follows_path"]  # on the course it steers by the path
    (label,) = (label for label in followed if label.startswith("test_episode"))
    drive = followed[label]
    assert not drive["follows_path"]  # a test drive has no path: its states are tracked
    # ... as de_mpc, whose settings it has but the path: de_mpc's run, not driven twice
    assert drive == {**metrics["tracking"]["controllers"]["de_mpc"][label], "same_run_as": "de_mpc"}
    for suffix in (".npz", ".png"):
        twin = (out / f"tracking_de_mpc_test_episode{suffix}").read_bytes()
        assert (out / f"tracking_follower_test_episode{suffix}").read_bytes() == twin
    path = run["path"]
    assert path["cones"] == 50 and 0 <= path["cones_hit"] <= 50
    assert path["passed"] == (path["reached_exit"] and path["cones_hit"] == 0)
    assert path["max_lateral_deviation_m"] >= path["rms_lateral_deviation_m"] >= 0
    assert "path" not in metrics["tracking"]["references"][metrics["tracking"]["reference"]]
    assert (out / "course_lane_change.png").stat().st_size > 10_000
    arrays = load_arrays(out / "course_lane_change.npz")
    assert arrays["cones"].shape == (50, 2)


def test_persistence_as_the_learner_skips_its_controller_not_the_baseline(tmp_path: Path) -> None:
    """learner=persistence: no MPC reads a held state, so DE-MPC is skipped with the reason;
    the physics baseline still tracks (its own model), and persistence's own prediction is the
    closed form: its RMSE over the whole drive equals prediction.persistence's."""
    # Drives that start rolling, so the baseline has a model to identify.
    metrics = run_main(
        tmp_path, tmp_path / "run", "learner=persistence", "data.start_speed_mps=[10,20]"
    )
    tracking = metrics["tracking"]
    assert "persistence is not a model a controller reads (it declares no" in tracking["skipped"]
    baseline = tracking["controllers"]["bicycle_mpc"]
    assert all("rmse" in run for run in baseline.values()) and baseline
    prediction = metrics["prediction"]
    for episode, held in prediction["persistence"].items():
        assert prediction[episode]["rmse"] == held["rmse"]
        assert "beats_persistence" not in prediction[episode]  # no verdict on itself


def test_a_later_job_reuses_the_baselines_runs_and_names_the_job_that_drove_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The physics baseline drives the same runs in every job of a dataset: a job that records
    nothing takes them from the one that drove them (harness/evaluation/reuse.py), the same
    metrics and arrays, marked; its own learner's controller is driven; other settings, or
    ``task.reuse_baseline_runs=false``, drive again."""
    from harness.evaluation import reuse

    monkeypatch.setattr(reuse, "root", lambda: tmp_path / "tracking")
    rolling = "data.start_speed_mps=[10,20]"  # drives the baseline can be identified on
    first = run_main(tmp_path, tmp_path / "a", "learner=edmd", rolling)
    second = run_main(tmp_path, tmp_path / "b", "learner=elm_edmd", rolling)
    driven = first["tracking"]["controllers"]["bicycle_mpc"]
    (label,) = driven
    reused = second["tracking"]["controllers"]["bicycle_mpc"][label]
    assert reused.pop("reused_from")["driven_in"] == str(tmp_path / "a")
    assert reused == driven[label]
    stem = "tracking_bicycle_mpc_test_episode.npz"
    assert (tmp_path / "b" / stem).read_bytes() == (tmp_path / "a" / stem).read_bytes()
    assert "reused_from" not in second["tracking"]["controllers"]["de_mpc"][label]
    other = run_main(
        tmp_path,
        tmp_path / "c",
        "learner=edmd",
        rolling,
        "task.extra_controllers.bicycle_mpc.R=50.0",
    )
    off = run_main(
        tmp_path, tmp_path / "d", "learner=edmd", rolling, "task.reuse_baseline_runs=false"
    )
    for metrics in (other, off):
        assert "reused_from" not in metrics["tracking"]["controllers"]["bicycle_mpc"][label]
