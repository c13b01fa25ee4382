"""How smoothly a closed loop drove, beside how well it tracked: ``tracking…quality``.

Tracking RMSE and cones do not see a controller that passes by stabbing the brake or sawing at
the wheel. Each measure here is computed from the run's own samples (period ``dt``); SI units
but the steering wheel's degrees:

- ``steer_rate_rms_deg_s``, ``steer_rate_peak_deg_s``: the steering-wheel rate, the first
  difference of the wheel angle over ``dt``;
- ``steering_reversals_per_min``: sign changes of the steering-wheel rate, counted over the
  samples where its magnitude exceeds ``STEER_RATE_THRESHOLD_DEG_S`` (slower corrections are
  no reversal a passenger feels), per minute of the run;
- ``pedal_changes_per_min``: changes between throttle (pedal > ``PEDAL_DEAD_BAND``) and brake
  (pedal < -``PEDAL_DEAD_BAND``, in -MPa), the released pedal between them not counted, per
  minute; ``brake_time_share``: the fraction of samples on the brake;
- ``long_jerk_rms_mps3``: RMS of d²vx/dt² (second differences); ``lat_jerk_rms_mps3``: RMS of
  the rate of a_y = dvy/dt + vx·r; ``lat_accel_peak_mps2``: the largest |a_y|;
- ``steer_increment_limit_share``, ``pedal_increment_limit_share``: for a controller that bounds
  its increments (``RateLimited``), the share of steps whose change of the input is at its bound
  (within ``AT_LIMIT``) or past it (the slack): a controller that lives there is bang-bang.

Ride comfort is judged on such quantities: a jerk of about 1-2 m/s³ is the comfort limit
commonly taken for road vehicles, and ISO 2631-1 weighs whole-body vibration by frequency, which
a steering or pedal saw at a few hertz excites (docs/guide/control.md keeps the measured values).
"""

from __future__ import annotations

import numpy as np

STEER_RATE_THRESHOLD_DEG_S = 20.0  # a steering-wheel rate below it is no reversal
PEDAL_DEAD_BAND = 0.02  # |pedal| below it is released (throttle fraction, or MPa of brake)
AT_LIMIT = 0.99  # an increment of at least this share of its bound is at the bound


def reversals(rate: np.ndarray, threshold: float, where: np.ndarray | None = None) -> int:
    """Sign changes of ``rate`` among its samples with |rate| > ``threshold``; with ``where``
    (a mask of ``rate``'s samples) only the changes that land on a sample it holds."""
    fast = np.abs(rate) > threshold
    signs = np.sign(rate[fast])
    changes = signs[1:] != signs[:-1]
    if where is not None:
        changes &= np.asarray(where, dtype=bool)[fast][1:]
    return int(np.count_nonzero(changes))


def pedal_changes(pedal: np.ndarray, dead_band: float = PEDAL_DEAD_BAND) -> int:
    """Changes between throttle and brake, the released pedal between them ignored."""
    side = np.where(pedal > dead_band, 1, np.where(pedal < -dead_band, -1, 0))
    pressed = side[side != 0]
    return int(np.count_nonzero(pressed[1:] != pressed[:-1]))


def _rates(
    states: np.ndarray, inputs: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steering-wheel rate (T-1), lateral acceleration (T), longitudinal jerk (T-2) and
    lateral jerk (T-1), each as the module docstring defines it."""
    steer_rate = np.diff(inputs[:, 0]) / dt
    vx, vy, r = states[:, 0], states[:, 1], states[:, 2]
    lat_accel = np.gradient(vy, dt) + vx * r if len(vy) > 1 else vx * r
    return steer_rate, lat_accel, np.diff(vx, 2) / dt**2, np.diff(lat_accel) / dt


def quality_series(
    states: np.ndarray, inputs: np.ndarray, dt: float
) -> dict[str, np.ndarray | dict[str, np.ndarray]]:
    """The recording's quality panel: the steering-wheel rate (deg/s) and the two jerks (m/s³)
    at every sample (the differences put at their later sample, NaN where there is none)."""
    states, inputs = np.asarray(states, dtype=float), np.asarray(inputs, dtype=float)
    steer_rate, _, long_jerk, lat_jerk = _rates(states, inputs, dt)

    def padded(values: np.ndarray) -> np.ndarray:
        return np.concatenate([np.full(len(states) - len(values), np.nan), values])

    return {
        "steering_wheel_rate_deg_s": padded(steer_rate),
        "jerk_mps3": {"longitudinal": padded(long_jerk), "lateral": padded(lat_jerk)},
    }


def control_quality(
    states: np.ndarray,
    inputs: np.ndarray,
    dt: float,
    increment_shares: np.ndarray | None = None,
) -> dict[str, float]:
    """The measures of the module docstring for a run of (T, 3) states (vx, vy, r) and (T, 2)
    inputs (steering-wheel angle in degrees, pedal) sampled every ``dt`` seconds;
    ``increment_shares``: (T - 1, 2) each step's change of each input as a share of the bound
    the controller put on it (``RateLimited``), if it has one."""
    states, inputs = np.asarray(states, dtype=float), np.asarray(inputs, dtype=float)
    minutes = max(len(states) - 1, 1) * dt / 60.0
    steer_rate, lat_accel, long_jerk, lat_jerk = _rates(states, inputs, dt)

    def rms(values: np.ndarray) -> float:
        return float(np.sqrt(np.mean(values**2))) if values.size else 0.0

    shares = {}
    if increment_shares is not None:
        at_limit = np.asarray(increment_shares, dtype=float) >= AT_LIMIT
        share = at_limit.mean(axis=0) if len(at_limit) else np.zeros(inputs.shape[1])
        shares = {
            "steer_increment_limit_share": float(share[0]),
            "pedal_increment_limit_share": float(share[1]),
        }
    return shares | {
        "steer_rate_rms_deg_s": rms(steer_rate),
        "steer_rate_peak_deg_s": float(np.max(np.abs(steer_rate), initial=0.0)),
        "steering_reversals_per_min": reversals(steer_rate, STEER_RATE_THRESHOLD_DEG_S) / minutes,
        "pedal_changes_per_min": pedal_changes(inputs[:, 1]) / minutes,
        "brake_time_share": float(np.mean(inputs[:, 1] < -PEDAL_DEAD_BAND)),
        "long_jerk_rms_mps3": rms(long_jerk),
        "lat_jerk_rms_mps3": rms(lat_jerk),
        "lat_accel_peak_mps2": float(np.max(np.abs(lat_accel), initial=0.0)),
    }
