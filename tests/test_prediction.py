"""The prediction experiments: RMSE definitions against hand computation, figures, recordings."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from harness.core.episode import Episode, InputChannel, MinMaxNormalizer
from harness.evaluation.prediction import (
    ENVELOPE_SPANS,
    _figure,
    beats_persistence,
    by_episode,
    envelope_exit,
    evaluate,
    input_groups,
    plot_prediction,
    robustness,
    window_name,
    windowed,
)
from harness.recorder import Recorder
from learners import DNN, EDMD, Learner, ThinPlateRBF
from tests.helpers import synthetic_episodes
from tests.toydata import drive_episodes

A_TRUE = np.array([[0.98, 0.05, 0.0], [-0.05, 0.95, 0.0], [0.0, 0.02, 0.9]])
B_TRUE = np.array([[0.01, 0.0], [0.0, 0.02], [0.01, -0.01]])


def linear_episode(name: str, steps: int, seed: int) -> Episode:
    """A linear system in the normalized coordinates of a 0..1 normalizer (physical = normalized
    for the states; inputs mapped back exactly), sampled at 10 ms."""
    (episode,) = synthetic_episodes(
        lambda z, v: A_TRUE @ z + B_TRUE @ v, NORMALIZER, count=1, steps=steps, seed=seed
    )
    return dataclasses.replace(episode, name=name)


NORMALIZER = MinMaxNormalizer(
    np.zeros(3), np.ones(3), np.array([-450.0, -1.0]), np.array([450.0, 1.0])
)


class Hold(Learner):
    """The initial state held: the 'no model' baseline, with an RMSE easy to compute by hand."""

    name = "hold"

    def fit(self, train, validation, normalizer):
        return self

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        return np.repeat(np.asarray(x0)[..., None, :], inputs.shape[-2] + 1, axis=-2)

    def _state(self) -> dict:
        return {}

    def _state_shapes(self, n: int, m: int) -> dict:
        return {}

    def _set_state(self, state) -> None:
        pass


class NoisyHold(Hold):
    """Hold plus a constant offset drawn per row from the random-layer seed (for robustness)."""

    name = "noisy_hold"

    @property
    def redraws_random_layer(self) -> bool:
        return True

    def predict(self, x0, inputs, *, random_layer_seed: int | None = None) -> np.ndarray:
        out = super().predict(x0, inputs)
        if random_layer_seed is not None:
            rng = np.random.default_rng(random_layer_seed)
            out = out + rng.normal(0, 1, (*out.shape[:-2], 1, 3))
        return out


def test_a_perfect_model_has_zero_rmse_in_every_metric() -> None:
    episodes = [linear_episode("train", 600, 0)]
    test = linear_episode("test", 1234, 1)
    exact = EDMD(ThinPlateRBF(0), include_constant=False, ridge=0.0).fit(episodes, [], NORMALIZER)
    results = evaluate({"exact": exact}, [test], window_steps=41, window_seconds=5.0)
    metrics = results["exact"]["test"]
    assert set(metrics) == {"diverged", "diverged_at_s", "rmse", "rmse_window_41", "rmse_window_5s"}
    assert metrics.pop("diverged") is False
    assert metrics.pop("diverged_at_s") is None
    for values in metrics.values():
        assert set(values) == {"vx", "vy", "yaw_rate"}
        assert max(values.values()) < 1e-9


def test_a_constant_offset_is_the_rmse_of_every_metric() -> None:
    """An exact model shifted by c per state errs by exactly |c| at every predicted row."""
    offset = np.array([0.3, -0.02, 0.005])

    class Shifted(Hold):
        def __init__(self, model: Learner) -> None:
            self.model = model

        def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
            out = self.model.predict(x0, inputs)
            out[..., 1:, :] += offset  # the first row is the measured start, as every model's
            return out

    exact = EDMD(ThinPlateRBF(0), include_constant=False, ridge=0.0)
    exact.fit([linear_episode("train", 600, 0)], [], NORMALIZER)
    test = linear_episode("test", 500, 1)
    metrics = evaluate({"shifted": Shifted(exact)}, [test], window_steps=41, window_seconds=1.0)
    assert metrics["shifted"]["test"].pop("diverged") is False
    assert metrics["shifted"]["test"].pop("diverged_at_s") is None
    for values in metrics["shifted"]["test"].values():
        np.testing.assert_allclose(list(values.values()), np.abs(offset), rtol=1e-6)


def test_rmses_of_holding_the_start_match_hand_computation() -> None:
    episode = drive_episodes(1, 12.0, first_seed=3)[0]  # 1201 samples
    x = episode.states
    results = evaluate({"hold": Hold()}, [episode], window_steps=41, window_seconds=10.0)
    metrics = results["hold"][episode.name]
    whole = np.sqrt(np.mean((x[1:] - x[0]) ** 2, axis=0))
    np.testing.assert_allclose(list(metrics["rmse"].values()), whole, rtol=1e-12)
    for key, w in (("rmse_window_41", 41), ("rmse_window_10s", 1000)):
        errors = [x[k] - x[(k // w) * w] for k in range(1, len(x)) if k % w]
        expected = np.sqrt(np.mean(np.square(errors), axis=0))
        np.testing.assert_allclose(list(metrics[key].values()), expected, rtol=1e-12)


def test_windows_restart_from_the_measured_state_and_cover_the_whole_episode() -> None:
    episode = linear_episode("e", 100, 2)
    predicted, rows = windowed(Hold(), episode, 30)
    np.testing.assert_array_equal(predicted[[0, 30, 60, 90]], episode.states[[0, 30, 60, 90]])
    np.testing.assert_array_equal(predicted[91:], np.repeat(episode.states[90:91], 9, 0))
    assert set(rows) == set(range(100)) - {0, 30, 60, 90}
    longer, rows = windowed(Hold(), episode, 500)  # one window, the whole episode
    np.testing.assert_array_equal(longer, np.repeat(episode.states[:1], 100, 0))
    assert list(rows) == list(range(1, 100))


def test_evaluate_draws_the_paper_figure_and_records_truth_with_predictions(
    tmp_path: Path,
) -> None:
    rollouts: list[dict[str, Any]] = []

    class Capture(Recorder):
        def rollout(self, name, time_s, states, inputs, poses=None, overlays=None, **kwargs):
            rollouts.append({"name": name, "states": states, "overlays": overlays})

    episodes = [linear_episode("a", 300, 3), linear_episode("b", 200, 4)]
    results = evaluate(
        {"hold": Hold(), "hold_too": Hold()}, episodes, recorder=Capture(), output_dir=tmp_path
    )
    assert set(results) == {"hold", "hold_too"} and set(results["hold"]) == {"a", "b"}
    assert set(by_episode(results)) == {"a", "b"}
    assert by_episode(results)["b"]["hold_too"] == results["hold_too"]["b"]
    assert [r["name"] for r in rollouts] == ["prediction/a", "prediction/b"]
    # Drawn on each state's plot beside the measured drive, one named line per learner.
    assert set(rollouts[0]["overlays"]) == {"predicted_hold", "predicted_hold_too"}
    assert rollouts[1]["overlays"]["predicted_hold"].shape == (200, 3)
    for name in ("a", "b"):
        assert (tmp_path / f"prediction_{name}.png").stat().st_size > 20_000


def test_a_diverging_model_reports_inf_not_nan_and_says_which_diverged_where(
    caplog: pytest.LogCaptureFixture,
) -> None:
    class Diverges(Hold):
        def predict(self, x0, inputs):
            out = super().predict(x0, inputs).astype(float)
            out[..., 5:, :] = np.nan
            return out

    episode = linear_episode("e", 50, 5)
    metrics = evaluate({"bad": Diverges()}, [episode])["bad"]["e"]
    assert metrics["rmse"] == {"vx": np.inf, "vy": np.inf, "yaw_rate": np.inf}
    assert metrics["diverged"] is True
    assert metrics["diverged_at_s"] == pytest.approx(episode.time_s[5])
    # Until then it held its start: the RMSE of rows 1..4 against the measured drive.
    until = np.sqrt(np.mean((episode.states[1:5] - episode.states[0]) ** 2, axis=0))
    np.testing.assert_allclose(list(metrics["rmse_until_diverged"].values()), until, rtol=1e-12)
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warning.startswith(
        "prediction: bad's open-loop prediction of e is not finite from t = 0.05 s on: it diverged"
    )


def test_robustness_summarizes_repeated_predictions(tmp_path: Path) -> None:
    episode = linear_episode("e", 120, 6)
    results = robustness(NoisyHold(), [episode], repeats=60, output_dir=tmp_path)
    summary = results["noisy_hold"]["e"]
    # repeat r = row r % 25 of the batch seeded 25 * (r // 25): recompute every RMSE by hand
    held = np.repeat(episode.states[:1], 120, 0)
    errors = []
    for first in (0, 25, 50):
        rows = min(25, 60 - first)
        offsets = np.random.default_rng(first).normal(0, 1, (rows, 1, 3))
        for r in range(rows):
            pred = held + offsets[r]
            errors.append(np.sqrt(np.mean((pred[1:] - episode.states[1:]) ** 2, axis=0)))
    errors = np.array(errors)
    np.testing.assert_allclose(list(summary["rmse_mean"].values()), errors.mean(0), rtol=1e-12)
    np.testing.assert_allclose(list(summary["rmse_std"].values()), errors.std(0), rtol=1e-12)
    np.testing.assert_allclose(list(summary["rmse_max"].values()), errors.max(0), rtol=1e-12)
    nominal = np.sqrt(np.mean((held[1:] - episode.states[1:]) ** 2, axis=0))
    np.testing.assert_allclose(list(summary["rmse_nominal"].values()), nominal, rtol=1e-12)
    assert (tmp_path / "robustness_e.png").stat().st_size > 20_000


def test_robustness_of_a_trained_dnn_spreads_and_refuses_models_without_the_layer() -> None:
    episodes = drive_episodes(3, 20.0, first_seed=20)
    normalizer = MinMaxNormalizer.fit(episodes[:2])
    dnn = DNN(
        hidden=[16, 16],
        horizon=8,
        random_layer={"enabled": True, "std": 0.3},
        training={"max_steps": 30, "batch_size": 16, "progress": False},
    )
    dnn.fit(episodes[:2], [], normalizer)
    summary = robustness({"dnn": dnn}, episodes[2:], repeats=10)["dnn"][episodes[2].name]
    assert all(v > 0 for v in summary["rmse_std"].values())
    for state, low in summary["rmse_min"].items():  # every redraw predicts differently
        assert low < summary["rmse_mean"][state] < summary["rmse_max"][state]
    with pytest.raises(ValueError, match="was not trained with a random layer"):
        robustness({"edmd": EDMD(ThinPlateRBF(5)).fit(episodes[:2], [], normalizer)}, episodes[2:])


class RunsAway(Hold):
    """Holds its start, then jumps to ``factor`` training spans above the training range at
    row ``row`` (a spin-out the data never showed)."""

    def __init__(self, factor: float, row: int = -1) -> None:
        super().__init__()
        self.factor, self.row = factor, row

    def fit(self, train, validation, normalizer):
        self.normalizer_ = normalizer
        return self

    def predict(self, x0, inputs):
        out = super().predict(x0, inputs).astype(float)
        span = self.normalizer_.state_max - self.normalizer_.state_min
        out[..., self.row :, 1] = self.normalizer_.state_max[1] + self.factor * span[1]
        return out


def test_a_rollout_outside_the_datas_envelope_is_flagged_diverged_though_finite() -> None:
    """Half a training span past the range (the envelope is twice the range) is a model that
    ran off; a prediction just outside the range (an honest extrapolation) is not flagged, and
    how far counts as diverged is a setting."""
    episode = linear_episode("e", 50, 5)
    normalizer = MinMaxNormalizer.fit([episode])
    flags = {}
    for factor in (0.9 * ENVELOPE_SPANS, 1.1 * ENVELOPE_SPANS):
        model = RunsAway(factor).fit([episode], [], normalizer)
        flags[factor] = evaluate({"m": model}, [episode])["m"]["e"]["diverged"]
    assert flags == {0.9 * ENVELOPE_SPANS: False, 1.1 * ENVELOPE_SPANS: True}
    wider = evaluate(
        {"m": RunsAway(1.1 * ENVELOPE_SPANS).fit([], [], normalizer)},
        [episode],
        envelope_spans=2 * ENVELOPE_SPANS,
    )
    assert wider["m"]["e"]["diverged"] is False


def test_a_model_made_to_spin_is_flagged_from_then_on_with_its_rmse_until_then(
    caplog: pytest.LogCaptureFixture,
) -> None:
    episode = linear_episode("e", 80, 5)
    spins = RunsAway(3.0, row=30).fit([episode], [], MinMaxNormalizer.fit([episode]))
    metrics = evaluate({"spins": spins}, [episode])["spins"]["e"]
    assert metrics["diverged"] is True
    assert metrics["diverged_at_s"] == pytest.approx(episode.time_s[30])
    assert np.isfinite(metrics["rmse"]["vy"])  # finite, so only the envelope could tell
    held = np.sqrt(np.mean((episode.states[1:30] - episode.states[0]) ** 2, axis=0))
    np.testing.assert_allclose(list(metrics["rmse_until_diverged"].values()), held, rtol=1e-12)
    assert metrics["rmse_until_diverged"]["vy"] < metrics["rmse"]["vy"]
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "leaves the training data's envelope (vx" in warning and "t = 0.30 s" in warning


def test_a_drive_beyond_the_training_range_stretches_the_envelope() -> None:
    """A test drive faster than any training drive, predicted exactly, is not a spin-out."""
    train, test = linear_episode("train", 50, 5), linear_episode("test", 50, 6)
    span = np.ptp(train.states, axis=0)
    faster = dataclasses.replace(test, states=test.states + train.states.max(0) + 2 * span)

    model = Hold()
    model.normalizer_ = MinMaxNormalizer.fit([train])  # type: ignore[attr-defined]
    assert envelope_exit(model, faster.states, measured=faster.states) is None
    assert envelope_exit(model, faster.states) == 0  # against the training range alone: out


def test_window_names_say_which_window_a_verdict_is_for() -> None:
    assert window_name("rmse") == "open_loop"
    assert window_name("rmse_window_41") == "41_steps"
    assert window_name("rmse_window_1.5s") == "1.5s"


def test_beating_persistence_is_a_lower_rmse_on_the_same_drive_state_by_state() -> None:
    result = {
        "diverged": False,
        "rmse": {"vx": 0.5, "vy": 0.2, "yaw_rate": float("inf")},
        "rmse_window_3s": {"vx": 0.1, "vy": 0.05, "yaw_rate": 0.01},
    }
    held = {
        "diverged": False,
        "rmse": {"vx": 1.0, "vy": 0.2, "yaw_rate": 0.1},  # a tie does not beat it
        "rmse_window_3s": {"vx": 0.2, "vy": 0.01, "yaw_rate": None},
    }
    assert beats_persistence(result, held) == {
        "open_loop": {"vx": True, "vy": False, "yaw_rate": False},
        "3s": {"vx": True, "vy": False, "yaw_rate": None},  # persistence has no number
    }
    # A whole-drive rollout that ran away beats nothing there, whatever its RMSE says.
    ran_away = result | {"diverged": True, "rmse_until_diverged": {"vx": 0.1}}
    assert beats_persistence(ran_away, held)["open_loop"] == dict.fromkeys(
        ("vx", "vy", "yaw_rate"), False
    )


RACE_CAR = (
    InputChannel("road_wheel_angle", role="road_wheel", unit="rad"),
    InputChannel("torque_rl", role="drive", unit="N*m"),
    InputChannel("torque_rr", role="drive", unit="N*m"),
    InputChannel("brake_front", role="brake", unit="bar"),
    InputChannel("brake_rear", role="brake", unit="bar"),
)


def test_inputs_of_one_unit_share_an_axis_and_other_units_get_their_own() -> None:
    assert input_groups(RACE_CAR) == [[0], [1, 2], [3, 4]]
    # Logs from before units: the first alone, the others together, as they were drawn.
    plain = tuple(InputChannel(c.name) for c in RACE_CAR)
    assert input_groups(plain) == [[0], [1, 2, 3, 4]]


def test_a_five_input_car_is_drawn_one_axis_per_unit(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    steps = 200
    inputs = np.column_stack(
        [
            rng.normal(0, 0.05, steps),
            *rng.uniform(0, 1250, (2, steps)),
            *rng.uniform(0, 32, (2, steps)),
        ]
    )
    states = np.column_stack([np.full(steps, 20.0), rng.normal(0, 0.1, (steps, 2))])
    episode = Episode(
        "lap", np.arange(steps) * 0.01, states, inputs, np.zeros((steps, 3)), RACE_CAR
    )
    path = plot_prediction(episode, {"held": np.repeat(states[:1], steps, 0)}, tmp_path / "p.png")
    assert path.stat().st_size > 20_000
    _, axes = _figure(episode)
    assert len(axes) == 3 + 3  # the states, then steering, drive torques, brake pressures
    assert axes[4].get_ylabel() == "torque_rl, torque_rr [N*m]"
    assert axes[5].get_ylabel() == "brake_front, brake_rear [bar]"


def test_a_rollout_out_at_its_first_step_has_no_rmse_before_it() -> None:
    episode = linear_episode("e", 50, 5)
    away = RunsAway(3.0, row=1).fit([episode], [], MinMaxNormalizer.fit([episode]))
    metrics = evaluate({"m": away}, [episode])["m"]["e"]
    assert metrics["diverged_at_s"] == pytest.approx(episode.time_s[1])
    assert metrics["rmse_until_diverged"] == {"vx": None, "vy": None, "yaw_rate": None}


def test_the_prediction_figure_marks_where_a_prediction_left_the_envelope(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import harness.evaluation.prediction as prediction

    drawn: list[Any] = []
    monkeypatch.setattr(prediction, "save_figure", lambda fig, path: drawn.append(fig) or path)
    episode = linear_episode("e", 80, 5)
    spins = RunsAway(3.0, row=30).fit([episode], [], MinMaxNormalizer.fit([episode]))
    evaluate({"spins": spins, "hold": Hold()}, [episode], output_dir=tmp_path)
    (figure,) = drawn
    at = float(episode.time_s[30])
    for axis in figure.axes[:3]:  # one dashed line per state panel, at the time, spins' only
        marks = [line for line in axis.lines if list(line.get_xdata()) == [at, at]]
        assert len(marks) == 1 and marks[0].get_linestyle() == "--"
