"""What the pipeline checks of a fitted model besides its predictions: its responses to steering
and throttle steps against the plant's, and its spectrum (``prediction.step_response``,
``spectrum``)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, cast

from controllers.as_controlled import AsControlled
from harness.core.contracts import LiftedModel, Model, RunLearner, dynamics_of
from harness.evaluation import spectrum, step_response
from harness.plant import Sedan
from harness.recorder import Recorder

log = logging.getLogger(__name__)

# prediction.step_response.<case>.as_controlled: the same case through the model as DE-MPC reads it
AS_CONTROLLED = "as_controlled"


def step_responses(
    learner: RunLearner, learner_name: str, plant: Sedan, recorder: Recorder, output_dir: Path
) -> dict[str, Any]:
    """``prediction.step_response.<case>``: steering and throttle steps from straight
    driving, the model's open-loop prediction against the plant's
    (harness/evaluation/step_response.py)."""
    models: dict[str, step_response.Predictor] = {learner_name: learner}
    # A model a controller reads is also checked as DE-MPC will predict with it, and must
    # respond to its inputs the plant's way (persistence declares no dynamics: no input
    # response by design, no controlled view, no warning).
    views = {learner_name: "its predictions"}
    if dynamics_of(learner) is not None:
        models[AS_CONTROLLED] = AsControlled(cast(Model, learner))
        views[AS_CONTROLLED] = "DE-MPC's read-out"
    results = step_response.evaluate(models, plant, recorder=recorder, output_dir=output_dir)
    cases = results[learner_name]
    for case, controlled in results.get(AS_CONTROLLED, {}).items():
        cases[case][AS_CONTROLLED] = controlled
    for view, label in views.items():
        for case, values in results[view].items():
            if AS_CONTROLLED in views and not values["input_sign_agrees"]:
                log.warning(
                    "%s: %s's effect on %s in %s has the wrong sign (or none) in %s: a "
                    "controller on this model pushes the wrong way (step_response.%s)",
                    learner_name,
                    values["input"],
                    values["output"],
                    case,
                    label,
                    case,
                )
    return cases


def spectrum_section(
    learner: RunLearner, learner_name: str, dt: float, recorder: Recorder, output_dir: Path
) -> dict[str, Any]:
    """``spectrum``: the eigenvalues of a Koopman model's state matrices, unstable modes
    named (harness/evaluation/spectrum.py), and ``spectrum.png``. A wrapper's are its
    core learner's (the pedal split changes only the inputs)."""
    learner = learner.core
    if dynamics_of(learner) not in ("linear", "bilinear"):
        return {"skipped": f"{learner_name} is not a lifted model"}
    assert isinstance(learner, LiftedModel)
    metrics, eigenvalues = spectrum.spectrum(learner, dt)
    spectrum.record_spectrum(recorder, eigenvalues)
    spectrum.plot_spectrum(eigenvalues, output_dir / "spectrum.png", title=learner_name)
    modes = metrics["unstable_modes"]
    if modes:
        fastest = min(modes, key=lambda mode: mode["doubling_time_s"])
        log.warning(
            "%s: %d modes outside the unit circle (spectrum.unstable_modes); the fastest, "
            "|λ| = %.6f, doubles in %.3g s (%s, at %s)",
            learner_name,
            len(modes),
            fastest["abs"],
            fastest["doubling_time_s"],
            fastest["dominant"],
            fastest["matrix"],
        )
    return metrics
