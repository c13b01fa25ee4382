"""Tracking: references are the states a path needs; a run reports, records and plots itself."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from controllers import DEMPC, DEMPCConfig
from harness.core.contracts import StepInfo
from harness.core.episode import Episode
from harness.evaluation import tracking
from harness.evaluation.tracking import TrackingTrajectory, predicted_path, track
from harness.recorder import Recorder, RerunRecorder
from harness.references import (
    BicycleParams,
    double_lane_change,
    double_lane_change_path,
    from_episode,
    lane_offset_m,
)
from harness.references.iso3888 import MIN_SPEED_MPS
from tests.toy_models import ModelPlant, feasible_reference
from tests.toy_models import toy_linear_model as linear_model

G = 9.81


def integrate_path(states: np.ndarray, dt: float = 0.01) -> np.ndarray:
    """World (X, Y) of the CG from (vx, vy, r): what a car driving these states covers."""
    vx, vy, r = states.T
    yaw = np.concatenate([[0.0], np.cumsum(r[:-1]) * dt])
    return (
        np.cumsum(
            np.stack([vx * np.cos(yaw) - vy * np.sin(yaw), vx * np.sin(yaw) + vy * np.cos(yaw)], 1),
            axis=0,
        )
        * dt
    )


def test_iso_3888_1_at_80_kph_is_driven_at_constant_speed_and_returns_to_its_lane() -> None:
    speed = 80 / 3.6
    states = double_lane_change(speed, "iso3888_1", sideslip=False)
    np.testing.assert_allclose(states[:, 0], speed)
    assert np.all(states[:, 1] == 0.0)
    path = integrate_path(states)
    _, y = double_lane_change_path("iso3888_1")
    assert path[:, 1].max() == pytest.approx(3.5, abs=0.05) == y.max()
    assert abs(path[-1, 1]) < 0.05 and abs(np.sum(states[:, 2]) * 0.01) < 1e-3  # heading back
    lateral_accel = np.abs(states[:, 0] * states[:, 2])
    assert 0.3 * G < lateral_accel.max() < 0.6 * G  # a real manoeuvre, inside the tyres' grip


def test_iso_3888_2_geometry_and_its_demand() -> None:
    assert lane_offset_m("iso3888_2", vehicle_width_m=1.8) == pytest.approx(3.515)
    slow = double_lane_change(45 / 3.6, "iso3888_2")
    fast = double_lane_change(80 / 3.6, "iso3888_2")
    assert np.abs(slow[:, 0] * slow[:, 2]).max() < 0.8 * G < np.abs(fast[:, 0] * fast[:, 2]).max()


def test_sideslip_follows_the_bicycle_models_steady_state() -> None:
    states = double_lane_change()
    gain = BicycleParams().vy_per_yaw_rate_m(80 / 3.6)
    assert -1.6 < gain < -1.0  # the body points inside the turn at 80 km/h
    np.testing.assert_allclose(states[:, 1], gain * states[:, 2])


def test_an_unknown_standard_or_speed_is_refused() -> None:
    with pytest.raises(ValueError, match="standard"):
        double_lane_change(20.0, "iso9999")
    with pytest.raises(ValueError, match="speed_mps"):
        double_lane_change(0.0)
    with pytest.raises(ValueError, match=r"speed_mps must be >= 1 m/s \(got 0.5\)"):
        double_lane_change(0.5)  # its run grows as 1 / speed: refused before it is built


def test_the_slowest_lane_change_allowed_is_as_long_as_a_paper_scale_test_drive() -> None:
    states = double_lane_change(MIN_SPEED_MPS)
    assert 15_000 < len(states) <= 40_000  # conf/data/paper.yaml: drives of 10k-40k steps


def test_a_reference_from_an_episode_is_its_recorded_states() -> None:
    states = np.random.default_rng(0).normal(size=(50, 3))
    episode = Episode("test_0", np.arange(50) * 0.01, states, np.zeros((50, 2)), np.zeros((50, 3)))
    reference = from_episode(episode)
    np.testing.assert_array_equal(reference, states)
    assert reference is not episode.states


class ListeningRecorder(Recorder):
    """Keeps what it is given, so a test can see what a run logs."""

    def __init__(self) -> None:
        super().__init__()
        self.rollouts: dict[str, dict] = {}
        self.series_calls: list[tuple[str, np.ndarray, dict]] = []

    def rollout(
        self,
        name,
        time_s,
        states,
        inputs,
        poses=None,
        extra=None,
        reference=None,
        overlays=None,
        **_,
    ) -> None:
        self.rollouts[name] = {
            "time_s": time_s,
            "states": states,
            "extra": extra or {},
            "reference": reference,
            "overlays": overlays or {},
        }

    def series(self, path, time_s, values, timeline="sim_time") -> None:
        self.series_calls.append((path, time_s, values))


def test_a_tracking_run_reports_records_and_plots(tmp_path: Path, monkeypatch) -> None:
    model = linear_model()
    reference = feasible_reference(model, steps=300)
    recorder = ListeningRecorder()
    figures: list[Figure] = []
    save_figure = tracking.save_figure

    def keep_figure(fig: Figure, path: Path) -> Path:
        figures.append(fig)
        return save_figure(fig, path)

    monkeypatch.setattr(tracking, "save_figure", keep_figure)
    metrics, run = track(
        ModelPlant(model, x0=reference[0]),
        DEMPC(model, DEMPCConfig(Np=10, Nc=7)),
        reference,
        name="dlc",
        recorder=recorder,
        figure_path=tmp_path / "tracking.png",
    )
    assert set(metrics["rmse"]) == {"vx", "vy", "yaw_rate"}
    assert set(metrics["solve_time_ms"]) == {"median", "p99", "max"}
    assert metrics["deadline_misses"] == 0 and metrics["solver_failures"] == 0
    assert sum(metrics["solve_paths"].values()) == metrics["steps"] == 299
    assert metrics["horizon"] == {"Np": 10, "Nc": 7}
    assert run.states.shape == reference.shape and run.predicted.shape == (300, 10, 3)
    # The rollout with its reference (each state's plot: reference, actual and the prediction
    # Np steps ahead, drawn at the time it predicts), then the whole horizon as columns.
    logged = recorder.rollouts["dlc"]
    assert logged["states"].shape == (300, 3)
    np.testing.assert_array_equal(logged["reference"], reference)
    # Beside the inputs, the quality panel: the steering-wheel rate and both jerks.
    assert set(logged["extra"]) == {"solve_time_ms", "steering_wheel_rate_deg_s", "jerk_mps3"}
    np.testing.assert_allclose(
        logged["extra"]["steering_wheel_rate_deg_s"][1:], np.diff(run.inputs[:, 0]) / 0.01
    )
    assert set(logged["extra"]["jerk_mps3"]) == {"longitudinal", "lateral"}
    # The prediction's legend says what it is: the model's, made one horizon (0.10 s) earlier.
    ahead = logged["overlays"]["model's prediction from 0.10 s before"]
    assert np.all(np.isnan(ahead[:10]))
    np.testing.assert_array_equal(ahead[10:], run.predicted[:-10, -1])
    horizon = next(v for p, _, v in recorder.series_calls if p == "dlc/horizon/vy")["ahead"]
    assert horizon.shape == (300, 10)
    # The figure: vx, vy, r each with the reference and the run, then the two inputs.
    (figure,) = figures
    axes = figure.axes
    assert len(axes) == 5
    for i in range(3):
        reference_line, actual = axes[i].get_lines()
        np.testing.assert_array_equal(reference_line.get_ydata(), reference[:, i])
        np.testing.assert_array_equal(actual.get_ydata(), run.states[:, i])
        np.testing.assert_array_equal(actual.get_xdata(), run.time_s)
    for j in range(2):
        (applied,) = axes[3 + j].get_lines()
        np.testing.assert_array_equal(applied.get_ydata(), run.inputs[:, j])
    assert [t.get_text() for t in axes[0].get_legend().get_texts()] == ["reference", "dlc"]
    assert (tmp_path / "tracking.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


class Clock:
    """A clock the controller below moves: time.perf_counter for the tracking loop."""

    now = 0.0

    def __call__(self) -> float:
        return self.now


class TimedController:
    """Holds its input; each step prepares for 4 ms, computes the input in 1 ms, says when it
    was ready, then keeps books for 2 ms."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock

    def reset(self, reference: np.ndarray, *, path=None, u_prev=None) -> None:
        pass

    def prepare(self) -> None:
        self.clock.now += 0.004

    def act(self, x: np.ndarray, t: float, *, pose=None):
        self.clock.now += 0.001
        ready = self.clock.now
        self.clock.now += 0.002
        return np.zeros(2), StepInfo(input_ready_s=ready)


