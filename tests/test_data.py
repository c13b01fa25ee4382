"""Driving data: a driver a person would recognise, and a store that never lies about its files."""

from __future__ import annotations

import dataclasses
import json
import pickle
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from harness.core.contracts import Plant
from harness.core.episode import SEDAN_INPUTS, Episode, InputChannel, MinMaxNormalizer
from harness.data import coverage
from harness.data.collect import reference_speeds
from harness.data.coverage import sawtooth_frames, steering_reversals
from harness.data.driver import DriverConfig, DriverKnowledge, SyntheticDriver
from harness.data.store import (
    DataConfig,
    Dataset,
    DatasetError,
    collect,
    content_key,
    drive_episode,
    load,
    write_manifest,
)
from harness.plant import Sedan, SedanParams
from harness.plant.params import TireParams
from harness.plant.rollout import simulate
from harness.references import Reference

DRY = DriverKnowledge.of(SedanParams())  # what the driver of the default sedan knows


def tiny(root: Path, **changes) -> DataConfig:
    values = dict(
        episodes=4,
        min_steps=150,
        max_steps=250,
        workers=1,
        root=str(root),
        split={"train": 2, "validation": 1, "test": 1},
    )
    values.update(changes)
    return DataConfig(**values)


@pytest.fixture(scope="module")
def driven(sedan_module: Sedan):
    config = DriverConfig()
    runs = []
    for seed in range(3):
        driver = SyntheticDriver(
            config, np.random.default_rng(seed), sedan_module.dt, road_friction=0.9
        )
        run = simulate(sedan_module, driver, 90.0, stop=lambda t, x, d=driver: d.spun)
        runs.append((run, sedan_module.clipped_inputs))
    return config, runs


@pytest.fixture(scope="module")
def sedan_module() -> Sedan:
    return Sedan()


def test_driver_inputs_stay_in_range_and_are_rate_limited(driven) -> None:
    config, runs = driven
    for run, clipped in runs:
        steer, pedal = run.inputs[:-1].T
        assert clipped == 0
        assert np.all(np.abs(steer) <= 450.0)
        assert np.all((pedal >= -9.1) & (pedal <= 0.2))
        dt = 0.01
        assert np.max(np.abs(np.diff(steer))) <= 2 * config.steer_rate_deg_per_s * dt + 1e-9
        assert np.max(np.abs(np.diff(pedal))) <= config.brake_rate_mpa_per_s * dt + 1e-9


def test_driver_never_goes_from_throttle_to_brake_without_lifting_off(driven) -> None:
    _, runs = driven
    for run, _ in runs:
        pedal = run.inputs[:-1, 1]
        sign_flips = np.nonzero(np.sign(pedal[1:]) * np.sign(pedal[:-1]) < 0)[0]
        # A flip happens only from near zero: the foot left one pedal before the other.
        assert np.all(np.abs(pedal[sign_flips]) <= 0.02 + 1e-9)
        assert np.all(np.abs(pedal[sign_flips + 1]) <= 0.25 + 1e-9)


def test_driver_starts_from_rest_with_a_random_wheel_and_explores_the_envelope(driven) -> None:
    _, runs = driven
    first_steers = {round(run.inputs[0, 0], 3) for run, _ in runs}
    assert len(first_steers) == 3  # random initial steering-wheel angle per episode
    for run, _ in runs:
        np.testing.assert_array_equal(run.states[0], 0.0)
        assert run.inputs[0, 1] <= 0.01  # throttle starts (near) zero
    states = np.concatenate([run.states for run, _ in runs])
    lateral = np.concatenate([np.abs(run.lateral_accel_mps2[2:]) for run, _ in runs])
    inputs = np.concatenate([run.inputs for run, _ in runs])
    assert states[:, 0].max() > 15.0 and np.mean(states[:, 0] < 5.0) > 0.05
    assert lateral.max() > 0.7 * 0.9 * 9.81  # some segments near the friction limit
    assert np.mean(inputs[:, 1] < 0) > 0.03 and np.mean(inputs[:, 1] > 0) > 0.3


