"""The dataset store: collect episodes once, reuse them by content key, split by episode.

On-disk format (one directory per dataset, ``<root>/<key>/``):

- ``episode_0000.npz`` ... : arrays ``time_s (T,)``, ``states (T,3)``, ``inputs (T,2)``,
  ``poses (T,3)`` in the plant's units (SI; steering in degrees; pedal as in the plant).
- ``manifest.json``: format version, content key, the data configuration, the plant's
  fingerprint, what the driver knew of the car, package versions, per episode its file,
  SHA-256, number of steps and whether the car spun; once complete also the split (episode
  names per train / validation / test) and the min-max normalizer fitted on the training
  episodes.

The key is a hash of everything that determines the data: the plant's fingerprint (for the
sedan its parameters, the sources of its tyre callback and MJCF, the MuJoCo version), the data
config (episodes, lengths, driver, seed), what the driver knows of the car and the driver's
source. The same configuration reuses the stored dataset; any change gives a new key. The store
knows plants only through :class:`harness.interfaces.Plant`; worker processes get the plant by
pickling (a ``Sedan`` pickles as its parameters and is rebuilt there).
Every file is written atomically; an interrupted collection resumes with the episodes that are
missing; a file whose checksum does not match is reported and never used.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import math
import os
import platform
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from multiprocessing import get_context, get_start_method
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from harness.data.driver import DriverConfig, DriverKnowledge, SyntheticDriver
from harness.data.episode import Episode, MinMaxNormalizer
from harness.interfaces import Plant
from harness.plant.native import cache_dir

FORMAT_VERSION = 1
SPLITS = ("train", "validation", "test")
_DRIVER_SOURCE = Path(__file__).with_name("driver.py")


class DatasetError(ValueError):
    """A stored dataset cannot be used as it is; the message says what to do."""


@dataclass
class DataConfig:
    """What to collect (``conf/data/*.yaml``, whose schema this is); ``root``, ``workers`` and
    ``record_every`` do not change the data."""

    name: str = "default"
    episodes: int = 12
    # Episode lengths are log-uniform in [min_steps, max_steps] control periods.
    min_steps: int = 2000
    max_steps: int = 4000
    split: dict[str, int] = field(default_factory=lambda: {"train": 8, "validation": 2, "test": 2})
    seed: int = 0
    driver: DriverConfig = field(default_factory=DriverConfig)
    root: str | None = None  # None: $KOOPMAN_HARNESS_CACHE/datasets (~/.cache/koopman-harness)
    workers: int = 2  # processes
    record_every: int = 1  # decimation of the recording only

    def __post_init__(self) -> None:
        if self.episodes < 3:
            raise ValueError(f"data.episodes must be >= 3 (got {self.episodes})")
        if not 10 <= self.min_steps <= self.max_steps:
            raise ValueError(
                f"data.min_steps ({self.min_steps}) must be >= 10 and <= data.max_steps "
                f"({self.max_steps})"
            )
        if set(self.split) != set(SPLITS) or any(v < 1 for v in self.split.values()):
            raise ValueError(
                f"data.split needs train, validation and test counts >= 1 ({self.split})"
            )
        if sum(self.split.values()) != self.episodes:
            raise ValueError(
                f"data.split counts sum to {sum(self.split.values())}, "
                f"not data.episodes ({self.episodes})"
            )
        if self.workers < 1 or self.record_every < 1:
            raise ValueError("data.workers and data.record_every must be >= 1")

    def content(self) -> dict[str, Any]:
        """The fields that determine the data (everything but where and how fast)."""
        values = dataclasses.asdict(self)
        for transient in ("root", "workers", "record_every", "name"):
            values.pop(transient)
        values["split"] = dict(self.split)
        return values

    def episode_lengths(self) -> list[int]:
        """Log-uniform lengths in [min_steps, max_steps]: many shorter drives, some long ones."""
        rng = np.random.default_rng([self.seed, 1])
        low, high = math.log(self.min_steps), math.log(self.max_steps)
        return [round(math.exp(v)) for v in rng.uniform(low, high, self.episodes)]


@dataclass
class Dataset:
    """Loaded episodes split by episode, with the normalizer fitted on ``train``."""

    path: Path
    manifest: dict[str, Any]
    train: list[Episode]
    validation: list[Episode]
    test: list[Episode]
    normalizer: MinMaxNormalizer

    @property
    def key(self) -> str:
        return self.manifest["key"]

    def episodes(self) -> list[Episode]:
        return self.train + self.validation + self.test


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for package in ("mujoco", "numpy", "koopman-vehicle-harness"):
        try:
            versions[package] = version(package)
        except PackageNotFoundError:
            versions[package] = "unknown"
    return versions


def content_key(
    fingerprint: Mapping[str, Any], data: DataConfig, knowledge: DriverKnowledge
) -> str:
    """Hash of everything that determines the episodes' contents (``fingerprint``: the plant's)."""
    identity = {
        "format": FORMAT_VERSION,
        "plant": fingerprint,
        "data": data.content(),
        "driver_knowledge": dataclasses.asdict(knowledge),
        "driver_source": hashlib.sha256(_DRIVER_SOURCE.read_bytes()).hexdigest(),
    }
    return hashlib.sha256(json.dumps(identity, sort_keys=True, default=list).encode()).hexdigest()[
        :16
    ]


def dataset_root(data: DataConfig) -> Path:
    return Path(data.root).expanduser() if data.root else cache_dir() / "datasets"


def _write_atomic(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    write(tmp)
    os.replace(tmp, path)


def _write_manifest(path: Path, manifest: dict[str, Any]) -> None:
    _write_atomic(
        path / "manifest.json", lambda tmp: tmp.write_text(json.dumps(manifest, indent=1))
    )


@contextmanager
def _locked(directory: Path) -> Iterator[None]:
    """One collector per dataset: concurrent jobs wait here instead of collecting twice."""
    with (directory / ".lock").open("w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _episode_seed(data: DataConfig, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([data.seed, 2, index]))


def drive_episode(
    plant: Plant, data: DataConfig, knowledge: DriverKnowledge, index: int, steps: int
) -> dict[str, np.ndarray | bool]:
    """One episode from rest, driven by the synthetic driver; stops early if the car spins."""
    driver = SyntheticDriver(
        data.driver,
        _episode_seed(data, index),
        plant.dt,
        road_friction=knowledge.road_friction,
        steering_ratio=knowledge.steering_ratio,
    )
    states = np.empty((steps, 3))
    inputs = np.empty((steps, 2))
    poses = np.empty((steps, 3))
    x = plant.reset(seed=index)
    n = steps
    for k in range(steps):
        states[k], poses[k] = x, plant.pose
        inputs[k] = driver(k * plant.dt, x)
        if driver.spun:  # keep the drive up to the spin, not the spin itself
            n = max(k, 2)
            break
        x = plant.step(inputs[k])
    return {
        "time_s": np.arange(n) * plant.dt,
        "states": states[:n],
        "inputs": inputs[:n],
        "poses": poses[:n],
        "spun": driver.spun,
    }


_worker_plant: Plant | None = None


def _start_worker(plant: Plant) -> None:
    """Each worker gets the plant once (pickled: a spawned process rebuilds it), not per episode."""
    global _worker_plant
    _worker_plant = plant


def _collect_one(
    data: DataConfig, knowledge: DriverKnowledge, index: int, steps: int, directory: str
) -> tuple[int, str, int, bool]:
    if _worker_plant is None:
        raise RuntimeError("a collection worker was started without its plant")
    episode = drive_episode(_worker_plant, data, knowledge, index, steps)
    path = Path(directory) / f"episode_{index:04d}.npz"
    arrays = {k: v for k, v in episode.items() if k != "spun"}

    def write(tmp: Path) -> None:
        with tmp.open("wb") as handle:
            np.savez(handle, **arrays)

    _write_atomic(path, write)
    return index, _sha256(path), len(episode["time_s"]), bool(episode["spun"])


def _executor(workers: int, plant: Plant) -> Executor:
    """Spawned worker processes; in-process (one thread, on ``plant`` itself) where spawning
    cannot work.

    A job run by a process-based launcher (joblib's loky workers) has a start method that a
    freshly spawned child cannot restore; there the sweep's other jobs keep the cores busy.
    """
    if workers > 1 and get_start_method(allow_none=True) in (None, "spawn", "fork", "forkserver"):
        return ProcessPoolExecutor(
            workers,
            mp_context=get_context("spawn"),
            initializer=_start_worker,
            initargs=(plant,),
        )
    return ThreadPoolExecutor(1, initializer=_start_worker, initargs=(plant,))


def _read_manifest(directory: Path) -> dict[str, Any]:
    path = directory / "manifest.json"
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise DatasetError(
            f"data: {path} is not valid JSON ({error}); delete {directory} to recollect"
        ) from error


def _verify(directory: Path, manifest: dict[str, Any]) -> None:
    for name, entry in manifest["episodes"].items():
        path = directory / entry["file"]
        if not path.exists():
            raise DatasetError(f"data: {path} is missing; delete {directory} to recollect")
        if _sha256(path) != entry["sha256"]:
            raise DatasetError(
                f"data: {path} fails its checksum (truncated or modified); delete that file "
                f"and rerun to recollect episode {name}"
            )


def collect(
    plant: Plant, data: DataConfig, knowledge: DriverKnowledge, *, progress: bool = True
) -> Path:
    """Make sure the dataset for this configuration exists and is intact; return its directory."""
    return collect_counted(plant, data, knowledge, progress=progress)[0]


def collect_counted(
    plant: Plant, data: DataConfig, knowledge: DriverKnowledge, *, progress: bool = True
) -> tuple[Path, int]:
    """``collect``, also returning how many episodes this call drove (0: all were reused).

    Concurrent callers (the jobs of a parallel sweep) queue on the dataset's lock: the first
    drives the episodes, the others find them stored and drive none.
    """
    fingerprint = plant.fingerprint
    key = content_key(fingerprint, data, knowledge)
    directory = dataset_root(data) / key
    directory.mkdir(parents=True, exist_ok=True)
    with _locked(directory):
        manifest_path = directory / "manifest.json"
        if manifest_path.exists():
            manifest = _read_manifest(directory)
            if manifest.get("key") != key:
                raise DatasetError(f"data: {manifest_path} belongs to another dataset; delete it")
        else:
            manifest = {
                "format": FORMAT_VERSION,
                "key": key,
                "data": data.content(),
                "plant": fingerprint,
                "driver_knowledge": dataclasses.asdict(knowledge),
                "versions": _versions(),
                "episodes": {},
                "complete": False,
            }
        # Finished episodes are kept (resume); a file that fails its checksum stops us here.
        _verify(directory, manifest)
        lengths = data.episode_lengths()
        todo = [i for i in range(data.episodes) if f"episode_{i:04d}" not in manifest["episodes"]]
        if todo:
            # Longest first: two workers finish together instead of one waiting on a long drive.
            todo.sort(key=lambda i: -lengths[i])
            bar = tqdm(
                total=sum(lengths[i] for i in todo),
                unit="step",
                desc="collect",
                disable=not progress,
                smoothing=0.1,
            )
            workers = min(data.workers, len(todo))
            with _executor(workers, plant) as pool:
                futures = [
                    pool.submit(_collect_one, data, knowledge, i, lengths[i], str(directory))
                    for i in todo
                ]
                for future in as_completed(futures):
                    index, sha, steps, spun = future.result()
                    manifest["episodes"][f"episode_{index:04d}"] = {
                        "file": f"episode_{index:04d}.npz",
                        "sha256": sha,
                        "steps": steps,
                        "spun": spun,
                    }
                    _write_manifest(directory, manifest)  # progress survives an interruption
                    bar.update(lengths[index])
            bar.close()
        if not manifest["complete"]:
            names = sorted(manifest["episodes"])
            order = np.random.default_rng([data.seed, 3]).permutation(len(names))
            shuffled = [names[i] for i in order]
            counts = [data.split[s] for s in SPLITS]
            bounds = np.cumsum([0, *counts])
            manifest["split"] = {
                s: sorted(shuffled[bounds[i] : bounds[i + 1]]) for i, s in enumerate(SPLITS)
            }
            train = [_load_episode(directory, n, manifest) for n in manifest["split"]["train"]]
            manifest["normalizer"] = MinMaxNormalizer.fit(train).to_dict()
            manifest["complete"] = True
            _write_manifest(directory, manifest)
    return directory, len(todo)


def _load_episode(directory: Path, name: str, manifest: dict[str, Any]) -> Episode:
    path = directory / manifest["episodes"][name]["file"]
    try:
        with np.load(path) as arrays:
            return Episode(
                name, arrays["time_s"], arrays["states"], arrays["inputs"], arrays["poses"]
            )
    except (OSError, ValueError, KeyError) as error:
        raise DatasetError(f"data: cannot read {path} ({error}); delete it and rerun") from error


def load(directory: Path | str) -> Dataset:
    """Load a complete dataset, checking every file against its checksum first."""
    directory = Path(directory)
    if not (directory / "manifest.json").exists():
        raise DatasetError(f"data: {directory} has no manifest.json; it is not a dataset")
    manifest = _read_manifest(directory)
    if manifest.get("format") != FORMAT_VERSION or not manifest.get("complete"):
        raise DatasetError(f"data: {directory} is incomplete or of another format; rerun collect")
    _verify(directory, manifest)
    splits = {
        s: [_load_episode(directory, n, manifest) for n in manifest["split"][s]] for s in SPLITS
    }
    return Dataset(
        directory,
        manifest,
        splits["train"],
        splits["validation"],
        splits["test"],
        MinMaxNormalizer.from_dict(manifest["normalizer"]),
    )


def drive_again(
    plant: Plant, data: DataConfig, knowledge: DriverKnowledge, episodes: Sequence[Episode]
) -> list[Episode]:
    """The same drives (episode seeds and lengths of ``data``) on another plant, not stored.

    The driver is closed-loop (it reacts to speed and slip), so on a wet road it drives the same
    intentions more gently; this is what a model trained on one plant meets on another.
    """
    lengths = data.episode_lengths()
    again = []
    for episode in episodes:
        index = int(episode.name.rsplit("_", 1)[-1])
        arrays = drive_episode(plant, data, knowledge, index, lengths[index])
        again.append(
            Episode(
                episode.name,
                arrays["time_s"],
                arrays["states"],
                arrays["inputs"],
                arrays["poses"],
            )
        )
    return again
