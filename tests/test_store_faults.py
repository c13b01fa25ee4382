"""Fault injection for the dataset store: what a damaged, full, read-only or killed store does.

Every repair ends byte-identical to an uninterrupted collection (episodes, split, normalizer and
the manifest itself); every refusal is one line that names the file or the directory.
"""

from __future__ import annotations

import errno
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from harness.config import validate
from harness.data import store
from harness.data.driver import DriverKnowledge
from harness.data.store import DataConfig, DatasetError, collect, collect_counted, load
from harness.plant import Sedan, SedanParams
from tests.helpers import compose

DRY = DriverKnowledge.of(SedanParams())
NAMES = [f"episode_{i:04d}" for i in range(4)]


def tiny(root: Path, **changes) -> DataConfig:
    values = dict(
        episodes=4,
        min_steps=200,
        max_steps=300,
        workers=1,
        root=str(root),
        split={"train": 2, "validation": 1, "test": 1},
    )
    values.update(changes)
    return DataConfig(**values)


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory, sedan: Sedan) -> Path:
    """An uninterrupted collection: what every repaired one must equal, byte for byte."""
    return collect(sedan, tiny(tmp_path_factory.mktemp("reference")), DRY, progress=False)


def copy_of(reference: Path, root: Path) -> Path:
    copy = root / reference.name
    copy.mkdir(parents=True)
    for path in reference.iterdir():
        (copy / path.name).write_bytes(path.read_bytes())
    return copy


def assert_same_bytes(directory: Path, reference: Path) -> None:
    for path in [*reference.glob("*.npz"), reference / "manifest.json"]:
        assert (directory / path.name).read_bytes() == path.read_bytes(), path.name
    assert not list(directory.glob(".*.tmp"))


def warnings_of(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]


# -- episode files -------------------------------------------------------------------------------


