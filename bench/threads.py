"""Threads per job: training and a closed loop at one thread and at every core, idle and busy.

``python -m bench.threads [--batches 100] [--repeats 2]`` prints one table. Each measurement runs
in its own subprocess with ``threads`` set as the harness sets it (``harness.core.threads``), on
the embedded default dataset (collected once into the cache if missing):

- training: ``learner.fit`` for ``--batches`` batches at the learner's full window (curriculum
  off, validation every 50 batches as in a run), ms per batch; the main job's networks
  (``deep_edmd``, ``dnn``) and the paper's (``deep_edmd_paper``, ``dnn_paper``);
- closed loop: DE-MPC at 60/50 (``de_mpc_long``) on a DNN, the first test drive on the plant, the
  whole loop's wall time per control step (plant, model linearisation, QP).

"Busy" runs one CPU-bound process per core but one beside the measurement, as on a laptop or a
shared server doing other work. Arms are interleaved and repeated; the fastest repeat is kept.
The ratio column is every-core time / one-thread time under the same load (> 1: one thread wins).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.machine import describe

TRAINED = ("deep_edmd", "dnn", "deep_edmd_paper", "dnn_paper")
LOOP = "closed loop (de_mpc_long on dnn)"
BURN = "while True: pass"


def _compose(*overrides: str):
    from hydra import compose, initialize_config_dir

    from harness.config import register_configs
    from harness.core.paths import CONF_DIR

    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _dataset():
    """The default dataset, from the cache (collected there on first use, seconds)."""
    from hydra.utils import instantiate

    from harness.data.collect import data_config, prepare
    from harness.recorder import Recorder

    cfg = _compose("recorder=none")
    with tempfile.TemporaryDirectory() as out:
        plant = instantiate(cfg.plant)
        dataset, _ = prepare(plant, data_config(cfg.data), Recorder(), Path(out))
    return dataset


def _learner(name: str, batches: int):
    from hydra.utils import instantiate

    cfg = _compose(
        f"learner={name}",
        f"learner.training.max_steps={batches}",
        "learner.training.eval_every_steps=50",
        "learner.training.checkpoint_every_steps=1000000",
        "learner.training.curriculum=null",
        "learner.training.progress=false",
    )
    return instantiate(cfg.learner)


def train_worker(name: str, threads: int, batches: int) -> dict:
    from harness.core.threads import use_threads

    use_threads(threads)
    dataset = _dataset()
    _learner(name, 5).fit(dataset.train, dataset.validation, dataset.normalizer)  # imports, JIT
    learner = _learner(name, batches)
    start = time.perf_counter()
    learner.fit(dataset.train, dataset.validation, dataset.normalizer)
    return {"ms": 1e3 * (time.perf_counter() - start) / batches}


def loop_worker(model_path: str, threads: int) -> dict:
    from hydra.utils import instantiate

    from harness.core.threads import use_threads
    from harness.evaluation.tracking import track
    from harness.recorder import Recorder
    from learners.model_file import load

    use_threads(threads)
    dataset = _dataset()
    cfg = _compose("learner=dnn", "controller=de_mpc_long")
    plant = instantiate(cfg.plant)
    model = load(model_path)
    reference = dataset.test[0].states
    make = instantiate(cfg.controller)
    start = time.perf_counter()
    metrics, _ = track(plant, make(model, plant.dt), reference, name="bench", recorder=Recorder())
    return {"ms": 1e3 * (time.perf_counter() - start) / metrics["steps"]}


def _worker(*args: str, env: dict[str, str] | None = None) -> dict:
    """A worker in a fresh process, in ``env`` (default: this one's) less ``OMP_NUM_THREADS``."""
    command = [sys.executable, "-m", "bench.threads", "--worker", *args]
    env = {k: v for k, v in (os.environ if env is None else env).items() if k != "OMP_NUM_THREADS"}
    done = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
    if done.returncode != 0:
        raise RuntimeError(f"{args} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _train_model(path: Path) -> None:
    """A DNN for the closed loop (300 batches: a model that drives; its accuracy is not timed)."""
    code = (
        "import sys; from bench.threads import _dataset, _learner; "
        "from harness.core.threads import use_threads; use_threads(1); d = _dataset(); "
        "m = _learner('dnn', 300).fit(d.train, d.validation, d.normalizer); m.save(sys.argv[1])"
    )
    subprocess.run([sys.executable, "-c", code, str(path)], check=True, capture_output=True)


class Busy:
    """``count`` CPU-bound processes for the duration of a block."""

    def __init__(self, count: int) -> None:
        self.count, self.processes = count, []

    def __enter__(self) -> None:
        self.processes = [subprocess.Popen([sys.executable, "-c", BURN]) for _ in range(self.count)]

    def __exit__(self, *_: object) -> None:
        for process in self.processes:
            process.kill()
            process.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", nargs="+")
    parser.add_argument("--batches", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--only", nargs="*", help="workloads to run (default: all)")
    args = parser.parse_args()
    if args.worker:
        kind, *rest = args.worker
        if kind == "train":
            result = train_worker(rest[0], int(rest[1]), int(rest[2]))
        else:
            result = loop_worker(rest[0], int(rest[1]))
        print(json.dumps(result))
        return

    cores = len(os.sched_getaffinity(0))
    counts = sorted({1, 2, cores})
    print(describe())
    _dataset()  # collected before any timing
    workloads = [w for w in (*TRAINED, LOOP) if not args.only or w.split()[0] in args.only]
    best: dict[tuple[str, str, int], float] = {}
    with tempfile.TemporaryDirectory() as out:
        model = Path(out) / "dnn.pt"
        if LOOP in workloads:
            _train_model(model)
        for _ in range(args.repeats):
            for load, burners in (("idle", 0), ("busy", max(1, cores - 1))):
                with Busy(burners):
                    for workload in workloads:
                        for threads in counts:
                            if workload == LOOP:
                                result = _worker("loop", str(model), str(threads))
                            else:
                                result = _worker("train", workload, str(threads), str(args.batches))
                            key = (workload, load, threads)
                            best[key] = min(best.get(key, float("inf")), result["ms"])
    print(
        f"\nms per training batch ({args.batches} batches) or per control step; fastest of "
        f"{args.repeats}; busy: {max(1, cores - 1)} CPU-bound process(es) beside it\n"
    )
    header = " | ".join(f"{n} thread{'s' * (n > 1)}" for n in counts)
    print(f"| workload | load | {header} | {cores} threads / 1 |")
    print("|---|---|" + "---|" * len(counts) + "---|")
    for workload in workloads:
        for load in ("idle", "busy"):
            times = [best[(workload, load, n)] for n in counts]
            ratio = best[(workload, load, cores)] / best[(workload, load, 1)]
            cells = " | ".join(f"{t:.2f}" for t in times)
            print(f"| {workload} | {load} | {cells} | {ratio:.2f}x |")


if __name__ == "__main__":
    main()
