"""Controllers that act on the plant: the Koopman MPC (DE-MPC) solved with PIQP, time-varying
for bilinear and linearizable models, and the single-track physics baseline (bicycle_mpc).

A controller is a :class:`harness.core.contracts.Controller`: ``reset(reference)`` before a run and
``act(x, t) -> (u, StepInfo)`` every control period (physical units in and out). Its config
builds a checked :class:`ControllerFactory`, which builds the controller on a fitted model.

May import ``harness.core`` and ``learners`` (the baseline fits its own single-track model):
no simulator, no recorder.
"""

from controllers.bicycle_mpc import BicycleMPCConfig
from controllers.condensed_qp import CondensedQP, QPSolution
from controllers.config import ControllerFactory, OwnModelFactory, check_controller_config
from controllers.de_mpc import DEMPC, DEMPCConfig
from controllers.time_varying_qp import TimeVaryingQP

__all__ = [
    "DEMPC",
    "BicycleMPCConfig",
    "CondensedQP",
    "ControllerFactory",
    "DEMPCConfig",
    "OwnModelFactory",
    "QPSolution",
    "TimeVaryingQP",
    "check_controller_config",
]
