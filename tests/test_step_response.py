"""Step responses from straight driving: the plant's facts, and the model compared row by row."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest

from harness.core.contracts import STATE_NAMES
from harness.evaluation import step_response
from harness.evaluation.step_response import DEFAULT_CASES, StepCase, respond
from harness.output import load_arrays
from harness.plant import Sedan
from harness.recorder import Recorder
from harness.report.jobs import Run
from harness.report.tables import prediction_table, spectrum_table, step_response_table

CASES = (
    StepCase(10.0, "steer_wheel_deg", 20.0, "yaw_rate"),
    StepCase(10.0, "steer_wheel_deg", -20.0, "yaw_rate"),
    StepCase(10.0, "pedal", 0.1, "vx"),
)


@pytest.fixture(scope="module")
def plant() -> Sedan:
    return Sedan()


class Oracle:
    """Predicts by replaying the plant's own run of the case that starts at x0."""

    def __init__(self, plant: Sedan) -> None:
        self.runs = [respond(plant, case) for case in CASES]

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        for run in self.runs:
            if not np.array_equal(run.states[run.first], x0):
                continue
            if np.array_equal(run.inputs[run.first : -1], inputs):
                return run.states[run.first :]
            if np.all(inputs == run.inputs[run.first - 1]):  # held: the settled plant stays
                return np.repeat(x0[None], len(inputs) + 1, 0)
        raise AssertionError("no plant run starts at this state under these inputs")


class Mirrored(Oracle):
    """The plant's response the wrong way round: an input gain of the wrong sign."""

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        return 2 * x0 - super().predict(x0, inputs)


class Holding:
    """Predicts that nothing changes: the response is zero."""

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        return np.repeat(x0[None], len(inputs) + 1, 0)


class Diverging:
    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        out = np.repeat(x0[None], len(inputs) + 1, 0)
        out[5:] = np.inf
        return out


class Rollouts(Recorder):
    def __init__(self) -> None:
        super().__init__()
        self.logged: dict[str, Mapping[str, np.ndarray]] = {}

    def rollout(self, name, time_s, states, inputs, poses=None, overlays=None, **kwargs) -> None:  # type: ignore[override]
        assert len(time_s) == len(states) == len(inputs) == len(poses)
        self.logged[name] = dict(overlays or {})


def test_the_plant_answers_a_steering_step_from_straight_driving_as_a_car(plant: Sedan) -> None:
    """Held speed before the step; yaw rate in the step's direction, equal and opposite for
    opposite steps, below the kinematic rate v * delta / L; a throttle step speeds the car up."""
    left, right, throttle = (respond(plant, case) for case in CASES)
    assert left.first == right.first == 50  # 0.5 s of straight driving shown before the step
    before = left.states[: left.first + 1]
    assert np.all(np.abs(before[:, 0] - 10.0) < 0.1) and np.all(np.abs(before[:, 2]) < 1e-6)
    settled = left.states[-1, 2]
    assert settled > 0.02 and right.states[-1, 2] == pytest.approx(-settled, rel=1e-3)
    kinematic = 10.0 * np.deg2rad(20.0 / 16.0) / 2.7  # steering ratio 16, wheelbase 2.7 m
    assert settled < kinematic
    assert throttle.states[-1, 0] > throttle.states[throttle.first, 0] + 0.3
    np.testing.assert_array_equal(left.inputs[: left.first, 0], 0.0)
    np.testing.assert_array_equal(left.inputs[left.first :, 0], 20.0)
    assert np.all(throttle.inputs[throttle.first :, 1] == throttle.hold_pedal + 0.1)


def test_a_model_equal_to_the_plant_has_zero_error_and_a_still_one_minus_one(
    plant: Sedan, tmp_path: Path
) -> None:
    """The comparison reads the model's row k against the plant's row (step + k): an oracle
    scores 0 exactly, a model predicting no change scores -1, a diverged one inf."""
    recorder = Rollouts()
    models = {"oracle": Oracle(plant), "holding": Holding(), "diverging": Diverging()}
    results = step_response.evaluate(
        models,  # type: ignore[arg-type]
        plant,
        CASES,
        recorder=recorder,
        output_dir=tmp_path,
    )
    assert list(results["oracle"]) == [
        "steer+20deg_10mps",
        "steer-20deg_10mps",
        "throttle+0.1_10mps",
    ]
    for case, metrics in results["oracle"].items():
        for at in ("at_300ms", "at_1500ms"):
            assert metrics[at]["relative_error"] == 0.0, case
            assert metrics[at]["model"] == metrics[at]["plant"]
            assert results["holding"][case][at]["relative_error"] == pytest.approx(-1.0)
            assert results["diverging"][case][at]["relative_error"] == np.inf
    steer = results["oracle"]["steer+20deg_10mps"]
    assert steer["output"] == "yaw_rate" and steer["at_1500ms"]["plant"] > 0.02
    assert results["oracle"]["throttle+0.1_10mps"]["output"] == "vx"
    assert (tmp_path / "step_response.png").stat().st_size > 10_000
    arrays = load_arrays(tmp_path / "step_response.npz")
    np.testing.assert_array_equal(
        arrays["steer+20deg_10mps__predicted_oracle"][0],
        arrays["steer+20deg_10mps__states"][50],
    )
    assert set(recorder.logged) == {f"step_response/{name}" for name in results["oracle"]}
    logged = recorder.logged["step_response/steer+20deg_10mps"]["predicted_holding"]
    assert np.all(np.isnan(logged[:50])) and np.all(np.isfinite(logged[50:]))


