"""Benchmarks: each module prints a table and the machine it ran on (docs/guide/benchmarks.md)."""

import harness  # noqa: F401  (first: it pins the numerical kernels before NumPy loads)
