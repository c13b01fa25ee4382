"""A user's driving logs become a dataset that every learner, the pipeline and the report use."""

from __future__ import annotations

import dataclasses
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf
from scipy.io import savemat

from harness.core.episode import InputChannel, MinMaxNormalizer
from harness.data.ddk import authors_split
from harness.data.logs import LogsConfig, import_logs, read_log
from harness.data.store import DatasetError, load
from harness.evaluation.prediction import evaluate
from harness.tasks.pipeline import Pipeline
from learners.dictionaries import ThinPlateRBF
from learners.edmd import EDMD
from learners.input_edmd import InputEDMD
from learners.persistence import Persistence
from tests.helpers import run_job

PERIOD = 0.01
COLUMNS = ["t", "speed_kmh", "vy", "r", "steer", "throttle", "brake"]


def drive(seed: int, rows: int = 400) -> np.ndarray:
    """(rows, 7): time, vx in km/h, vy, r, and three inputs of a stable linear car at 10 ms."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-1, 1, (rows // 20 + 1, 3)), 20, axis=0)[:rows]
    x = np.zeros((rows, 3))
    x[0] = [15.0, 0.0, 0.0]
    for k in range(rows - 1):
        vx, vy, r = x[k]
        x[k + 1] = [
            vx + PERIOD * (0.8 * u[k, 1] - 1.5 * u[k, 2] - 0.02 * (vx - 15.0)),
            vy + PERIOD * (-2.0 * vy - 4.0 * r + 3.0 * u[k, 0]),
            r + PERIOD * (0.5 * vy - 3.0 * r + 2.0 * u[k, 0]),
        ]
    table = np.column_stack([np.arange(rows) * PERIOD, x, u])
    table[:, 1] *= 3.6
    return table


def logs_config(path: Path, **changes: object) -> LogsConfig:
    values: dict[str, object] = {
        "path": str(path),
        "files": ["*.csv"],
        "time": {"column": "t"},
        "model_period_s": 0.05,
        "states": {"vx": {"column": "speed_kmh", "scale": 1 / 3.6}, "vy": "vy", "yaw_rate": "r"},
        "inputs": {"steer": "steer", "throttle": "throttle", "brake": "brake"},
        "split": {"train": 0.6, "validation": 0.2, "test": 0.2},
        "root": str(path / "store"),
    }
    return LogsConfig(**(values | changes))  # type: ignore[arg-type]


def logs_by_index(path: Path) -> LogsConfig:
    """The same columns as :func:`logs_config`'s, by index into the table ``log``."""
    return logs_config(
        path,
        array="log",
        time={"column": 0},
        states={"vx": {"column": 1, "scale": 1 / 3.6}, "vy": 2, "yaw_rate": 3},
        inputs={"steer": 4, "throttle": 5, "brake": 6},
    )


def write_csv(path: Path, table: np.ndarray, header: bool = True) -> Path:
    text = ",".join(COLUMNS) + "\n" if header else ""
    text += "\n".join(",".join(f"{v:.17g}" for v in row) for row in table) + "\n"
    path.write_text(text)
    return path


