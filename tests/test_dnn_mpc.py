"""The DNN as the model of the time-varying DE-MPC: its step is the trained network, its
Jacobians are the network's (finite differences and ``torch.func`` agree), and the controller
closes the loop on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch.func import jacrev, vmap

from controllers import DEMPC, DEMPCConfig
from controllers.time_varying_qp import TimeVaryingQP
from harness.core.contracts import LinearizableModel
from harness.core.episode import MinMaxNormalizer
from harness.evaluation.tracking import track
from harness.recorder import Recorder
from harness.tasks.closed_loops import not_lifted_linear
from learners import DNN
from learners.model_file import load as load_learner
from learners.nets import Dense, NumpyMLP, mlp_apply
from tests.toy_models import OwnModelPlant
from tests.toydata import drive_episodes


@pytest.fixture(scope="module", params=[False, True], ids=["direct", "residual"])
def dnn(request: pytest.FixtureRequest) -> DNN:
    """A small DNN fitted for 30 steps (residual: 400) on 40 s of driving (about a second)."""
    episodes = drive_episodes(3, 20.0, first_seed=10)
    train, validation = episodes[:2], episodes[2:]
    training = {"max_steps": 30, "batch_size": 16, "lr": 3e-3, "progress": False}
    if request.param:  # the residual starts as the state held: it needs longer to steer
        training = {**training, "max_steps": 400, "lr": 1e-2}
    learner = DNN(hidden=[16, 32, 16], horizon=8, residual=request.param, training=training)
    return learner.fit(train, validation, MinMaxNormalizer.fit(train))


def points(dnn: DNN, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` (z, v) pairs inside the normalized data box."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0.1, 0.9, size=(count, 3)), rng.uniform(0.1, 0.9, size=(count, 2))


def test_a_fitted_dnn_is_a_linearizable_model_in_the_normalized_state(dnn: DNN) -> None:
    assert isinstance(dnn, LinearizableModel) and not_lifted_linear(dnn) is None
    assert not isinstance(DNN(), LinearizableModel)  # unfitted: nothing to linearise
    assert "not a model a controller reads" in str(not_lifted_linear(DNN()))
    np.testing.assert_array_equal(dnn.C_, np.eye(3))
    x = np.array([12.0, 0.3, -0.1])
    np.testing.assert_allclose(dnn.lift(x), dnn.normalizer_.states(x))


def test_the_step_is_the_trained_network_one_prediction_step(dnn: DNN) -> None:
    episode = drive_episodes(3, 20.0, first_seed=10)[2]
    x, u = episode.states[500:520], episode.inputs[500:520]
    predicted = dnn.predict(x, u[:, None])[:, 1]  # float32 torch, one step from each x
    stepped = dnn.normalizer_.states_inverse(dnn.step(dnn.lift(x), dnn.normalizer_.inputs(u)))
    np.testing.assert_allclose(stepped, predicted, rtol=1e-5, atol=1e-5)
    z, v = points(dnn, 4)
    np.testing.assert_allclose(dnn.step(z, v)[2], dnn.step(z[2], v[2]), atol=1e-14)


def test_the_jacobians_equal_finite_differences_and_torch_func(dnn: DNN) -> None:
    z, v = points(dnn, 6)
    A, B, d = dnn.linearize(z, v)
    assert A.shape == (6, 3, 3) and B.shape == (6, 3, 2) and d.shape == (6, 3)
    h = 1e-6  # a ReLU network is piecewise affine: central differences are exact off the kinks
    for k in range(len(z)):
        for i in range(3):
            e = np.eye(3)[i] * h
            column = (dnn.step(z[k] + e, v[k]) - dnn.step(z[k] - e, v[k])) / (2 * h)
            np.testing.assert_allclose(A[k][:, i], column, atol=1e-7)
        for j in range(2):
            e = np.eye(2)[j] * h
            column = (dnn.step(z[k], v[k] + e) - dnn.step(z[k], v[k] - e)) / (2 * h)
            np.testing.assert_allclose(B[k][:, j], column, atol=1e-7)
    # The specification: torch.func's reverse-mode Jacobians of the network, batched.
    layers = [
        Dense(layer.weight.double(), layer.bias.double(), layer.activation)
        for layer in dnn.params_.layers("model")
        if layer.bias is not None
    ]

    def step(zk: torch.Tensor, vk: torch.Tensor) -> torch.Tensor:
        out = mlp_apply(layers, torch.cat([zk, vk]))
        return zk + torch.from_numpy(dnn.increment_scale_) * out if dnn.residual else out

    jz, jv = vmap(jacrev(step, argnums=(0, 1)))(torch.from_numpy(z), torch.from_numpy(v))
    np.testing.assert_allclose(A, jz.numpy(), atol=1e-12)
    np.testing.assert_allclose(B, jv.numpy(), atol=1e-12)
    # d makes the linearisation exact at its point.
    np.testing.assert_allclose(
        np.einsum("kab,kb->ka", A, z) + np.einsum("kaj,kj->ka", B, v) + d,
        dnn.step(z, v),
        atol=1e-12,
    )


def test_a_loaded_dnn_linearises_as_the_fitted_one(dnn: DNN, tmp_path: Path) -> None:
    loaded = load_learner(dnn.save(tmp_path / "dnn.pt"))
    assert isinstance(loaded, DNN) and isinstance(loaded, LinearizableModel)
    z, v = points(dnn, 3)
    for got, expected in zip(loaded.linearize(z, v), dnn.linearize(z, v), strict=True):
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("horizons", [{"Np": 10, "Nc": 7}, {"Np": 30, "Nc": 20}])
def test_de_mpc_tracks_a_reference_the_dnn_can_drive_on_the_dnn_itself(
    dnn: DNN, horizons: dict[str, int]
) -> None:
    """On its own model as the plant, a reference the DNN itself drives (a steering sweep from
    a state of the data) is tracked to near zero error through the linearisation."""
    episode = drive_episodes(3, 20.0, first_seed=10)[2]
    x0, u0 = episode.states[1500], episode.inputs[1500]
    plant = OwnModelPlant(dnn, x0)
    steer = u0[0] + 30.0 * np.sin(2 * np.pi * 0.5 * np.arange(120) * plant.dt)
    reference = np.array([x0, *(plant.step(np.array([s, u0[1]])) for s in steer[:-1])])
    # As controller=dnn_mpc: two linearisations a step, along the plan.
    controller = DEMPC(dnn, DEMPCConfig(**horizons, sqp_iterations=2, linearization="predicted"))
    assert isinstance(controller.qp, TimeVaryingQP)
    controller.reset(reference, u_prev=u0)  # from the input that drove the reference
    states, inputs = [plant.reset()], []
    for k in range(len(reference) - 1):
        u, info = controller.act(states[-1], k * plant.dt)
        assert not info.fallback and np.all(np.isfinite(u))
        assert np.all(np.isfinite(info.predicted_states))
        inputs.append(u)
        states.append(plant.step(u))
    assert np.ptp(np.array(inputs)[:, 0]) > 10.0  # it steers
    rmse = np.sqrt(np.mean((np.array(states) - reference) ** 2, axis=0))
    assert np.all(rmse < 0.02 * np.ptp(reference, axis=0)), (rmse, np.ptp(reference, axis=0))
    # Through the harness's tracking loop (from u = 0, one linearisation per step): its metrics.
    metrics, _ = track(
        plant, DEMPC(dnn, DEMPCConfig(**horizons)), reference, name="own", recorder=Recorder()
    )
    assert metrics["solver_failures"] == 0 and metrics["steps"] == len(reference) - 1
    assert all(np.isfinite(value) for value in metrics["rmse"].values())


@pytest.mark.parametrize("activation", ["relu", "sigmoid", "linear"])
def test_numpy_mlp_is_the_torch_network_and_its_jacobian_is_torch_funcs(activation: str) -> None:
    generator = torch.Generator().manual_seed(0)
    widths = [5, 8, 6, 3]
    layers = [
        Dense(
            torch.randn(widths[i + 1], widths[i], generator=generator, dtype=torch.float64),
            torch.randn(widths[i + 1], generator=generator, dtype=torch.float64),
            activation if i < 2 else "linear",
        )
        for i in range(3)
    ]
    network = NumpyMLP(layers, 3)
    rng = np.random.default_rng(1)
    z, v = rng.normal(size=(4, 3)), rng.normal(size=(4, 2))
    expected = mlp_apply(layers, torch.from_numpy(np.hstack([z, v]))).numpy()
    np.testing.assert_allclose(network(z, v), expected, atol=1e-12)
    out, jz, jv = network.jacobian(z, v)
    np.testing.assert_allclose(out, expected, atol=1e-12)

    def forward(zk: torch.Tensor, vk: torch.Tensor) -> torch.Tensor:
        return mlp_apply(layers, torch.cat([zk, vk]))

    tz, tv = vmap(jacrev(forward, argnums=(0, 1)))(torch.from_numpy(z), torch.from_numpy(v))
    np.testing.assert_allclose(jz, tz.numpy(), atol=1e-12)
    np.testing.assert_allclose(jv, tv.numpy(), atol=1e-12)
