"""The MuJoCo sedan plant: ``Sedan`` steps (vx, vy, yaw_rate) under (steer_wheel_deg, pedal)."""

from harness.plant.params import SedanParams
from harness.plant.sedan import INPUT_NAMES, STATE_NAMES, Sedan

__all__ = ["INPUT_NAMES", "STATE_NAMES", "Sedan", "SedanParams"]
