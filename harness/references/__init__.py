"""Tracking references: what the controllers follow, one class per ``conf/reference/`` config.

A reference is built once the plant and the test drives are known, as (T, 3) physical states
(vx, vy, yaw_rate), SI, one row per control step. The pipeline tracks every reference under
``task.references.<name>`` (``conf/task/pipeline.yaml``); adding one is a class with the two
members of :class:`harness.core.contracts.Reference` plus a YAML file naming it with ``_target_``.

May import ``harness.core``, ``harness.output`` and ``harness.recorder``.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from harness.core.contracts import Reference
from harness.core.reference_path import FrenetState, ReferencePath
from harness.references.course import Course, Lane, path_metrics, plot_course
from harness.references.episode import HeldOutEpisode, from_episode
from harness.references.iso3888 import (
    BicycleParams,
    DoubleLaneChange,
    double_lane_change,
    double_lane_change_course,
    double_lane_change_path,
    lane_offset_m,
)


@runtime_checkable
class CourseReference(Reference, Protocol):
    """A reference driven on a course (cones, centre line): its runs are also judged by where
    the car went (``path.*``, a top view) — the pipeline asks the reference, not its name."""

    def course(self) -> Course:
        """The course in the world frame of a run that starts at the origin heading along X."""
        ...


__all__ = [
    "BicycleParams",
    "Course",
    "CourseReference",
    "DoubleLaneChange",
    "FrenetState",
    "HeldOutEpisode",
    "Lane",
    "Reference",
    "ReferencePath",
    "double_lane_change",
    "double_lane_change_course",
    "double_lane_change_path",
    "from_episode",
    "lane_offset_m",
    "path_metrics",
    "plot_course",
]