def expected(table: np.ndarray, every: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    kept = table[::every]
    states = np.column_stack([kept[:, 1] / 3.6, kept[:, 2], kept[:, 3]])
    return kept[:, 0] - kept[0, 0], states, kept[:, 4:7]


def test_a_log_in_every_format_reads_as_the_arrays_written(tmp_path: Path) -> None:
    """CSV by name and by index, npz by variable and as one array, MATLAB v5, Parquet: the same
    drive, scaled to SI and decimated to the model period, inputs held (every 5th sample)."""
    table = drive(0)
    write_csv(tmp_path / "named.csv", table)
    write_csv(tmp_path / "plain.csv", table, header=False)
    np.savez(tmp_path / "variables.npz", **{c: table[:, j] for j, c in enumerate(COLUMNS)})
    np.savez(tmp_path / "matrix.npz", log=table)
    savemat(tmp_path / "matrix.mat", {"log": table})
    by_name = logs_config(tmp_path)
    by_index = logs_by_index(tmp_path)
    cases = [
        ("named.csv", by_name),
        ("plain.csv", by_index),
        ("variables.npz", by_name),
        ("matrix.npz", by_index),
        ("matrix.mat", by_index),
    ]
    parquet = pytest.importorskip("pyarrow.parquet")
    import pyarrow

    columns = {c: table[:, j] for j, c in enumerate(COLUMNS)}
    parquet.write_table(pyarrow.table(columns), tmp_path / "table.parquet")
    cases.append(("table.parquet", by_name))
    time_s, states, inputs = expected(table)
    for name, config in cases:
        episode = read_log(tmp_path / name, config)
        assert episode.name == Path(name).stem
        np.testing.assert_allclose(episode.time_s, time_s, rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(episode.states, states, rtol=1e-12, err_msg=name)
        np.testing.assert_array_equal(episode.inputs, inputs, err_msg=name)
        assert episode.input_names == ("steer", "throttle", "brake")


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ("missing", r"b\.csv has no column 'r' for states\.yaw_rate"),
        ("nan", r"b\.csv has a non-finite vy \(nan\) in data row 8"),
        ("time", r"b\.csv has time that does not increase at data row 11"),
        ("period", r"b\.csv is sampled every 0\.03 s, which does not divide .*0\.05"),
        ("twice", r"b\.csv has two columns named 'vy' \(columns 2 and 3, 0-based\): rename one"),
        ("sentinel", r"b\.csv has vy = 999999 in data row 8, outside \[-50, 50\] \(data\.state_"),
        ("huge", r"b\.csv has yaw_rate = 1e\+300 in data row 8, outside \[-10, 10\]"),
        ("header only", r"b\.csv has a header and no data rows"),
        ("two rows", r"b\.csv has 2 rows, 1 at the model period \(0\.05 s\): a drive needs at"),
        ("milliseconds", r"b\.csv is sampled every 10 s: is its time in ms or ns\? scale it"),
        ("text in a row", r"b\.csv has a first line of numbers and text \(0,54,NA"),
        ("ragged", r"b\.csv is not a table of numbers: Line #21 \(got 6 columns instead of 7\)"),
    ],
)
def test_a_bad_log_fails_in_one_line_naming_the_file(
    tmp_path: Path, damage: str, message: str
) -> None:
    for i, name in enumerate("acde"):
        write_csv(tmp_path / f"{name}.csv", drive(i))
    table = drive(9)
    if damage == "nan":
        table[7, 2] = np.nan
    elif damage == "milliseconds":  # read as seconds: "does not divide 0.05"
        table[:, 0] *= 1000.0
    elif damage == "sentinel":  # a logger's "no value": it ran to the end, RMSE 2.6e3
        table[7, 2] = 999999.0
    elif damage == "huge":  # finite: it crashed the summary after training
        table[7, 3] = 1e300
    elif damage == "time":
        table[10, 0] = table[9, 0]
    elif damage == "period":
        table[:, 0] *= 3
    write_csv(tmp_path / "b.csv", table)
    text = (tmp_path / "b.csv").read_text()
    if damage == "missing":
        (tmp_path / "b.csv").write_text(text.replace(",r,", ",yaw,", 1))
    elif damage == "twice":  # the last of two would have won, silently
        (tmp_path / "b.csv").write_text(text.replace(",r,", ",vy,", 1))
    elif damage == "two rows":  # it read as "model period nan s" of the other logs
        (tmp_path / "b.csv").write_text("\n".join(text.splitlines()[:3]) + "\n")
    elif damage == "header only":  # it read as "7 header names for 0 columns"
        (tmp_path / "b.csv").write_text(text.splitlines()[0] + "\n")
    elif damage == "text in a row":  # without a header its first row was dropped silently
        rows = text.splitlines()[1:]
        rows[0] = ",".join(["0", "54", "NA", *rows[0].split(",")[3:]])
        (tmp_path / "b.csv").write_text("\n".join(rows) + "\n")
    elif damage == "ragged":  # numpy's reason is on its second line
        lines = text.splitlines()
        lines[20] = lines[20].rsplit(",", 1)[0]
        (tmp_path / "b.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=message) as info:
        import_logs(logs_config(tmp_path))
    assert "\n" not in str(info.value)
    # Every file is checked before anything is written: no episode, lock or folder is left.
    assert not (tmp_path / "store").exists()


def test_only_the_configured_columns_are_read_as_numbers(tmp_path: Path) -> None:
    """A text column or variable beside the configured ones (a driver's name, a unit) leaves
    the file readable; configured, it is refused naming it, as is a MATLAB struct."""
    table = drive(0)
    columns = {c: table[:, j] for j, c in enumerate(COLUMNS)}
    savemat(tmp_path / "units.mat", columns | {"units": "km/h"})
    episode = read_log(tmp_path / "units.mat", logs_config(tmp_path))
    np.testing.assert_allclose(episode.states, expected(table)[1], rtol=1e-12)
    savemat(tmp_path / "struct.mat", columns | {"r": {"value": table[:, 3]}})
    with pytest.raises(ValueError, match=r"has a struct, not numbers, in 'r' for states.yaw_rate"):
        read_log(tmp_path / "struct.mat", logs_config(tmp_path))
    parquet = pytest.importorskip("pyarrow.parquet")
    import pyarrow

    text = pyarrow.table(columns | {"driver": ["someone"] * len(table)})
    parquet.write_table(text, tmp_path / "driver.parquet")
    episode = read_log(tmp_path / "driver.parquet", logs_config(tmp_path))
    np.testing.assert_allclose(episode.states, expected(table)[1], rtol=1e-12)
    config = logs_config(tmp_path, inputs={"steer": "driver", "throttle": "throttle"})
    with pytest.raises(ValueError, match=r"has text, not numbers, in 'driver' for inputs.steer"):
        read_log(tmp_path / "driver.parquet", config)


def test_a_transposed_matlab_table_is_named_so(tmp_path: Path) -> None:
    savemat(tmp_path / "rows.mat", {"log": drive(0).T})  # a row per signal
    config = logs_by_index(tmp_path)
    with pytest.raises(ValueError, match=r"has .log. of 7 rows and 400 columns: .*transposed"):
        read_log(tmp_path / "rows.mat", config)


def test_a_loggers_microsecond_jitter_passes_the_period_check_and_the_decimation(
    tmp_path: Path,
) -> None:
    """±4 µs on 10 ms stamps: one tolerance for both checks (the decimation refused it)."""
    table = drive(0)
    table[:, 0] += np.random.default_rng(1).uniform(-4e-6, 4e-6, len(table))
    episode = read_log(write_csv(tmp_path / "jitter.csv", table), logs_config(tmp_path))
    assert len(episode.time_s) == len(table[::5])


def test_a_csv_with_a_byte_order_mark_reads_its_first_column_by_name(tmp_path: Path) -> None:
    table = drive(0)
    path = write_csv(tmp_path / "excel.csv", table)
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())  # as spreadsheet programs save
    np.testing.assert_allclose(read_log(path, logs_config(tmp_path)).time_s, expected(table)[0])


