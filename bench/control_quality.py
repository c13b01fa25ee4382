"""How smoothly the main job's controller drives each learned model, one factor changed at a time.

``python -m bench.control_quality --arm NAME [overrides...] --learners deep_edmd,dnn,input_edmd
--seeds 0,1,2 --jsonl FILE`` composes the main job as ``python -m harness`` would (``conf/``,
``data=default``), fits each learner once per seed and set of kernels (kept in
``~/.cache/koopman-harness/bench/``, so that every arm drives the same models; an arm's
``learner.`` overrides fit models of their own), then drives the main controller and the
physics baseline beside it (``bicycle_mpc_path_long_offset_free``, identified from the same
drives) through the job's references: the test drive and the 80 km/h lane change. The overrides
are Hydra's and apply to the main controller (``controller.R=[5000,50]``); ``--both`` applies each
``controller.`` override to the baseline too, so that a change meant for every controller is
judged against the baseline it would give.

Each row (``--jsonl`` appends it; ``--table FILE`` prints a file's rows, averaged over seeds):
the lane change's verdict (max deviation m, cones), the tracking RMSE (vx m/s, yaw rate rad/s),
and ``tracking…quality``: steering reversals per minute (``reversals_stopped``: how many of
them came below 1 m/s, at a stop), throttle-brake changes (a count, the
per minute), longitudinal jerk RMS m/s³, steering-wheel rate RMS deg/s,
each with its ratio to the baseline's in the same arm. ``--slopes`` prints what the pedal does
at 80 km/h, the plant against each fitted model (the models of the arms; an arm with another data
setting, such as ``data.pedal_gains``, has a dataset key and models of its own); ``--slalom``
how much each swings vx through a slalom at a constant brake, where the plant barely does;
``--steering`` the yaw rate a wheel step gives at 80 km/h.
The findings of docs/findings/smooth_driving.md ran on this. Run arms two at a time on two
cores (one thread each).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
from collections import defaultdict
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

MAIN = "main"
BASELINE = "baseline"
BASELINE_CONFIG = "bicycle_mpc_path_long_offset_free"
MODELS = Path(os.path.expanduser("~/.cache/koopman-harness/bench/control_quality"))
COLUMNS = ("reversals", "pedal_changes", "long_jerk", "steer_rate")
STOPPED_MPS = 1.0  # a reversal below this |vx| is counted as one at a stop (``reversals_stopped``)


def _compose(learner: str, seed: int, overrides: Sequence[str], both: bool) -> Any:
    from hydra import compose, initialize_config_module

    from harness.config import register_configs

    register_configs()
    baseline = [
        f"+task.extra_controllers.{BASELINE_CONFIG}.{o.removeprefix('controller.')}"
        if o.startswith("controller.")
        else o
        for o in overrides
        if both and o.startswith("controller.")
    ]
    with initialize_config_module("conf", version_base=None):
        cfg = compose(
            "config",
            overrides=[
                f"learner={learner}",
                f"seed={seed}",
                "recorder=none",
                f"task.learner_name={learner}",  # Hydra's runtime choices, unset without a run
                "task.controller_name=main",
                *overrides,
            ],
        )
    for override in baseline:  # the baseline's block holds every DE-MPC key: set, not added
        key, value = override.removeprefix("+").split("=", 1)
        from omegaconf import OmegaConf

        OmegaConf.update(cfg, key, OmegaConf.create({"v": _yaml(value)})["v"], merge=False)
    return cfg


def _yaml(text: str) -> Any:
    import yaml

    return yaml.safe_load(text)


def _model_name(learner: str, overrides: Sequence[str]) -> str:
    """The kept model's name: the preset's, and a digest of the arm's ``learner.`` overrides,
    so that an arm that changes the learner fits its own model instead of driving the preset's."""
    changed = sorted(o for o in overrides if o.lstrip("+~").startswith("learner."))
    if not changed:
        return learner
    return f"{learner}-{hashlib.sha1(' '.join(changed).encode()).hexdigest()[:8]}"


def _fitted(pipeline: Any, dataset: Any, name: str, seed: int) -> Any:
    """The learner fitted on the dataset's training drives, once per (model name, seed, data,
    kernels): a model trained on other kernels is another model (harness/core/kernels.py)."""
    from harness.core.kernels import in_force
    from learners.model_file import load

    kernels = hashlib.sha1(json.dumps(in_force(), sort_keys=True).encode()).hexdigest()[:8]
    path = MODELS / f"{name}_seed{seed}_{dataset.key}_{kernels}.pt"
    if path.exists():
        return load(path)
    fitted = pipeline.learner.fit(dataset.train, dataset.validation, dataset.normalizer)
    path.parent.mkdir(parents=True, exist_ok=True)
    fitted.save(path, {})
    return fitted


