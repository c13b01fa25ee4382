"""``python -m harness`` works from any directory and leaves its results in the run directory."""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from harness.core.files import DirectoryInUseError, lock_directory, try_lock, unlock_directory
from harness.core.kernels import has_avx2, unpinned
from tests.helpers import run_job

CHARACTERIZE_KEYS = {
    "understeer_gradient_deg_per_g",
    "max_lateral_accel_mps2",
    "yaw_rate_rise_time_s",
    "yaw_rate_overshoot",
    "braking_distance_100kph_m",
    "accel_0_100kph_s",
    "top_speed_mps",
    "kinematic_yaw_rate_error",
    "drag_coefficient_fit",
    "rolling_resistance_fit",
}


TINY_COLLECTION = (  # task=collect on three short drives
    "task=collect",
    "data.episodes=3",
    "data.min_steps=100",
    "data.max_steps=150",
    "data.split={train: 1, validation: 1, test: 1}",
)


def run_harness(
    cwd: Path, *overrides: str, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """``python -m harness`` itself, for what only the command shows: its one-line errors and
    exit status, Hydra's callbacks, the environment it starts in (the jobs' results are
    checked in process, through :func:`tests.helpers.run_job`)."""
    return subprocess.run(
        [sys.executable, "-m", "harness", *overrides],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.fixture(scope="module")
def characterize_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """One characterization run of the wet plant, started from an unrelated directory."""
    cwd = tmp_path_factory.mktemp("elsewhere")
    run_dir = tmp_path_factory.mktemp("runs") / "wet"
    run_job(run_dir, "task=characterize", "plant=sedan_wet", cwd=cwd)
    return cwd, run_dir


def test_metrics_json_has_the_documented_characterize_keys(characterize_run) -> None:
    _, run_dir = characterize_run
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert set(metrics["characterize"]) >= CHARACTERIZE_KEYS
    assert metrics["characterize"]["road_friction"] == 0.5  # the override reached the plant


def test_recording_and_figure_land_in_the_run_directory_only(characterize_run) -> None:
    cwd, run_dir = characterize_run
    assert (run_dir / "characterize.rrd").stat().st_size > 10_000
    assert (run_dir / "characterize.png").stat().st_size > 10_000
    assert list(cwd.iterdir()) == []  # nothing written where the command was started
    assert not list(run_dir.glob("*.tmp*"))


def test_a_wrong_config_value_fails_with_one_line(tmp_path: Path) -> None:
    # A process: the line and the exit status are what the command prints and returns.
    result = run_harness(
        tmp_path, "plant.tire.road_friction=-1", "recorder=none", f"hydra.run.dir={tmp_path}/run"
    )
    assert result.returncode == 2
    error_lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert error_lines == ["error: ValueError: plant.tire.road_friction must be > 0 (got -1)"]


@pytest.mark.parametrize("value", ["0", "two"])
def test_a_wrong_thread_count_fails_with_one_line_before_any_work(tmp_path: Path, value) -> None:
    # A process: the line and the exit status are what the command prints and returns.
    result = run_harness(tmp_path, f"threads={value}", f"hydra.run.dir={tmp_path}/run")
    assert result.returncode == 2
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "threads must be an integer >= 1" in errors[0]
    assert not (tmp_path / "run" / "metrics.json").exists()


def test_an_unknown_plant_is_named_with_the_choices(tmp_path: Path) -> None:
    # A process: Hydra's own error, before any job, as the command line prints it.
    result = run_harness(tmp_path, "plant=tractor", f"hydra.run.dir={tmp_path}/run")
    assert result.returncode != 0
    assert "plant/tractor" in result.stderr and "sedan_wet" in result.stderr


def test_collect_task_writes_coverage_metrics_figure_and_recording(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    metrics = run_job(run_dir, *TINY_COLLECTION, f"data.root={tmp_path}/datasets", cwd=tmp_path)
    data = metrics["data"]
    assert data["coverage"]["episodes"] == 3 and data["coverage"]["frames"] > 300
    assert Path(data["path"]).parent == tmp_path / "datasets"
    assert (run_dir / "data_coverage.png").exists() and (run_dir / "collect.rrd").exists()


def test_a_run_into_another_runs_directory_moves_its_results_aside_and_never_merges_them(
    characterize_run, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A finished characterization's directory reused by a collection: the new metrics.json is
    the collection's alone, the characterization's files move to previous/<time>/ (said in one
    line), and the report counts the job under its own config."""
    from harness.report.jobs import read_run

    _, finished = characterize_run
    run_dir = tmp_path / "reused"
    shutil.copytree(finished, run_dir)
    with caplog.at_level(logging.WARNING):
        run_job(run_dir, *TINY_COLLECTION, f"data.root={tmp_path}/datasets", cwd=tmp_path)
    assert set(json.loads((run_dir / "metrics.json").read_text())) == {"data", "run"}
    (previous,) = (run_dir / "previous").iterdir()
    assert set(json.loads((previous / "metrics.json").read_text())) == {"characterize", "run"}
    assert (previous / "finished.json").exists() and not (run_dir / "characterize.rrd").exists()
    assert f"moved to {previous}" in caplog.text
    assert read_run(run_dir).error is None and set(read_run(run_dir).metrics or {}) == {
        "data",
        "run",
    }


def test_a_directory_that_cannot_be_written_is_named_with_the_setting_to_change(
    tmp_path: Path,
) -> None:
    """A run directory or a cache under a file (as a read-only disk, for any user, root too):
    one line naming the path and the setting, no Hydra callback warning."""
    # A process: the lock callback's exit and the one line come before the job, from Hydra.
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    result = run_harness(tmp_path, "task=characterize", f"hydra.run.dir={blocker / 'run'}")
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"error: cannot write {blocker / 'run'} (Not a directory): choose another hydra.run.dir"
    ]
    env = {**os.environ, "KOOPMAN_HARNESS_CACHE": str(blocker / "cache")}
    result = run_harness(tmp_path, *TINY_COLLECTION, f"hydra.run.dir={tmp_path / 'run'}", env=env)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == (
        f"error: cannot write {blocker / 'cache'} (Not a directory): choose another "
        "KOOPMAN_HARNESS_CACHE (the caches) or data.root (the datasets)"
    )


def test_a_long_override_list_still_makes_a_valid_distinct_job_directory() -> None:
    from harness.app import job_dirname

    short = "learner=edmd,seed=0"
    assert job_dirname(short) == short
    long_a, long_b = ("x" * 300 + "=1"), ("x" * 300 + "=2")
    names = {job_dirname(long_a), job_dirname(long_b)}
    assert len(names) == 2 and all(len(n.encode()) <= 200 for n in names)
    assert job_dirname("task.model_path=/runs/a/model.pt") == "task.model_path=_runs_a_model.pt"


@pytest.mark.parametrize(("mode", "key"), [([], "hydra.run.dir"), (["-m"], "hydra.sweep.dir")])
def test_a_directory_another_run_holds_is_refused_before_anything_is_written(
    tmp_path: Path, mode: list[str], key: str
) -> None:
    """Two runs in one directory mixed their metrics, models and figures."""
    # A process: the lock is refused to another process, before Hydra writes .hydra/.
    run_dir = (tmp_path / "run").resolve()
    run_dir.mkdir()
    held = try_lock(run_dir / ".lock")  # the run writing there now (another open file)
    assert held is not None
    try:
        result = run_harness(
            tmp_path, *mode, "task=characterize", "recorder=none", f"{key}={run_dir}"
        )
    finally:
        os.close(held)
    assert result.returncode == 2, result.stderr[-2000:]
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert errors == [
        f"error: {run_dir} is in use by another run (it holds {run_dir / '.lock'}); "
        f"choose another {key}"
    ]
    assert [p.name for p in run_dir.iterdir()] == [".lock"]  # not even Hydra's .hydra/


def test_a_killed_run_leaves_its_directory_free(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import time; from harness.core.files import lock_directory; "
            f"lock_directory({str(run_dir)!r}, 'hydra.run.dir'); print('held', flush=True); "
            "time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        with pytest.raises(DirectoryInUseError, match=r"choose another hydra\.run\.dir"):
            lock_directory(run_dir, "hydra.run.dir")
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert lock_directory(run_dir, "hydra.run.dir")  # the lock died with its process
    try:
        assert not lock_directory(run_dir, "hydra.run.dir")  # held once per process
        assert try_lock(run_dir / ".lock") is None  # but refused to any other open file
    finally:
        unlock_directory(run_dir)
    free = try_lock(run_dir / ".lock")
    assert free is not None
    os.close(free)


def test_a_jobs_config_digest_changes_with_what_it_computes_not_with_where_it_runs() -> None:
    """The digest a sweep rerun compares (``finished.json``): a ridge, a seed or a learner make
    another job; the dataset's directory, the worker count, the recorder and the progress bar
    do not."""
    from harness.app import config_digest
    from tests.helpers import compose

    def digest(*overrides: str) -> str:
        return config_digest(compose("learner=input_edmd", *overrides))

    base = digest()
    for same in ("data.root=/elsewhere", "data.workers=1", "recorder=none"):
        assert digest(same) == base, same
    assert digest("learner=deep_edmd", "learner.training.progress=false") == digest(
        "learner=deep_edmd"
    )
    for other in ("learner.ridge=1e-3", "seed=1", "learner=edmd", "data.episodes=20"):
        assert digest(other) != base, other


def test_the_same_seed_gives_the_same_numbers_whatever_the_threads_and_the_cpus_kernels(
    tmp_path: Path,
) -> None:
    """The job computes on ``threads`` (default 1) whatever ``OMP_NUM_THREADS`` says, and with
    MKL's AVX2 kernels whatever the CPU offers (harness/core/kernels.py): a Deep EDMD whose
    reductions are large enough to be split over threads (batch x window x lifted state >
    32768) trains, predicts and tracks to the same digits with the threads unset, 1 and 2, and
    with MKL told to run as on a CPU without AVX-512. Without the thread setting, on two cores,
    this job's vx RMSE moved by 5 %; without the kernels', on an AVX-512 Xeon, the main job's
    open-loop vx RMSE by 13 %."""
    # A process each: OMP_NUM_THREADS is read once, when the libraries load.
    overrides = [
        "data.episodes=3",
        "data.min_steps=3000",
        "data.max_steps=3000",
        "data.split={train: 1, validation: 1, test: 1}",
        f"data.root={tmp_path}/datasets",
        "recorder=none",
        "~reference@task.references.double_lane_change",
        "controller=de_mpc",
        *(
            f"~controller@task.extra_controllers.{name}"
            for name in (
                "de_mpc",
                "bicycle_mpc",
                "bicycle_mpc_path_long_offset_free",
                "de_mpc_offset_free",
                "bicycle_mpc_offset_free",
                "de_mpc_path",
                "bicycle_mpc_path",
            )
        ),
        "learner=deep_edmd",
        "learner.lifted_dim=40",
        "learner.training.max_steps=100",
        "learner.training.eval_every_steps=50",
        "learner.training.curriculum=null",
        "learner.training.progress=false",
    ]
    clean = {k: v for k, v in unpinned(os.environ).items() if k != "OMP_NUM_THREADS"}
    environments = {
        "threads unset": clean,
        "1 thread": {**clean, "OMP_NUM_THREADS": "1"},
        "2 threads": {**clean, "OMP_NUM_THREADS": "2"},
        "MKL as on an AVX2 CPU": {**clean, "MKL_ENABLE_INSTRUCTIONS": "AVX2"},
    }
    numbers = {}
    for name, env in environments.items():
        run_dir = tmp_path / name.replace(" ", "_")
        result = run_harness(tmp_path, *overrides, f"hydra.run.dir={run_dir}", env=env)
        assert result.returncode == 0, result.stderr[-2000:]
        metrics = json.loads((run_dir / "metrics.json").read_text())
        tracked = metrics["tracking"]
        numbers[name] = (metrics["prediction"], tracked["rmse"], tracked["final_error"])
        assert metrics["run"]["kernels"]["same_everywhere"] is has_avx2()
    assert all(value == numbers["threads unset"] for value in numbers.values())


def test_a_model_file_the_new_run_reads_stays_where_it_is(tmp_path: Path) -> None:
    """``task.model_path`` into the directory it lies in: the earlier run's results move aside,
    the model file this run loads does not."""
    from harness.app import move_previous_results

    for name in ("metrics.json", "finished.json", "model_edmd.pt", "prediction.png", "app.log"):
        (tmp_path / name).write_text(name)
    moved = move_previous_results(tmp_path, [tmp_path / "model_edmd.pt"])
    assert moved is not None
    assert sorted(p.name for p in moved.iterdir()) == [
        "finished.json",
        "metrics.json",
        "prediction.png",
    ]
    assert (tmp_path / "model_edmd.pt").exists() and (tmp_path / "app.log").exists()
    assert move_previous_results(tmp_path) is None  # nothing of a finished run is left
