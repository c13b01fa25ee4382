"""The paper's prediction experiments (Sec. VI-C): open-loop RMSE, its figure, and robustness.

:func:`evaluate` predicts every test episode with every learner, from the episode's initial
state under the recorded inputs, three ways, and returns RMSEs per state in SI units:

- ``rmse``: one open-loop rollout over the whole episode (the paper's Table of RMSEs);
- ``rmse_window_<p>``: windows of ``window_steps`` steps tiling the episode, each re-initialised
  from the measured state (what an MPC with horizon p relies on);
- ``rmse_window_<s>s``: the same with windows of each of ``window_seconds``.

Row 0 of every rollout is the measured state itself and is left out of the RMSE. A model that
diverges gives inf (written as null in ``metrics.json``). A whole-episode rollout that is not
finite, or leaves the data's envelope (per state, the training range, stretched to hold the
drive's own, widened by ``envelope_spans`` training spans on each side: a spin-out the data
never showed), is flagged
``diverged`` from that time on (``diverged_at_s``), with its RMSE up to then beside the flag
(``rmse_until_diverged``); the report shows it as diverged, never inside a mean.

:func:`beats_persistence` compares every window's RMSE with persistence's (the state held) on
the same drive: the verdict ``prediction.<episode>.beats_persistence.<window>.<state>``.

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

from harness.core.contracts import RunLearner
from harness.core.episode import Episode, InputChannel, is_sedan
from harness.output import save_arrays, save_figure
from harness.recorder import Recorder

__all__ = [
    "ENVELOPE_SPANS",
    "STATE_NAMES",
    "beats_persistence",
    "by_episode",
    "envelope_exit",
    "evaluate",
    "open_loop",
    "plot_prediction",
    "plot_robustness",
    "rmse",
    "robustness",
    "window_name",
    "windowed",
]

STATE_NAMES = ("vx", "vy", "yaw_rate")
_UNITS = ("m/s", "m/s", "rad/s")
log = logging.getLogger(__name__)
_REPEAT_CHUNK = 25  # repeated predictions per batched rollout (bounds memory on long episodes)
# A prediction this many training spans beyond the training range (on either side: the envelope is
# twice the range) has left what the model knows: a vy of 5.85 m/s on a lap that never passes
# 0.27, a spin-out the data never showed. Its RMSE measures how fast it ran away, not how well it
# predicts. The main job's learners stay within 0.12 spans of their range.
ENVELOPE_SPANS = 0.5


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


def open_loop(learner: RunLearner, episode: Episode, **kwargs: Any) -> np.ndarray:
    """(T, 3) prediction of the whole episode from its first state under its inputs."""
    return learner.predict(episode.states[0], episode.inputs[:-1], **kwargs)


def windowed(
    learner: RunLearner, episode: Episode, window_steps: int
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
    learners: Mapping[str, RunLearner],
    episodes: Sequence[Episode],
    *,
    window_steps: int = 41,
    window_seconds: float | Sequence[float] = 10.0,
    envelope_spans: float = ENVELOPE_SPANS,
    recorder: Recorder | None = None,
    output_dir: Path | None = None,
    prefix: str = "",
) -> dict[str, dict[str, dict[str, Any]]]:
    """RMSEs of every learner on every episode: ``{learner: {episode: {metric: {state: v}}}}``.

    Metrics: ``diverged`` and ``diverged_at_s`` (null unless it diverged; then also
    ``rmse_until_diverged``), ``rmse``, ``rmse_window_<window_steps>``, ``rmse_window_<s>s`` for
    each ``s`` of ``window_seconds`` (see the module docstring). Writes
    ``prediction_<episode>.png`` (truth and every learner's open-loop prediction, as the paper's
    figure) into ``output_dir`` and one recording per episode (``<prefix>prediction/<episode>``,
    predictions as ``extra/predicted_<learner>``); ``recorder=None`` and ``output_dir=None``
    write nothing.
    Use :func:`by_episode` for ``{episode: {learner: ...}}``.
    """
    seconds = [window_seconds] if isinstance(window_seconds, int | float) else window_seconds
    results: dict[str, dict[str, dict[str, Any]]] = {name: {} for name in learners}
    for episode in episodes:
        dt = float(np.median(np.diff(episode.time_s)))
        predictions = {}
        for name, learner in learners.items():
            pred = open_loop(learner, episode)
            exit_row = envelope_exit(learner, pred, envelope_spans, episode.states)
            predictions[name] = pred
            results[name][episode.name] = {
                "diverged": exit_row is not None,
                "diverged_at_s": None,
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
            if exit_row is not None:
                _warn_diverged(name, episode, pred, exit_row)
                results[name][episode.name]["diverged_at_s"] = float(episode.time_s[exit_row])
                # Null where it left at its first predicted step: nothing came before.
                results[name][episode.name]["rmse_until_diverged"] = (
                    rmse(pred, episode.states, np.arange(1, exit_row))
                    if exit_row > 1
                    else dict.fromkeys(STATE_NAMES)
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
            left = {name: r[episode.name]["diverged_at_s"] for name, r in results.items()}
            plot_prediction(
                episode, predictions, Path(output_dir) / f"prediction_{episode.name}.png", left
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


def envelope_exit(
    learner: RunLearner,
    predicted: np.ndarray,
    spans: float = ENVELOPE_SPANS,
    measured: np.ndarray | None = None,
) -> int | None:
    """The first row where a rollout is not finite or leaves the envelope: the training data's
    range (stretched to hold the ``measured`` drive's, so a drive faster than training is no
    spin-out) widened by ``spans`` training spans on each side, in the learner's min-max
    normalized units; None when it stays inside. A model that knows no training range is
    judged by finiteness alone."""
    with np.errstate(invalid="ignore"):
        outside = ~np.all(np.isfinite(predicted), axis=-1)
        normalizer = getattr(learner, "normalizer_", None)
        if normalizer is not None:
            low, high = np.zeros(predicted.shape[-1]), np.ones(predicted.shape[-1])
            if measured is not None:
                truth = normalizer.states(measured)
                low, high = np.minimum(low, truth.min(0)), np.maximum(high, truth.max(0))
            scaled = normalizer.states(np.where(np.isfinite(predicted), predicted, 0.0))
            outside |= np.any((scaled < low - spans) | (scaled > high + spans), axis=-1)
    return int(np.argmax(outside)) if outside.any() else None


def _warn_diverged(name: str, episode: Episode, predicted: np.ndarray, row: int) -> None:
    """Say which learner diverged on which drive, when and how: in ``metrics.json`` it is a flag
    and a time, and a controller on that model is the next to meet the runaway."""
    values = predicted[row]
    how = (
        "is not finite"
        if not np.all(np.isfinite(values))
        else "leaves the training data's envelope ("
        + ", ".join(f"{s} {v:.3g}" for s, v in zip(STATE_NAMES, values, strict=True))
        + ")"
    )
    log.warning(
        "prediction: %s's open-loop prediction of %s %s from t = %.2f s on: it diverged there "
        "(prediction.%s.diverged_at_s; its RMSE until then is rmse_until_diverged)",
        name,
        episode.name,
        how,
        episode.time_s[row],
        episode.name,
    )


def window_name(metric: str) -> str:
    """The window an RMSE key scores: ``rmse`` -> ``open_loop`` (the whole drive),
    ``rmse_window_41`` -> ``41_steps``, ``rmse_window_3s`` -> ``3s``."""
    if metric == "rmse":
        return "open_loop"
    window = metric.removeprefix("rmse_window_")
    return window if window.endswith("s") else f"{window}_steps"


def beats_persistence(
    result: Mapping[str, Any], held: Mapping[str, Any]
) -> dict[str, dict[str, bool | None]]:
    """Per window and state, whether a learner's RMSE on a drive is below persistence's (the
    state held) on the same drive: ``{window_name: {state: verdict}}``. A diverged whole-drive
    rollout or a non-finite RMSE does not beat it; None where persistence has no number."""
    verdicts: dict[str, dict[str, bool | None]] = {}
    for metric, values in result.items():
        bar = held.get(metric)
        if metric == "rmse_until_diverged" or not metric.startswith("rmse"):
            continue
        if not (isinstance(values, Mapping) and isinstance(bar, Mapping)):
            continue
        ran_away = metric == "rmse" and bool(result.get("diverged"))
        verdicts[window_name(metric)] = {
            state: _below(values.get(state), bar.get(state), ran_away) for state in STATE_NAMES
        }
    return verdicts


def _below(own: float | None, bar: float | None, ran_away: bool) -> bool | None:
    if bar is None or not np.isfinite(bar):
        return None
    return not ran_away and own is not None and bool(np.isfinite(own)) and own < bar


def by_episode(results: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Swap the first two levels: ``{learner: {episode: x}}`` -> ``{episode: {learner: x}}``."""
    out: dict[str, dict[str, Any]] = {}
    for learner, per_episode in results.items():
        for episode, value in per_episode.items():
            out.setdefault(episode, {})[learner] = value
    return out


