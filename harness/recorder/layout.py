"""The default viewer layout (a Rerun blueprint) of a recording: one tab per rollout, plots whose
ranges are the data's, and at most MAX_VIEWS views."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import rerun.blueprint as rrb

from harness.recorder.entities import SIM_TIMELINE, STEER, child, title

log = logging.getLogger(__name__)

# Views the default layout holds at most: a blueprint of about 40 rollout tabs (320 views) made
# the viewer (0.41) refuse the whole recording ("Data source finished without loading a
# recording"), 30 tabs (240 views) loaded (synthetic recordings;
# docs/reference/reliability_run.md). Tabs
# go in priority order until the next would pass it; every rollout stays in the recording.
MAX_VIEWS = 200
# The narrowest y range of a state's plot (SI): what a driver would call a small change of it.
MIN_STATE_SPAN = {"vx": 2.0, "vy": 0.5, "yaw_rate": 0.2}


def fitted_range(values: np.ndarray, symmetric: bool = False) -> tuple[float, float] | None:
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


def state_range(name: str, values: np.ndarray) -> tuple[float, float] | None:
    """A state plot's y range: the values' (10 % margin), at least ``MIN_STATE_SPAN`` wide about
    their middle, so that a car holding 80 km/h within 0.1 m/s draws a flat line, not a crisis
    scaled to fill the plot."""
    fitted = fitted_range(values)
    span = MIN_STATE_SPAN.get(name)
    if fitted is None or span is None or fitted[1] - fitted[0] >= span:
        return fitted
    middle = 0.5 * (fitted[0] + fitted[1])
    return middle - 0.5 * span, middle + 0.5 * span


def input_plot(name: str, values: np.ndarray) -> tuple[str, tuple[float, float] | None]:
    """Title and y range of an input's plot: the range the input was used over.

    The steering is centred on straight ahead and its peak is in the title: on a plot a few
    hundred pixels high the viewer labels only the zero tick of a +-70 deg range.
    """
    if name != STEER:
        return title(name), fitted_range(values)
    finite = values[np.isfinite(values)]
    peak = f", peak {np.max(np.abs(finite)):.0f}" if finite.size else ""
    return title(name) + peak, fitted_range(values, symmetric=True)


@dataclass
class RolloutInfo:
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


def tab_views(r: RolloutInfo) -> int:
    """Views in a rollout's tab: the car, one plot per state, per input, the error, per extra."""
    return (
        int(r.has_pose) + len(r.states) + len(r.input_plots) + int(r.has_reference) + len(r.extras)
    )


@dataclass
class SeriesInfo:
    """What the blueprint needs to know about one ``series()`` path."""

    root: str
    timeline: str
    keys: list[str] = field(default_factory=list)


def blueprint(
    rollouts: Sequence[RolloutInfo], series: Mapping[str, SeriesInfo], name: str
) -> rrb.Blueprint | None:
    """Default viewer layout for what has been logged so far (None if nothing was); ``name``:
    the recording's, for the line that says which rollouts the layout leaves out.

    One tab per rollout: 3D car + path on the left, one plot per state in the middle
    (with its reference and overlays), one plot per input, the tracking error and one per
    extra on the right. Series get one tab with one plot per ``series()`` path. Time axes
    of all plots are linked so zooming is shared.
    """
    tabs: list[rrb.Container | rrb.View] = []
    link = rrb.TimeAxis(link="LinkToGlobal")
    legend = rrb.PlotLegend(corner="LeftTop")
    count, left_out = len(series), []  # views; the series tab's are kept first
    for r in sorted(rollouts, key=lambda r: -r.priority):  # stable: logged order
        size = tab_views(r)
        if count + size > MAX_VIEWS:
            left_out.append(r.name)
            continue
        count += size
        tabs.append(_rollout_tab(r, link, legend))
    if series:
        views = [
            rrb.TimeSeriesView(origin=s.root, name=s.root.lstrip("/")) for s in series.values()
        ]
        tabs.append(rrb.Grid(*views, name="series"))
    if left_out:
        log.info(
            "%s: the default layout shows %d of %d rollouts (at most %d views); the other "
            "%d are in the recording, under their names: %s",
            name,
            len(rollouts) - len(left_out),
            len(rollouts),
            MAX_VIEWS,
            len(left_out),
            ", ".join(left_out),
        )
    if not tabs:
        return None
    timeline = SIM_TIMELINE if rollouts else next(iter(series.values())).timeline
    return rrb.Blueprint(
        rrb.Tabs(*tabs, active_tab=0),
        rrb.TimePanel(timeline=timeline, state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
    )


def _rollout_tab(r: RolloutInfo, link: rrb.TimeAxis, legend: rrb.PlotLegend) -> rrb.Horizontal:
    """A rollout's tab: the car, its state plots, then its inputs, error and extras."""
    # Each state's plot lists its lines by path: the reference is drawn where it is.
    state_views = [
        rrb.TimeSeriesView(
            origin=child(r.root, "state", s),
            contents=[child(r.root, "state", s), *r.on_state_plot.get(s, [])],
            name=title(s),
            axis_x=link,
            axis_y=rrb.ScalarAxis(range=r.state_ranges.get(s)),
            plot_legend=legend,
        )
        for s in r.states
    ]
    other_views = [
        rrb.TimeSeriesView(
            origin=child(r.root, "input", s),
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
                origin=child(r.root, "error"),
                name="error: actual - reference",
                axis_x=link,
                plot_legend=legend,
            )
        )
    other_views += [
        rrb.TimeSeriesView(
            origin=child(r.root, "extra", k), name=k, axis_x=link, plot_legend=legend
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
    return rrb.Horizontal(*columns, column_shares=shares, name=r.name)