def test_logs_are_stored_once_by_content_and_split_by_seed_or_by_file(tmp_path: Path) -> None:
    for i in range(5):
        write_csv(tmp_path / f"run_{i}.csv", drive(i))
    config = logs_config(tmp_path)
    directory = import_logs(config)
    dataset = load(directory)
    assert dataset.from_logs and dataset.period_s == 0.05
    assert sorted(e.name for e in dataset.episodes()) == [f"run_{i}" for i in range(5)]
    assert [len(s) for s in (dataset.train, dataset.validation, dataset.test)] == [3, 1, 1]
    assert dataset.normalizer.input_names == ("steer", "throttle", "brake")
    assert dataset.normalizer.same_as(MinMaxNormalizer.fit(dataset.train))
    assert import_logs(config) == directory  # the same files and config: reused
    write_csv(tmp_path / "run_0.csv", drive(7))
    assert import_logs(config) != directory  # other bytes: another dataset
    by_file = logs_config(
        tmp_path,
        split={"train": ["run_[0-2].csv"], "validation": ["run_3.csv"], "test": ["run_4.csv"]},
    )
    split = load(import_logs(by_file)).manifest["split"]
    assert split == {
        "train": ["run_0", "run_1", "run_2"],
        "validation": ["run_3"],
        "test": ["run_4"],
    }
    twice = logs_config(
        tmp_path, split={"train": ["*"], "validation": ["run_3.csv"], "test": ["run_4.csv"]}
    )
    with pytest.raises(DatasetError, match=r"run_3\.csv is in train and in validation"):
        import_logs(twice)
    # Whole numbers are counts of files: 2/1/1 of 5 files is refused, not dealt as 3/1/1.
    with pytest.raises(DatasetError, match=r"counts 2/1/1 sum to 4, but data.files match 5"):
        import_logs(logs_config(tmp_path, split={"train": 2, "validation": 1, "test": 1}))
    counted = logs_config(tmp_path, split={"train": 2, "validation": 2, "test": 1})
    split = load(import_logs(counted)).manifest["split"]
    assert [len(split[s]) for s in ("train", "validation", "test")] == [2, 2, 1]


