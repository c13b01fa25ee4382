"""Physical parameters of the sedan plant, one dataclass per subsystem, SI units throughout.

These dataclasses are the schema of ``conf/plant/*.yaml`` (registered with Hydra's ConfigStore in
``harness/config.py``): OmegaConf checks key names and types when the config is composed, and
each ``__post_init__`` checks ranges, raising a one-line ``ValueError`` that names the full key.
Defaults describe the dry-road C-class sedan (see README).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from harness.core import checks
from harness.core.checks import in_range, require


def check_ranges(
    prefix: str,
    part: Any,
    *,
    positive: Iterable[str] = (),
    non_negative: Iterable[str] = (),
) -> None:
    """Every number of ``part`` finite, the named ones > 0 or >= 0; errors name ``prefix.key``."""
    for f in dataclasses.fields(part):
        value = getattr(part, f.name)
        for number in value if isinstance(value, tuple) else (value,):
            if isinstance(number, (int, float)):
                require(math.isfinite(number), f"{prefix}.{f.name}", "finite", value)
    for name in positive:
        checks.positive(f"{prefix}.{name}", getattr(part, name))
    for name in non_negative:
        checks.non_negative(f"{prefix}.{name}", getattr(part, name))


@dataclass
class TireParams:
    """Magic-Formula tyre (pure and combined slip, MF 5.2 style) on a vertical tyre spring.

    Peak friction is ``road_friction * (1 + load_sensitivity * dfz)`` with
    ``dfz = (Fz - nominal_load_n) / nominal_load_n``; the shape, curvature and combined-slip
    coefficients are CommonRoad's published set (pcx1, pex1, pkx1, pcy1, rbx1 ... rcy1).
    """

    road_friction: float = 0.9
    nominal_load_n: float = 4000.0
    unloaded_radius_m: float = 0.325
    vertical_stiffness_n_per_m: float = 250_000.0
    vertical_damping_n_s_per_m: float = 500.0
    # Cornering stiffness normalised by the nominal load (rad^-1): rear stiffer -> understeer.
    cornering_stiffness_front_per_rad: float = 13.0
    cornering_stiffness_rear_per_rad: float = 20.0
    # Degressive growth of cornering stiffness with load: K ~ sin(2 atan(Fz / (c * Fz0))).
    cornering_stiffness_load_shape: float = 2.0
    slip_stiffness_per_unit_slip: float = 22.3  # pkx1: longitudinal stiffness / Fz
    shape_x: float = 1.6411  # pcx1
    curvature_x: float = 0.464  # pex1
    load_sensitivity_x: float = -0.1
    shape_y: float = 1.3507  # pcy1
    curvature_y: float = -0.0075  # pey1
    load_sensitivity_y: float = -0.1
    combined_bx1: float = 13.276  # rbx1
    combined_bx2: float = -13.778  # rbx2
    combined_cx1: float = 1.2568  # rcx1
    combined_by1: float = 7.1433  # rby1
    combined_by2: float = 9.1916  # rby2
    combined_cy1: float = 1.0719  # rcy1
    # Slip denominators never drop below this speed (m/s): keeps slip finite at standstill.
    slip_speed_min_mps: float = 0.1
    # Fraction of the force that would cancel the patch slip velocity in one physics step that
    # a tyre may apply: the explicit-integration stability bound that makes a tyre at very low
    # speed behave like a stiff no-slip contact instead of an unstable damper (0 < gain <= 1).
    slip_limiter_gain: float = 0.5

    def __post_init__(self) -> None:
        check_ranges(
            "plant.tire",
            self,
            positive=(
                "road_friction",
                "nominal_load_n",
                "unloaded_radius_m",
                "vertical_stiffness_n_per_m",
                "cornering_stiffness_front_per_rad",
                "cornering_stiffness_rear_per_rad",
                "cornering_stiffness_load_shape",
                "slip_stiffness_per_unit_slip",
                "shape_x",
                "shape_y",
                "slip_speed_min_mps",
                "slip_limiter_gain",
            ),
            non_negative=("vertical_damping_n_s_per_m",),
        )
        for name in ("curvature_x", "curvature_y"):
            value = getattr(self, name)
            require(value < 1, f"plant.tire.{name}", "< 1 for a Magic-Formula curve", value)
        in_range("plant.tire.slip_limiter_gain", self.slip_limiter_gain, 0.0, 1.0, open_low=True)


@dataclass
class PowertrainParams:
    """Front-wheel drive through an open differential; torque falls with wheel speed."""

    peak_wheel_torque_nm: float = 3600.0  # at the axle, full pedal
    max_power_w: float = 110_000.0  # full pedal; the paper's throttle 0.2 gives 22 kW
    max_wheel_speed_radps: float = 220.0  # torque tapers to zero here (about 250 km/h)

    def __post_init__(self) -> None:
        check_ranges(
            "plant.powertrain",
            self,
            positive=("peak_wheel_torque_nm", "max_power_w", "max_wheel_speed_radps"),
        )


@dataclass
class BrakeParams:
    """Brake torque per wheel proportional to master-cylinder pressure."""

    front_gain_nm_per_mpa: float = 145.0
    rear_gain_nm_per_mpa: float = 52.0

    def __post_init__(self) -> None:
        check_ranges(
            "plant.brakes", self, non_negative=("front_gain_nm_per_mpa", "rear_gain_nm_per_mpa")
        )


@dataclass
class SteeringParams:
    """Steering-wheel angle to road-wheel angles through a ratio and Ackermann geometry."""

    steering_ratio: float = 16.0
    ackermann: float = 1.0  # 1 = full Ackermann, 0 = parallel steer
    servo_stiffness_nm_per_rad: float = 3000.0
    servo_damping_nm_s_per_rad: float = 60.0

    def __post_init__(self) -> None:
        check_ranges(
            "plant.steering",
            self,
            positive=("steering_ratio", "servo_stiffness_nm_per_rad"),
            non_negative=("servo_damping_nm_s_per_rad",),
        )
        in_range("plant.steering.ackermann", self.ackermann, 0.0, 1.0)


@dataclass
class ResistanceParams:
    """Rolling resistance on every wheel and aerodynamic drag on the body."""

    rolling_resistance: float = 0.012
    drag_coefficient: float = 0.30
    frontal_area_m2: float = 2.2
    air_density_kg_per_m3: float = 1.2

    def __post_init__(self) -> None:
        check_ranges(
            "plant.resistance",
            self,
            positive=("frontal_area_m2", "air_density_kg_per_m3"),
            non_negative=("rolling_resistance", "drag_coefficient"),
        )


@dataclass
class ChassisParams:
    """Masses and the anti-roll bars; geometry and springs live in models/mjcf/sedan.xml."""

    sprung_mass_kg: float = 1340.0
    payload_kg: float = 0.0
    payload_position_m: tuple[float, float, float] = (-0.3, 0.0, 0.1)
    anti_roll_front_n_per_m: float = 10_400.0
    anti_roll_rear_n_per_m: float = 3_000.0

    def __post_init__(self) -> None:
        self.payload_position_m = tuple(self.payload_position_m)  # the schema hands over a list
        if len(self.payload_position_m) != 3:
            raise ValueError(
                "plant.chassis.payload_position_m must be (x, y, z) "
                f"(got {list(self.payload_position_m)})"
            )
        check_ranges(
            "plant.chassis",
            self,
            positive=("sprung_mass_kg",),
            non_negative=("payload_kg", "anti_roll_front_n_per_m", "anti_roll_rear_n_per_m"),
        )


@dataclass
class SedanParams:
    """Everything that defines one plant variant (``conf/plant/<name>.yaml``)."""

    name: str = "sedan"
    control_period_s: float = 0.01
    physics_timestep_s: float = 0.001
    tire: TireParams = field(default_factory=TireParams)
    powertrain: PowertrainParams = field(default_factory=PowertrainParams)
    brakes: BrakeParams = field(default_factory=BrakeParams)
    steering: SteeringParams = field(default_factory=SteeringParams)
    resistance: ResistanceParams = field(default_factory=ResistanceParams)
    chassis: ChassisParams = field(default_factory=ChassisParams)

    def __post_init__(self) -> None:
        check_ranges("plant", self, positive=("control_period_s", "physics_timestep_s"))
        ratio = self.control_period_s / self.physics_timestep_s
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                f"plant.control_period_s ({self.control_period_s}) must be a whole multiple of "
                f"plant.physics_timestep_s ({self.physics_timestep_s})"
            )

    @property
    def substeps(self) -> int:
        """Physics steps per control period."""
        return round(self.control_period_s / self.physics_timestep_s)
