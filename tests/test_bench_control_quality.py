"""The control-quality benchmark keeps one model per learner setting, never another arm's."""

from bench.control_quality import _model_name


def test_an_arm_that_changes_only_the_controller_drives_the_presets_model() -> None:
    assert _model_name("deep_edmd", ["controller.R=[1,2]", "--both"]) == "deep_edmd"


def test_an_arm_that_changes_the_learner_fits_a_model_of_its_own() -> None:
    preset = _model_name("deep_edmd", [])
    horizon = _model_name("deep_edmd", ["learner.horizon=50", "controller.R=1"])
    other = _model_name("deep_edmd", ["learner.horizon=60"])
    appended = _model_name("deep_edmd", ["+learner.extra=1"])
    assert len({preset, horizon, other, appended}) == 4
    assert horizon == _model_name("deep_edmd", ["controller.R=1", "learner.horizon=50"])
