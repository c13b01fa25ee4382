"""The physics baseline's closed loops, driven once per machine and code, not once per job.

A controller that brings its own model (``OwnModelFactory``: the single-track MPC) drives the
same run in every job of a sweep that shares its plant, dataset and references: its model is
identified from the training drives, not from the job's learner. At paper scale that was 5 of a
job's 7 minutes of tracking, repeated by every learner. Such a run is stored under
``$KOOPMAN_HARNESS_CACHE/tracking/<key>/`` (``metrics.json``, ``run.npz``, ``figure.png``) and
reused, its metrics marked ``reused_from`` (the key and the run directory that drove it; its
step times are that run's).

The key is a SHA-256 of everything the run depends on: the source of every module of
``harness``, ``learners`` and ``controllers`` (and the plant's C and MJCF files) with the versions
of the numerical libraries, the plant's parameters, the dataset's key, the model's and the
controller's settings, the reference and its path, and the job's thread counts. A change to any
of them is another key. Only a job that records nothing reuses a run: a recording holds what its
job drove. The cache is safe to delete.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from collections.abc import Mapping
from functools import cache
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from harness.core.kernels import in_force
from harness.core.paths import REPO_ROOT
from harness.core.threads import threads_in_use
from harness.plant.native import cache_dir

PACKAGES = ("harness", "learners", "controllers", "models")  # models: the MJCF the plant loads
SOURCES = ("*.py", "*.c", "*.h", "*.xml")
LIBRARIES = ("numpy", "scipy", "mujoco", "daqp", "piqp", "torch")
FILES = ("metrics.json", "run.npz", "figure.png")


@cache
def code_digest() -> str:
    """SHA-256 of every source file of the packages (path and bytes) and the libraries'
    versions: the code a stored run was driven by."""
    digest = hashlib.sha256()
    for package in PACKAGES:
        for pattern in SOURCES:
            for path in sorted((REPO_ROOT / package).rglob(pattern)):
                digest.update(str(path.relative_to(REPO_ROOT)).encode())
                digest.update(path.read_bytes())
    for library in LIBRARIES:
        try:
            version = metadata.version(library)
        except metadata.PackageNotFoundError:
            version = "absent"
        digest.update(f"{library}=={version}".encode())
    return digest.hexdigest()


def run_key(parts: Mapping[str, Any], reference: np.ndarray) -> str:
    """The key of one run: ``parts`` (plain values, settings' reprs) and the reference's bytes,
    with the code and the job's threads and kernels."""
    described = {
        **parts,
        "code": code_digest(),
        "threads": threads_in_use(),
        "kernels": in_force(),
        "reference": hashlib.sha256(np.ascontiguousarray(reference).tobytes()).hexdigest(),
    }
    text = json.dumps(described, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def root() -> Path:
    return cache_dir() / "tracking"


def load(key: str) -> dict[str, Any] | None:
    """The stored run: ``{"metrics": ..., "driven_in": <its run directory>}`` (None: not
    stored, or stored incompletely)."""
    folder = root() / key
    if not all((folder / name).is_file() for name in FILES[:2]):
        return None
    try:
        stored = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(stored, dict) or not {"metrics", "driven_in"} <= set(stored):
        return None
    return stored


def copy_out(key: str, arrays_path: Path, figure_path: Path) -> None:
    """The stored run's arrays and figure, where the job's own would go."""
    folder = root() / key
    shutil.copyfile(folder / "run.npz", arrays_path)
    if (folder / "figure.png").is_file():
        shutil.copyfile(folder / "figure.png", figure_path)


def store(key: str, driven: Mapping[str, Any], arrays_path: Path, figure_path: Path) -> None:
    """Keep a run for the jobs after this one: written whole into a temporary folder, then
    renamed (a job beside this one storing the same run first wins; either is the same run)."""
    folder = root() / key
    if folder.exists():
        return
    root().mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=root(), prefix=f".{key}."))
    try:
        (staging / "metrics.json").write_text(json.dumps(driven, indent=1))
        shutil.copyfile(arrays_path, staging / "run.npz")
        if figure_path.is_file():
            shutil.copyfile(figure_path, staging / "figure.png")
        staging.rename(folder)
    except OSError:
        shutil.rmtree(staging, ignore_errors=True)
