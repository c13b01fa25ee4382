"""The single-track model's identification (``learners/single_track.py``): the lateral and yaw
equations together by separable least squares, the axle geometry when it is not measured, and
the signed least squares of the longitudinal channel."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear, minimize, minimize_scalar

from harness.core.episode import InputChannel, is_sedan

log = logging.getLogger(__name__)

LATERAL = ("front_per_mass", "rear_per_mass", "steer_per_mass")  # C_f/m, C_r/m, C_f/(m i_s)
YAW = ("mass_per_inertia",)  # m / I_z
MAX_SUBSTEPS = 50
# a and b of any road car: from a city car's 0.8 m to a long van's 3 m, with margin.
GEOMETRY_BOUNDS_M = (0.5, 3.5)
SEDAN_GEOMETRY = {"cg_to_front_m": 1.15, "cg_to_rear_m": 1.55, "mass_kg": 1500.0}


@dataclass(frozen=True)
class LateralSamples:
    """The samples the lateral and yaw equations are fitted on: states, road-wheel angle
    (rad), lateral and yaw acceleration."""

    x: np.ndarray
    delta: np.ndarray
    lateral_accel: np.ndarray
    yaw_accel: np.ndarray

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return self.x, self.delta, self.lateral_accel, self.yaw_accel


def form_of(
    physics: Mapping[str, float], a: float, b: float
) -> tuple[float, float, float, float, float, float]:
    """θ_1 .. θ_6 of the single-track model with C_f/m, C_r/m, C_f/(m i_s), m/I_z, a and b."""
    front, rear, steer = (physics[k] for k in LATERAL)
    k = physics["mass_per_inertia"]
    moment = a * front - b * rear
    return (
        steer,
        -(front + rear),
        -moment,
        k * a * steer,
        -k * moment,
        -k * (a * a * front + b * b * rear),
    )


def identify_lateral(
    samples: LateralSamples, a: float | None, b: float | None, min_speed: float
) -> tuple[tuple[float, ...], tuple[float, float] | None]:
    """θ_1 .. θ_6 of the lateral and yaw equations, and the a and b identified within
    :data:`GEOMETRY_BOUNDS_M` where the free fit's were not a road car's (else None). With a and
    b measured, the physical fit with them; without, the free least squares."""
    if a is not None and b is not None:
        return fit_geometry(samples, a, b), None
    x, delta, lateral_accel, yaw_accel = samples.arrays()
    w = np.maximum(x[:, 0], min_speed)
    regressors = np.column_stack([delta, x[:, 1] / w, x[:, 2] / w])
    form = (*_lstsq(regressors, lateral_accel), *_lstsq(regressors, yaw_accel))
    a_free, b_free = geometry_of(form)
    low, high = GEOMETRY_BOUNDS_M
    if low <= a_free <= high and low <= b_free <= high:
        return form, None
    a, b = bounded_geometry(samples, a_free, b_free, min_speed)
    return fit_geometry(samples, a, b), (a, b)


def fit_geometry(
    samples: LateralSamples, a: float, b: float
) -> tuple[float, float, float, float, float, float]:
    """θ_1 .. θ_6 of the physical fit with a and b given."""
    fitted = fit_lateral(*samples.arrays(), a, b)
    return form_of(dict(zip(LATERAL + YAW, fitted, strict=True)), a, b)


def bounded_geometry(
    samples: LateralSamples, a_free: float, b_free: float, min_speed: float
) -> tuple[float, float]:
    """a and b within :data:`GEOMETRY_BOUNDS_M` that fit the lateral and yaw equations
    best (a coarse grid, then a bounded local search), with a warning that the free fit's
    were not a road car's."""
    low, high = GEOMETRY_BOUNDS_M

    def residual(ab: np.ndarray) -> float:
        return lateral_residual(samples, float(ab[0]), float(ab[1]), min_speed)

    grid = np.linspace(low, high, 7)
    start = min(((a, b) for a in grid for b in grid), key=lambda ab: residual(np.array(ab)))
    best = minimize(residual, np.array(start), bounds=[(low, high)] * 2, method="L-BFGS-B")
    a, b = (float(v) for v in best.x)
    log.warning(
        "single_track: the data gives a = %.3g m, b = %.3g m, outside [%g, %g] m: it cannot "
        "separate the axles; identified within those bounds instead, a = %.2f m, b = %.2f "
        "m. Measured ones are better: learner.cg_to_front_m, learner.cg_to_rear_m",
        a_free,
        b_free,
        low,
        high,
        a,
        b,
    )
    return a, b


