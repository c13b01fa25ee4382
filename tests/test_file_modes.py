"""Shared results: every file and directory the harness writes has the mode the umask gives.

A colleague on a shared ``data.root`` or sweep directory must be able to read the dataset the
cache promises to share and the results beside it, so nothing may end up 0600 behind a 022 umask.
"""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from harness.core.files import umask, write_json_atomic, write_text_atomic


def modes_under(root: Path) -> dict[str, int]:
    """Permission bits of ``root``'s tree, relative path -> mode (directories end in '/')."""
    found = {}
    for path in [root, *root.rglob("*")]:
        name = str(path.relative_to(root)) + ("/" if path.is_dir() else "")
        found[name] = stat.S_IMODE(path.stat().st_mode)
    return found


@pytest.fixture(params=[0o022, 0o077, 0o027])
def process_umask(request: pytest.FixtureRequest):
    previous = os.umask(request.param)
    yield request.param
    os.umask(previous)


def test_umask_is_read_without_changing_it(process_umask: int) -> None:
    assert umask() == process_umask
    assert umask() == process_umask


def test_atomic_writes_get_the_mode_open_would_give(tmp_path: Path, process_umask: int) -> None:
    plain_open = tmp_path / "by_open.txt"
    plain_open.write_text("x")
    write_text_atomic(tmp_path / "nested" / "atomic.txt", "x")
    write_json_atomic(tmp_path / "nested" / "metrics.json", {"a": 1.0})
    expected = 0o666 & ~process_umask
    assert stat.S_IMODE(plain_open.stat().st_mode) == expected
    for name in ("atomic.txt", "metrics.json"):
        assert stat.S_IMODE((tmp_path / "nested" / name).stat().st_mode) == expected
    assert stat.S_IMODE((tmp_path / "nested").stat().st_mode) == 0o777 & ~process_umask


@pytest.mark.parametrize("mask", [0o022, 0o077])
def test_a_collect_run_leaves_every_file_and_directory_as_the_umask_says(
    tmp_path: Path, mask: int
) -> None:
    """Dataset (episodes, manifest), metrics, figure, recording and Hydra's own files."""
    # A process: Hydra writes .hydra/ and the job's log only when it runs the command.
    run_dir, data_root = tmp_path / "run", tmp_path / "datasets"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "harness",
            "task=collect",
            "data.episodes=3",
            "data.min_steps=100",
            "data.max_steps=150",
            "data.split={train: 1, validation: 1, test: 1}",
            f"data.root={data_root}",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=lambda: os.umask(mask),
    )
    assert result.returncode == 0, result.stderr[-2000:]
    modes = {**modes_under(run_dir), **{f"data/{k}": v for k, v in modes_under(data_root).items()}}
    assert any(name.endswith(".npz") for name in modes) and any(
        name.endswith(".rrd") for name in modes
    )
    wrong = {
        name: oct(mode)
        for name, mode in modes.items()
        if mode != (0o777 if name.endswith("/") else 0o666) & ~mask
    }
    assert wrong == {}
