"""The lane change judged by where the car went: cones, lateral deviation, exit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from harness.references import CourseReference, DoubleLaneChange, path_metrics, plot_course
from harness.references.course import Course, Lane, cones_hit

BODY = {"length_m": 4.6, "width_m": 1.8}


def centre_line_poses(course: Course, shift_m: float = 0.0) -> np.ndarray:
    x, y = course.centre_x_m, course.centre_y_m
    return np.stack([x, y + shift_m, np.arctan(np.gradient(y, x))], axis=1)


def constant_speed(poses: np.ndarray, speed_mps: float = 22.2) -> np.ndarray:
    return np.tile([speed_mps, 0.0, 0.0], (len(poses), 1))


@pytest.mark.parametrize("standard", ["iso3888_1", "iso3888_2"])
def test_the_reference_line_driven_exactly_clears_every_cone(standard: str) -> None:
    reference = DoubleLaneChange(standard=standard)
    assert isinstance(reference, CourseReference)
    course = reference.course()
    poses = centre_line_poses(course)
    metrics = path_metrics(course, poses, constant_speed(poses))
    assert metrics["passed"] and metrics["cones_hit"] == 0 and metrics["cones"] > 20
    assert metrics["max_lateral_deviation_m"] == pytest.approx(0.0, abs=1e-9)
    assert metrics["exit_heading_error_rad"] == pytest.approx(0.0, abs=1e-6)
    assert metrics["exit_speed_mps"] == 22.2


def test_the_iso_3888_1_lanes_scale_with_the_car_and_lane_3_is_offset() -> None:
    lanes = DoubleLaneChange(vehicle_width_m=2.0).course().lanes
    widths = [lane.left_m - lane.right_m for lane in lanes]
    np.testing.assert_allclose(widths, [1.1 * 2 + 0.25, 1.2 * 2 + 0.25, 1.3 * 2 + 0.25])
    assert [lane.end_m - lane.start_m for lane in lanes] == [15.0, 25.0, 15.0]
    assert (lanes[1].left_m + lanes[1].right_m) / 2 == pytest.approx(3.5)
    assert lanes[1].start_m - lanes[0].end_m == 30.0 and lanes[2].start_m - lanes[1].end_m == 25.0


def test_a_car_that_keeps_straight_knocks_down_lane_3s_near_cones_and_fails() -> None:
    course = DoubleLaneChange().course()
    poses = centre_line_poses(course) * [1.0, 0.0, 0.0]
    metrics = path_metrics(course, poses, constant_speed(poses))
    assert not metrics["passed"]
    assert metrics["max_lateral_deviation_m"] == pytest.approx(3.5, abs=1e-6)
    cones, sides = course.cones()
    hit = cones_hit(course, poses, **BODY)
    lane3 = (cones[:, 0] >= 65.0) & (cones[:, 0] <= 90.0)
    assert np.all(hit[lane3 & (sides < 0)]) and not np.any(hit[lane3 & (sides > 0)])
    assert metrics["cones_hit"] == int(np.sum(lane3 & (sides < 0)))


def test_a_cone_is_hit_by_the_body_not_the_centre() -> None:
    """Lane 2.2 m wide: a 1.8 m car 0.25 m off centre keeps its centre inside the lane (by
    0.85 m) but its body crosses the left line."""
    course = Course(np.array([0.0, 100.0]), np.zeros(2), (Lane("lane", 40.0, 60.0, -1.1, 1.1),))
    x = np.arange(0.0, 100.0, 0.1)
    for shift, hits in ((0.15, 0), (0.25, 1)):
        poses = np.stack([x, np.full_like(x, shift), np.zeros_like(x)], axis=1)
        metrics = path_metrics(course, poses, constant_speed(poses))
        assert (metrics["cones_hit"] > 0) == bool(hits)
        assert metrics["max_lateral_deviation_m"] == pytest.approx(shift)
    # yawed 8 degrees with its centre on the line: the corners reach 1.21 m sideways
    poses = np.stack([x, np.zeros_like(x), np.full_like(x, np.radians(8.0))], axis=1)
    assert path_metrics(course, poses, constant_speed(poses))["cones_hit"] > 0


def test_a_car_that_never_reaches_the_exit_does_not_pass() -> None:
    course = DoubleLaneChange().course()
    poses = centre_line_poses(course)[: len(course.centre_x_m) // 2]
    metrics = path_metrics(course, poses, constant_speed(poses))
    assert metrics["cones_hit"] == 0
    assert not metrics["reached_exit"] and not metrics["passed"]
    assert metrics["exit_speed_mps"] is None and metrics["exit_heading_error_rad"] is None


def test_the_top_view_draws_every_run(tmp_path: Path) -> None:
    course = DoubleLaneChange().course()
    runs = {"line": centre_line_poses(course), "off": centre_line_poses(course, 0.6)}
    plot_course(course, runs, tmp_path / "course.png")
    assert (tmp_path / "course.png").stat().st_size > 10_000


def test_the_course_survives_its_arrays() -> None:
    course = DoubleLaneChange().course()
    again = Course.from_arrays(course.as_arrays())
    np.testing.assert_array_equal(again.cones()[0], course.cones()[0])
    assert [(ln.start_m, ln.left_m) for ln in again.lanes] == [
        (ln.start_m, ln.left_m) for ln in course.lanes
    ]