def test_learners_fit_and_predict_three_inputs_and_persistence_has_its_closed_form(
    tmp_path: Path,
) -> None:
    for i in range(5):
        write_csv(tmp_path / f"run_{i}.csv", drive(i))
    dataset = load(import_logs(logs_config(tmp_path)))
    small = InputEDMD(ThinPlateRBF(20, center_draw="samples"), ridge=[1e-6, 1e-3])
    for learner in (EDMD(ThinPlateRBF(20)), small):
        model = learner.fit(dataset.train, dataset.validation, dataset.normalizer)
        episode = dataset.test[0]
        predicted = model.predict(episode.states[0], episode.inputs[:-1])
        assert predicted.shape == episode.states.shape and np.isfinite(predicted).all()
        with pytest.raises(ValueError, match=r"inputs \(\.\.\., T, 3\)"):
            model.predict(episode.states[0], episode.inputs[:-1, :2])
    # Persistence on a ramp x_k = k c: each window of p steps from its start errs by c, 2c, ...
    ramp = dataset.test[0]
    steps = np.arange(len(ramp))[:, None] * np.array([[0.1, 0.01, 0.001]])
    ramp = type(ramp)(ramp.name, ramp.time_s, steps, ramp.inputs, ramp.poses, ramp.channels)
    held = Persistence().fit([], [], dataset.normalizer)
    result = evaluate({"p": held}, [ramp], window_steps=4, window_seconds=[])["p"][ramp.name]
    whole = np.sqrt(np.mean(np.arange(1, len(ramp)) ** 2))
    np.testing.assert_allclose(list(result["rmse"].values()), whole * np.array([0.1, 0.01, 0.001]))
    rows = np.setdiff1d(np.arange(len(ramp)), np.arange(0, len(ramp), 4))
    window = np.sqrt(np.mean((rows % 4) ** 2))
    np.testing.assert_allclose(
        list(result["rmse_window_4"].values()), window * np.array([0.1, 0.01, 0.001])
    )


