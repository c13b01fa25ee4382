"""Data collection throughput for ``data=paper`` (40 episodes, ~8.7e5 frames at 10 ms).

Collects into a temporary directory (never the cache) with 2 processes, and the first few
episodes again with 1 process for the side-by-side ratio. Target: the paper-scale dataset in
<= 90 s on 2 cores. Run: ``python -m bench.collect_throughput [--episodes 40]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time

from hydra import compose, initialize_config_dir

from bench.machine import describe
from harness.config import as_object, register_configs
from harness.core.paths import CONF_DIR
from harness.data.driver import DriverKnowledge
from harness.data.store import DataConfig, collect, load
from harness.plant import Sedan


def paper_config(root: str, workers: int, episodes: int | None) -> DataConfig:
    register_configs()
    overrides = ["data=paper", f"data.root={root}", f"data.workers={workers}"]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    data = as_object(cfg.data, DataConfig)
    if episodes is not None and episodes != data.episodes:
        split = {"train": episodes - 2, "validation": 1, "test": 1}
        data = dataclasses.replace(data, episodes=episodes, split=split)
    return data


def timed_collect(data: DataConfig) -> tuple[int, float]:
    start = time.perf_counter()
    plant = Sedan()
    directory = collect(plant, data, DriverKnowledge.of(plant.params), progress=False)
    wall = time.perf_counter() - start
    return sum(len(e) for e in load(directory).episodes()), wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--episodes", type=int, default=40, help="episodes for the 2-process run")
    parser.add_argument("--single", type=int, default=4, help="episodes for the 1-process run")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as root:
        frames, wall = timed_collect(paper_config(root + "/two", 2, args.episodes))
        rows.append(("data=paper, 2 processes (ours)", args.episodes, frames, wall))
        frames1, wall1 = timed_collect(paper_config(root + "/one", 1, args.single))
        rows.append(("data=paper, 1 process", args.single, frames1, wall1))
    print(f"machine: {describe()}")
    print("| collection | episodes | frames | wall (s) | frames/s | vs 1 process |")
    print("|---|---|---|---|---|---|")
    base = rows[1][2] / rows[1][3]
    for name, episodes, frames, wall in rows:
        rate = frames / wall
        print(
            f"| {name} | {episodes} | {frames:,} | {wall:.1f} | {rate:,.0f} | {rate / base:.2f}x |"
        )


if __name__ == "__main__":
    main()
