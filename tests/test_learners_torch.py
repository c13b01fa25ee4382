"""DNN and Deep EDMD: losses by hand, the fast gradients, and the training loop's guarantees."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from harness.core.episode import MinMaxNormalizer
from harness.evaluation import training_report
from harness.recorder import Recorder
from learners import DNN, DeepEDMD
from learners.deep_edmd import LossWeights, deep_edmd_loss_terms, deep_edmd_step
from learners.dnn import DNNLossWeights, dnn_loss_terms, dnn_step
from learners.model_file import check_same_learner
from learners.model_file import load as load_learner
from learners.nets import Dense, mlp_apply
from learners.trained import TrainedLearner
from learners.training import History, TrainingConfig, _State
from learners.windows import WindowData
from tests.toydata import drive_episodes


def sigmoid(a: float) -> float:
    return 1.0 / (1.0 + math.exp(-a))


def tensor(*values) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float32)


@pytest.fixture(scope="module")
def data() -> dict:
    episodes = drive_episodes(4, 20.0, first_seed=10)
    train, validation = episodes[:3], episodes[3:]
    return {"train": train, "validation": validation, "normalizer": MinMaxNormalizer.fit(train)}


def small(cls, checkpoint_dir: Path | None = None, **overrides):
    """A learner small and short enough to fit in well under a second."""
    training = {
        "max_steps": 30,
        "batch_size": 16,
        "lr": 3e-3,
        "eval_every_steps": 10,
        "checkpoint_every_steps": 5,
        "progress": False,
        **overrides.pop("training", {}),
    }
    if cls is DNN:
        learner = DNN(hidden=[16, 16], horizon=8, training=training, **overrides)
    else:  # Deep EDMD or a subclass (bilinear Deep EDMD)
        learner = cls(
            lifted_dim=4,
            encoder_hidden=[16],
            decoder_hidden=[16],
            horizon=8,
            training=training,
            **overrides,
        )
    learner.checkpoint_dir = checkpoint_dir
    return learner


# -- losses against hand computation ------------------------------------------------------------


def test_deep_edmd_losses_match_a_hand_computed_case() -> None:
    """n = m = L = 1, p = 2: phi(x) = 2 relu(x), z = [x, 2x], dec(z) = sigmoid(z_1)."""
    encoder = [
        Dense(tensor([1.0]).view(1, 1), tensor(0.0), "relu"),
        Dense(tensor([2.0]).view(1, 1), tensor(0.0), "linear"),
    ]
    decoder = [Dense(tensor([1.0, 0.0]).view(1, 2), tensor(0.0), "sigmoid")]
    a = torch.tensor([[1.0, 0.0], [0.0, 0.5]])
    b = torch.tensor([[0.1], [0.2]])
    x = tensor(0.5, 0.6, 0.8).view(1, 3, 1)
    v = tensor(1.0, -1.0).view(1, 2, 1)
    # K^1 z0 = [0.5 + 0.1, 0.5 + 0.2] = [0.6, 0.7];  K^2 z0 = [0.6 - 0.1, 0.35 - 0.2] = [0.5, 0.15]
    # z1 = [0.6, 1.2], z2 = [0.8, 1.6]
    recon = [0.6 - sigmoid(0.6), 0.8 - sigmoid(0.8)]
    pred = [0.6 - sigmoid(0.6), 0.8 - sigmoid(0.5)]
    expected = {
        "ox": (recon[0] ** 2 + recon[1] ** 2) / 2,
        "xx": (pred[0] ** 2 + pred[1] ** 2) / 2,
        "xo": ((0.0**2 + 0.5**2) + (0.3**2 + 1.45**2)) / 2,
        "inf": (abs(recon[0]) + abs(recon[1])) / 2 + (abs(pred[0]) + abs(pred[1])) / 2,
    }
    terms = deep_edmd_loss_terms(encoder, decoder, a, b, x, v, lifted_includes_state=True)
    for key, value in expected.items():
        assert float(terms[key]) == pytest.approx(value, rel=1e-6), key
    weights = LossWeights(ox=1.0, xx=2.0, xo=0.3, inf=0.5)
    total = sum(getattr(weights, k) * v for k, v in expected.items())
    grads = {"grad_a": torch.zeros(2, 2), "grad_b": torch.zeros(2, 1)}
    loss = deep_edmd_step(
        encoder, decoder, a, b, **grads, x=x, v=v, weights=weights, lifted_includes_state=True
    )
    assert loss == pytest.approx(total, rel=1e-6)


@pytest.mark.parametrize("residual", [False, True])
def test_dnn_loss_matches_a_hand_computed_case(residual: bool) -> None:
    """M(x, u) = 0.5 relu(x + u) + 0.1 on x = [0.2, 0.4, 0.3], u = [0.4, -1.0]."""
    layers = [
        Dense(tensor(1.0, 1.0).view(1, 2), tensor(0.0), "relu"),
        Dense(tensor(0.5).view(1, 1), tensor(0.1), "linear"),
    ]
    x = tensor(0.2, 0.4, 0.3).view(1, 3, 1)
    v = tensor(0.4, -1.0).view(1, 2, 1)
    # plain: x1 = 0.5 * 0.6 + 0.1 = 0.4, x2 = 0.5 * relu(-0.6) + 0.1 = 0.1 -> errors 0, 0.2
    # residual: x1 = 0.2 + 0.4 = 0.6, x2 = 0.6 + 0.5 * relu(-0.4) + 0.1 = 0.7 -> -0.2, -0.4
    errors = [-0.2, -0.4] if residual else [0.0, 0.2]
    terms = dnn_loss_terms(layers, x, v, residual=residual)
    assert float(terms["prediction"]) == pytest.approx((errors[0] ** 2 + errors[1] ** 2) / 2)
    assert float(terms["inf"]) == pytest.approx((abs(errors[0]) + abs(errors[1])) / 2)
    loss = dnn_step(layers, x, v, DNNLossWeights(prediction=1.0, inf=0.5), residual=residual)
    assert loss == pytest.approx(float(terms["prediction"] + 0.5 * terms["inf"]), rel=1e-6)


# -- fast gradients against autograd on the readable definition --------------------------------


def autograd_objective(learner, x, v, step):
    """Loss and flat gradient of the paper's objective through the readable autograd terms."""
    params = learner.params_
    leaf = params.data.clone().requires_grad_()
    layer = learner._step_layer(step)
    if isinstance(learner, DeepEDMD):
        encoder = params.layers("encoder", leaf)
        if layer is not None:
            encoder = [*encoder[:-1], layer, encoder[-1]]
        views = params.views(leaf)
        terms = deep_edmd_loss_terms(
            encoder,
            params.layers("decoder", leaf),
            views["koopman.A.weight"],
            views["koopman.B.weight"],
            x,
            v,
            lifted_includes_state=learner.lifted_includes_state,
            state_weights=learner._state_weights_tensor(),
        )
        alpha = learner.alpha
        loss = sum(w * terms[k] for k, w in alpha.data_terms().items())
        objective = (
            loss
            + alpha.encoder_l2 * leaf[params.span("encoder")].square().sum()
            + alpha.decoder_l2 * leaf[params.span("decoder")].square().sum()
        )
    else:
        layers = params.layers("model", leaf)
        if layer is not None:
            layers = [*layers[:-1], layer, layers[-1]]
        terms = dnn_loss_terms(
            layers,
            x,
            v,
            residual=learner.residual,
            increment_scale=learner._increment_scale_tensor(),
            state_weights=learner._state_weights_tensor(),
        )
        loss = learner.beta.prediction * terms["prediction"] + learner.beta.inf * terms["inf"]
        objective = loss + learner.beta.l2 * leaf.square().sum()
    (grad,) = torch.autograd.grad(objective, leaf)
    return float(loss.detach()), grad


