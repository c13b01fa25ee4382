"""The ISO 3888 double lane change as a tracking reference (``conf/reference/``).

:class:`DoubleLaneChange` builds the (T, 3) physical states (vx, vy, yaw_rate), SI, one row per
control step, that a car needs to drive an ISO 3888 double lane change at constant speed along a
smooth centreline; the standard handling test beside the paper's held-out test drives.

The lane change is specified as a path and turned into states: vx = v (constant), yaw rate =
v·κ(s) along the path, and vy from the linear bicycle model's steady-state sideslip at that yaw
rate, vy = r·(b - m·a·v² / (L·C_r)) (about -1.3·r for the sedan at 80 km/h; the rear axle
"steers" the car body outwards at speed). ``sideslip=False`` gives vy = 0 instead.

ISO geometry (lengths in m, W = vehicle width): the car enters lane 1, crosses to lane 3 offset
sideways, and returns to lane 5 on the original line.

=============  ========  ==========  ========  ==========  ========  ======================
standard       lane 1    gap 2       lane 3    gap 4       lane 5    lateral offset of lane 3
=============  ========  ==========  ========  ==========  ========  ======================
3888-1 (DLC)   15        30          25        25          15        3.5 (centres)
3888-2 (OA)    12        13.5        11        12.5        12        (1.1W + 0.25)/2 + 1 + (W + 1)/2
=============  ========  ==========  ========  ==========  ========  ======================

The centreline moves sideways along a quintic smootherstep (continuous curvature, so the yaw
rate has no steps) spanning each gap plus half of the lanes on either side (a driver starts
turning inside the lane). At 80 km/h the 3888-1 path peaks at 4.9 m/s² (0.5 g), inside the
sedan's 7.9 m/s²; 3888-2's short gaps need 17 m/s² there, beyond any road car (the test finds
the highest passable speed): 6.7 m/s² at 50 km/h, 5.4 m/s² at 45 km/h.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from harness.data.episode import Episode

_GEOMETRY = {
    "iso3888_1": (15.0, 30.0, 25.0, 25.0, 15.0),
    "iso3888_2": (12.0, 13.5, 11.0, 12.5, 12.0),
}


@dataclass(frozen=True)
class BicycleParams:
    """Linear single-track model of the sedan for the steady-state sideslip (SI).

    Defaults: the dry sedan of ``harness/plant`` (1500 kg, a = 1.15 m, b = 1.55 m; rear axle
    cornering stiffness 2 × 20 × 4000 N × sin(2·atan(Fz / 8000 N)) at Fz = 3134 N per tyre).
    """

    mass_kg: float = 1500.0
    cg_to_front_m: float = 1.15
    cg_to_rear_m: float = 1.55
    rear_cornering_stiffness_n_per_rad: float = 1.087e5

    def vy_per_yaw_rate_m(self, speed_mps: float) -> float:
        """vy / r at steady state: b - m·a·v² / (L·C_r)."""
        wheelbase = self.cg_to_front_m + self.cg_to_rear_m
        lateral = (
            self.mass_kg
            * self.cg_to_front_m
            * speed_mps**2
            / (wheelbase * self.rear_cornering_stiffness_n_per_rad)
        )
        return self.cg_to_rear_m - lateral


def lane_offset_m(standard: str, vehicle_width_m: float = 1.8) -> float:
    """Lateral offset between the centres of lanes 1 and 3."""
    if standard == "iso3888_1":
        return 3.5
    width = vehicle_width_m
    return (1.1 * width + 0.25) / 2 + 1.0 + (width + 1.0) / 2


def double_lane_change_path(
    standard: str = "iso3888_1",
    *,
    vehicle_width_m: float = 1.8,
    run_in_m: float = 20.0,
    run_out_m: float = 30.0,
    step_m: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Centreline (X, Y) in m through the ISO gates, with straight run-in and run-out."""
    if standard not in _GEOMETRY:
        raise ValueError(f"standard must be one of {sorted(_GEOMETRY)} (got {standard!r})")
    lane1, gap2, lane3, gap4, lane5 = _GEOMETRY[standard]
    offset = lane_offset_m(standard, vehicle_width_m)
    start = run_in_m
    # Transitions: from the middle of one lane to the middle of the next across the gap.
    out_from, out_to = start + lane1 / 2, start + lane1 + gap2 + lane3 / 2
    back_from, back_to = out_to, start + lane1 + gap2 + lane3 + gap4 + lane5 / 2
    x = np.arange(0.0, start + lane1 + gap2 + lane3 + gap4 + lane5 + run_out_m + step_m, step_m)
    y = offset * (_smootherstep(x, out_from, out_to) - _smootherstep(x, back_from, back_to))
    return x, y


def double_lane_change(
    speed_mps: float = 80 / 3.6,
    standard: str = "iso3888_1",
    *,
    dt: float = 0.01,
    vehicle_width_m: float = 1.8,
    sideslip: bool = True,
    bicycle: BicycleParams | None = None,
) -> np.ndarray:
    """(T, 3) states (vx, vy, yaw_rate) that drive the ISO double lane change at speed_mps."""
    if not speed_mps > 0:
        raise ValueError(f"speed_mps must be > 0 (got {speed_mps})")
    x, y = double_lane_change_path(standard, vehicle_width_m=vehicle_width_m)
    slope = np.gradient(y, x)
    curvature = np.gradient(slope, x) / (1 + slope**2) ** 1.5
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    s = np.arange(0.0, arc[-1], speed_mps * dt)
    yaw_rate = speed_mps * np.interp(s, arc, curvature)
    gain = (bicycle or BicycleParams()).vy_per_yaw_rate_m(speed_mps) if sideslip else 0.0
    return np.stack([np.full_like(s, speed_mps), gain * yaw_rate, yaw_rate], axis=1)


class DoubleLaneChange:
    """The ISO 3888 double lane change at constant ``speed_mps``; the same on every plant.

    A plain class, not a dataclass: Hydra keeps built objects in a config node, which would turn
    a dataclass back into a config.
    """

    def __init__(
        self,
        speed_mps: float = 80 / 3.6,
        standard: str = "iso3888_1",
        vehicle_width_m: float = 1.8,
        sideslip: bool = True,
    ) -> None:
        if not speed_mps > 0:
            raise ValueError(f"speed_mps must be > 0 (got {speed_mps})")
        if standard not in _GEOMETRY:
            raise ValueError(f"standard must be one of {sorted(_GEOMETRY)} (got {standard!r})")
        self.speed_mps, self.standard = speed_mps, standard
        self.vehicle_width_m, self.sideslip = vehicle_width_m, sideslip

    def label(self, name: str, episodes: Sequence[Episode]) -> str:
        """The config's name alone: the lane change does not depend on the drives."""
        return name

    def build(self, dt: float, episodes: Sequence[Episode]) -> np.ndarray:
        return double_lane_change(
            self.speed_mps,
            self.standard,
            dt=dt,
            vehicle_width_m=self.vehicle_width_m,
            sideslip=self.sideslip,
        )


def _smootherstep(x: np.ndarray, start: float, end: float) -> np.ndarray:
    """0 before start, 1 after end, 6p⁵ - 15p⁴ + 10p³ between: slope and curvature continuous.

    A continuous curvature keeps the yaw-rate reference continuous (a half-cosine would step
    it at both ends).
    """
    p = np.clip((x - start) / (end - start), 0.0, 1.0)
    return p**3 * (10.0 + p * (-15.0 + 6.0 * p))
