"""The recorder that writes a Rerun ``.rrd`` file (the entity layout: ``harness/recorder``)."""

from __future__ import annotations

import logging
import os
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from harness.recorder.base import Recorder, Rollout
from harness.recorder.car import chase_eye, log_car
from harness.recorder.entities import (
    SIM_TIMELINE,
    STEER,
    as_matrix,
    as_time,
    child,
    color,
    entity_root,
    on_ground,
    time_column,
)
from harness.recorder.layout import (
    RolloutInfo,
    SeriesInfo,
    blueprint,
    input_plot,
    state_range,
)

log = logging.getLogger(__name__)

# Palette offsets: each kind of line keeps its colors across recordings.
_STATE_OFFSET = 0
_INPUT_OFFSET = 4
_EXTRA_OFFSET = 3
_OVERLAY_OFFSET = 3
_REFERENCE = "reference"
_REFERENCE_COLOR = (235, 235, 235)  # light on the viewer's dark plots, under the colored actual


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
        self._rollouts: list[RolloutInfo] = []
        self._series: dict[str, SeriesInfo] = {}
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

    def _log_rollout(self, rollout: Rollout) -> None:
        """Log one rollout; see :meth:`Recorder.rollout`. Raises ValueError on bad shapes, before
        anything is sent (a bad call logs nothing)."""
        self._check_open()
        if not isinstance(rollout.name, str):
            raise ValueError(f"name must be a string, got {rollout.name!r}")
        root = entity_root(rollout.name)
        if any(r.root == root for r in self._rollouts):
            raise ValueError(f"rollout {rollout.name!r} was already logged in {self.path}")
        r = _Checked.of(rollout)
        index = time_column(SIM_TIMELINE, r.t)
        on_plot = self._send_states(root, index, r)
        for i, s in enumerate(r.input_names):
            self._send_scalars(
                child(root, "input", s), index, r.u[:, i : i + 1], [s], [color(_INPUT_OFFSET + i)]
            )
        for j, (key, v) in enumerate(r.extras.items()):
            k = v.shape[1]
            names = r.extra_lines.get(key) or (
                [key] if k == 1 else [f"{key}[{c}]" for c in range(k)]
            )
            colors = [color(_EXTRA_OFFSET + j + c) for c in range(k)]
            self._send_scalars(child(root, "extra", key), index, v, names, colors)
        if r.pose is not None:
            log_car(self._check_open(), root, index, r.pose, self._road_wheel(r))
        drawn = [r.x, *([] if r.ref is None else [r.ref]), *r.over.values()]  # on the state plots
        self._rollouts.append(
            RolloutInfo(
                name=rollout.name,
                root=root,
                states=r.state_names,
                inputs=r.input_names,
                extras=list(r.extras),
                has_pose=r.pose is not None,
                on_state_plot=on_plot,
                has_reference=r.ref is not None,
                input_plots={s: input_plot(s, r.u[:, i]) for i, s in enumerate(r.input_names)},
                state_ranges={
                    s: state_range(s, np.concatenate([a[:, i] for a in drawn]))
                    for i, s in enumerate(r.state_names)
                },
                priority=rollout.priority,
                **({} if r.pose is None else chase_eye(r.pose)),
            )
        )

    def _send_states(self, root: str, index: rr.TimeColumn, r: _Checked) -> dict[str, list[str]]:
        """Each state's plot: the state, its reference and error, the overlays; what each plot
        draws besides the state, as entity paths."""
        # Beside a reference or an overlay the state is the "actual" line; alone, its own name.
        actual = "actual" if r.ref is not None or r.over else None
        on_plot: dict[str, list[str]] = {}
        for i, s in enumerate(r.state_names):
            entity = child(root, "state", s)
            line_color = color(_STATE_OFFSET + i)
            self._send_scalars(
                entity, index, r.x[:, i : i + 1], [actual or s], [line_color], width=2.0
            )
            on_plot[s] = []
            if r.ref is not None:
                on_plot[s].append(child(entity, _REFERENCE))
                self._send_scalars(
                    on_plot[s][-1], index, r.ref[:, i : i + 1], [_REFERENCE], [_REFERENCE_COLOR]
                )
                self._send_scalars(
                    child(root, "error", s),
                    index,
                    r.x[:, i : i + 1] - r.ref[:, i : i + 1],
                    [f"{s} error"],
                    [line_color],
                )
            for j, (key, v) in enumerate(r.over.items()):
                on_plot[s].append(child(entity, key))
                self._send_scalars(
                    on_plot[s][-1], index, v[:, i : i + 1], [key], [color(_OVERLAY_OFFSET + j)]
                )
        return on_plot

    def _road_wheel(self, r: _Checked) -> np.ndarray:
        """The drawn front wheels' angle (rad): the wheel's by the steering ratio, or straight."""
        steer = r.u[:, r.input_names.index(STEER)] if STEER in r.input_names else None
        if steer is None or self.steering_ratio is None:
            return np.zeros(len(r.t))
        return np.nan_to_num(np.deg2rad(steer) / self.steering_ratio)

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
        entity = child(entity_root(name), "scene", key)
        if strips:
            lifted = [on_ground(as_matrix("strip", strip, len(strip), 2)) for strip in strips]
            rec.log(entity, rr.LineStrips3D(lifted, colors=[color], radii=0.05), static=True)
        if points is not None:
            cones = on_ground(as_matrix("points", points, len(points), 2), height=0.35)
            rec.log(entity, rr.Points3D(cones, colors=[color], radii=0.18), static=True)

    def path_ahead(self, name: str, time_s: np.ndarray, paths: np.ndarray) -> None:
        """See :meth:`Recorder.path_ahead`; one column send, rows without a finite point skipped."""
        rec = self._check_open()
        t = as_time("time_s", time_s).astype(np.float64)
        paths = np.asarray(paths, dtype=np.float64)
        if paths.ndim != 3 or paths.shape[0] != t.shape[0] or paths.shape[2] != 2:
            raise ValueError(f"paths must be (T={t.shape[0]}, K, 2), got {paths.shape}")
        keep = np.all(np.isfinite(paths), axis=(1, 2))
        if not keep.any():
            return
        strips = [on_ground(path, height=0.04) for path in paths[keep]]
        rec.send_columns(
            child(entity_root(name), "predicted_path"),
            indexes=[time_column(SIM_TIMELINE, t[keep])],
            columns=rr.LineStrips3D.columns(strips=strips),
            strict=True,
        )
        rec.log(
            child(entity_root(name), "predicted_path"),
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
        root = entity_root(path)
        t = as_time("time_s", time_s)
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
            str(k): as_matrix(f"values[{k!r}]", v, t.shape[0], None) for k, v in values.items()
        }

        index = time_column(timeline, t)
        if info is None:
            info = self._series[root] = SeriesInfo(root=root, timeline=timeline)
        for key, v in blocks.items():
            if key not in info.keys:
                info.keys.append(key)
            j = info.keys.index(key)
            k = v.shape[1]
            names = [key] if k == 1 else [f"{key}[{c}]" for c in range(k)]
            colors = [color(j + c) for c in range(k)]
            self._send_scalars(child(root, key), index, v, names, colors)

    def blueprint(self) -> rrb.Blueprint | None:
        """Default viewer layout for what has been logged so far (``layout.blueprint``)."""
        return blueprint(self._rollouts, self._series, self.path.name)

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


