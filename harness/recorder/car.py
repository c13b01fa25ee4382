"""The car drawn in a recording's 3D view: body, cabin and four wheels (the front pair steers),
moved along the run's poses, with its path on the ground."""

from __future__ import annotations

import numpy as np
import rerun as rr

from harness.recorder.entities import child

# The drawn car: the body the lane change judges against the cones (harness/references/course.py,
# centred on the pose), a cabin on it, and wheels where models/mjcf/sedan.xml puts them.
CAR_LENGTH_M = 4.6
CAR_WIDTH_M = 1.8
CAR_HEIGHT_M = 1.45
WHEEL_RADIUS_M = 0.31  # the MJCF's tyre
FRONT_AXLE_X_M = 1.15  # ahead of the pose (the MJCF's corner_fl)
REAR_AXLE_X_M = -1.55  # (corner_rl)
_BODY_Z_M = (0.30, 0.95)  # bottom and top of the lower body
# The cabin: centre and half sizes, on the body up to the car's height (the MJCF's, lowered).
_CABIN = (
    (-0.2, 0.0, (_BODY_Z_M[1] + CAR_HEIGHT_M) / 2),
    (1.2, 0.8, (CAR_HEIGHT_M - _BODY_Z_M[1]) / 2),
)
_WHEEL_WIDTH_M = 0.2
# Wheel centres a little outboard of the MJCF's 0.775 m so that they show beside the body.
_WHEEL_Y_M = CAR_WIDTH_M / 2 - 0.05
_CHASE_HALF_EXTENT_M = 8.0


def log_car(
    rec: rr.RecordingStream,
    root: str,
    index: rr.TimeColumn,
    pose: np.ndarray,
    road_wheel_rad: np.ndarray,
) -> None:
    """A car (body, cabin, four wheels) moved by a Transform3D column; static full path.

    The front wheels turn about their vertical axis by ``road_wheel_rad`` (the mean of the
    two: Ackermann is not drawn), at every sample of the simulation time.
    """
    # Z up (X forward, Y left) on the 3D view origin, so the ground grid is the XY plane.
    rec.log(root, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True, strict=True)
    car = child(root, "car")
    _log_body(rec, car)
    _log_wheels(rec, car, index, road_wheel_rad)
    # Invisible points around the car: the 3D view, when it starts tracking an entity,
    # zooms to 1.5x that entity's bounding sphere. Tracking this anchor (instead of the
    # 4.6 m box) gives a chase camera ~17 m away that shows the car and the road around it.
    half = _CHASE_HALF_EXTENT_M
    rec.log(
        f"{car}/chase_anchor",
        rr.Points3D(
            [[half, half, 0.0], [-half, -half, CAR_HEIGHT_M]],
            radii=0.001,
            colors=[(0, 0, 0, 0)],
        ),
        static=True,
        strict=True,
    )
    translation = np.zeros((pose.shape[0], 3))
    translation[:, :2] = pose[:, :2]
    rec.send_columns(
        car,
        indexes=[index],
        columns=rr.Transform3D.columns(
            translation=translation, quaternion=yaw_quaternions(pose[:, 2])
        ),
        strict=True,
    )
    path = translation.copy()
    path[:, 2] = 0.02  # just above the ground grid so it is not z-fighting
    rec.log(
        child(root, "path"),
        rr.LineStrips3D([path], colors=[(220, 50, 50)], radii=0.08),
        static=True,
        strict=True,
    )


def _log_body(rec: rr.RecordingStream, car: str) -> None:
    """The lower body and the cabin, two static boxes."""
    bottom, top = _BODY_Z_M
    cabin_center, cabin_half = _CABIN
    rec.log(
        child(car, "body"),
        rr.Boxes3D(
            half_sizes=[[CAR_LENGTH_M / 2, CAR_WIDTH_M / 2, (top - bottom) / 2], cabin_half],
            centers=[[0.0, 0.0, (top + bottom) / 2], cabin_center],
            colors=[(30, 144, 255), (20, 60, 110)],
            fill_mode="solid",
        ),
        static=True,
        strict=True,
    )


def _log_wheels(
    rec: rr.RecordingStream, car: str, index: rr.TimeColumn, road_wheel_rad: np.ndarray
) -> None:
    """Four wheels where the MJCF puts them; the front pair turned by the road-wheel angle."""
    # A cylinder's axis is its local Z: a quarter turn about X lays it along the axle (Y).
    axle = rr.Quaternion(xyzw=[np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)])
    n = len(road_wheel_rad)
    front = {"fl": FRONT_AXLE_X_M, "fr": FRONT_AXLE_X_M}
    for corner, x in (front | {"rl": REAR_AXLE_X_M, "rr": REAR_AXLE_X_M}).items():
        wheel = child(car, f"wheel_{corner}")
        rec.log(
            wheel,
            rr.Cylinders3D(
                lengths=[_WHEEL_WIDTH_M],
                radii=[WHEEL_RADIUS_M],
                quaternions=[axle],
                colors=[(75, 75, 75)],  # tyres, light enough to show on the dark ground
                fill_mode="solid",
            ),
            static=True,
            strict=True,
        )
        center = [x, _WHEEL_Y_M if corner.endswith("l") else -_WHEEL_Y_M, WHEEL_RADIUS_M]
        if corner in front:
            rec.send_columns(
                wheel,
                indexes=[index],
                columns=rr.Transform3D.columns(
                    translation=np.tile(center, (n, 1)),
                    quaternion=yaw_quaternions(road_wheel_rad),
                ),
                strict=True,
            )
        else:
            rec.log(wheel, rr.Transform3D(translation=center), static=True, strict=True)


def yaw_quaternions(yaw: np.ndarray) -> np.ndarray:
    """(N, 4) xyzw quaternions of rotations by ``yaw`` [rad] about the vertical (Z) axis."""
    quat = np.zeros((len(yaw), 4))
    quat[:, 2] = np.sin(yaw / 2.0)
    quat[:, 3] = np.cos(yaw / 2.0)
    return quat


def chase_eye(pose: np.ndarray) -> dict[str, tuple[float, float, float]]:
    """Initial 3D camera: behind, left of and above the car at its first finite pose.

    The view tracks the car, keeping this offset, so the box stays readable instead of
    being a dot in a whole-trajectory overview (zoom out with the mouse for that).
    """
    finite = np.flatnonzero(np.all(np.isfinite(pose), axis=1))
    x0, y0, yaw0 = pose[finite[0]] if finite.size else (0.0, 0.0, 0.0)
    c, s = float(np.cos(yaw0)), float(np.sin(yaw0))
    back, left, up = 20.0, 8.0, 12.0
    return {
        "eye_position": (
            float(x0) - back * c - left * s,
            float(y0) - back * s + left * c,
            up,
        ),
        "eye_target": (float(x0), float(y0), CAR_HEIGHT_M / 2),
    }
