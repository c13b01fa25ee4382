"""The one closed-loop rollout loop (harness/rollout.closed_loop) and its options, on a toy."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from harness.core.contracts import Plant, StepInfo
from harness.plant.rollout import NO_INFO, closed_loop, simulate


class Integrator:
    """x⁺ = x + (u0, u1, 0): every state is the sum of the inputs before it, easy to check."""

    dt = 0.5

    def __init__(self) -> None:
        self.x = np.zeros(3)
        self.resets: list[tuple[int | None, float]] = []

    def reset(self, seed: int | None = None, speed_mps: float = 0.0) -> np.ndarray:
        self.resets.append((seed, speed_mps))
        self.x = np.array([speed_mps, 0.0, 0.0])
        return self.x.copy()

    def step(self, u: np.ndarray) -> np.ndarray:
        self.x = self.x + np.array([u[0], u[1], 0.0])
        return self.x.copy()

    @property
    def pose(self) -> np.ndarray:
        return np.array([self.x[0], 0.0, 0.0])

    @property
    def fingerprint(self) -> dict[str, Any]:
        return {"plant": "integrator"}


class Counting:
    """A policy that answers (k, -k) at frame k and remembers how often it was asked."""

    def __init__(self) -> None:
        self.calls: list[float] = []

    def __call__(self, x: np.ndarray, t: float) -> tuple[np.ndarray, StepInfo]:
        self.calls.append(t)
        k = round(t / Integrator.dt)
        info = StepInfo(predicted_states=np.full((4, 3), float(k)), solve_path=f"p{k}")
        return np.array([k, -k], dtype=float), info


def test_the_integrator_is_a_plant() -> None:
    assert isinstance(Integrator(), Plant)


def test_the_last_frame_repeats_the_previous_input_unless_the_policy_acts_there() -> None:
    plant, policy = Integrator(), Counting()
    run = closed_loop(plant, policy, 5, seed=7, speed_mps=2.0)
    assert plant.resets == [(7, 2.0)]
    assert len(policy.calls) == 4 and run.acted == 4 and not run.stopped
    np.testing.assert_array_equal(run.time_s, [0.0, 0.5, 1.0, 1.5, 2.0])
    np.testing.assert_array_equal(run.inputs[:, 0], [0, 1, 2, 3, 3])
    np.testing.assert_array_equal(run.states[:, 0], [2, 2, 3, 5, 8])  # 2 + 0 + 1 + 2 + 3
    np.testing.assert_array_equal(run.poses[:, 0], run.states[:, 0])

    policy = Counting()
    run = closed_loop(Integrator(), policy, 5, act_on_last=True)
    assert len(policy.calls) == 5 and run.acted == 5
    np.testing.assert_array_equal(run.inputs[:, 0], [0, 1, 2, 3, 4])


def test_a_stop_keeps_or_drops_the_frame_where_it_fired() -> None:
    def past_three(t: float, x: np.ndarray) -> bool:
        return x[0] >= 3.0  # states 0, 0, 1, 3, 6, ...: fires at frame 3

    kept = closed_loop(Integrator(), Counting(), 10, stop=past_three)
    assert kept.stopped and len(kept.time_s) == 4 and kept.acted == 3
    np.testing.assert_array_equal(kept.states[:, 0], [0, 0, 1, 3])
    np.testing.assert_array_equal(kept.inputs[:, 0], [0, 1, 2, 2])  # the last input repeated

    dropped = closed_loop(
        Integrator(), Counting(), 10, stop=past_three, keep_stop_frame=False, act_on_last=True
    )
    assert dropped.stopped and len(dropped.time_s) == 3 and dropped.acted == 3
    np.testing.assert_array_equal(dropped.inputs[:, 0], [0, 1, 2])  # the inputs applied there

    never = closed_loop(Integrator(), Counting(), 2, stop=lambda t, x: True)
    assert not never.stopped and len(never.time_s) == 2  # checked from frame 2 on


def test_solve_times_and_horizons_are_kept_on_request() -> None:
    plain = closed_loop(Integrator(), Counting(), 4)
    assert plain.infos == [] and np.all(np.isnan(plain.solve_time_s))
    with pytest.raises(ValueError, match="keep_infos"):
        plain.predicted()

    run = closed_loop(Integrator(), Counting(), 4, timed=True, keep_infos=True)
    assert [info.solve_path for info in run.infos] == ["p0", "p1", "p2"]
    assert np.all(run.solve_time_s[:3] >= 0) and np.isnan(run.solve_time_s[3])
    predicted = run.predicted()
    assert predicted.shape == (4, 4, 3)
    np.testing.assert_array_equal(predicted[:3, 0, 0], [0, 1, 2])
    assert np.all(np.isnan(predicted[3]))


def test_simulate_keeps_the_state_after_the_last_step_and_a_blow_up_is_an_error() -> None:
    run = simulate(Integrator(), lambda t, x: (1.0, 0.0), 2.0)
    assert len(run.time_s) == 5 and run.states[-1, 0] == 4.0

    def blow_up(x: np.ndarray, t: float) -> tuple[tuple[float, float], StepInfo]:
        return (np.inf if t >= 1.0 else 0.0, 0.0), NO_INFO

    with pytest.raises(RuntimeError, match=r"non-finite at t = 1\.00 s"):
        closed_loop(Integrator(), blow_up, 10)
    with pytest.raises(ValueError, match="at least 2 frames"):
        closed_loop(Integrator(), blow_up, 1)
