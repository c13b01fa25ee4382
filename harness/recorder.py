"""Rerun logging for every rollout of the project, behind one small interface.

Why a single module: the plant, the characterization app and the training code all
produce the same kind of data (time, vehicle state, driver inputs, pose). Logging them
in one place keeps entity paths, units, colors and the viewer layout identical across
recordings, so two ``.rrd`` files can be opened side by side and compared.

Entity layout of a rollout called ``name`` (all series on the ``sim_time`` duration
timeline, in seconds)::

    {name}/state/<state_name>             scalar per sample (SI units): the actual state
    {name}/state/<state_name>/reference   its reference, when the rollout tracks one
    {name}/state/<state_name>/<overlay>   a series drawn on the state's plot (a prediction)
    {name}/error/<state_name>             actual - reference, when the rollout tracks one
    {name}/input/<input_name>             scalar per sample (deg, pedal fraction / -MPa)
    {name}/extra/<key>                    scalar(s) per sample
    {name}/car                            moved by a Transform3D column (the pose)
    {name}/car/body                       static Boxes3D: body and cabin
    {name}/car/wheel_<fl|fr|rl|rr>        static Cylinders3D; the front pair steers
    {name}/path                           static LineStrips3D of the whole trajectory

Every plotted line has a name (``SeriesLines``): a state's plot reads ``reference``,
``actual`` and the overlays' keys; the error plot ``<state> error``.

:class:`Recorder` is the null recorder (selected with ``recorder=none``);
:class:`RerunRecorder` writes a ``.rrd`` file. Both are built the same way from Hydra
(``_partial_: true``) and then called with ``path=...``; ``conf/recorder/rerun.yaml``
gives the plant's steering ratio, so the drawn front wheels turn by the road-wheel angle.
"""

from __future__ import annotations

import logging
import os
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import NamedTuple, Self

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

__all__ = [
    "CAR_HEIGHT_M",
    "CAR_LENGTH_M",
    "CAR_WIDTH_M",
    "FRONT_AXLE_X_M",
    "MAX_VIEWS",
    "MIN_STATE_SPAN",
    "REAR_AXLE_X_M",
    "WHEEL_RADIUS_M",
    "Recorder",
    "RerunRecorder",
]

log = logging.getLogger(__name__)

# Views the default layout holds at most: a blueprint of about 40 rollout tabs (320 views) made
# the viewer (0.41) refuse the whole recording ("Data source finished without loading a
# recording"), 30 tabs (240 views) loaded (synthetic recordings;
# docs/reference/reliability_run.md). Tabs
# go in priority order until the next would pass it; every rollout stays in the recording.
MAX_VIEWS = 200
# The narrowest y range of a state's plot (SI): what a driver would call a small change of it.
MIN_STATE_SPAN = {"vx": 2.0, "vy": 0.5, "yaw_rate": 0.2}

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

SIM_TIMELINE = "sim_time"
_CHASE_HALF_EXTENT_M = 8.0

# Colors (RGB) cycled over series so that e.g. vx is always the same color in every recording.
_PALETTE: tuple[tuple[int, int, int], ...] = (
    (228, 26, 28),
    (55, 126, 184),
    (77, 175, 74),
    (152, 78, 163),
    (255, 127, 0),
    (166, 86, 40),
    (247, 129, 191),
    (153, 153, 153),
)
# Units shown in plot titles for the project's standard series names.
_UNITS = {
    "vx": "m/s",
    "vy": "m/s",
    "yaw_rate": "rad/s",
    "steer_wheel_deg": "deg",
    "pedal": "throttle 0..0.2 / -brake MPa",
}
_STATE_OFFSET = 0
_INPUT_OFFSET = 4
_EXTRA_OFFSET = 3
_OVERLAY_OFFSET = 3
_REFERENCE = "reference"
_REFERENCE_COLOR = (235, 235, 235)  # light on the viewer's dark plots, under the colored actual
_STEER = "steer_wheel_deg"  # the input that turns the drawn front wheels


def _color(i: int) -> tuple[int, int, int]:
    """Palette color ``i`` (cycled), so a given series keeps its color across recordings."""
    return _PALETTE[i % len(_PALETTE)]


