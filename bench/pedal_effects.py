"""What a pedal step does to vx over a controller's horizon: each model as DE-MPC reads it, the
plant beside.

``python -m bench.pedal_effects run/model_deep_edmd.pt [more model files]`` starts the plant
rolling straight at each speed with the pedal released, then steps the pedal to a throttle (+0.1)
or a brake (-3 MPa) and holds it. Each row is the effect on vx (the run with the step minus the
run without it, m/s) after 1, 5, 10, 30 and 60 steps of the model's period: the paper's 10/7
DE-MPC sees the first 10, the main job's 60/50 all 60. A model is read as the controller reads it
(:class:`~controllers.as_controlled.AsControlled`: lift, its step, x = C z), from the state the
plant was in. A row whose early effect has the wrong sign, or is a hundred times the plant's, is a
model a short-horizon MPC cannot use, whatever its long-run accuracy
(docs/findings/deep_edmd_vx.md, "The split as a model option").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

STEPS = (1, 5, 10, 30, 60)
PEDALS = (("throttle +0.1", 0.1), ("brake 3 MPa", -3.0))
SPEEDS_MPS = (10.0, 22.0)


def plant_effect(speed_mps: float, pedal: float, steps: int) -> np.ndarray:
    """The plant's vx with the pedal stepped minus released, (steps,), from straight driving."""
    from harness.plant import Sedan

    runs = []
    for held in (0.0, pedal):
        plant = Sedan()
        plant.reset(speed_mps=speed_mps)
        runs.append([plant.step(np.array([0.0, held]))[0] for _ in range(steps)])
    return np.asarray(runs[1]) - np.asarray(runs[0])


def model_effect(model: object, speed_mps: float, pedal: float, steps: int) -> np.ndarray:
    """The same as DE-MPC predicts it from straight driving at ``speed_mps``."""
    from controllers.as_controlled import AsControlled

    controlled = AsControlled(model)  # type: ignore[arg-type]
    x0 = np.array([speed_mps, 0.0, 0.0])
    runs = [
        controlled.predict(x0, np.tile([0.0, held], (steps, 1)))[1:, 0] for held in (0.0, pedal)
    ]
    return runs[1] - runs[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="*", type=Path, help="model files (model_<learner>.pt)")
    args = parser.parse_args()
    from learners import load

    rows: list[tuple[str, object | None]] = [("plant", None)]
    rows += [(path.parent.name or path.name, load(path)) for path in args.models]
    last = max(STEPS)
    print("| model | speed m/s | pedal | " + " | ".join(f"{k} steps" for k in STEPS) + " |")
    print("|---|---|---|" + "---|" * len(STEPS))
    for speed in SPEEDS_MPS:
        for label, pedal in PEDALS:
            for name, model in rows:
                effect = (
                    plant_effect(speed, pedal, last)
                    if model is None
                    else model_effect(model, speed, pedal, last)
                )
                cells = " | ".join(f"{effect[k - 1]:+.3f}" for k in STEPS)
                print(f"| {name} | {speed:g} | {label} | {cells} |", flush=True)


if __name__ == "__main__":
    main()