@pytest.mark.parametrize(
    "make",
    [
        lambda: DeepEDMD(alpha={"inf": 0.1, "encoder_l2": 0.01, "decoder_l2": 0.02}),
        lambda: DeepEDMD(alpha={"readout": 2.0}),
        lambda: DeepEDMD(lifted_includes_state=False, alpha={"inf": 0.1}),
        lambda: DeepEDMD(random_layer={"enabled": True, "std": 0.3}),
        lambda: DNN(beta={"inf": 0.1, "l2": 0.01}),
        lambda: DNN(residual=True, random_layer={"enabled": True, "std": 0.3}),
        lambda: DeepEDMD(alpha={"inf": 0.1}, loss_scales=[0.2, 0.1, 0.05]),
        lambda: DNN(residual=True, beta={"inf": 0.1}, loss_scales=[0.2, 0.1, 0.05]),
    ],
    ids=[
        "deep_edmd",
        "deep_edmd_readout",
        "deep_edmd_phi_only",
        "deep_edmd_random",
        "dnn",
        "dnn_residual_random",
        "deep_edmd_state_weights",
        "dnn_residual_scaled_state_weights",
    ],
)
def test_the_hand_written_gradients_equal_autograd_on_the_paper_loss(make) -> None:
    """Paper-sized networks, p = 12, with every loss term and regularizer switched on (and ours:
    per-state weights, the residual's increment scale D)."""
    learner = make()
    learner._build(3, 2)
    learner.normalizer_ = MinMaxNormalizer(
        np.zeros(3), np.array([30.0, 2.0, 1.0]), np.zeros(2), np.ones(2)
    )
    learner.increment_scale_ = np.array([0.01, 0.002, 0.03])
    learner.params_.initialize(torch.Generator().manual_seed(0))
    generator = torch.Generator().manual_seed(1)
    x = torch.rand(16, 13, 3, generator=generator)
    v = torch.rand(16, 12, 2, generator=generator)
    expected_loss, expected_grad = autograd_objective(learner, x, v, step=7)
    learner.params_.grad.zero_()
    loss = learner._objective().train_step(x, v, 7)
    grad = learner.params_.grad
    assert loss == pytest.approx(expected_loss, rel=1e-5)
    assert float((grad - expected_grad).norm() / expected_grad.norm()) < 1e-5


# -- the training loop ---------------------------------------------------------------------------


@pytest.mark.parametrize("cls", [DNN, DeepEDMD])
def test_two_fits_with_one_seed_predict_identically(cls, data: dict) -> None:
    x0, inputs = data["validation"][0].states[0], data["validation"][0].inputs[:200]
    runs = [
        small(cls, training={"seed": seed})
        .fit(data["train"], data["validation"], data["normalizer"])
        .predict(x0, inputs)
        for seed in (0, 0, 1)
    ]
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])


