"""Controllers that act on the plant: the Koopman MPC (DE-MPC) solved with PIQP.

A controller has two members: ``reset(...)`` before a run and ``act(x, t) -> u`` every control
period (physical units in and out).
"""

from controllers.condensed_qp import CondensedQP, QPSolution
from controllers.de_mpc import DEMPC, KoopmanModel

__all__ = ["DEMPC", "CondensedQP", "KoopmanModel", "QPSolution"]
