"""A controller config builds a checked factory; the factory builds the controller on a model.

Every ``conf/controller/*.yaml`` names a settings dataclass as its ``_target_`` (DE-MPC:
:class:`~controllers.de_mpc.DEMPCConfig`), whose ``__post_init__`` checks every value. Hydra
builds it with the task, so a wrong setting fails before any data is collected or any model
trained; the fitted model, which exists only after training, is given to the factory later.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig

from harness.core.contracts import Controller, Model
from learners.base import Learner


@runtime_checkable
class ControllerFactory(Protocol):
    """Checked settings that build a controller on a fitted model (``instantiate(cfg)``), and
    the clock the loop runs it on (``COMPUTE_DELAYS``: the loop, not the controller, holds
    each input; the controller built here compensates for it)."""

    compute_delay: str

    def __call__(self, model: Model, control_period_s: float | None = None) -> Controller: ...


@runtime_checkable
class OwnModelFactory(Protocol):
    """A controller factory that brings its own model instead of the run's learner (the
    physics baseline): the pipeline fits ``learner()`` on the same training episodes and builds
    the controller on that."""

    compute_delay: str

    def learner(self) -> Learner:
        """The unfitted model the controller runs on."""
        ...

    def __call__(self, model: Model, control_period_s: float | None = None) -> Controller: ...


def check_controller_config(node: DictConfig) -> ControllerFactory:
    """The checked factory of a composed ``controller`` node, without a model.

    Raises the settings' own one-line ``ValueError`` (naming its key), not Hydra's wrapper.
    """
    try:
        factory: ControllerFactory = instantiate(node)
    except InstantiationException as error:
        if isinstance(error.__cause__, ValueError):
            raise error.__cause__ from None
        raise
    return factory
