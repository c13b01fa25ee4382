"""A test course on the ground: lanes marked by cones, and how a car's path is judged on it.

A vehicle engineer judges a lane change by where the car went, not by its state history: did
it stay inside the cone lanes, how far did it stray from the centre line, how did it leave.
:class:`Course` holds the geometry (world frame, m: X along the course, Y to the left), and
:func:`path_metrics` scores a run's poses on it (``tracking.references.<name>.path.*``):

- ``max_lateral_deviation_m``, ``rms_lateral_deviation_m``: distance of the car's reference
  point (its pose) from the centre line, perpendicular to it, between the course's entry and exit;
- ``cones_hit`` of ``cones``: a cone is hit when the car's *body* (a rectangle of the car's
  length and width around its pose) reaches the cone's station with its edge on or beyond the
  cone, on the cone's side of the lane; a car entirely outside the lane there knocks it down too;
- ``passed``: the exit was reached and no cone was hit;
- ``exit_heading_error_rad`` (yaw minus the centre line's heading) and ``exit_speed_mps`` (vx)
  where the car's reference point crosses the exit; null when it never did.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from harness.core.reference_path import ReferencePath
from harness.output import save_figure
from harness.recorder import Recorder


@dataclass(frozen=True)
class Lane:
    """One coned section: the car must pass X in [start_m, end_m] with its body in (right, left)."""

    name: str
    start_m: float
    end_m: float
    right_m: float  # Y of the right-hand cone line
    left_m: float  # Y of the left-hand cone line


@dataclass(frozen=True)
class Course:
    """Lanes, cones and the centre line a car should follow; X increases along the course."""

    centre_x_m: np.ndarray  # (K,) increasing
    centre_y_m: np.ndarray  # (K,)
    lanes: tuple[Lane, ...]
    vehicle_length_m: float = 4.6  # the body judged against the cones, centred on the pose
    vehicle_width_m: float = 1.8
    cone_spacing_m: float = 2.5

    @property
    def entry_m(self) -> float:
        return min(lane.start_m for lane in self.lanes)

    @property
    def exit_m(self) -> float:
        return max(lane.end_m for lane in self.lanes)

    def cones(self) -> tuple[np.ndarray, np.ndarray]:
        """(C, 2) cone positions (X, Y) and (C,) side (+1 left line, -1 right line): each cone line
        has a cone at both ends and at most ``cone_spacing_m`` apart between."""
        positions, sides = [], []
        for lane in self.lanes:
            count = max(2, int(np.ceil((lane.end_m - lane.start_m) / self.cone_spacing_m)) + 1)
            x = np.linspace(lane.start_m, lane.end_m, count)
            for y, side in ((lane.left_m, 1.0), (lane.right_m, -1.0)):
                positions.append(np.stack([x, np.full_like(x, y)], axis=1))
                sides.append(np.full(count, side))
        return np.concatenate(positions), np.concatenate(sides)

    def centre_at(self, x_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre line Y and heading (rad) at stations ``x_m`` (held flat outside the course)."""
        slope = np.gradient(self.centre_y_m, self.centre_x_m)
        y = np.interp(x_m, self.centre_x_m, self.centre_y_m)
        return y, np.arctan(np.interp(x_m, self.centre_x_m, slope))

    def path(self) -> ReferencePath:
        """The centre line as a path to follow (``controller.reference: path``)."""
        return ReferencePath.from_points(self.centre_x_m, self.centre_y_m)

    def as_arrays(self) -> dict[str, np.ndarray]:
        """The course as arrays (for ``course_<reference>.npz``, which the report draws)."""
        cones, sides = self.cones()
        lanes = np.array([[ln.start_m, ln.end_m, ln.right_m, ln.left_m] for ln in self.lanes])
        return {
            "vehicle_size_m": np.array([self.vehicle_length_m, self.vehicle_width_m]),
            "centre_x_m": self.centre_x_m,
            "centre_y_m": self.centre_y_m,
            "lanes": lanes,
            "cones": cones,
            "cone_sides": sides,
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> Course:
        lanes = tuple(
            Lane(f"lane {2 * i + 1}", *map(float, row)) for i, row in enumerate(arrays["lanes"])
        )
        length, width = map(float, arrays["vehicle_size_m"])
        x, y = np.asarray(arrays["centre_x_m"]), np.asarray(arrays["centre_y_m"])
        return cls(x, y, lanes, length, width)


def body_corners(poses: np.ndarray, length_m: float, width_m: float) -> np.ndarray:
    """(T, 4, 2) corners of a length × width rectangle centred on each pose (X, Y, yaw)."""
    local = 0.5 * np.array(
        [[length_m, width_m], [length_m, -width_m], [-length_m, -width_m], [-length_m, width_m]]
    )
    cos, sin = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    x = poses[:, :1] + cos * local[:, 0] - sin * local[:, 1]
    y = poses[:, 1:2] + sin * local[:, 0] + cos * local[:, 1]
    return np.stack([x, y], axis=-1)


def _body_span_at(corners: np.ndarray, stations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, C) lowest and highest Y of each body rectangle on the line X = station (NaN where the
    body does not reach that station). The rectangle is convex: its section is spanned by the
    points where its four edges cross the line."""
    start, end = corners, np.roll(corners, -1, axis=1)  # (T, 4, 2) edges
    x0, x1 = start[..., 0][..., None], end[..., 0][..., None]  # (T, 4, 1)
    y0, y1 = start[..., 1][..., None], end[..., 1][..., None]
    s = stations[None, None, :]
    lo, hi = np.minimum(x0, x1), np.maximum(x0, x1)
    crosses = (s >= lo) & (s <= hi) & (hi > lo)
    with np.errstate(invalid="ignore", divide="ignore"):
        y = y0 + (y1 - y0) * (s - x0) / (x1 - x0)
    low = np.where(crosses, y, np.inf).min(axis=1)
    high = np.where(crosses, y, -np.inf).max(axis=1)
    reached = np.isfinite(low)
    return np.where(reached, low, np.nan), np.where(reached, high, np.nan)


def cones_hit(course: Course, poses: np.ndarray, length_m: float, width_m: float) -> np.ndarray:
    """(C,) whether each cone of :meth:`Course.cones` was hit by the body during the run."""
    cones, sides = course.cones()
    low, high = _body_span_at(body_corners(poses, length_m, width_m), cones[:, 0])
    with np.errstate(invalid="ignore"):
        # A left-line cone is hit when the body reaches its Y from the lane side (or lies beyond
        # it); a right-line cone likewise from below.
        hit = np.where(sides > 0, high >= cones[:, 1], low <= cones[:, 1])
    return np.any(hit & np.isfinite(low), axis=0)


def path_metrics(course: Course, poses: np.ndarray, states: np.ndarray) -> dict[str, Any]:
    """``path.*`` of a run (poses (T, 3) X, Y, yaw; states (T, 3) vx, vy, yaw rate), SI."""
    poses, states = np.asarray(poses, dtype=float), np.asarray(states, dtype=float)
    on_course = (poses[:, 0] >= course.entry_m) & (poses[:, 0] <= course.exit_m)
    centre_y, heading = course.centre_at(poses[:, 0])
    deviation = (poses[:, 1] - centre_y) * np.cos(heading)
    hit = cones_hit(course, poses, course.vehicle_length_m, course.vehicle_width_m)
    beyond = np.flatnonzero(poses[:, 0] >= course.exit_m)
    reached = beyond.size > 0
    exit_heading = exit_speed = None
    if reached:
        k = int(beyond[0])
        error = poses[k, 2] - heading[k]
        exit_heading = float(np.arctan2(np.sin(error), np.cos(error)))
        exit_speed = float(states[k, 0])
    inside = deviation[on_course]
    return {
        "max_lateral_deviation_m": float(np.max(np.abs(inside))) if inside.size else None,
        "rms_lateral_deviation_m": float(np.sqrt(np.mean(inside**2))) if inside.size else None,
        "cones_hit": int(hit.sum()),
        "cones": int(hit.size),
        "reached_exit": reached,
        "passed": bool(reached and not hit.any()),
        "exit_heading_error_rad": exit_heading,
        "exit_speed_mps": exit_speed,
    }


def record_course(recorder: Recorder, name: str, course: Course) -> None:
    """The course in rollout ``name``'s 3D view: cones (orange), lane lines and centre line."""
    cones, _ = course.cones()
    recorder.scene(name, "cones", points=cones, color=(255, 140, 0))
    edges = [
        np.array([[lane.start_m, y], [lane.end_m, y]])
        for lane in course.lanes
        for y in (lane.left_m, lane.right_m)
    ]
    recorder.scene(name, "lanes", strips=edges, color=(240, 240, 240))
    centre = np.column_stack([course.centre_x_m, course.centre_y_m])[::10]
    recorder.scene(name, "centre_line", strips=[centre], color=(90, 90, 90))


def plot_course(
    course: Course,
    paths: Mapping[str, np.ndarray],
    path: Path,
    *,
    title: str = "",
) -> None:
    """Top view: cones (red where any run hit them), lane lines, the centre line and each run's
    path (poses (T, 3)), with the car's outline every 10 m along the course."""
    fig = Figure(figsize=(12, 4.5))
    ax = fig.subplots()
    cones, _ = course.cones()
    ax.plot(course.centre_x_m, course.centre_y_m, "k--", lw=0.8, label="centre line")
    for lane in course.lanes:
        for y in (lane.left_m, lane.right_m):
            ax.plot([lane.start_m, lane.end_m], [y, y], color="0.6", lw=0.6)
    length_m, width_m = course.vehicle_length_m, course.vehicle_width_m
    hit_any = np.zeros(len(cones), dtype=bool)
    for i, (label, poses) in enumerate(paths.items()):
        poses = np.asarray(poses, dtype=float)
        hit = cones_hit(course, poses, length_m, width_m)
        hit_any |= hit
        color = f"C{i}"
        ax.plot(poses[:, 0], poses[:, 1], color=color, lw=1.3, label=f"{label} ({hit.sum()} hit)")
        marks = np.searchsorted(poses[:, 0], np.arange(course.entry_m, course.exit_m, 10.0))
        for corners in body_corners(poses[marks[marks < len(poses)]], length_m, width_m):
            ax.fill(corners[:, 0], corners[:, 1], color=color, alpha=0.12, lw=0)
    standing, down = cones[~hit_any], cones[hit_any]
    ax.scatter(standing[:, 0], standing[:, 1], s=14, marker="^", color="orange", label="cone")
    if len(down):
        ax.scatter(down[:, 0], down[:, 1], s=30, marker="^", color="red", label="cone hit")
    ax.set_xlim(course.entry_m - 15, course.exit_m + 15)
    lanes_y = [y for lane in course.lanes for y in (lane.left_m, lane.right_m)]
    ax.set_ylim(max(-8.0, min(lanes_y) - 2.0), min(12.0, max(lanes_y) + 2.0))
    ax.set_aspect(3.0)  # Y stretched: the course is 150 m long and 6 m wide
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m] (3× stretched)")
    if title:
        ax.set_title(title)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.3), fontsize=8, ncols=4)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path)
