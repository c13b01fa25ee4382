"""harness.core.kernels: importing harness asks every numerical library for its AVX2 kernels,
so that a seed gives the same digits on every x86-64 machine; the run says which kernels ran."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from harness.core.kernels import NATIVE, has_avx2, unpinned

needs_avx2 = pytest.mark.skipif(not has_avx2(), reason="the kernels are pinned on AVX2 CPUs only")

# A few Adam steps of a small tanh network (MKL's products) and NumPy's exp and arctan2 (its
# SIMD functions), hashed: what differs in the last bit between kernels differs here.
DIGITS = """
import hashlib, json, sys
FIRST
import numpy as np, torch
from harness.core.kernels import in_force, why_not_same_everywhere
torch.manual_seed(0)
x, y = torch.randn(64, 128), torch.randn(64, 3)
net = torch.nn.Sequential(torch.nn.Linear(128, 128), torch.nn.Tanh(), torch.nn.Linear(128, 3))
opt = torch.optim.Adam(net.parameters(), 1e-2)
for _ in range(20):
    opt.zero_grad(); loss = ((net(x) - y) ** 2).mean(); loss.backward(); opt.step()
a = np.random.default_rng(0).normal(size=4096)
digits = hashlib.sha256(net(x).detach().numpy().tobytes() + np.exp(a).tobytes()
                        + np.arctan2(a, a + 1).tobytes()).hexdigest()
kernels = in_force()
why = None if kernels["same_everywhere"] else why_not_same_everywhere(kernels)
print(json.dumps({"digits": digits, "kernels": kernels, "why": why}))
"""


def _run(first: str, **env: str) -> dict:
    """The DIGITS script in a fresh interpreter, ``first`` its first import, the pins unset
    unless ``env`` sets them."""
    clean = unpinned(os.environ)
    result = subprocess.run(
        [sys.executable, "-c", DIGITS.replace("FIRST", first)],
        env={**clean, **env},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout.splitlines()[-1])


@needs_avx2
def test_importing_harness_pins_the_avx2_kernels_and_the_digits_do_not_follow_the_cpu() -> None:
    pinned = _run("import harness")
    assert pinned["kernels"] == {
        "mkl": "AVX2",
        "numpy": pinned["kernels"]["numpy"],
        "openblas": ["Haswell"],
        "torch": "AVX2",
        "same_everywhere": True,
    }
    assert not {"X86_V4", "AVX512_ICL", "AVX512_SPR"} & set(pinned["kernels"]["numpy"])
    # MKL told to run as on a CPU without AVX-512: the pinned digits are the same.
    as_on_avx2 = _run("import harness", MKL_ENABLE_INSTRUCTIONS="AVX2")
    assert as_on_avx2["digits"] == pinned["digits"]


@needs_avx2
def test_a_kernel_the_environment_chose_and_the_native_switch_are_kept_and_reported() -> None:
    chosen = _run("import harness", MKL_CBWR="AUTO")
    assert chosen["kernels"]["mkl"] == "AUTO" and not chosen["kernels"]["same_everywhere"]
    assert chosen["why"].startswith("MKL AUTO") and "set by the environment" in chosen["why"]
    native = _run("import harness", **{NATIVE: "1"})
    assert native["kernels"]["mkl"] == "native" and not native["kernels"]["same_everywhere"]
    assert NATIVE in native["why"]


@needs_avx2
def test_numpy_imported_before_harness_keeps_its_own_kernels_and_the_run_is_told_why() -> None:
    late = _run("import numpy, harness")
    assert late["kernels"]["mkl"] == "AVX2"  # MKL reads its branch at its first call: in time
    if late["kernels"]["same_everywhere"]:  # a CPU without AVX-512: NumPy's own are AVX2
        assert late["why"] is None
    else:
        assert "import harness first" in late["why"]
