"""Every config composes and builds; a wrong value is refused in one line that names its key.

Keys and types are checked by the schema when the config is composed (harness/config.py);
ranges by the dataclasses' ``__post_init__``, all at once by ``validate`` before a run starts.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import shutil
from pathlib import Path

import numpy as np
import pytest
from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.errors import ConfigCompositionException
from hydra.utils import instantiate
from omegaconf import OmegaConf

from controllers import DEMPCConfig
from controllers.disturbance import DisturbanceEstimator
from harness.config import validate
from harness.core.contracts import Plant
from harness.core.paths import CONF_DIR
from harness.data.logs import LogsConfig
from harness.data.store import DataConfig
from harness.plant import Sedan, SedanParams
from harness.plant.params import ChassisParams, TireParams
from harness.references import Reference
from harness.report.jobs import sweep_jobs
from harness.tasks.characterize import Characterize
from harness.tasks.collect import Collect
from harness.tasks.pipeline import Pipeline
from learners import Learner
from learners.training import TrainingConfig
from tests.helpers import compose

SCHEMAS = {"plant": SedanParams, "data": (DataConfig, LogsConfig)}
CONFIGS = [
    (group, path.stem) for group in SCHEMAS for path in sorted((CONF_DIR / group).glob("*.yaml"))
]
PLANTS = [name for group, name in CONFIGS if group == "plant"]


def test_the_three_plants_exist() -> None:
    assert {"sedan", "sedan_wet", "sedan_loaded"} <= set(PLANTS)


@pytest.mark.parametrize(("group", "name"), CONFIGS, ids=[f"{g}/{n}" for g, n in CONFIGS])
def test_every_plant_and_data_config_composes_and_converts_to_its_schema(
    group: str, name: str
) -> None:
    # A user's logs (``- logs_schema``) need the directory they are in: any one composes.
    logs = "logs_schema" in (CONF_DIR / group / f"{name}.yaml").read_text()
    cfg = compose(f"{group}={name}", *(["data.path=."] if logs else []))
    validate(cfg)
    block = OmegaConf.to_object(cfg[group])
    assert isinstance(block, SCHEMAS[group]) and block.name == name


def test_logs_without_their_directory_are_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match=r"^data\.path must be given") as info:
        validate(compose("data=ddk_carsim"))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("name", PLANTS)
def test_every_plant_composes_loads_resets_and_steps(name: str) -> None:
    plant = instantiate(compose(f"plant={name}").plant)
    assert isinstance(plant, Sedan) and plant.params.name == name
    x0 = plant.reset(seed=0)
    np.testing.assert_array_equal(x0, np.zeros(3))
    states = np.array(
        [plant.step((90.0 * np.sin(k / 30), 0.2 if k < 100 else -2.0)) for k in range(200)]
    )
    assert np.all(np.isfinite(states))
    assert states[:, 0].max() > 1.0  # it drove off ...
    assert abs(states[-1, 0]) < 0.05  # ... and the brake stopped it


def test_the_plant_config_builds_a_sedan_on_real_parameter_dataclasses() -> None:
    plant = instantiate(compose("plant=sedan_loaded").plant)
    params = plant.params
    assert type(params) is SedanParams  # not the schema with Hydra's keys
    assert isinstance(params.tire, TireParams) and isinstance(params.chassis, ChassisParams)
    assert params.chassis.payload_position_m == (-0.3, 0.0, 0.1)  # a tuple, as declared
    assert dataclasses.replace(params, name="sedan") != SedanParams()  # the payload differs


def test_plant_variants_differ_only_where_configured() -> None:
    dry, wet, loaded = (
        instantiate(compose(f"plant={n}").plant) for n in ("sedan", "sedan_wet", "sedan_loaded")
    )
    assert wet.params.tire.road_friction == 0.5 and dry.params.tire.road_friction == 0.9
    assert dataclasses.replace(wet.params.tire, road_friction=0.9) == dry.params.tire
    assert wet.params.chassis == dry.params.chassis
    assert loaded.model.body_subtreemass[1] == pytest.approx(dry.model.body_subtreemass[1] + 300)


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("plant.tire.road_friction=abc", "plant.tire.road_friction"),  # wrong type
        ("plant.tire.grip=1", "plant.tire.grip"),  # unknown key
        ("data.driver.grip=1", "data.driver.grip"),
        ("data.episodes=many", "data.episodes"),
        ("data.split.train=one", "data.split.train"),
    ],
)
def test_a_wrong_type_or_an_unknown_key_fails_at_composition_naming_the_key(
    override: str, key: str
) -> None:
    with pytest.raises(ConfigCompositionException) as info:
        compose(override)
    assert key in str(info.value).splitlines()[0]
    assert info.value.__cause__.full_key == key  # type: ignore[union-attr]


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("plant.tire.road_friction=-1", "plant.tire.road_friction must be > 0 (got -1)"),
        ("plant.tire.road_friction=inf", "plant.tire.road_friction must be finite (got inf)"),
        ("plant.chassis.sprung_mass_kg=-5", "plant.chassis.sprung_mass_kg must be > 0"),
        ("plant.physics_timestep_s=0.003", "plant.control_period_s (0.01) must be a whole"),
        ("plant.brakes.front_gain_nm_per_mpa=-1", "plant.brakes.front_gain_nm_per_mpa must be"),
        ("plant.chassis.payload_position_m=[1,2]", "plant.chassis.payload_position_m must be"),
        ("+plant.tire.grip=1", "unknown key plant.tire.grip; known keys: road_friction,"),
        ("data.split.train=2", "data.split counts sum to 6, not data.episodes (12)"),
        ("data.min_steps=5000", "data.min_steps (5000) must be >= 10 and <= data.max_steps"),
        (
            "data.driver.lateral_weights=[1,2]",
            "data.driver.lateral_weights must be 6 weights with a positive sum",
        ),
        ("data.driver.steer_rate_deg_per_s=-1", "data.driver.steer_rate_deg_per_s must be"),
        ("experiment=generalization", None),  # the other plants are checked as well ...
    ],
)
def test_an_out_of_range_value_fails_validation_in_one_line_naming_the_key(
    override: str, message: str | None
) -> None:
    cfg = compose(override)
    if message is None:
        validate(cfg)
        cfg.task.other_plants.sedan_wet.tire.road_friction = -1.0
        # ... and refused, naming the key where that plant lives
        message = "task.other_plants.sedan_wet.tire.road_friction must be > 0 (got -1)"
    with pytest.raises(ValueError) as info:
        validate(cfg)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_experiment_paper_is_a_sweep_of_every_learner_over_three_seeds_at_both_horizons(
    tmp_path: Path,
) -> None:
    cfg = compose("experiment=paper", as_app=True)
    params = cfg.hydra.sweeper.params
    assert params.seed == "0,1,2"
    # Every learner of conf/learner/, the physics baseline and the bilinear ones included: the
    # sweep names no learner, it globs the group, and the report resolves the glob as Hydra does.
    assert params.learner == "glob(*,exclude=*_schema)"
    OmegaConf.save(cfg, tmp_path / "multirun.yaml")
    jobs = sweep_jobs(tmp_path / "multirun.yaml")
    assert jobs is not None
    learners = {p.stem for p in (CONF_DIR / "learner").glob("*.yaml")}
    assert len(jobs) == 3 * len(learners)
    assert {overrides["learner"] for _, overrides in jobs} == learners
    assert [overrides["seed"] for _, overrides in jobs[: len(learners)]] == ["0"] * len(learners)
    assert cfg.data.episodes == 40
    assert (cfg.controller.Np, cfg.controller.Nc) == (10, 7)
    long = cfg.task.extra_controllers.de_mpc_long
    assert (long.Np, long.Nc) == (60, 50)
    main_job = cfg.task.extra_controllers.de_mpc_path_long_offset_free  # the main job's, beside
    assert (main_job.Np, main_job.reference) == (60, "path")
    assert main_job.disturbance._target_ == "controllers.disturbance.OffsetFree"  # offset-free


def test_random_layer_learners_are_their_base_learner_with_the_layer_on() -> None:
    for name in ("dnn", "deep_edmd"):
        base = compose(f"learner={name}").learner
        variant = compose(f"learner={name}_random_layer").learner
        assert variant.random_layer.enabled and not base.random_layer.enabled
        assert variant._target_ == base._target_ and variant.training == base.training


def test_experiment_generalization_evaluates_on_the_wet_and_loaded_plants() -> None:
    cfg = compose("experiment=generalization")
    others = cfg.task.other_plants
    assert set(others) == {"sedan_wet", "sedan_loaded"}
    assert others.sedan_wet.tire.road_friction == 0.5
    assert others.sedan_loaded.chassis.payload_kg == 300.0
    assert cfg.plant.name == "sedan"


def _every_config_file() -> list[tuple[str, str]]:
    """(group, option) for every YAML under conf/ except config.yaml itself."""
    return sorted(
        (path.parent.relative_to(CONF_DIR).as_posix(), path.stem)
        for path in CONF_DIR.rglob("*.yaml")
        if path.parent != CONF_DIR
    )


ALL_CONFIGS = _every_config_file()


def test_the_config_list_covers_every_group() -> None:
    groups = {group for group, _ in ALL_CONFIGS}
    assert groups >= {
        "plant",
        "data",
        "learner",
        "controller",
        "task",
        "recorder",
        "reference",
        "experiment",
        "hydra/launcher",
    }


# What each group's option builds: the contracts of harness/core/contracts.py where there is one.
BUILDS: dict[str, type | tuple[type, ...]] = {
    "plant": Plant,
    "data": (DataConfig, LogsConfig),
    "learner": Learner,
    "controller": DEMPCConfig,
    "task": (Pipeline, Characterize, Collect),
    "experiment": Pipeline,
    "recorder": functools.partial,
    "reference": Reference,
    "disturbance": DisturbanceEstimator,
    "horizon": DEMPCConfig,
    "tracking": DEMPCConfig,
    "training": TrainingConfig,
}


@pytest.mark.parametrize(("group", "name"), ALL_CONFIGS, ids=[f"{g}/{n}" for g, n in ALL_CONFIGS])
def test_every_config_file_composes_validates_and_builds(group: str, name: str) -> None:
    """Each option, chosen on top of the defaults, composes, passes every check and builds."""
    if group == "hydra/launcher":
        if name.startswith("ray"):  # the Ray launcher is an optional extra (make test-ray)
            pytest.importorskip("hydra_plugins.hydra_ray_launcher")
        cfg = compose(f"hydra/launcher={name}", as_app=True)
        module, _, cls = cfg.hydra.launcher._target_.rpartition(".")
        assert isinstance(getattr(importlib.import_module(module), cls), type)
        return
    if group == "reference":  # a reference is built where a task lists it
        cfg = compose(f"+reference@task.references.probe={name}", as_app=True)
        node = cfg.task.references.probe
    elif group == "disturbance":  # an estimator is built where a controller names it
        cfg = compose(f"disturbance@controller.disturbance={name}", as_app=True)
        node = cfg.controller.disturbance
    elif group in ("horizon", "tracking"):  # a part of a controller preset
        cfg = compose(f"{group}@controller={name}", as_app=True)
        node = cfg.controller
    elif group == "training":  # a part of a trained learner's preset
        cfg = compose("learner=dnn", f"training@learner.training={name}", as_app=True)
        node = cfg.learner.training
    else:
        logs = group == "data" and "logs_schema" in (CONF_DIR / "data" / f"{name}.yaml").read_text()
        cfg = compose(f"{group}={name}", *(["data.path=."] if logs else []), as_app=True)
        node = cfg.task if group == "experiment" else cfg[group]
    validate(cfg)
    built = OmegaConf.to_object(node) if group == "data" else instantiate(node)
    assert isinstance(built, BUILDS[group]), f"{group}={name} built a {type(built).__name__}"
    if group == "plant":
        assert built.reset(seed=0).shape == (3,)


def _defaults_depth(group: str, name: str) -> int:
    """How many levels of presets of ``group`` (and schemas) ``name`` builds on."""
    node = OmegaConf.load(CONF_DIR / group / f"{name}.yaml")
    depth = 0
    for entry in node.get("defaults", []):
        if isinstance(entry, str) and entry != "_self_":
            below = CONF_DIR / group / f"{entry}.yaml"
            depth = max(depth, 1 + (_defaults_depth(group, entry) if below.exists() else 0))
    return depth


@pytest.mark.parametrize("preset", sorted(p.stem for p in (CONF_DIR / "controller").glob("*.yaml")))
def test_a_controller_preset_is_a_few_lines_built_from_parts(preset: str) -> None:
    """A preset names the base controller and the parts it adds (``/horizon@_here_: long``,
    ``/tracking@_here_: path``, ``/disturbance@disturbance: offset_free``) and what it sets
    itself: at most 10 lines of YAML, at most 2 levels of defaults (preset, base, schema)."""
    text = (CONF_DIR / "controller" / f"{preset}.yaml").read_text()
    lines = [
        line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")
    ]
    assert len(lines) <= 10, f"{preset}.yaml has {len(lines)} lines of YAML"
    assert _defaults_depth("controller", preset) <= 2, f"{preset}.yaml builds on too many levels"


def _schema_of_file(group: str, name: str) -> str | None:
    """The schema a preset composes, itself or through the presets of its group it builds on."""
    for entry in OmegaConf.load(CONF_DIR / group / f"{name}.yaml").get("defaults", []):
        if isinstance(entry, str) and entry.endswith("_schema"):
            return entry
        if isinstance(entry, str) and (CONF_DIR / group / f"{entry}.yaml").exists():
            found = _schema_of_file(group, entry)
            if found is not None:
                return found
    return None


SCHEMA_FILES = [(g, n) for g, n in ALL_CONFIGS if "/" not in g and _schema_of_file(g, n)]


def _leaves(node: object, prefix: str = "") -> dict[str, object]:
    if isinstance(node, dict) and node:
        found: dict[str, object] = {}
        for key, value in node.items():
            found.update(_leaves(value, f"{prefix}.{key}" if prefix else str(key)))
        return found
    return {prefix: node} if prefix else {}


def _at(node: object, key: str) -> object:
    """The value at a dotted key of nested dicts, unresolved (``${seed}`` as written)."""
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return "<absent>"
        node = node[part]
    return node


@pytest.fixture(scope="module")
def conf_copy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    copy = tmp_path_factory.mktemp("conf") / "conf"
    shutil.copytree(CONF_DIR, copy)
    return copy


@pytest.mark.parametrize(("group", "name"), SCHEMA_FILES, ids=[f"{g}/{n}" for g, n in SCHEMA_FILES])
def test_a_preset_with_a_schema_lists_only_what_differs(
    group: str, name: str, conf_copy: Path
) -> None:
    """Every key a preset sets changes what it composes to: its schema's defaults (and the
    presets and parts it builds on) hold the rest, so a setting's value is written once."""
    path = conf_copy / group / f"{name}.yaml"
    written = path.read_text()
    own = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    assert isinstance(own, dict)
    defaults = own.pop("defaults", None)
    package = written.splitlines()[0] if written.startswith("# @package") else ""

    def composed() -> dict[str, object]:
        with initialize_config_dir(config_dir=str(conf_copy), version_base="1.3"):
            cfg = hydra_compose(config_name="config", overrides=[f"{group}={name}"])
        node = OmegaConf.to_container(cfg, resolve=False)
        return node if package else node[group]  # type: ignore[index, return-value]

    try:
        path.write_text(f"{package}\n" + OmegaConf.to_yaml({"defaults": defaults or []}))
        base = composed()
    finally:
        path.write_text(written)
    preset = composed()
    same = [key for key in _leaves(own) if _at(base, key) == _at(preset, key)]
    assert not same, f"conf/{group}/{name}.yaml sets {same} to what its defaults give already"
