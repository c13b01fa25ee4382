"""How much of the operating range a dataset covers: a summary for metrics.json and a figure."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from harness.core.episode import SEDAN_INPUTS, Episode, is_sedan
from harness.output import save_figure

G = 9.81
# A steering reversal: the steering rate changes sign, counting only rates beyond this dead band
# (the driver's hand tremor moves the wheel at about 20 deg/s rms from step to step).
REVERSAL_DEAD_BAND_DEG_PER_S = 60.0
# A saw-tooth: more reversals than this within one second (a person's fastest slalom, 1 Hz,
# reverses twice a second).
SAWTOOTH_WINDOW_S = 1.0
SAWTOOTH_REVERSALS = 4


def lateral_accel(episode: Episode) -> np.ndarray:
    vx, vy, yaw_rate = episode.states.T
    return np.gradient(vy, episode.time_s) + vx * yaw_rate


def longitudinal_accel(episode: Episode) -> np.ndarray:
    vx, vy, yaw_rate = episode.states.T
    return np.gradient(vx, episode.time_s) - vy * yaw_rate


def steering_reversals(
    steer_deg: np.ndarray, dt: float, dead_band: float = REVERSAL_DEAD_BAND_DEG_PER_S
) -> np.ndarray:
    """Frame indices where the steering rate reverses: a sign change between successive rates
    beyond ``dead_band`` (deg/s), rates inside the band skipped."""
    rate = np.diff(np.asarray(steer_deg, dtype=float)) / dt
    moving = np.flatnonzero(np.abs(rate) > dead_band)
    signs = np.sign(rate[moving])
    return moving[1:][signs[1:] != signs[:-1]]


def sawtooth_frames(
    steer_deg: np.ndarray,
    dt: float,
    window_s: float = SAWTOOTH_WINDOW_S,
    reversals: int = SAWTOOTH_REVERSALS,
) -> np.ndarray:
    """(T,) bool: frames inside a window of ``window_s`` that holds more than ``reversals``
    steering reversals (no person steers like that; a limit cycle of a driver's logic does)."""
    frames = len(steer_deg)
    width = max(round(window_s / dt), 1)
    counts = np.zeros(frames + 1)
    np.add.at(counts, steering_reversals(steer_deg, dt) + 1, 1)
    cumulative = np.cumsum(counts)
    starts = np.arange(frames)
    in_window = cumulative[np.minimum(starts + width, frames)] - cumulative[starts]
    busy = np.flatnonzero(in_window > reversals)
    marks = np.zeros(frames + 1)
    np.add.at(marks, busy, 1)
    np.add.at(marks, np.minimum(busy + width, frames), -1)
    return np.cumsum(marks)[:frames] > 0


def summary(
    episodes: Sequence[Episode], road_friction: float | None
) -> dict[str, float | int | dict[str, list[float]]]:
    """Coverage numbers, SI: frames, speed range, lateral acceleration relative to mu g (where
    the road's friction is known), the inputs' use (the sedan's pedal and steering; the range
    of each input of a user's logs)."""
    states = np.concatenate([e.states for e in episodes])
    inputs = np.concatenate([e.inputs for e in episodes])
    a_y = np.abs(np.concatenate([lateral_accel(e) for e in episodes]))
    vx = states[:, 0]
    dt = float(episodes[0].time_s[1] - episodes[0].time_s[0])
    common: dict[str, float | int | dict[str, list[float]]] = {
        "episodes": len(episodes),
        "frames": len(states),
        "hours": float(len(states) * dt / 3600),
        "vx_max_mps": float(vx.max()),
        "vx_min_mps": float(vx.min()),
        "start_speed_max_mps": float(max(e.states[0, 0] for e in episodes)),
        "vx_p50_mps": float(np.median(vx)),
        "fraction_below_5mps": float(np.mean(vx < 5.0)),
        "fraction_above_25mps": float(np.mean(vx > 25.0)),
        "vy_abs_max_mps": float(np.abs(states[:, 1]).max()),
        "yaw_rate_abs_max_radps": float(np.abs(states[:, 2]).max()),
        "lateral_accel_p99_mps2": float(np.percentile(a_y, 99)),
        "lateral_accel_max_mps2": float(a_y.max()),
    }
    if road_friction is None or not is_sedan(episodes[0].channels):
        names = episodes[0].input_names
        ranges = {
            n: [float(inputs[:, j].min()), float(inputs[:, j].max())] for j, n in enumerate(names)
        }
        return common | {"input_range": ranges}
    limit = road_friction * G
    sawtooth = sum(int(sawtooth_frames(e.inputs[:, 0], dt).sum()) for e in episodes)
    reversals = sum(len(steering_reversals(e.inputs[:, 0], dt)) for e in episodes)
    return common | {
        "fraction_lateral_above_half_mu_g": float(np.mean(a_y > 0.5 * limit)),
        "fraction_lateral_above_0.8_mu_g": float(np.mean(a_y > 0.8 * limit)),
        "steer_abs_p99_deg": float(np.percentile(np.abs(inputs[:, 0]), 99)),
        "fraction_throttle": float(np.mean(inputs[:, 1] > 0)),
        "fraction_brake": float(np.mean(inputs[:, 1] < 0)),
        "fraction_hard_brake_above_6mpa": float(np.mean(inputs[:, 1] < -6.0)),
        "steering_reversals_per_minute": float(reversals / (len(states) * dt / 60)),
        "fraction_steering_sawtooth": float(sawtooth / len(states)),
    }


def plot(splits: Mapping[str, Sequence[Episode]], road_friction: float | None, path: Path) -> None:
    """:func:`figure`, saved to ``path``."""
    save_figure(figure(splits, road_friction), path, dpi=100)


def figure(splits: Mapping[str, Sequence[Episode]], road_friction: float | None) -> Figure:
    """Like the paper's training-data figure: every path (without poses: the speed and the
    accelerations), the state distribution, a_y and u."""
    episodes = [e for split in splits.values() for e in split]
    states = np.concatenate([e.states for e in episodes])
    inputs = np.concatenate([e.inputs for e in episodes])
    a_y = np.concatenate([lateral_accel(e) for e in episodes])
    fig = Figure(figsize=(16, 9))
    grid = fig.add_gridspec(2, 4)

    if not any(np.ptp(e.poses[:, :2]) > 0 for e in episodes):  # logs without poses
        _speed_and_accelerations(fig, grid, episodes, states)
    else:
        _paths(fig.add_subplot(grid[:, :2]), splits, len(episodes))

    panels = [
        (grid[0, 2], states[:, 0], states[:, 1], "vx (m/s)", "vy (m/s)"),
        (grid[0, 3], states[:, 0], states[:, 2], "vx (m/s)", "yaw rate (rad/s)"),
    ]
    for cell, x, y, xlabel, ylabel in panels:
        ax = fig.add_subplot(cell)
        ax.hexbin(x, y, gridsize=50, bins="log", cmap="viridis", mincnt=1)
        ax.set(xlabel=xlabel, ylabel=ylabel, title="state distribution (log count)")

    ax = fig.add_subplot(grid[1, 2])
    ax.hist(a_y / G, bins=80, log=True, color="tab:purple")
    if road_friction is not None:
        for sign in (-1, 1):
            ax.axvline(sign * road_friction, color="k", ls=":")
    title = "a_y, dotted: ±μg" if road_friction is not None else "a_y"
    ax.set(xlabel="lateral acceleration (g)", ylabel="frames", title=title)

    ax = fig.add_subplot(grid[1, 3])
    channels = episodes[0].channels
    labels: tuple[str, ...]
    if is_sedan(channels):
        pedal = channels[1]
        labels = (
            "steering-wheel angle (deg)",
            "throttle / 0.2  |  −brake / 9.1 MPa"
            if channels == SEDAN_INPUTS
            else f"throttle × {pedal.gain_positive:g}  |  −brake MPa × {pedal.gain_negative:g}",
        )
    else:
        labels = tuple(c.name + (f" ({c.unit})" if c.unit else "") for c in channels[:2])
    if len(channels) == 1:
        ax.hist(inputs[:, 0], bins=80, log=True)
        ax.set(xlabel=labels[0], ylabel="frames", title="input (log count)")
    else:
        second = channels[1].feature(inputs[:, 1])
        ax.hexbin(inputs[:, 0], second, gridsize=50, bins="log", cmap="magma", mincnt=1)
        ax.set(xlabel=labels[0], ylabel=labels[1], title="inputs (log count)")
    dt = float(episodes[0].time_s[1] - episodes[0].time_s[0])
    fig.suptitle(f"Driving data: {len(states):,} frames at {dt * 1000:g} ms")
    fig.tight_layout()
    return fig


def _paths(ax: Any, splits: Mapping[str, Sequence[Episode]], count: int) -> None:
    """Every episode's path (X, Y), styled by split."""
    styles = {"train": "-", "validation": "--", "test": ":"}
    for split, members in splits.items():
        for e in members:
            ax.plot(
                e.poses[:, 0],
                e.poses[:, 1],
                styles.get(split, "-"),
                lw=0.8,
                label=f"{e.name} ({split})" if count <= 12 else None,
            )
    ax.set(xlabel="X (m)", ylabel="Y (m)", title=f"{count} episodes (paths)")
    ax.set_aspect("equal", adjustable="datalim")
    if count <= 12:
        ax.legend(fontsize=7, loc="best")


def _speed_and_accelerations(
    fig: Figure, grid: Any, episodes: Sequence[Episode], states: np.ndarray
) -> None:
    """Where the logs have no poses, what the path panel would say about coverage: the speed
    the car was driven at, and its longitudinal and lateral accelerations together."""
    ax = fig.add_subplot(grid[0, :2])
    ax.hist(states[:, 0], bins=80, color="tab:blue")
    ax.set(xlabel="vx (m/s)", ylabel="frames", title=f"{len(episodes)} episodes (no poses): speed")
    a_x = np.concatenate([longitudinal_accel(e) for e in episodes])
    a_y = np.concatenate([lateral_accel(e) for e in episodes])
    ax = fig.add_subplot(grid[1, :2])
    ax.hexbin(a_y / G, a_x / G, gridsize=60, bins="log", cmap="viridis", mincnt=1)
    ax.set(
        xlabel="lateral acceleration (g)",
        ylabel="longitudinal acceleration (g)",
        title="accelerations (log count)",
    )
    ax.set_aspect("equal", adjustable="datalim")
