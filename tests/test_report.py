"""Sweeps: every job's result, or the reason it has none, ends up in the report's tables."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from harness.core.files import try_lock
from harness.report import Run, load, main, read_runs, report
from harness.report.figures import loss_figure
from harness.report.jobs import NEVER_STARTED
from harness.report.summary import summary
from harness.report.tables import (
    QUALITY,
    course_speed_table,
    course_table,
    generalization_table,
    prediction_table,
    quality_table,
)
from tests.test_pipeline import TINY


def sweep(tmp: Path, sweep_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    # A process: a sweep is Hydra's multirun, its directories and its end-of-sweep callback.
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "harness",
            "-m",
            *TINY,
            # Tiny drives span little: one tiny EDMD leaves their envelope, which is not these
            # tests' subject (tests/test_prediction.py's is); a wide one keeps every seed in.
            "task.prediction_envelope_spans=10",
            f"data.root={tmp}/datasets",
            f"hydra.sweep.dir={sweep_dir}",
            *overrides,
        ],
        cwd=tmp,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture(scope="module")
def tiny_sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 learners x 2 seeds on tiny data, plus one job that fails on a bad value."""
    tmp = tmp_path_factory.mktemp("sweep")
    sweep_dir = tmp / "multirun"
    result = sweep(tmp, sweep_dir, "learner=edmd,elm_edmd", "seed=0,1")
    assert result.returncode == 0, result.stderr[-3000:]
    # every sweep ends with its report (the WriteReport callback), before anyone asks for it
    assert "elm_edmd" in (sweep_dir / "report" / "report.md").read_text()
    failing = sweep(tmp, sweep_dir / "bad", "learner=edmd", "learner.ridge=-1,0.0")
    assert failing.returncode == 0, failing.stderr[-3000:]  # one failed job ends no sweep
    return sweep_dir


def test_sweep_jobs_get_readable_directories(tiny_sweep: Path) -> None:
    names = [job.name for job in read_runs(tiny_sweep)]
    for learner in ("edmd", "elm_edmd"):
        for seed in (0, 1):
            assert sum(f"learner={learner}," in n and f"seed={seed}" in n for n in names) == 1


def test_report_has_a_row_per_learner_and_test_episode_over_seeds(tiny_sweep: Path) -> None:
    text = report(tiny_sweep).read_text()
    prediction = (tiny_sweep / "report" / "prediction.csv").read_text().splitlines()
    assert prediction[0] == "learner,plant,variant,test episode,jobs,vx,vy,yaw_rate"
    rows = [line.split(",") for line in prediction[1:]]
    plain = {(r[0], r[4]) for r in rows if r[2] == "—"}
    # two seeds each, and persistence (the state held) on the same drive: one row, no fit
    assert plain == {("edmd", "2"), ("elm_edmd", "2"), ("persistence", "—")}
    assert sum(r[2] == "—" for r in rows) == 3  # one test episode per learner
    assert all("±" in r[5] for r in rows if r[4] == "2")  # mean ± std over the two seeds
    assert any(r[2] == "learner.ridge=0.0" for r in rows)  # a different variant is its own row
    tracking = (tiny_sweep / "report" / "tracking.csv").read_text()
    assert "edmd,de_mpc,10/7" in tracking
    assert "5 of 6 jobs finished" in text


def test_a_failed_job_is_reported_with_its_error(tiny_sweep: Path) -> None:
    report(tiny_sweep)
    failures = (tiny_sweep / "report" / "failures.csv").read_text()
    assert "learner.ridge=-1" in failures and "learner.ridge" in failures.split("\n", 2)[1]


