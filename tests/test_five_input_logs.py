"""bench/five_input_logs.py: another car's logs with five inputs, read back as anyone's logs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from bench.five_input_logs import KNEE_MPA, REAR_SLOPE, logged_inputs, main
from harness.data.logs import LogsConfig, read_log
from harness.plant.params import SedanParams


def test_the_logger_records_what_the_pedal_and_the_wheel_did() -> None:
    """Steering over the ratio in rad; torque only on throttle, equal left and right; brake
    pressure in bar only on brake, the rear's through the valve above its knee."""
    params = SedanParams()
    inputs = np.array([[160.0, 0.1], [-80.0, -1.0], [0.0, -5.0], [0.0, 0.0]])
    logged = logged_inputs(inputs, np.full(4, 20.0), params)
    np.testing.assert_allclose(logged[:, 0], np.deg2rad(inputs[:, 0]) / 16.0)
    assert logged[0, 1] == logged[0, 2] > 0 and np.all(logged[1:, 1:3] == 0)
    np.testing.assert_allclose(logged[1:, 3], [10.0, 50.0, 0.0])  # MPa -> bar
    rear_at_5 = 10.0 * (KNEE_MPA + REAR_SLOPE * (5.0 - KNEE_MPA))
    np.testing.assert_allclose(logged[1:, 4], [10.0, rear_at_5, 0.0])


def test_the_written_logs_read_back_with_every_role(tmp_path: Path) -> None:
    assert main([str(tmp_path), "--episodes", "2", "--steps", "200"]) == 0
    text = (tmp_path / "data" / "five_input.yaml").read_text()
    values = OmegaConf.create(text)
    del values["defaults"]
    config = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(LogsConfig), values))
    assert isinstance(config, LogsConfig)
    episode = read_log(tmp_path / "logs" / "drive_1.csv", config)
    assert len(episode) == 200 and episode.inputs.shape == (200, 5)
    roles = [c.role for c in episode.channels]
    assert roles == ["road_wheel", "drive", "drive", "brake", "brake"]
