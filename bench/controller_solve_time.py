"""Whole control steps of every controller, today's code against a base commit's, in one run.

``python -m bench.controller_solve_time [--quick] [--base REV] [--horizons 60/50] ...``. One model
of each kind is fitted on the synthetic driver's drives (6 drives of 30 s; ``--quick``: 3 of 15 s;
the networks for a few hundred batches: a step's time depends on the network's size, not on its
accuracy) and closes the loop on the sedan through the ISO 3888-1 double lane change at 80 km/h:

- DE-MPC on EDMD (N = 104) and Deep EDMD (N = 13): lifted-linear, prediction matrices built once;
- DE-MPC on bilinear EDMD (N = 104), input EDMD (N = 3) and the DNN (N = 3, two linearisations a
  step at 10/7 as ``controller=dnn_mpc``, one at 60/50 as ``dnn_mpc_long``): linearised every step;
- ``bicycle_mpc``: the identified single-track model (N = 3), time-varying in the speed;

each tracking the reference's states (the paper's), offset-free, and following the course's
centre line (``reference: path``), at both of the paper's horizons (10/7 and 60/50).

Every case runs twice, back to back, on the same saved model: with this checkout's code and with
the code of ``--base`` (a commit, exported with ``git archive`` to a temporary folder and run in
a subprocess with ``PYTHONPATH`` on it): the ratio base/new is measured under the same load.
Times are whole ``act`` calls as ``harness.evaluation.tracking`` measures them (``solve_time_ms``:
with a real-time-iteration controller the feedback phase, ``prepare_time_ms`` the preparation).
The lane change's maximum lateral deviation and yaw-rate RMSE of both runs are printed too: a
faster step must track the same.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from controllers.disturbance import OffsetFree

REPO = Path(__file__).resolve().parents[1]
# The implementation before the real-time iteration and the faster QPs (the comparison's base).
BASE_COMMIT = "35feb0485a809d40155c0d6fe746e2e8e7fe63b8"
# The targets for the feedback phase (ms): median, p99, max at 60/50; median at 10/7;
# median for the models with three states.
TARGETS_MS = {"60/50": (1.0, 2.0, 5.0), "10/7": (0.2, None, None)}
SMALL_MEDIAN_MS = 0.3
HORIZONS = ("10/7", "60/50")
MODES: dict[str, dict[str, Any]] = {
    "states": {},
    "offset-free": {"disturbance": OffsetFree()},
    "path": {"reference": "path"},
}
# name: (conf/learner file, DEMPCConfig keys beyond the mode's)
CONTROLLERS: dict[str, tuple[str, dict[str, Any]]] = {
    "edmd": ("edmd", {}),
    "deep_edmd": ("deep_edmd", {}),
    "bilinear_edmd": ("bilinear_edmd", {}),
    "input_edmd": ("input_edmd", {}),
    "dnn": ("dnn", {"sqp_iterations": 2, "linearization": "predicted"}),  # as dnn_mpc.yaml
    "bicycle_mpc": ("single_track", {}),
}
# Keys of a controller at one horizon: the DNN at 60/50 as dnn_mpc_long.yaml (one linearisation).
AT_HORIZON: dict[tuple[str, str], dict[str, Any]] = {("dnn", "60/50"): {"sqp_iterations": 1}}
_TRAINING = [
    "learner.training.max_steps=300",
    "learner.training.eval_every_steps=300",
    "learner.training.checkpoint_every_steps=300",
    "learner.training.progress=false",
    "learner.training.num_threads=1",
]


# ---- the worker: runs cases with whichever code its PYTHONPATH imports ------------------------


def run_case(
    model_path: str,
    controller: str,
    mode: str,
    horizon: str,
    settings: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One lane change of ``controller`` in ``mode`` at ``horizon`` (DE-MPC ``settings`` on
    top): times and tracking."""
    from controllers import BicycleMPCConfig, DEMPCConfig
    from harness.evaluation.tracking import track
    from harness.plant import Sedan
    from harness.recorder import Recorder
    from harness.references import DoubleLaneChange, path_metrics
    from learners import load

    model: Any = _MODELS.get(model_path)
    if model is None:
        model = _MODELS[model_path] = load(model_path)
    Np, Nc = (int(value) for value in horizon.split("/"))
    factory = BicycleMPCConfig if controller == "bicycle_mpc" else DEMPCConfig
    keys = {
        **CONTROLLERS[controller][1],
        **AT_HORIZON.get((controller, horizon), {}),
        **MODES[mode],
        **(settings or {}),
    }
    plant = Sedan()
    lane_change = DoubleLaneChange()
    reference, course = lane_change.build(plant.dt, []), lane_change.course()
    built = factory(Np=Np, Nc=Nc, **keys)(model, plant.dt)  # type: ignore[arg-type]
    metrics, run = track(
        plant, built, reference, name="bench", recorder=Recorder(), path=course.path()
    )
    judged = path_metrics(course, run.poses, run.states)
    return {
        "feedback": metrics["solve_time_ms"],
        "step": metrics.get("step_time_ms", metrics["solve_time_ms"]),  # one phase: act is all
        "prepare": metrics.get("prepare_time_ms"),
        "misses": metrics["deadline_misses"],
        "deviation_m": judged["max_lateral_deviation_m"],
        "rmse_yaw_rate": metrics["rmse"]["yaw_rate"],
        "N": int(np.asarray(model.C_).shape[1]),
    }


