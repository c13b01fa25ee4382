"""Koopman vehicle harness: a MuJoCo sedan plant, learners, controllers and the Hydra app.

The layers, bottom up (the allowed arrows are listed once, in ``tests/test_imports.py``):
``harness.core``; ``learners``, ``controllers``, ``harness.plant``, ``harness.output``,
``harness.recorder``; ``harness.references``, ``harness.data``, ``harness.evaluation``;
``harness.config``, ``harness.tasks``, ``harness.report``; ``harness.app``.
"""

from harness.core.kernels import pin

# Before NumPy, OpenBLAS or MKL compute: the same kernels, hence the same digits, on every
# x86-64 machine with AVX2 (harness/core/kernels.py).
pin()