def _title(name: str) -> str:
    """Plot title: the series name, with its unit when it is a standard one."""
    unit = _UNITS.get(name)
    return f"{name} [{unit}]" if unit else name


def _root(path: str) -> str:
    """Entity path from a user path whose ``/`` separate levels (rollout name, series path).

    Every segment is escaped so names with spaces, dots or brackets stay one segment, and
    the same string is used for logging and in the blueprint (they must match exactly).
    """
    segments = [seg for seg in str(path).split("/") if seg]
    if not segments:
        raise ValueError(f"entity path is empty: {path!r}")
    return "/" + "/".join(rr.escape_entity_path_part(seg) for seg in segments)


def _child(root: str, *parts: str) -> str:
    """Append single (escaped) segments to an already escaped entity path."""
    return "/".join([root, *(rr.escape_entity_path_part(str(p)) for p in parts)])


def _as_time(name: str, time_s: np.ndarray) -> np.ndarray:
    """Validate a 1-D, finite time vector."""
    t = np.asarray(time_s)
    if t.ndim != 1:
        raise ValueError(f"{name} must be 1-D (N,), got shape {t.shape}")
    if t.shape[0] == 0:
        raise ValueError(f"{name} is empty")
    if not (np.issubdtype(t.dtype, np.integer) or np.issubdtype(t.dtype, np.floating)):
        raise ValueError(f"{name} must be numeric, got dtype {t.dtype}")
    if np.issubdtype(t.dtype, np.floating) and not np.all(np.isfinite(t)):
        raise ValueError(f"{name} contains NaN or inf")
    return t


def _as_matrix(name: str, x: np.ndarray, n: int, cols: int | None) -> np.ndarray:
    """Return ``x`` as float64 (n, cols) (or (n, k) with any k>=1 when cols is None)."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1 and cols in (None, 1):
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] != n or (cols is not None and a.shape[1] != cols):
        want = f"({n}, {cols})" if cols is not None else f"({n},) or ({n}, k)"
        raise ValueError(f"{name} must have shape {want}, got {np.shape(x)}")
    if a.shape[1] == 0:
        raise ValueError(f"{name} has no columns, got shape {np.shape(x)}")
    return a


def _time_column(timeline: str, t: np.ndarray) -> rr.TimeColumn:
    """Integer times become a sequence timeline, float times a duration in seconds."""
    if np.issubdtype(t.dtype, np.integer):
        return rr.TimeColumn(timeline, sequence=t.astype(np.int64))
    # Round to whole nanoseconds ourselves: rerun truncates, which turns 0.29 s into 0.289999999 s.
    ns = np.round(t.astype(np.float64) * 1e9).astype(np.int64)
    return rr.TimeColumn(timeline, duration=ns.astype("timedelta64[ns]"))


def _fitted_range(values: np.ndarray, symmetric: bool = False) -> tuple[float, float] | None:
    """Plot range of the values actually logged, 10 % margin; symmetric about 0 when asked.

    Given to the plot so that its scale is the data's (None: no finite value, let the viewer fit).
    """
    v = values[np.isfinite(values)]
    if v.size == 0:
        return None
    lo, hi = float(v.min()), float(v.max())
    if symmetric:
        lo, hi = -max(abs(lo), abs(hi)), max(abs(lo), abs(hi))
    margin = 0.1 * (hi - lo) if hi > lo else max(abs(hi), 1.0) * 0.1
    return lo - margin, hi + margin


def _state_range(name: str, values: np.ndarray) -> tuple[float, float] | None:
    """A state plot's y range: the values' (10 % margin), at least ``MIN_STATE_SPAN`` wide about
    their middle, so that a car holding 80 km/h within 0.1 m/s draws a flat line, not a crisis
    scaled to fill the plot."""
    fitted = _fitted_range(values)
    span = MIN_STATE_SPAN.get(name)
    if fitted is None or span is None or fitted[1] - fitted[0] >= span:
        return fitted
    middle = 0.5 * (fitted[0] + fitted[1])
    return middle - 0.5 * span, middle + 0.5 * span


def _input_plot(name: str, values: np.ndarray) -> tuple[str, tuple[float, float] | None]:
    """Title and y range of an input's plot: the range the input was used over.

    The steering is centred on straight ahead and its peak is in the title: on a plot a few
    hundred pixels high the viewer labels only the zero tick of a +-70 deg range.
    """
    if name != _STEER:
        return _title(name), _fitted_range(values)
    finite = values[np.isfinite(values)]
    peak = f", peak {np.max(np.abs(finite)):.0f}" if finite.size else ""
    return _title(name) + peak, _fitted_range(values, symmetric=True)


def _yaw_quaternions(yaw: np.ndarray) -> np.ndarray:
    """(N, 4) xyzw quaternions of rotations by ``yaw`` [rad] about the vertical (Z) axis."""
    quat = np.zeros((len(yaw), 4))
    quat[:, 2] = np.sin(yaw / 2.0)
    quat[:, 3] = np.cos(yaw / 2.0)
    return quat


def _on_ground(xy: np.ndarray, height: float = 0.02) -> np.ndarray:
    """(K, 2) X, Y -> (K, 3) at ``height`` m above the ground grid (no z-fighting)."""
    return np.column_stack([xy, np.full(len(xy), height)])


def _chase_eye(pose: np.ndarray) -> dict[str, tuple[float, float, float]]:
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


@dataclass
class _RolloutInfo:
    """What the blueprint needs to know about one logged rollout."""

    name: str
    root: str
    states: list[str]
    inputs: list[str]
    extras: list[str]
    has_pose: bool
    # What each state's plot draws besides the state (reference, overlays), as entity paths.
    on_state_plot: dict[str, list[str]] = field(default_factory=dict)
    has_reference: bool = False
    input_plots: dict[str, tuple[str, tuple[float, float] | None]] = field(default_factory=dict)
    state_ranges: dict[str, tuple[float, float] | None] = field(default_factory=dict)
    priority: int = 0
    eye_position: tuple[float, float, float] | None = None
    eye_target: tuple[float, float, float] | None = None


def _tab_views(r: _RolloutInfo) -> int:
    """Views in a rollout's tab: the car, one plot per state, per input, the error, per extra."""
    return (
        int(r.has_pose) + len(r.states) + len(r.input_plots) + int(r.has_reference) + len(r.extras)
    )


