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
knows plants only through :class:`harness.core.contracts.Plant`; worker processes get the plant by
pickling (a ``Sedan`` pickles as its parameters and is rebuilt there).

What the store guarantees (``tests/test_store_faults.py`` injects each fault):

- Every file is written atomically; temporary files a killed writer left behind are removed by
  the next collection, under the dataset's lock.
- An interrupted collection resumes with the episodes that are missing. A missing episode file,
  or one that fails its checksum, is recollected alone (its seed and length are fixed by the
  config, so it gets the same bytes); the warning says so. A recollected episode whose bytes
  differ from its recorded checksum stops the run (the machine does not reproduce the data).
- ``manifest.json`` carries a SHA-256 of its own content (``manifest_sha256``). A manifest that
  cannot be read or fails that checksum is rebuilt from the episode files that verify on their
  own (the zip's CRC-32 of every array, shapes, the time axis, the planned length); everything
  in it is derived from the config, the plant and those files, so the rebuilt manifest has the
  bytes of the original (as long as the package versions it records have not changed).
- ``load`` never uses a file that fails a checksum: it stops with one line naming the file.
- No episode holding a NaN or an infinity is used, nor reaches the normalizer or the manifest:
  every read goes through ``_read_episode``. Without a manifest such a file is recollected
  alone (the warning names the file, the array, the column and the time); one that a manifest
  vouches for stops ``load`` in one line saying to delete it and the manifest.
- A disk that is full or not writable stops the collection with one line naming the directory.
- Worker processes exit as soon as their parent dies or is interrupted (SIGKILL, SIGTERM,
  Ctrl-C): each watches a pipe that only the parent holds open.
"""

from __future__ import annotations

import dataclasses
import errno
import fcntl
import hashlib
import json
import logging
import math
import os
import platform
import threading
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from multiprocessing import get_context, get_start_method
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from harness.core.checks import integer
from harness.core.contracts import Plant
from harness.core.episode import (
    SEDAN_INPUTS,
    Episode,
    InputChannel,
    MinMaxNormalizer,
    channels_from_dicts,
    sedan_inputs,
)
from harness.core.files import write_atomic, write_text_atomic
from harness.data.driver import DriverConfig, DriverKnowledge, SyntheticDriver
from harness.plant.native import cache_dir
from harness.plant.rollout import NO_INFO, closed_loop

FORMAT_VERSION = 1
SPLITS = ("train", "validation", "test")
_DRIVER_SOURCE = Path(__file__).with_name("driver.py")
MANIFEST = "manifest.json"
MANIFEST_CHECKSUM = "manifest_sha256"
# Refuse configs that imply more control steps than this: 7.2 GB of episodes on disk and in
# memory when loaded, hours of collection (data=paper has at most 1.6e6).
MAX_TOTAL_STEPS = 100_000_000
BYTES_PER_STEP = 9 * 8  # time, 3 states, 2 inputs, 3 poses as float64
STEPS_PER_SECOND = 10_000  # one collection process (bench/collect_throughput.py)
_NOT_WRITABLE = (errno.EACCES, errno.EPERM, errno.EROFS)
_FULL = (errno.ENOSPC, errno.EDQUOT)

RERUN = "rerun the same collection (task=collect, same plant and data)"

log = logging.getLogger(__name__)


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
    # Each drive starts rolling straight at a speed drawn uniformly from [low, high] m/s (its
    # own seed per episode), up to a little above the lane change's 22.2 m/s that the main job
    # tracks; [0, 0]: every drive starts from rest, as the paper's (data=paper).
    start_speed_mps: tuple[float, float] = (0.0, 28.0)
    # The pedal's feature, the input the models are fitted in: [per unit of throttle opening,
    # per MPa of brake pressure]; null: the signed scale, throttle / 0.2 and brake / 9.1 MPa, each
    # in [-1, 1]. The episodes are the same; their key (and every model fitted on them) is not.
    pedal_gains: tuple[float, float] | None = None
    driver: DriverConfig = field(default_factory=DriverConfig)
    root: str | None = None  # None: $KOOPMAN_HARNESS_CACHE/datasets (~/.cache/koopman-harness)
    workers: int = 2  # processes
    record_every: int = 1  # decimation of the recording only

    def __post_init__(self) -> None:
        minimums = {"episodes": 3, "min_steps": 10, "max_steps": 10, "seed": 0}
        for key, minimum in {**minimums, "workers": 1, "record_every": 1}.items():
            setattr(self, key, integer(f"data.{key}", getattr(self, key), minimum))
        if not self.min_steps <= self.max_steps:
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
        speeds = tuple(float(v) for v in self.start_speed_mps)  # the schema hands a list
        self.start_speed_mps = speeds  # type: ignore[assignment]
        if len(speeds) != 2 or not 0 <= speeds[0] <= speeds[1] <= self.driver.max_speed_mps:
            raise ValueError(
                f"data.start_speed_mps must be [low, high] with 0 <= low <= high <= "
                f"data.driver.max_speed_mps ({self.driver.max_speed_mps}), got {list(speeds)}"
            )
        if self.pedal_gains is not None:
            gains = tuple(float(v) for v in self.pedal_gains)  # the schema hands a list
            self.pedal_gains = gains  # type: ignore[assignment]
            if len(gains) != 2 or not all(0 < g < math.inf for g in gains):
                raise ValueError(
                    f"data.pedal_gains must be [throttle, brake] gains > 0 and finite, or null "
                    f"(got {list(gains)})"
                )
        total = self.episodes * self.max_steps
        if total > MAX_TOTAL_STEPS:
            raise ValueError(
                f"data.max_steps ({self.max_steps}) x data.episodes ({self.episodes}) allows "
                f"{total:.3g} control steps, about {total * BYTES_PER_STEP / 1e9:.3g} GB and "
                f"{total / STEPS_PER_SECOND / 3600:.3g} h of collection; at most "
                f"{MAX_TOTAL_STEPS:.0e} are accepted (data=paper: 1.6e+06)"
            )

    def content(self) -> dict[str, Any]:
        """The fields that determine the data (everything but where and how fast)."""
        values = dataclasses.asdict(self)
        for transient in ("root", "workers", "record_every", "name"):
            values.pop(transient)
        values["split"] = dict(self.split)
        if self.pedal_gains is None:  # the signed scale: the key datasets had before the setting
            values.pop("pedal_gains")
        return values

    @property
    def channels(self) -> tuple[InputChannel, ...]:
        """The inputs as the models see them: the sedan's, with :attr:`pedal_gains`."""
        return sedan_inputs(self.pedal_gains)

    def start_speed(self, index: int) -> float:
        """The speed episode ``index`` starts at (m/s), from a seed of its own: the other draws
        of the drive do not move when the range changes."""
        low, high = self.start_speed_mps
        if high == 0:
            return 0.0
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 4, index]))
        return float(rng.uniform(low, high))

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

    @property
    def period_s(self) -> float:
        """The model period: the time between two samples of every episode (to 9 digits: a
        log's time column of 0.01 s steps sums to 0.05000000000001 s)."""
        return float(f"{np.median(np.diff(self.train[0].time_s)):.9g}")

    @property
    def from_logs(self) -> bool:
        """Whether these are a user's logs (:mod:`harness.data.logs`), not drives of our plant."""
        return self.manifest.get("source") == "logs"

    def episodes(self) -> list[Episode]:
        return self.train + self.validation + self.test


