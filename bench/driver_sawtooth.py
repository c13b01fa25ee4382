"""The synthetic driver's steering saw-tooth: the fraction of frames inside a one-second window
with more than 4 steering reversals (``harness.data.coverage.sawtooth_frames``).

Drives the episodes of a data preset with the driver alone (no dataset is stored), each cut to
``--max-steps``; the reversal count also stands in ``data.coverage`` of every collection. Run:
``python -m bench.driver_sawtooth --data default`` or
``python -m bench.driver_sawtooth --data paper --episodes 6 --max-steps 6000``.
"""

from __future__ import annotations

import argparse

import numpy as np
from hydra import compose, initialize_config_dir

from harness.config import as_object, register_configs
from harness.core.paths import CONF_DIR
from harness.data.coverage import sawtooth_frames, steering_reversals
from harness.data.driver import DriverKnowledge
from harness.data.store import DataConfig, drive_episode
from harness.plant import Sedan


def data_config(preset: str) -> DataConfig:
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"data={preset}"])
    return as_object(cfg.data, DataConfig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", default="default", help="data preset (conf/data/<name>.yaml)")
    parser.add_argument("--episodes", type=int, default=None, help="the first N episodes")
    parser.add_argument("--max-steps", type=int, default=None, help="cut each episode to this")
    args = parser.parse_args()
    data = data_config(args.data)
    plant = Sedan()
    knowledge = DriverKnowledge.of(plant.params)
    lengths = data.episode_lengths()
    count = data.episodes if args.episodes is None else args.episodes
    total = affected = reversals = spun = 0
    print("| episode | frames | reversals / min | saw-tooth frames | fraction | spun |")
    print("|---|---|---|---|---|---|")
    for index in range(count):
        steps = lengths[index] if args.max_steps is None else min(lengths[index], args.max_steps)
        episode = drive_episode(plant, data, knowledge, index, steps)
        steer = np.asarray(episode["inputs"])[:, 0]
        bad = int(sawtooth_frames(steer, plant.dt).sum())
        turns = len(steering_reversals(steer, plant.dt))
        total, affected, reversals = total + len(steer), affected + bad, reversals + turns
        spun += bool(episode["spun"])
        per_minute = turns / (len(steer) * plant.dt / 60)
        row = f"| {index} | {len(steer)} | {per_minute:.1f} | {bad} | {bad / len(steer):.4f} |"
        print(f"{row} {bool(episode['spun'])} |")
    print(
        f"| all {count} | {total} | {reversals / (total * plant.dt / 60):.1f} | {affected} | "
        f"{affected / total:.4f} | {spun} |"
    )


if __name__ == "__main__":
    main()