def run_arm(arm: str, overrides: Sequence[str], learner: str, seed: int, both: bool) -> list[dict]:
    from hydra.utils import instantiate

    from harness.core.threads import use_threads
    from harness.data.collect import data_config
    from harness.data.driver import DriverKnowledge
    from harness.data.store import DataConfig, collect_counted, load
    from harness.recorder import Recorder

    use_threads(1)
    cfg = _compose(learner, seed, overrides, both)
    plant = instantiate(cfg.plant)
    pipeline = instantiate(cfg.task)
    loops = pipeline.closed_loops
    loops.controllers = {
        MAIN: next(iter(loops.controllers.values())),  # the run's controller comes first
        BASELINE: loops.controllers[BASELINE_CONFIG],
    }
    data = data_config(cfg.data)
    if not isinstance(data, DataConfig):
        raise ValueError("bench.control_quality drives the sedan: data= must be a preset, not logs")
    directory, _ = collect_counted(plant, data, DriverKnowledge.of(plant.params), progress=False)
    dataset = load(directory)
    model = _fitted(pipeline, dataset, _model_name(learner, overrides), seed)
    models = loops.models(model, dataset)
    loops.reuse_baseline_runs = False
    with tempfile.TemporaryDirectory() as output:
        tracking = loops.track(
            models, plant, dataset.test, Recorder(), Path(output), data_key=dataset.key
        )
        assert tracking is not None
        stopped = {
            (controller, reference): _reversals_below(
                Path(output) / f"tracking_{controller}_{name}.npz", STOPPED_MPS
            )
            for controller, references in tracking["controllers"].items()
            for name, reference in zip(loops.references, references, strict=True)
        }
    rows = []
    for controller, references in tracking["controllers"].items():
        for reference, metrics in references.items():
            quality, path = metrics["quality"], metrics.get("path") or {}
            rows.append(
                {
                    "arm": arm,
                    "overrides": list(overrides),
                    "both": both,
                    "learner": learner,
                    "seed": seed,
                    "controller": controller,
                    "reference": reference,
                    "max_deviation_m": path.get("max_lateral_deviation_m"),
                    "cones": path.get("cones_hit"),
                    "rmse_vx": metrics["rmse"]["vx"],
                    "rmse_yaw_rate": metrics["rmse"]["yaw_rate"],
                    "reversals": quality["steering_reversals_per_min"],
                    "reversals_stopped": stopped[controller, reference],
                    "pedal_changes": quality["pedal_changes_per_min"],
                    "long_jerk": quality["long_jerk_rms_mps3"],
                    "steer_rate": quality["steer_rate_rms_deg_s"],
                    "step_ms_p99": metrics["step_time_ms"]["p99"],
                }
            )
    return rows


def _reversals_below(arrays: Path, speed_mps: float) -> int:
    """The run's steering reversals (``harness/evaluation/quality.py``'s) at a measured
    |vx| below ``speed_mps``: a wheel sawing at a stop, where it steers nothing."""
    from harness.evaluation.quality import STEER_RATE_THRESHOLD_DEG_S, reversals

    run = np.load(arrays)
    dt = float(run["time_s"][1] - run["time_s"][0])
    rate = np.diff(run["inputs"][:, 0]) / dt
    slow = np.abs(run["states"][1:, 0]) < speed_mps
    return reversals(rate, STEER_RATE_THRESHOLD_DEG_S, where=slow)


def mean(key: str, rows: Sequence[dict]) -> float:
    """The mean of ``key`` over ``rows`` where it is known (NaN where it never is)."""
    values = [r[key] for r in rows if r[key] is not None]
    return float(np.mean(values)) if values else float("nan")


