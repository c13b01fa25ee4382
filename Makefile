# Newcomer entry points. `make run` and `make test` set everything up themselves.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: help setup run test test-fp test-ray bench format lint docs

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-8s %s\n", $$1, $$2}'

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(VENV)/.installed: $(BIN)/python pyproject.toml
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0  # CPU build from local disk; before the project
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $@

setup: $(VENV)/.installed  ## create .venv and install the harness (editable) with dev tools

run: setup  ## run the main job (results under outputs/<date>/<time>/)
	$(BIN)/python -m harness $(ARGS)

# Passed on a 2-core AMD EPYC without AVX-512 (2026-11-25) on every path of FP_PATHS below too.
lint: setup  ## ruff (lint and format check) and mypy
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

test: lint docs  ## lint and type-check, build the docs strictly, then the test suite (slow tests excluded)
	$(BIN)/python -m pytest

docs: setup  ## the documentation site, built strictly into site/ (a broken link or anchor fails)
	$(BIN)/python -m harness.config_reference --check
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

# The floating-point paths `make test-fp` runs the suite on, one after the other: one BLAS thread,
# OpenBLAS's kernels for three CPU families, and NumPy without its AVX2/AVX-512 dispatch.
FP_PATHS := OMP_NUM_THREADS=1 OPENBLAS_CORETYPE=Sandybridge OPENBLAS_CORETYPE=Haswell \
	OPENBLAS_CORETYPE=Zen NPY_DISABLE_CPU_FEATURES=X86_V3

test-fp: setup  ## the test suite once per floating-point path (BLAS threads, kernels, SIMD): ~5x `make test`
	@for path in $(FP_PATHS); do echo "== $$path"; env $$path $(BIN)/python -m pytest -q || exit 1; done

test-ray: setup  ## the Ray launcher's tests (installs the `ray` extra: ~60 packages, ~2 min)
	$(BIN)/pip install --quiet -e '.[dev,ray]'
	$(BIN)/python -m pytest tests/test_launchers.py -m '' --durations=0

bench: setup  ## benchmarks, printed as tables (installs the `bench` extra: cvxpy)
	$(BIN)/pip install --quiet -e '.[dev,bench]'
	$(BIN)/python -m bench.plant_throughput
	$(BIN)/python -m bench.collect_throughput
	$(BIN)/python -m bench.driver_sawtooth
	$(BIN)/python -m bench.mpc_solve_time
	$(BIN)/python -m bench.controller_solve_time
	$(BIN)/python -m bench.qp_formulation --quick
	$(BIN)/python -m bench.training_speed
	$(BIN)/python -m bench.input_structure

format: setup  ## format and autofix
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .
