"""How many threads a job computes on: one by default, whatever the environment says.

The harness's networks are small (batches of 64, layers of 128) and its matrices a few hundred
rows: split over threads, each operation waits for the slowest core. Measured on 2 cores
(``bench/threads.py``, docs/guide/benchmarks.md, "Threads per job"): two threads were as fast as
one on an idle machine (the paper's Deep EDMD 1.3x faster) and 5-33x slower beside another
process, and the metrics moved with the thread count (a reduction summed in another order).
So a job computes on ``threads`` (the
top-level config key, default 1) PyTorch and OpenBLAS threads, set here once before any work,
and a machine's cores are used by running jobs side by side (``hydra/launcher=local_cores``).

NumPy and SciPy each bundle an OpenBLAS that reads ``OMP_NUM_THREADS`` once, when it loads;
:func:`openblas` finds every one mapped into the process and sets it through its own setter
(ctypes, no new dependency). PyTorch's MKL and OpenMP follow ``torch.set_num_threads``.
"""

from __future__ import annotations

import ctypes
import os
from functools import cache
from pathlib import Path
from typing import Any

# Name prefixes and suffixes of the OpenBLAS builds NumPy and SciPy ship (64- and 32-bit ints):
# each exports <prefix>set_num_threads<suffix>, get_num_threads and get_corename.
_BUILDS = (
    ("scipy_openblas_", "64_"),
    ("scipy_openblas_", ""),
    ("openblas_", "64_"),
    ("openblas_", ""),
)


@cache
def _loaded() -> list[tuple[Any, str, str]]:
    """Every OpenBLAS mapped into this process, with its symbols' prefix and suffix (found
    once, after import)."""
    import numpy  # noqa: F401  (both libraries are mapped once these are imported)
    import scipy.linalg  # noqa: F401

    found = []
    maps = Path("/proc/self/maps")
    paths = (
        {line.split()[-1] for line in maps.read_text().splitlines() if "openblas" in line}
        if maps.exists()
        else set()
    )
    for path in sorted(paths):
        try:
            library = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix, suffix in _BUILDS:
            if hasattr(library, f"{prefix}set_num_threads{suffix}"):
                found.append((library, prefix, suffix))
                break
    return found


@cache
def openblas() -> list[tuple[Any, Any]]:
    """(set, get) of every OpenBLAS mapped into this process (found once: a controller asks
    twice a step)."""
    return [
        (
            getattr(library, f"{prefix}set_num_threads{suffix}"),
            getattr(library, f"{prefix}get_num_threads{suffix}"),
        )
        for library, prefix, suffix in _loaded()
    ]


def openblas_kernels() -> list[str]:
    """The kernels each loaded OpenBLAS runs (its core name: ``Haswell``, ``SkylakeX``...)."""
    names = []
    for library, prefix, suffix in _loaded():
        corename = getattr(library, f"{prefix}get_corename{suffix}", None)
        if corename is None:
            names.append("unknown")
            continue
        corename.restype = ctypes.c_char_p
        names.append(corename().decode())
    return names


def environment_threads() -> int:
    """What the environment would give a job: ``OMP_NUM_THREADS`` where a launcher set it
    (joblib's workers get cores / jobs, Ray a job's ``num_cpus``), else every core this
    process may run on."""
    cores = len(os.sched_getaffinity(0))
    try:
        return max(1, min(cores, int(os.environ.get("OMP_NUM_THREADS", cores))))
    except ValueError:
        return cores


def use_threads(count: int | None) -> int:
    """Compute on ``count`` threads from now on (None: :func:`environment_threads`), in PyTorch
    (intra-op, MKL, OpenMP) and in every loaded OpenBLAS; returns the count set."""
    import torch

    count = environment_threads() if count is None else count
    torch.set_num_threads(count)
    for set_threads, _ in openblas():
        set_threads(count)
    return count


def threads_in_use() -> dict[str, Any]:
    """The thread counts in force, for ``metrics.json`` (``run.threads``)."""
    import torch

    return {
        "torch": torch.get_num_threads(),
        "openblas": [int(get()) for _, get in openblas()],
    }
