"""The standstill trap, one factor: DE-MPC with and without ``release_brake`` from a stop.

``python -m bench.standstill MODEL.pt [MODEL.pt ...] [--controllers de_mpc,...] [--steps 3600]``
tracks the first ``--steps`` steps of ``data=paper``'s held-out test drive ``episode_0013`` (it
starts from rest, stops for 4.75 s at 22.4 s and drives off again at 27.2 s) on the sedan with
each controller config of ``conf/controller/``, once with ``controller.release_brake=false`` and
once with ``true``, and prints one Markdown row per run: the tracking RMSE, how long after the
reference the car first passes 1 m/s at the start and after the stop, and the mean pedal over
the last 0.2 s of the stop; ``--figure PNG`` draws every run's vx against the reference. A model
is any ``model_<learner>.pt`` a run wrote (trained on
``data=paper`` for the numbers in docs/control.md, "The standstill trap"). The dataset is
collected into the cache on first use (about 10 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

EPISODE = "episode_0013"
STOP_END = 2719  # the step the reference leaves its stop at 22.4-27.2 s
MOVING_MPS = 1.0


def _first_above(vx: np.ndarray, start: int) -> int | None:
    above = np.flatnonzero(vx[start:] > MOVING_MPS)
    return start + int(above[0]) if len(above) else None


def _lag(reference: int | None, car: int | None, dt: float) -> str:
    if reference is None:
        return "—"
    return "never" if car is None else f"{(car - reference) * dt:.2f}"


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", type=Path, help="model_<learner>.pt files")
    parser.add_argument("--controllers", default="de_mpc,de_mpc_path_long_offset_free")
    parser.add_argument("--steps", type=int, default=3600)
    parser.add_argument("--figure", type=Path, help="draw vx of every run against the reference")
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
    reference = episode.states[: args.steps]
    start_ref, go_ref = _first_above(reference[:, 0], 0), _first_above(reference[:, 0], STOP_END)
    print(
        "| model | controller | release_brake | RMSE vx / vy / r | start lag s | "
        "restart lag s | pedal at the stop's end |"
    )
    print("|---|---|---|---|---|---|---|")
    runs: dict[str, np.ndarray] = {}
    for path in args.models:
        model = load_model(path)
        for name in args.controllers.split(","):
            for release in ("false", "true"):
                with initialize_config_module("conf", version_base=None):
                    cfg = compose(
                        "config",
                        overrides=[
                            f"controller={name}",
                            "recorder=none",
                            f"controller.release_brake={release}",
                        ],
                    )
                controller = instantiate(cfg.controller, _convert_="object")(model, plant.dt)
                metrics, run = track(plant, controller, reference, name="x", recorder=Recorder())
                vx, pedal = np.asarray(run.states)[:, 0], np.asarray(run.inputs)[:, 1]
                rmse = " / ".join(f"{metrics['rmse'][s]:.3g}" for s in ("vx", "vy", "yaw_rate"))
                start = _lag(start_ref, _first_above(vx, 0), plant.dt)
                restart = _lag(go_ref, _first_above(vx, STOP_END - 100), plant.dt)
                held = pedal[STOP_END - 20 : STOP_END].mean()
                runs[f"{path.stem}, {name}, release_brake={release}"] = vx
                print(
                    f"| {path.stem} | {name} | {release} | {rmse} | {start} | {restart} | "
                    f"{held:+.2f} |",
                    flush=True,
                )
    if args.figure:
        _draw(args.figure, reference[:, 0], runs, plant.dt)


def _draw(path: Path, reference: np.ndarray, runs: dict[str, np.ndarray], dt: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = sorted({label.split(",")[0] for label in runs})
    fig, axes = plt.subplots(len(models), 1, figsize=(9, 3.2 * len(models)), squeeze=False)
    t = np.arange(len(reference)) * dt
    for ax, model in zip(axes[:, 0], models, strict=True):
        ax.plot(t, reference, "k--", label="reference")
        for label, vx in runs.items():
            if label.startswith(model + ","):
                ax.plot(t[: len(vx)], vx, label=label.split(", ", 1)[1])
        ax.set_title(model)
        ax.set_ylabel("vx [m/s]")
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
