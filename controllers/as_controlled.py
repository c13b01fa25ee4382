"""A fitted model as DE-MPC predicts with it: lift, the model's own step, the linear read-out C z.

A learner's ``predict`` may read its lifted state out another way than DE-MPC does: Deep EDMD
predicts through its decoder network, while DE-MPC's prediction matrices read x = C z. The two
can disagree on what matters most to a controller: on the main job's data, seed 1's Deep EDMD
has the pedal's effect on speed right through its decoder and reversed through C z, so DE-MPC
braked to speed up (docs/findings/lane_change.md). :class:`AsControlled` wraps a
model so that any open-loop check (the step responses) sees what the controller will see.
"""

from __future__ import annotations

from typing import cast

import numpy as np

from controllers.linearization import linearization_of
from harness.core.contracts import LiftedModel, Model
from harness.core.episode import MinMaxNormalizer


class AsControlled:
    """``predict(x0, U)`` of ``model`` the way DE-MPC predicts: z₀ = lift(x0), z⁺ = A z + B v
    (lifted-linear) or the model's own step (bilinear, nonlinear), x = C z, in physical units."""

    def __init__(self, model: Model) -> None:
        self.model = model
        self._stepper = linearization_of(model)  # None: lifted-linear; raises for no dynamics
        self.normalizer_: MinMaxNormalizer = model.normalizer_
        self._C = np.asarray(model.C_, dtype=float)
        if self._stepper is None:
            lifted = cast(LiftedModel, model)
            self._A = np.asarray(lifted.A_, dtype=float)
            self._B = np.asarray(lifted.B_, dtype=float)

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """(T + 1, n) states from x0 under the T inputs (physical units), as DE-MPC predicts."""
        v = self.normalizer_.inputs(np.asarray(inputs, dtype=float))
        z = np.asarray(self.model.lift(np.asarray(x0, dtype=float)), dtype=float)
        lifted = [z]
        with np.errstate(over="ignore", invalid="ignore"):
            for v_k in v:
                if self._stepper is None:
                    z = self._A @ z + self._B @ v_k
                else:
                    z = np.asarray(self._stepper.step(z, v_k), dtype=float)
                lifted.append(z)
            return np.asarray(self.normalizer_.states_inverse(np.array(lifted) @ self._C.T))
