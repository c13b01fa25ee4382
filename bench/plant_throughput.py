"""Plant throughput: one car driven in closed loop at 10 ms, physics at 1 ms.

Ours (C callback) against the same model with the force callback in Python, in one run, plus
the aggregate rate of MuJoCo's threaded rollout over two cores. Target: >= 50x real time per
core. Run: ``python bench/plant_throughput.py [--seconds 60]``.
"""

from __future__ import annotations

import argparse
import time

import mujoco
import mujoco.rollout
import numpy as np

from bench.machine import describe
from harness.plant import Sedan, native, reference


def driver_inputs(steps: int, dt: float) -> np.ndarray:
    """Slalom-and-speed-change inputs a test driver might give (no feedback needed)."""
    t = np.arange(steps) * dt
    steer = 120.0 * np.sin(2 * np.pi * 0.2 * t) + 60.0 * np.sin(2 * np.pi * 0.53 * t)
    pedal = np.where(np.sin(2 * np.pi * 0.05 * t) > -0.3, 0.15, -2.0)
    return np.column_stack([steer, pedal])


def time_closed_loop(plant: Sedan, inputs: np.ndarray) -> float:
    plant.reset(speed_mps=15.0)
    start = time.perf_counter()
    for u in inputs:
        x = plant.step(u)
        if not np.isfinite(x[0]):
            raise RuntimeError("plant diverged during the benchmark")
    return time.perf_counter() - start


def time_rollout(plant: Sedan, inputs: np.ndarray, batch: int, threads: int) -> float:
    substeps = plant.params.substeps
    control = np.repeat(inputs, substeps, axis=0)[None].repeat(batch, axis=0)
    plant.reset(speed_mps=15.0)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.empty(mujoco.mj_stateSize(plant.model, spec))
    mujoco.mj_getState(plant.model, plant.data, state, spec)
    datas = [mujoco.MjData(plant.model) for _ in range(threads)]
    start = time.perf_counter()
    mujoco.rollout.rollout(plant.model, datas, state[None].repeat(batch, axis=0), control)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per run")
    args = parser.parse_args()
    plant = Sedan()
    steps = int(args.seconds / plant.dt)
    physics_steps = steps * plant.params.substeps
    inputs = driver_inputs(steps, plant.dt)
    rows = []

    wall_c = time_closed_loop(plant, inputs)
    rows.append(
        ("C callback, closed loop (ours)", 1, physics_steps / wall_c, args.seconds / wall_c)
    )

    mujoco.set_mjcb_control(reference.vehicle_control)
    try:
        short = max(steps // 10, 1)
        wall_py = time_closed_loop(plant, inputs[:short]) * steps / short
    finally:
        mujoco.set_mjcb_control(None)
        native.install_callback()
    rows.append(
        ("Python callback, closed loop", 1, physics_steps / wall_py, args.seconds / wall_py)
    )

    batch = 8
    wall_rollout = time_rollout(plant, inputs, batch, threads=2)
    rows.append(
        (
            "C callback, mujoco.rollout 2 threads",
            2,
            batch * physics_steps / wall_rollout,
            batch * args.seconds / wall_rollout,
        )
    )

    print(f"machine: {describe()}")
    print(
        f"simulated {args.seconds:.0f} s per car, "
        f"physics dt {plant.model.opt.timestep * 1e3:.1f} ms"
    )
    print(f"| {'plant':<38} | threads | physics steps/s | real-time factor | vs Python |")
    print(f"|{'-' * 40}|---------|-----------------|------------------|-----------|")
    for name, threads, rate, rtf in rows:
        print(
            f"| {name:<38} | {threads:>7} | {rate:>15,.0f} | {rtf:>15.0f}x "
            f"| {rate / rows[1][2]:>8.1f}x |"
        )


if __name__ == "__main__":
    main()
