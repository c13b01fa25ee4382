"""The lane change driven by state tracking, offset-free and path following, side by side.

``python -m bench.path_following [--horizon 10/7|60/50] [--learners a,b] [--weights q,...]``.
Models are fitted on ``data=default`` (collected once into the dataset cache, as the main job
does) and close the loop on the sedan through the ISO 3888-1 double lane change at 80 km/h:
``controller.reference`` states and path, each without and with ``offset_free``; ``--weights``
adds path-following runs with other ``Q_path`` diagonals (``vx:vy:r:lateral:heading``, e.g.
``1000:0:0:200:2000``), the study that chose the default (docs/findings/lane_change.md, "Path
following").

Printed per run: the course's judgement (maximum lateral deviation, cones hit), the yaw-rate RMSE
against the reference's states, the error the run ends with (``final_error``: mean |x − x_ref|
over its last 0.5 s) and the solve time of whole control steps on the machine as it is.
"""

from __future__ import annotations

import argparse
import itertools
import os
from typing import Any

from bench.machine import describe
from controllers import BicycleMPCConfig, DEMPCConfig
from controllers.disturbance import OffsetFree
from harness.core.contracts import Model
from harness.data.driver import DriverKnowledge
from harness.data.store import DataConfig, collect_counted, load
from harness.evaluation.tracking import track
from harness.plant import Sedan
from harness.recorder import Recorder
from harness.references import DoubleLaneChange, path_metrics
from learners.base import Learner
from learners.bilinear import BilinearEDMD
from learners.edmd import EDMD
from learners.input_edmd import InputEDMD
from learners.single_track import SingleTrack

LEARNERS = {
    "single_track": SingleTrack,
    "edmd": EDMD,
    "bilinear_edmd": BilinearEDMD,
    "input_edmd": InputEDMD,
}


def _weights(text: str) -> tuple[float, ...]:
    return tuple(float(value) for value in text.split(":"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--horizon", default="10/7", choices=["10/7", "60/50"])
    parser.add_argument("--learners", default=",".join(LEARNERS))
    parser.add_argument("--weights", default="", help="extra Q_path diagonals, comma-separated")
    parser.add_argument("--speed-kph", type=float, default=80.0)
    args = parser.parse_args()
    Np, Nc = (int(value) for value in args.horizon.split("/"))
    plant = Sedan()
    directory, _ = collect_counted(plant, DataConfig(), DriverKnowledge.of(plant.params))
    dataset = load(directory)
    lane_change = DoubleLaneChange(speed_mps=args.speed_kph / 3.6)
    reference, course = lane_change.build(plant.dt, []), lane_change.course()
    extra = [_weights(text) for text in args.weights.split(",") if text]
    modes: list[tuple[str, dict[str, Any]]] = [
        (
            f"{reference_mode}{' offset-free' if offset_free else ''}",
            {
                "reference": reference_mode,
                "disturbance": OffsetFree() if offset_free else None,
            },
        )
        for reference_mode, offset_free in itertools.product(("states", "path"), (False, True))
    ]
    modes += [
        (f"path Q_path={weights}", {"reference": "path", "Q_path": weights}) for weights in extra
    ]
    print(f"machine: {describe()}; load average {os.getloadavg()[0]:.2f} at start")
    print(
        f"data=default ({dataset.key}); ISO 3888-1 at {args.speed_kph:g} km/h; Np/Nc = {Np}/{Nc}\n"
    )
    print(
        "| model | mode | max deviation m | cones | yaw-rate RMSE | final error vx / vy / r | "
        "solve median / p99 / max ms |"
    )
    print("|" + "---|" * 7)
    for name in args.learners.split(","):
        learner: Learner = LEARNERS[name]()
        model = learner.fit(dataset.train, dataset.validation, dataset.normalizer)
        assert isinstance(model, Model)
        factory = BicycleMPCConfig if name == "single_track" else DEMPCConfig
        for mode, keys in modes:
            controller = factory(Np=Np, Nc=Nc, **keys)(model, plant.dt)
            metrics, run = track(
                plant, controller, reference, name="bench", recorder=Recorder(), path=course.path()
            )
            judged = path_metrics(course, run.poses, run.states)
            final, times = metrics["final_error"], metrics["solve_time_ms"]
            print(
                f"| {name} | {mode} | {judged['max_lateral_deviation_m']:.2f} | "
                f"{judged['cones_hit']} | {metrics['rmse']['yaw_rate']:.4f} | "
                f"{final['vx']:.3f} / {final['vy']:.3f} / {final['yaw_rate']:.4f} | "
                f"{times['median']:.2f} / {times['p99']:.2f} / {times['max']:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