def file_sha256(path: Path) -> str:
    """The file's SHA-256 (hex), read in chunks: a stored episode's, or a user's log's."""
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


def dataset_root(data: Any) -> Path:
    """Where datasets of ``data`` (a :class:`DataConfig` or logs' config: its ``root``) live."""
    root = getattr(data, "root", None)
    return Path(root).expanduser() if root else cache_dir() / "datasets"


def _episode_name(index: int) -> str:
    return f"episode_{index:04d}"


def _manifest_body(
    key: str,
    data: DataConfig,
    fingerprint: Mapping[str, Any],
    knowledge: DriverKnowledge,
    versions: Mapping[str, str],
    episodes: Mapping[str, Mapping[str, Any]],
) -> dict[str, Any]:
    """The manifest of an incomplete dataset: all of it derived from the config, the plant and
    the episode files (episodes in name order, so a rebuilt manifest has the original's bytes)."""
    body = {
        "format": FORMAT_VERSION,
        "key": key,
        "data": data.content(),
        "plant": dict(fingerprint),
        "driver_knowledge": dataclasses.asdict(knowledge),
        "versions": dict(versions),
        "episodes": {name: dict(episodes[name]) for name in sorted(episodes)},
        "complete": False,
    }
    if data.channels != SEDAN_INPUTS:  # the pedal in other units: the episodes' channels say so
        body["inputs"] = [channel.to_dict() for channel in data.channels]
    return body