def test_the_latency_ends_when_the_input_is_ready_and_the_rest_counts_in_the_period(
    monkeypatch,
) -> None:
    """solve_time_ms is measurement to input (1 ms); the preparation and the bookkeeping after
    the input (4 + 2 ms) are the step's other work, and all of it (7 ms) must fit the period."""
    clock = Clock()
    monkeypatch.setattr(tracking.time, "perf_counter", clock)
    model = linear_model()
    reference = feasible_reference(model, steps=50)
    plant = ModelPlant(model, x0=reference[0])
    metrics, _ = track(plant, TimedController(clock), reference, name="t", recorder=Recorder())
    for key, expected_ms in (
        ("solve_time_ms", 1.0),
        ("prepare_time_ms", 6.0),
        ("step_time_ms", 7.0),
    ):
        for statistic in ("median", "p99", "max"):
            assert metrics[key][statistic] == pytest.approx(expected_ms, abs=1e-6)
    assert metrics["deadline_misses"] == 0
    plant.dt = 0.005  # the same work no longer fits a 5 ms period: every step misses it
    metrics, _ = track(plant, TimedController(clock), reference, name="t", recorder=Recorder())
    assert metrics["deadline_misses"] == metrics["steps"] == 49


def test_de_mpc_says_when_its_input_was_ready_within_its_act() -> None:
    model = linear_model()
    reference = feasible_reference(model, steps=30)
    controller = DEMPC(model, DEMPCConfig(Np=10, Nc=7))
    controller.reset(reference)
    before = time.perf_counter()
    _, info = controller.act(reference[0], 0.0)
    after = time.perf_counter()
    assert info.input_ready_s is not None and before < info.input_ready_s < after