@pytest.mark.parametrize("cls", [DNN, DeepEDMD])
def test_a_killed_run_resumes_from_its_checkpoint_to_the_uninterrupted_result(
    cls, data: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    args = (data["train"], data["validation"], data["normalizer"])
    whole = small(cls, tmp_path / "whole").fit(*args)

    calls = {"n": 0}
    adam_step = torch.optim.Adam.step

    def dies_at_step_13(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 13:
            raise KeyboardInterrupt("killed")
        return adam_step(self, *a, **k)

    with monkeypatch.context() as patch:
        patch.setattr(torch.optim.Adam, "step", dies_at_step_13)
        with pytest.raises(KeyboardInterrupt):
            small(cls, tmp_path / "killed").fit(*args)
    assert (tmp_path / "killed" / f"{cls.name}.ckpt").exists()
    resumed = small(cls, tmp_path / "killed").fit(*args)  # from step 10

    short = small(cls, tmp_path / "extended", training={"max_steps": 20}).fit(*args)
    assert short.history_.step[-1] == 20
    extended = small(cls, tmp_path / "extended").fit(*args)  # 20 more steps

    for other in (resumed, extended):
        np.testing.assert_array_equal(other.params_.data, whole.params_.data)
        assert other.history_ == whole.history_


def test_a_checkpoint_of_other_hyperparameters_is_refused(data: dict, tmp_path: Path) -> None:
    args = (data["train"], data["validation"], data["normalizer"])
    small(DeepEDMD, tmp_path).fit(*args)
    with pytest.raises(ValueError, match="written for other data or hyperparameters") as info:
        small(DeepEDMD, tmp_path, training={"lr": 1e-3}).fit(*args)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("cls", [DNN, DeepEDMD])
def test_divergence_stops_training_with_a_one_line_error(cls, data: dict) -> None:
    learner = small(cls, training={"lr": 1e4, "max_steps": 200})
    with pytest.raises(RuntimeError, match="training diverged at step") as info:
        learner.fit(data["train"], data["validation"], data["normalizer"])
    assert "\n" not in str(info.value)


def test_early_stopping_counts_validations_without_improvement() -> None:
    state = _State.fresh()
    config = TrainingConfig(patience=2)
    params = type("P", (), {"data": torch.zeros(1)})()
    for step, loss in enumerate([1.0, 0.9, 0.95, 0.9, 0.97], start=1):
        params.data = torch.tensor([float(step)])
        state.step, state.train_count, state.train_sum = step, 1, loss
        state.evaluate({"loss": loss}, params, config)
        if state.stopped:
            break
    assert state.stopped == "early_stopping" and state.step == 4  # 0.95 and 0.9 do not improve
    assert float(state.best_params) == 2.0 and state.best_loss == 0.9


@pytest.mark.parametrize("cls", [DNN, DeepEDMD])
def test_fit_returns_the_best_validated_model_and_writes_nothing(
    cls, data: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Data in, fitted attributes out: without a checkpoint_dir no file appears anywhere."""
    monkeypatch.chdir(tmp_path)
    learner = small(cls, training={"max_steps": 60, "lr": 3e-2}).fit(
        data["train"], data["validation"], data["normalizer"]
    )
    assert list(tmp_path.iterdir()) == []
    history: History = learner.history_
    assert history.step == [10, 20, 30, 40, 50, 60] and history.stopped == "max_steps"
    window_data = WindowData.from_episodes(data["validation"], data["normalizer"])
    starts = window_data.window_starts(learner.horizon)
    final = learner._objective().validate(*window_data.gather(starts, learner.horizon))
    assert final["loss"] == pytest.approx(min(v["loss"] for v in history.validation), rel=1e-5)


@pytest.mark.parametrize("cls", [DNN, DeepEDMD])
def test_a_run_fits_in_its_directory_and_keeps_the_loss_curves(
    cls, data: dict, tmp_path: Path
) -> None:
    """training_report.fit: checkpoint, training_history.json, recording and figure."""
    logged = {}

    class Capture(Recorder):
        def series(self, path, time_s, values, timeline="sim_time"):
            logged[path] = (np.asarray(time_s), dict(values), timeline)

    learner = training_report.fit(
        small(cls, training={"max_steps": 60, "lr": 3e-2}),
        data["train"],
        data["validation"],
        data["normalizer"],
        recorder=Capture(),
        output_dir=tmp_path,
    )
    history: History = learner.history_
    assert (tmp_path / f"{cls.name}.ckpt").exists()
    assert json.loads((tmp_path / "training_history.json").read_text()) == history.to_dict()
    steps, values, timeline = logged[f"training/{cls.name}"]
    assert timeline == "step" and steps.dtype == np.int64 and list(steps) == history.step
    np.testing.assert_array_equal(values["train"], history.train)
    np.testing.assert_array_equal(values["validation"], [v["loss"] for v in history.validation])
    assert set(values) == {"train", "validation", *(f"validation_{k}" for k in learner_terms(cls))}
    assert (tmp_path / f"{cls.name}_loss.png").stat().st_size > 10_000


def learner_terms(cls) -> tuple[str, ...]:
    """The loss terms a learner validates besides their weighted sum ``loss``."""
    return ("ox", "xx", "xo", "inf", "readout") if cls is DeepEDMD else ("prediction", "inf")


@pytest.mark.parametrize("cls", [DNN, DeepEDMD])
def test_the_random_layer_is_redrawn_per_seed_and_nominal_without_one(cls, data: dict) -> None:
    learner = small(cls, random_layer={"enabled": True, "std": 0.2}).fit(
        data["train"], data["validation"], data["normalizer"]
    )
    x0, inputs = data["validation"][0].states[100], data["validation"][0].inputs[100:150]
    nominal = learner.predict(x0, inputs)
    first, again, other = (learner.predict(x0, inputs, random_layer_seed=s) for s in (3, 3, 4))
    np.testing.assert_array_equal(first, again)
    assert not np.allclose(first, other) and not np.allclose(first, nominal)
    # the layer's mean is the identity after a ReLU: drawn with std 0 it changes nothing
    learner.random_layer = type(learner.random_layer)(enabled=True, std=0.0)
    np.testing.assert_allclose(learner.predict(x0, inputs, random_layer_seed=5), nominal, rtol=1e-6)
    learner.random_layer = type(learner.random_layer)(enabled=False)
    with pytest.raises(ValueError, match="has no random layer"):
        learner.predict(x0, inputs, random_layer_seed=0)


def test_the_least_squares_refit_solves_the_normal_equations_of_the_lifted_data(
    data: dict, tmp_path: Path
) -> None:
    """W^T (Y - W Theta) = 0 for regressors W = [z_k v_k], targets Y = z_{k+1}, Theta = [A B]^T
    (up to the float32 storage of A, B); the trained A, B are far from it."""
    args = (data["train"], data["validation"], data["normalizer"])
    trained = small(DeepEDMD).fit(*args)
    refit = small(DeepEDMD, refit_koopman_lstsq=True).fit(*args)
    np.testing.assert_array_equal(trained.params_.data[:100], refit.params_.data[:100])

    def normal_equations(model) -> float:
        """||W^T (Y - W Theta)|| / ||W^T Y|| on the lifted training data."""
        w = np.vstack(
            [
                np.hstack([model.lift(e.states)[:-1], data["normalizer"].inputs(e.inputs)[:-1]])
                for e in data["train"]
            ]
        )
        y = np.vstack([model.lift(e.states)[1:] for e in data["train"]])
        theta = np.hstack([model.A_, model.B_]).T
        return float(np.linalg.norm(w.T @ (y - w @ theta)) / np.linalg.norm(w.T @ y))

    assert normal_equations(refit) < 1e-6
    assert normal_equations(trained) > 1e-3
    # the refit is a post-processing of the same network: applied to a trained model it gives
    # exactly what training with refit_koopman_lstsq gives
    linear = small(DeepEDMD, refit_koopman_lstsq=True, prediction_output="linear").fit(*args)
    afterwards = trained.refit_koopman(data["train"])
    np.testing.assert_array_equal(afterwards.A_, refit.A_)
    np.testing.assert_array_equal(afterwards.B_, refit.B_)
    # ... and is learner=deep_edmd_lstsq in every hyperparameter, so its file loads as that
    # learner (task.model_path) and predicts with C z, as DE-MPC does
    assert afterwards.hyperparameters == linear.hyperparameters
    loaded = load_learner(afterwards.save(tmp_path / "refit.pt"))
    check_same_learner(loaded, linear, "refit.pt", "deep_edmd_lstsq")
    episode = data["validation"][0]
    np.testing.assert_allclose(
        loaded.predict(episode.states[0], episode.inputs[:-1]),
        linear.predict(episode.states[0], episode.inputs[:-1]),
        rtol=0,
        atol=1e-9,
    )


def test_the_input_refit_solves_the_normal_equations_of_b_with_the_trained_a(
    data: dict,
) -> None:
    """V^T (Z_{k+1} - Z_k A^T - V B^T) = 0 for the lifted training data and the model's own A
    (up to the float32 storage of B); the trained B is far from it, and A is not touched."""
    args = (data["train"], data["validation"], data["normalizer"])
    trained = small(DeepEDMD).fit(*args)
    a_trained, b_trained = trained.A_.copy(), trained.B_.copy()

    def normal_equations(model) -> float:
        """||V^T R|| / ||V^T (Z_{k+1} - Z_k A^T)||, R the one-step residual."""
        z = [model.lift(e.states) for e in data["train"]]
        v = np.vstack([data["normalizer"].inputs(e.inputs)[:-1] for e in data["train"]])
        target = np.vstack([zk[1:] - zk[:-1] @ model.A_.T for zk in z])
        residual = target - v @ model.B_.T
        return float(np.linalg.norm(v.T @ residual) / np.linalg.norm(v.T @ target))

    assert normal_equations(trained) > 1e-3
    refit = trained.refit_inputs(data["train"])
    assert normal_equations(refit) < 1e-5
    np.testing.assert_array_equal(refit.A_, a_trained)
    assert not np.allclose(refit.B_, b_trained)
    assert refit.hyperparameters["refit_inputs_lstsq"] is True
    # training with the refit ends in the same kind of model: B solves its normal equations
    assert normal_equations(small(DeepEDMD, refit_inputs_lstsq=True).fit(*args)) < 1e-5


def test_one_refit_at_a_time() -> None:
    with pytest.raises(ValueError, match=r"learner\.refit_inputs_lstsq must be false"):
        DeepEDMD(refit_koopman_lstsq=True, refit_inputs_lstsq=True)


def test_training_keeps_the_threads_in_force_unless_num_threads_says_otherwise(
    data: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``num_threads`` null trains on the job's threads (harness.core.threads); a number holds
    for the fit alone, and the caller's count is back after it."""
    args = (data["train"], data["validation"], data["normalizer"])
    before = torch.get_num_threads()
    set_threads = torch.set_num_threads
    seen: list[int] = []

    def recording(count: int) -> None:
        seen.append(count)
        set_threads(count)

    try:
        set_threads(1)
        monkeypatch.setattr(torch, "set_num_threads", recording)
        small(DNN).fit(*args)
        assert set(seen) <= {1}  # null: the threads in force, nothing else
        seen.clear()
        small(DNN, training={"num_threads": 2}).fit(*args)
        assert seen[0] == 2 and seen[-1] == 1 and torch.get_num_threads() == 1
    finally:
        set_threads(before)


def test_bilinear_deep_edmd_is_deep_edmds_network_with_a_bilinear_operator(
    data: dict, tmp_path: Path
) -> None:
    """bilinear_training false: the same training as Deep EDMD (same network bit for bit), then
    [A B H] solving the normal equations of the bilinear regression on the lifted data; saved
    and loaded whole."""
    from harness.core.contracts import BilinearModel
    from learners.bilinear import bilinear_regression_rows
    from learners.bilinear_deep_edmd import BilinearDeepEDMD

    args = (data["train"], data["validation"], data["normalizer"])
    plain = small(DeepEDMD).fit(*args)
    model = small(BilinearDeepEDMD, ridge_prior="zero", bilinear_ridge=0.0, bilinear_training=False)
    model.fit(*args)
    np.testing.assert_array_equal(plain.params_.data, model.params_.data)
    assert isinstance(model, BilinearModel) and model.H_.shape == (2, 7, 7)
    rows = [
        bilinear_regression_rows(
            model.lift(e.states)[:-1],
            data["normalizer"].inputs(e.inputs)[:-1],
            model.lift(e.states)[1:],
            model.v0_,
            np.arange(7),
            "zero",
        )
        for e in data["train"]
    ]
    w, y = np.vstack([r[0] for r in rows]), np.vstack([r[1] for r in rows])
    theta = np.hstack([model.A_, model.B_, *(model.H_[j] for j in range(2))]).T
    assert np.linalg.norm(w.T @ (y - w @ theta)) / np.linalg.norm(w.T @ y) < 1e-6
    # predictions are the bilinear rollout read out by C z, and survive the model file
    episode = data["validation"][0]
    loaded = load_learner(model.save(tmp_path / "bilinear_deep.pt"))
    np.testing.assert_array_equal(loaded.H_, model.H_)
    np.testing.assert_allclose(
        loaded.predict(episode.states[0], episode.inputs[:-1]),
        model.predict(episode.states[0], episode.inputs[:-1]),
        rtol=0,
        atol=1e-9,
    )
    check_same_learner(loaded, model, "bilinear_deep.pt", "bilinear_deep_edmd")
    with pytest.raises(ValueError, match=r"learner\.refit_koopman_lstsq must be false"):
        BilinearDeepEDMD(refit_koopman_lstsq=True)


# -- bilinear Deep EDMD: trained through the bilinear term ----------------------------------------


def small_bilinear(**overrides):
    """A bilinear Deep EDMD as small and short as :func:`small`'s Deep EDMD."""
    from learners.bilinear_deep_edmd import BilinearDeepEDMD

    return small(BilinearDeepEDMD, **overrides)


@pytest.mark.parametrize(
    "overrides",
    [
        {"alpha": {"inf": 0.1, "encoder_l2": 0.01, "decoder_l2": 0.02}},
        {"lifted_includes_state": False, "random_layer": {"enabled": True, "std": 0.3}},
        {"stability": {"weight": 0.5, "radius": 0.9}},
    ],
    ids=["all_terms", "phi_only_random", "stability"],
)
def test_the_bilinear_step_gradients_equal_autograd_on_the_bilinear_loss(overrides) -> None:
    """Paper-sized networks, p = 12, a nonzero H: the hand-written adjoint through
    z+ = A z + B v + sum_j (v_j - v0_j) H_j z against autograd on the readable rollout (and the
    stability penalty's autograd gradient added on top)."""
    from learners.bilinear_deep_edmd import BilinearDeepEDMD, stability_penalty
    from learners.deep_edmd import BilinearTerm

    normalizer = MinMaxNormalizer.fit(drive_episodes(1, 5.0, first_seed=10))
    learner = BilinearDeepEDMD(**overrides)
    learner.normalizer_ = normalizer
    learner._build(3, 2)
    learner.params_.initialize(torch.Generator().manual_seed(0))
    params = learner.params_
    params.views()["koopman.H.weight"].normal_(0.0, 0.1, generator=torch.Generator().manual_seed(2))
    generator = torch.Generator().manual_seed(1)
    x = torch.rand(16, 13, 3, generator=generator)
    v = torch.rand(16, 12, 2, generator=generator)

    leaf = params.data.clone().requires_grad_()
    encoder, layer = params.layers("encoder", leaf), learner._step_layer(7)
    if layer is not None:
        encoder = [*encoder[:-1], layer, encoder[-1]]
    views = params.views(leaf)
    a, size = views["koopman.A.weight"], views["koopman.A.weight"].shape[0]
    h = views["koopman.H.weight"].view(2, size, size)
    v0 = torch.from_numpy(learner.v0_.astype(np.float32))
    terms = deep_edmd_loss_terms(
        encoder,
        params.layers("decoder", leaf),
        a,
        views["koopman.B.weight"],
        x,
        v,
        lifted_includes_state=learner.lifted_includes_state,
        bilinear=BilinearTerm(h, v0),
    )
    alpha, stability = learner.alpha, learner.stability
    loss = sum(w * terms[k] for k, w in alpha.data_terms().items())
    loss = loss + stability.weight * stability_penalty(a, h, v0, stability.radius)
    objective = (
        loss
        + alpha.encoder_l2 * leaf[params.span("encoder")].square().sum()
        + alpha.decoder_l2 * leaf[params.span("decoder")].square().sum()
    )
    (expected,) = torch.autograd.grad(objective, leaf)
    params.grad.zero_()
    assert learner._objective().train_step(x, v, 7) == pytest.approx(float(loss.detach()), rel=1e-5)
    assert float((params.grad - expected).norm() / expected.norm()) < 1e-5
    h_grad = params.views(params.grad)["koopman.H.weight"]
    assert float(h_grad.norm()) > 1e-3 * float(params.grad.norm())  # H is trained


def test_h_starts_at_zero_from_deep_edmds_initial_network_and_training_moves_it(
    data: dict,
) -> None:
    """H is the last tensor and starts at zero without drawing: every other initial weight is
    Deep EDMD's. Training through the bilinear term makes H nonzero; with bilinear_refit none
    the model is the trained A, B, H (predict rolls that operator out)."""
    from learners.bilinear import bilinear_rollout

    args = (data["train"], data["validation"], data["normalizer"])
    plain, bilinear = small(DeepEDMD), small_bilinear(bilinear_refit="none")
    for learner in (plain, bilinear):
        learner._build(3, 2)
        learner.params_.initialize(torch.Generator().manual_seed(0))
    h0 = bilinear.params_.views()["koopman.H.weight"]
    assert h0.shape == (2 * 7, 7) and not h0.any()
    np.testing.assert_array_equal(bilinear.params_.data[: len(plain.params_)], plain.params_.data)
    model = bilinear.fit(*args)
    trained = model.params_.views()
    assert np.abs(model.H_).max() > 1e-4
    np.testing.assert_array_equal(model.H_, trained["koopman.H.weight"].view(2, 7, 7).double())
    np.testing.assert_array_equal(model.A_, trained["koopman.A.weight"].double())
    np.testing.assert_array_equal(model.B_, trained["koopman.B.weight"].double())
    episode = data["validation"][0]
    inputs = episode.inputs[:50]
    z = bilinear_rollout(
        model.A_,
        model.B_,
        model.H_,
        model.lift(episode.states[0]),
        data["normalizer"].inputs(inputs),
        model.v0_,
    )
    expected = data["normalizer"].states_inverse(z @ model.C_.T)
    # float32 encoder: lift(x0) of one state and of predict's batch may round differently
    np.testing.assert_allclose(
        model.predict(episode.states[0], inputs)[1:], expected[1:], rtol=1e-5, atol=1e-6
    )
    # the refit replaces the trained operator, on the network trained through H
    refit = small_bilinear(bilinear_refit="lstsq").fit(*args)
    np.testing.assert_array_equal(refit.params_.data, model.params_.data)
    assert not np.array_equal(refit.H_, model.H_)


def test_the_stability_penalty_is_zero_when_stable_and_pushes_unstable_modes_in() -> None:
    """sum max(0, |lambda| - radius) over A and A + sum_j (c_j - v0_j) H_j at the input box's
    corners: zero for a contraction; for a mode outside the circle, positive, and gradient
    steps on it bring every eigenvalue back inside."""
    from learners.bilinear_deep_edmd import stability_penalty

    generator = torch.Generator().manual_seed(0)
    v0 = torch.tensor([0.45, 0.1])
    a = 0.5 * torch.eye(5) + 0.05 * torch.randn(5, 5, generator=generator)
    h = 0.05 * torch.randn(2, 5, 5, generator=generator)
    assert float(stability_penalty(a, h, v0, 1.0)) == 0.0
    unstable = a.clone()
    unstable[0, 0] = 1.05
    assert float(stability_penalty(unstable, None, v0, 1.0)) > 0.0  # A alone
    # only the corners' modes are outside at radius 1 when H alone pushes them out
    assert float(stability_penalty(a, 20 * h, v0, 1.0)) > 0.0
    a_leaf, h_leaf = unstable.clone().requires_grad_(), h.clone().requires_grad_()
    values = []
    for _ in range(50):
        penalty = stability_penalty(a_leaf, h_leaf, v0, 1.0)
        values.append(float(penalty.detach()))
        grad_a, grad_h = torch.autograd.grad(penalty, [a_leaf, h_leaf])
        with torch.no_grad():
            a_leaf -= 0.01 * grad_a
            h_leaf -= 0.01 * grad_h
    assert values[0] > 0.05 and values[-1] == 0.0
    assert all(later <= earlier for earlier, later in itertools.pairwise(values))


def test_a_stability_weight_pulls_the_trained_operator_inside_the_circle(data: dict) -> None:
    """The same short training with and without the penalty (radius 0.2, well inside the
    initial weights' spectrum, so that it binds): the penalised model's eigenvalues over A and
    the corners exceed the radius by less, and validation reports the term."""
    from learners.bilinear_deep_edmd import stability_penalty

    args = (data["train"], data["validation"], data["normalizer"])

    def worst(model) -> float:
        views = model.params_.views()
        a = views["koopman.A.weight"]
        h = views["koopman.H.weight"].view(2, *a.shape)
        v0 = torch.from_numpy(model.v0_.astype(np.float32))
        return float(stability_penalty(a, h, v0, 0.2))

    free = small_bilinear(bilinear_refit="none", training={"lr": 1e-2}).fit(*args)
    held = small_bilinear(
        bilinear_refit="none", training={"lr": 1e-2}, stability={"weight": 1.0, "radius": 0.2}
    ).fit(*args)
    assert worst(held) < 0.5 * worst(free)
    assert "stability" in held.history_.validation[-1]
    assert "stability" not in free.history_.validation[-1]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"bilinear_refit": "qr"}, r"learner\.bilinear_refit must be one of lstsq, none"),
        ({"bilinear_training": "yes"}, r"learner\.bilinear_training must be true or false"),
        ({"stability": {"weight": -1.0}}, r"learner\.stability\.weight must be >= 0"),
        ({"stability": {"radius": 0.0}}, r"learner\.stability\.radius must be > 0"),
        ({"stability": {"wieght": 1.0}}, r"learner\.stability\.wieght is not a key"),
        ({"refit_koopman_lstsq": True}, r"learner\.refit_koopman_lstsq must be false"),
    ],
)
def test_bad_bilinear_deep_edmd_settings_fail_in_one_line(overrides, message: str) -> None:
    from learners.bilinear_deep_edmd import BilinearDeepEDMD

    with pytest.raises(ValueError, match=message) as info:
        BilinearDeepEDMD(**overrides)
    assert "\n" not in str(info.value)


