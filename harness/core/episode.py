"""Episodes and the normalization every learner and evaluator shares."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from harness.core.limits import BRAKE_MAX_MPA, THROTTLE_MAX
from harness.core.names import INPUT_NAMES, STATE_NAMES

POSE_NAMES = ("X", "Y", "yaw")


# What an input is, for a model that knows physics (the single-track baseline): the steering at
# the steering wheel or at the road wheel (unit deg or rad), a drive (force, torque or throttle:
# more of it accelerates), a brake (more of it decelerates, whatever its unit), or the sedan's
# signed pedal (drive above zero, brake below).
STEERING_ROLES = ("steering_wheel", "road_wheel")
ROLES = (*STEERING_ROLES, "drive", "brake", "pedal")
ANGLE_UNITS = {"deg": math.pi / 180.0, "rad": 1.0}


@dataclass(frozen=True)
class InputChannel:
    """One input column as the models see it: its name and the gains that turn it into the
    feature they are fitted in (``value * gain_positive`` where value >= 0, ``value *
    gain_negative`` below). A dataset describes its inputs with these: the sedan's pedal is
    throttle opening above zero and brake pressure below, each scaled to [-1, 1]; a column of a
    user's log is taken as it is (gains 1).

    ``role`` (one of :data:`ROLES`) and ``unit`` say what the input is, for the physics
    baseline and the figures; they describe the column, they do not change its values, so two
    channels that differ only in them compare equal (a model file from before roles were
    described is the same model).
    """

    name: str
    gain_positive: float = 1.0
    gain_negative: float = 1.0
    role: str | None = dataclasses.field(default=None, compare=False)
    unit: str | None = dataclasses.field(default=None, compare=False)

    def __post_init__(self) -> None:
        check_role(f"input {self.name}", self.role, self.unit)

    def feature(self, value: np.ndarray) -> np.ndarray:
        value = np.asarray(value, dtype=float)
        return np.where(value >= 0, value * self.gain_positive, value * self.gain_negative)

    def value(self, feature: np.ndarray) -> np.ndarray:
        feature = np.asarray(feature, dtype=float)
        return np.where(feature >= 0, feature / self.gain_positive, feature / self.gain_negative)

    def to_dict(self) -> dict[str, Any]:
        """Name and gains; role and unit where declared (older files have neither)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


def check_role(key: str, role: str | None, unit: str | None) -> None:
    """A role of :data:`ROLES` or none; a steering input's unit is an angle's (deg or rad)."""
    if role is not None and role not in ROLES:
        raise ValueError(f"{key}: role must be one of {', '.join(ROLES)} (got {role!r})")
    if role in STEERING_ROLES and unit not in ANGLE_UNITS:
        raise ValueError(f"{key}: a steering input's unit must be deg or rad (got {unit!r})")
    if unit is not None and not (isinstance(unit, str) and unit):
        raise ValueError(f"{key}: unit must be a word such as N*m, bar or deg (got {unit!r})")


# The sedan's inputs (``harness.core.contracts.INPUT_NAMES``): the paper's per-step increments
# (throttle 0.004, brake 0.18 MPa) are both ~0.02 on the pedal's signed scale, and throttle no
# longer occupies 2 % of the pedal's range after min-max normalization.
SEDAN_INPUTS: tuple[InputChannel, ...] = (
    InputChannel(INPUT_NAMES[0], role="steering_wheel", unit="deg"),
    InputChannel(
        INPUT_NAMES[1],
        1.0 / THROTTLE_MAX,
        1.0 / BRAKE_MAX_MPA,
        role="pedal",
        unit="throttle 0..0.2 / -brake MPa",
    ),
)


def sedan_inputs(pedal_gains: Sequence[float] | None = None) -> tuple[InputChannel, ...]:
    """The sedan's inputs with the pedal's feature in other units: ``pedal_gains`` = (feature
    per unit of throttle opening, feature per MPa of brake pressure); None: :data:`SEDAN_INPUTS`
    (the signed scale, 1/0.2 and 1/9.1)."""
    if pedal_gains is None:
        return SEDAN_INPUTS
    positive, negative = (float(gain) for gain in pedal_gains)
    pedal = dataclasses.replace(SEDAN_INPUTS[1], gain_positive=positive, gain_negative=negative)
    return (SEDAN_INPUTS[0], pedal)