def robustness(
    learners: RunLearner | Mapping[str, RunLearner],
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
    if not isinstance(learners, Mapping):
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


def _repeated(learner: RunLearner, episode: Episode, repeats: int) -> np.ndarray:
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


def input_groups(channels: Sequence[InputChannel]) -> list[list[int]]:
    """The inputs drawn together on one axis: those of one unit (or, without a unit, one role);
    inputs that declare neither are each drawn alone after the first (logs from before roles:
    the first alone, the others together, as they were)."""
    if all(c.unit is None and c.role is None for c in channels):
        return [[0], list(range(1, len(channels)))] if len(channels) > 1 else [[0]]
    groups: dict[str, list[int]] = {}
    for j, channel in enumerate(channels):
        groups.setdefault(channel.unit or channel.role or channel.name, []).append(j)
    return list(groups.values())


def _figure(episode: Episode) -> tuple[Figure, np.ndarray]:
    sedan = is_sedan(episode.channels)
    groups = [[0, 1]] if sedan else input_groups(episode.channels)
    fig = Figure(figsize=(9, 9 + 1.5 * (len(groups) - 1)))
    axes = fig.subplots(3 + len(groups), 1, sharex=True)
    t = episode.time_s
    for ax, i in zip(axes[:3], range(3), strict=True):
        ax.plot(t, episode.states[:, i], "k-", lw=1.6, label="measured")
        ax.set_ylabel(f"{STATE_NAMES[i]} [{_UNITS[i]}]")
        ax.grid(True, alpha=0.3)
        span = np.ptp(episode.states[:, i])
        pad = 0.5 * span + 1e-3
        ax.set_ylim(episode.states[:, i].min() - pad, episode.states[:, i].max() + pad)
    if sedan:  # steering on the left, the signed pedal on a twin axis
        ax_u = axes[3]
        ax_u.plot(t, episode.inputs[:, 0], color="C7", lw=1.0)
        ax_u.set_ylabel("steer_wheel [deg]", color="C7")
        ax_p = ax_u.twinx()
        ax_p.plot(t, episode.inputs[:, 1], color="C8", lw=1.0, label=episode.input_names[1])
        ax_p.set_ylabel("pedal [throttle / -MPa]", color="C8")
    else:  # one axis per unit, so a brake's bar and a torque's N·m do not share a scale
        for ax, group in zip(axes[3:], groups, strict=True):
            for j in group:
                channel = episode.channels[j]
                ax.plot(t, episode.inputs[:, j], color=f"C{7 + j}", lw=1.0, label=channel.name)
            units = {episode.channels[j].unit for j in group} - {None}
            label = ", ".join(episode.input_names[j] for j in group) if len(group) < 3 else "inputs"
            ax.set_ylabel(f"{label} [{units.pop()}]" if len(units) == 1 else label, fontsize=8)
            if len(group) > 1:
                ax.legend(fontsize=7, loc="upper right")
            ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    axes[3].grid(True, alpha=0.3)
    return fig, axes


def plot_prediction(
    episode: Episode,
    predictions: Mapping[str, np.ndarray],
    path: Path,
    diverged_at_s: Mapping[str, float | None] | None = None,
) -> Path:
    """Three state panels (measured and every learner's open-loop prediction) and the inputs;
    a dashed line in a learner's colour where its prediction left the data's envelope."""
    fig, axes = _figure(episode)
    for k, (name, pred) in enumerate(predictions.items()):
        left = (diverged_at_s or {}).get(name)
        for i in range(3):
            axes[i].plot(episode.time_s, pred[:, i], color=f"C{k}", lw=1.0, label=name)
            if left is not None:
                axes[i].axvline(left, color=f"C{k}", ls="--", lw=0.8)
        if left is not None:
            axes[0].text(
                left,
                1.0,
                " diverged",
                color=f"C{k}",
                fontsize=7,
                va="top",
                transform=axes[0].get_xaxis_transform(),
            )
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