def test_a_bilinear_deep_edmd_trained_through_h_saves_and_loads_whole(
    data: dict, tmp_path: Path
) -> None:
    model = small_bilinear(bilinear_refit="none").fit(
        data["train"], data["validation"], data["normalizer"]
    )
    loaded = load_learner(model.save(tmp_path / "through.pt"))
    assert loaded.hyperparameters == model.hyperparameters
    np.testing.assert_array_equal(loaded.params_.data, model.params_.data)
    np.testing.assert_array_equal(loaded.H_, model.H_)
    episode = data["validation"][0]
    np.testing.assert_array_equal(
        loaded.predict(episode.states[0], episode.inputs[:100]),
        model.predict(episode.states[0], episode.inputs[:100]),
    )


def test_a_model_file_from_before_bilinear_training_loads_as_trained_then() -> None:
    """Files written before the key existed hold Deep EDMD's network and the refit."""
    from learners.bilinear_deep_edmd import BilinearDeepEDMD

    old = {
        k: v
        for k, v in BilinearDeepEDMD(bilinear_training=False).hyperparameters.items()
        if k not in ("bilinear_training", "bilinear_refit", "stability")
    }
    learner = BilinearDeepEDMD.from_hyperparameters(old)
    assert not learner.bilinear_training and learner.bilinear_refit == "lstsq"
    assert BilinearDeepEDMD().bilinear_training  # a new model trains through H


