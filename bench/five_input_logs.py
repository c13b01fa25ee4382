"""Logs of another car with five inputs, made with the plant: a user's logs the harness never saw.

``python -m bench.five_input_logs OUT [--plant sedan_loaded] [--episodes 12] [--steps 3000]``
drives a plant variant (by default the sedan with 300 kg behind its centre of gravity: another
mass, yaw inertia and axle load split) with the synthetic driver and writes, per drive,
``OUT/logs/drive_<i>.csv`` with what a race car's logger records instead of the sedan's two
inputs:

- ``#delta_rad``: the road-wheel angle (rad), the steering wheel over the steering ratio;
- ``#T_fl_Nm``, ``#T_fr_Nm``: the front wheels' drive torques (N·m), the pedal's throttle as the
  powertrain's torque at the wheels (its peak torque, capped by its power at the wheel speed),
  halved by the open differential;
- ``#p_f_bar``, ``#p_r_bar``: the brake line pressures (bar), front at the master cylinder's and
  rear through a proportioning valve (above 2 MPa, 30 % of the rise);

with time, vx, vy and yaw rate, and ``OUT/data/five_input.yaml``, the config that reads them (every
input's role and unit). Then ``python -m harness -cd OUT data=five_input learner=<l>`` runs any
learner on them as on anyone's logs, and ``task.logs_from_plant`` stays false: the models see
five inputs the plant does not take.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import numpy as np

COLUMNS = ("#t_s", "#vx_mps", "#vy_mps", "#r_radps")
INPUTS = ("#delta_rad", "#T_fl_Nm", "#T_fr_Nm", "#p_f_bar", "#p_r_bar")
KNEE_MPA, REAR_SLOPE = 2.0, 0.3  # the proportioning valve: rear pressure above the knee


def logged_inputs(inputs: np.ndarray, vx: np.ndarray, params: object) -> np.ndarray:
    """(T, 5) the logger's inputs of the sedan's (T, 2) inputs at speeds ``vx`` (m/s)."""
    steering = params.steering  # type: ignore[attr-defined]
    powertrain = params.powertrain  # type: ignore[attr-defined]
    radius = params.tire.unloaded_radius_m  # type: ignore[attr-defined]
    from harness.core.limits import THROTTLE_MAX

    steer_deg, pedal = inputs[:, 0], inputs[:, 1]
    delta = np.deg2rad(steer_deg) / steering.steering_ratio
    wheel_speed = np.maximum(np.abs(vx) / radius, 1.0)
    available = np.minimum(powertrain.peak_wheel_torque_nm, powertrain.max_power_w / wheel_speed)
    torque = np.clip(pedal, 0.0, None) / THROTTLE_MAX * available / 2.0
    pressure = np.clip(-pedal, 0.0, None)  # MPa
    rear = np.where(pressure > KNEE_MPA, KNEE_MPA + REAR_SLOPE * (pressure - KNEE_MPA), pressure)
    return np.column_stack([delta, torque, torque, 10.0 * pressure, 10.0 * rear])


CONFIG = """\
# Logs of the plant variant {plant} with five inputs (bench/five_input_logs.py).
defaults:
  - logs_schema
  - _self_
name: five_input
path: {path}
files: ["drive_*.csv"]
time: {{column: "#t_s"}}
states:
  vx: {{column: "#vx_mps"}}
  vy: {{column: "#vy_mps"}}
  yaw_rate: {{column: "#r_radps"}}
inputs:
  delta_rad: {{column: "#delta_rad", role: road_wheel, unit: rad}}
  torque_fl: {{column: "#T_fl_Nm", role: drive, unit: N*m}}
  torque_fr: {{column: "#T_fr_Nm", role: drive, unit: N*m}}
  brake_front: {{column: "#p_f_bar", role: brake, unit: bar}}
  brake_rear: {{column: "#p_r_bar", role: brake, unit: bar}}
split: {{train: 0.7, validation: 0.15, test: 0.15}}
"""


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--plant", default="sedan_loaded")
    parser.add_argument("--episodes", type=int, default=12)
    parser.add_argument("--steps", type=int, default=3000)
    args = parser.parse_args(argv)

    from hydra import compose, initialize_config_module
    from hydra.utils import instantiate

    from harness.config import register_configs
    from harness.data.driver import DriverKnowledge
    from harness.data.store import DataConfig, drive_episode

    register_configs()
    with initialize_config_module("conf", version_base=None):
        cfg = compose("config", overrides=[f"plant={args.plant}"])
    plant = instantiate(cfg.plant)
    logs = args.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    data = DataConfig()
    knowledge = DriverKnowledge.of(plant.params)
    for index in range(args.episodes):
        drive = drive_episode(plant, data, knowledge, index, args.steps)
        states, inputs = np.asarray(drive["states"]), np.asarray(drive["inputs"])
        table = np.column_stack(
            [drive["time_s"], states, logged_inputs(inputs, states[:, 0], plant.params)]
        )
        header = ",".join((*COLUMNS, *INPUTS))
        np.savetxt(logs / f"drive_{index}.csv", table, delimiter=",", header=header, comments="")
        print(f"drive_{index}: {len(table)} rows")
    config = args.out / "data" / "five_input.yaml"
    config.parent.mkdir(parents=True, exist_ok=True)
    config.write_text(CONFIG.format(plant=args.plant, path=logs.resolve()))
    print(f"wrote {config}: python -m harness -cd {args.out} data=five_input learner=<learner>")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
