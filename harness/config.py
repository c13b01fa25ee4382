"""Hydra's one schema: the dataclasses behind the config groups, and the check of a whole config.

Each schema is stored in Hydra's ConfigStore under its group, and each YAML file of that group
names it first in its defaults list (``conf/plant/sedan.yaml``: ``- sedan_schema``), so
OmegaConf refuses an unknown key or a value of the wrong type when the config is composed,
naming the full key. Range checks live in each dataclass's ``__post_init__``; :func:`validate`
builds every structured node at once, so all of them run before any work starts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, TypeVar

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, ListConfig, OmegaConf

from harness.data.store import DataConfig
from harness.plant.params import SedanParams

T = TypeVar("T")


@dataclass
class SedanConfig(SedanParams):
    """``conf/plant/*.yaml``: the sedan's parameters and how Hydra builds the plant from them.

    ``_convert_: object`` hands the sub-blocks to ``Sedan`` as ``TireParams``, ... instances,
    so the plant gets a real :class:`SedanParams`.
    """

    _target_: str = "harness.plant.Sedan"
    _convert_: str = "object"


def register_configs() -> None:
    """Store the schemas; call before composing (the app does on import, tests in conftest)."""
    store = ConfigStore.instance()
    store.store(group="plant", name="sedan_schema", node=SedanConfig)
    store.store(group="data", name="data_schema", node=DataConfig)


def validate(cfg: DictConfig) -> None:
    """Build the dataclass of every structured node of ``cfg`` (Hydra's own node aside), so
    every range check runs now; the first failure raises its one-line ``ValueError``.

    Keys added with ``+key=value`` bypass the schema at composition (Hydra opens the node for
    them) and ``OmegaConf.to_object`` would drop them silently: they are refused here.
    """
    _validate(cfg, path="", in_schema=False)


def _validate(node: DictConfig | ListConfig, path: str, in_schema: bool) -> None:
    schema = OmegaConf.get_type(node) if isinstance(node, DictConfig) else None
    structured = dataclasses.is_dataclass(schema)
    known = [f.name for f in dataclasses.fields(schema)] if structured else []  # type: ignore[arg-type]
    keys: list[Any] = list(node.keys()) if isinstance(node, DictConfig) else list(range(len(node)))
    for key in keys:
        full_key = f"{path}.{key}" if path else str(key)
        if structured and key not in known:
            raise ValueError(f"unknown key {full_key}; known keys: {', '.join(known)}")
        # Interpolations point at nodes checked where they live (``task.data: ${data}``).
        if (
            full_key == "hydra"
            or OmegaConf.is_interpolation(node, key)
            or OmegaConf.is_missing(node, key)
        ):
            continue
        child = node[key]
        if isinstance(child, (DictConfig, ListConfig)):
            _validate(child, full_key, in_schema or structured)
    if structured and not in_schema:
        OmegaConf.to_object(node)  # runs every __post_init__ of the block, innermost first


def as_object(node: Any, schema: type[T]) -> T:
    """The ``schema`` instance behind a composed structured node (an instance passes through):
    what a task gets for a block that Hydra hands over as a config node."""
    value = node if isinstance(node, schema) else OmegaConf.to_object(node)
    if not isinstance(value, schema):
        raise ValueError(f"expected a {schema.__name__} config, got {type(value).__name__}")
    return value
