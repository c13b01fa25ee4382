"""Learners of x_{k+1} = f(x_k, u_k): EDMD, ELM-EDMD, DNN and Deep EDMD (paper Secs. IV, VI).

Every learner follows :class:`learners.base.Learner` (``fit`` / ``predict`` / ``save`` / ``load``);
the Koopman ones (EDMD, ELM-EDMD, Deep EDMD) also follow :class:`learners.base.KoopmanLearner`
(``A_``, ``B_``, ``C_``, ``lift``, ``normalizer_``) for the MPC. ``learners.load(path)`` reads any
saved learner. Configs: ``conf/learner/{edmd,elm_edmd,dnn,deep_edmd}.yaml``.
"""

from learners.base import KoopmanLearner, Learner, load
from learners.deep_edmd import DeepEDMD
from learners.dnn import DNN
from learners.edmd import EDMD
from learners.elm_edmd import ELMEDMD

__all__ = ["DNN", "EDMD", "ELMEDMD", "DeepEDMD", "KoopmanLearner", "Learner", "load"]
