"""What one set of kernels costs: training and a closed loop with the pinned AVX2 kernels
(harness/core/kernels.py) against each library's own choice, side by side.

``python -m bench.kernels [--batches 150] [--repeats 2]`` prints one table. Each measurement runs
in its own process (``bench.threads``' workers, one thread, on the embedded default dataset):
ms per training batch of the main job's networks and the paper's, and ms per control step of
DE-MPC at 60/50 on a DNN (``de_mpc_long``). "native" sets ``KOOPMAN_HARNESS_NATIVE_KERNELS=1``:
each library picks its kernels by the CPU (AVX-512 where there is one). Arms are interleaved and
repeated; the fastest repeat is kept. The ratio is pinned / native (> 1: the pinned kernels are
slower). On a CPU without AVX-512 both arms run the same kernels.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from bench.machine import describe
from bench.threads import LOOP, TRAINED, _dataset, _train_model
from bench.threads import _worker as threads_worker
from harness.core.kernels import NATIVE, unpinned

ARMS = {"pinned": {}, "native": {NATIVE: "1"}}


def _worker(arm: str, *args: str) -> dict:
    """``bench.threads``' worker in a fresh process, its kernels chosen there as ``arm`` says."""
    return threads_worker(*args, env={**unpinned(os.environ), **ARMS[arm]})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, default=150)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    print(describe())
    _dataset()  # collected before any timing
    best: dict[tuple[str, str], float] = {}
    with tempfile.TemporaryDirectory() as out:
        model = Path(out) / "dnn.pt"
        _train_model(model)
        for _ in range(args.repeats):
            for workload in (*TRAINED, LOOP):
                for arm in ARMS:
                    if workload == LOOP:
                        result = _worker(arm, "loop", str(model), "1")
                    else:
                        result = _worker(arm, "train", workload, "1", str(args.batches))
                    best[workload, arm] = min(best.get((workload, arm), float("inf")), result["ms"])
    print(
        f"\nms per training batch ({args.batches} batches) or per control step, one thread; "
        f"fastest of {args.repeats}\n"
    )
    print("| workload | pinned (AVX2) | native | pinned / native |")
    print("|---|---|---|---|")
    for workload in (*TRAINED, LOOP):
        pinned, native = best[workload, "pinned"], best[workload, "native"]
        print(f"| {workload} | {pinned:.2f} | {native:.2f} | {pinned / native:.2f}x |")


if __name__ == "__main__":
    main()
