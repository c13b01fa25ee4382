"""Entity paths, times, colors and shape checks shared by everything the recorder logs."""

from __future__ import annotations

import numpy as np
import rerun as rr

SIM_TIMELINE = "sim_time"
STEER = "steer_wheel_deg"  # the input that turns the drawn front wheels

# Colors (RGB) cycled over series so that e.g. vx is always the same color in every recording.
PALETTE: tuple[tuple[int, int, int], ...] = (
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
UNITS = {
    "vx": "m/s",
    "vy": "m/s",
    "yaw_rate": "rad/s",
    "steer_wheel_deg": "deg",
    "pedal": "throttle 0..0.2 / -brake MPa",
}


def color(i: int) -> tuple[int, int, int]:
    """Palette color ``i`` (cycled), so a given series keeps its color across recordings."""
    return PALETTE[i % len(PALETTE)]


def title(name: str) -> str:
    """Plot title: the series name, with its unit when it is a standard one."""
    unit = UNITS.get(name)
    return f"{name} [{unit}]" if unit else name


def entity_root(path: str) -> str:
    """Entity path from a user path whose ``/`` separate levels (rollout name, series path).

    Every segment is escaped so names with spaces, dots or brackets stay one segment, and
    the same string is used for logging and in the blueprint (they must match exactly).
    """
    segments = [seg for seg in str(path).split("/") if seg]
    if not segments:
        raise ValueError(f"entity path is empty: {path!r}")
    return "/" + "/".join(rr.escape_entity_path_part(seg) for seg in segments)


def child(root: str, *parts: str) -> str:
    """Append single (escaped) segments to an already escaped entity path."""
    return "/".join([root, *(rr.escape_entity_path_part(str(p)) for p in parts)])


def as_time(name: str, time_s: np.ndarray) -> np.ndarray:
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


def as_matrix(name: str, x: np.ndarray, n: int, cols: int | None) -> np.ndarray:
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


def time_column(timeline: str, t: np.ndarray) -> rr.TimeColumn:
    """Integer times become a sequence timeline, float times a duration in seconds."""
    if np.issubdtype(t.dtype, np.integer):
        return rr.TimeColumn(timeline, sequence=t.astype(np.int64))
    # Round to whole nanoseconds ourselves: rerun truncates, which turns 0.29 s into 0.289999999 s.
    ns = np.round(t.astype(np.float64) * 1e9).astype(np.int64)
    return rr.TimeColumn(timeline, duration=ns.astype("timedelta64[ns]"))


def on_ground(xy: np.ndarray, height: float = 0.02) -> np.ndarray:
    """(K, 2) X, Y -> (K, 3) at ``height`` m above the ground grid (no z-fighting)."""
    return np.column_stack([xy, np.full(len(xy), height)])