@dataclass(frozen=True)
class _Checked:
    """A rollout's arrays as they are sent: float64 (N, k) blocks, names as strings."""

    t: np.ndarray
    state_names: list[str]
    input_names: list[str]
    x: np.ndarray
    u: np.ndarray
    pose: np.ndarray | None
    extras: dict[str, np.ndarray]
    extra_lines: dict[str, list[str]]
    ref: np.ndarray | None
    over: dict[str, np.ndarray]

    @classmethod
    def of(cls, rollout: Rollout) -> _Checked:
        """Every array of ``rollout`` checked against its time column (ValueError: which)."""
        t = as_time("time_s", rollout.time_s)
        n = t.shape[0]
        if np.issubdtype(t.dtype, np.integer):
            t = t.astype(np.float64)
        state_names = [str(s) for s in rollout.state_names]
        input_names = [str(s) for s in rollout.input_names]
        ns = len(state_names)
        x = as_matrix("states", rollout.states, n, ns)
        u = as_matrix("inputs", rollout.inputs, n, len(input_names))
        pose = None if rollout.poses is None else as_matrix("poses", rollout.poses, n, 3)
        extras: dict[str, np.ndarray] = {}
        extra_lines: dict[str, list[str]] = {}
        for k, v in (rollout.extra or {}).items():
            if isinstance(v, Mapping):  # named columns on one plot
                extra_lines[str(k)] = [str(c) for c in v]
                columns = [as_matrix(f"extra[{k!r}][{c!r}]", v[c], n, 1) for c in v]
                extras[str(k)] = np.hstack(columns) if columns else np.zeros((n, 0))
            else:
                extras[str(k)] = as_matrix(f"extra[{k!r}]", v, n, None)
        reference = rollout.reference
        ref = None if reference is None else as_matrix("reference", reference, n, ns)
        over = {
            str(k): as_matrix(f"overlays[{k!r}]", v, n, ns)
            for k, v in (rollout.overlays or {}).items()
        }
        if _REFERENCE in over:
            raise ValueError(f"overlays may not be called {_REFERENCE!r}: pass it as reference=")
        return cls(
            t=t,
            state_names=state_names,
            input_names=input_names,
            x=x,
            u=u,
            pose=pose,
            extras=extras,
            extra_lines=extra_lines,
            ref=ref,
            over=over,
        )
