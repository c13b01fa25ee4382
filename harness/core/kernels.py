"""One set of numerical kernels on every x86-64 machine: the same seed, the same numbers.

MKL (PyTorch's BLAS), NumPy's SIMD functions and OpenBLAS (NumPy's and SciPy's) each choose
their kernels by the CPU they run on: AVX-512 on one machine, AVX2 on another, which sum in
another order or round ``exp`` in another last bit. Training turns a last bit into another
network: the main job's Deep EDMD, trained on one Xeon, predicted its first test drive at
6.06 m/s vx RMSE with MKL's AVX-512 kernels and 5.35 with its AVX2 ones
(docs/guide/benchmarks.md, "One set of kernels"). So, on any machine with AVX2, the harness
asks each library for its AVX2 kernels before any of them computes:

- MKL: its conditional-numerical-reproducibility branch AVX2 (``MKL_CBWR``), the same results
  on every processor that runs it; read at MKL's first call;
- NumPy: its dispatch above AVX2 off (``NPY_DISABLE_CPU_FEATURES``); read when NumPy is imported;
- OpenBLAS: its Haswell (AVX2) kernels (``OPENBLAS_CORETYPE``); read when it loads;
- PyTorch's own kernels and oneDNN: capped at AVX2 (``ATEN_CPU_CAPABILITY``,
  ``ONEDNN_MAX_CPU_ISA``); read at their first use.

:func:`pin` sets them when ``harness`` is imported. A variable the environment sets already is
kept; ``KOOPMAN_HARNESS_NATIVE_KERNELS=1`` keeps every library's own choice (training on an
AVX-512 machine is then up to a fifth faster, and its last digits that machine's). A process
that imported NumPy before ``harness`` keeps this machine's NumPy and OpenBLAS kernels:
:func:`in_force` says which ran (``metrics.json``: ``run.kernels``).
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

NATIVE = "KOOPMAN_HARNESS_NATIVE_KERNELS"
# NumPy >= 2.4 dispatches on x86-64 psABI levels: X86_V4 and above is AVX-512.
NUMPY_ABOVE_AVX2 = ("X86_V4", "AVX512_ICL", "AVX512_SPR")
PINS = {
    "MKL_CBWR": "AVX2",
    "NPY_DISABLE_CPU_FEATURES": " ".join(NUMPY_ABOVE_AVX2),
    "OPENBLAS_CORETYPE": "Haswell",
    "ATEN_CPU_CAPABILITY": "avx2",
    "ONEDNN_MAX_CPU_ISA": "AVX2",
}
_numpy_before_pin = False


def has_avx2() -> bool:
    """Whether this is an x86-64 machine whose CPU has AVX2 (read from ``/proc/cpuinfo``;
    False where it cannot be read: the libraries then choose as they would)."""
    if platform.machine().lower() not in {"x86_64", "amd64"}:
        return False
    try:
        with Path("/proc/cpuinfo").open() as cpuinfo:
            for line in cpuinfo:
                if line.startswith("flags"):
                    return "avx2" in line.split()
    except OSError:
        return False
    return False


def native_asked() -> bool:
    """Whether ``KOOPMAN_HARNESS_NATIVE_KERNELS`` asks for every library's own kernels."""
    return os.environ.get(NATIVE, "") not in {"", "0"}


def unpinned(environment: Mapping[str, str]) -> dict[str, str]:
    """``environment`` without the pins and the opt-out: what a process started from a shell
    gets, which pins its kernels itself if it runs this harness (an older commit's does not)."""
    return {k: v for k, v in environment.items() if k not in {*PINS, NATIVE}}


def pin() -> bool:
    """Ask every library for its AVX2 kernels (module docstring); True if asked. Call before any
    of them computes; a variable already set, and ``KOOPMAN_HARNESS_NATIVE_KERNELS=1``, win."""
    global _numpy_before_pin
    if native_asked() or not has_avx2():
        return False
    _numpy_before_pin = "numpy" in sys.modules
    for name, value in PINS.items():
        os.environ.setdefault(name, value)
    return True


def in_force() -> dict[str, Any]:
    """The kernels this process computes with: MKL's branch (``native`` when none is set),
    NumPy's SIMD dispatch targets in use, each loaded OpenBLAS's kernels, PyTorch's CPU
    capability; ``same_everywhere``: whether they are the pinned set."""
    import torch

    from harness.core.threads import openblas_kernels

    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

        numpy_targets = [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]
    except ImportError:  # another NumPy layout: say so rather than guess
        numpy_targets = ["unknown"]
    kernels: dict[str, Any] = {
        "mkl": os.environ.get("MKL_CBWR", "native"),
        "numpy": numpy_targets,
        "openblas": sorted(set(openblas_kernels())),
        "torch": torch.backends.cpu.get_cpu_capability(),
    }
    kernels["same_everywhere"] = not _not_pinned(kernels)
    return kernels


def _not_pinned(kernels: dict[str, Any]) -> list[str]:
    """The libraries whose kernels (:func:`in_force`) are not the pinned set, named for a run."""
    differs = [
        f"MKL {kernels['mkl']}" if kernels["mkl"] != PINS["MKL_CBWR"] else "",
        "NumPy's AVX-512" if set(kernels["numpy"]) & set(NUMPY_ABOVE_AVX2) else "",
        f"OpenBLAS {'/'.join(kernels['openblas'])}"
        if kernels["openblas"] not in ([], [PINS["OPENBLAS_CORETYPE"]])
        else "",
        f"PyTorch {kernels['torch']}" if kernels["torch"] not in {"AVX2", "DEFAULT"} else "",
    ]
    return [library for library in differs if library]


def why_not_same_everywhere(kernels: dict[str, Any]) -> str:
    """One line for a run whose kernels (:func:`in_force`) are not the pinned set: which
    library differs, why, and what to do."""
    which = ", ".join(_not_pinned(kernels)) + " kernels"
    if native_asked():
        return f"{which}, as {NATIVE} asks: this machine's last digits"
    if not has_avx2():
        return f"{which}: no AVX2 on this CPU (or not x86-64), this machine's last digits"
    if _numpy_before_pin:
        return (
            f"{which}: NumPy was imported before harness, so the last digits may differ from "
            "another machine's; import harness first"
        )
    return (
        f"{which}: set by the environment (or NumPy older than 2.4), so the last digits may "
        f"differ from another machine's; unset {', '.join(PINS)} for the pinned set"
    )
