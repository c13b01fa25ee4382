"""The paper's DNN baseline: an MLP M(x, u) -> next state, trained on multi-step rollouts.

The paper's network is [n + m, 32, 64, 128, 128, 64, 32, n] (ReLU hidden layers, linear
output) on normalized coordinates (``learner=dnn_paper``); ``learner=dnn`` uses [n + m, 128, 128,
128, n] (ours): with our training the narrow, deep one predicts whole drives 3-6x worse
(docs/findings/training_recipe.md, *The network's shape*).

Loss over windows of p = ``horizon`` steps (the paper's eq. for L_mlp, batch mean)::

    x_hat_0 = x_0,   x_hat_i = M(x_hat_{i-1}, v_{i-1})          (x_hat_{i-1} + M(...) if residual)
    L_mlp = b_1/p sum_{i=1..p} ||x_i - x_hat_i||^2 + b_2/p sum_i ||x_i - x_hat_i||_inf
            + b_3 ||theta_M||^2

The paper's indices (x_{i+1} - M(x_hat_i)) are read as this rollout: each prediction is fed
back, and every predicted step is compared with the measured state. :func:`dnn_loss_terms` is the
definition in plain autograd; training uses :func:`dnn_step`, the same loss with a hand-written
back-propagation through time (tests check they agree).

Fitted, the DNN is a :class:`~harness.core.contracts.LinearizableModel` in the normalized state
(z = x_norm, C_ = I, step = M or z + M): the time-varying DE-MPC linearises it along its plan,
A_k = ∂step/∂z, B_k = ∂step/∂v at every point of the horizon at once (``controller=dnn_mpc``,
or any DE-MPC config). A ReLU network is piecewise affine, so each linearisation is exact in
the region of its point. The controller reads a float64 NumPy copy of the network
(:class:`~learners.nets.NumpyMLP`), made after training or loading.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

import numpy as np
import torch

from harness.core.checks import boolean, integer, non_negative
from harness.core.contracts import Dynamics
from harness.core.episode import Episode
from learners.base import Shape
from learners.nets import Dense, LayerSpec, NumpyMLP, mlp_apply, mlp_forward, mlp_specs
from learners.settings import block, settle
from learners.trained import TrainedLearner, settle_trained
from learners.training import RandomLayerConfig, TrainingConfig, batch_mean_terms

__all__ = ["DNN", "DNNConfig", "DNNLossWeights", "dnn_loss_terms", "dnn_step"]


@dataclass(frozen=True)
class DNNLossWeights:
    """beta_1 .. beta_3 of L_mlp (defaults: the paper's Table of hyperparameters); the schema of
    ``learner.beta``."""

    prediction: float = 1.0
    inf: float = 1e-9
    l2: float = 1e-9

    def __post_init__(self) -> None:
        for f in fields(self):
            non_negative(f"learner.beta.{f.name}", getattr(self, f.name))


def dnn_loss_terms(
    layers: Sequence[Dense],
    x: torch.Tensor,
    v: torch.Tensor,
    *,
    residual: bool,
    increment_scale: torch.Tensor | None = None,
    state_weights: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """The data terms of L_mlp for windows x (B, p+1, n), v (B, p, m): batch means, autograd.

    ``increment_scale`` D (n,): the residual step is x_hat + D * M (ours; None: D = 1).
    ``state_weights`` w (n,): the squared error is sum_s w_s err_s^2 (ours; None: w = 1).
    """
    x_hat, sq, peak = x[:, 0], [], []
    for i in range(v.shape[1]):
        step = mlp_apply(layers, torch.cat([x_hat, v[:, i]], -1))
        if residual and increment_scale is not None:
            step = step * increment_scale
        x_hat = x_hat + step if residual else step
        err = x[:, i + 1] - x_hat
        sq.append(
            (err**2 * state_weights).sum(-1) if state_weights is not None else (err**2).sum(-1)
        )
        peak.append(err.abs().amax(-1))
    return {
        "prediction": torch.stack(sq, 1).mean(1).mean(),
        "inf": torch.stack(peak, 1).mean(1).mean(),
    }


def dnn_step(
    layers: Sequence[Dense],
    x: torch.Tensor,
    v: torch.Tensor,
    weights: DNNLossWeights,
    *,
    residual: bool,
    increment_scale: torch.Tensor | None = None,
    state_weights: torch.Tensor | None = None,
) -> float:
    """b_1 L_pred + b_2 L_inf, its gradient ADDED into the layers' grad views (BPTT by hand).

    ``increment_scale`` and ``state_weights`` as in :func:`dnn_loss_terms`.

    The same loss as :func:`dnn_loss_terms`, computed for speed: the input half of the first
    layer (W_u v_i + b for every step) is one matmul; each step's activations are written into
    time-major buffers; the backward pass through time only propagates d loss / d x_hat and
    stores each layer's pre-activation gradients, so every weight gradient is one matmul over
    all p steps at the end.
    """
    batch, p, n = x.shape[0], v.shape[1], x.shape[2]
    m = v.shape[2]
    x = x.transpose(0, 1)  # (p+1, B, n), time-major
    first = layers[0]
    w_x, w_u = first.weight[:, :n], first.weight[:, n:]
    v_rows = v.transpose(0, 1).reshape(-1, m)
    drive = torch.addmm(first.bias, v_rows, w_u.t()).view(p, batch, -1)  # W_u v_i + b
    acts = [torch.empty(p, batch, layer.weight.shape[0]) for layer in layers]
    fed = torch.empty(p, batch, n)  # x_hat fed to step i
    x_hat = x[0]
    for i in range(p):
        fed[i] = x_hat
        a = torch.addmm(drive[i], x_hat, w_x.t(), out=acts[0][i])
        _activate_(a, first.activation)
        for layer, out in zip(layers[1:], acts[1:], strict=True):
            a = torch.addmm(layer.bias, a, layer.weight.t(), out=out[i])
            _activate_(a, layer.activation)
        if residual:
            x_hat = x_hat + (a * increment_scale if increment_scale is not None else a)
        else:
            x_hat = a
    err = x[1:] - torch.cat([fed[1:], x_hat.unsqueeze(0)])  # predictions x_hat_1 .. x_hat_p
    c_sq, c_inf = weights.prediction / (batch * p), weights.inf / (batch * p)
    peak, where = err.abs().max(-1)
    weighted = err * state_weights if state_weights is not None else err
    loss = c_sq * (err * weighted).sum() + c_inf * peak.sum()
    grad_err = weighted * (-2.0 * c_sq)  # d loss / d x_hat_{i+1}
    where = where.unsqueeze(-1)
    grad_err.scatter_add_(-1, where, -c_inf * torch.sign(err.gather(-1, where)))
    pre = [torch.empty_like(a) for a in acts]  # d loss / d pre-activation, per layer and step
    carry = torch.zeros(batch, n)
    for i in range(p - 1, -1, -1):
        g = grad_err[i] + carry  # total d loss / d x_hat_{i+1}
        top = g
        if residual and increment_scale is not None:
            g = g * increment_scale  # d loss / d M
        for k in range(len(layers) - 1, -1, -1):
            _activation_backward(g, acts[k][i], layers[k].activation, out=pre[k][i])
            g = pre[k][i] @ (layers[k].weight if k else w_x)
        carry = g + top if residual else g
    inputs = [fed, *acts[:-1]]
    for k, layer in enumerate(layers):
        if layer.grad_weight is None:
            continue
        grad_rows = pre[k].view(-1, pre[k].shape[-1])
        if k == 0:
            layer.grad_weight[:, :n].addmm_(grad_rows.t(), fed.view(-1, n))
            layer.grad_weight[:, n:].addmm_(grad_rows.t(), v_rows)
        else:
            layer.grad_weight.addmm_(grad_rows.t(), inputs[k].view(-1, inputs[k].shape[-1]))
        if layer.grad_bias is not None:
            layer.grad_bias.add_(grad_rows.sum(0))
    return float(loss)


def _activate_(a: torch.Tensor, activation: str) -> None:
    if activation == "relu":
        a.clamp_(min=0.0)
    elif activation == "sigmoid":
        a.sigmoid_()


def _activation_backward(
    g: torch.Tensor, y: torch.Tensor, activation: str, *, out: torch.Tensor
) -> None:
    """out = d loss / d pre-activation from g = d loss / d output y."""
    if activation == "relu":
        _threshold_backward(g, y, 0.0, grad_input=out)
    elif activation == "sigmoid":
        torch.mul(g, y * (1.0 - y), out=out)
    else:
        out.copy_(g)


_threshold_backward = torch.ops.aten.threshold_backward.grad_input


class _Objective:
    """The DNN's loss for the training loop (learners.training.Objective)."""

    def __init__(self, learner: DNN) -> None:
        self.learner = learner
        self.params = learner.params_
        self.layers = self.params.layers("model")
        self.scale = learner._increment_scale_tensor()
        self.state_weights = learner._state_weights_tensor()

    def _layers(self, layer: Dense | None) -> list[Dense]:
        return self.layers if layer is None else [*self.layers[:-1], layer, self.layers[-1]]

    def train_step(self, x: torch.Tensor, v: torch.Tensor, step: int) -> float:
        learner = self.learner
        loss = dnn_step(
            self._layers(learner._step_layer(step)),
            x,
            v,
            learner.beta,
            residual=learner.residual,
            increment_scale=self.scale,
            state_weights=self.state_weights,
        )
        if learner.beta.l2:  # beta_3 ||theta||^2: gradient 2 beta_3 theta
            self.params.grad.add_(self.params.data, alpha=2.0 * learner.beta.l2)
        return loss

    def validate(self, x: torch.Tensor, v: torch.Tensor) -> dict[str, float]:
        with torch.no_grad():
            terms = dnn_loss_terms(
                self.layers,
                x,
                v,
                residual=self.learner.residual,
                increment_scale=self.scale,
                state_weights=self.state_weights,
            )
        beta = self.learner.beta
        return batch_mean_terms(terms, {"prediction": beta.prediction, "inf": beta.inf})


@dataclass(frozen=True)
class DNNConfig:
    """The DNN's settings (``conf/learner/dnn.yaml``); the defaults are the paper's Table."""

    # Hidden widths of M: [n+m 32 64 128 128 64 32 n] (the paper's).
    hidden: Sequence[int] = (32, 64, 128, 128, 64, 32)
    horizon: int = 41  # p, steps per training window at the data's period (the paper's)
    beta: DNNLossWeights = field(default_factory=DNNLossWeights)  # the paper's beta_1..3
    # x_{k+1} = x_k + D M(x_k, u_k), D the increments' std (ours); false: x_{k+1} = M (paper).
    residual: bool = False
    # [vx m/s, vy m/s, r rad/s] an error counts in (ours); null: normalized units (the paper).
    loss_scales: Sequence[float] | None = None
    # Robustness experiment: extra layer redrawn each step.
    random_layer: RandomLayerConfig = field(default_factory=RandomLayerConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)

    def __post_init__(self) -> None:
        hidden = tuple(integer("learner.hidden", w, 1) for w in self.hidden)
        if not hidden:
            raise ValueError("learner.hidden must list at least one width (got [])")
        settle(
            self,
            hidden=hidden,
            beta=block(DNNLossWeights, self.beta, "beta"),
            residual=boolean("learner.residual", self.residual),
        )
        settle_trained(self)


class DNN(TrainedLearner):
    """The paper's DNN (see the module docstring).

    Settings (:class:`DNNConfig`):
        hidden: Hidden widths (paper: 32, 64, 128, 128, 64, 32).
        horizon: p, the steps of every training window.
        beta: Loss weights prediction, inf, l2 (the paper's beta_1..3).
        residual: Predict x_{k+1} = x_k + D * M(x_k, u_k) (ours; off in the paper): D (n,) is
            the std of the training drives' one-step increments (normalized), so M's outputs
            are of order one, and M's last layer starts at zero (the model starts as x_{k+1} =
            x_k).
        loss_scales: Weigh each state's squared error in units of its scale (physical units,
            e.g. [0.2, 0.1, 0.05] for vx m/s, vy m/s, r rad/s; ours). None: the paper's
            normalized units.
        random_layer: ``enabled``, ``std`` of the extra layer (before the output layer) redrawn
            every step.
        training: :class:`~learners.training.TrainingConfig` keys.
    """

    name: ClassVar[str] = "dnn"
    config_class: ClassVar[type] = DNNConfig
    config: DNNConfig
    dynamics: ClassVar[Dynamics] = "nonlinear"  # DE-MPC linearises it along its plan
    C_: np.ndarray  # (n, n) = I: the lifted state is the normalized state
    _mlp: NumpyMLP

    def __init__(self, *args: Any, **settings: Any) -> None:
        super().__init__(*args, **settings)
        self.hidden = list(self.config.hidden)
        self.beta = self.config.beta
        self.residual = self.config.residual
        self._random_layer_width = self.hidden[-1]

    def _specs(self, n: int, m: int) -> list[LayerSpec]:
        specs = mlp_specs("model", [n + m, *self.hidden, n], "linear")
        if self.residual:  # start as x_{k+1} = x_k
            specs[-1] = replace(specs[-1], init="zero")
        return specs

    def _before_training(self, train: Sequence[Episode]) -> None:
        n = self.normalizer_.state_min.shape[0]
        if self.residual:
            steps = np.concatenate(
                [np.diff(self.normalizer_.states(e.states), axis=0) for e in train]
            )
            self.increment_scale_ = np.maximum(steps.std(axis=0), 1e-8)
        else:
            self.increment_scale_ = np.ones(n)

    def _increment_scale_tensor(self) -> torch.Tensor | None:
        if not self.residual:
            return None
        return torch.from_numpy(self.increment_scale_.astype(np.float32))

    def _objective(self) -> _Objective:
        return _Objective(self)

    def _rollout_n(self, x0: torch.Tensor, v: torch.Tensor, layer: Dense | None) -> torch.Tensor:
        layers = self.params_.layers("model")
        if layer is not None:
            layers = [*layers[:-1], layer, layers[-1]]
        out = torch.empty(x0.shape[0], v.shape[1] + 1, x0.shape[1])
        out[:, 0] = x_hat = x0
        scale = self._increment_scale_tensor()
        for k in range(v.shape[1]):
            step = mlp_forward(layers, torch.cat([x_hat, v[:, k]], -1))[-1]
            x_hat = x_hat + step * scale if scale is not None else step
            out[:, k + 1] = x_hat
        return out

    def _after_training(self, train: Sequence[Episode]) -> None:
        self._for_control()

    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        state = super()._state()
        if self.residual:
            state["increment_scale"] = self.increment_scale_
        return state

    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        shapes = super()._state_shapes(n, m)
        if self.residual:
            shapes["increment_scale"] = (n,)
        return shapes

    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        super()._set_state(state)
        n = self.normalizer_.state_min.shape[0]
        self.increment_scale_ = (
            state["increment_scale"].double().numpy().copy() if self.residual else np.ones(n)
        )
        self._for_control()

    def _for_control(self) -> None:
        """C_ and the float64 network the controller reads (the nominal one: no random layer,
        whose mean is the identity)."""
        n = self.normalizer_.state_min.shape[0]
        self.C_ = np.eye(n)
        self._mlp = NumpyMLP(self.params_.layers("model"), n)

    # -- the LinearizableModel contract (normalized units) ----------------------------------

    def lift(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.normalizer_.states(np.asarray(x, dtype=float)), dtype=float)

    def step(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        out = self._mlp(z, v)
        return z + self.increment_scale_ * out if self.residual else out

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        out, A, B = self._mlp.jacobian(z, v)
        if self.residual:  # z⁺ = z + D M(z, v)
            scale = self.increment_scale_
            out = z + scale * out
            A = np.eye(z.shape[1]) + scale[:, None] * A
            B = scale[:, None] * B
        d = out - (A @ z[:, :, None])[:, :, 0] - (B @ v[:, :, None])[:, :, 0]
        return A, B, d
