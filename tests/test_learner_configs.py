"""Every learner YAML is tested by being there: a new learner is one class plus one YAML file, and
the YAML alone enrols it here (the class needs one row of tiny settings below, keyed by the
class, not by the config's name).

Each ``conf/learner/*.yaml`` composes, builds its class, fits a few drives of the real plant in
seconds, predicts a held-out drive finitely from its measured start, survives a save and a
load with the same predictions to rounding, and, where DE-MPC linearises it (bilinear or
nonlinear dynamics), gives the Jacobians of its own step.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hydra.utils import get_class, instantiate

from controllers.linearization import BilinearLinearization
from harness.core.contracts import dynamics_of
from harness.core.episode import Episode, MinMaxNormalizer
from harness.core.paths import CONF_DIR
from learners import Learner
from learners import load as load_learner
from learners.wrapping import WrappingLearner
from tests.helpers import learner_config
from tests.toydata import drive_episodes

NAMES = sorted(path.stem for path in (CONF_DIR / "learner").glob("*.yaml"))

_NETWORK = [
    "learner.training.max_steps=60",
    "learner.training.eval_every_steps=30",
    "learner.training.checkpoint_every_steps=30",
    "learner.training.batch_size=16",
    "learner.training.progress=false",
    "learner.horizon=10",
]
# Sizes small enough for seconds, keyed by the class a YAML names (its ``_target_``).
TINY: dict[str, list[str]] = {
    "learners.edmd.EDMD": [],
    "learners.bilinear.BilinearEDMD": ["learner.dictionary.num_centers=30"],
    "learners.input_edmd.InputEDMD": ["learner.dictionary.num_centers=100"],
    "learners.single_track.SingleTrack": [],
    "learners.persistence.Persistence": [],
    "learners.sindy.SINDyC": [],
    "learners.dnn.DNN": [*_NETWORK, "learner.hidden=[16,16]"],
    "learners.deep_edmd.DeepEDMD": _NETWORK,
    "learners.bilinear_deep_edmd.BilinearDeepEDMD": _NETWORK,
}


def _wraps(target: str) -> bool:
    """Whether the class a YAML names wraps another learner (learner.inner): its tiny settings
    are its inner learner's row, under learner.inner."""
    return issubclass(get_class(target), WrappingLearner)


def tiny(name: str) -> list[str]:
    """The tiny settings of ``conf/learner/<name>.yaml``'s class (its inner one's, moved)."""
    cfg = learner_config(name)
    if not _wraps(cfg._target_):
        return TINY[cfg._target_]
    return [o.replace("learner.", "learner.inner.", 1) for o in TINY[cfg.inner._target_]]


@pytest.fixture(scope="module")
def drives() -> dict:
    episodes = drive_episodes(6, 60.0)  # the drives tests/test_learners.py fits (cached)
    return {
        "train": episodes[:4],
        "validation": episodes[4:5],
        "test": episodes[5],
        "normalizer": MinMaxNormalizer.fit(episodes[:4]),
    }


def test_every_learner_class_of_conf_has_its_tiny_settings() -> None:
    targets = {t for t in (learner_config(name)._target_ for name in NAMES) if not _wraps(t)}
    targets |= {learner_config(n).inner._target_ for n in NAMES if "inner" in learner_config(n)}
    missing = targets - set(TINY)
    assert missing == set(), f"add a row to TINY in {__file__} for {sorted(missing)}"
    assert len(NAMES) >= 11


@pytest.mark.parametrize("name", NAMES)
def test_every_learner_yaml_builds_fits_predicts_and_round_trips(
    name: str, drives: dict, tmp_path: Path
) -> None:
    cfg = learner_config(name, *tiny(name))
    learner = instantiate(cfg)
    assert type(learner) is get_class(cfg._target_) and isinstance(learner, Learner)
    fitted = learner.fit(drives["train"], drives["validation"], drives["normalizer"])
    assert fitted is learner
    test = drives["test"]
    predicted = learner.predict(test.states[0], test.inputs[:300])
    assert predicted.shape == (301, 3) and np.isfinite(predicted).all()
    np.testing.assert_array_equal(predicted[0], test.states[0])  # it starts where the car was
    loaded = load_learner(learner.save(tmp_path / f"model_{name}.pt"))
    assert type(loaded) is type(learner)
    np.testing.assert_allclose(
        loaded.predict(test.states[0], test.inputs[:300]), predicted, rtol=1e-6, atol=1e-9
    )
    check_linearization(learner, test)


def check_linearization(learner: Learner, drive: Episode) -> None:
    """A model DE-MPC linearises (declared bilinear or nonlinear) gives the Jacobians of its own
    step (central differences) and the affine term that makes the linearisation exact at the
    point; checked at points of a held-out drive."""
    dynamics = dynamics_of(learner)
    if dynamics not in ("bilinear", "nonlinear"):
        return
    model: Any = BilinearLinearization(learner) if dynamics == "bilinear" else learner  # type: ignore[arg-type]
    rows = np.linspace(100, len(drive.states) - 100, 4).astype(int)
    z = model.lift(drive.states[rows])
    v = model.normalizer_.inputs(drive.inputs[rows])
    A, B, d = model.linearize(z, v)
    h = 1e-6
    for jacobian, point in ((A, z), (B, v)):
        for j in range(point.shape[1]):
            delta = np.zeros(point.shape[1])
            delta[j] = h
            if point is z:
                slope = (model.step(z + delta, v) - model.step(z - delta, v)) / (2 * h)
            else:
                slope = (model.step(z, v + delta) - model.step(z, v - delta)) / (2 * h)
            np.testing.assert_allclose(jacobian[:, :, j], slope, atol=1e-4, err_msg=f"column {j}")
    exact = (A @ z[..., None])[..., 0] + (B @ v[..., None])[..., 0] + d
    np.testing.assert_allclose(exact, model.step(z, v), atol=1e-9)


def test_the_paper_presets_keep_the_papers_table_where_our_defaults_depart_from_it() -> None:
    """``learner=*_paper`` is the paper's Table of hyperparameters as written; the defaults are
    ours (docs/findings/training_recipe.md), so a change to a default must not leak into the
    paper's preset."""
    dnn, dnn_paper = learner_config("dnn"), learner_config("dnn_paper")
    assert list(dnn_paper.hidden) == [32, 64, 128, 128, 64, 32]
    assert list(dnn.hidden) != list(dnn_paper.hidden)  # ours: wider and shallower
    for paper in (dnn_paper, learner_config("deep_edmd_paper")):
        assert paper.horizon == 41 and paper.loss_scales is None
        assert paper.training.lr == 1e-4 and paper.training.lr_schedule == "constant"
        assert paper.training.max_steps == 100_000 and paper.training.selection == "window_loss"
    assert dnn_paper.residual is False
    deep_paper = learner_config("deep_edmd_paper")
    assert list(deep_paper.encoder_hidden) == [32, 64] and deep_paper.lifted_dim == 10
    assert list(deep_paper.decoder_hidden) == [128, 64, 32] and deep_paper.alpha.readout == 0.0
    assert deep_paper.refit_inputs_lstsq is False and deep_paper.refit_koopman_lstsq is False
    assert learner_config("deep_edmd").refit_inputs_lstsq is True  # ours: B by least squares
