"""The names of the model's states and of the sedan's inputs, in the order every array holds them.

Their own module so that both the contracts (:mod:`harness.core.contracts`) and the episodes
(:mod:`harness.core.episode`) read them without either importing the other.
"""

from __future__ import annotations

__all__ = ["INPUT_NAMES", "STATE_NAMES"]

STATE_NAMES: tuple[str, ...] = ("vx", "vy", "yaw_rate")  # m/s, m/s, rad/s
INPUT_NAMES: tuple[str, ...] = ("steer_wheel_deg", "pedal")  # deg; throttle >= 0, -MPa < 0
