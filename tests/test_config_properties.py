"""Any value for any numeric key: it runs, or it is refused in one line naming the key.

A property test (hypothesis) over every numeric key of every config group: plant, data, each
learner (nested blocks included), controller, reference, the pipeline's and characterize's own
keys. A random value (negative, zero, huge, NaN, inf, a string, a list) is composed as an
override exactly as on the command line; then the config is composed, validated and built as
``python -m harness`` does before its first episode, and a plant is stepped. Each example must
either pass (and a built plant step to finite states) or fail in one line that names the key
(or its block, for a value checked with its siblings): never a traceback of another kind, a
hang, or a NaN state. No data is collected and nothing is trained.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf

from harness.app import composition_error
from harness.config import validate
from harness.plant import Sedan
from harness.plant.sedan import PlantUnstableError
from tests.helpers import compose

hypothesis = pytest.importorskip("hypothesis")
st = pytest.importorskip("hypothesis.strategies")

# (the options chosen, the subtree whose numeric leaves are probed)
SETUPS: list[tuple[tuple[str, ...], str]] = [
    (("plant=sedan",), "plant"),
    (("data=default",), "data"),
    (("learner=edmd",), "learner"),
    (("learner=elm_edmd",), "learner"),
    (("learner=dnn",), "learner"),
    (("learner=deep_edmd",), "learner"),
    (("controller=de_mpc",), "controller"),
    ((), "task.references.double_lane_change"),
    ((), "task"),
    (("task=characterize",), "task"),
]
SKIP = {"seed", "learner.seed", "learner.training.seed", "data.seed"}  # any int is a valid seed


def numeric_keys(node: DictConfig | ListConfig, path: str) -> list[str]:
    """Full keys of every int or float leaf below ``node`` (interpolations and lists aside)."""
    keys: list[str] = []
    if not isinstance(node, DictConfig):
        return keys
    for key in map(str, node):
        if OmegaConf.is_interpolation(node, key) or OmegaConf.is_missing(node, key):
            continue
        value, full_key = node[key], f"{path}.{key}"
        if isinstance(value, DictConfig):
            keys.extend(numeric_keys(value, full_key))
        elif isinstance(value, int | float) and not isinstance(value, bool):
            keys.append(full_key)
    return keys


def _cases() -> list[tuple[tuple[str, ...], str]]:
    cases = []
    for options, subtree in SETUPS:
        cfg = compose(*options, as_app=True)
        for key in numeric_keys(OmegaConf.select(cfg, subtree), subtree):
            if key not in SKIP:
                cases.append((options, key))
    return cases


CASES = _cases()
VALUES = st.one_of(
    st.sampled_from(["nan", "inf", "-inf", "abc", "[1,2]", "{a: 1}", "null", "true", "''"]),
    st.sampled_from([0, -1, 1, 2, 10**12, -(10**12), 10**30]).map(str),
    st.sampled_from([0.0, -0.5, 1e-12, 0.3, 1e30, -1e30, 1e300]).map(repr),
    st.integers(min_value=-(10**6), max_value=10**6).map(str),
    st.floats(allow_nan=False, allow_infinity=False, width=32).map(repr),
)


def test_the_probe_covers_every_group() -> None:
    groups = {key.split(".")[0] for _, key in CASES}
    assert groups == {"plant", "data", "learner", "controller", "task"}
    assert any(key.startswith("task.references.") for _, key in CASES)
    assert len(CASES) > 100


def _names(message: str, key: str) -> bool:
    """The message names the key, or its block (``data.split`` for ``data.split.train``)."""
    parent = key.rpartition(".")[0]
    return key in message or (parent.count(".") >= 1 and parent in message)


def check_one(options: tuple[str, ...], key: str, value: str) -> None:
    override = f"{key}={value}"
    try:
        cfg = compose(*options, override, as_app=True)
    except Exception as error:  # Hydra's own: a value of the wrong type, a bad override
        message = composition_error(error)
        assert "\n" not in message and _names(message, key), (override, message)
        return
    try:
        validate(cfg)
        try:
            plant = instantiate(cfg.plant)
            instantiate(cfg.task)
        except InstantiationException as error:  # the app prints the part's own error
            raise error.__cause__ from None  # type: ignore[misc]
        if key.startswith("plant."):
            states = [plant.step((90.0, 0.2)) for _ in range(20)]
            assert np.all(np.isfinite(states)), (override, states[-1])
    except (ValueError, PlantUnstableError) as error:
        message = str(error)
        assert "\n" not in message and _names(message, key), (override, message)
        return
    accepted = OmegaConf.select(cfg, key)
    if isinstance(accepted, float):
        assert math.isfinite(accepted), (override, accepted)


@hypothesis.settings(
    max_examples=40,
    deadline=None,
    derandomize=True,  # the same examples on every run: CI is reproducible
    database=None,
    suppress_health_check=list(hypothesis.HealthCheck),
)
@hypothesis.given(case=st.sampled_from(CASES), value=VALUES)
def test_any_value_of_any_numeric_key_runs_or_fails_in_one_line_naming_it(
    case: tuple[tuple[str, ...], str], value: str
) -> None:
    options, key = case
    check_one(options, key, value)


def test_a_plant_built_from_defaults_steps_finite() -> None:
    plant = Sedan()
    assert np.all(np.isfinite([plant.step((0.0, 0.2)) for _ in range(10)]))