def test_driver_is_reproducible_from_its_seed(sedan_module: Sedan) -> None:
    def drive(seed: int) -> np.ndarray:
        driver = SyntheticDriver(
            DriverConfig(), np.random.default_rng(seed), 0.01, road_friction=0.9
        )
        return simulate(sedan_module, driver, 10.0).inputs

    np.testing.assert_array_equal(drive(5), drive(5))
    assert not np.array_equal(drive(5), drive(6))


def test_bad_data_values_name_their_key(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"data\.split counts sum"):
        tiny(tmp_path, split={"train": 1, "validation": 1, "test": 1})
    with pytest.raises(ValueError, match=r"data\.min_steps"):
        tiny(tmp_path, min_steps=500, max_steps=100)
    with pytest.raises(ValueError, match=r"data\.driver\.steer_rate_deg_per_s"):
        DriverConfig(steer_rate_deg_per_s=-1.0)
    with pytest.raises(ValueError, match=r"data\.driver\.segment_duration_s"):
        DriverConfig(segment_duration_s=(1.0, 2.0, 3.0))
    below = r"data\.driver\.recovery_exit_sideslip_deg must be below .*\(got 9\)"
    with pytest.raises(ValueError, match=below):
        DriverConfig(recovery_exit_sideslip_deg=9.0)
    with pytest.raises(ValueError, match=r"data\.start_speed_mps must be \[low, high\]"):
        tiny(tmp_path, start_speed_mps=[20.0, 5.0])
    with pytest.raises(ValueError, match=r"data\.start_speed_mps .*max_speed_mps \(33"):
        tiny(tmp_path, start_speed_mps=[0.0, 40.0])
    for gains in ([0.0, 1.0], [1.0], [3.3, -0.83], [float("inf"), 1.0]):
        with pytest.raises(ValueError, match=r"data\.pedal_gains must be \[throttle, brake\]"):
            tiny(tmp_path, pedal_gains=gains)


def rear_slip_state(speed: float, rear_slip_deg: float, yaw_rate: float = 0.2) -> np.ndarray:
    """A state whose rear-axle sideslip (half a wheelbase, 1.35 m, behind the CG) is given."""
    vy = speed * np.tan(np.radians(rear_slip_deg)) + 1.35 * yaw_rate
    return np.array([speed, vy, yaw_rate])


def test_the_driver_recovers_from_a_rear_slide_with_hysteresis() -> None:
    driver = SyntheticDriver(DriverConfig(), np.random.default_rng(0), 0.01, road_friction=0.9)
    driver(0.0, rear_slip_state(20.0, 0.0))
    seen = []
    for slip in (5.0, 9.0, 7.0, 5.0, 3.5, 2.5, 5.0, 7.9, 8.5):
        driver(0.01, rear_slip_state(20.0, slip))
        seen.append(driver.recovering)
    # Enters above 8 deg, stays in down to 3 deg, stays out until 8 deg again.
    assert seen == [False, True, True, True, True, False, False, False, True]
    steer, pedal = driver.steer, driver.pedal
    driver(0.02, rear_slip_state(20.0, 9.0))
    # Straightening the wheel at twice the normal rate (7.2 deg a step) and lifting off.
    assert abs(driver.steer) < max(abs(steer) - 5.0, 3.0)
    assert driver.pedal <= max(pedal, 0.0)


def test_a_gripping_turn_at_walking_pace_is_not_a_slide() -> None:
    """At 4 m/s and r = 0.8 rad/s every tyre grips with 12 deg of sideslip at the CG (the
    geometry's, atan(b r / v)): the rear axle's is zero, and the driver keeps steering."""
    driver = SyntheticDriver(DriverConfig(), np.random.default_rng(0), 0.01, road_friction=0.9)
    x = rear_slip_state(4.0, 0.0, yaw_rate=0.8)
    assert np.degrees(np.arctan2(x[1], x[0])) > 12.0 and abs(driver.rear_sideslip_deg(x)) < 1e-9
    for k in range(50):
        driver(k * 0.01, x)
        assert not driver.recovering


