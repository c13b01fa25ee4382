"""The recorder's interface, and the null recorder that implements it by writing nothing."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from types import TracebackType
from typing import NamedTuple, Self

import numpy as np

from harness.recorder.entities import SIM_TIMELINE


class Rollout(NamedTuple):
    """The arguments of :meth:`Recorder.rollout`, as one value handed to the writer (its fields
    are documented there)."""

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
            Rollout(
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

    def _log_rollout(self, rollout: Rollout) -> None:
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
