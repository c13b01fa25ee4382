"""Every config composes and builds; a wrong value is refused in one line that names its key."""

from __future__ import annotations

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from harness.paths import CONF_DIR
from harness.plant import Sedan, SedanParams

PLANTS = sorted(p.stem for p in (CONF_DIR / "plant").glob("*.yaml"))


def compose_config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def test_the_three_plants_exist() -> None:
    assert {"sedan", "sedan_wet", "sedan_loaded"} <= set(PLANTS)


@pytest.mark.parametrize("name", PLANTS)
def test_every_plant_composes_loads_resets_and_steps(name: str) -> None:
    plant = instantiate(compose_config(f"plant={name}").plant)
    assert isinstance(plant, Sedan) and plant.params.name == name
    x0 = plant.reset(seed=0)
    np.testing.assert_array_equal(x0, np.zeros(3))
    states = np.array(
        [plant.step((90.0 * np.sin(k / 30), 0.2 if k < 100 else -2.0)) for k in range(200)]
    )
    assert np.all(np.isfinite(states))
    assert states[:, 0].max() > 1.0  # it drove off ...
    assert abs(states[-1, 0]) < 0.05  # ... and the brake stopped it


def test_plant_variants_differ_only_where_configured() -> None:
    dry, wet, loaded = (
        instantiate(compose_config(f"plant={n}").plant)
        for n in ("sedan", "sedan_wet", "sedan_loaded")
    )
    assert wet.params.tire.road_friction == 0.5 and dry.params.tire.road_friction == 0.9
    assert wet.params.chassis == dry.params.chassis
    assert loaded.model.body_subtreemass[1] == pytest.approx(dry.model.body_subtreemass[1] + 300)


def test_yaml_defaults_match_the_dataclass_defaults() -> None:
    """conf/plant/sedan.yaml lists every parameter; it must not drift from the code."""
    from_yaml = instantiate(compose_config("plant=sedan").plant).params
    assert from_yaml == SedanParams()


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("plant.tire.road_friction=0", "plant.tire.road_friction"),
        ("plant.chassis.sprung_mass_kg=-5", "plant.chassis.sprung_mass_kg"),
        ("plant.physics_timestep_s=0.003", "plant.control_period_s"),
        ("plant.brakes.front_gain_nm_per_mpa=-1", "plant.brakes.front_gain_nm_per_mpa"),
        ("+plant.tire.grip=1", "plant.tire.grip"),
    ],
)
def test_a_wrong_plant_value_names_its_key(override: str, key: str) -> None:
    with pytest.raises(Exception) as info:
        instantiate(compose_config(override).plant)
    error = info.value.__cause__ or info.value
    assert isinstance(error, ValueError)
    assert key in str(error) and "\n" not in str(error)


def test_experiment_paper_is_a_sweep_of_every_learner_over_three_seeds_at_both_horizons() -> None:
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="config", overrides=["experiment=paper"], return_hydra_config=True
        )
    params = cfg.hydra.sweeper.params
    assert params.seed == "0,1,2"
    assert set(params.learner.split(",")) == {
        "edmd",
        "elm_edmd",
        "dnn",
        "deep_edmd",
        "dnn_random_layer",
        "deep_edmd_random_layer",
        "deep_edmd_lstsq",
    }
    assert cfg.data.episodes == 40
    assert (cfg.controller.Np, cfg.controller.Nc) == (10, 7)
    long = cfg.task.extra_controllers.de_mpc_long
    assert (long.Np, long.Nc) == (60, 50)


def test_random_layer_learners_are_their_base_learner_with_the_layer_on() -> None:
    for name in ("dnn", "deep_edmd"):
        base = compose_config(f"learner={name}").learner
        variant = compose_config(f"learner={name}_random_layer").learner
        assert variant.random_layer.enabled and not base.random_layer.enabled
        assert variant._target_ == base._target_ and variant.training == base.training


def test_experiment_generalization_evaluates_on_the_wet_and_loaded_plants() -> None:
    cfg = compose_config("experiment=generalization")
    others = cfg.task.other_plants
    assert set(others) == {"sedan_wet", "sedan_loaded"}
    assert others.sedan_wet.tire.road_friction == 0.5
    assert others.sedan_loaded.chassis.payload_kg == 300.0
    assert cfg.plant.name == "sedan"