def test_truncated_deleted_and_altered_episodes_are_recollected_alone_to_the_same_bytes(
    reference: Path, tmp_path: Path, sedan: Sedan, caplog: pytest.LogCaptureFixture
) -> None:
    copy = copy_of(reference, tmp_path)
    truncated, deleted, altered, kept = (copy / f"{name}.npz" for name in NAMES)
    truncated.write_bytes(truncated.read_bytes()[:-100])
    deleted.unlink()
    raw = bytearray(altered.read_bytes())
    raw[len(raw) // 2] ^= 0x01
    altered.write_bytes(bytes(raw))
    stamp = kept.stat().st_mtime_ns
    with pytest.raises(DatasetError, match=r"episode_0000\.npz fails its checksum.*alone"):
        load(copy)  # load alone cannot recollect: it says how

    directory, collected = collect_counted(sedan, tiny(tmp_path), DRY, progress=False)
    assert (directory, collected) == (copy, 3)
    warnings = warnings_of(caplog)
    for path, name in [(truncated, NAMES[0]), (deleted, NAMES[1]), (altered, NAMES[2])]:
        (line,) = [w for w in warnings if str(path) in w]
        assert f"recollecting {name} alone" in line and "\n" not in line
    assert kept.stat().st_mtime_ns == stamp
    assert_same_bytes(copy, reference)
    assert [e.name for e in load(copy).test] == [e.name for e in load(reference).test]


# -- the manifest --------------------------------------------------------------------------------


def flip_a_byte(text: bytes) -> bytes:
    raw = bytearray(text)
    raw[200] ^= 0x80  # a reported case: 'byte 0x89 in position 200'
    return bytes(raw)


def invalid_utf8(text: bytes) -> bytes:
    return text[:300] + b"\xff\xfe" + text[300:]


def invalid_json(text: bytes) -> bytes:
    return text[: len(text) // 2]


def not_an_object(text: bytes) -> bytes:
    return b"[]"


def normalizer_digit(text: bytes) -> bytes:
    at = text.index(b'"state_max"')
    digit = re.compile(rb"[0-9]").search(text, at).start()
    return text[:digit] + str((int(text[digit : digit + 1]) + 1) % 10).encode() + text[digit + 1 :]


def normalizer_nan(text: bytes) -> bytes:
    manifest = json.loads(text)
    manifest["normalizer"]["state_max"][0] = float("nan")
    return json.dumps(manifest, indent=1).encode()


def split_name(text: bytes) -> bytes:
    at = text.rindex(b'"validation": [')
    return text[:at] + b'"validatoin": [' + text[at + len(b'"validation": [') :]


def episode_checksum(text: bytes) -> bytes:
    at = text.index(b'"sha256": "') + len(b'"sha256": "')
    swapped = b"0" if text[at : at + 1] != b"0" else b"1"
    return text[:at] + swapped + text[at + 1 :]


def no_checksum(text: bytes) -> bytes:
    manifest = json.loads(text)
    del manifest["manifest_sha256"]  # as an older harness wrote it
    return json.dumps(manifest, indent=1).encode()


DAMAGES = [
    flip_a_byte,
    invalid_utf8,
    invalid_json,
    not_an_object,
    normalizer_digit,
    normalizer_nan,
    split_name,
    episode_checksum,
    no_checksum,
]


@pytest.mark.parametrize("damage", DAMAGES, ids=lambda f: f.__name__)
def test_a_damaged_manifest_is_named_in_one_line_and_rebuilt_from_the_episode_files(
    damage: Callable[[bytes], bytes],
    reference: Path,
    tmp_path: Path,
    sedan: Sedan,
    caplog: pytest.LogCaptureFixture,
) -> None:
    copy = copy_of(reference, tmp_path)
    manifest = copy / "manifest.json"
    manifest.write_bytes(damage(manifest.read_bytes()))
    assert manifest.read_bytes() != (reference / "manifest.json").read_bytes()
    with pytest.raises(DatasetError) as info:
        load(copy)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"data: {manifest} ")
    assert "rebuild it from the episode files" in message
    assert "episode_0" not in message  # a changed checksum blames the manifest, not a good file

    stamps = {p.name: p.stat().st_mtime_ns for p in copy.glob("*.npz")}
    assert collect_counted(sedan, tiny(tmp_path), DRY, progress=False) == (copy, 0)
    (line,) = warnings_of(caplog)
    assert line.startswith(f"data: {manifest} ") and "rebuilding it from the episode files" in line
    assert {p.name: p.stat().st_mtime_ns for p in copy.glob("*.npz")} == stamps
    assert_same_bytes(copy, reference)


def test_a_damaged_manifest_beside_a_damaged_episode_keeps_the_good_ones_and_redrives_the_bad(
    reference: Path, tmp_path: Path, sedan: Sedan, caplog: pytest.LogCaptureFixture
) -> None:
    copy = copy_of(reference, tmp_path)
    (copy / "manifest.json").write_bytes(flip_a_byte((copy / "manifest.json").read_bytes()))
    victim = copy / "episode_0002.npz"
    raw = bytearray(victim.read_bytes())
    raw[len(raw) // 2] ^= 0x01  # the zip's CRC-32 of the array catches it without a manifest
    victim.write_bytes(bytes(raw))
    assert collect_counted(sedan, tiny(tmp_path), DRY, progress=False) == (copy, 1)
    assert any(
        str(victim) in w and "recollecting episode_0002 alone" in w for w in warnings_of(caplog)
    )
    assert_same_bytes(copy, reference)


def poison(path: Path, array: str, row: int, column: int, value: float) -> None:
    """Write one non-finite value into an episode file, as a valid zip (its CRC-32 agrees)."""
    with np.load(path) as stored:
        arrays = {k: stored[k].copy() for k in stored.files}
    arrays[array][row, column] = value
    np.savez(path, **arrays)


def test_a_non_finite_episode_without_a_manifest_is_named_and_recollected_alone(
    reference: Path, tmp_path: Path, sedan: Sedan, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: NaN in a training drive failed in the manifest writer ('Out of range float
    values are not JSON compliant', no file named); inf in a test drive exited 0 with every
    prediction RMSE null."""
    copy = copy_of(reference, tmp_path)
    (copy / "manifest.json").unlink()
    split = load(reference).manifest["split"]
    train, test = (copy / f"{split[s][0]}.npz" for s in ("train", "test"))
    poison(train, "states", 5, 1, np.nan)
    poison(test, "inputs", 7, 0, np.inf)
    assert collect_counted(sedan, tiny(tmp_path), DRY, progress=False) == (copy, 2)
    named = {
        train: "is damaged (states has 1 non-finite value (vy at t = 0.05 s)); recollecting",
        test: "is damaged (inputs has 1 non-finite value (steer_wheel_deg at t = 0.07 s))",
    }
    for path, clause in named.items():
        assert any(w.startswith(f"data: {path} {clause}") for w in warnings_of(caplog)), path
    assert_same_bytes(copy, reference)


def test_a_non_finite_episode_its_manifest_vouches_for_is_refused_naming_file_and_column(
    reference: Path, tmp_path: Path, sedan: Sedan
) -> None:
    """A manifest rebuilt by an older harness from a poisoned file holds that file's checksum:
    the file must go with the manifest, or recollecting it would contradict the checksum."""
    copy = copy_of(reference, tmp_path)
    test = copy / f"{load(reference).manifest['split']['test'][0]}.npz"
    poison(test, "inputs", 7, 0, np.inf)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["episodes"][test.stem]["sha256"] = store.file_sha256(test)
    store.write_manifest(copy, manifest)
    with pytest.raises(DatasetError) as info:
        load(copy)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(
        f"data: {test}: inputs has 1 non-finite value (steer_wheel_deg at t = 0.07 s); "
        f"delete it and {copy / 'manifest.json'}, then rerun the same collection"
    )
    test.unlink()
    (copy / "manifest.json").unlink()  # what the message says to do
    assert collect_counted(sedan, tiny(tmp_path), DRY, progress=False) == (copy, 1)
    assert_same_bytes(copy, reference)


# -- sizes and disks -----------------------------------------------------------------------------


def test_absurd_sizes_are_refused_in_one_line_naming_the_key_before_any_work() -> None:
    with pytest.raises(ValueError, match=r"^data\.max_steps \(10000000000000\) x data\.episodes"):
        DataConfig(max_steps=10**13)
    split = {"train": 10**6 - 2, "validation": 1, "test": 1}
    with pytest.raises(ValueError, match=r"data\.max_steps \(4000\) x data\.episodes \(1000000\)"):
        DataConfig(episodes=10**6, split=split)
    with pytest.raises(ValueError, match=r"data\.max_steps must be an integer >= 10 \(got 10\.5"):
        DataConfig(max_steps=10.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^data\.max_steps \(10000000000000\) x data\.episodes"):
        DataConfig(max_steps=1e13)  # type: ignore[arg-type]  # a whole float (1e13 typed) is one
    cfg = compose("task=collect", "data.max_steps=10000000000000")
    with pytest.raises(ValueError, match=r"data\.max_steps") as info:
        validate(cfg)  # what the app runs before it builds anything
    assert "\n" not in str(info.value)
    paper = {"train": 36, "validation": 2, "test": 2}
    DataConfig(episodes=40, min_steps=10_000, max_steps=40_000, split=paper)  # data=paper is fine


def test_a_full_disk_stops_in_one_line_naming_the_dataset_and_leaves_no_temporary_file(
    reference: Path, tmp_path: Path, sedan: Sedan, monkeypatch: pytest.MonkeyPatch
) -> None:
    savez, written = np.savez, []

    def fills_the_disk(handle, **arrays) -> None:
        if written:  # the second episode finds the disk full half-way
            handle.write(b"\0" * 4096)
            raise OSError(errno.ENOSPC, "No space left on device")
        savez(handle, **arrays)
        written.append(handle)

    directory = tmp_path / reference.name
    with monkeypatch.context() as patch:
        patch.setattr(np, "savez", fills_the_disk)
        with pytest.raises(DatasetError) as info:
            collect(sedan, tiny(tmp_path), DRY, progress=False)
    message = str(info.value)
    assert "\n" not in message and f"dataset {directory} " in message
    assert "No space left on device" in message and "data.root=" in message
    assert [p.name for p in directory.iterdir() if p.name.endswith(".tmp")] == []
    # Space freed: the run resumes from the episode that was stored.
    assert collect_counted(sedan, tiny(tmp_path), DRY, progress=False) == (directory, 3)
    assert_same_bytes(directory, reference)


def refuse_writes_under(root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A read-only mount at ``root``; as root, permissions alone would not stop a write."""
    root.chmod(0o555)
    if os.geteuid() != 0:
        return
    mkdir, open_ = Path.mkdir, Path.open

    def read_only(path: Path) -> OSError:
        return OSError(errno.EROFS, "Read-only file system", str(path))

    def no_mkdir(self: Path, *args, **kwargs) -> None:
        if self.is_relative_to(root) and not self.is_dir():
            raise read_only(self)
        mkdir(self, *args, **kwargs)

    def no_write(self: Path, mode: str = "r", *args, **kwargs):
        if self.is_relative_to(root) and any(c in mode for c in "wax+"):
            raise read_only(self)
        return open_(self, mode, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", no_mkdir)
    monkeypatch.setattr(Path, "open", no_write)


def test_a_read_only_root_says_so_and_suggests_data_root(
    reference: Path, tmp_path: Path, sedan: Sedan, monkeypatch: pytest.MonkeyPatch
) -> None:
    empty, stored = tmp_path / "empty", tmp_path / "stored"
    empty.mkdir()
    copy_of(reference, stored)
    refuse_writes_under(empty, monkeypatch)
    with pytest.raises(DatasetError) as info:
        collect(sedan, tiny(empty), DRY, progress=False)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"data: {empty} is not writable (")
    assert message.endswith("set data.root=<a writable directory>")
    # A complete dataset on a read-only disk is used as it is.
    refuse_writes_under(stored, monkeypatch)
    (stored / reference.name).chmod(0o555)
    assert collect_counted(sedan, tiny(stored), DRY, progress=False) == (
        stored / reference.name,
        0,
    )


# -- killed collections: no process left behind, resumed to the same bytes -----------------------

# Four drives on two workers: when the first is stored, two more are under way and one waits, so
# the signal always lands mid-collection, even on a loaded machine.
KILLED = {"episodes": 4, "min_steps": 5000, "max_steps": 5000}
SPLIT = {"train": 2, "validation": 1, "test": 1}


def killed_config(root: Path, workers: int) -> DataConfig:
    return DataConfig(**KILLED, split=SPLIT, root=str(root), workers=workers)


@pytest.fixture(scope="module")
def killed_reference(tmp_path_factory: pytest.TempPathFactory, sedan: Sedan) -> Path:
    root = tmp_path_factory.mktemp("killed_reference")
    return collect(sedan, killed_config(root, workers=1), DRY, progress=False)


def _interruptible() -> None:
    """In the child before exec: SIGINT at its default (Python makes it KeyboardInterrupt)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def children(pid: int) -> list[int]:
    found = []
    for status in Path("/proc").glob("[0-9]*/status"):
        try:
            fields = dict(line.split(":\t", 1) for line in status.read_text().splitlines())
        except (OSError, ValueError):
            continue  # gone meanwhile
        if int(fields.get("PPid", "0")) == pid:
            found.append(int(status.parent.name))
    return found


def alive(pid: int) -> bool:
    try:
        return "\nState:\tZ" not in Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False


def spawned_workers(pid: int) -> list[int]:
    return [
        c
        for c in children(pid)
        if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()
        and b"--multiprocessing-fork" in Path(f"/proc/{c}/cmdline").read_bytes()
    ]


@pytest.mark.parametrize(
    "signum", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT], ids=lambda s: s.name
)
def test_a_killed_collection_leaves_no_process_behind_and_resumes_to_the_same_bytes(
    signum: signal.Signals, killed_reference: Path, tmp_path: Path, sedan: Sedan
) -> None:
    root = tmp_path / "datasets"
    directory = root / killed_reference.name
    overrides = [
        "task=collect",
        "recorder=none",
        f"hydra.run.dir={tmp_path / 'run'}",
        f"data.root={root}",
        "data.workers=2",
        "data.split={" + ", ".join(f"{k}: {v}" for k, v in SPLIT.items()) + "}",
        *(f"data.{key}={value}" for key, value in KILLED.items()),
    ]
    with (tmp_path / "stderr.txt").open("wb") as stderr:
        # A process: it is killed, and its workers must die with it.
        process = subprocess.Popen(
            [sys.executable, "-m", "harness", *overrides],
            stdout=subprocess.DEVNULL,
            stderr=stderr,
            # As a user's job at a terminal: a test run in the background (nohup, `&` in a script)
            # inherits SIGINT ignored, and the job would then finish instead of stopping.
            preexec_fn=_interruptible,
        )
    try:
        deadline = time.monotonic() + 120
        stored: dict = {}
        while not stored or len(spawned_workers(process.pid)) < 2:
            assert process.poll() is None, (tmp_path / "stderr.txt").read_text()[-2000:]
            assert time.monotonic() < deadline, "the collection did not start its workers"
            time.sleep(0.05)
            if (directory / "manifest.json").exists():
                stored = json.loads((directory / "manifest.json").read_text())["episodes"]
        # Its workers and the multiprocessing resource tracker.
        family = children(process.pid)
        process.send_signal(signum)
        process.wait(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode != 0
    if signum == signal.SIGINT:  # Ctrl-C: one line that says how to go on, no traceback
        said = (tmp_path / "stderr.txt").read_text()
        assert process.returncode == 130
        assert any(
            line.startswith("interrupted: what finished is in") for line in said.splitlines()
        )
        assert "Traceback" not in said
    deadline = time.monotonic() + 5
    while any(alive(pid) for pid in family) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = [Path(f"/proc/{p}/cmdline").read_bytes()[:80] for p in family if alive(p)]
    assert not left, f"still running 5 s after the parent got {signum.name}: {left}"

    stored = json.loads((directory / "manifest.json").read_text())["episodes"]
    assert 1 <= len(stored) < KILLED["episodes"]
    stamps = {name: (directory / f"{name}.npz").stat().st_mtime_ns for name in stored}
    resumed = collect_counted(sedan, killed_config(root, workers=1), DRY, progress=False)
    assert resumed == (directory, KILLED["episodes"] - len(stored))  # only the missing ones
    assert {name: (directory / f"{name}.npz").stat().st_mtime_ns for name in stored} == stamps
    assert_same_bytes(directory, killed_reference)
