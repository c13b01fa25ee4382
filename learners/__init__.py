"""Learners of x_{k+1} = f(x_k, u_k): EDMD (any dictionary), DNN, Deep EDMD (paper Secs. IV, VI).

Every learner follows :class:`learners.base.Learner` (``fit`` / ``predict`` / ``save`` / ``load``);
``fit`` takes data only (figures and recordings of its loss curves are the caller's). The Koopman
ones (EDMD, Deep EDMD) also follow :class:`learners.base.KoopmanLearner` (``A_``, ``B_``, ``C_``,
``lift``, ``normalizer_``) for the MPC. EDMD's observables are a dictionary
(:mod:`learners.dictionaries`): thin-plate RBFs (the paper's EDMD) or random ELM units
(ELM-EDMD). ``learners.load(path)`` reads any saved learner. Configs:
``conf/learner/*.yaml``; the bilinear ones (:mod:`learners.bilinear`,
:mod:`learners.bilinear_deep_edmd`) let the input multiply the lifted state; input EDMD
(:mod:`learners.input_edmd`) lifts the state and the input together and re-lifts every step.

May import ``harness.core`` only (contracts, episodes, limits, files): a learner is usable
without the simulator or the recorder.
"""

from learners.base import KoopmanLearner, Learner
from learners.deep_edmd import DeepEDMD
from learners.dictionaries import Dictionary, RandomFeatures, ThinPlateRBF
from learners.dnn import DNN
from learners.edmd import EDMD
from learners.model_file import load

__all__ = [
    "DNN",
    "EDMD",
    "DeepEDMD",
    "Dictionary",
    "KoopmanLearner",
    "Learner",
    "RandomFeatures",
    "ThinPlateRBF",
    "load",
]
