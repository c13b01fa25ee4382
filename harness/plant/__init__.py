"""The MuJoCo sedan plant: ``Sedan`` steps (vx, vy, yaw_rate) under (steer_wheel_deg, pedal).

Owns MuJoCo, the tyre model's C callback and the one closed loop (``rollout``). May import
``harness.core`` only.
"""

from harness.core.contracts import INPUT_NAMES, STATE_NAMES
from harness.plant.params import SedanParams
from harness.plant.sedan import Sedan

__all__ = ["INPUT_NAMES", "STATE_NAMES", "Sedan", "SedanParams"]
