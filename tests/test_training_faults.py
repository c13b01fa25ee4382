"""Fault injection for the training store: damaged checkpoints, and a training killed with
SIGKILL that resumes to the uninterrupted result (same seed, CPU)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from harness.core.episode import MinMaxNormalizer
from learners import DNN, DeepEDMD
from learners.trained import TrainedLearner
from learners.training import _read_checkpoint
from tests.toydata import drive_episodes

MAX_STEPS = 600  # about 2 s of training here: long enough to be killed in the middle


def toy_data() -> tuple[list, list, MinMaxNormalizer]:
    episodes = drive_episodes(4, 20.0, first_seed=10)
    return episodes[:3], episodes[3:], MinMaxNormalizer.fit(episodes[:3])


def tiny(kind: str, checkpoint_dir: Path | None, max_steps: int = MAX_STEPS) -> TrainedLearner:
    """One thread, so that a run in another process is bitwise the same as one here."""
    training = {
        "max_steps": max_steps,
        "batch_size": 16,
        "lr": 3e-3,
        "eval_every_steps": 50,
        "checkpoint_every_steps": 20,
        "num_threads": 1,
        "progress": False,
    }
    learner: TrainedLearner
    if kind == "dnn":
        learner = DNN(hidden=[16, 16], horizon=8, training=training)
    else:
        learner = DeepEDMD(
            lifted_dim=4, encoder_hidden=[16], decoder_hidden=[16], horizon=8, training=training
        )
    learner.checkpoint_dir = checkpoint_dir
    return learner


def train_here(kind: str, checkpoint_dir: str) -> None:
    """What the killed subprocess runs: ``python -c "...; train_here('dnn', '<dir>')"``."""
    tiny(kind, Path(checkpoint_dir)).fit(*toy_data())


@pytest.fixture(scope="module")
def data() -> tuple[list, list, MinMaxNormalizer]:
    return toy_data()


@pytest.fixture(scope="module")
def uninterrupted(data, tmp_path_factory: pytest.TempPathFactory) -> dict[str, TrainedLearner]:
    return {
        kind: tiny(kind, tmp_path_factory.mktemp(kind), max_steps=100).fit(*data)
        for kind in ("dnn", "deep_edmd")
    }


def damage_truncate(raw: bytes) -> bytes:
    return raw[: len(raw) // 2]


def damage_flip_a_parameter_byte(raw: bytes) -> bytes:
    flipped = bytearray(raw)
    flipped[len(raw) // 2] ^= 0x01  # torch itself may load such a file without complaint
    return bytes(flipped)


def damage_garbage(raw: bytes) -> bytes:
    return b"\x89PNG not a checkpoint at all"


@pytest.mark.parametrize(
    "damage",
    [damage_truncate, damage_flip_a_parameter_byte, damage_garbage],
    ids=lambda f: f.__name__,
)
@pytest.mark.parametrize("kind", ["dnn", "deep_edmd"])
def test_a_damaged_checkpoint_is_named_set_aside_and_training_starts_afresh(
    kind, damage, data, uninterrupted, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    half = tiny(kind, tmp_path, max_steps=40).fit(*data)
    path = half.checkpoint_path
    assert path is not None
    damaged = damage(path.read_bytes())
    path.write_bytes(damaged)
    again = tiny(kind, tmp_path, max_steps=100).fit(*data)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert str(path) in warnings[0] and "training starts afresh" in warnings[0]
    assert (tmp_path / f"{path.name}.damaged").read_bytes() == damaged  # nothing lost
    # Afresh: the 100 steps of a run that never had a checkpoint, not 40 resumed + 60.
    np.testing.assert_array_equal(again.params_.data, uninterrupted[kind].params_.data)
    assert again.history_ == uninterrupted[kind].history_


@pytest.mark.parametrize("kind", ["dnn", "deep_edmd"])
def test_a_training_killed_with_sigkill_resumes_to_the_uninterrupted_result(
    kind, data, tmp_path: Path
) -> None:
    killed_dir = tmp_path / "killed"
    process = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"from tests.test_training_faults import train_here; "
            f"train_here({kind!r}, {str(killed_dir)!r})",
        ],
        stderr=subprocess.PIPE,
    )
    checkpoint = killed_dir / f"{tiny(kind, None).name}.ckpt"
    step = 0
    deadline = time.monotonic() + 120
    try:
        while step < MAX_STEPS // 5 and time.monotonic() < deadline:
            assert process.poll() is None, process.stderr.read().decode()[-2000:]
            time.sleep(0.02)
            if checkpoint.exists():
                step = _read_checkpoint(checkpoint)["state"]["step"]
    finally:
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
    assert process.returncode == -signal.SIGKILL
    saved = _read_checkpoint(checkpoint)["state"]
    assert 0 < saved["step"] < MAX_STEPS  # killed in the middle
    resumed = tiny(kind, killed_dir).fit(*data)
    whole = tiny(kind, tmp_path / "whole").fit(*data)
    # the killed run's training time up to its checkpoint is counted, not forgotten
    assert saved["trained_s"] > 0 and resumed.history_.resumed_s == saved["trained_s"]
    assert whole.history_.resumed_s == 0.0
    assert resumed.history_.step[-1] == MAX_STEPS
    assert resumed.history_.validation[-1]["loss"] == whole.history_.validation[-1]["loss"]
    assert resumed.history_ == whole.history_
    np.testing.assert_array_equal(resumed.params_.data, whole.params_.data)
