"""The MuJoCo sedan plant: the one interface every rollout in the harness steps.

State ``x = (vx, vy, yaw_rate)``: velocity of the centre of gravity in the yaw (heading) frame,
i.e. the body frame projected onto the road plane, so body roll and pitch do not leak into vx/vy
(m/s, m/s, rad/s). Input ``u = (steer_wheel_deg, pedal)`` as in the paper: steering-wheel angle
in degrees within [-450, 450]; ``pedal >= 0`` is throttle in [0, 0.2], ``pedal < 0`` is brake
master-cylinder pressure ``-pedal`` in MPa within [0, 9.1]; one pedal at a time by construction.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
from functools import cache
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from harness.core.limits import BRAKE_MAX_MPA, STEER_WHEEL_LIMIT_DEG, THROTTLE_MAX
from harness.core.paths import MJCF_DIR
from harness.plant import native
from harness.plant.params import SedanParams

log = logging.getLogger(__name__)

MJCF_PATH: Path = MJCF_DIR / "sedan.xml"
CORNERS = ("fl", "fr", "rl", "rr")
# MuJoCo's instability warnings: a NaN, inf or huge position, velocity or acceleration. MuJoCo
# then resets the simulation to the model's initial state and carries on (its "autoreset"), so
# the states stay finite and a diverged car would otherwise look like a car at rest.
_BADQPOS, _BADQVEL, _BADQACC = (
    int(mujoco.mjtWarning.mjWARN_BADQPOS),
    int(mujoco.mjtWarning.mjWARN_BADQVEL),
    int(mujoco.mjtWarning.mjWARN_BADQACC),
)
# What makes the explicit physics step diverge: stiff springs and light or heavy bodies for the
# physics timestep. Named when no key differs from its default.
STIFFNESS_KEYS = (
    "plant.physics_timestep_s",
    "plant.tire.vertical_stiffness_n_per_m",
    "plant.tire.vertical_damping_n_s_per_m",
    "plant.steering.servo_stiffness_nm_per_rad",
    "plant.chassis.sprung_mass_kg",
    "plant.chassis.payload_kg",
)


class PlantUnstableError(RuntimeError):
    """The physics diverged (MuJoCo's instability warning): the plant's parameters are wrong."""


@cache
def _route_mujoco_warnings() -> None:
    """MuJoCo's warnings to the log, not to stdout and a MUJOCO_LOG.TXT in the working
    directory (the plant raises :class:`PlantUnstableError` for the ones that matter)."""
    mujoco.set_mju_user_warning(lambda message: log.warning("MuJoCo: %s", message))


def changed_keys(params: SedanParams) -> list[str]:
    """``plant.<key>=<value>`` of every parameter that differs from the default sedan's."""
    changed: list[str] = []

    def walk(value: Any, default: Any, key: str) -> None:
        if isinstance(value, dict):
            for name in value:
                walk(value[name], default.get(name), f"{key}.{name}")
        elif value != default:
            changed.append(f"{key}={value}")

    ours, defaults = dataclasses.asdict(params), dataclasses.asdict(SedanParams())
    ours.pop("name")
    walk(ours, defaults, "plant")
    return changed


def build_model(params: SedanParams) -> mujoco.MjModel:
    """Compose the variant from the one MJCF through MjSpec and pack the callback parameters."""
    spec = mujoco.MjSpec.from_file(str(MJCF_PATH))
    spec.option.timestep = params.physics_timestep_s
    chassis = spec.body("chassis")
    scale = params.chassis.sprung_mass_kg / chassis.mass
    chassis.mass = params.chassis.sprung_mass_kg
    chassis.inertia = np.asarray(chassis.inertia) * scale
    if params.chassis.payload_kg > 0:
        payload = chassis.add_body(name="payload", pos=list(params.chassis.payload_position_m))
        payload.mass = params.chassis.payload_kg
        payload.inertia = [params.chassis.payload_kg * 0.1] * 3
        payload.explicitinertial = True
    spec.add_numeric(name="vehicle_params", data=[0.0] * len(native.PARAM_NAMES))
    model = spec.compile()
    model.numeric("vehicle_params").data[:] = _pack(model, params)
    return model


def _pack(model: mujoco.MjModel, params: SedanParams) -> np.ndarray:
    def joint(name: str) -> mujoco._structs._MjModelJointViews:
        return model.joint(name)

    tire, power, brakes = params.tire, params.powertrain, params.brakes
    front = model.body("corner_fl").pos
    rear = model.body("corner_rl").pos
    values: dict[str, float] = {
        "LAYOUT_KEY": native.LAYOUT_KEY_VALUE,
        "CTRL_STEER": model.actuator("steer_wheel_deg").id,
        "CTRL_PEDAL": model.actuator("pedal").id,
        "CHASSIS_BODY": model.body("chassis").id,
        "TOTAL_MASS": float(model.body_subtreemass[model.body("chassis").id]),
        "WHEELBASE": float(front[0] - rear[0]),
        "TRACK_FRONT": float(2 * front[1]),
        "STEERING_RATIO": params.steering.steering_ratio,
        "ACKERMANN": params.steering.ackermann,
        "SERVO_KP": params.steering.servo_stiffness_nm_per_rad,
        "SERVO_KD": params.steering.servo_damping_nm_s_per_rad,
        "ARB_FRONT": params.chassis.anti_roll_front_n_per_m,
        "ARB_REAR": params.chassis.anti_roll_rear_n_per_m,
        "PEAK_TORQUE": power.peak_wheel_torque_nm,
        "MAX_POWER": power.max_power_w,
        "MAX_WHEEL_SPEED": power.max_wheel_speed_radps,
        "BRAKE_FRONT": brakes.front_gain_nm_per_mpa,
        "BRAKE_REAR": brakes.rear_gain_nm_per_mpa,
        "ROLLING_RESISTANCE": params.resistance.rolling_resistance,
        "AIR_DENSITY": params.resistance.air_density_kg_per_m3,
        "DRAG_AREA": params.resistance.drag_coefficient * params.resistance.frontal_area_m2,
        "ROAD_FRICTION": tire.road_friction,
        "NOMINAL_LOAD": tire.nominal_load_n,
        "UNLOADED_RADIUS": tire.unloaded_radius_m,
        "TIRE_KZ": tire.vertical_stiffness_n_per_m,
        "TIRE_CZ": tire.vertical_damping_n_s_per_m,
        "CORNERING_FRONT": tire.cornering_stiffness_front_per_rad,
        "CORNERING_REAR": tire.cornering_stiffness_rear_per_rad,
        "CORNERING_LOAD_SHAPE": tire.cornering_stiffness_load_shape,
        "SLIP_STIFFNESS": tire.slip_stiffness_per_unit_slip,
        "SHAPE_X": tire.shape_x,
        "CURV_X": tire.curvature_x,
        "LOAD_SENS_X": tire.load_sensitivity_x,
        "SHAPE_Y": tire.shape_y,
        "CURV_Y": tire.curvature_y,
        "LOAD_SENS_Y": tire.load_sensitivity_y,
        "RBX1": tire.combined_bx1,
        "RBX2": tire.combined_bx2,
        "RCX1": tire.combined_cx1,
        "RBY1": tire.combined_by1,
        "RBY2": tire.combined_by2,
        "RCY1": tire.combined_cy1,
        "SLIP_SPEED_MIN": tire.slip_speed_min_mps,
        "SLIP_LIMITER_GAIN": tire.slip_limiter_gain,
    }
    for j, corner in enumerate(CORNERS):
        values[f"WHEEL_BODY_{j}"] = model.body(f"wheel_{corner}").id
        values[f"SPIN_DOF_{j}"] = joint(f"spin_{corner}").dofadr[0]
        values[f"SUSP_DOF_{j}"] = joint(f"susp_{corner}").dofadr[0]
        values[f"SUSP_QPOS_{j}"] = joint(f"susp_{corner}").qposadr[0]
    for j, corner in enumerate(CORNERS[:2]):
        values[f"STEER_DOF_{j}"] = joint(f"steer_{corner}").dofadr[0]
        values[f"STEER_QPOS_{j}"] = joint(f"steer_{corner}").qposadr[0]
    missing = set(native.PARAM_NAMES) - set(values)
    if missing:
        raise RuntimeError(f"vehicle parameters not packed: {sorted(missing)}")
    return np.array([float(values[name]) for name in native.PARAM_NAMES])


@cache
def _source_digests() -> dict[str, str]:
    """SHA-256 of the files besides the parameters that decide how the car moves."""
    return {
        path.name: hashlib.sha256(path.read_bytes()).hexdigest()
        for path in (native.SOURCE, MJCF_PATH)
    }


class Sedan:
    """A C-class sedan on a flat road; steps at ``dt`` = 10 ms with 1 ms physics substeps.

    Implements :class:`harness.core.contracts.Plant`. ``Sedan()`` is the dry default,
    ``Sedan(params)`` any variant; Hydra builds it from ``conf/plant/*.yaml`` as
    ``Sedan(**fields)`` with ``SedanParams``' fields (sub-blocks already their dataclasses).
    """

    input_low = np.array([-STEER_WHEEL_LIMIT_DEG, -BRAKE_MAX_MPA])
    input_high = np.array([STEER_WHEEL_LIMIT_DEG, THROTTLE_MAX])

    def __init__(self, params: SedanParams | None = None, /, **fields: Any) -> None:
        if params is not None and fields:
            raise ValueError("give either params or SedanParams fields, not both")
        self.params = params if params is not None else SedanParams(**fields)
        native.install_callback()
        _route_mujoco_warnings()
        self.model = build_model(self.params)
        self.data = mujoco.MjData(self.model)
        # A live view of MuJoCo's warning counters (reset by mj_resetData): read every step.
        self._warnings = self.data.warning.number
        self.dt: float = self.params.control_period_s
        self._substeps = self.params.substeps
        self._chassis = self.model.body("chassis").id
        self._free_qpos = self.model.joint("chassis").qposadr[0]
        self._free_dof = self.model.joint("chassis").dofadr[0]
        self._spin_dofs = [self.model.joint(f"spin_{c}").dofadr[0] for c in CORNERS]
        self._rolling_radius = self._settle()
        self.clipped_inputs = 0
        self.reset()

    def __reduce__(self) -> tuple[type[Sedan], tuple[SedanParams]]:
        """A Sedan pickles as its parameters: a worker process rebuilds it, at rest."""
        return type(self), (self.params,)

    @property
    def fingerprint(self) -> dict[str, Any]:
        """Everything that decides how this car moves: what a dataset of it is keyed on."""
        return {
            "plant": type(self).__name__,
            "params": dataclasses.asdict(self.params),
            "sources": dict(_source_digests()),
            "mujoco": mujoco.__version__,
        }

    def _settle(self) -> float:
        """Let the car sink onto its springs once; every reset starts from this rest pose."""
        mujoco.mj_resetData(self.model, self.data)
        mujoco.mj_step(self.model, self.data, nstep=int(2.0 / self.model.opt.timestep))
        self._check_stable("while settling onto its springs")
        if not np.all(np.isfinite(self.data.qpos)):
            raise RuntimeError(f"plant {self.params.name!r} does not settle: check its parameters")
        self._rest_qpos = self.data.qpos.copy()
        wheel_height = self.data.xpos[self.model.body("wheel_rl").id, 2]
        deflection = self.params.tire.unloaded_radius_m - wheel_height
        return float(self.params.tire.unloaded_radius_m - deflection / 3.0)

    def reset(self, seed: int | None = None, speed_mps: float = 0.0) -> np.ndarray:
        """Start at rest (the paper's x0 = 0), or rolling straight at ``speed_mps`` for tests.

        The plant is deterministic; ``seed`` is accepted so every component resets alike.
        """
        del seed
        if not math.isfinite(speed_mps):
            raise ValueError(f"speed_mps must be finite (got {speed_mps})")
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = self._rest_qpos
        if speed_mps:
            self.data.qvel[self._free_dof] = speed_mps  # world x = heading at rest
            self.data.qvel[self._spin_dofs] = speed_mps / self._rolling_radius
        self.clipped_inputs = 0
        mujoco.mj_forward(self.model, self.data)
        return self.state

    def step(self, u: np.ndarray | tuple[float, float]) -> np.ndarray:
        """Hold ``u`` for one control period; out-of-range inputs are clipped and counted."""
        u = np.asarray(u, dtype=float)
        if u.shape != (2,):
            raise ValueError(f"input must be (steer_wheel_deg, pedal), got shape {u.shape}")
        if not np.all(np.isfinite(u)):
            raise ValueError(f"input must be finite, got {u.tolist()}")
        clipped = np.clip(u, self.input_low, self.input_high)
        if np.any(clipped != u):
            self.clipped_inputs += 1
        self.data.ctrl[:] = clipped
        mujoco.mj_step(self.model, self.data, nstep=self._substeps)
        warnings = self._warnings  # three integer reads: under a microsecond of a ~150 us step
        if warnings[_BADQACC] or warnings[_BADQVEL] or warnings[_BADQPOS]:
            self._check_stable("in a control step")
        return self.state

    def _check_stable(self, when: str) -> None:
        """Raise :class:`PlantUnstableError`, naming the keys to check, if MuJoCo warned that
        the simulation diverged (and reset it) since the last :meth:`reset`."""
        bad = [w for w in (_BADQACC, _BADQVEL, _BADQPOS) if self._warnings[w]]
        if not bad:
            return
        warning = mujoco.mjtWarning(bad[0])
        keys = changed_keys(self.params) or list(STIFFNESS_KEYS)
        raise PlantUnstableError(
            f"plant {self.params.name!r} diverged {when} (MuJoCo {warning.name}: NaN or huge "
            f"values, simulation reset): check {', '.join(keys)}, or make "
            "plant.physics_timestep_s smaller"
        )

    @property
    def state(self) -> np.ndarray:
        """(vx, vy, yaw_rate) of the centre of gravity in the yaw frame, SI."""
        velocity = self.data.qvel[self._free_dof : self._free_dof + 3]
        yaw = self.yaw
        cos, sin = np.cos(yaw), np.sin(yaw)
        vx = cos * velocity[0] + sin * velocity[1]
        vy = -sin * velocity[0] + cos * velocity[1]
        # Free-joint angular velocity is in the body frame; rotate to world, take z.
        omega_world = (
            self.data.xmat[self._chassis].reshape(3, 3)
            @ self.data.qvel[self._free_dof + 3 : self._free_dof + 6]
        )
        return np.array([vx, vy, omega_world[2]])

    @property
    def yaw(self) -> float:
        w, x, y, z = self.data.qpos[self._free_qpos + 3 : self._free_qpos + 7]
        return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))

    @property
    def pose(self) -> np.ndarray:
        """(X, Y, yaw) in the world frame, for display."""
        position = self.data.qpos[self._free_qpos : self._free_qpos + 2]
        return np.array([position[0], position[1], self.yaw])
