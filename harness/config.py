"""Hydra's one schema: the dataclasses behind the config groups, and the check of a whole config.

Each schema is stored in Hydra's ConfigStore under its group, and each YAML file of that group
names it first in its defaults list (``conf/plant/sedan.yaml``: ``- sedan_schema``), so
OmegaConf refuses an unknown key or a value of the wrong type when the config is composed,
naming the full key. Range checks live in each dataclass's ``__post_init__``; :func:`validate`
checks every key of the composed config at once, before any work starts: it builds the
settings dataclass of every structured node (plant, data, learner, controllers, other plants)
and every other ``_target_`` node but the task (references, recorder), and checks that every
part the task uses shares the plant's control period. Errors are one line naming the full key
where the node lives (``task.extra_controllers.de_mpc_long.Np``, not the ``controller.Np`` its
class says).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import inspect
import math
import pkgutil
import re
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from hydra.core.config_store import ConfigStore
from hydra.errors import InstantiationException
from hydra.utils import get_object, instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

import learners
from controllers import BicycleMPCConfig, DEMPCConfig
from harness.core.checks import is_number
from harness.data.logs import LogsConfig
from harness.data.store import DataConfig
from harness.plant.params import SedanParams
from harness.tasks.characterize import Characterize
from learners import Learner

T = TypeVar("T")


@dataclass
class SedanConfig(SedanParams):
    """``conf/plant/*.yaml``: the sedan's parameters and how Hydra builds the plant from them.

    ``_convert_: object`` hands the sub-blocks to ``Sedan`` as ``TireParams``, ... instances,
    so the plant gets a real :class:`SedanParams`.
    """

    _target_: str = "harness.plant.Sedan"
    _convert_: str = "object"  # the blocks reach Sedan as TireParams, ChassisParams, ... instances


def schema_of(settings: type, convert: str | None = "all", target: type | None = None) -> type:
    """A settings dataclass as a Hydra schema: the same fields and defaults, and ``_target_``
    naming the class, so its YAML files list only what differs from the defaults and every key
    can still be overridden (``controller.Np=60``). Not frozen, as Hydra merges overrides into
    it; composing it checks the types, building it runs the class's own ``__post_init__``.

    ``target``: the class the node builds when it is not ``settings`` itself (a learner, which
    takes its settings as keywords); ``convert`` None leaves ``_convert_`` out (Hydra's
    default). A field holding a settings dataclass (``learner.training``) is a nested schema
    with its own ``_target_``, so it is built as that dataclass and checked where it lives.
    """
    hints = typing.get_type_hints(settings)
    names = [f.name for f in dataclasses.fields(settings)]
    built = target or settings
    specs: list[tuple[str, Any, Any]] = [
        ("_target_", str, dataclasses.field(default=f"{built.__module__}.{built.__qualname__}")),
    ]
    if convert is not None:
        specs.append(("_convert_", str, dataclasses.field(default=convert)))
    for f in dataclasses.fields(settings):
        factory: Any = f.default_factory
        default = factory() if f.default is dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(hints[f.name]):
            nested = schema_of(hints[f.name], convert=None)
            specs.append((f.name, nested, _nested_field(nested, default)))
        elif isinstance(default, tuple | list):  # OmegaConf holds sequences as lists
            specs.append((f.name, _schema_hint(hints[f.name]), _list_field(_as_lists(default))))
        else:
            specs.append((f.name, _schema_hint(hints[f.name]), dataclasses.field(default=default)))

    def check(self: Any) -> None:
        settings(**{name: getattr(self, name) for name in names})

    return dataclasses.make_dataclass(
        f"{settings.__name__}Schema", specs, namespace={"__post_init__": check}
    )


def _schema_hint(hint: Any) -> Any:
    """``hint`` as OmegaConf types it: a ``Sequence[X]`` as ``list[X]`` (of lists, nested)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (types.UnionType, typing.Union):
        options = [a for a in args if a is not type(None)]
        single = len(options) == 1 and len(args) == 2
        return typing.Optional[_schema_hint(options[0])] if single else hint  # noqa: UP045
    if origin in (list, tuple, Sequence) and len(args) == 1:
        return typing.List[_schema_hint(args[0])]  # type: ignore[misc]  # noqa: UP006
    return hint


def _as_lists(value: Any) -> Any:
    return [_as_lists(v) for v in value] if isinstance(value, tuple | list) else value


def _list_field(default: list[Any]) -> Any:
    return dataclasses.field(default_factory=lambda: _as_lists(default))


def _nested_field(schema: type, default: Any) -> Any:
    """A nested schema's default: the settings dataclass's default instance, field by field."""
    values = {f.name: _as_lists(getattr(default, f.name)) for f in dataclasses.fields(default)}
    return dataclasses.field(default_factory=lambda: schema(**values))


def register_configs() -> None:
    """Store the schemas; call before composing (the app does on import, tests in conftest)."""
    store = ConfigStore.instance()
    store.store(group="plant", name="sedan_schema", node=SedanConfig)
    store.store(group="data", name="data_schema", node=DataConfig)
    store.store(group="data", name="logs_schema", node=LogsConfig)
    store.store(group="controller", name="de_mpc_schema", node=schema_of(DEMPCConfig))
    store.store(group="controller", name="bicycle_mpc_schema", node=schema_of(BicycleMPCConfig))
    store.store(group="task", name="characterize_schema", node=schema_of(Characterize))
    for learner in learner_classes():  # built by the learner, which takes its settings
        node = schema_of(learner.config_class, convert=None, target=learner)
        store.store(group="learner", name=f"{learner.name}_schema", node=node)


@functools.cache
def learner_classes() -> tuple[type[Learner], ...]:
    """Every learner class of the ``learners`` package, by name: each has a schema of its own,
    ``<name>_schema`` (a new learner is its class and its YAML file, no list to extend)."""
    for module in pkgutil.iter_modules(learners.__path__):
        importlib.import_module(f"{learners.__name__}.{module.name}")
    found: dict[str, Any] = {}
    stack: list[Any] = [Learner]
    while stack:
        cls = stack.pop()
        stack.extend(cls.__subclasses__())
        if cls.__module__.startswith(f"{learners.__name__}.") and not inspect.isabstract(cls):
            found.setdefault(cls.name, cls)
    return tuple(found[name] for name in sorted(found))


# Keys that hold the control period: plant, data, model and controller share one (the model
# steps once per period, the reference is indexed by t / dt), so they must all agree.
PERIOD_KEYS = ("dt", "control_period_s")


def validate(cfg: DictConfig) -> None:
    """Check every key of ``cfg`` (Hydra's own node aside) before any work; the first failure
    raises a one-line ``ValueError`` naming the full key.

    1. the dataclass of every structured node is built, so every ``__post_init__`` runs; keys
       added with ``+key=value`` bypass the schema at composition (Hydra opens the node for
       them) and ``OmegaConf.to_object`` would drop them silently: they are refused here;
    2. every other ``_target_`` node but the task itself is built, after the ``_target_``
       nodes it holds (cheap: references and the recorder are settings until used);
    3. every control period the task uses equals ``plant.control_period_s``.

    An extra controller named as the run's controller (``controller=de_mpc`` beside the
    pipeline's extra ``de_mpc``) is the run's controller: it is removed first, so that it runs
    once, with the run's settings.
    """
    _drop_extra_named_as_the_run_controller(cfg)
    _validate(cfg, path="", in_schema=False)
    _build_targets(cfg, path="")
    _check_periods(cfg)


def _drop_extra_named_as_the_run_controller(cfg: DictConfig) -> None:
    name = OmegaConf.select(cfg, "hydra.runtime.choices.controller")
    extras = OmegaConf.select(cfg, "task.extra_controllers")
    if isinstance(name, str) and isinstance(extras, DictConfig) and name in extras:
        with open_dict(extras):
            extras.pop(name)


def _validate(node: DictConfig | ListConfig, path: str, in_schema: bool) -> None:
    schema = OmegaConf.get_type(node) if isinstance(node, DictConfig) else None
    structured = dataclasses.is_dataclass(schema)
    known = [f.name for f in dataclasses.fields(schema)] if structured else []  # type: ignore[arg-type]
    keys: list[Any] = list(node.keys()) if isinstance(node, DictConfig) else list(range(len(node)))
    for key in keys:
        full_key = f"{path}.{key}" if path else str(key)
        if structured and key not in known:
            raise ValueError(f"unknown key {full_key}; known keys: {', '.join(known)}")
        if structured and OmegaConf.is_missing(node, key):  # ``???``: the user must say it
            raise ValueError(f"{full_key} must be given (it has no default): add {full_key}=...")
        if _not_checked_here(node, key, full_key):
            continue
        child = node[key]
        if isinstance(child, float) and not math.isfinite(child):
            raise ValueError(f"{full_key} must be finite (got {child})")  # no key means NaN
        if isinstance(child, (DictConfig, ListConfig)):
            _validate(child, full_key, in_schema or structured)
    # A learner's settings are checked where it lives too (the pedal split's learner.inner), so
    # that an error names its keys there, not under learner.
    inner_learner = structured and in_schema and _builds_a_learner(schema)  # type: ignore[arg-type]
    if structured and (not in_schema or inner_learner):
        try:
            OmegaConf.to_object(node)  # runs every __post_init__ of the block, innermost first
        except ValueError as error:
            message = str(error)
            if inner_learner and message.startswith("learner."):
                message = path + message[len("learner") :]
            raise ValueError(_rekeyed(message, path, node)) from None


def _builds_a_learner(schema: type) -> bool:
    """Whether a schema's ``_target_`` is a learner class (a schema of :func:`learner_classes`)."""
    target = {f.name: f.default for f in dataclasses.fields(schema)}.get("_target_")
    return any(target == f"{cls.__module__}.{cls.__qualname__}" for cls in learner_classes())


def _not_checked_here(node: DictConfig | ListConfig, key: Any, full_key: str) -> bool:
    """Hydra's own node, interpolations (checked where they point: ``task.data: ${data}``) and
    missing values are not checked where they appear."""
    return (
        full_key == "hydra"
        or OmegaConf.is_interpolation(node, key)
        or OmegaConf.is_missing(node, key)
    )


def _build_targets(node: DictConfig | ListConfig, path: str) -> None:
    """Instantiate every ``_target_`` node below ``node`` that no structured schema covers, each
    after the ``_target_`` nodes it holds: a failure is that of the node at its own key."""
    keys: list[Any] = list(node.keys()) if isinstance(node, DictConfig) else list(range(len(node)))
    for key in keys:
        full_key = f"{path}.{key}" if path else str(key)
        if _not_checked_here(node, key, full_key):
            continue
        child = node[key]
        if not isinstance(child, (DictConfig, ListConfig)):
            continue
        structured = dataclasses.is_dataclass(OmegaConf.get_type(child))
        if structured:
            continue
        _build_targets(child, full_key)
        # The task is built by the app, with the plant; the parts it holds are built here.
        if isinstance(child, DictConfig) and "_target_" in child:
            _check_argument_types(child, full_key)
            if full_key != "task":
                _build(child, full_key)


def _build(node: DictConfig, path: str) -> None:
    """Instantiate ``node`` (the ``_target_`` nodes it holds were built before it); its error as
    one line naming the key: a target that cannot be imported, a key its signature does not
    take, or the target's own check."""
    try:
        target = get_object(str(node._target_))
    except Exception as error:  # Hydra's: no such module or name
        reason = _first_line(error.__cause__ or error)
        raise ValueError(
            f"{path}._target_ {node._target_!r} cannot be imported ({reason})"
        ) from None
    accepted = _keywords(target)
    unknown = [str(k) for k in node if not str(k).startswith("_") and str(k) not in accepted]
    if accepted and unknown:
        raise ValueError(f"unknown key {path}.{unknown[0]}; known keys: {', '.join(accepted)}")
    try:
        instantiate(node)
    except Exception as error:  # a config's own check: the user's
        cause = error.__cause__ if isinstance(error, InstantiationException) else error
        message = _first_line(cause or error)
        raise ValueError(_rekeyed(message, path, node)) from None


def _keywords(target: Any) -> list[str]:
    """The keywords ``target`` takes; empty when it takes any (``**kwargs``) or has no signature
    Python can read."""
    try:
        parameters = inspect.signature(target).parameters.values()
    except (TypeError, ValueError):
        return []
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        return []
    named = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return [p.name for p in parameters if p.kind in named]


def _first_line(error: BaseException) -> str:
    return str(error).splitlines()[0] if str(error) else type(error).__name__


def _check_argument_types(node: DictConfig, path: str) -> None:
    """Numbers where the target's signature says ``int`` or ``float``, booleans for ``bool``:
    ``speed_mps=abc`` names its key here, not as a ``TypeError`` from inside the class. Nested
    ``_target_`` blocks are checked the same way; keys of other types are the class's."""
    try:
        target = get_object(str(node._target_))
        hints = typing.get_type_hints(
            target if dataclasses.is_dataclass(target) else target.__init__
        )
    except Exception:  # not importable or no resolvable hints: instantiate reports it
        return
    for key in map(str, node):
        if key.startswith("_") or OmegaConf.is_interpolation(node, key) or key not in hints:
            continue
        value, full_key = node[key], f"{path}.{key}"
        if isinstance(value, DictConfig) and "_target_" in value:
            _check_argument_types(value, full_key)
            continue
        kinds = _scalar_kinds(hints[key])
        if kinds is None or (value is None and type(None) in kinds):
            continue
        if bool in kinds and not kinds - {bool, type(None)}:
            if not isinstance(value, bool):
                raise ValueError(f"{full_key} must be true or false (got {value!r})")
        elif not is_number(value):
            raise ValueError(f"{full_key} must be a number (got {value!r})")


def _scalar_kinds(hint: Any) -> set[type] | None:
    """{int, float, bool, NoneType} a hint allows, or None when it allows anything else too."""
    options = typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)
    if typing.get_origin(hint) is typing.Union:
        options = typing.get_args(hint)
    kinds = set(options)
    return kinds if kinds and kinds <= {int, float, bool, type(None)} else None


def _rekeyed(message: str, path: str, node: Any) -> str:
    """``message`` naming keys where ``node`` lives, ``path``.

    A class names its keys by its home group (``controller.Np``); built at another place of the
    config (``task.extra_controllers.de_mpc_long``) the keys are rewritten there. A message that
    starts with a bare key of the node (``speed_mps must be > 0``) gets the path in front; any
    other message that does not name the path, the path and a colon.
    """
    home = re.match(r"([A-Za-z_]\w*)\.", message)
    if home and home.group(1) != path.split(".")[0] and not message.startswith(path + "."):
        return re.sub(rf"(?<![\w.]){re.escape(home.group(1))}\.", path + ".", message)
    first = re.match(r"(\w+)\b", message)
    if first and isinstance(node, DictConfig) and first.group(1) in node:
        return f"{path}.{message}"
    return message if path in message else f"{path}: {message}"


def _check_periods(cfg: DictConfig) -> None:
    """Every control period that the task uses equals ``plant.control_period_s``."""
    if "plant" not in cfg or "task" not in cfg or "control_period_s" not in cfg.plant:
        return
    period = float(cfg.plant.control_period_s)
    # The task's own subtree, and every top-level group it takes by interpolation (``${x}``).
    task = OmegaConf.to_container(cfg.task, resolve=False)
    assert isinstance(task, dict)
    used = {"task": cfg.task}
    groups = {"${" + str(name) + "}": str(name) for name in cfg if name != "plant"}
    for value in task.values():
        if isinstance(value, str) and value in groups:
            used[groups[value]] = cfg[groups[value]]
    for path, node in used.items():
        for key, value in _periods(node, path):
            if not math.isclose(value, period, rel_tol=1e-9):
                raise ValueError(
                    f"{key} ({value:g}) must equal plant.control_period_s ({period:g}): plant, "
                    "data, model and controller share one sampling period"
                )


def _periods(node: Any, path: str) -> list[tuple[str, float]]:
    """(full key, value) of every numeric ``PERIOD_KEYS`` entry below ``node``."""
    found: list[tuple[str, float]] = []
    if not isinstance(node, DictConfig):
        return found
    for key in map(str, node):
        if OmegaConf.is_interpolation(node, key) or OmegaConf.is_missing(node, key):
            continue
        value, full_key = node[key], f"{path}.{key}"
        if key in PERIOD_KEYS and isinstance(value, int | float) and not isinstance(value, bool):
            found.append((full_key, float(value)))
        elif isinstance(value, DictConfig):
            found.extend(_periods(value, full_key))
    return found


def as_object(node: Any, schema: type[T]) -> T:
    """The ``schema`` instance behind a composed structured node (an instance passes through):
    what a task gets for a block that Hydra hands over as a config node."""
    value = node if isinstance(node, schema) else OmegaConf.to_object(node)
    if not isinstance(value, schema):
        raise ValueError(f"expected a {schema.__name__} config, got {type(value).__name__}")
    return value
