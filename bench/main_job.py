"""The main job end to end, this checkout against another commit, idle and beside a busy core.

``python -m bench.main_job [--base 6e92ddf] [--this REV] [--load idle busy] [--repeats 1]
[--data data=paper] [-- OVERRIDES]`` runs ``python -m harness recorder=none`` (the default
job, no environment variables: what ``make run`` runs, less the recording) from this checkout
(or a worktree of ``--this``) and from a worktree of ``--base`` (made under a temporary folder,
removed after), interleaved, each into its own run directory with the dataset cache shared
(collected once before any timing). "Busy": one CPU-bound process per core but one beside the
job. It prints per arm the wall time, ``training.fit_time_s``, this checkout's phases (its log's
phase lines) and the ratio base / this checkout; and whether the two give the same metrics
(prediction and tracking RMSE).

Overrides after ``--`` go to both (``-- learner=dnn``, or ``--data data=paper -- experiment=paper
learner=edmd`` for a paper-scale job).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.machine import describe
from bench.threads import Busy
from harness.core.kernels import unpinned
from harness.core.paths import REPO_ROOT

PHASE = re.compile(r"\]\[harness\]\[INFO\] - (?P<phase>[^:]+): .*\((?P<time>[^()]*)\)$")


def _seconds(text: str) -> float:
    minutes = re.match(r"(\d+) min (\d+) s", text)
    if minutes:
        return 60 * int(minutes[1]) + int(minutes[2])
    return float(text.removesuffix(" s"))


def run_job(code: Path, run_dir: Path, cache: Path, overrides: list[str]) -> dict:
    """One main job from checkout ``code``; its wall time, fit time, phases and numbers."""
    # As a user's shell starts it: no thread count, and no kernel this process was pinned to
    # (a checkout that pins its kernels does so itself; an older one runs as it did).
    env = {k: v for k, v in unpinned(os.environ).items() if not k.endswith("_NUM_THREADS")}
    env |= {"PYTHONPATH": str(code), "KOOPMAN_HARNESS_CACHE": str(cache)}
    command = [sys.executable, "-m", "harness", "recorder=none", f"hydra.run.dir={run_dir}"]
    start = time.perf_counter()
    done = subprocess.run(
        [*command, *overrides], cwd=code, env=env, capture_output=True, text=True, check=False
    )
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{code}: {done.stderr[-2000:]}")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    log = (run_dir / "app.log").read_text() if (run_dir / "app.log").exists() else ""
    phases: dict[str, float] = {}
    for line in log.splitlines():
        match = PHASE.search(line)
        if match:
            name = match["phase"].split(" ")[0]
            phases[name] = phases.get(name, 0.0) + _seconds(match["time"])
    tracking = metrics.get("tracking", {}).get("controllers", {})
    numbers = {
        "prediction": {
            k: v.get("rmse") for k, v in metrics["prediction"].items() if isinstance(v, dict)
        },
        "tracking": {
            c: {r: m.get("rmse") for r, m in runs.items()} for c, runs in tracking.items()
        },
    }
    fit = metrics["training"]["fit_time_s"]
    return {"wall_s": wall, "fit_s": fit, "phases": phases, "numbers": numbers}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", default="6e92ddf", help="the commit to compare with")
    parser.add_argument("--this", help="a commit to run instead of this checkout's working tree")
    parser.add_argument("--load", nargs="+", default=["idle", "busy"], choices=["idle", "busy"])
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument(
        "--data",
        nargs="*",
        help="overrides that choose the data, collected before any timing (default: the "
        "overrides that start with 'data'; experiment=paper needs --data data=paper)",
    )
    parser.add_argument("overrides", nargs="*", help="after --: overrides for both jobs")
    args = parser.parse_args()
    cores = len(os.sched_getaffinity(0))
    print(describe())
    with tempfile.TemporaryDirectory() as tmp:
        base, this = Path(tmp) / "base", REPO_ROOT
        worktrees = [(base, args.base)]
        if args.this:
            this = Path(tmp) / "this"
            worktrees.append((this, args.this))
        for folder, commit in worktrees:
            subprocess.run(
                ["git", "-C", str(REPO_ROOT), "worktree", "add", "--detach", str(folder), commit],
                check=True,
                capture_output=True,
            )
        try:
            cache = Path(tmp) / "cache"
            collect = [sys.executable, "-m", "harness", "task=collect", "recorder=none"]
            env = os.environ | {"KOOPMAN_HARNESS_CACHE": str(cache), "PYTHONPATH": str(REPO_ROOT)}
            data = args.data
            if data is None:
                data = [o for o in args.overrides if o.startswith("data")]
            done = subprocess.run(
                [*collect, f"hydra.run.dir={tmp}/collect", *data],
                env=env,
                capture_output=True,
                text=True,
                check=False,
            )
            if done.returncode != 0:
                raise SystemExit(f"collecting the data failed: {done.stderr[-2000:]}")
            results: dict[tuple[str, str], dict] = {}
            for k in range(args.repeats):
                for load in args.load:
                    with Busy(max(1, cores - 1) if load == "busy" else 0):
                        for arm, code in (("base", base), ("this", this)):
                            run_dir = Path(tmp) / f"{arm}_{load}_{k}"
                            result = run_job(code, run_dir, cache, args.overrides)
                            best = results.get((arm, load))
                            if best is None or result["wall_s"] < best["wall_s"]:
                                results[(arm, load)] = result
        finally:
            for folder, _ in worktrees:
                subprocess.run(
                    ["git", "-C", str(REPO_ROOT), "worktree", "remove", "--force", str(folder)],
                    check=False,
                    capture_output=True,
                )
    overrides = " ".join(args.overrides) or "(defaults)"
    print(
        f"\npython -m harness recorder=none {overrides}; base {args.base}; fastest of "
        f"{args.repeats}; busy: {max(1, cores - 1)} CPU-bound process(es) beside it\n"
    )
    print("| load | checkout | wall | training | phases | base / this |")
    print("|---|---|---|---|---|---|")
    for load in args.load:
        this, old = results[("this", load)], results[("base", load)]
        for arm, result in (("base", old), ("this", this)):
            phases = ", ".join(f"{k} {v:.0f} s" for k, v in result["phases"].items()) or "-"
            ratio = f"{old['wall_s'] / this['wall_s']:.2f}x" if arm == "this" else ""
            print(
                f"| {load} | {args.base if arm == 'base' else args.this or 'this'} "
                f"| {result['wall_s']:.0f} s "
                f"| {result['fit_s']:.0f} s | {phases} | {ratio} |"
            )
    for load in args.load:
        same = results[("this", load)]["numbers"] == results[("base", load)]["numbers"]
        print(f"\n{load}: the same prediction and tracking RMSE as {args.base}: {same}")
    idle_busy = [
        results[("this", load)]["wall_s"] for load in ("idle", "busy") if load in args.load
    ]
    if len(idle_busy) == 2:
        print(f"this checkout, busy / idle: {idle_busy[1] / idle_busy[0]:.2f}x")


if __name__ == "__main__":
    main()