def lateral_residual(samples: LateralSamples, a: float, b: float, min_speed: float) -> float:
    """Normalized squared residual of both equations with a and b given."""
    form = fit_geometry(samples, a, b)
    x, delta, lateral_accel, yaw_accel = samples.arrays()
    vx, vy, r = x[:, 0], x[:, 1], x[:, 2]
    w = np.maximum(vx, min_speed)
    regressors = np.column_stack([delta, vy / w, r / w])
    lateral = regressors @ np.array(form[:3]) - lateral_accel
    yaw = regressors @ np.array(form[3:]) - yaw_accel
    return float(np.mean(lateral**2) / lateral_accel.var() + np.mean(yaw**2) / yaw_accel.var())


def fit_lateral(
    x: np.ndarray,
    delta: np.ndarray,
    lateral_accel: np.ndarray,
    yaw_accel: np.ndarray,
    a: float,
    b: float,
) -> tuple[float, float, float, float]:
    """(C_f/m, C_r/m, C_f/(m i_s), m/I_z): both equations together, by separable least
    squares (for a given m/I_z both are linear in the rest; the best m/I_z by a bounded
    scalar search). Each equation is scaled by its spread so both count.

    Fitted apart, the lateral equation alone cannot tell C_f from C_r (both multiply
    nearly −vy/vx): on ``data=default`` it gave C_r = 5·C_f and a model that lost the lane
    change; the yaw equation weighs them with +a and −b and separates them.
    """
    vx, vy, r = x[:, 0], x[:, 1], x[:, 2]
    w = np.maximum(vx, 1e-9)
    alpha_f, alpha_r = -(vy + a * r) / w, -(vy - b * r) / w
    lateral = np.column_stack([alpha_f, alpha_r, delta]) / lateral_accel.std()
    yaw = np.column_stack([a * alpha_f, -b * alpha_r, a * delta])
    yaw /= yaw_accel.std()
    target = np.concatenate([lateral_accel / lateral_accel.std(), yaw_accel / yaw_accel.std()])

    def fit(log_ratio: float) -> tuple[np.ndarray, float]:
        regressors = np.vstack([lateral, np.exp(log_ratio) * yaw])
        solution = _lstsq(regressors, target)
        return solution, float(np.sum((regressors @ solution - target) ** 2))

    # m / I_z = 1 / (yaw radius of gyration)²: radii from 0.3 m to 10 m cover any car.
    best = minimize_scalar(
        lambda log_ratio: fit(log_ratio)[1],
        bounds=(np.log(0.01), np.log(11.0)),
        method="bounded",
        options={"xatol": 1e-10},
    )
    (front, rear, steer), _ = fit(float(best.x))
    return float(front), float(rear), float(steer), float(np.exp(best.x))


def warn_sedan_geometry(own: Mapping[str, float | None], channels: Sequence[InputChannel]) -> None:
    """Logs of another car fitted with the sedan's measured geometry and mass (``own``: the
    model's cg_to_front_m, cg_to_rear_m, mass_kg): say so."""
    defaults = [key for key, value in own.items() if value == SEDAN_GEOMETRY[key]]
    if is_sedan(channels) or not defaults:
        return
    log.warning(
        "single_track: these inputs are not the sedan's, but %s %s the sedan's (%s): set "
        "learner.%s to this car's (null a and b: identified from the data)",
        ", ".join(defaults),
        "is" if len(defaults) == 1 else "are",
        ", ".join(f"{SEDAN_GEOMETRY[k]:g}" for k in defaults),
        "=…, learner.".join(defaults) + "=…",
    )


def stable_substeps(
    coefficients: np.ndarray, dt: float, min_speed: float, fastest_mps: float
) -> int:
    """Euler sub-steps per period that keep every lateral eigenvalue λ stable with a factor
    2 margin (h |λ|² <= |Re λ|), from min_speed_mps to ``fastest_mps``."""
    _, t2, t3, _, t5, t6 = coefficients[:6]
    needed = 1
    for vx in np.linspace(min_speed, max(fastest_mps, min_speed), 50):
        w = max(vx, min_speed)
        jacobian = np.array([[t2 / w, t3 / w - vx], [t5 / w, t6 / w]])
        for eigenvalue in np.linalg.eigvals(jacobian):
            if eigenvalue.real >= 0:
                continue  # not damped: no step size makes Euler follow it more stably
            largest = abs(eigenvalue.real) / abs(eigenvalue) ** 2
            needed = max(needed, math.ceil(dt / largest - 1e-9))
    return min(needed, MAX_SUBSTEPS)