def test_a_job_without_metrics_is_named(tiny_sweep: Path, tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(tiny_sweep, copy)
    (victim,) = [
        j.path for j in read_runs(copy) if "learner=edmd," in j.name and "seed=1" in j.name
    ]
    (victim / "metrics.json").unlink()
    report(copy)
    failures = (copy / "report" / "failures.csv").read_text()
    assert f"{victim.name},no metrics.json" in failures.replace('"', "")


def test_an_empty_directory_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no Hydra job directories"):
        report(tmp_path)


def test_a_directory_that_does_not_exist_is_named_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([str(tmp_path / "typo")]) == 2
    assert (
        capsys.readouterr().err == f"error: {tmp_path / 'typo'} does not exist; give the "
        "sweep's directory (hydra.sweep.dir)\n"
    )
    assert not (tmp_path / "typo").exists()


def test_a_killed_sweep_counts_the_jobs_it_never_started_and_its_rerun_leaves_no_stale_file(
    tiny_sweep: Path, tmp_path: Path
) -> None:
    """The 4 jobs of the sweep (``multirun.yaml``): one killed while saving a figure, one never
    started; then the sweep rerun into the same directory, every job finished."""
    copy = tmp_path / "sweep"
    shutil.copytree(tiny_sweep, copy, ignore=shutil.ignore_patterns("bad"))
    by_name = {j.name: j.path for j in read_runs(copy)}
    (killed,) = [p for n, p in by_name.items() if "learner=edmd," in n and "seed=1" in n]
    (never,) = [p for n, p in by_name.items() if "learner=elm_edmd," in n and "seed=1" in n]
    (killed / "metrics.json").rename(tmp_path / "metrics.json")
    half_written = killed / ".prediction_episode_0002.png.x1y2z3.tmp"
    half_written.write_bytes(b"\x89PNG")
    shutil.move(never, tmp_path / "never")
    (copy / "report" / "stale.png").write_bytes(b"")  # a figure of an earlier report

    held = try_lock(killed / ".lock")  # while the job is still running, its files are its own
    assert held is not None
    try:
        report(copy)
    finally:
        os.close(held)
    assert half_written.exists()
    text = report(copy).read_text()
    assert "2 of 4 jobs finished" in text
    failures = (copy / "report" / "failures.csv").read_text().replace('"', "")
    assert f"{killed.name},no metrics.json" in failures
    assert f"{never.name},never started" in failures
    hydra = next(p for n, p in by_name.items() if "learner=elm_edmd," in n and "seed=0" in n)
    shutil.move(hydra / ".hydra", tmp_path / "hydra")  # results left, their config lost
    (lost,) = [r for r in read_runs(copy) if r.path == hydra]
    assert ".hydra is missing: its results cannot be matched to a config" in str(lost.error)
    shutil.move(tmp_path / "hydra", hydra / ".hydra")
    (unstarted,) = [r for r in read_runs(copy) if r.error == NEVER_STARTED]
    assert (unstarted.learner, unstarted.seed) == ("elm_edmd", 1)  # named by its overrides
    assert not half_written.exists()  # left by a killed writer: removed once no run holds it
    assert not (copy / "report" / "stale.png").exists()

    (tmp_path / "metrics.json").rename(killed / "metrics.json")
    shutil.move(tmp_path / "never", never)
    text = report(copy).read_text()
    assert "4 of 4 jobs finished" in text
    assert not (copy / "report" / "failures.csv").exists()  # no job failed: no stale list
    assert not list(copy.glob(".report*.tmp"))
    linked = {line.split("](")[1].rstrip(")") for line in text.splitlines() if "](" in line}
    assert {p.name for p in (copy / "report").glob("*.png")} == linked


def test_a_sweep_rerun_into_its_directory_skips_the_finished_jobs_and_runs_the_rest(
    tiny_sweep: Path, tmp_path: Path
) -> None:
    """Stop a long sweep and start it again: each job whose metrics.json is complete with the
    same config is skipped and says so; a job that failed, never finished or now has another
    config runs again."""
    copy = tmp_path / "multirun"
    shutil.copytree(tiny_sweep, copy, ignore=shutil.ignore_patterns("bad"))
    jobs = {j.name: j.path for j in read_runs(copy)}
    assert len(jobs) == 4
    stamps = {name: (path / "metrics.json").stat().st_mtime_ns for name, path in jobs.items()}
    (unfinished,) = [p for n, p in jobs.items() if "learner=elm_edmd," in n and "seed=1" in n]
    (unfinished / "finished.json").unlink()  # as a job killed before its end leaves it
    again = sweep(tmp_path, copy, "learner=edmd,elm_edmd", "seed=0,1")
    assert again.returncode == 0, again.stderr[-3000:]
    said = again.stdout + again.stderr
    for name, path in jobs.items():
        rerun = path == unfinished
        assert (f"skipped {name}: it finished before" in said) is not rerun
        assert ((path / "metrics.json").stat().st_mtime_ns != stamps[name]) is rerun
    assert (unfinished / "finished.json").exists()
    assert "4 of 4 jobs finished" in (copy / "report" / "report.md").read_text()


def test_a_job_whose_results_are_another_configs_is_not_counted_and_says_why(
    tiny_sweep: Path, tmp_path: Path
) -> None:
    """A finished.json whose digest is not its directory's config (another run ended there):
    the job's metrics.json is not reported as this config's; the failures say which file."""
    copy = tmp_path / "copy"
    shutil.copytree(tiny_sweep, copy)
    (victim,) = [
        j.path for j in read_runs(copy) if "learner=elm_edmd," in j.name and "seed=0" in j.name
    ]
    record = json.loads((victim / "finished.json").read_text())
    (victim / "finished.json").write_text(json.dumps(record | {"config_sha256": "0" * 64}))
    (run,) = [j for j in read_runs(copy) if j.path == victim]
    assert run.metrics is None and "is of another config" in str(run.error)
    assert "4 of 6 jobs finished" in report(copy).read_text()  # one failed by design


@pytest.mark.parametrize("damaged", ["metrics.json", ".hydra/hydra.yaml"])
def test_a_damaged_job_file_is_named_in_the_failures_and_the_rest_reported(
    tiny_sweep: Path, tmp_path: Path, damaged: str
) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(tiny_sweep, copy)
    (victim,) = [
        j.path for j in read_runs(copy) if "learner=elm_edmd," in j.name and "seed=0" in j.name
    ]
    text = (victim / damaged).read_text()
    (victim / damaged).write_text(text[: len(text) // 2] + "\n[torn")  # a torn copy
    assert "4 of 6 jobs finished" in report(copy).read_text()
    with (copy / "report" / "failures.csv").open() as handle:
        reasons = {row[0]: row[1] for row in csv.reader(handle)}
    assert str(victim / damaged.split("/")[0]) in reasons[victim.name]
    assert "\n" not in reasons[victim.name]


def test_the_report_redraws_the_paper_figures_with_every_learner(tiny_sweep: Path) -> None:
    text = report(tiny_sweep).read_text()
    out = tiny_sweep / "report"
    (episode,) = {p.stem.removeprefix("prediction_") for p in tiny_sweep.rglob("prediction_*.npz")}
    prediction = next(out.glob(f"prediction_{episode}*.png"))
    assert f"({prediction.name})" in text  # linked from report.md
    tracking = sorted(p.name for p in out.glob("tracking_de_mpc_*.png"))
    assert any(n.startswith("tracking_de_mpc_test_episode") for n in tracking), tracking


def test_loss_curves_show_every_seed_of_every_trained_network(tmp_path: Path) -> None:
    jobs = []
    for learner in ("dnn", "deep_edmd"):
        for seed in (0, 1):
            path = tmp_path / f"{learner}-{seed}"
            path.mkdir()
            history = {
                "step": [10, 20],
                "epoch": [0, 1],
                "train": [1.0, 0.5],
                "validation": [{"loss": 1.1}, {"loss": 0.6}],
                "stopped": "max_steps",
            }
            (path / "training_history.json").write_text(json.dumps(history))
            jobs.append(Run(path, choices={"learner": learner}, seed=seed))
    figure = loss_figure(jobs, tmp_path)
    assert figure is not None and figure.stat().st_size > 10_000
    assert loss_figure([Run(tmp_path / "edmd", choices={"learner": "edmd"})], tmp_path) is None


def _job(learner: str, seed: int, metrics: dict) -> Run:
    """A job of ``learner`` and ``seed`` on the sedan whose metrics.json is ``metrics``."""
    return Run(
        Path(f"{learner}-{seed}"),
        choices={"learner": learner, "plant": "sedan"},
        overrides={"learner": learner, "seed": str(seed)},
        seed=seed,
        metrics=metrics,
    )


def test_generalization_rows_put_each_model_on_its_own_plant_and_on_the_others() -> None:
    def section(value: float) -> dict:
        rmse = {"vx": value, "vy": value, "yaw_rate": value}
        tracking = {
            "references": {
                "test_episode/episode_0001": {"rmse": rmse},
                "double_lane_change": {"rmse": {k: 2 * v for k, v in rmse.items()}},
            }
        }
        return {"prediction": {"episode_0001": {"rmse": rmse}}, "tracking": tracking}

    jobs = [
        _job(
            "edmd",
            seed,
            {**section(1.0 + seed), "generalization": {"sedan_wet": section(3.0 + seed)}},
        )
        for seed in (0, 1)
    ]
    rows = {row[2]: row for row in generalization_table(jobs).rows}
    assert set(rows) == {"sedan", "sedan_wet"}
    assert rows["sedan"][:5] == ["edmd", "sedan", "sedan", "—", "2"]
    assert rows["sedan"][5].startswith("1.5 ±") and rows["sedan_wet"][5].startswith("3.5 ±")
    assert rows["sedan_wet"][-1].startswith("7 ±")  # lane change, mean of 6 and 8


def test_a_rollout_diverged_on_another_plant_is_named_in_its_row_not_averaged() -> None:
    def section(vx: float, diverged: bool = False) -> dict:
        rmse = {"vx": vx, "vy": 0.1, "yaw_rate": 0.01}
        return {"prediction": {"episode_0001": {"rmse": rmse, "diverged": diverged}}}

    wet = [section(2.0), section(4.0), section(1.3e8, diverged=True)]
    jobs = [
        _job("input_edmd", seed, {**section(1.0), "generalization": {"sedan_wet": wet[seed]}})
        for seed in (0, 1, 2)
    ]
    rows = {row[2]: row for row in generalization_table(jobs).rows}
    assert rows["sedan"][5] == "1 ± 0"
    assert rows["sedan_wet"][5] == "3 ± 1.4 (1 of 3 diverged)"  # mean and std of 2 and 4


def test_a_diverged_rollout_is_named_in_the_prediction_table_not_averaged() -> None:
    def job(seed: int, vx: float, diverged: bool) -> Run:
        rmse = {"vx": vx, "vy": 0.1, "yaw_rate": 0.01}
        held = {"rmse": {"vx": 5.0, "vy": 0.2, "yaw_rate": 0.08}}
        prediction = {"run_1": {"rmse": rmse, "diverged": diverged}, "persistence": {"run_1": held}}
        return _job("input_edmd", seed, {"prediction": prediction})

    table = prediction_table([job(0, 1.0, False), job(1, 3.0, False), job(2, 1e9, True)])
    learner, persistence = table.rows
    assert learner[:5] == ["input_edmd", "sedan", "—", "run_1", "2"]
    assert learner[5] == "2 ± 1.4 (1 of 3 diverged)"  # 1e9 is in no mean
    assert persistence[0] == "persistence" and persistence[5] == "5"
    everything_gone = prediction_table([job(2, 1e9, True)]).rows[0]
    assert everything_gone[5:] == ["diverged (1 of 1)"] * 3
    # On a user's logs the configured plant never ran: the row names the logs.
    logs = job(0, 1.0, False)
    logs.choices["data"] = "ddk_carsim"
    logs.metrics["data"] = {"source": "logs"}
    assert prediction_table([logs]).rows[0][1] == "logs: ddk_carsim"


def write_job(path: Path, choices: dict, overrides: list[str], seed: int, metrics: dict) -> Path:
    """A job directory as Hydra leaves it (the parts the report reads) with its metrics."""
    (path / ".hydra").mkdir(parents=True)
    hydra = {"hydra": {"runtime": {"choices": choices}, "overrides": {"task": overrides}}}
    (path / ".hydra" / "hydra.yaml").write_text(json.dumps(hydra))  # JSON is YAML
    (path / ".hydra" / "config.yaml").write_text(f"seed: {seed}\n")
    (path / "metrics.json").write_text(json.dumps(metrics))
    return path


def test_rows_are_named_by_the_jobs_choices_not_by_their_command_lines(tmp_path: Path) -> None:
    """A job that overrides nothing is named by the learner, plant and controller Hydra chose
    (here an experiment chose them), and its seed is the one its config ran with."""
    rmse = {"vx": 1.0, "vy": 2.0, "yaw_rate": 3.0}
    tracking = {
        "reference": "lane/episode_0002",
        "references": {
            "lane/episode_0002": {
                "rmse": rmse,
                "final_error": {"vx": 0.5, "vy": 0.25, "yaw_rate": 0.125},
            },
            "alpha": {"rmse": rmse},  # written before final_error existed
        },
    }
    choices = {"learner": "dnn", "plant": "sedan_wet", "controller": "de_mpc_long"}
    for seed in (3, 4):
        write_job(
            tmp_path / f"job{seed}",
            choices,
            ["experiment=mine", "learner.ridge=1e-3"],
            seed,
            {"prediction": {"episode_0002": {"rmse": rmse}}, "tracking": tracking},
        )
    runs = read_runs(tmp_path)
    assert [(r.learner, r.plant, r.controller, r.seed) for r in runs] == [
        ("dnn", "sedan_wet", "de_mpc_long", 3),
        ("dnn", "sedan_wet", "de_mpc_long", 4),
    ]
    assert runs[0].overrides == {"experiment": "mine", "learner.ridge": "0.001"}  # Hydra's form
    report(tmp_path)
    prediction = (tmp_path / "report" / "prediction.csv").read_text().splitlines()
    assert prediction[1].startswith("dnn,sedan_wet,—,episode_0002,2,")
    tracking_rows = (tmp_path / "report" / "tracking.csv").read_text().splitlines()[1:]
    # the controller the job chose; the reference it tracked first comes first
    assert [row.split(",")[:4] for row in tracking_rows] == [
        ["dnn", "de_mpc_long", "?/?", "lane"],
        ["dnn", "de_mpc_long", "?/?", "alpha"],
    ]
    # the error each run ended with (the mean of the jobs), "—" where a run has none
    assert [row.split(",")[9] for row in tracking_rows] == ["0.5 / 0.25 / 0.125", "— / — / —"]


def test_the_course_tables_judge_every_run_on_its_course_and_name_the_highest_speed() -> None:
    """A row per learner × controller × surface × lane-change speed (60 before 100), passes of
    jobs; the headline: the highest speed passed by every job (the wet road passes less)."""

    def lane_changes(fails_from_kph: int) -> dict:
        runs = {}
        for kph in (60, 80, 100):
            passed = kph < fails_from_kph
            path = {
                "passed": passed,
                "cones_hit": 0 if passed else 4,
                "reference_speed_mps": kph / 3.6,
            }
            runs[f"lane_change_{kph}kph"] = {"rmse": {}, "path": path}
        runs["test_episode/episode_0001"] = {"rmse": {}}  # no course: not in these tables
        return {"tracking": {"controllers": {"de_mpc": runs}}}

    jobs = [
        Run(
            Path(f"edmd-{seed}"),
            choices={"learner": "edmd", "plant": "sedan", "controller": "de_mpc"},
            overrides={"seed": str(seed)},
            seed=seed,
            # seed 1 fails at 80 km/h on the dry road: the row's headline is 60
            metrics={
                **lane_changes(100 if seed == 0 else 80),
                "generalization": {"sedan_wet": lane_changes(80)},
            },
        )
        for seed in (0, 1)
    ]
    rows = course_table(jobs).rows
    assert [row[2:4] for row in rows[:3]] == [
        ["sedan", "lane_change_60kph"],
        ["sedan", "lane_change_80kph"],
        ["sedan", "lane_change_100kph"],
    ]
    assert rows[1][5:7] == ["1/2", "2 ± 2.8"] and len(rows) == 6
    headline = {row[2]: row[4:] for row in course_speed_table(jobs).rows}
    assert headline == {
        "sedan": ["2", "60", "60, 80, 100"],
        "sedan_wet": ["2", "60", "60, 80, 100"],
    }


def test_load_gives_one_row_per_job_controller_and_reference_with_every_metric(
    tiny_sweep: Path,
) -> None:
    """``harness.report.load``: the sweep as a pandas table whose numbers are the jobs' own."""
    table = load(tiny_sweep)
    runs = read_runs(tiny_sweep)
    for run in runs:
        rows = table[table.job == run.name]
        if run.metrics is None:  # the failed job: one row, its error, no closed loop
            assert len(rows) == 1 and rows.error.iloc[0] and rows.controller.isna().all()
            continue
        controllers = run.metrics["tracking"]["controllers"]
        skipped = [name for name, runs in controllers.items() if "skipped" in runs]
        loops = [
            (controller, reference, values)
            for controller, references in controllers.items()
            for reference, values in references.items()
            if controller not in skipped
        ]
        assert len(rows) == len(loops) + len(skipped) and loops  # DE-MPC tracked at least
        for name in skipped:  # the baseline on drives too short to identify it: its own row
            (row,) = rows[rows.controller == name].index
            assert table.at[row, "skipped"] == controllers[name]["skipped"]
        for controller, reference, values in loops:
            (row,) = rows[(rows.controller == controller) & (rows.reference == reference)].index
            assert table.at[row, "rmse.yaw_rate"] == values["rmse"]["yaw_rate"]
            assert table.at[row, "solve_time_ms.p99"] == values["solve_time_ms"]["p99"]
            assert table.at[row, "horizon"] == "10/7" and table.at[row, "mode"] == "states"
            assert table.at[row, "learner"] == run.learner and table.at[row, "seed"] == run.seed
        (episode,) = run.metrics["data"]["split"]["test"]
        column = f"prediction.{episode}.rmse.vx"
        assert (rows[column] == run.metrics["prediction"][episode]["rmse"]["vx"]).all()
    # One query of the kind the docs show: the mean over seeds, per learner and controller.
    means = table.dropna(subset=["controller"]).groupby(["learner", "controller"])["rmse.vx"]
    assert set(means.mean().index.get_level_values("learner")) == {"edmd", "elm_edmd"}
    with pytest.raises(ValueError, match="holds no Hydra job directories"):
        load(tiny_sweep / "report")
    with pytest.raises(ValueError, match=r"typo does not exist; give a sweep's, a study's"):
        load(tiny_sweep / "typo")


def test_load_gives_the_closed_loops_on_other_plants_rows_of_their_own(
    tiny_sweep: Path, tmp_path: Path
) -> None:
    """experiment=generalization tracks on sedan_wet too (``generalization.<plant>.tracking``):
    those runs are rows whose plant is the one driven, not columns of the dry rows."""
    job = next(run.path for run in read_runs(tiny_sweep) if run.metrics is not None)
    copy = tmp_path / job.name
    shutil.copytree(job, copy)
    metrics = json.loads((copy / "metrics.json").read_text())
    wet = json.loads(json.dumps(metrics["tracking"]))  # the same numbers, said of sedan_wet
    wet["controllers"]["de_mpc"][next(iter(wet["controllers"]["de_mpc"]))]["rmse"]["vx"] = 9.0
    metrics["generalization"] = {"sedan_wet": {"tracking": wet, "prediction": {"x": 1.0}}}
    (copy / "metrics.json").write_text(json.dumps(metrics))
    table = load(copy)
    dry, other = table[table.plant == "sedan"], table[table.plant == "sedan_wet"]
    assert len(dry) == len(other) > 0
    assert (other[other.controller == "de_mpc"]["rmse.vx"] == 9.0).all()
    assert (dry["generalization.sedan_wet.prediction.x"] == 1.0).all()
    assert not any(column.startswith("generalization.sedan_wet.tracking") for column in table)


def test_a_runs_summary_says_per_controller_whether_the_lane_change_passed() -> None:
    """One line per test drive (with persistence beside it), one per controller (the run's
    first): the course's verdict, deviation and cones, a test drive's tracking RMSE, the step."""
    run = {
        "rmse": {"vx": 0.05, "vy": 0.02, "yaw_rate": 0.01},
        "step_time_ms": {"median": 1.0, "p99": 2.5, "max": 3.0},
        "deadline_misses": 0,
        "horizon": {"Np": 60, "Nc": 50},
    }
    course = {
        **run,
        "deadline_misses": 3,
        "path": {
            "passed": False,
            "max_lateral_deviation_m": 0.41,
            "cones_hit": 2,
            "reference_speed_mps": 22.222,
        },
    }
    metrics = {
        "prediction": {
            "episode_0000": {"rmse": {"vx": 0.5, "vy": 0.05, "yaw_rate": 0.02}, "diverged": False},
            "persistence": {"episode_0000": {"rmse": {"vx": 6.0, "vy": 0.3, "yaw_rate": 0.3}}},
        },
        "tracking": {
            "controllers": {
                "main": {"test_episode/episode_0000": run, "double_lane_change": course},
                "beside": {"skipped": "no model"},
            }
        },
    }
    lines = summary(metrics, "edmd, seed 0:").splitlines()
    assert lines[0] == "edmd, seed 0:"
    assert lines[1] == (
        "  test drive episode_0000, open loop RMSE vx / vy / r: 0.5 / 0.05 / 0.02;"
        " persistence 6 / 0.3 / 0.3"
    )
    assert lines[2] == (
        "  main 60/50, the run's controller: test_episode/episode_0000 tracked, RMSE"
        " 0.05 / 0.02 / 0.01; double_lane_change at 80 km/h FAILED, 0.41 m, 2 cones,"
        " 3 deadline misses; step 1.00 / 2.50 ms (median / p99)"
    )
    assert lines[3] == "  beside: skipped (no model)"
    assert len(lines) == 4
    course["path"]["reached_exit"] = False  # a car that stopped before the cones
    assert "FAILED (never reached the exit), 0.41 m" in summary(metrics).splitlines()[1]
    # how smoothly it drove, where the run measured it (tracking…quality)
    course["quality"] = {
        "steering_reversals_per_min": 583.2,
        "pedal_changes_per_min": 83.0,
        "long_jerk_rms_mps3": 4.38,
    }
    assert (
        "2 cones (steering 583 reversals/min, pedal 83 throttle-brake changes/min, jerk 4.4 m/s³),"
        " 3 deadline misses" in summary(metrics).splitlines()[1]
    )


def test_the_quality_table_averages_how_smoothly_each_controller_drove_over_seeds() -> None:
    """A row per learner × controller × reference with tracking…quality's means over seeds; a
    job measured before the key existed gives no row, so an older study's report is unchanged."""

    def quality(reversals: float, jerk: float) -> dict:
        keys = dict.fromkeys(QUALITY, 0.0)
        return keys | {"steering_reversals_per_min": reversals, "long_jerk_rms_mps3": jerk}

    def metrics(reversals: float, jerk: float) -> dict:
        run = {"rmse": {"vx": 0.1}, "horizon": {"Np": 60, "Nc": 50}}
        return {
            "tracking": {
                "controllers": {
                    "main": {
                        "double_lane_change": run | {"quality": quality(reversals, jerk)},
                        "test_episode/episode_0000": run,  # measured before quality: no row
                    }
                }
            }
        }

    jobs = [_job("deep_edmd", 0, metrics(60.0, 1.0)), _job("deep_edmd", 1, metrics(80.0, 2.0))]
    (row,) = quality_table(jobs).rows
    assert row[:6] == ["deep_edmd", "main", "60/50", "double_lane_change", "—", "2"]
    assert row[6] == "70 ± 14" and row[10] == "1.5 ± 0.71"
    assert quality_table([_job("edmd", 0, {"tracking": {"rmse": {"vx": 0.1}}})]).rows == []


def test_the_prediction_table_marks_each_state_where_a_learner_does_not_beat_persistence() -> None:
    def job(seed: int, vy_beats: bool) -> Run:
        rmse = {"vx": 1.0, "vy": 0.25, "yaw_rate": 0.01}
        verdicts = {"open_loop": {"vx": True, "vy": vy_beats, "yaw_rate": True}}
        episode = {"rmse": rmse, "diverged": False, "beats_persistence": verdicts}
        return _job("edmd", seed, {"prediction": {"run_1": episode}})

    always = prediction_table([job(0, False), job(1, False)]).rows[0]
    assert always[5] == "1 ± 0"  # vx beats it: no mark
    assert always[6] == "0.25 ± 0 (worse than persistence)"
    once = prediction_table([job(0, True), job(1, False), job(2, True)]).rows[0]
    assert once[6] == "0.25 ± 0 (worse than persistence in 1 of 3)"
    # The verdict is per window: the 3 s table reads its own (none here: no mark).
    assert "worse" not in " ".join(prediction_table([job(0, False)], "rmse_window_3s").rows[0])


def test_the_summary_names_the_states_and_windows_where_persistence_was_not_beaten() -> None:
    rmse = {"vx": 0.5, "vy": 0.05, "yaw_rate": 0.02}
    verdicts = {
        "open_loop": {"vx": True, "vy": False, "yaw_rate": True},
        "41_steps": {"vx": False, "vy": True, "yaw_rate": True},
        "1.5s": {"vx": False, "vy": False, "yaw_rate": None},
    }
    beaten = {"rmse": rmse, "beats_persistence": verdicts}
    spun = {
        "rmse": rmse,
        "diverged": True,
        "diverged_at_s": 90.24,
        "rmse_until_diverged": {"vx": 0.3, "vy": 0.04, "yaw_rate": 0.01},
        "beats_persistence": {"open_loop": dict.fromkeys(("vx", "vy", "yaw_rate"), True)},
    }
    lines = summary({"prediction": {"lap_1": beaten, "lap_2": spun}}).splitlines()
    assert lines[1] == (
        "    not better than persistence on vx (41-step windows, 1.5 s windows), "
        "vy (open loop, 1.5 s windows)"
    )
    assert lines[2].endswith(
        "0.5 / 0.05 / 0.02 (diverged at t = 90.2 s; until then 0.3 / 0.04 / 0.01)"
    )
    assert len(lines) == 3  # a drive that beats it everywhere has no such line


def test_the_summary_prints_a_value_the_run_could_not_compute_and_says_when_solves_failed() -> None:
    """A null RMSE (an overflow, a window longer than the drive) is n/a, not a crash; failed
    solves are counted beside the deadline misses."""
    metrics = {
        "prediction": {"episode_0000": {"rmse": {"vx": None, "vy": 0.05, "yaw_rate": 0.02}}},
        "tracking": {
            "controllers": {
                "main": {
                    "test_episode/episode_0000": {
                        "rmse": {"vx": 0.05, "vy": 0.02, "yaw_rate": 0.01},
                        "solver_failures": 268,
                        "steps": 387,
                    }
                }
            }
        },
    }
    lines = summary(metrics).splitlines()
    assert lines[0].endswith("open loop RMSE vx / vy / r: n/a / 0.05 / 0.02")
    assert lines[1].endswith("RMSE 0.05 / 0.02 / 0.01, 268 of 387 solves failed")
