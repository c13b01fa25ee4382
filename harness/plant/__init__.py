"""The MuJoCo sedan plant: ``Sedan`` steps (vx, vy, yaw_rate) under (steer_wheel_deg, pedal)."""

from harness.interfaces import INPUT_NAMES, STATE_NAMES
from harness.plant.params import SedanParams
from harness.plant.sedan import Sedan

__all__ = ["INPUT_NAMES", "STATE_NAMES", "Sedan", "SedanParams"]