# -- ours: selection by rollout, schedules, per-state weights, the scaled residual --------------

RECIPE = {
    "selection": "rollout",
    "lr_schedule": "cosine",
    "warmup_steps": 4,
    "lr_final": 1e-4,
    "grad_clip_norm": 0.5,
    "curriculum": [[3, 7], [5, 6]],
    "initial_state_noise": 0.01,
    "average_decay": 0.9,
}


@pytest.mark.parametrize("cls", [DNN, DeepEDMD])
def test_rollout_selection_keeps_the_checkpoint_that_predicts_the_validation_drives_best(
    cls, data: dict
) -> None:
    from harness.evaluation.prediction import open_loop, rmse

    learner = small(cls, training={**RECIPE, "lr": 3e-2}, loss_scales=[0.2, 0.1, 0.05])
    learner.fit(data["train"], data["validation"], data["normalizer"])
    scores = [v["rollout_score"] for v in learner.history_.validation]
    assert len(scores) == 3 and len(set(scores)) > 1  # every 10 of 30 steps, and it moved
    curriculum = learner.training.curriculum_steps  # its checkpoints are no candidates
    scores = [s for s, t in zip(scores, learner.history_.step, strict=True) if t > curriculum]
    # the score of the fitted model, recomputed directly as the prediction tables compute it
    scales = np.array(RECIPE_SCALES)
    direct = [
        np.array(list(rmse(open_loop(learner, e), e.states).values())) / scales
        for e in data["validation"]
    ]
    assert float(np.mean(direct)) == pytest.approx(min(scores), rel=1e-6)
    scorer = learner._rollout_scorer(data["train"], data["validation"])
    assert scorer()["rollout_score"] == pytest.approx(min(scores), rel=1e-6)


