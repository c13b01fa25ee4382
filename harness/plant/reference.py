"""A line-by-line Python port of ``vehicle_forces.c``, for checking the C and for benchmarks.

Not used by the plant: it is ~10x slower. ``tests/test_native.py`` asserts that both write the
same generalized forces, and ``bench/plant_throughput.py`` times both in one run.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from harness.plant.native import LAYOUT_KEY_VALUE, PARAM_INDEX


def _magic_formula(s: float, b: float, c: float, d: float, e: float) -> float:
    bs = b * s
    return d * math.sin(c * math.atan(bs - e * (bs - math.atan(bs))))


def _combined_weight(s: float, b: float, c: float) -> float:
    return max(math.cos(c * math.atan(b * s)), 0.0)


def _longitudinal_force(kappa: float, alpha: float, kx: float, dx: float, p) -> float:
    fx0 = _magic_formula(kappa, kx / (p.SHAPE_X * dx), p.SHAPE_X, dx, p.CURV_X)
    bxa = p.RBX1 * math.cos(math.atan(p.RBX2 * kappa))
    return _combined_weight(alpha, bxa, p.RCX1) * fx0


def _friction_torque(torque: float, omega: float, inertia: float, dt: float, gain: float) -> float:
    limit = gain * inertia * abs(omega) / dt
    return -math.copysign(1.0, omega) * min(torque, limit) if omega != 0 else 0.0


class _Params:
    def __init__(self, values: np.ndarray) -> None:
        for name, index in PARAM_INDEX.items():
            setattr(self, name, float(values[index]))


def vehicle_control(m: mujoco.MjModel, d: mujoco.MjData) -> None:
    """Same signature and effect as the C ``vehicle_control``."""
    try:
        values = m.numeric("vehicle_params").data
    except KeyError:
        return
    if len(values) != len(PARAM_INDEX) or values[0] != LAYOUT_KEY_VALUE:
        return
    p = _Params(values)
    d.qfrc_applied[:] = 0.0
    steer_wheel_deg = d.ctrl[int(p.CTRL_STEER)]
    pedal = d.ctrl[int(p.CTRL_PEDAL)]
    throttle, brake_mpa = max(pedal, 0.0), max(-pedal, 0.0)

    delta = math.radians(steer_wheel_deg) / p.STEERING_RATIO
    _steering_and_anti_roll(d, p, delta)
    spin_dofs = [int(getattr(p, f"SPIN_DOF_{j}")) for j in range(4)]
    omega_diff = 0.5 * (d.qvel[spin_dofs[0]] + d.qvel[spin_dofs[1]])
    axle_torque = 0.0
    if throttle > 0:
        w = max(abs(omega_diff), 1e-3)
        axle_torque = throttle * min(p.MAX_POWER / w, p.PEAK_TORQUE)

    chassis = int(p.CHASSIS_BODY)
    chassis_dof = m.jnt_dofadr[m.body_jntadr[chassis]]
    vel = np.zeros(6)
    zero3 = np.zeros(3)
    for j in range(4):
        _tyre(m, d, p, j, spin_dofs[j], axle_torque, brake_mpa, chassis_dof, vel)
    mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, chassis, vel, 0)
    speed = math.hypot(vel[3], vel[4])
    drag = 0.5 * p.AIR_DENSITY * p.DRAG_AREA * speed
    mujoco.mj_applyFT(
        m,
        d,
        np.array([-drag * vel[3], -drag * vel[4], 0.0]),
        zero3,
        d.xipos[chassis].copy(),
        chassis,
        d.qfrc_applied,
    )


def _steering_and_anti_roll(d: mujoco.MjData, p: _Params, delta: float) -> None:
    """The front wheels' steering servos (to the Ackermann angles of road-wheel angle
    ``delta``) and each axle's anti-roll bar, as generalized forces."""
    targets = [delta, delta]
    if abs(delta) > 1e-9:
        turn_radius = p.WHEELBASE / math.tan(delta)
        half_track = 0.5 * p.TRACK_FRONT
        targets = [
            (1 - p.ACKERMANN) * delta
            + p.ACKERMANN * math.atan(p.WHEELBASE / (turn_radius - half_track)),
            (1 - p.ACKERMANN) * delta
            + p.ACKERMANN * math.atan(p.WHEELBASE / (turn_radius + half_track)),
        ]
    for k in range(2):
        qadr, vadr = int(getattr(p, f"STEER_QPOS_{k}")), int(getattr(p, f"STEER_DOF_{k}"))
        d.qfrc_applied[vadr] += p.SERVO_KP * (targets[k] - d.qpos[qadr]) - p.SERVO_KD * d.qvel[vadr]

    for axle in range(2):
        left, right = 2 * axle, 2 * axle + 1
        k_arb = p.ARB_FRONT if axle == 0 else p.ARB_REAR
        twist = (
            d.qpos[int(getattr(p, f"SUSP_QPOS_{left}"))]
            - d.qpos[int(getattr(p, f"SUSP_QPOS_{right}"))]
        )
        d.qfrc_applied[int(getattr(p, f"SUSP_DOF_{left}"))] -= k_arb * twist
        d.qfrc_applied[int(getattr(p, f"SUSP_DOF_{right}"))] += k_arb * twist


