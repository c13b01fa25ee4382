"""A reference path on the ground, and where a car stands relative to it (the Frenet frame).

A path-following controller (``controller.reference: path``) needs three things a state
reference cannot give: how far the car is from the line (lateral error, m, positive to the
left of the direction of travel), how its heading differs from the line's (heading error, rad),
and how the line bends ahead (curvature, 1/m, positive turning left). :class:`ReferencePath`
holds a polyline sampled finely enough (the ISO course's centre line: every 5 cm) that the
nearest sample, refined on its segment, is the projection.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# After the first call the nearest point is searched from the last one: this far back (m) and
# this far ahead (m), so a path that comes back near itself is never confused with its return.
_SEARCH_BACK_M = 10.0
_SEARCH_AHEAD_M = 60.0


@dataclass(frozen=True)
class FrenetState:
    """Where a pose stands on a path: station (m along it), lateral and heading error."""

    station_m: float
    lateral_error_m: float  # > 0: the car is left of the line
    heading_error_rad: float  # car yaw minus the line's heading, wrapped to (-pi, pi]
    index: int  # nearest sample (the next search starts here)


@dataclass(frozen=True)
class ReferencePath:
    """A smooth path in the world frame (m): stations, points, heading and curvature."""

    station_m: np.ndarray  # (K,) arc length from the first point, increasing
    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray
    curvature_per_m: np.ndarray

    @classmethod
    def from_points(cls, x_m: np.ndarray, y_m: np.ndarray) -> ReferencePath:
        """The path through points (X, Y), at least 3, none repeated: heading and curvature
        by finite differences along the arc length."""
        x, y = np.asarray(x_m, dtype=float), np.asarray(y_m, dtype=float)
        if x.ndim != 1 or x.shape != y.shape or len(x) < 3:
            raise ValueError(f"a path needs matching 1-D X and Y of >= 3 points (got {x.shape})")
        steps = np.hypot(np.diff(x), np.diff(y))
        if not np.all(steps > 0):
            raise ValueError("a path's points must all differ from their neighbours")
        station = np.concatenate([[0.0], np.cumsum(steps)])
        dx, dy = np.gradient(x, station), np.gradient(y, station)
        heading = np.unwrap(np.arctan2(dy, dx))
        curvature = np.gradient(heading, station)
        return cls(station, x, y, heading, curvature)

    def locate(self, pose: np.ndarray, hint: int | None = None) -> FrenetState:
        """The pose (X, Y, yaw) relative to the path; ``hint``: the last call's ``index``.
        Scalars in Python floats: a controller calls this every step, and NumPy's scalar
        functions cost a microsecond each."""
        X, Y, yaw = np.asarray(pose, dtype=float).tolist()
        if hint is None:
            lo, hi = 0, len(self.station_m)
        else:
            s = float(self.station_m[hint])
            lo, hi = np.searchsorted(self.station_m, (s - _SEARCH_BACK_M, s + _SEARCH_AHEAD_M))
            hi += 1
        distance = (self.x_m[lo:hi] - X) ** 2 + (self.y_m[lo:hi] - Y) ** 2
        k = int(lo + distance.argmin())
        heading = float(self.heading_rad[k])
        cos, sin = math.cos(heading), math.sin(heading)
        dx, dy = X - float(self.x_m[k]), Y - float(self.y_m[k])
        error = yaw - heading
        return FrenetState(
            station_m=float(self.station_m[k]) + (cos * dx + sin * dy),
            lateral_error_m=-sin * dx + cos * dy,
            heading_error_rad=math.atan2(math.sin(error), math.cos(error)),
            index=k,
        )

    def curvature_at(self, station_m: np.ndarray) -> np.ndarray:
        """Curvature (1/m) at stations (held at the ends: straight beyond a straight end)."""
        return np.interp(station_m, self.station_m, self.curvature_per_m)