RECIPE_SCALES = TrainingConfig().rollout_scales


def _planted_training(
    scores: list[float], validated: bool = True, **config
) -> tuple[list[float], float, Any]:
    """Train a one-weight model that Adam moves by lr every step, with the rollout score of
    each evaluation planted: (the weight at each evaluation, the weight kept, the history).
    ``validated`` False: no validation data (nothing is evaluated)."""
    from learners import training as loop
    from learners.nets import FlatParameters, LayerSpec

    params = FlatParameters([LayerSpec("w", 1, 1, "linear", bias=False)])
    at_evaluation: list[float] = []

    class Objective:
        def __init__(self) -> None:
            self.params = params

        def train_step(self, x: torch.Tensor, v: torch.Tensor, step: int) -> float:
            params.grad.fill_(1.0)
            return 1.0

        def validate(self, x: torch.Tensor, v: torch.Tensor) -> dict[str, float]:
            at_evaluation.append(float(params.data[0]))
            return {"loss": 1.0 / len(at_evaluation)}  # falls at every evaluation

    windows = WindowData(torch.rand(40, 1), torch.rand(40, 1), np.array([0]), np.array([40]))
    planted = iter(scores)
    settings = {"batch_size": 2, "lr": 0.1, "eval_every_steps": 1, "progress": False, **config}
    history = loop.train(
        "planted",
        Objective(),
        windows,
        windows if validated else None,
        3,
        TrainingConfig(**settings),
        fingerprint={},
        rollout_score=lambda: {"rollout_score": next(planted)},
    )
    return at_evaluation, float(params.data[0]), history


def test_the_kept_checkpoint_is_the_best_by_rollout_not_by_window_loss() -> None:
    """A planted sequence: rollout scores 5, 3, 4, 1, 2, 2.5 at the six evaluations while the
    window loss falls at every one; each selection keeps its own best checkpoint."""
    for selection, kept in (("rollout", 3), ("window_loss", 5)):
        at_evaluation, weight, history = _planted_training(
            [5.0, 3.0, 4.0, 1.0, 2.0, 2.5], max_steps=6, patience=10, selection=selection
        )
        assert len(at_evaluation) == 6 and len(set(at_evaluation)) == 6
        assert weight == pytest.approx(at_evaluation[kept])
        assert all("loss" in v for v in history.validation)  # the window loss is kept either way
        assert ("rollout_score" in history.validation[0]) == (selection == "rollout")