_MODELS: dict[str, Any] = {}


def worker() -> None:
    """Answer one JSON case per stdin line with one JSON result line (until stdin closes)."""
    for line in sys.stdin:
        case = json.loads(line)
        try:
            result: dict[str, Any] = run_case(**case)
        except Exception as error:  # a case the base code cannot run is reported, not fatal
            result = {"error": f"{type(error).__name__}: {str(error).splitlines()[0][:120]}"}
        print(json.dumps(result), flush=True)


class Worker:
    """A worker subprocess importing the project from ``root``."""

    def __init__(self, root: Path) -> None:
        env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}
        self.process = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=env,
            cwd=str(root),
        )

    def run(self, case: dict[str, Any]) -> dict[str, Any]:
        assert self.process.stdin is not None and self.process.stdout is not None
        self.process.stdin.write(json.dumps(case) + "\n")
        self.process.stdin.flush()
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"the worker in {case} ended without an answer")
        return dict(json.loads(line))

    def close(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.close()
        self.process.wait()


# ---- the driver: fits the models, runs every case on both codes, prints the table -------------


def fit_models(directory: Path, quick: bool, names: list[str]) -> dict[str, str]:
    """Each learner of ``names`` fitted on the synthetic driver's drives and saved: its path."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from harness.config import register_configs
    from harness.core.episode import Episode, MinMaxNormalizer
    from harness.core.paths import CONF_DIR
    from harness.data.driver import DriverKnowledge
    from harness.data.store import DataConfig, drive_episode
    from harness.plant import Sedan

    register_configs()
    count, steps = (3, 1500) if quick else (6, 3000)
    plant, data, drives = Sedan(), DataConfig(), []
    for index in range(count + 1):
        d = drive_episode(plant, data, DriverKnowledge.of(plant.params), index, steps)
        drives.append(Episode(f"drive_{index}", d["time_s"], d["states"], d["inputs"], d["poses"]))
    train, validation = drives[:count], drives[count:]
    normalizer = MinMaxNormalizer.fit(train)
    paths = {}
    for name in names:
        if (directory / f"{name}.pt").exists():  # --models: fitted by an earlier run
            paths[name] = str(directory / f"{name}.pt")
            continue
        learner_file = CONTROLLERS[name][0]
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=[f"learner={learner_file}"])
            if "training" in cfg.learner:
                cfg = compose(
                    config_name="config", overrides=[f"learner={learner_file}", *_TRAINING]
                )
        learner = instantiate(cfg.learner)
        learner.fit(train, validation, normalizer)
        paths[name] = str(learner.save(directory / f"{name}.pt"))
    print(f"models fitted on {count} drives of {steps / 100:.0f} s (networks: 300 batches)")
    return paths


def export(revision: str, directory: Path) -> Path:
    """The tree of ``revision`` (git archive, no worktree) under ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    sha = subprocess.run(
        ["git", "rev-parse", revision], cwd=REPO, check=True, capture_output=True, text=True
    ).stdout.strip()
    archive = subprocess.run(["git", "archive", sha], cwd=REPO, check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(directory)], input=archive.stdout, check=True)
    print(f"base: {sha} (exported to {directory})")
    return directory


def _settings(text: str) -> dict[str, Any]:
    """``key=value,key=value`` as DE-MPC keys (numbers and true/false parsed)."""
    out: dict[str, Any] = {}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        parsed: Any = value
        if value in ("true", "false"):
            parsed = value == "true"
        else:
            with contextlib.suppress(ValueError):  # a word stays a string
                parsed = int(value) if value.lstrip("-").isdigit() else float(value)
        out[key.strip()] = parsed
    return out


def _times(times: dict[str, float] | None) -> str:
    if not times:
        return "–"
    return f"{times['median']:.3f} / {times['p99']:.3f} / {times['max']:.2f}"