def is_sedan(channels: Sequence[InputChannel]) -> bool:
    """Whether ``channels`` are the sedan's inputs, whatever the pedal's gains."""
    return tuple(c.name for c in channels) == tuple(c.name for c in SEDAN_INPUTS)


def channels_from_dicts(described: Sequence[Mapping[str, Any]] | None) -> tuple[InputChannel, ...]:
    """The channels :meth:`InputChannel.to_dict` wrote; none (a file from before inputs were
    described) are the sedan's, and a sedan channel written before roles gets its role."""
    if described is None:
        return SEDAN_INPUTS
    sedan = {channel.name: channel for channel in SEDAN_INPUTS}
    channels = []
    for values in described:
        channel = InputChannel(**dict(values))
        known = sedan.get(channel.name)
        if channel.role is None and known is not None and channel == known:
            channel = known
        channels.append(channel)
    return tuple(channels)


@dataclass(frozen=True)
class Episode:
    """One drive sampled at the control period, physical units (SI; steering in degrees).

    ``states[k]`` is x_k = (vx, vy, yaw_rate) at ``time_s[k]``; ``inputs[k]`` = u_k is held from
    t_k to t_{k+1}, so x_{k+1} = f(x_k, u_k) for k < T - 1 (the last input has no successor).
    """

    name: str
    time_s: np.ndarray  # (T,)
    states: np.ndarray  # (T, 3)
    inputs: np.ndarray  # (T, m): for the sedan steer_wheel_deg, pedal
    poses: np.ndarray  # (T, 3): X, Y, yaw for display (zeros where a log has none)
    channels: tuple[InputChannel, ...] = SEDAN_INPUTS  # what each input column is

    def __post_init__(self) -> None:
        length = len(self.time_s)
        for field_name in ("states", "inputs", "poses"):
            if len(getattr(self, field_name)) != length:
                raise ValueError(f"episode {self.name}: {field_name} has a different length")
        if np.ndim(self.inputs) == 2 and np.shape(self.inputs)[1] != len(self.channels):
            raise ValueError(
                f"episode {self.name}: inputs has {np.shape(self.inputs)[1]} columns for "
                f"{len(self.channels)} input channels ({', '.join(self.input_names)})"
            )

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(channel.name for channel in self.channels)

    def __len__(self) -> int:
        return len(self.time_s)

    def non_finite(self) -> str | None:
        """What in this episode is NaN or infinite, as a clause naming the array, the column and
        the time of the first such value (e.g. ``inputs has 1 non-finite value (steer_wheel_deg
        at t = 2.31 s)``); None when every value is finite.

        A NaN in a stored drive does not stop where it is read: it turns the normalizer, the fit
        or an RMSE into NaN (or ``null`` in JSON) far from the file that holds it.
        """
        columns = {"states": STATE_NAMES, "inputs": self.input_names, "poses": POSE_NAMES}
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
    """Signed pedal in [-1, 1]: throttle / 0.2 above zero, brake pressure / 9.1 MPa below."""
    return SEDAN_INPUTS[1].feature(pedal)