def test_the_sawtooth_measure_flags_a_zigzag_and_not_a_slalom() -> None:
    dt = 0.01
    t = np.arange(0, 4, dt)
    zigzag = np.clip(np.cumsum(np.sign(np.sin(2 * np.pi * 4 * t))) * 7.2, -30, 30)
    slalom = 200 * np.sin(2 * np.pi * 1.0 * t)  # the driver's fastest slalom, 1 Hz
    assert len(steering_reversals(slalom, dt)) == 8  # two a second, at each peak
    assert sawtooth_frames(zigzag, dt).mean() > 0.9
    assert not sawtooth_frames(slalom, dt).any()


def test_default_drives_keep_steering_reversals_human(sedan_module: Sedan) -> None:
    """Episode 2 of data=default saw-toothed at 11-13 s (+-30 deg at several Hz) before the
    recovery logic had hysteresis and looked at the rear axle; episode 7 for 24 % of its frames."""
    data = DataConfig(start_speed_mps=[0.0, 0.0])  # the old default's drives, from rest
    for index in (2, 7):
        drive = drive_episode(sedan_module, data, DRY, index, 1500)
        steer = np.asarray(drive["inputs"])[:, 0]
        assert not sawtooth_frames(steer, 0.01).any()
        reversals = steering_reversals(steer, 0.01)
        per_second = np.bincount(reversals // 100)
        assert per_second.max() <= 4, per_second


def test_a_rolling_start_is_drawn_per_episode_and_cruised_on(sedan_module: Sedan) -> None:
    data = DataConfig(start_speed_mps=[10.0, 28.0])
    speeds = [data.start_speed(i) for i in range(6)]
    assert speeds == [data.start_speed(i) for i in range(6)]  # from the episode's seed
    assert all(10.0 <= v <= 28.0 for v in speeds) and len(set(speeds)) == 6
    assert DataConfig(start_speed_mps=[0.0, 0.0]).start_speed(3) == 0.0  # data=paper: from rest
    assert 0 <= DataConfig().start_speed(3) <= 28.0  # data=default rolls
    drive = drive_episode(sedan_module, data, DRY, 0, 300)
    vx = np.asarray(drive["states"])[:, 0]
    assert vx[0] == pytest.approx(speeds[0], abs=1e-6)
    # Cruising on near the speed it has: no launch, no braking to a stop within 3 s.
    assert np.all(np.abs(vx - speeds[0]) < 0.25 * speeds[0]) and not drive["spun"]


@pytest.fixture(scope="module")
def stored(
    tmp_path_factory: pytest.TempPathFactory, sedan_module: Sedan
) -> tuple[DataConfig, Path]:
    data = tiny(tmp_path_factory.mktemp("datasets"))
    return data, collect(sedan_module, data, DRY, progress=False)


def test_split_is_disjoint_by_episode_and_reproducible(
    stored, tmp_path: Path, sedan_module: Sedan
) -> None:
    _data, directory = stored
    dataset = load(directory)
    names = [e.name for e in dataset.train + dataset.validation + dataset.test]
    assert len(names) == len(set(names)) == 4
    assert (len(dataset.train), len(dataset.validation), len(dataset.test)) == (2, 1, 1)
    again = load(collect(sedan_module, tiny(tmp_path), DRY, progress=False))
    assert [e.name for e in again.test] == [e.name for e in dataset.test]
    for a, b in zip(again.episodes(), dataset.episodes(), strict=True):
        np.testing.assert_array_equal(a.states, b.states)


def test_normalizer_is_fitted_on_train_only_and_round_trips(stored) -> None:
    _, directory = stored
    dataset = load(directory)
    train_states = np.concatenate([e.states for e in dataset.train])
    np.testing.assert_allclose(dataset.normalizer.state_min, train_states.min(0))
    np.testing.assert_allclose(dataset.normalizer.state_max, train_states.max(0))
    everything = np.concatenate([e.states for e in dataset.episodes()])
    assert not np.allclose(dataset.normalizer.state_max, everything.max(0))  # test differs
    x = dataset.test[0].states
    u = dataset.test[0].inputs
    round_trip = dataset.normalizer.states_inverse(dataset.normalizer.states(x))
    np.testing.assert_allclose(round_trip, x, atol=1e-12)  # a rolling start's vy is ~1e-37
    np.testing.assert_allclose(
        dataset.normalizer.inputs_inverse(dataset.normalizer.inputs(u)), u, atol=1e-12
    )


def test_a_non_finite_value_is_named_by_array_column_and_time_and_no_normalizer_takes_it(
    stored,
) -> None:
    good = load(stored[1]).train[0]
    assert good.non_finite() is None
    cases = [
        ("inputs", (123, 0), "inputs has 1 non-finite value (steer_wheel_deg at t = 1.23 s)"),
        ("states", ([90, 40], 2), "states has 2 non-finite values (first: yaw_rate at t = 0.40 s)"),
        ("time_s", 3, "time_s has 1 non-finite value (row 3)"),
    ]
    for field, where, said in cases:
        values = getattr(good, field).copy()
        values[where] = np.inf if field == "inputs" else np.nan
        bad = dataclasses.replace(good, name="episode_0003", **{field: values})
        assert bad.non_finite() == said
        with pytest.raises(ValueError) as info:
            MinMaxNormalizer.fit([good, bad])
        assert str(info.value) == f"cannot fit a normalizer: episode episode_0003 {said}"


def test_same_config_reuses_and_a_changed_one_does_not(stored, sedan_module: Sedan) -> None:
    data, directory = stored
    before = (directory / "manifest.json").stat().st_mtime_ns
    assert collect(sedan_module, data, DRY, progress=False) == directory
    assert (directory / "manifest.json").stat().st_mtime_ns == before
    dry = sedan_module.fingerprint
    assert content_key(dry, data, DRY) == directory.name
    wet = Sedan(SedanParams(tire=TireParams(road_friction=0.5))).fingerprint
    assert content_key(wet, data, DRY) != directory.name  # another plant
    assert content_key(dry, data, DriverKnowledge(0.5, 16.0)) != directory.name  # driver
    assert content_key(dry, tiny(Path(data.root), seed=1), DRY) != directory.name  # data
    # Where and how fast it is collected does not change the data.
    assert content_key(dry, tiny(Path("/elsewhere"), workers=2), DRY) == directory.name


def test_the_pedal_in_other_units_is_a_dataset_of_its_own_with_the_same_drives(
    stored, sedan_module: Sedan
) -> None:
    data, directory = stored
    # Off (null): the signed scale, and the content key datasets had before the setting.
    assert "pedal_gains" not in data.content() and data.channels == SEDAN_INPUTS
    other = tiny(Path(data.root), pedal_gains=[3.3, 0.83])
    pedal = other.channels[1]
    assert (pedal.name, pedal.role, pedal.gain_positive, pedal.gain_negative) == (
        "pedal",
        "pedal",
        3.3,
        0.83,
    )
    assert content_key(sedan_module.fingerprint, other, DRY) != directory.name
    dataset, today = load(collect(sedan_module, other, DRY, progress=False)), load(directory)
    for episode, same in zip(dataset.episodes(), today.episodes(), strict=True):
        np.testing.assert_array_equal(episode.inputs, same.inputs)  # the plant's units
        assert episode.channels == other.channels
    assert dataset.normalizer.channels == other.channels  # a model file's, with its gains
    assert MinMaxNormalizer.from_dict(dataset.normalizer.to_dict()).channels == other.channels
    pedals = np.array([0.2, 0.05, 0.0, -1.0, -9.1])  # throttle, or brake in -MPa
    np.testing.assert_allclose(pedal.feature(pedals), [0.66, 0.165, 0.0, -0.83, -7.553])
    np.testing.assert_allclose(pedal.value(pedal.feature(pedals)), pedals, atol=1e-15)
    u = np.column_stack([np.linspace(-90.0, 90.0, len(pedals)), pedals])
    normalizer = dataset.normalizer
    np.testing.assert_allclose(normalizer.inputs_inverse(normalizer.inputs(u)), u, atol=1e-12)


def test_the_sedan_is_a_plant_whose_fingerprint_names_what_moves_it(sedan_module: Sedan) -> None:
    fingerprint = sedan_module.fingerprint
    assert isinstance(sedan_module, Plant)
    assert json.loads(json.dumps(fingerprint))["params"]["tire"]["road_friction"] == 0.9
    assert set(fingerprint["sources"]) == {"vehicle_forces.c", "sedan.xml"}
    assert Sedan(SedanParams(name="x")).fingerprint != fingerprint
    # A worker process gets the plant by pickling: rebuilt from its parameters, at rest.
    sedan_module.step((0.0, 0.2))
    copy = pickle.loads(pickle.dumps(sedan_module))
    assert copy.fingerprint == fingerprint
    inputs = [(30.0, 0.2)] * 50
    sedan_module.reset()
    copy.reset()
    np.testing.assert_array_equal(
        [sedan_module.step(u) for u in inputs], [copy.step(u) for u in inputs]
    )


def test_worker_processes_store_the_same_bytes_as_one_in_process_worker(
    stored, tmp_path: Path
) -> None:
    _data, directory = stored
    parallel = collect(Sedan(), tiny(tmp_path, workers=2), DRY, progress=False)
    assert parallel.name == directory.name

    def checksums(path: Path) -> dict[str, str]:
        episodes = json.loads((path / "manifest.json").read_text())["episodes"]
        return {name: entry["sha256"] for name, entry in episodes.items()}

    assert checksums(parallel) == checksums(directory)


def test_a_truncated_episode_is_never_loaded_and_the_next_collection_redrives_it_alone(
    stored, tmp_path: Path, sedan_module: Sedan, caplog: pytest.LogCaptureFixture
) -> None:
    _data, directory = stored
    copy = tmp_path / directory.name
    copy.mkdir()
    for path in directory.iterdir():
        (copy / path.name).write_bytes(path.read_bytes())
    victim = copy / "episode_0001.npz"
    victim.write_bytes(victim.read_bytes()[:-100])
    with pytest.raises(DatasetError, match=r"episode_0001\.npz fails its checksum") as info:
        load(copy)
    assert "\n" not in str(info.value)
    assert "recollect episode_0001 alone" in str(info.value)
    untouched = {
        n: (copy / f"{n}.npz").stat().st_mtime_ns for n in ("episode_0000", "episode_0002")
    }
    assert collect(sedan_module, tiny(tmp_path), DRY, progress=False) == copy
    assert "recollecting episode_0001 alone" in caplog.text
    assert victim.read_bytes() == (directory / victim.name).read_bytes()
    assert {n: (copy / f"{n}.npz").stat().st_mtime_ns for n in untouched} == untouched
    assert (copy / "manifest.json").read_bytes() == (directory / "manifest.json").read_bytes()


def test_interrupted_collection_resumes_without_redoing_finished_episodes(
    stored, tmp_path: Path, sedan_module: Sedan
) -> None:
    _data, directory = stored
    resumed = tiny(tmp_path)
    target = tmp_path / directory.name
    target.mkdir()
    manifest = json.loads((directory / "manifest.json").read_text())
    # The state an interrupted run leaves: two episodes done, the rest missing, not complete.
    kept = ["episode_0000", "episode_0002"]
    manifest["episodes"] = {k: v for k, v in manifest["episodes"].items() if k in kept}
    manifest["complete"] = False
    manifest.pop("split"), manifest.pop("normalizer")
    write_manifest(target, manifest)
    for name in kept:
        (target / f"{name}.npz").write_bytes((directory / f"{name}.npz").read_bytes())
    stamps = {name: (target / f"{name}.npz").stat().st_mtime_ns for name in kept}
    assert collect(sedan_module, resumed, DRY, progress=False) == target
    assert {n: (target / f"{n}.npz").stat().st_mtime_ns for n in kept} == stamps
    original, finished = load(directory), load(target)
    assert finished.manifest["split"] == original.manifest["split"]
    assert (target / "manifest.json").read_bytes() == (directory / "manifest.json").read_bytes()
    for a, b in zip(finished.episodes(), original.episodes(), strict=True):
        np.testing.assert_array_equal(a.inputs, b.inputs)


class ConstantSpeed:
    """A reference at one speed (a toy of the ISO lane change at 22.2 m/s)."""

    def __init__(self, speed: float) -> None:
        self.speed = speed

    def label(self, name: str, episodes: Sequence[Episode]) -> str:
        return f"{name}_{self.speed:g}"

    def build(self, dt: float, episodes: Sequence[Episode]) -> np.ndarray:
        return np.tile([self.speed, 0.0, 0.0], (50, 1))


def test_references_outside_the_training_speeds_are_named(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def drive(name: str, top: float) -> Episode:
        t = np.arange(100) * 0.01
        states = np.stack([np.linspace(0.0, top, 100), 0 * t, 0 * t], axis=1)
        return Episode(name, t, states, np.zeros((100, 2)), np.zeros((100, 3)))

    train, test = [drive("a", 20.7), drive("b", 12.0)], [drive("c", 25.0)]
    dataset = Dataset(Path("."), {}, train, test, test, MinMaxNormalizer.fit(train))
    references = {"slow": ConstantSpeed(15.0), "lane_change": ConstantSpeed(22.2)}
    assert all(isinstance(r, Reference) for r in references.values())
    with caplog.at_level("WARNING"):
        result = reference_speeds(references, 0.01, dataset)
    assert result["training_speed_range_mps"] == [0.0, pytest.approx(20.7)]
    assert result["reference_speed_range_mps"] == {
        "slow_15": [15.0, 15.0],
        "lane_change_22.2": [22.2, 22.2],
    }
    assert result["outside_training_speed"] == ["lane_change_22.2"]
    assert "lane_change_22.2 runs at 22.2 to 22.2 m/s, outside" in caplog.text
    assert "slow_15" not in caplog.text


def test_the_coverage_figure_of_logs_without_poses_shows_speed_and_accelerations() -> None:
    """No poses, no path to draw: the panel shows how fast and how hard the car was driven."""
    rng = np.random.default_rng(0)
    steps = 300
    states = np.column_stack([np.linspace(5, 25, steps), rng.normal(0, 0.2, (steps, 2))])
    channels = (InputChannel("delta", role="road_wheel", unit="rad"), InputChannel("torque"))
    inputs = rng.normal(0, 1, (steps, 2))
    episode = Episode(
        "lap", np.arange(steps) * 0.01, states, inputs, np.zeros((steps, 3)), channels
    )
    titles = [ax.get_title() for ax in coverage.figure({"train": [episode]}, None).axes]
    assert "1 episodes (no poses): speed" in titles and "accelerations (log count)" in titles
    assert not any("(paths)" in title for title in titles)
    with_poses = dataclasses.replace(episode, poses=rng.normal(0, 10, (steps, 3)))
    titles = [ax.get_title() for ax in coverage.figure({"train": [with_poses]}, None).axes]
    assert "1 episodes (paths)" in titles