def test_a_run_writes_a_rerun_recording(tmp_path: Path) -> None:
    model = linear_model()
    reference = feasible_reference(model, steps=100)
    with RerunRecorder(tmp_path / "track.rrd") as recorder:
        track(
            ModelPlant(model, x0=reference[0]),
            DEMPC(model, DEMPCConfig()),
            reference,
            name="short",
            recorder=recorder,
        )
    assert (tmp_path / "track.rrd").stat().st_size > 0


def test_a_malformed_reference_is_refused() -> None:
    model = linear_model()
    with pytest.raises(ValueError, match="reference"):
        track(
            ModelPlant(model),
            DEMPC(model, DEMPCConfig()),
            np.zeros((10, 2)),
            name="x",
            recorder=Recorder(),
        )


def test_the_predicted_path_integrates_the_predicted_states_from_the_pose() -> None:
    """Driving at 10 m/s heading +Y, the path ahead is a straight line 0.1 m a step; a yaw rate
    turns it the way the car turns."""
    steps, horizon, dt = 3, 5, 0.01
    states = np.tile([10.0, 0.0, 0.0], (steps, 1))
    poses = np.tile([1.0, 2.0, np.pi / 2], (steps, 1))
    predicted = np.tile(states[:, None, :], (1, horizon, 1))
    run = TrackingTrajectory(
        np.arange(steps) * dt, states, np.zeros((steps, 2)), poses, states, predicted
    )
    path = predicted_path(run, dt)
    assert path.shape == (steps, horizon + 1, 2)
    np.testing.assert_allclose(path[0, :, 0], 1.0, atol=1e-12)
    np.testing.assert_allclose(path[0, :, 1], 2.0 + 0.1 * np.arange(horizon + 1))
    run.predicted[..., 2] = 1.0  # turning left (counter-clockwise) at 1 rad/s
    # the first step moves with the measured state (no yaw rate), then the path bends to -X
    assert np.all(np.diff(predicted_path(run, dt)[0, 1:, 0])[1:] < 0)
