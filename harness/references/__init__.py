"""Tracking references: what the controllers follow, one class per ``conf/reference/`` config.

A reference is built once the plant and the test drives are known, as (T, 3) physical states
(vx, vy, yaw_rate), SI, one row per control step. The pipeline tracks every reference under
``task.references.<name>`` (``conf/task/pipeline.yaml``); adding one is a class with the two
members of :class:`Reference` plus a YAML file naming it with ``_target_``.

May import ``harness.core``, ``harness.output`` and ``harness.recorder``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from harness.core.episode import Episode
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
class Reference(Protocol):
    """What the pipeline asks of a reference: its label in the metrics, and its states."""

    def label(self, name: str, episodes: Sequence[Episode]) -> str:
        """The key of its run under ``tracking.references`` (``name`` is its config key)."""
        ...

    def build(self, dt: float, episodes: Sequence[Episode]) -> np.ndarray:
        """(T, 3) states (vx, vy, yaw_rate) at the plant's step ``dt``, from the test drives."""
        ...


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
