"""Traps of a linearising DE-MPC, one factor at a time, on a window of the paper-scale test drive.

``python -m bench.linearization_traps MODEL.pt [MODEL.pt ...] [--controllers de_mpc,...]
[--factor KEY=A|B|...] [--start-s 0] [--steps 3600] [--figure PNG]`` tracks ``--steps`` steps of
``data=paper``'s held-out test drive ``episode_0013`` from ``--start-s`` (rolling at the
reference's speed there) on the sedan with each controller config of ``conf/controller/``, once
per value of the one ``--factor`` (a key of the controller config), and prints one Markdown row
per run: the tracking RMSE, the largest speed error, and from the drive's start (``--start-s 0``)
how long after the reference the car first passes 1 m/s at the start and after the drive's first
stop, and the mean pedal over the stop's last 0.2 s. ``--figure PNG`` draws every run's vx and
pedal against the reference. A model is any ``model_<learner>.pt`` a run wrote.

The two traps in docs/findings/smooth_driving.md, each with its command there:

- *The standstill trap* (``--factor "release_brake=false|true"``, the default; the drive starts
  from rest, stops for 4.75 s at 22.4 s and drives off again at 27.2 s);
- *The pedal's flat tangent* (``--factor "input_secant_span=0|[0,0.2]" --start-s 100
  --steps 2500``: braking from 19 to 4 m/s in a turn at 109-118 s).

The dataset is collected into the cache on first use (about 10 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

EPISODE = "episode_0013"
STOP_END = 2719  # the step the reference leaves its first stop at 22.4-27.2 s
MOVING_MPS = 1.0


def _first_above(vx: np.ndarray, start: int) -> int | None:
    above = np.flatnonzero(vx[start:] > MOVING_MPS)
    return start + int(above[0]) if len(above) else None


def _lag(reference: int | None, car: int | None, dt: float) -> str:
    if reference is None:
        return "—"
    return "never" if car is None else f"{(car - reference) * dt:.2f}"


def _factor(text: str) -> tuple[str, list[str]]:
    """``KEY=A|B|...`` as (KEY, [A, B, ...]): values as Hydra overrides write them."""
    key, _, values = text.partition("=")
    if not key or not values:
        raise SystemExit(f"--factor must be KEY=A|B|... (got {text!r})")
    return key, values.split("|")


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", type=Path, help="model_<learner>.pt files")
    parser.add_argument("--controllers", default="de_mpc,de_mpc_path_long_offset_free")
    parser.add_argument("--factor", default="release_brake=false|true", type=_factor)
    parser.add_argument("--start-s", type=float, default=0.0, help="where the window starts")
    parser.add_argument("--steps", type=int, default=3600)
    parser.add_argument("--figure", type=Path, help="draw vx and pedal of every run")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")

    from hydra import compose, initialize_config_module
    from hydra.utils import instantiate

    from harness.config import as_object, register_configs
    from harness.data.driver import DriverKnowledge
    from harness.data.store import DataConfig, collect_counted, load
    from harness.evaluation.tracking import track
    from harness.plant import Sedan
    from harness.recorder import Recorder
    from learners import load as load_model

    register_configs()
    plant = Sedan()
    with initialize_config_module("conf", version_base=None):
        data_cfg = compose("config", overrides=["data=paper", "recorder=none"]).data
    directory, _ = collect_counted(
        plant, as_object(data_cfg, DataConfig), DriverKnowledge.of(plant.params), progress=False
    )
    episode = next(e for e in load(directory).test if e.name == EPISODE)
    first = round(args.start_s / plant.dt)
    reference = episode.states[first : first + args.steps]
    from_start = first == 0
    start_ref = _first_above(reference[:, 0], 0) if from_start else None
    go_ref = _first_above(reference[:, 0], STOP_END) if from_start else None
    key, values = args.factor
    print(
        f"| model | controller | {key} | RMSE vx / vy / r | largest vx error | start lag s | "
        "restart lag s | pedal at the stop's end |"
    )
    print("|---|---|---|---|---|---|---|---|")
    runs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for path in args.models:
        model = load_model(path)
        for name in args.controllers.split(","):
            for value in values:
                with initialize_config_module("conf", version_base=None):
                    overrides = [f"controller={name}", "recorder=none", f"controller.{key}={value}"]
                    cfg = compose("config", overrides=overrides)
                controller = instantiate(cfg.controller, _convert_="object")(model, plant.dt)
                metrics, run = track(plant, controller, reference, name="x", recorder=Recorder())
                vx, pedal = np.asarray(run.states)[:, 0], np.asarray(run.inputs)[:, 1]
                rmse = " / ".join(f"{metrics['rmse'][s]:.3g}" for s in ("vx", "vy", "yaw_rate"))
                worst = np.max(np.abs(vx - reference[: len(vx), 0]))
                start = _lag(start_ref, _first_above(vx, 0), plant.dt)
                restart = _lag(go_ref, _first_above(vx, STOP_END - 100), plant.dt)
                held = f"{pedal[STOP_END - 20 : STOP_END].mean():+.2f}" if from_start else "—"
                runs[f"{path.stem}, {name}, {key}={value}"] = (vx, pedal)
                print(
                    f"| {path.stem} | {name} | {value} | {rmse} | {worst:.2f} | {start} | "
                    f"{restart} | {held} |",
                    flush=True,
                )
    if args.figure:
        _draw(args.figure, reference[:, 0], runs, plant.dt, args.start_s)


def _draw(
    path: Path,
    reference: np.ndarray,
    runs: dict[str, tuple[np.ndarray, np.ndarray]],
    dt: float,
    start_s: float,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = sorted({label.split(",")[0] for label in runs})
    fig, axes = plt.subplots(
        len(models), 2, figsize=(13, 3.2 * len(models)), squeeze=False, width_ratios=(3, 2)
    )
    t = start_s + np.arange(len(reference)) * dt
    for (speed_ax, pedal_ax), model in zip(axes, models, strict=True):
        speed_ax.plot(t, reference, "k--", label="reference")
        for label, (vx, pedal) in runs.items():
            if label.startswith(model + ","):
                speed_ax.plot(t[: len(vx)], vx, label=label.split(", ", 1)[1])
                pedal_ax.plot(t[: len(pedal)], pedal, label=label.split(", ", 1)[1])
        speed_ax.set_title(model)
        speed_ax.set_ylabel("vx [m/s]")
        speed_ax.legend(fontsize=7)
        pedal_ax.set_ylabel("pedal [throttle; -MPa brake]")
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
