"""Controllers that act on the plant: the Koopman MPC (DE-MPC) solved with PIQP.

A controller is a :class:`harness.interfaces.Controller`: ``reset(reference)`` before a run and
``act(x, t) -> (u, StepInfo)`` every control period (physical units in and out). Its config
builds a checked :class:`ControllerFactory`, which builds the controller on a fitted model.
"""

from controllers.condensed_qp import CondensedQP, QPSolution
from controllers.config import ControllerFactory, check_controller_config
from controllers.de_mpc import DEMPC, DEMPCConfig

__all__ = [
    "DEMPC",
    "CondensedQP",
    "ControllerFactory",
    "DEMPCConfig",
    "QPSolution",
    "check_controller_config",
]