def test_the_default_cases_are_the_issues_steps_at_10_and_22_mps() -> None:
    names = [case.name for case in DEFAULT_CASES]
    assert names == [
        f"{step}_{speed}mps"
        for speed in (10, 22)
        for step in ("steer+20deg", "steer-20deg", "steer+60deg", "throttle+0.1")
    ]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"input_name": "brake"}, "step input must be one of"),
        ({"output": "yaw"}, "step output must be one of"),
        ({"speed_mps": 0.0}, "step speed must be > 0"),
    ],
)
def test_a_wrong_case_is_refused(kwargs: dict, message: str) -> None:
    values = {"speed_mps": 10.0, "input_name": "pedal", "step": 0.1, "output": "vx", **kwargs}
    with pytest.raises(ValueError, match=message):
        StepCase(**values)


def test_the_report_has_a_row_per_learner_and_case_and_leaves_the_steps_out_of_prediction() -> None:
    def metrics(error: float | None, modes: int) -> dict:
        case = {
            "output": "yaw_rate",
            "at_300ms": {"plant": 0.1, "model": 0.05, "relative_error": error},
        }
        mode = {"matrix": "A", "abs": 1.001, "doubling_time_s": 6.9, "dominant": "vx"}
        return {
            "prediction": {
                "episode_0000": {"rmse": {"vx": 1.0, "vy": 0.1, "yaw_rate": 0.1}},
                "step_response": {"steer+20deg_22mps": case},
            },
            "spectrum": {"max_abs_eigenvalue": 1.001, "unstable_modes": [mode] * modes},
        }

    jobs = [
        Run(Path(f"edmd-{seed}"), choices={"learner": "edmd"}, seed=seed, metrics=metrics(e, n))
        for seed, e, n in ((0, -0.5, 1), (1, None, 3))  # seed 1 diverged in the step
    ]
    (row,) = step_response_table(jobs).rows
    assert row[:4] == ["edmd", "—", "steer+20deg_22mps", "2"]
    assert row[4:7] == ["0.1 ± 0", "0.05 ± 0", "-0.5"]  # the diverged job adds no error
    assert row[7:] == ["—", "—", "—"]  # no job reported 1.5 s
    table = spectrum_table(jobs)
    assert all("|" not in cell for cell in [*table.columns, *table.rows[0]])  # Markdown-safe
    (spectral,) = table.rows
    assert spectral[:5] == ["edmd", "—", "2", "1.001 ± 0", "2 ± 1.4"]
    assert spectral[5] == "abs λ 1.001000, doubles in 6.9 s, vx at A"
    (episode,) = prediction_table(jobs).rows
    assert episode[3] == "episode_0000"


def test_the_input_effect_is_the_step_minus_the_held_prediction_and_its_sign_is_checked(
    plant: Sedan,
) -> None:
    """The oracle's input effect is the plant's whole response (the settled plant does not
    drift), with the plant's sign; a model that responds the wrong way, or not at all, does not
    agree in sign."""
    oracle, mirrored = Oracle(plant), Mirrored(plant)
    models = {"oracle": oracle, "mirrored": mirrored, "holding": Holding()}
    results = step_response.evaluate(models, plant, CASES)  # type: ignore[arg-type]
    for case, metrics in results["oracle"].items():
        run = next(r for r in oracle.runs if r.case.name == case)
        column = STATE_NAMES.index(metrics["output"])
        for at, row in (("at_300ms", 30), ("at_1500ms", 150)):
            change = run.states[run.first + row, column] - run.states[run.first, column]
            assert metrics[at]["model_input_effect"] == pytest.approx(change, abs=1e-12)
            assert results["mirrored"][case][at]["model_input_effect"] == pytest.approx(-change)
        assert metrics["input_sign_agrees"]
        assert not results["mirrored"][case]["input_sign_agrees"]
        assert not results["holding"][case]["input_sign_agrees"]
