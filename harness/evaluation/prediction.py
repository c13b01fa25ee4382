"""The paper's prediction experiments (Sec. VI-C): open-loop RMSE, its figure, and robustness.

:func:`evaluate` predicts every test episode with every learner, from the episode's initial
state under the recorded inputs, three ways, and returns RMSEs per state in SI units:

- ``rmse``: one open-loop rollout over the whole episode (the paper's Table of RMSEs);
- ``rmse_window_<p>``: windows of ``window_steps`` steps tiling the episode, each re-initialised
  from the measured state (what an MPC with horizon p relies on);
- ``rmse_window_<s>s``: the same with windows of each of ``window_seconds``.

Row 0 of every rollout is the measured state itself and is left out of the RMSE. A model that
diverges gives inf (written as null in ``metrics.json``). A whole-episode rollout that is not
finite, or leaves the training data's range by more than ``DIVERGED_SPANS`` times its span in
any state, is flagged ``diverged``: the report shows it as such, never inside a mean.

:func:`robustness` repeats predictions of learners trained with a random layer, drawing the
layer anew each time (the paper's second experiment), and reports the RMSE's mean and spread.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from harness.core.episode import SEDAN_INPUTS, Episode
from harness.output import save_arrays, save_figure
from harness.recorder import Recorder
from learners.base import Learner

__all__ = [
    "STATE_NAMES",
    "by_episode",
    "evaluate",
    "open_loop",
    "plot_prediction",
    "plot_robustness",
    "rmse",
    "robustness",
    "windowed",
]

STATE_NAMES = ("vx", "vy", "yaw_rate")
_UNITS = ("m/s", "m/s", "rad/s")
log = logging.getLogger(__name__)
_REPEAT_CHUNK = 25  # repeated predictions per batched rollout (bounds memory on long episodes)
# A prediction this many training ranges outside the training data has left what the model knows:
# its RMSE measures how fast it ran away, not how well it predicts.
DIVERGED_SPANS = 10.0


def rmse(
    predicted: np.ndarray, truth: np.ndarray, rows: np.ndarray | None = None
) -> dict[str, float]:
    """RMSE per state of (T, 3) arrays over ``rows`` (default 1..T-1: row 0 is given, not
    predicted); a NaN (diverged) prediction counts as inf."""
    rows = np.arange(1, len(truth)) if rows is None else rows
    with np.errstate(over="ignore", invalid="ignore"):
        values = np.sqrt(np.mean((predicted[rows] - truth[rows]) ** 2, axis=0))
    return {
        name: float(np.where(np.isnan(v), np.inf, v))
        for name, v in zip(STATE_NAMES, values, strict=True)
    }


def open_loop(learner: Learner, episode: Episode, **kwargs: Any) -> np.ndarray:
    """(T, 3) prediction of the whole episode from its first state under its inputs."""
    return learner.predict(episode.states[0], episode.inputs[:-1], **kwargs)


def windowed(
    learner: Learner, episode: Episode, window_steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """Predictions in windows of ``window_steps``, each started from the measured state.

    Returns the (T, 3) predictions, whose rows 0, w, 2w, ... are the measured window starts,
    and the indices of the predicted rows (the others). The last window may be shorter; full
    windows go through ``predict`` as one batch.
    """
    if window_steps < 1:
        raise ValueError(f"window_steps must be >= 1 (got {window_steps})")
    length = len(episode)
    out = episode.states.astype(float).copy()
    full = (length - 1) // window_steps
    if full:
        starts = np.arange(full) * window_steps
        index = starts[:, None] + np.arange(window_steps)
        pred = learner.predict(episode.states[starts], episode.inputs[index])
        rows = starts[:, None] + np.arange(1, window_steps + 1)
        out[rows] = pred[:, 1:]
    rest = full * window_steps
    if rest < length - 1:
        out[rest + 1 :] = learner.predict(episode.states[rest], episode.inputs[rest:-1])[1:]
    out[np.arange(0, length, window_steps)] = episode.states[::window_steps]
    predicted = np.setdiff1d(np.arange(length), np.arange(0, length, window_steps))
    return out, predicted


def evaluate(
    learners: Mapping[str, Learner],
    episodes: Sequence[Episode],
    *,
    window_steps: int = 41,
    window_seconds: float | Sequence[float] = 10.0,
    recorder: Recorder | None = None,
    output_dir: Path | None = None,
    prefix: str = "",
) -> dict[str, dict[str, dict[str, Any]]]:
    """RMSEs of every learner on every episode: ``{learner: {episode: {metric: {state: v}}}}``.

    Metrics: ``rmse``, ``rmse_window_<window_steps>``, ``rmse_window_<s>s`` for each ``s`` of
    ``window_seconds`` (see the module docstring). Writes ``prediction_<episode>.png`` (truth
    and every learner's open-loop prediction, as the paper's figure) into ``output_dir`` and one
    recording per episode (``<prefix>prediction/<episode>``, predictions as
    ``extra/predicted_<learner>``); ``recorder=None`` and ``output_dir=None`` write nothing.
    Use :func:`by_episode` for ``{episode: {learner: ...}}``.
    """
    seconds = [window_seconds] if isinstance(window_seconds, int | float) else window_seconds
    results: dict[str, dict[str, dict[str, Any]]] = {name: {} for name in learners}
    for episode in episodes:
        dt = float(np.median(np.diff(episode.time_s)))
        predictions = {}
        for name, learner in learners.items():
            pred = open_loop(learner, episode)
            _warn_diverged(name, episode, pred)
            predictions[name] = pred
            results[name][episode.name] = {
                "diverged": diverged(learner, pred),
                "rmse": rmse(pred, episode.states),
                f"rmse_window_{window_steps}": rmse(
                    *_pair(windowed(learner, episode, window_steps), episode)
                ),
            }
            for s in seconds:
                steps = max(1, round(s / dt))
                results[name][episode.name][f"rmse_window_{s:g}s"] = rmse(
                    *_pair(windowed(learner, episode, steps), episode)
                )
        if recorder is not None:
            recorder.rollout(
                f"{prefix}prediction/{episode.name}",
                episode.time_s,
                episode.states,
                episode.inputs,
                poses=episode.poses,
                input_names=episode.input_names,
                overlays={f"predicted_{name}": _finite(p) for name, p in predictions.items()},
            )
        if output_dir is not None:
            plot_prediction(
                episode, predictions, Path(output_dir) / f"prediction_{episode.name}.png"
            )
            save_arrays(
                Path(output_dir) / f"prediction_{episode.name}.npz",
                time_s=episode.time_s,
                states=episode.states,
                inputs=episode.inputs,
                poses=episode.poses,
                **{f"predicted_{name}": p for name, p in predictions.items()},
            )
    return results


def diverged(learner: Learner, predicted: np.ndarray) -> bool:
    """Whether a rollout is not finite or leaves the training data's range by more than
    ``DIVERGED_SPANS`` spans in any state (in the learner's min-max normalized units)."""
    if not np.all(np.isfinite(predicted)):
        return True
    normalizer = getattr(learner, "normalizer_", None)
    if normalizer is None:  # a model that knows no training range: finiteness is all there is
        return False
    scaled = normalizer.states(predicted)
    return bool(np.any((scaled < -DIVERGED_SPANS) | (scaled > 1.0 + DIVERGED_SPANS)))


def _warn_diverged(name: str, episode: Episode, predicted: np.ndarray) -> None:
    """Say which learner diverged on which drive, and when: in ``metrics.json`` it is only a
    null RMSE, and a controller on that model is the next to meet the NaN."""
    bad = ~np.all(np.isfinite(predicted), axis=-1)
    if bad.any():
        first = int(np.argmax(bad))
        log.warning(
            "prediction: %s's open-loop prediction of %s is not finite from t = %.2f s on (%d "
            "of %d steps): it diverged there, so its RMSE is inf (null in metrics.json)",
            name,
            episode.name,
            episode.time_s[first],
            int(bad.sum()),
            len(bad),
        )


def by_episode(results: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Swap the first two levels: ``{learner: {episode: x}}`` -> ``{episode: {learner: x}}``."""
    out: dict[str, dict[str, Any]] = {}
    for learner, per_episode in results.items():
        for episode, value in per_episode.items():
            out.setdefault(episode, {})[learner] = value
    return out


def robustness(
    learners: Learner | Mapping[str, Learner],
    episodes: Sequence[Episode],
    repeats: int = 100,
    *,
    recorder: Recorder | None = None,
    output_dir: Path | None = None,
    prefix: str = "",
) -> dict[str, dict[str, dict[str, dict[str, float]]]]:
    """Open-loop RMSE over ``repeats`` predictions, each with a freshly drawn random layer.

    Every learner must have been trained with ``random_layer.enabled``. Repeats run in batches
    of 25 rows; batch c passes seed 25 c and every row draws its own layer from it, so results
    are reproducible. Returns ``{learner: {episode: {"rmse_mean" | "rmse_std" | "rmse_min" |
    "rmse_max" | "rmse_nominal": {state: v}}}}`` and writes ``robustness_<episode>.png`` (mean
    prediction with the 5-95 % band of the repeats shaded, as the paper's figure).
    """
    if isinstance(learners, Learner):
        learners = {learners.name: learners}
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1 (got {repeats})")
    for name, learner in learners.items():
        if not learner.redraws_random_layer:
            raise ValueError(f"learner {name!r} was not trained with a random layer")
    recorder = recorder or Recorder()
    results: dict[str, dict[str, dict[str, dict[str, float]]]] = {name: {} for name in learners}
    for episode in episodes:
        bands = {}
        for name, learner in learners.items():
            preds = _repeated(learner, episode, repeats)
            errors = np.array([list(rmse(p, episode.states).values()) for p in preds])
            summary = {
                "rmse_mean": errors.mean(0),
                "rmse_std": errors.std(0),
                "rmse_min": errors.min(0),
                "rmse_max": errors.max(0),
            }
            results[name][episode.name] = {
                key: dict(zip(STATE_NAMES, map(float, value), strict=True))
                for key, value in summary.items()
            }
            results[name][episode.name]["rmse_nominal"] = rmse(
                open_loop(learner, episode), episode.states
            )
            with np.errstate(invalid="ignore"):
                bands[name] = (
                    np.nanmean(preds, 0),
                    np.nanpercentile(preds, 5, axis=0),
                    np.nanpercentile(preds, 95, axis=0),
                )
        recorder.rollout(
            f"robustness/{episode.name}",
            episode.time_s,
            episode.states,
            episode.inputs,
            poses=episode.poses,
            input_names=episode.input_names,
            overlays={f"mean_{name}": _finite(b[0]) for name, b in bands.items()},
        )
        if output_dir is not None:
            plot_robustness(episode, bands, Path(output_dir) / f"robustness_{episode.name}.png")
    return results


def _pair(
    result: tuple[np.ndarray, np.ndarray], episode: Episode
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return result[0], episode.states, result[1]


def _repeated(learner: Learner, episode: Episode, repeats: int) -> np.ndarray:
    """(repeats, T, 3): repeat r with the random layer drawn from seed r."""
    out = []
    for first in range(0, repeats, _REPEAT_CHUNK):
        rows = min(_REPEAT_CHUNK, repeats - first)
        x0 = np.repeat(episode.states[:1], rows, 0)
        inputs = np.repeat(episode.inputs[None, :-1], rows, 0)
        out.append(learner.predict(x0, inputs, random_layer_seed=first))  # type: ignore[call-arg]
    return np.concatenate(out)


def _finite(x: np.ndarray) -> np.ndarray:
    """Diverged predictions are logged as NaN (the recorder keeps NaN, not inf)."""
    return np.where(np.isfinite(x), x, np.nan)


def _figure(episode: Episode) -> tuple[Figure, np.ndarray]:
    fig = Figure(figsize=(9, 9))
    axes = fig.subplots(4, 1, sharex=True)
    t = episode.time_s
    for ax, i in zip(axes[:3], range(3), strict=True):
        ax.plot(t, episode.states[:, i], "k-", lw=1.6, label="measured")
        ax.set_ylabel(f"{STATE_NAMES[i]} [{_UNITS[i]}]")
        ax.grid(True, alpha=0.3)
        span = np.ptp(episode.states[:, i])
        pad = 0.5 * span + 1e-3
        ax.set_ylim(episode.states[:, i].min() - pad, episode.states[:, i].max() + pad)
    ax_u = axes[3]
    ax_u.plot(t, episode.inputs[:, 0], color="C7", lw=1.0)
    sedan = episode.channels == SEDAN_INPUTS
    ax_u.set_ylabel("steer_wheel [deg]" if sedan else episode.input_names[0], color="C7")
    if episode.inputs.shape[1] > 1:  # the others on one axis of their own
        ax_p = ax_u.twinx()
        for j, name in enumerate(episode.input_names[1:], start=1):
            ax_p.plot(t, episode.inputs[:, j], color=f"C{7 + j}", lw=1.0, label=name)
        if sedan:
            ax_p.set_ylabel("pedal [throttle / -MPa]", color="C8")
        else:
            ax_p.set_ylabel(", ".join(episode.input_names[1:]))
            ax_p.legend(fontsize=7, loc="upper right")
    ax_u.set_xlabel("time [s]")
    ax_u.grid(True, alpha=0.3)
    return fig, axes


def plot_prediction(episode: Episode, predictions: Mapping[str, np.ndarray], path: Path) -> Path:
    """Three state panels (measured and every learner's open-loop prediction) and the inputs."""
    fig, axes = _figure(episode)
    for k, (name, pred) in enumerate(predictions.items()):
        for i in range(3):
            axes[i].plot(episode.time_s, pred[:, i], color=f"C{k}", lw=1.0, label=name)
    axes[0].legend(loc="upper left", fontsize=7, ncol=min(len(predictions) + 1, 4))
    axes[0].set_title(f"open-loop prediction, {episode.name} (axes clipped to 2x the data range)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, path)


def plot_robustness(
    episode: Episode,
    bands: Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
    path: Path,
) -> Path:
    """Mean of the repeated predictions per learner with their 5-95 % band shaded."""
    fig, axes = _figure(episode)
    for k, (name, (mean, low, high)) in enumerate(bands.items()):
        for i in range(3):
            axes[i].plot(episode.time_s, mean[:, i], color=f"C{k}", lw=1.0, label=f"{name} mean")
            axes[i].fill_between(
                episode.time_s, low[:, i], high[:, i], color=f"C{k}", alpha=0.25, lw=0
            )
    axes[0].legend(loc="upper left", fontsize=8, ncol=len(bands) + 1)
    axes[0].set_title(f"repeated predictions with a random layer, {episode.name} (5-95 % band)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, path)
