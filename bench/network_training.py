"""One arm of the network-training experiment: a learner config plus overrides, trained and scored.

``python -m bench.network_training learner=dnn seed=0 learner.residual=true ...`` composes the
learner exactly as ``python -m harness`` would (``conf/``, the same overrides), fits it on
``data=`` (default: the embedded default, collected once into the dataset cache), and prints
one Markdown row: the open-loop RMSE of every test drive (vx m/s / vy m/s / yaw rate rad/s,
whole drive from its first state, as ``metrics.json``'s ``prediction.<episode>.rmse``; with
``--window-s W`` in windows of W seconds, as ``rmse_window_<W>s``), each
state's worst ratio to input EDMD fitted on the same data in the same run, the training time
and how training stopped. ``--baselines`` adds the rows of input EDMD and persistence (the
state held). ``--jsonl FILE`` appends the row as JSON, so that the arms of a study can run in
separate processes (two at a time on two cores, one thread each) and be tabulated together
with ``--table FILE``. The study of docs/findings/training_recipe.md ran on this.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

STATES = ("vx", "vy", "yaw_rate")


def _compose(overrides: Sequence[str]) -> Any:
    from hydra import compose, initialize_config_module

    from harness.config import register_configs

    register_configs()
    with initialize_config_module("conf", version_base=None):
        return compose("config", overrides=[*overrides, "recorder=none"])


def _dataset(cfg: Any) -> Any:
    """``cfg.data`` as the pipeline reads it: drives collected on the sedan, or a user's logs."""
    from harness.data.collect import data_config
    from harness.data.driver import DriverKnowledge
    from harness.data.logs import LogsConfig, import_logs
    from harness.data.store import collect_counted, load
    from harness.plant import Sedan

    data = data_config(cfg.data)
    if isinstance(data, LogsConfig):
        return load(import_logs(data))
    plant = Sedan()
    directory, _ = collect_counted(plant, data, DriverKnowledge.of(plant.params), progress=False)
    return load(directory)


def _rmse(
    learner: Any, episodes: Sequence[Any], window_steps: int | None = None
) -> dict[str, list[float]]:
    """Per drive, the RMSE of each state: whole from its first state, or in windows of
    ``window_steps`` each started from the measured state (``rmse_window_<W>s``)."""
    from harness.evaluation.prediction import open_loop, rmse, windowed

    def scored(e: Any) -> dict[str, float]:
        if window_steps is None:
            return rmse(open_loop(learner, e), e.states)
        predicted, rows = windowed(learner, e, window_steps)
        return rmse(predicted, e.states, rows)

    return {e.name: [scored(e)[s] for s in STATES] for e in episodes}


class Persistence:
    """The state held: x_k = x_0 for every k (the bar every model must clear)."""

    def predict(self, x0: np.ndarray, inputs: np.ndarray, **_: Any) -> np.ndarray:
        x0 = np.asarray(x0, float)
        return np.repeat(x0[..., None, :], inputs.shape[-2] + 1, axis=-2)


def run(
    overrides: Sequence[str], arm: str, baselines: bool, window_s: float | None = None
) -> list[dict[str, Any]]:
    from hydra.utils import instantiate

    from learners.input_edmd import InputEDMD

    cfg = _compose(overrides)
    dataset = _dataset(cfg)
    window = None if window_s is None else max(1, round(window_s / dataset.period_s))

    def _score(model: Any) -> dict[str, list[float]]:
        return _rmse(model, dataset.test, window)

    reference = InputEDMD().fit(dataset.train, dataset.validation, dataset.normalizer)
    ref = _score(reference)
    rows = []
    if baselines:
        rows.append({"arm": "input_edmd", "rmse": ref, "seconds": None, "stopped": ""})
        rows.append(
            {
                "arm": "persistence",
                "rmse": _score(Persistence()),
                "seconds": None,
                "stopped": "",
            }
        )
    learner = instantiate(cfg.learner, _convert_="object")
    start = time.perf_counter()
    learner.fit(dataset.train, dataset.validation, dataset.normalizer)
    seconds = time.perf_counter() - start
    history = getattr(learner.core, "history_", None)  # a wrapper's (split pedal) inner learner
    rows.append(
        {
            "arm": arm,
            "overrides": list(overrides),
            "rmse": _score(learner),
            "seconds": seconds,
            "stopped": history.stopped if history is not None else "",
            "steps": history.step[-1] if history is not None and history.step else None,
        }
    )
    for row in rows:
        row["ratio_to_input_edmd"] = {
            e: [a / b for a, b in zip(row["rmse"][e], ref[e], strict=True)] for e in ref
        }
        row["data"] = dataset.key
        row["window_s"] = window_s
    return rows


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of a JSON-lines file that ``append_rows`` wrote (arms run in separate processes)."""
    return [json.loads(line) for line in path.read_text().splitlines() if line]


def append_rows(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    with path.open("a") as handle:
        for row in rows:
            handle.write(json.dumps(row) + "\n")


def _markdown(rows: Sequence[dict[str, Any]]) -> str:
    episodes = list(rows[0]["rmse"])
    head = "| arm | " + " | ".join(episodes) + " | worst ratio to input EDMD | train s | stop |"
    lines = [head, "|" + "---|" * (len(episodes) + 4)]
    for row in rows:
        cells = [" / ".join(f"{v:.3g}" for v in row["rmse"][e]) for e in episodes]
        worst = max(max(r) for r in row["ratio_to_input_edmd"].values())
        seconds = f"{row['seconds']:.0f}" if row.get("seconds") else ""
        lines.append(
            f"| {row['arm']} | " + " | ".join(cells) + f" | {worst:.2f}x | {seconds} | "
            f"{row.get('stopped', '')} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, as for python -m harness")
    parser.add_argument("--arm", default="", help="the row's name (default: the overrides)")
    parser.add_argument("--baselines", action="store_true", help="add input EDMD, persistence")
    parser.add_argument("--jsonl", type=Path, help="append the rows as JSON lines")
    parser.add_argument("--table", type=Path, help="print the table of a JSON-lines file, only")
    parser.add_argument("--window-s", type=float, help="score W s windows, not whole drives")
    args = parser.parse_args()
    if args.table:
        print(_markdown(read_rows(args.table)))
        return
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    name = args.arm or " ".join(args.overrides)
    rows = run(args.overrides, name, args.baselines, args.window_s)
    if args.jsonl:
        append_rows(args.jsonl, rows)
    print(_markdown(rows))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