def test_no_checkpoint_of_the_curriculum_is_kept_and_patience_starts_after_it() -> None:
    """Planted rollout scores 1, 9, 9, 5, 4, 6, 6 at steps 1..7 with a 3-step curriculum: the
    excellent score at step 1 (short windows) is not kept, patience (2) counts from step 4, so
    training stops at step 7 and keeps step 5's parameters."""
    at_evaluation, weight, history = _planted_training(
        [1.0, 9.0, 9.0, 5.0, 4.0, 6.0, 6.0, 6.0, 6.0, 6.0],
        max_steps=10,
        patience=2,
        selection="rollout",
        curriculum=[[2, 3]],
    )
    assert history.stopped == "early_stopping" and history.step[-1] == 7
    assert weight == pytest.approx(at_evaluation[4])  # step 5, not step 1


def test_the_averaged_weights_are_what_is_validated_kept_and_returned() -> None:
    """With ``average_decay`` d, evaluation s sees a_s = d a_(s-1) + (1 - d) w_s from a_0 = w_0
    = 0, where w_s are the weights of the same run without the average (Adam steps the raw
    weights, untouched by the evaluations), and the checkpoint kept is the best average."""
    scores = [5.0, 3.0, 4.0, 1.0, 2.0, 2.5]
    raw, _, _ = _planted_training(scores, max_steps=6, patience=10, selection="rollout")
    averaged, kept, _ = _planted_training(
        scores, max_steps=6, patience=10, selection="rollout", average_decay=0.75
    )
    expected, a = [], 0.0
    for w in raw:
        a = 0.75 * a + 0.25 * w
        expected.append(a)
    assert averaged == pytest.approx(expected, rel=1e-6)
    assert abs(averaged[-1]) < abs(raw[-1])  # the average lags the moving weights
    assert kept == pytest.approx(expected[3], rel=1e-6)  # the best score, 1.0, at step 4


def test_without_validation_the_average_is_the_model_returned() -> None:
    """Adam moves the planted weight by exactly -lr a step (a constant gradient), so w_s = -0.1 s;
    with nothing to validate on, the model returned is the average of w_0..w_5, not w_5."""
    _, last, _ = _planted_training([], max_steps=5, validated=False)
    _, returned, _ = _planted_training([], max_steps=5, validated=False, average_decay=0.5)
    a = 0.0
    for step in range(1, 6):
        a = 0.5 * a + 0.5 * (-0.1 * step)
    assert last == pytest.approx(-0.5, rel=1e-6)
    assert returned == pytest.approx(a, rel=1e-6)


def test_schedules_are_functions_of_the_step() -> None:
    config = TrainingConfig(
        lr=1e-3,
        lr_schedule="cosine",
        warmup_steps=10,
        lr_final=1e-5,
        max_steps=110,
        curriculum=[[10, 5], [50, 20]],
    )
    assert config.lr_at(0) == pytest.approx(1e-4) and config.lr_at(9) == pytest.approx(1e-3)
    assert config.lr_at(60) == pytest.approx(1e-5 + 0.5 * (1e-3 - 1e-5))  # half-way: cos = 0
    assert config.lr_at(110) == pytest.approx(1e-5)
    assert [config.horizon_at(s, 200) for s in (0, 4, 5, 24, 25, 1000)] == [
        10,
        10,
        50,
        50,
        200,
        200,
    ]
    assert TrainingConfig(lr=2e-4).lr_at(12345) == 2e-4  # the paper's constant rate


def test_the_progress_bar_counts_each_batch_at_its_windows_cost_so_its_estimate_holds() -> None:
    """Batches of the curriculum's short windows cost less: the bar counts window steps plus a
    batch's fixed cost, summed phase by phase, so a resumed run starts where the cost stood."""
    from learners.training import BATCH_FIXED_STEPS as F

    config = TrainingConfig(max_steps=110, curriculum=[[10, 5], [50, 20]])
    assert config.work_until(0, 200) == 0
    assert config.work_until(3, 200) == 3 * (10 + F)
    assert config.work_until(25, 200) == 5 * (10 + F) + 20 * (50 + F)
    assert config.work_until(110, 200) == 5 * (10 + F) + 20 * (50 + F) + 85 * (200 + F)
    assert TrainingConfig(max_steps=7).work_until(7, 41) == 7 * (41 + F)  # no curriculum


