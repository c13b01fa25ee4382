"""The pedal as one input or two, the one thing changed: why models affine in u miss vx.

``python -m bench.pedal_structure learner=bilinear_edmd [data=paper] [overrides]`` composes the
learner as ``python -m harness`` would and fits it twice on the same drives:

- ``pedal``: the dataset as it is, the sedan's signed pedal (throttle above zero, brake below,
  each scaled to [-1, 1]) one input column;
- ``split``: the same column as two, throttle = max(pedal, 0) and brake = max(-pedal, 0), so
  that a model affine in u has one slope for each.

Each row is the open-loop RMSE of every test drive (vx m/s / vy m/s / yaw rate rad/s, whole
drive, as ``metrics.json``'s ``prediction.<episode>.rmse``). ``--slopes`` first prints what the
pedal does to the plant, measured on the training drives: the least-squares fit of the
longitudinal acceleration (vx_{k+1} - vx_k) / dt on [1, vx, vy r, throttle, brake] (the pedal
in its [-1, 1] feature) in bands of speed, the slope of each side per band. One slope for both
sides and every speed is what a model with a constant B assumes. ``--baselines`` adds the bars
every model must clear: persistence (the state held) and the identified single-track model, on
the pedal as it is. ``--jsonl FILE`` appends the rows, ``--table FILE`` prints a file's rows
(arms in separate processes, two at a time on two cores). docs/findings/deep_edmd_vx.md, "The
pedal's
two slopes", ran on this.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bench.network_training import (
    Persistence,
    _compose,
    _dataset,
    _rmse,
    append_rows,
    read_rows,
)
from learners.split_pedal import pedal_column, split_pedal

ARMS = ("pedal", "split")
SPEED_BANDS_MPS = ((0.5, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 20.0), (20.0, 25.0), (25.0, 35.0))


def pedal_slopes(episodes: Sequence[Any]) -> dict[tuple[float, float], tuple[float, float, int]]:
    """{speed band: (throttle slope, brake slope, samples)}: m/s² of acceleration per unit of the
    pedal's feature, each band its own least squares on [1, vx, vy r, throttle, brake]."""
    columns, targets = [], []
    for episode in episodes:
        j = pedal_column(episode.input_names, "pedal", f"episode {episode.name}")
        pedal = episode.channels[j].feature(episode.inputs[:-1, j])
        vx, vy, yaw_rate = episode.states[:-1].T
        throttle, brake = np.maximum(pedal, 0.0), np.maximum(-pedal, 0.0)
        columns.append(np.stack([np.ones_like(vx), vx, vy * yaw_rate, throttle, brake], 1))
        targets.append(np.diff(episode.states[:, 0]) / np.diff(episode.time_s))
    regressors, acceleration = np.concatenate(columns), np.concatenate(targets)
    slopes = {}
    for low, high in SPEED_BANDS_MPS:
        rows = (regressors[:, 1] >= low) & (regressors[:, 1] < high)
        if rows.sum() < 100 or np.ptp(regressors[rows, 3]) == 0 or np.ptp(regressors[rows, 4]) == 0:
            continue  # too few drives through this band to tell
        c, *_ = np.linalg.lstsq(regressors[rows], acceleration[rows], rcond=None)
        slopes[(low, high)] = (c[3], -c[4], int(rows.sum()))  # brake slows: -c4 per unit
    return slopes


def run(
    cfg: Any,
    dataset: Any,
    overrides: Sequence[str],
    arms: Sequence[str],
    label: str = "",
    baselines: bool = False,
) -> list[dict[str, Any]]:
    """Fit ``cfg.learner`` on ``dataset`` once per arm (composed from ``overrides``)."""
    from hydra.utils import instantiate

    from harness.core.episode import MinMaxNormalizer

    rows = []
    if baselines:  # the bars, on the pedal as it is: the state held, the identified physics
        physics = _compose(
            [o for o in overrides if o.startswith("data")] + ["learner=single_track"]
        )
        single_track = instantiate(physics.learner, _convert_="object")
        single_track.fit(dataset.train, dataset.validation, dataset.normalizer)
        for name, model in (("persistence", Persistence()), ("single_track", single_track)):
            row = {"learner": name, "overrides": [], "label": name, "arm": "pedal"}
            rows.append({**row, "rmse": _rmse(model, dataset.test), "seconds": 0.0})
            print(_markdown(rows[-1:], header=len(rows) == 1), flush=True)
    for arm in arms:
        change = split_pedal if arm == "split" else (lambda e: e)
        train, validation, test = (
            [change(e) for e in part] for part in (dataset.train, dataset.validation, dataset.test)
        )
        learner = instantiate(cfg.learner, _convert_="object")
        start = time.perf_counter()
        learner.fit(train, validation, MinMaxNormalizer.fit(train))
        rows.append(
            {
                "learner": cfg.learner._target_.rsplit(".", 1)[-1],
                "overrides": list(overrides),
                "label": label,
                "arm": arm,
                "rmse": _rmse(learner, test),
                "seconds": time.perf_counter() - start,
                "data": dataset.key,
            }
        )
        print(_markdown(rows[-1:], header=len(rows) == 1), flush=True)
    return rows


def _markdown(rows: Sequence[dict[str, Any]], header: bool = True) -> str:
    episodes = list(rows[0]["rmse"])
    lines = []
    if header:
        lines += ["| learner (overrides) | arm | " + " | ".join(episodes) + " | fit s |"]
        lines += ["|" + "---|" * (len(episodes) + 3)]
    for row in rows:
        cells = [" / ".join(f"{v:.3g}" for v in row["rmse"][e]) for e in episodes]
        name = row.get("label") or " ".join(row["overrides"]) or row["learner"]
        lines.append(
            f"| {name} | {row['arm']} | " + " | ".join(cells) + f" | {row['seconds']:.0f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, as for python -m harness")
    parser.add_argument("--arms", default=",".join(ARMS), help="pedal, split or both")
    parser.add_argument("--label", default="", help="the rows' name (default: the overrides)")
    parser.add_argument("--baselines", action="store_true", help="add persistence, single-track")
    parser.add_argument("--slopes", action="store_true", help="first print the pedal's slopes")
    parser.add_argument("--jsonl", type=Path, help="append the rows as JSON lines")
    parser.add_argument("--table", type=Path, help="print the table of a JSON-lines file, only")
    args = parser.parse_args()
    if args.table:
        print(_markdown(read_rows(args.table)))
        return
    arms = [a for a in args.arms.split(",") if a]
    unknown = sorted(set(arms) - set(ARMS))
    if unknown:
        parser.error(f"unknown arm {', '.join(unknown)}: choose from {', '.join(ARMS)}")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    cfg = _compose(args.overrides)
    dataset = _dataset(cfg)  # once: the slopes and every arm read the same drives
    if args.slopes:
        print("| vx m/s | throttle m/s² | brake m/s² | brake / throttle | samples |")
        print("|---|---|---|---|---|")
        for (low, high), (throttle, brake, n) in pedal_slopes(dataset.train).items():
            ratio = brake / throttle
            print(f"| {low:g}-{high:g} | {throttle:.2f} | {brake:.2f} | {ratio:.1f} | {n} |")
        print()
    rows = run(cfg, dataset, args.overrides, arms, args.label, args.baselines)
    if args.jsonl:
        append_rows(args.jsonl, rows)


if __name__ == "__main__":
    main()
