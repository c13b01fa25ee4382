"""One side of the pedal at a time: throttle or brake, the other only when the plan needs it.

A model with one slope for the signed pedal (every model affine in u: EDMD, Deep EDMD, input
EDMD) has the throttle and the brake wrong in opposite directions: on ``data=default`` at
80 km/h Deep EDMD's brake decelerates 5-6x less per MPa than the sedan's, its throttle 1.7-2.1x
more (3 seeds). A QP on such a model shaves a 0.1 m/s overshoot with the brake, which bites
several times harder than planned, and the throttle catches it: the main controller changed
between throttle and brake 8 times in the 7 s of a constant-speed lane change
(docs/findings/smooth_driving.md).

A driver lifts off before braking. :class:`PedalSides` keeps the plan on the side the pedal is
on (throttle and coasting, or brake and releasing): the pedal may go back to released, never
past it, until the plan on this side, the best the QP found, still misses the reference's speed
within the horizon by more than ``margin_mps`` (faster than asked on the throttle side, slower
on the brake side); the next step then opens the other side. The bounds are the QP's hard input
bounds of that step (``CondensedQP.set_input_bounds``), so the optimum on a side is exact.
"""

from __future__ import annotations

import numpy as np

from harness.core.contracts import INPUT_NAMES
from harness.core.episode import MinMaxNormalizer

PEDAL = INPUT_NAMES.index("pedal")  # the pedal's column of the inputs (steer_wheel_deg, pedal)


def pedal_frame(normalizer: MinMaxNormalizer) -> tuple[float, float, float]:
    """(the released pedal, normalized; vx's min and range, m/s): where a controller in the
    model's normalized units finds the pedal's sides and the speed."""
    released = float(normalizer.inputs(np.zeros(len(INPUT_NAMES)))[PEDAL])
    vx_min = float(normalizer.state_min[0])
    return released, vx_min, max(float(normalizer.state_max[0]) - vx_min, 1e-9)


class PedalSides:
    """The side the pedal may use this step, and when to open the other.

    Args:
        margin_mps: the speed error (m/s) the plan may keep on one side before the other opens.
        released: the released pedal, normalized (the boundary between the sides).
        vx_span: the normalizer's vx range (m/s): predicted and reference speeds are normalized.
    """

    def __init__(self, margin_mps: float, released: float, vx_span: float) -> None:
        self.margin = float(margin_mps) / float(vx_span)  # normalized
        self.released = float(released)
        self.braking = False

    @classmethod
    def of(cls, margin_mps: float, normalizer: MinMaxNormalizer) -> PedalSides:
        """The sides of a model's normalized pedal (its released point and vx range)."""
        released, _, vx_span = pedal_frame(normalizer)
        return cls(margin_mps, released, vx_span)

    def reset(self, v_prev: np.ndarray) -> None:
        """A run starts on the side its first pedal is on (released: the throttle's)."""
        self.braking = bool(v_prev[PEDAL] < self.released)

    def bounds(
        self, v_min: np.ndarray, v_max: np.ndarray, v_prev: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The step's input bounds: ``v_min``/``v_max`` with the pedal held to its side. A pedal
        still on the other side (the step it changed sides) may come back as slowly as its
        increments allow: the bound is where it is, not the released pedal."""
        low, high = np.array(v_min, dtype=float), np.array(v_max, dtype=float)
        pedal = float(v_prev[PEDAL])
        if self.braking:
            high[PEDAL] = min(high[PEDAL], max(self.released, pedal))
        else:
            low[PEDAL] = max(low[PEDAL], min(self.released, pedal))
        return low, high

    def update(self, predicted_vx: np.ndarray, reference_vx: np.ndarray) -> None:
        """After a step's plan (normalized speeds over the horizon): open the other side when
        this one's best plan misses the reference by more than the margin."""
        error = np.asarray(predicted_vx, dtype=float) - np.asarray(reference_vx, dtype=float)
        if self.braking and np.max(-error) > self.margin:
            self.braking = False
        elif not self.braking and np.max(error) > self.margin:
            self.braking = True