def table(rows: Sequence[dict]) -> str:
    """Per arm, learner and reference: the mean over seeds, and the ratio to the baseline's."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for row in rows:
        key = (row["arm"], row["learner"], row["reference"], row["controller"])
        groups[key].append(row)
    lines = [
        "| arm | model | reference | seeds | max dev m · cones | vx / r RMSE | reversals /min "
        "(× baseline) | throttle-brake /min (baseline) | long. jerk m/s³ (× baseline) | "
        "wheel rate deg/s | step p99 ms |",
        "|" + "---|" * 11,
    ]
    for (arm, learner, reference, controller), members in groups.items():
        if controller != MAIN:
            continue
        base = groups.get((arm, learner, reference, BASELINE), [])

        def ratio(key: str, members: Sequence[dict] = members, base: Sequence[dict] = base) -> str:
            value, bar = mean(key, members), mean(key, base)
            return f"{value:.2f} (×{value / bar:.1f})" if bar > 0 else f"{value:.2f}"

        verdict = (
            f"{mean('max_deviation_m', members):.2f} · {mean('cones', members):.1f}"
            if members[0]["cones"] is not None
            else "-"
        )
        lines.append(
            f"| {arm} | {learner} | {reference} | {len(members)} | {verdict} | "
            f"{mean('rmse_vx', members):.3f} / {mean('rmse_yaw_rate', members):.4f} | "
            f"{ratio('reversals')} | {mean('pedal_changes', members):.1f} "
            f"({mean('pedal_changes', base):.1f}) | {ratio('long_jerk')} | "
            f"{mean('steer_rate', members):.1f} | {mean('step_ms_p99', members):.2f} |"
        )
    return "\n".join(lines)


PEDALS = (-2.0, -1.0, -0.3, 0.0, 0.05, 0.1, 0.2)  # brake in -MPa, throttle 0..0.2


def pedal_slopes(learner: str, seeds: Sequence[int], speed_mps: float = 22.2) -> str:
    """What the pedal does at ``speed_mps`` straight ahead, the plant against each fitted model:
    the mean longitudinal acceleration (m/s²) over 0.2-0.5 s of a pedal held from rest-rolling."""
    from harness.plant import Sedan
    from learners.model_file import load

    lines = [
        f"| model | {' | '.join(f'{p:+g}' for p in PEDALS)} |",
        "|" + "---|" * (len(PEDALS) + 1),
    ]

    def acceleration(vx: np.ndarray) -> float:
        return float((vx[50] - vx[20]) / 0.3)

    plant_row = []
    for pedal in PEDALS:
        plant = Sedan()
        states = [plant.reset(speed_mps=speed_mps)]
        states += [plant.step(np.array([0.0, pedal])) for _ in range(50)]
        plant_row.append(acceleration(np.array(states)[:, 0]))
    lines.append("| plant | " + " | ".join(f"{a:+.2f}" for a in plant_row) + " |")
    for seed in seeds:
        for path in sorted(MODELS.glob(f"{learner}_seed{seed}_*.pt")):  # one per dataset
            model = load(path)
            row = []
            for pedal in PEDALS:
                inputs = np.tile([0.0, pedal], (50, 1))
                x0 = np.array([speed_mps, 0.0, 0.0])
                row.append(acceleration(model.predict(x0, inputs)[:, 0]))
            data = path.stem.rsplit("_", 1)[-1]
            cells = " | ".join(f"{a:+.2f}" for a in row)
            lines.append(f"| {learner} seed {seed} (data {data}) | {cells} |")
    return "\n".join(lines)


SLALOM = {"speed_mps": 12.0, "steer_deg": 80.0, "frequency_hz": 0.6, "brake_mpa": 0.9, "s": 3.0}
STEER_STEP = {"speed_mps": 22.2, "steer_deg": 20.0, "throttle": 0.05, "steps": (1, 3, 10, 40)}


def _plant_answer(speed_mps: float, inputs: np.ndarray) -> np.ndarray:
    """The sedan's states (T + 1, 3) from ``speed_mps`` straight ahead under ``inputs``."""
    from harness.plant import Sedan

    plant = Sedan()
    states = [plant.reset(speed_mps=speed_mps)]
    states += [plant.step(u) for u in inputs]
    return np.array(states)


def _model_answers(
    learner: str, seeds: Sequence[int], x0: np.ndarray, inputs: np.ndarray
) -> Iterator[tuple[str, np.ndarray, np.ndarray | None]]:
    """Per fitted model of the arms: its name, its ``predict`` from ``x0`` under ``inputs`` and,
    for a lifted-linear model, its read-out C z (what DE-MPC predicts with; None otherwise)."""
    from harness.core.contracts import dynamics_of
    from learners.model_file import load

    for seed in seeds:
        for path in sorted(MODELS.glob(f"{learner}_seed{seed}_*.pt")):  # one per dataset
            model = load(path)
            readout = None
            if dynamics_of(model) == "linear":
                normalizer = model.normalizer_
                z, lifted = model.lift(x0), [x0]
                for v in normalizer.inputs(inputs):
                    z = model.A_ @ z + model.B_ @ v
                    lifted.append(normalizer.states_inverse(model.C_ @ z))
                readout = np.array(lifted)
            name = f"{learner} seed {seed} (data {path.stem.rsplit('_', 1)[-1]})"
            yield name, model.predict(x0, inputs), readout