@dataclass
class _SeriesInfo:
    """What the blueprint needs to know about one ``series()`` path."""

    root: str
    timeline: str
    keys: list[str] = field(default_factory=list)


class _Rollout(NamedTuple):
    """The arguments of :meth:`Recorder.rollout`, as one value handed to the writer."""

    name: str
    time_s: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    poses: np.ndarray | None
    state_names: Sequence[str]
    input_names: Sequence[str]
    extra: Mapping[str, np.ndarray | Mapping[str, np.ndarray]] | None
    priority: int
    reference: np.ndarray | None
    overlays: Mapping[str, np.ndarray] | None


class Recorder:
    """Null recorder: accepts every call and writes nothing.

    It is also the base class, so calling code never needs ``if recorder is not None``.
    The constructor accepts (and ignores) the arguments of :class:`RerunRecorder` so that
    both Hydra partials are called the same way: ``partial(path=run_dir / "x.rrd")``.
    """

    def __init__(
        self,
        path: str | os.PathLike[str] | None = None,
        application_id: str = "koopman_vehicle",
        steering_ratio: float | None = None,
    ) -> None:
        """Ignore all arguments (kept for call compatibility with RerunRecorder)."""
        del path, application_id, steering_ratio

    def rollout(
        self,
        name: str,
        time_s: np.ndarray,
        states: np.ndarray,
        inputs: np.ndarray,
        poses: np.ndarray | None = None,
        state_names: Sequence[str] = ("vx", "vy", "yaw_rate"),
        input_names: Sequence[str] = ("steer_wheel_deg", "pedal"),
        extra: Mapping[str, np.ndarray | Mapping[str, np.ndarray]] | None = None,
        priority: int = 0,
        reference: np.ndarray | None = None,
        overlays: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """Log one rollout of N samples under entity path ``name``.

        Args:
            name: Rollout name, used as the entity-path root (may contain ``/``).
            time_s: (N,) simulation time in seconds.
            states: (N, len(state_names)) vehicle state, SI units (m/s, m/s, rad/s).
            inputs: (N, len(input_names)) steering-wheel angle [deg] and pedal
                (>=0 throttle fraction, <0 minus brake pressure [MPa]).
            poses: (N, 3) world pose (X [m], Y [m], yaw [rad]), or None.
            state_names: Names of the state columns.
            input_names: Names of the input columns.
            extra: Further named (N,) or (N, k) series, logged under ``{name}/extra/<key>``,
                one plot each; a mapping of named (N,) columns is one plot of those lines.
            priority: Tabs go in descending priority, then in logged order: a run's result
                (the closed-loop tracking, the lane change first) is what the recording opens on,
                and what the layout keeps when it reaches MAX_VIEWS (the drives a run learns
                from have -1: shown last).
            reference: (N, len(state_names)) states the rollout tracks: drawn on each state's
                plot (``reference`` beside ``actual``), and actual - reference on one error plot.
            overlays: Further (N, len(state_names)) series drawn on each state's plot under
                their key (a model's prediction); NaN where there is none.
        """
        self._log_rollout(
            _Rollout(
                name,
                time_s,
                states,
                inputs,
                poses,
                state_names,
                input_names,
                extra,
                priority,
                reference,
                overlays,
            )
        )

    def _log_rollout(self, rollout: _Rollout) -> None:
        """What :meth:`rollout` logs (here: nothing); a recorder that writes overrides it."""
        del rollout

    def scene(
        self,
        name: str,
        key: str,
        *,
        strips: Sequence[np.ndarray] = (),
        points: np.ndarray | None = None,
        color: tuple[int, int, int] = (160, 160, 160),
    ) -> None:
        """Static world-frame geometry shown in rollout ``name``'s 3D view (a course's lane
        lines as ``strips`` of (K, 2) X, Y in m; its cones as (C, 2) ``points``)."""

    def path_ahead(self, name: str, time_s: np.ndarray, paths: np.ndarray) -> None:
        """A path that changes every sample (T, K, 2: X, Y in m), drawn in rollout ``name``'s
        3D view at each time: the controller's predicted path ahead of the car."""

    def series(
        self,
        path: str,
        time_s: np.ndarray,
        values: Mapping[str, np.ndarray],
        timeline: str = SIM_TIMELINE,
    ) -> None:
        """Log named scalar series under ``path/<key>`` (e.g. loss curves).

        Args:
            path: Entity path root for the series (may contain ``/``).
            time_s: (N,) times; integer dtype gives a sequence timeline (epoch, step),
                float dtype a duration timeline in seconds.
            values: Mapping key -> (N,) or (N, k) values.
            timeline: Timeline name.
        """

    def close(self) -> None:
        """Finish the recording (no-op here)."""

    def __enter__(self) -> Self:
        """Use as ``with recorder as rec:`` so the file is finalized even on errors."""
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        """Close on exit; what was logged before an exception is kept (useful to debug it)."""
        self.close()


class RerunRecorder(Recorder):
    """Recorder writing a Rerun ``.rrd`` file through a private recording stream.

    Data goes to ``<path>.tmp`` while logging; :meth:`close` adds the default blueprint,
    flushes, finalizes the file and atomically renames it to ``path``. A run that dies
    therefore leaves at most a ``.tmp`` file, never a truncated ``.rrd``.

    A private :class:`rerun.RecordingStream` (not the global one) is used so that several
    recorders can live in one process (tests, parallel rollouts) without mixing data.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        application_id: str = "koopman_vehicle",
        steering_ratio: float | None = None,
    ) -> None:
        """Open the stream and start writing to the temporary file.

        Args:
            path: Final ``.rrd`` path; parent directories are created.
            application_id: Rerun application id (the viewer groups recordings by it).
            steering_ratio: Steering-wheel angle per road-wheel angle of the plant (its
                ``plant.steering.steering_ratio``): the drawn front wheels turn by
                ``steer_wheel_deg / steering_ratio``. None draws them straight ahead.
        """
        super().__init__()
        if steering_ratio is not None and not (np.isfinite(steering_ratio) and steering_ratio > 0):
            raise ValueError(f"steering_ratio must be a positive number (got {steering_ratio!r})")
        self.steering_ratio = steering_ratio
        self.path = Path(path)
        self.tmp_path = self.path.with_name(self.path.name + ".tmp")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._rollouts: list[_RolloutInfo] = []
        self._series: dict[str, _SeriesInfo] = {}
        self._timeline_kinds: dict[str, str] = {SIM_TIMELINE: "duration"}
        self._closed = False
        # Explicit random recording id: without it, every stream of the process shares one id.
        self._rec = rr.RecordingStream(application_id, recording_id=uuid.uuid4())
        self._rec.save(self.tmp_path)
        self._rec.send_recording_name(self.path.stem)

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` has been called."""
        return self._closed

    def _check_open(self) -> rr.RecordingStream:
        """The stream, or RuntimeError: logging after close() would silently be lost."""
        if self._closed:
            raise RuntimeError(f"recorder for {self.path} is closed")
        return self._rec

    def _send_scalars(
        self,
        entity: str,
        index: rr.TimeColumn,
        values: np.ndarray,
        names: Sequence[str],
        colors: Sequence[tuple[int, int, int]],
        width: float = 1.5,
    ) -> None:
        """Bulk-send a (N, k) scalar block plus static line styling for the plot legend."""
        rec = self._check_open()
        scalars = values[:, 0] if values.shape[1] == 1 else values
        rec.send_columns(
            entity, indexes=[index], columns=rr.Scalars.columns(scalars=scalars), strict=True
        )
        rec.log(
            entity,
            rr.SeriesLines(names=list(names), colors=list(colors), widths=[width] * len(names)),
            static=True,
            strict=True,
        )

    def _log_rollout(self, rollout: _Rollout) -> None:
        """Log one rollout; see :meth:`Recorder.rollout`. Raises ValueError on bad shapes."""
        (
            name,
            time_s,
            states,
            inputs,
            poses,
            state_names,
            input_names,
            extra,
            priority,
            reference,
            overlays,
        ) = rollout
        self._check_open()
        if not isinstance(name, str):
            raise ValueError(f"name must be a string, got {name!r}")
        root = _root(name)
        if any(r.root == root for r in self._rollouts):
            raise ValueError(f"rollout {name!r} was already logged in {self.path}")

        # Validate everything before sending anything, so a bad call logs nothing.
        t = _as_time("time_s", time_s)
        n = t.shape[0]
        if np.issubdtype(t.dtype, np.integer):
            t = t.astype(np.float64)
        state_names = [str(s) for s in state_names]
        input_names = [str(s) for s in input_names]
        x = _as_matrix("states", states, n, len(state_names))
        u = _as_matrix("inputs", inputs, n, len(input_names))
        pose = None if poses is None else _as_matrix("poses", poses, n, 3)
        extras: dict[str, np.ndarray] = {}
        extra_lines: dict[str, list[str]] = {}
        for k, v in (extra or {}).items():
            if isinstance(v, Mapping):  # named columns on one plot
                extra_lines[str(k)] = [str(c) for c in v]
                columns = [_as_matrix(f"extra[{k!r}][{c!r}]", v[c], n, 1) for c in v]
                extras[str(k)] = np.hstack(columns) if columns else np.zeros((n, 0))
            else:
                extras[str(k)] = _as_matrix(f"extra[{k!r}]", v, n, None)
        ns = len(state_names)
        ref = None if reference is None else _as_matrix("reference", reference, n, ns)
        over = {
            str(k): _as_matrix(f"overlays[{k!r}]", v, n, ns) for k, v in (overlays or {}).items()
        }
        if _REFERENCE in over:
            raise ValueError(f"overlays may not be called {_REFERENCE!r}: pass it as reference=")

        index = _time_column(SIM_TIMELINE, t)
        # Beside a reference or an overlay the state is the "actual" line; alone, its own name.
        actual = "actual" if ref is not None or over else None
        on_plot: dict[str, list[str]] = {}
        for i, s in enumerate(state_names):
            entity = _child(root, "state", s)
            color = _color(_STATE_OFFSET + i)
            self._send_scalars(entity, index, x[:, i : i + 1], [actual or s], [color], width=2.0)
            on_plot[s] = []
            if ref is not None:
                on_plot[s].append(_child(entity, _REFERENCE))
                self._send_scalars(
                    on_plot[s][-1], index, ref[:, i : i + 1], [_REFERENCE], [_REFERENCE_COLOR]
                )
                self._send_scalars(
                    _child(root, "error", s),
                    index,
                    x[:, i : i + 1] - ref[:, i : i + 1],
                    [f"{s} error"],
                    [color],
                )
            for j, (key, v) in enumerate(over.items()):
                on_plot[s].append(_child(entity, key))
                self._send_scalars(
                    on_plot[s][-1], index, v[:, i : i + 1], [key], [_color(_OVERLAY_OFFSET + j)]
                )
        for i, s in enumerate(input_names):
            self._send_scalars(
                _child(root, "input", s), index, u[:, i : i + 1], [s], [_color(_INPUT_OFFSET + i)]
            )
        for j, (key, v) in enumerate(extras.items()):
            k = v.shape[1]
            names = extra_lines.get(key) or ([key] if k == 1 else [f"{key}[{c}]" for c in range(k)])
            colors = [_color(_EXTRA_OFFSET + j + c) for c in range(k)]
            self._send_scalars(_child(root, "extra", key), index, v, names, colors)
        if pose is not None:
            steer = u[:, input_names.index(_STEER)] if _STEER in input_names else None
            self._log_car(root, index, pose, steer)

        drawn = [x, *([] if ref is None else [ref]), *over.values()]  # on the state plots
        self._rollouts.append(
            _RolloutInfo(
                name=name,
                root=root,
                states=state_names,
                inputs=input_names,
                extras=list(extras),
                has_pose=pose is not None,
                on_state_plot=on_plot,
                has_reference=ref is not None,
                input_plots={s: _input_plot(s, u[:, i]) for i, s in enumerate(input_names)},
                state_ranges={
                    s: _state_range(s, np.concatenate([a[:, i] for a in drawn]))
                    for i, s in enumerate(state_names)
                },
                priority=priority,
                **({} if pose is None else _chase_eye(pose)),
            )
        )

    def _log_car(
        self, root: str, index: rr.TimeColumn, pose: np.ndarray, steer_deg: np.ndarray | None
    ) -> None:
        """A car (body, cabin, four wheels) moved by a Transform3D column; static full path.

        The front wheels turn about their vertical axis by the road-wheel angle,
        ``steer_deg / steering_ratio`` (the mean of the two: Ackermann is not drawn), at every
        sample of the simulation time.
        """
        rec = self._check_open()
        # Z up (X forward, Y left) on the 3D view origin, so the ground grid is the XY plane.
        rec.log(root, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True, strict=True)
        car = _child(root, "car")
        bottom, top = _BODY_Z_M
        cabin_center, cabin_half = _CABIN
        rec.log(
            _child(car, "body"),
            rr.Boxes3D(
                half_sizes=[[CAR_LENGTH_M / 2, CAR_WIDTH_M / 2, (top - bottom) / 2], cabin_half],
                centers=[[0.0, 0.0, (top + bottom) / 2], cabin_center],
                colors=[(30, 144, 255), (20, 60, 110)],
                fill_mode="solid",
            ),
            static=True,
            strict=True,
        )
        # A cylinder's axis is its local Z: a quarter turn about X lays it along the axle (Y).
        axle = rr.Quaternion(xyzw=[np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)])
        n = pose.shape[0]
        road_wheel = (
            np.zeros(n)
            if steer_deg is None or self.steering_ratio is None
            else np.nan_to_num(np.deg2rad(steer_deg) / self.steering_ratio)
        )
        front = {"fl": FRONT_AXLE_X_M, "fr": FRONT_AXLE_X_M}
        for corner, x in (front | {"rl": REAR_AXLE_X_M, "rr": REAR_AXLE_X_M}).items():
            wheel = _child(car, f"wheel_{corner}")
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
                        translation=np.tile(center, (n, 1)), quaternion=_yaw_quaternions(road_wheel)
                    ),
                    strict=True,
                )
            else:
                rec.log(wheel, rr.Transform3D(translation=center), static=True, strict=True)
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
        translation = np.zeros((n, 3))
        translation[:, :2] = pose[:, :2]
        rec.send_columns(
            car,
            indexes=[index],
            columns=rr.Transform3D.columns(
                translation=translation, quaternion=_yaw_quaternions(pose[:, 2])
            ),
            strict=True,
        )
        path = translation.copy()
        path[:, 2] = 0.02  # just above the ground grid so it is not z-fighting
        rec.log(
            _child(root, "path"),
            rr.LineStrips3D([path], colors=[(220, 50, 50)], radii=0.08),
            static=True,
            strict=True,
        )

    def scene(
        self,
        name: str,
        key: str,
        *,
        strips: Sequence[np.ndarray] = (),
        points: np.ndarray | None = None,
        color: tuple[int, int, int] = (160, 160, 160),
    ) -> None:
        """See :meth:`Recorder.scene`; slightly above the ground grid, like the car's path."""
        rec = self._check_open()
        entity = _child(_root(name), "scene", key)
        if strips:
            lifted = [_on_ground(_as_matrix("strip", strip, len(strip), 2)) for strip in strips]
            rec.log(entity, rr.LineStrips3D(lifted, colors=[color], radii=0.05), static=True)
        if points is not None:
            cones = _on_ground(_as_matrix("points", points, len(points), 2), height=0.35)
            rec.log(entity, rr.Points3D(cones, colors=[color], radii=0.18), static=True)

    def path_ahead(self, name: str, time_s: np.ndarray, paths: np.ndarray) -> None:
        """See :meth:`Recorder.path_ahead`; one column send, rows without a finite point skipped."""
        rec = self._check_open()
        t = _as_time("time_s", time_s).astype(np.float64)
        paths = np.asarray(paths, dtype=np.float64)
        if paths.ndim != 3 or paths.shape[0] != t.shape[0] or paths.shape[2] != 2:
            raise ValueError(f"paths must be (T={t.shape[0]}, K, 2), got {paths.shape}")
        keep = np.all(np.isfinite(paths), axis=(1, 2))
        if not keep.any():
            return
        strips = [_on_ground(path, height=0.04) for path in paths[keep]]
        rec.send_columns(
            _child(_root(name), "predicted_path"),
            indexes=[_time_column(SIM_TIMELINE, t[keep])],
            columns=rr.LineStrips3D.columns(strips=strips),
            strict=True,
        )
        rec.log(
            _child(_root(name), "predicted_path"),
            rr.LineStrips3D.from_fields(colors=[(120, 220, 120)], radii=0.06),
            static=True,
        )

    def series(
        self,
        path: str,
        time_s: np.ndarray,
        values: Mapping[str, np.ndarray],
        timeline: str = SIM_TIMELINE,
    ) -> None:
        """Log scalar series; see :meth:`Recorder.series`. Raises ValueError on bad shapes."""
        self._check_open()
        if not isinstance(path, str):
            raise ValueError(f"path must be a string, got {path!r}")
        if not values:
            raise ValueError("values is empty")
        root = _root(path)
        t = _as_time("time_s", time_s)
        kind = "sequence" if np.issubdtype(t.dtype, np.integer) else "duration"
        known = self._timeline_kinds.setdefault(timeline, kind)
        if known != kind:
            raise ValueError(
                f"timeline {timeline!r} is a {known} timeline, but time_s of dtype {t.dtype} "
                f"would make it a {kind} timeline"
            )
        info = self._series.get(root)
        if info is not None and info.timeline != timeline:
            raise ValueError(f"series {path!r} already uses timeline {info.timeline!r}")
        blocks = {
            str(k): _as_matrix(f"values[{k!r}]", v, t.shape[0], None) for k, v in values.items()
        }

        index = _time_column(timeline, t)
        if info is None:
            info = self._series[root] = _SeriesInfo(root=root, timeline=timeline)
        for key, v in blocks.items():
            if key not in info.keys:
                info.keys.append(key)
            j = info.keys.index(key)
            k = v.shape[1]
            names = [key] if k == 1 else [f"{key}[{c}]" for c in range(k)]
            colors = [_color(j + c) for c in range(k)]
            self._send_scalars(_child(root, key), index, v, names, colors)

    def blueprint(self) -> rrb.Blueprint | None:
        """Default viewer layout for what has been logged so far (None if nothing was).

        One tab per rollout: 3D car + path on the left, one plot per state in the middle
        (with its reference and overlays), one plot per input, the tracking error and one per
        extra on the right. Series get one tab with one plot per ``series()`` path. Time axes
        of all plots are linked so zooming is shared.
        """
        tabs: list[rrb.Container | rrb.View] = []
        link = rrb.TimeAxis(link="LinkToGlobal")
        legend = rrb.PlotLegend(corner="LeftTop")
        count, left_out = len(self._series), []  # views; the series tab's are kept first
        for r in sorted(self._rollouts, key=lambda r: -r.priority):  # stable: logged order
            size = _tab_views(r)
            if count + size > MAX_VIEWS:
                left_out.append(r.name)
                continue
            count += size
            # Each state's plot lists its lines by path: the reference is drawn where it is.
            state_views = [
                rrb.TimeSeriesView(
                    origin=_child(r.root, "state", s),
                    contents=[_child(r.root, "state", s), *r.on_state_plot.get(s, [])],
                    name=_title(s),
                    axis_x=link,
                    axis_y=rrb.ScalarAxis(range=r.state_ranges.get(s)),
                    plot_legend=legend,
                )
                for s in r.states
            ]
            other_views = [
                rrb.TimeSeriesView(
                    origin=_child(r.root, "input", s),
                    name=title,
                    axis_x=link,
                    axis_y=rrb.ScalarAxis(range=y_range),
                    plot_legend=legend,
                )
                for s, (title, y_range) in r.input_plots.items()
            ]
            if r.has_reference:
                other_views.append(
                    rrb.TimeSeriesView(
                        origin=_child(r.root, "error"),
                        name="error: actual - reference",
                        axis_x=link,
                        plot_legend=legend,
                    )
                )
            other_views += [
                rrb.TimeSeriesView(
                    origin=_child(r.root, "extra", k), name=k, axis_x=link, plot_legend=legend
                )
                for k in r.extras
            ]
            columns: list[rrb.Container | rrb.View] = []
            shares: list[float] = []
            if r.has_pose:
                columns.append(
                    rrb.Spatial3DView(
                        origin=r.root,
                        contents=[
                            f"{r.root}/car/**",
                            f"{r.root}/path",
                            f"{r.root}/scene/**",
                            f"{r.root}/predicted_path",
                        ],
                        name="car",
                        line_grid=rrb.LineGrid3D(visible=True, spacing=1.0),
                        eye_controls=rrb.EyeControls3D(
                            tracking_entity=f"{r.root}/car/chase_anchor",
                            position=r.eye_position,
                            look_target=r.eye_target,
                        ),
                    )
                )
                shares.append(1.5)
            columns += [rrb.Vertical(*state_views), rrb.Vertical(*other_views)]
            shares += [1.0, 1.0]
            tabs.append(rrb.Horizontal(*columns, column_shares=shares, name=r.name))
        if self._series:
            views = [
                rrb.TimeSeriesView(origin=s.root, name=s.root.lstrip("/"))
                for s in self._series.values()
            ]
            tabs.append(rrb.Grid(*views, name="series"))
        if left_out:
            log.info(
                "%s: the default layout shows %d of %d rollouts (at most %d views); the other "
                "%d are in the recording, under their names: %s",
                self.path.name,
                len(self._rollouts) - len(left_out),
                len(self._rollouts),
                MAX_VIEWS,
                len(left_out),
                ", ".join(left_out),
            )
        if not tabs:
            return None
        timeline = SIM_TIMELINE if self._rollouts else next(iter(self._series.values())).timeline
        return rrb.Blueprint(
            rrb.Tabs(*tabs, active_tab=0),
            rrb.TimePanel(timeline=timeline, state="collapsed"),
            rrb.SelectionPanel(state="collapsed"),
            rrb.BlueprintPanel(state="collapsed"),
        )

    def close(self) -> None:
        """Send the blueprint, finalize the file and move it to its final path (idempotent).

        The blueprint is built here, from the complete list of rollouts and series, and
        sent as default + active blueprint: it lands in the same ``.rrd`` as a blueprint
        store. The stream is flushed (blocking) and disconnected, which writes the RRD
        footer and closes the file, before the atomic rename (``os.replace``).
        """
        if self._closed:
            return
        self._closed = True
        rec = self._rec
        bp = self.blueprint()
        if bp is not None:
            rec.send_blueprint(bp, make_active=True, make_default=True)
        rec.flush()
        rec.disconnect()
        self.tmp_path.replace(self.path)