def ddk_clone(root: Path, rows: int = 300) -> Path:
    """The DDK repository's layout with 38 small synthetic runs (theirs are not ours to ship):
    raw ``data_unit_<i>.mat`` (30 columns) and the authors' normalized copies, named by split."""
    raw, normalized = root / "CarsimDatasets", root / "MPC" / "CarsimDClassSUVDatasets"
    raw.mkdir(parents=True)
    normalized.mkdir(parents=True)
    roles = {1: "test_0", 24: "test_1", 31: "test_2", 38: "test_3"}
    roles |= {10: "val_0", 14: "val_1", 25: "val_2", 35: "val_3"}
    train = iter(range(30))
    for i in range(1, 39):
        table = drive(i, rows)
        data = np.zeros((rows, 30))
        data[:, 0] = table[:, 0] + PERIOD
        data[:, 1:4] = np.random.default_rng(i).normal(size=(rows, 3)).cumsum(0)
        data[:, 4], data[:, 5:7] = table[:, 1] / 3.6, table[:, 2:4]
        data[:, 27:30] = table[:, 4:7] * [0.05, 0.1, 0.5]
        savemat(raw / f"data_unit_{i}.mat", {"data": data})
        role = roles.get(i) or str(next(train))
        savemat(
            normalized / f"Carsim_DClassSUV_{role}.mat", {"Pos": data[:, 1:4], "X": data[:, 4:7]}
        )
    return root


def test_the_authors_split_is_matched_exactly_and_is_the_presets(tmp_path: Path) -> None:
    clone = ddk_clone(tmp_path / "DDK")
    split = authors_split(clone)
    assert split["test"] == [
        "data_unit_1.mat",
        "data_unit_24.mat",
        "data_unit_31.mat",
        "data_unit_38.mat",
    ]
    assert split["validation"] == [
        "data_unit_10.mat",
        "data_unit_14.mat",
        "data_unit_25.mat",
        "data_unit_35.mat",
    ]
    assert len(split["train"]) == 30
    with initialize_config_module(config_module="conf", version_base=None):
        cfg = compose("config", overrides=["data=ddk_carsim", f"data.path={clone}"])
    preset = OmegaConf.to_object(cfg.data)
    assert isinstance(preset, LogsConfig)
    assert {k: [p.split("/")[-1] for p in v] for k, v in preset.split.items()} == split
    # A copy whose run is missing, or two runs with one pose track: refused, not guessed.
    twin = clone / "CarsimDatasets" / "data_unit_2.mat"
    twin.write_bytes((clone / "CarsimDatasets" / "data_unit_1.mat").read_bytes())
    with pytest.raises(ValueError, match=r"matches [02] raw runs"):
        authors_split(clone)


def harness_on(clone: Path, tmp_path: Path, run_dir: Path, *overrides: str) -> dict:
    """``python -m harness data=ddk_carsim`` on ``clone`` with a small input EDMD, in this
    process; its metrics.json."""
    return run_job(
        run_dir,
        "data=ddk_carsim",
        f"data.path={clone}",
        f"data.root={tmp_path}/store",
        "learner=input_edmd",
        "learner.dictionary.num_centers=20",
        "recorder=none",
        *overrides,
        cwd=tmp_path,
    )


def ddk_pipeline(tmp_path: Path, learner: str, *overrides: str) -> Pipeline:
    """The pipeline built on the DDK preset (its files absent: nothing may read them)."""
    from hydra.utils import instantiate

    with initialize_config_module(config_module="conf", version_base=None):
        cfg = compose(
            "config",
            overrides=[
                "data=ddk_carsim",
                f"data.path={tmp_path / 'absent'}",
                f"learner={learner}",
                *overrides,
            ],
        )
    return Pipeline(cfg.data, instantiate(cfg.learner, _convert_="object"), learner)