@pytest.mark.parametrize("cls", [DNN, DeepEDMD])
def test_a_killed_run_with_every_schedule_resumes_to_the_uninterrupted_result(
    cls, data: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    args = (data["train"], data["validation"], data["normalizer"])
    whole = small(cls, tmp_path / "whole", training=RECIPE).fit(*args)
    adam_step, calls = torch.optim.Adam.step, {"n": 0}

    def dies_at_step_13(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 13:  # inside the curriculum's second phase
            raise KeyboardInterrupt("killed")
        return adam_step(self, *a, **k)

    with monkeypatch.context() as patch:
        patch.setattr(torch.optim.Adam, "step", dies_at_step_13)
        with pytest.raises(KeyboardInterrupt):
            small(cls, tmp_path / "killed", training=RECIPE).fit(*args)
    resumed = small(cls, tmp_path / "killed", training=RECIPE).fit(*args)
    np.testing.assert_array_equal(resumed.params_.data, whole.params_.data)
    assert resumed.history_ == whole.history_


def test_the_scaled_residual_dnn_starts_as_the_state_held_and_linearizes_exactly(
    data: dict,
) -> None:
    learner = small(DNN, residual=True, training={"max_steps": 1, "lr": 1e-9})
    learner.fit(data["train"], data["validation"], data["normalizer"])
    x0, inputs = data["validation"][0].states[0], data["validation"][0].inputs[:20]
    np.testing.assert_allclose(learner.predict(x0, inputs), np.tile(x0, (21, 1)), atol=1e-4)
    normalize = data["normalizer"].states
    steps = np.concatenate([np.diff(normalize(e.states), axis=0) for e in data["train"]])
    np.testing.assert_allclose(learner.increment_scale_, steps.std(0))  # D: increments' std
    trained = small(DNN, residual=True, training={"max_steps": 40, "lr": 1e-2})
    trained.fit(data["train"], data["validation"], data["normalizer"])
    rng = np.random.default_rng(0)
    z, v = rng.uniform(0.2, 0.8, (5, 3)), rng.uniform(0.2, 0.8, (5, 2))
    A, B, d = trained.linearize(z, v)
    np.testing.assert_allclose(
        (A @ z[..., None])[..., 0] + (B @ v[..., None])[..., 0] + d, trained.step(z, v), atol=1e-12
    )
    eps = 1e-6
    for j in range(3):
        dz = np.zeros(3)
        dz[j] = eps
        fd = (trained.step(z + dz, v) - trained.step(z - dz, v)) / (2 * eps)
        np.testing.assert_allclose(A[:, :, j], fd, atol=1e-6)


@pytest.mark.parametrize(
    ("training", "message"),
    [
        ({"selection": "best"}, "training.selection"),
        ({"curriculum": [[10]]}, "training.curriculum"),
        ({"lr_schedule": "cosine", "max_steps": None, "max_epochs": 3}, "training.max_steps"),
        ({"grad_clip_norm": -1.0}, "training.grad_clip_norm"),
        ({"rollout_scales": "vx"}, "training.rollout_scales"),
        ({"average_decay": 1.0}, "training.average_decay"),
        ({"average_decay": "yes"}, "training.average_decay"),
    ],
)
def test_bad_training_recipe_settings_fail_in_one_line(training: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message) as info:
        TrainingConfig(**training)
    assert "\n" not in str(info.value)


def test_loss_scales_of_the_wrong_length_fail_in_one_line(data: dict) -> None:
    learner = small(DNN, loss_scales=[0.2, 0.1])
    with pytest.raises(ValueError, match=r"learner\.loss_scales has 2 entries") as info:
        learner.fit(data["train"], data["validation"], data["normalizer"])
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("cls", ["deep_edmd", "bilinear_deep_edmd"])
@pytest.mark.parametrize("lifted_includes_state", [True, False])
def test_a_trained_deep_edmd_lifts_for_control_as_its_network_does(
    data: dict, tmp_path: Path, cls, lifted_includes_state: bool
) -> None:
    """``lift`` (what DE-MPC calls every step) runs the trained encoder in float64 NumPy; it is
    the network's own lift (torch, float32) to float32's precision, after the fit and after a
    load, for one state and a batch."""
    from learners.bilinear_deep_edmd import BilinearDeepEDMD

    kind = DeepEDMD if cls == "deep_edmd" else BilinearDeepEDMD
    learner = small(kind, lifted_includes_state=lifted_includes_state)
    learner.fit(data["train"], data["validation"], data["normalizer"])
    loaded = load_learner(learner.save(tmp_path / "model.pt"))
    states = data["validation"][0].states[::50]
    with torch.inference_mode():
        x_n = torch.from_numpy(learner.normalizer_.states(states).astype(np.float32))
        by_network = learner._lift_n(x_n).double().numpy()
    for model in (learner, loaded):
        lifted = model.lift(states)
        assert lifted.dtype == np.float64 and lifted.shape == by_network.shape
        np.testing.assert_allclose(lifted, by_network, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(model.lift(states[3]), lifted[3], rtol=1e-12)


# -- the read-out DE-MPC uses: checkpoints whose C z disagrees with the decoder rank last ---------


def test_read_outs_agree_when_c_z_moves_each_inputs_strongest_state_the_decoders_way() -> None:
    from learners.deep_edmd import readouts_agree

    decoder = np.array([[0.01, 0.03, 0.12], [0.006, -0.006, 0.0]])  # steering: r; pedal: vx
    assert readouts_agree({"decoder": decoder, "linear": decoder * 2.0})
    weaker_flipped = decoder * np.array([[1.0, -1.0, 1.0], [1.0, 1.0, 1.0]])
    assert readouts_agree({"decoder": decoder, "linear": weaker_flipped})
    pedal_brakes = decoder * np.array([[1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]])  # seed 1's C z
    assert not readouts_agree({"decoder": decoder, "linear": pedal_brakes})


def test_the_c_z_input_effect_is_its_closed_form(data: dict) -> None:
    """Held inputs ±δ for T steps move x = C z by 2δ C (I + A + ... + A^{T-1}) B e_j,
    whatever the start: the linear effects of ``input_effects`` are exactly that."""
    from learners.deep_edmd import _EFFECT_STEP, _effect_starts

    learner = small(DeepEDMD).fit(data["train"], data["validation"], data["normalizer"])
    starts, inputs = _effect_starts(data["validation"], learner.normalizer_)
    effects = learner.input_effects(starts, inputs)
    A, B, C = learner.A_, learner.B_, learner.C_
    powers = sum(np.linalg.matrix_power(A, k) for k in range(inputs.shape[1]))
    expected = (2 * _EFFECT_STEP * C @ powers @ B).T  # (m, n)
    np.testing.assert_allclose(effects["linear"], expected, rtol=1e-5, atol=1e-7)
    assert effects["decoder"].shape == expected.shape
    assert learner.prediction_output == "decoder"  # restored after the check


@pytest.mark.parametrize("agree", [True, False])
def test_every_checkpoint_records_whether_its_read_outs_agree_beside_an_unchanged_score(
    data: dict, monkeypatch, agree: bool
) -> None:
    import learners.deep_edmd as deep_edmd

    learner = small(DeepEDMD, training={"selection": "rollout"})
    learner.fit(data["train"], data["validation"], data["normalizer"])
    assert all("readouts_agree" in v for v in learner.history_.validation)
    plain = TrainedLearner._rollout_scorer(learner, data["train"], data["validation"])()
    monkeypatch.setattr(deep_edmd, "readouts_agree", lambda effects: agree)
    scored = learner._rollout_scorer(data["train"], data["validation"])()
    assert scored["rollout_score"] == plain["rollout_score"]
    assert scored["readouts_agree"] == float(agree)


def test_the_readout_loss_is_the_state_part_of_the_lift_error_and_needs_the_state_in_z() -> None:
    """L_readout = 1/p sum ||x_i - C K^[i] z_0||^2 with C = [I 0]: the first n coordinates of
    L_xo's error; a lift without the state has no C to train."""
    learner = DeepEDMD(lifted_dim=4, encoder_hidden=[8], decoder_hidden=[8], horizon=5)
    learner._build(3, 2)
    learner.params_.initialize(torch.Generator().manual_seed(0))
    generator = torch.Generator().manual_seed(1)
    x, v = torch.rand(6, 6, 3, generator=generator), torch.rand(6, 5, 2, generator=generator)
    params, views = learner.params_, learner.params_.views()
    a, b = views["koopman.A.weight"], views["koopman.B.weight"]
    terms = deep_edmd_loss_terms(
        params.layers("encoder"), params.layers("decoder"), a, b, x, v, lifted_includes_state=True
    )
    z = torch.cat([x, mlp_apply(params.layers("encoder"), x)], -1)
    state, predicted = x[:, 1:], z[:, 0]
    expected = 0.0
    for i in range(5):
        predicted = predicted @ a.t() + v[:, i] @ b.t()
        expected += ((state[:, i] - predicted[:, :3]) ** 2).sum(-1).mean() / 5
    assert float(terms["readout"]) == pytest.approx(float(expected), rel=1e-5)
    with pytest.raises(ValueError, match="lifted_includes_state"):
        DeepEDMD(lifted_includes_state=False, alpha={"readout": 1.0})