def _manifest_digest(manifest: Mapping[str, Any]) -> str:
    body = {k: v for k, v in manifest.items() if k != MANIFEST_CHECKSUM}
    canonical = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canonical.encode()).hexdigest()


def write_manifest(directory: Path, manifest: dict[str, Any]) -> None:
    """The manifest, with a checksum of its own body, written atomically: the last file a
    dataset gets, so that a directory with one is complete."""
    body = {k: v for k, v in manifest.items() if k != MANIFEST_CHECKSUM}
    text = json.dumps({**body, MANIFEST_CHECKSUM: _manifest_digest(body)}, indent=1)
    write_text_atomic(directory / MANIFEST, text)


class _ManifestError(Exception):
    """``manifest.json`` cannot be trusted; the message says why (a clause after its path)."""


def read_manifest(directory: Path) -> dict[str, Any] | None:
    """The stored manifest, None where there is none; :class:`_ManifestError` where it cannot
    be read or does not match its own checksum (a flipped byte, an edited digit or name)."""
    path = directory / MANIFEST
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    try:
        manifest = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as error:
        raise _ManifestError(
            f"is not UTF-8 text (byte 0x{raw[error.start]:02x} at {error.start})"
        ) from None
    except json.JSONDecodeError as error:
        raise _ManifestError(f"is not valid JSON ({error})") from None
    if not isinstance(manifest, dict):
        raise _ManifestError("is not a JSON object")
    if MANIFEST_CHECKSUM not in manifest:
        raise _ManifestError("has no checksum of its own (written by an older harness)")
    try:
        digest = _manifest_digest(manifest)
    except ValueError as error:  # NaN or infinity written into it
        raise _ManifestError(f"holds a value JSON does not allow ({error})") from None
    if manifest[MANIFEST_CHECKSUM] != digest:
        raise _ManifestError("fails its own checksum (edited or damaged)")
    if manifest.get("format") != FORMAT_VERSION:
        raise _ManifestError(f"is of format {manifest.get('format')}, not {FORMAT_VERSION}")
    return manifest