def test_a_learner_needing_an_input_the_logs_lack_is_refused_before_they_are_read(
    tmp_path: Path,
) -> None:
    """The pedal split on logs with throttle and brake already apart: one line, no data read."""
    with pytest.raises(ValueError) as info:
        ddk_pipeline(tmp_path, "deep_edmd_split")
    assert str(info.value) == (
        "the data config has no 'pedal' input (front_wheel_angle_rad, throttle, brake_mpa): the "
        "pedal split needs a signed throttle/brake input (learner.pedal names it)"
    )


def test_the_pipeline_runs_on_logs_and_skips_what_needs_their_car(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    """data=ddk_carsim on a synthetic clone: fit, predict (whole runs, windows, persistence),
    spectrum; step responses and tracking skipped with the reason, at the logs' 50 ms."""
    clone = ddk_clone(tmp_path / "DDK")
    run_dir = tmp_path / "run"
    with caplog.at_level(logging.INFO):
        metrics = harness_on(clone, tmp_path, run_dir)
    assert metrics["data"]["inputs"] == ["front_wheel_angle_rad", "throttle", "brake_mpa"]
    assert metrics["data"]["period_s"] == 0.05 and metrics["data"]["source"] == "logs"
    assert metrics["data"]["split"]["test"] == [
        "data_unit_1",
        "data_unit_24",
        "data_unit_31",
        "data_unit_38",
    ]
    prediction = metrics["prediction"]
    for episode in metrics["data"]["split"]["test"]:
        for table in (prediction[episode], prediction["persistence"][episode]):
            assert set(table) >= {"rmse", "rmse_window_41", "rmse_window_3s", "rmse_window_1.5s"}
        # On a car driven by changing inputs the model beats holding the state.
        assert (
            prediction[episode]["rmse_window_3s"]["vx"]
            < prediction["persistence"][episode]["rmse_window_3s"]["vx"]
        )
    assert "input_edmd, seed 0, on logs: ddk_carsim:" in caplog.text
    assert "needs the car that made them" in prediction["step_response"]["skipped"]
    assert "needs the car that made them" in metrics["tracking"]["skipped"]
    assert metrics["spectrum"]
    model = run_dir / "model_input_edmd.pt"
    from learners import load as load_learner

    # The model steps once per 50 ms: on the same logs kept every 10 ms it is refused.
    capsys.readouterr()
    with pytest.raises(SystemExit) as again:
        harness_on(
            clone,
            tmp_path,
            tmp_path / "again",
            "data.model_period_s=0.01",
            f"task.model_path={model}",
        )
    assert again.value.code != 0
    assert "was fitted at a period of 0.05 s, but the data's is 0.01 s" in capsys.readouterr().err

    assert load_learner(model).normalizer_.channels == (
        InputChannel("front_wheel_angle_rad"),
        InputChannel("throttle"),
        InputChannel("brake_mpa"),
    )


def test_the_physics_baseline_on_logs_without_roles_is_refused_before_they_are_read(
    tmp_path: Path,
) -> None:
    """learner=single_track needs to know which input steers and which brakes: one line naming
    the key to set, no data read; the preset's roles pass the same check."""

    def pipeline(*overrides: str) -> Pipeline:
        return ddk_pipeline(tmp_path, "single_track", *overrides)

    assert pipeline().data.channels[2].role == "brake"  # the preset declares every role
    with pytest.raises(ValueError) as info:
        pipeline("data.inputs.brake_mpa.role=null")
    assert str(info.value).startswith(
        "single_track: input 'brake_mpa' declares no role, so the physics baseline cannot tell "
        "whether it steers, drives or brakes: set data.inputs.brake_mpa.role to one of "
    )
    with pytest.raises(ValueError, match=r"data\.inputs\.throttle: role must be one of"):
        pipeline("data.inputs.throttle.role=gas")
    with pytest.raises(ValueError, match=r"a steering input's unit must be deg or rad"):
        pipeline("data.inputs.front_wheel_angle_rad.unit=null")
    assert not (tmp_path / "absent").exists()


def test_logs_the_plant_made_are_tracked_on_it_when_the_user_says_so(tmp_path: Path) -> None:
    """Drives of our sedan exported as CSV and read back through a user's YAML (the one file a
    user writes, found with ``-cd``): with ``task.logs_from_plant=true`` the pipeline runs the
    step responses and DE-MPC on the plant, as it does on collected drives."""
    from harness.data.driver import DriverKnowledge
    from harness.data.store import DataConfig, drive_episode
    from harness.plant import Sedan

    plant = Sedan()
    logs = tmp_path / "logs"
    logs.mkdir()
    for index in range(4):
        d = drive_episode(plant, DataConfig(), DriverKnowledge.of(plant.params), index, 800)
        table = np.column_stack([d["time_s"], d["states"], d["inputs"], d["poses"]])
        header = "t,vx,vy,r,steer_wheel_deg,pedal,X,Y,yaw"
        np.savetxt(logs / f"drive_{index}.csv", table, delimiter=",", header=header, comments="")
    conf = tmp_path / "conf" / "data"
    conf.mkdir(parents=True)
    (conf / "sedan_logs.yaml").write_text(
        "defaults:\n  - logs_schema\n  - _self_\nname: sedan_logs\n"
        f"path: {logs}\nfiles: ['drive_*.csv']\ntime: {{column: t}}\n"
        "states: {vx: {column: vx}, vy: {column: vy}, yaw_rate: {column: r}}\n"
        "inputs: {steer_wheel_deg: {column: steer_wheel_deg, role: steering_wheel, unit: deg},"
        " pedal: {column: pedal, role: pedal}}\n"
        "poses: {X: {column: X}, Y: {column: Y}, yaw: {column: yaw}}\n"
        "split: {train: [drive_0.csv, drive_1.csv], validation: [drive_2.csv], "
        "test: [drive_3.csv]}\n"
        f"root: {tmp_path / 'store'}\n"
    )
    run_dir = tmp_path / "run"
    metrics = run_job(
        run_dir,
        # In process, the search path -cd adds to (the command line's -cd is checked below).
        f"hydra.searchpath=[file://{tmp_path / 'conf'}]",
        "data=sedan_logs",
        "task.logs_from_plant=true",
        "learner=input_edmd",
        "learner.dictionary.num_centers=20",
        "recorder=none",
        "controller=de_mpc",  # beside it the baseline only
        *(
            f"~controller@task.extra_controllers.{name}"
            for name in (
                "de_mpc",
                "bicycle_mpc_path_long_offset_free",
                "de_mpc_offset_free",
                "bicycle_mpc_offset_free",
                "de_mpc_path",
                "bicycle_mpc_path",
            )
        ),
        "~reference@task.references.double_lane_change",
        cwd=tmp_path,
    )
    assert metrics["data"]["source"] == "logs"
    assert "skipped" not in metrics["prediction"]["step_response"]
    assert "skipped" not in metrics["tracking"]
    assert np.isfinite(list(metrics["tracking"]["rmse"].values())).all()
    assert metrics["tracking"]["references"]["test_episode/drive_3"]["rmse"]
    assert set(metrics["tracking"]["controllers"]) == {"de_mpc", "bicycle_mpc"}
    assert "skipped" not in metrics["tracking"]["controllers"]["bicycle_mpc"]  # by its roles

    # A column given as a bare name where the schema wants {column: ...}: one line, its key.
    # A process: Hydra's own error while composing, as the command line prints it.
    yaml = conf / "sedan_logs.yaml"
    yaml.write_text(yaml.read_text().replace("vy: {column: vy}", "vy: vy"))
    bad = subprocess.run(
        [sys.executable, "-m", "harness", "-cd", str(tmp_path / "conf"), "data=sedan_logs"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert bad.returncode != 0
    assert bad.stderr.strip().splitlines()[-1].endswith("(key data.states.vy)"), bad.stderr


@pytest.mark.parametrize(
    ("period_s", "names", "message"),
    [
        (0.05, ("steer_wheel_deg", "pedal"), "set data.model_period_s=0.01 or plant."),
        (0.01, ("steer", "throttle", "brake"), "inputs are steer, throttle, brake; the plant"),
    ],
)
def test_logs_that_cannot_drive_the_plant_are_refused_in_one_line(
    period_s: float, names: tuple[str, ...], message: str
) -> None:
    from types import SimpleNamespace

    from harness.plant import Sedan
    from harness.tasks.pipeline import check_logs_drive

    episode = SimpleNamespace(channels=tuple(InputChannel(name) for name in names))
    dataset = SimpleNamespace(period_s=period_s, train=[episode])
    with pytest.raises(ValueError, match=r"task\.logs_from_plant") as error:
        check_logs_drive(Sedan(), dataset, "my_logs")  # type: ignore[arg-type]
    assert message in str(error.value) and "\n" not in str(error.value)


def test_logs_of_two_periods_are_refused_and_leave_a_stored_dataset_as_it_was(
    tmp_path: Path,
) -> None:
    """Each log at its own period (no data.model_period_s): a log twice as slow as the others
    is named; the dataset already stored from the good logs is untouched, file for file."""
    for i, name in enumerate("abcde"):
        write_csv(tmp_path / f"{name}.csv", drive(i))
    good = logs_config(tmp_path, model_period_s=None)
    stored = import_logs(good)
    before = {p: p.read_bytes() for p in sorted((tmp_path / "store").rglob("*")) if p.is_file()}
    slow = drive(9)
    slow[:, 0] *= 2
    write_csv(tmp_path / "f.csv", slow)
    with pytest.raises(DatasetError, match=r"f\.csv has model period 0\.02 s, the other logs"):
        import_logs(good)
    after = {p: p.read_bytes() for p in sorted((tmp_path / "store").rglob("*")) if p.is_file()}
    assert after == before and stored.is_dir()


def test_the_schema_page_is_generated_from_the_config_and_its_examples_are_valid(
    tmp_path: Path,
) -> None:
    """docs/guide/data_schema.md is what harness.data.schema writes; every example is a config
    the schema accepts, and the CSV one, quoted '#' names and all, reads its logs."""
    from harness.data.schema import EXAMPLES, PAGE, reference

    assert PAGE.read_text() == reference() + "\n", "run python -m harness.data.schema"
    configs = {}
    for title, text in EXAMPLES.items():
        values = OmegaConf.create(text)
        del values["defaults"]
        merged = OmegaConf.merge(OmegaConf.structured(LogsConfig), values)
        configs[title] = OmegaConf.to_object(merged)
        assert isinstance(configs[title], LogsConfig)
    race = configs["CSV with a header whose names start with #"]
    columns = ["#t_s", "#vx_mps", "#vy_mps", "#yawrate_degps", "#delta_rad", "#T_rl_Nm"]
    columns += ["#T_rr_Nm", "#p_f_bar", "#p_r_bar"]
    for lap in range(7):
        table = drive(lap)
        rows = np.column_stack([table[:, :4], table[:, 4:], table[:, 5:]])
        text = ",".join(columns) + "\n" + "\n".join(",".join(f"{v:.17g}" for v in r) for r in rows)
        (tmp_path / f"lap_{lap}.csv").write_text(text + "\n")
    race = dataclasses.replace(race, path=str(tmp_path), root=str(tmp_path / "store"))
    episode = read_log(tmp_path / "lap_0.csv", race)
    assert episode.input_names[1:3] == ("torque_rl", "torque_rr")
    assert [c.role for c in episode.channels] == ["road_wheel", "drive", "drive", "brake", "brake"]
    np.testing.assert_allclose(episode.states[:, 2], np.deg2rad(drive(0)[:, 3]), rtol=1e-12)
    assert import_logs(race).is_dir()