def _mark(result: dict[str, Any], horizon: str) -> str:
    """✓ where the feedback phase meets the targets (TARGETS_MS), ✗ where it does not."""
    median_max, p99_max, max_max = TARGETS_MS[horizon]
    if result["N"] <= 3 and horizon == "60/50":
        median_max = SMALL_MEDIAN_MS
    times = result["feedback"]
    met = times["median"] <= median_max
    met &= p99_max is None or times["p99"] <= p99_max
    met &= max_max is None or times["max"] <= max_max
    return "✓" if met else "✗"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 drives of 15 s to fit on")
    parser.add_argument(
        "--base",
        default=BASE_COMMIT,
        help="commit to compare with ('' skips; 'same': this code, with --base-settings)",
    )
    parser.add_argument(
        "--settings", default="", help="DE-MPC keys for this code, e.g. linearization=predicted"
    )
    parser.add_argument("--base-settings", default="", help="DE-MPC keys for the base side")
    parser.add_argument("--horizons", default=",".join(HORIZONS))
    parser.add_argument("--controllers", default=",".join(CONTROLLERS))
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--models", default="", help="folder to keep fitted models in, reused")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--fit-into", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker()
        return
    if args.fit_into:
        fit_models(Path(args.fit_into), args.quick, args.controllers.split(","))
        return
    from bench.machine import describe

    horizons, modes = args.horizons.split(","), args.modes.split(",")
    names = args.controllers.split(",")
    for value, known, key in (
        (horizons, HORIZONS, "horizons"),
        (names, CONTROLLERS, "controllers"),
        (modes, MODES, "modes"),
    ):
        unknown = sorted(set(value) - set(known))
        if unknown:
            parser.error(f"--{key}: unknown {', '.join(unknown)} (known: {', '.join(known)})")
    print(f"machine: {describe()}; load average {os.getloadavg()[0]:.2f} at start")
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(args.models) if args.models else Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        same = args.base == "same"
        base_root = export(args.base, Path(scratch) / "base") if args.base and not same else None
        # Fitted and saved by the older code where there is one: both codes read its files.
        root = REPO if base_root is None else base_root
        command = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--fit-into",
            str(folder),
            "--controllers",
            ",".join(names),
            *(["--quick"] if args.quick else []),
        ]
        subprocess.run(command, check=True, cwd=root, env={**os.environ, "PYTHONPATH": str(root)})
        models = {name: str(folder / f"{name}.pt") for name in names}
        new = Worker(REPO)
        base = Worker(base_root) if base_root is not None else Worker(REPO) if same else None
        settings, base_settings = _settings(args.settings), _settings(args.base_settings)
        if settings or base_settings:
            print(
                f"settings: this code {settings or 'defaults'}; base {base_settings or 'defaults'}"
            )
        print(
            "\n| Np/Nc | controller | mode | N | feedback median / p99 / max ms | target | "
            "prepare median / p99 / max ms | step median / p99 / max ms | misses | "
            "base feedback median / p99 ms | base step median / p99 / max ms | "
            "base/new step median | base/new step p99 | "
            "max deviation m new / base | yaw-rate RMSE new / base |"
        )
        print("|" + "---|" * 15)
        for horizon, name, mode in itertools.product(horizons, names, modes):
            case = {
                "model_path": models[name],
                "controller": name,
                "mode": mode,
                "horizon": horizon,
            }
            ours = new.run({**case, "settings": settings})
            theirs: dict[str, Any] = {"error": "–"}
            if base is not None:
                theirs = base.run({**case, "settings": base_settings})
            if "error" in ours:
                print(f"| {horizon} | {name} | {mode} | – | {ours['error']} |", flush=True)
                continue
            theirs_feedback = "–"
            if "error" in theirs:
                theirs_times, ratio_median, ratio_p99, deviation, rmse = "–", "–", "–", "–", "–"
            else:
                feedback = theirs["feedback"]
                theirs_feedback = f"{feedback['median']:.3f} / {feedback['p99']:.3f}"
                # a whole step of each (the base's act, where it had no preparation)
                theirs_step = theirs.get("step") or theirs["feedback"]
                theirs_times = _times(theirs_step)
                ratio_median = f"{theirs_step['median'] / ours['step']['median']:.1f}"
                ratio_p99 = f"{theirs_step['p99'] / ours['step']['p99']:.1f}"
                deviation, rmse = f"{theirs['deviation_m']:.3f}", f"{theirs['rmse_yaw_rate']:.4f}"
            print(
                f"| {horizon} | {name} | {mode} | {ours['N']} | {_times(ours['feedback'])} | "
                f"{_mark(ours, horizon)} | {_times(ours['prepare'])} | {_times(ours['step'])} | "
                f"{ours['misses']} | {theirs_feedback} | "
                f"{theirs_times} | {ratio_median} | {ratio_p99} | "
                f"{ours['deviation_m']:.3f} / {deviation} | "
                f"{ours['rmse_yaw_rate']:.4f} / {rmse} |",
                flush=True,
            )
        new.close()
        if base is not None:
            base.close()
    print(
        f"\nload average {os.getloadavg()[0]:.2f} at the end. Targets (feedback phase): "
        "60/50 median <= 1 ms (<= 0.3 ms for N = 3), p99 <= 2 ms, max <= 5 ms; 10/7 median "
        "<= 0.2 ms (✓/✗). Ratios: base / new whole steps (preparation + feedback), the same "
        "case back to back."
    )


if __name__ == "__main__":
    main()