def slalom_swings(learner: str, seeds: Sequence[int]) -> str:
    """How much each model swings vx through a slalom at a constant brake, against the plant:
    the RMS of vx about its linear trend after the first second (m/s), by ``predict`` and, for a
    lifted-linear model, by the read-out C z that DE-MPC predicts with; and the mean
    deceleration (m/s²). A car's cornering drag is even in the steering: it barely swings."""
    dt = 0.01
    time = np.arange(round(SLALOM["s"] / dt)) * dt
    steer = SLALOM["steer_deg"] * np.sin(2 * np.pi * SLALOM["frequency_hz"] * time)
    inputs = np.c_[steer, np.full_like(time, -SLALOM["brake_mpa"])]
    truth = _plant_answer(SLALOM["speed_mps"], inputs)
    clock = np.arange(len(truth)) * dt

    def swing(vx: np.ndarray) -> str:
        fit = np.polyfit(clock, vx, 1)
        residual = vx - np.polyval(fit, clock)
        return f"{np.sqrt(np.mean(residual[round(1 / dt) :] ** 2)):.3f} | {fit[0]:+.2f}"

    lines = [
        "| model | vx swing m/s | mean decel. m/s² | read-out C z: swing | decel. |",
        "|---|---|---|---|---|",
        f"| plant | {swing(truth[:, 0])} | - | - |",
    ]
    for name, predicted, readout in _model_answers(learner, seeds, truth[0], inputs):
        lifted = "- | -" if readout is None else swing(readout[:, 0])
        lines.append(f"| {name} | {swing(predicted[:, 0])} | {lifted} |")
    return "\n".join(lines)


def steering_steps(learner: str, seeds: Sequence[int]) -> str:
    """The yaw rate (rad/s) a held wheel step gives at 80 km/h after 1 to 40 steps, the plant
    against each model: by ``predict`` and, for a lifted-linear model, by the read-out C z that
    DE-MPC predicts with. A controller that believes the wheel does little moves it a lot."""
    steps = STEER_STEP["steps"]
    inputs = np.tile([STEER_STEP["steer_deg"], STEER_STEP["throttle"]], (max(steps), 1))
    truth = _plant_answer(STEER_STEP["speed_mps"], inputs)

    def cells(x: np.ndarray) -> str:
        return " / ".join(f"{x[k, 2]:+.3f}" for k in steps)

    lines = [
        f"| model | yaw rate after {' / '.join(map(str, steps))} steps | read-out C z |",
        "|---|---|---|",
        f"| plant | {cells(truth)} | - |",
    ]
    for name, predicted, readout in _model_answers(learner, seeds, truth[0], inputs):
        lifted = "-" if readout is None else cells(readout)
        lines.append(f"| {name} | {cells(predicted)} | {lifted} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arm", default="today")
    parser.add_argument("--learners", default="deep_edmd,dnn,input_edmd")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--both", action="store_true", help="apply to the baseline too")
    parser.add_argument("--jsonl", type=Path)
    parser.add_argument("--table", type=Path, help="print a file's rows and stop")
    parser.add_argument(
        "--slopes", action="store_true", help="the pedal's effect, plant against the models"
    )
    parser.add_argument(
        "--slalom", action="store_true", help="vx through a slalom, plant against the models"
    )
    parser.add_argument(
        "--steering", action="store_true", help="a wheel step at 80 km/h, plant against the models"
    )
    args, overrides = parser.parse_known_args(argv)
    if args.steering:
        for learner in args.learners.split(","):
            print(steering_steps(learner, [int(s) for s in args.seeds.split(",")]))
        return
    if args.slalom:
        for learner in args.learners.split(","):
            print(slalom_swings(learner, [int(s) for s in args.seeds.split(",")]))
        return
    if args.slopes:
        seeds = [int(s) for s in args.seeds.split(",")]
        for learner in args.learners.split(","):
            print(pedal_slopes(learner, seeds))
        return
    if args.table is not None:
        rows = [json.loads(line) for line in args.table.read_text().splitlines() if line]
        print(table(rows))
        return
    rows = []
    for learner in args.learners.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            got = run_arm(args.arm, overrides, learner, seed, args.both)
            rows += got
            if args.jsonl is not None:
                with args.jsonl.open("a") as file:
                    file.writelines(json.dumps(row) + "\n" for row in got)
            print(table(got), file=sys.stderr, flush=True)
    print(table(rows))


if __name__ == "__main__":
    main()