def physical_parameters(
    coefficients: np.ndarray,
    a_given: float | None,
    b_given: float | None,
    mass_kg: float,
    names: Sequence[str],
) -> dict[str, float]:
    """The identified physics, in SI units: C_f, C_r (N/rad per axle), I_z (kg m²), the
    steering ratio (per unit of the steering input), a and b (given or recovered), and the
    longitudinal coefficients (per unit mass) under their ``names`` (the coefficients')."""
    t1, t2, t3, _, t5, _ = coefficients[:6].tolist()
    mass_per_inertia = t5 / t3 if t3 else float("nan")
    total, moment = -t2, -t3
    if a_given is not None and b_given is not None:
        a, b = a_given, b_given
    else:
        a, b = geometry_of(coefficients[:6])
    rear = (a * total - moment) / (a + b)
    front = total - rear
    return {
        "cornering_stiffness_front_n_per_rad": front * mass_kg,
        "cornering_stiffness_rear_n_per_rad": rear * mass_kg,
        "yaw_inertia_kg_m2": mass_kg / mass_per_inertia,
        "steering_ratio": front / t1 if t1 else float("inf"),
        "cg_to_front_m": a,
        "cg_to_rear_m": b,
        **dict(zip(names[6:], coefficients[6:].tolist(), strict=True)),
    }


def identify_longitudinal(
    regressors: np.ndarray,
    target: np.ndarray,
    bounds: Sequence[tuple[float, float] | None],
    names: Sequence[str],
) -> tuple[np.ndarray, list[int]]:
    """The longitudinal coefficients (``names``) by least squares, each held to the sign physics
    gives it (:func:`signed_lstsq`), with a warning naming those held at a bound."""
    fitted, bounded = signed_lstsq(regressors, target, bounds)
    if bounded:
        log.warning(
            "single_track: the least-squares fit gave %s the sign physics forbids (an input "
            "that brakes accelerating, a drive that slows); fitted again with the signs as "
            "bounds, %s (training.fit.bounded)",
            ", ".join(names[i] for i in bounded),
            "held at its bound" if len(bounded) == 1 else "each held at its bound",
        )
    return fitted, bounded


def geometry_of(form: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """a and b recovered from θ_1 .. θ_6: a = θ_4 / (k θ_1) with k = m / I_z = θ_5 / θ_3; b
    from C_f + C_r, a C_f − b C_r and a² C_f + b² C_r."""
    t1, t2, t3, t4, t5, t6 = (float(v) for v in form)
    mass_per_inertia = t5 / t3 if t3 else float("nan")
    total, moment = -t2, -t3
    with np.errstate(divide="ignore", invalid="ignore"):
        a = t4 / (mass_per_inertia * t1) if t1 else float("nan")
        denominator = a * total - moment
        b = a + (-t6 / mass_per_inertia - a * a * total) / denominator if denominator else a
    return a, b


def signed_lstsq(
    regressors: np.ndarray, target: np.ndarray, bounds: Sequence[tuple[float, float] | None]
) -> tuple[np.ndarray, list[int]]:
    """Least squares with each coefficient in its bounds (None: held at 0), and the indices of
    those held at a bound. The plain solution where it keeps every sign (the same bits as an
    unbounded fit); else the bounded one. A regressor that is 0 throughout (a brake column
    never negative) has nothing to fit: its coefficient is 0."""
    used = np.any(regressors != 0, axis=0)
    free = [i for i, bound in enumerate(bounds) if bound is not None and used[i]]
    low = np.array([bounds[i][0] for i in free])  # type: ignore[index]
    high = np.array([bounds[i][1] for i in free])  # type: ignore[index]
    solution = np.zeros(len(bounds))
    columns = regressors if len(free) == len(bounds) else regressors[:, free]
    plain = _lstsq(columns, target)
    if np.all((plain >= low) & (plain <= high)):
        solution[free] = plain
        return solution, []
    bounded = lsq_linear(columns, target, bounds=(low, high), method="bvls").x
    solution[free] = bounded
    held = [free[k] for k in np.flatnonzero((bounded == low) | (bounded == high))]
    return solution, held


def _lstsq(regressors: np.ndarray, target: np.ndarray) -> np.ndarray:
    solution, *_ = np.linalg.lstsq(regressors, target, rcond=None)
    return np.asarray(solution, dtype=np.float64)