@dataclass(frozen=True)
class MinMaxNormalizer:
    """The paper's min-max normalization (x - x_min) / (x_max - x_min), fitted on training data.

    Inputs are first mapped to their features by the dataset's ``channels`` (for the sedan:
    steering-wheel degrees and the signed pedal scale, see :data:`SEDAN_INPUTS`); the channels
    travel with the normalizer, so a saved model knows its inputs' names and scaling.
    """

    state_min: np.ndarray
    state_max: np.ndarray
    input_min: np.ndarray
    input_max: np.ndarray
    channels: tuple[InputChannel, ...] = SEDAN_INPUTS

    @classmethod
    def fit(cls, episodes: Sequence[Episode]) -> MinMaxNormalizer:
        if not episodes:
            raise ValueError("cannot fit a normalizer on zero episodes")
        channels = episodes[0].channels
        for episode in episodes:  # a NaN would pass min() and max() on to every model and file
            problem = episode.non_finite()
            if problem is not None:
                raise ValueError(f"cannot fit a normalizer: episode {episode.name} {problem}")
            if episode.channels != channels:
                raise ValueError(
                    f"cannot fit a normalizer: episode {episode.name} has inputs "
                    f"({', '.join(episode.input_names)}), episode {episodes[0].name} "
                    f"({', '.join(episodes[0].input_names)})"
                )
        states = np.concatenate([e.states for e in episodes])
        features = input_features(np.concatenate([e.inputs for e in episodes]), channels)
        return cls(states.min(0), states.max(0), features.min(0), features.max(0), channels)

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(channel.name for channel in self.channels)

    # Derived once (a controller converts every step): the spans, and each input's gains.
    @functools.cached_property
    def _state_span(self) -> np.ndarray:
        return _span(self.state_min, self.state_max)

    @functools.cached_property
    def _input_span(self) -> np.ndarray:
        return _span(self.input_min, self.input_max)

    @functools.cached_property
    def _gains(self) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.array([c.gain_positive for c in self.channels], dtype=float),
            np.array([c.gain_negative for c in self.channels], dtype=float),
        )

    @property
    def state_span(self) -> np.ndarray:
        """Each state's max - min (1 where it never varied): normalized = (x - min) / span."""
        return self._state_span

    @property
    def input_span(self) -> np.ndarray:
        """Each input feature's max - min (1 where it never varied)."""
        return self._input_span

    def states(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x) - self.state_min) / self._state_span

    def states_inverse(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(z) * self._state_span + self.state_min

    def input_features(self, u: np.ndarray) -> np.ndarray:
        """The inputs ``u`` (..., m) in the units the models are fitted in (before min-max)."""
        return input_features(u, self.channels)

    def inputs(self, u: np.ndarray) -> np.ndarray:
        return (self.input_features(u) - self.input_min) / self._input_span

    def inputs_inverse(self, v: np.ndarray) -> np.ndarray:
        """Physical inputs of normalized ``v`` (..., m): :meth:`InputChannel.value` of every
        column at once (the same division, the same bits)."""
        features = np.asarray(v, dtype=float) * self._input_span + self.input_min
        positive, negative = self._gains
        return features / np.where(features >= 0, positive, negative)

    def to_dict(self) -> dict[str, Any]:
        values: dict[str, Any] = {k: np.asarray(getattr(self, k)).tolist() for k in _RANGES}
        values["inputs"] = [c.to_dict() for c in self.channels]
        return values

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> MinMaxNormalizer:
        """The normalizer :meth:`to_dict` wrote; one without ``inputs`` (written before inputs
        were described) is the sedan's."""
        ranges = {k: np.asarray(values[k], dtype=float) for k in _RANGES}
        return cls(**ranges, channels=channels_from_dicts(values.get("inputs")))

    def same_as(self, other: MinMaxNormalizer) -> bool:
        """Equal to the last bit: the same training drives give the same min and max."""
        return self.channels == other.channels and all(
            np.array_equal(getattr(self, k), getattr(other, k)) for k in _RANGES
        )


_RANGES = ("state_min", "state_max", "input_min", "input_max")


def _span(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """high - low, 1 where a column never varied (it maps to 0 rather than dividing by 0)."""
    return np.where(high - low > 1e-12, high - low, 1.0)


def input_features(u: np.ndarray, channels: Sequence[InputChannel]) -> np.ndarray:
    """Inputs ``u`` (..., m) as the features of ``channels`` (see :class:`InputChannel`)."""
    u = np.asarray(u, dtype=float)
    return np.stack([c.feature(u[..., j]) for j, c in enumerate(channels)], axis=-1)