@contextmanager
def locked(directory: Path) -> Iterator[None]:
    """One collector per dataset: concurrent jobs wait here instead of collecting twice."""
    with (directory / ".lock").open("w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def remove_temporaries(directory: Path) -> None:
    """Half-written files of a killed writer (``.<name>.<random>.tmp``); call under the lock."""
    for path in directory.glob(".*.tmp"):
        path.unlink(missing_ok=True)


def _episode_seed(data: DataConfig, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([data.seed, 2, index]))


def drive_episode(
    plant: Plant, data: DataConfig, knowledge: DriverKnowledge, index: int, steps: int
) -> dict[str, np.ndarray | bool]:
    """One episode from rest or rolling (``data.start_speed``), driven by the synthetic driver;
    stops early if the car spins (the drive is kept up to the spin, not the spin itself)."""
    speed = data.start_speed(index)
    driver = SyntheticDriver(
        data.driver,
        _episode_seed(data, index),
        plant.dt,
        road_friction=knowledge.road_friction,
        steering_ratio=knowledge.steering_ratio,
        speed_mps=speed,
    )
    run = closed_loop(
        plant,
        lambda x, t: (driver(t, x), NO_INFO),
        steps,
        seed=index,
        speed_mps=speed,
        stop=lambda t, x: driver.spinning(x),
        keep_stop_frame=False,
        act_on_last=True,  # every recorded frame holds the input the driver applied there
    )
    return {
        "time_s": run.time_s,
        "states": run.states,
        "inputs": run.inputs,
        "poses": run.poses,
        "spun": run.stopped,
    }


def _entry(path: Path, steps: int, spun: bool) -> dict[str, Any]:
    return {"file": path.name, "sha256": file_sha256(path), "steps": steps, "spun": spun}


def _check_episode_file(path: Path, planned: int, dt: float) -> dict[str, Any]:
    """The manifest entry of an episode file that verifies on its own, without a manifest: the
    zip's CRC-32 of every array, the shapes, the time axis and the planned length. An episode
    shorter than planned is one where the car spun (``drive_episode`` stops there).

    Raises ``ValueError`` (or ``OSError``, ``zipfile.BadZipFile``) saying what is wrong."""
    episode = _read_episode(path, path.stem)
    steps = len(episode)
    if not 2 <= steps <= planned:
        raise ValueError(f"has {steps} steps ({planned} planned)")
    if not np.array_equal(episode.time_s, np.arange(steps) * dt):
        raise ValueError("has another time axis")
    return _entry(path, steps, steps < planned)


def _read_episode(
    path: Path, name: str, channels: tuple[InputChannel, ...] = SEDAN_INPUTS
) -> Episode:
    """The episode in ``path``: every read of an episode file goes through here, so a NaN or an
    infinity in it is refused by file name before a normalizer, a fit or a manifest sees it.

    Raises ``ValueError`` (or ``OSError``, ``zipfile.BadZipFile``) with a clause saying what is
    wrong (the caller names the file)."""
    with np.load(path) as arrays:
        if sorted(arrays.files) != ["inputs", "poses", "states", "time_s"]:
            raise ValueError(f"holds arrays {sorted(arrays.files)}")
        time_s, states = arrays["time_s"], arrays["states"]
        inputs, poses = arrays["inputs"], arrays["poses"]
    steps = len(time_s) if time_s.ndim == 1 else -1
    shapes = (time_s.shape, states.shape, inputs.shape, poses.shape)
    if shapes != ((steps,), (steps, 3), (steps, len(channels)), (steps, 3)):
        raise ValueError(f"holds arrays of shapes {shapes} (time_s, states, inputs, poses)")
    episode = Episode(name, time_s, states, inputs, poses, channels)
    problem = episode.non_finite()
    if problem is not None:
        raise ValueError(problem)
    return episode


def verify_episodes(directory: Path, episodes: Mapping[str, Mapping[str, Any]]) -> dict[str, str]:
    """Per episode that cannot be used, what is wrong with its file."""
    problems = {}
    for name, entry in episodes.items():
        path = directory / entry["file"]
        if not path.exists():
            problems[name] = "is missing"
        elif file_sha256(path) != entry["sha256"]:
            problems[name] = "fails its checksum (truncated or modified)"
    return problems


_worker_plant: Plant | None = None


def _start_worker(plant: Plant, parent: Connection | None) -> None:
    """Each worker gets the plant once (pickled: a spawned process rebuilds it), not per episode,
    and (in a process) the reading end of a pipe only its parent holds open."""
    global _worker_plant
    _worker_plant = plant
    if parent is not None:
        threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()


def _exit_with_parent(parent: Connection) -> None:
    """Wait for end-of-file on the pipe (the parent exited, was killed or gave up on us), then
    leave at once: an orphaned worker would idle forever and keep the resource tracker alive."""
    try:
        while True:
            parent.recv_bytes()
    except (EOFError, OSError):
        os._exit(1)


def _collect_one(
    data: DataConfig, knowledge: DriverKnowledge, index: int, steps: int, directory: str
) -> tuple[int, dict[str, Any]]:
    if _worker_plant is None:
        raise RuntimeError("a collection worker was started without its plant")
    episode = drive_episode(_worker_plant, data, knowledge, index, steps)
    path = Path(directory) / f"{_episode_name(index)}.npz"
    arrays = {k: v for k, v in episode.items() if k != "spun"}
    write_atomic(path, lambda handle: np.savez(handle, **arrays))
    return index, _entry(path, len(episode["time_s"]), bool(episode["spun"]))


@contextmanager
def _pool(workers: int, plant: Plant) -> Iterator[Executor]:
    """Spawned worker processes; in-process (one thread, on ``plant`` itself) where spawning
    cannot work. Leaving the block by an exception (an error, Ctrl-C) stops the workers at once
    instead of letting them finish the queued episodes.

    A job run by a process-based launcher (joblib's loky workers) has a start method that a
    freshly spawned child cannot restore; there the sweep's other jobs keep the cores busy.
    """
    pool: Executor
    alive: Connection | None = None
    if workers > 1 and get_start_method(allow_none=True) in (None, "spawn", "fork", "forkserver"):
        context = get_context("spawn")
        watched, alive = context.Pipe(duplex=False)
        pool = ProcessPoolExecutor(
            workers, mp_context=context, initializer=_start_worker, initargs=(plant, watched)
        )
    else:
        watched = None
        pool = ThreadPoolExecutor(1, initializer=_start_worker, initargs=(plant, None))
    try:
        yield pool
    except BaseException:
        if alive is not None:
            alive.close()  # every worker reads end-of-file and exits, mid-episode
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    else:
        pool.shutdown(wait=True)
    finally:
        for end in (alive, watched):
            if end is not None:
                end.close()


def _os_error(error: OSError, directory: Path, data: DataConfig) -> DatasetError:
    """A full or read-only disk in one line that names the directory and what to do."""
    reason = error.strerror or str(error)
    if error.errno in _FULL:
        return DatasetError(
            f"data: no space left to write the dataset {directory} ({reason}); free space "
            f"there and rerun (the finished episodes are kept) or set data.root=<another disk>"
        )
    if error.errno in _NOT_WRITABLE:
        return DatasetError(
            f"data: {dataset_root(data)} is not writable ({reason}); "
            f"set data.root=<a writable directory>"
        )
    return DatasetError(f"data: cannot write the dataset {directory} ({error})")


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
    drives the episodes, the others find them stored and drive none. Damage is repaired, with a
    warning naming the file: a missing or corrupt episode is recollected alone, a damaged
    manifest rebuilt from the episode files.
    """
    fingerprint = plant.fingerprint
    key = content_key(fingerprint, data, knowledge)
    directory = dataset_root(data) / key
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with locked(directory):
            try:
                return directory, _collect_locked(plant, data, knowledge, directory, key, progress)
            finally:
                remove_temporaries(directory)  # the workers have stopped by now
    except OSError as error:
        if error.errno in _NOT_WRITABLE and _intact(directory, key):
            return directory, 0  # a complete dataset on a read-only disk is fine to use
        raise _os_error(error, directory, data) from error


def _intact(directory: Path, key: str) -> bool:
    try:
        manifest = read_manifest(directory)
    except (_ManifestError, OSError):
        return False
    return (
        manifest is not None
        and manifest["key"] == key
        and manifest["complete"]
        and not verify_episodes(directory, manifest["episodes"])
    )


def _collect_locked(
    plant: Plant,
    data: DataConfig,
    knowledge: DriverKnowledge,
    directory: Path,
    key: str,
    progress: bool,
) -> int:
    """Repair, resume or reuse the dataset in ``directory`` (locked); the episodes driven."""
    remove_temporaries(directory)
    manifest_path = directory / MANIFEST
    lengths = data.episode_lengths()
    try:
        stored = read_manifest(directory)
    except _ManifestError as damaged:
        log.warning("data: %s %s; rebuilding it from the episode files", manifest_path, damaged)
        stored = None
    if stored is not None and stored["key"] != key:
        raise DatasetError(
            f"data: {manifest_path} belongs to dataset {stored['key']}, not to {key} (its "
            f"directory); delete {directory} to collect afresh"
        )
    recorded: dict[str, str] = {}  # checksums the recollected episodes must reproduce
    if stored is None:
        versions = _versions()
        episodes = _episodes_from_files(directory, data, lengths, plant.dt)
    else:
        versions = stored["versions"]
        episodes = dict(stored["episodes"])
        for name, problem in verify_episodes(directory, episodes).items():
            path = directory / episodes[name]["file"]
            log.warning(
                "data: %s %s; recollecting %s alone (same seed, same bytes)", path, problem, name
            )
            path.unlink(missing_ok=True)
            recorded[name] = episodes.pop(name)["sha256"]
    manifest = _manifest_body(key, data, plant.fingerprint, knowledge, versions, episodes)
    todo = [i for i in range(data.episodes) if _episode_name(i) not in episodes]
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
        with _pool(min(data.workers, len(todo)), plant) as pool:
            futures = [
                pool.submit(_collect_one, data, knowledge, i, lengths[i], str(directory))
                for i in todo
            ]
            for future in as_completed(futures):
                index, entry = future.result()
                name = _episode_name(index)
                if name in recorded and entry["sha256"] != recorded[name]:
                    raise DatasetError(
                        f"data: {directory / entry['file']} was recollected with other bytes "
                        f"than it had: this machine does not reproduce the dataset; delete "
                        f"{directory} to collect afresh"
                    )
                manifest["episodes"][name] = entry
                manifest["episodes"] = dict(sorted(manifest["episodes"].items()))
                write_manifest(directory, manifest)  # progress survives an interruption
                bar.update(lengths[index])
        bar.close()
    if stored is None or todo or not stored["complete"]:
        _complete(directory, data, manifest)
    return len(todo)


def _complete(directory: Path, data: DataConfig, manifest: dict[str, Any]) -> None:
    """Every episode collected: the seeded split and the training drives' normalizer, and the
    manifest marked complete."""
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
    write_manifest(directory, manifest)


def _episodes_from_files(
    directory: Path, data: DataConfig, lengths: Sequence[int], dt: float
) -> dict[str, dict[str, Any]]:
    """Manifest entries of the episode files that verify on their own (no manifest to trust);
    a file that does not is removed, with a warning, and recollected."""
    episodes = {}
    for index in range(data.episodes):
        name = _episode_name(index)
        path = directory / f"{name}.npz"
        if not path.exists():
            continue
        try:
            episodes[name] = _check_episode_file(path, lengths[index], dt)
        except (ValueError, KeyError, zipfile.BadZipFile, EOFError) as error:
            log.warning("data: %s is damaged (%s); recollecting %s alone", path, error, name)
            path.unlink()
    return episodes


def _load_episode(directory: Path, name: str, manifest: Mapping[str, Any]) -> Episode:
    """Episode ``name``, whose file has passed its checksum: a file that still cannot be used is
    one the manifest vouches for (rebuilt from it by an older harness, or edited with it), so
    both must go for the collection to drive the episode again."""
    path = directory / manifest["episodes"][name]["file"]
    described = manifest.get("inputs")  # logs, or the sedan's in other units; else the sedan's
    channels = channels_from_dicts(described)
    try:
        return _read_episode(path, name, channels)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as error:
        raise DatasetError(
            f"data: {path}: {error}; delete it and {directory / MANIFEST}, then {RERUN} to "
            f"recollect {name} alone"
        ) from error


def load(directory: Path | str) -> Dataset:
    """Load a complete dataset, checking the manifest and every file against its checksum first.

    Repairs are :func:`collect`'s (it knows the plant and the config); here a damaged file stops
    the load with one line naming it and saying how to repair it.
    """
    directory = Path(directory)
    path = directory / MANIFEST
    try:
        manifest = read_manifest(directory)
    except _ManifestError as damaged:
        raise DatasetError(
            f"data: {path} {damaged}; {RERUN} to rebuild it from the episode files"
        ) from None
    if manifest is None:
        raise DatasetError(f"data: {directory} has no {MANIFEST}; it is not a dataset")
    if not manifest["complete"]:
        raise DatasetError(f"data: {directory} is incomplete; {RERUN} to finish it")
    problems = verify_episodes(directory, manifest["episodes"])
    for name, problem in problems.items():
        raise DatasetError(
            f"data: {directory / manifest['episodes'][name]['file']} {problem}; {RERUN} to "
            f"recollect {name} alone (same seed, same bytes)"
        )
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
                data.channels,
            )
        )
    return again