def _tyre(
    m: mujoco.MjModel,
    d: mujoco.MjData,
    p: _Params,
    j: int,
    spin: int,
    axle_torque: float,
    brake_mpa: float,
    chassis_dof: int,
    vel: np.ndarray,
) -> None:
    """Wheel ``j``'s drive, brake and rolling-resistance torque on its spin joint, and its
    tyre's contact force at the ground (combined-slip magic formula), on the body."""
    dt = m.opt.timestep
    zero3 = np.zeros(3)
    body = int(getattr(p, f"WHEEL_BODY_{j}"))
    front = j < 2
    center = d.xpos[body]
    rot = d.xmat[body]
    axis = np.array([rot[1], rot[4], rot[7]])
    mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, body, vel, 0)
    omega = float(vel[:3] @ axis)
    omega_rel = d.qvel[spin]

    height = center[2]
    deflection = p.UNLOADED_RADIUS - height
    fz = max(p.TIRE_KZ * deflection - p.TIRE_CZ * vel[5], 0.0) if deflection > 0 else 0.0

    spin_inertia = m.body_inertia[body, 1] + m.dof_armature[spin]
    torque = 0.0
    if front:
        omega_max = p.MAX_WHEEL_SPEED
        taper = min(max((omega_max - abs(omega_rel)) / (0.1 * omega_max), 0.0), 1.0)
        torque += 0.5 * axle_torque * taper
    brake_torque = brake_mpa * (p.BRAKE_FRONT if front else p.BRAKE_REAR)
    resist_torque = p.ROLLING_RESISTANCE * fz * max(height, 0.0)
    torque += _friction_torque(
        brake_torque + resist_torque, omega_rel, spin_inertia, dt, p.SLIP_LIMITER_GAIN
    )
    d.qfrc_applied[spin] += torque
    if fz <= 0:
        return

    ex = np.array([axis[1], -axis[0], 0.0])
    norm = math.hypot(ex[0], ex[1])
    if norm < 1e-6:
        return
    ex /= norm
    ey = np.array([-ex[1], ex[0], 0.0])
    vx = vel[3] * ex[0] + vel[4] * ex[1]
    vy = vel[3] * ey[0] + vel[4] * ey[1]

    rolling_radius = p.UNLOADED_RADIUS - deflection / 3.0
    slip_velocity = vx - omega * rolling_radius
    denom = max(abs(vx), p.SLIP_SPEED_MIN)
    kappa = -slip_velocity / denom
    alpha = math.atan2(vy, denom)

    fx, fy, kx, dx = _slip_forces(p, fz, kappa, alpha, front)

    h = 1e-4
    dfx_dkappa = (
        _longitudinal_force(kappa + h, alpha, kx, dx, p)
        - _longitudinal_force(kappa - h, alpha, kx, dx, p)
    ) / (2 * h)
    dfx_dvs = min(-dfx_dkappa / denom, 0.0)
    accel = d.qacc_warmstart[chassis_dof] * ex[0] + d.qacc_warmstart[chassis_dof + 1] * ex[1]
    r_over_i = rolling_radius / spin_inertia
    vs_rate = accel - r_over_i * (torque - fx * rolling_radius)
    vs_change = dt * vs_rate / (1 - dt * rolling_radius * r_over_i * dfx_dvs)
    fx += dfx_dvs * vs_change

    limit_y = p.SLIP_LIMITER_GAIN * 0.25 * p.TOTAL_MASS * abs(vy) / dt
    fy = min(max(fy, -limit_y), limit_y)

    force = np.array([fx * ex[0] + fy * ey[0], fx * ex[1] + fy * ey[1], fz])
    point = np.array([center[0], center[1], 0.0])
    mujoco.mj_applyFT(m, d, force, zero3, point, body, d.qfrc_applied)


def _slip_forces(
    p: _Params, fz: float, kappa: float, alpha: float, front: bool
) -> tuple[float, float, float, float]:
    """(Fx, Fy) of the combined-slip magic formula at load ``fz``, slip ratio ``kappa`` and slip
    angle ``alpha``; with the longitudinal slip stiffness and peak (kx, dx) they came from."""
    fz0 = p.NOMINAL_LOAD
    dfz = (fz - fz0) / fz0
    dx = max(p.ROAD_FRICTION * (1 + p.LOAD_SENS_X * dfz) * fz, 1e-3)
    dy = max(p.ROAD_FRICTION * (1 + p.LOAD_SENS_Y * dfz) * fz, 1e-3)
    kx = p.SLIP_STIFFNESS * fz
    shape = p.CORNERING_LOAD_SHAPE
    ky = (
        (p.CORNERING_FRONT if front else p.CORNERING_REAR)
        * fz0
        * math.sin(2 * math.atan(fz / (shape * fz0)))
        / math.sin(2 * math.atan(1 / shape))
    )
    fy0 = -_magic_formula(alpha, ky / (p.SHAPE_Y * dy), p.SHAPE_Y, dy, p.CURV_Y)
    fx = _longitudinal_force(kappa, alpha, kx, dx, p)
    byk = p.RBY1 * math.cos(math.atan(p.RBY2 * alpha))
    return fx, _combined_weight(kappa, byk, p.RCY1) * fy0, kx, dx
