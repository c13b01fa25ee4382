"""Episodes and the normalization every learner and evaluator shares."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from harness.core.contracts import INPUT_NAMES, STATE_NAMES
from harness.core.limits import BRAKE_MAX_MPA, THROTTLE_MAX

POSE_NAMES = ("X", "Y", "yaw")


@dataclass(frozen=True)
class Episode:
    """One drive sampled at the control period, physical units (SI; steering in degrees).

    ``states[k]`` is x_k = (vx, vy, yaw_rate) at ``time_s[k]``; ``inputs[k]`` = u_k is held from
    t_k to t_{k+1}, so x_{k+1} = f(x_k, u_k) for k < T - 1 (the last input has no successor).
    """

    name: str
    time_s: np.ndarray  # (T,)
    states: np.ndarray  # (T, 3)
    inputs: np.ndarray  # (T, 2): steer_wheel_deg, pedal
    poses: np.ndarray  # (T, 3): X, Y, yaw for display

    def __post_init__(self) -> None:
        length = len(self.time_s)
        for field_name in ("states", "inputs", "poses"):
            if len(getattr(self, field_name)) != length:
                raise ValueError(f"episode {self.name}: {field_name} has a different length")

    def __len__(self) -> int:
        return len(self.time_s)

    def non_finite(self) -> str | None:
        """What in this episode is NaN or infinite, as a clause naming the array, the column and
        the time of the first such value (e.g. ``inputs has 1 non-finite value (steer_wheel_deg
        at t = 2.31 s)``); None when every value is finite.

        A NaN in a stored drive does not stop where it is read: it turns the normalizer, the fit
        or an RMSE into NaN (or ``null`` in JSON) far from the file that holds it.
        """
        columns = {"states": STATE_NAMES, "inputs": INPUT_NAMES, "poses": POSE_NAMES}
        for field_name in ("time_s", "states", "inputs", "poses"):
            values = np.asarray(getattr(self, field_name))
            bad = ~np.isfinite(values)
            count = int(bad.sum())
            if not count:
                continue
            row, *column = np.argwhere(bad)[0]
            time = float(self.time_s[row]) if np.isfinite(self.time_s[row]) else None
            where = f"t = {time:.2f} s" if time is not None else f"row {row}"
            if column:
                names = columns[field_name]
                name = names[column[0]] if column[0] < len(names) else f"column {column[0]}"
                where = f"{name} at {where}"
            plural = "value" if count == 1 else "values"
            first = "" if count == 1 else "first: "
            return f"{field_name} has {count} non-finite {plural} ({first}{where})"
        return None


def pedal_scale(pedal: np.ndarray) -> np.ndarray:
    """Signed pedal in [-1, 1]: throttle / 0.2 above zero, brake pressure / 9.1 MPa below.

    The paper's per-step increments (throttle 0.004, brake 0.18 MPa) are both ~0.02 on this scale,
    and throttle no longer occupies 2 % of the pedal's range after min-max normalization.
    """
    pedal = np.asarray(pedal, dtype=float)
    return np.where(pedal >= 0, pedal / THROTTLE_MAX, pedal / BRAKE_MAX_MPA)


def pedal_unscale(scaled: np.ndarray) -> np.ndarray:
    scaled = np.asarray(scaled, dtype=float)
    return np.where(scaled >= 0, scaled * THROTTLE_MAX, scaled * BRAKE_MAX_MPA)


@dataclass(frozen=True)
class MinMaxNormalizer:
    """The paper's min-max normalization (x - x_min) / (x_max - x_min), fitted on training data.

    Inputs are first mapped to (steer_wheel_deg, signed pedal scale); see :func:`pedal_scale`.
    """

    state_min: np.ndarray
    state_max: np.ndarray
    input_min: np.ndarray
    input_max: np.ndarray

    @classmethod
    def fit(cls, episodes: Sequence[Episode]) -> MinMaxNormalizer:
        if not episodes:
            raise ValueError("cannot fit a normalizer on zero episodes")
        for episode in episodes:  # a NaN would pass min() and max() on to every model and file
            problem = episode.non_finite()
            if problem is not None:
                raise ValueError(f"cannot fit a normalizer: episode {episode.name} {problem}")
        states = np.concatenate([e.states for e in episodes])
        inputs = np.concatenate([_input_features(e.inputs) for e in episodes])
        return cls(states.min(0), states.max(0), inputs.min(0), inputs.max(0))

    def _span(self, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        return np.where(high - low > 1e-12, high - low, 1.0)

    def states(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x) - self.state_min) / self._span(self.state_min, self.state_max)

    def states_inverse(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(z) * self._span(self.state_min, self.state_max) + self.state_min

    def inputs(self, u: np.ndarray) -> np.ndarray:
        return (_input_features(u) - self.input_min) / self._span(self.input_min, self.input_max)

    def inputs_inverse(self, v: np.ndarray) -> np.ndarray:
        features = np.asarray(v) * self._span(self.input_min, self.input_max) + self.input_min
        return np.stack([features[..., 0], pedal_unscale(features[..., 1])], axis=-1)

    def to_dict(self) -> dict[str, list[float]]:
        return {k: np.asarray(getattr(self, k)).tolist() for k in self.__dataclass_fields__}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> MinMaxNormalizer:
        return cls(**{k: np.asarray(values[k], dtype=float) for k in cls.__dataclass_fields__})


def _input_features(u: np.ndarray) -> np.ndarray:
    u = np.asarray(u, dtype=float)
    return np.stack([u[..., 0], pedal_scale(u[..., 1])], axis=-1)
