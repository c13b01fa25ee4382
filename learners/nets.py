"""Fully connected networks as views into one flat parameter buffer, with a hand-written backward.

Why not ``torch.nn`` + autograd for training: on 2 CPU cores the Deep EDMD batch (64 windows of
42 samples through encoder and decoder) is small enough that autograd's graph bookkeeping, the
bias-broadcast copies of ``addmm`` and the zero-filled gradients of slicing cost as much as the
arithmetic. Here every trainable tensor is a view into one float32 buffer (``FlatParameters``),
the forward keeps its activations, and :func:`mlp_backward` writes the gradient straight into the
matching views of one flat gradient buffer, so that Adam updates a single tensor. The readable
autograd versions of every loss (``*_loss_terms`` in the learner modules) remain the
specification: the tests check the two agree to float32 rounding.

For control (a trained network as the model of an MPC, every 10 ms), :class:`NumpyMLP` holds
the layers as float64 NumPy arrays: one point's forward is ~30 µs (torch: ~60 µs), and the
Jacobians at every point of a horizon are one chain-rule product per layer over all points,
~10x faster than ``torch.func.vmap(jacrev(...))`` (0.2 vs 2.2 ms at 10 points, 0.7 vs 10 ms
at 60 on one core); the tests check it against ``torch.func`` and finite differences.

Initialization is PyTorch's default for ``nn.Linear`` and the paper's: weights and biases uniform
in [-1/sqrt(fan_in), 1/sqrt(fan_in)] (Goodfellow et al.'s heuristic, which the paper cites with
"a" the number of inputs of the layer).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

__all__ = [
    "Dense",
    "FlatParameters",
    "LayerSpec",
    "NumpyMLP",
    "mlp_apply",
    "mlp_backward",
    "mlp_forward",
    "mlp_specs",
    "random_layer",
]

ACTIVATIONS = ("relu", "linear", "sigmoid")
_threshold_backward = torch.ops.aten.threshold_backward


@dataclass(frozen=True)
class LayerSpec:
    """One affine layer y = act(W x + b): W (fan_out, fan_in) stored as ``{name}.weight``.

    ``init``: ``uniform`` (module docstring) or ``zero`` (a term that starts switched off, such
    as bilinear Deep EDMD's H: it draws nothing, so the other tensors get the same values).
    """

    name: str
    fan_in: int
    fan_out: int
    activation: str = "relu"
    bias: bool = True
    init: str = "uniform"


def mlp_specs(prefix: str, widths: Sequence[int], last_activation: str) -> list[LayerSpec]:
    """ReLU layers through ``widths`` = [in, hidden..., out]; the last layer gets its own act."""
    return [
        LayerSpec(
            f"{prefix}.{i}",
            widths[i],
            widths[i + 1],
            "relu" if i < len(widths) - 2 else last_activation,
        )
        for i in range(len(widths) - 1)
    ]


class FlatParameters:
    """Named float32 tensors that are views into one flat buffer ``data`` (and ``grad``)."""

    def __init__(self, specs: Sequence[LayerSpec]) -> None:
        self.specs = list(specs)
        self.shapes: dict[str, tuple[int, ...]] = {}
        for s in self.specs:
            self.shapes[f"{s.name}.weight"] = (s.fan_out, s.fan_in)
            if s.bias:
                self.shapes[f"{s.name}.bias"] = (s.fan_out,)
        self.offsets: dict[str, tuple[int, int]] = {}
        offset = 0
        for key, shape in self.shapes.items():
            size = math.prod(shape)
            self.offsets[key] = (offset, offset + size)
            offset += size
        self.data = torch.zeros(offset)
        self.grad = torch.zeros(offset)

    def __len__(self) -> int:
        return self.data.numel()

    def views(self, flat: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Named views of ``flat`` (default ``data``); a leaf ``flat`` gets a flat gradient."""
        flat = self.data if flat is None else flat
        return {k: flat[a:b].view(self.shapes[k]) for k, (a, b) in self.offsets.items()}

    def span(self, prefix: str) -> slice:
        """The contiguous range of every tensor whose name starts with ``prefix.``."""
        ranges = [r for k, r in self.offsets.items() if k.startswith(prefix + ".")]
        return slice(min(a for a, _ in ranges), max(b for _, b in ranges))

    def initialize(self, generator: torch.Generator) -> None:
        """Uniform in [-1/sqrt(fan_in), 1/sqrt(fan_in)] for weights and biases (module doc);
        zeros, without drawing, for the ``init: zero`` tensors."""
        views = self.views()
        for s in self.specs:
            if s.init == "zero":
                for key in (f"{s.name}.weight", f"{s.name}.bias"):
                    if key in views:
                        views[key].zero_()
                continue
            bound = 1.0 / math.sqrt(s.fan_in)
            for key in (f"{s.name}.weight", f"{s.name}.bias"):
                if key in views:
                    views[key].uniform_(-bound, bound, generator=generator)

    def layers(self, prefix: str, flat: torch.Tensor | None = None) -> list[Dense]:
        """The :class:`Dense` layers named ``prefix.*`` bound to ``flat`` and to ``grad``."""
        views = self.views(flat)
        grads = self.views(self.grad)
        return [
            Dense(
                views[f"{s.name}.weight"],
                views.get(f"{s.name}.bias"),
                s.activation,
                grads[f"{s.name}.weight"],
                grads.get(f"{s.name}.bias"),
            )
            for s in self.specs
            if s.name.startswith(prefix + ".")
        ]


@dataclass
class Dense:
    """A layer bound to tensors: ``grad_weight`` None means not trained (the random layer)."""

    weight: torch.Tensor  # (out, in), or (R, out, in): one sample per batch row (inference)
    bias: torch.Tensor | None
    activation: str
    grad_weight: torch.Tensor | None = None
    grad_bias: torch.Tensor | None = None


def random_layer(width: int, std: float, generator: torch.Generator, rows: int = 0) -> Dense:
    """A ReLU layer with W ~ I + N(0, std^2), b ~ N(0, std^2), drawn from ``generator``.

    Its mean is the identity, so after a ReLU layer (inputs >= 0) the nominal layer changes
    nothing and ``std`` alone sets how much it perturbs. ``rows`` > 0 draws one layer per batch
    row (for repeated predictions in one batched rollout).
    """
    shape = (rows, width, width) if rows else (width, width)
    weight = torch.eye(width) + std * torch.randn(shape, generator=generator)
    bias = std * torch.randn(shape[:-1], generator=generator)
    return Dense(weight, bias, "relu")


def _affine(layer: Dense, a: torch.Tensor) -> torch.Tensor:
    if layer.weight.dim() == 3:  # per-row weights: a (R, in) -> (R, out)
        h = torch.bmm(layer.weight, a.unsqueeze(-1)).squeeze(-1)
        return h + layer.bias if layer.bias is not None else h
    if layer.bias is None:
        return a @ layer.weight.t()
    return torch.addmm(layer.bias, a, layer.weight.t())


def mlp_forward(layers: Sequence[Dense], x: torch.Tensor) -> list[torch.Tensor]:
    """Activations [x, y_1, ..., y_H] (no autograd; the last one is the output)."""
    acts = [x]
    for layer in layers:
        h = _affine(layer, acts[-1])
        if layer.activation == "relu":
            h.clamp_(min=0.0)
        elif layer.activation == "sigmoid":
            h.sigmoid_()
        acts.append(h)
    return acts


def mlp_backward(
    layers: Sequence[Dense],
    acts: Sequence[torch.Tensor],
    grad_out: torch.Tensor,
    need_input_grad: bool = True,
) -> torch.Tensor | None:
    """Back-propagate d loss / d output; ADD parameter gradients into the layers' grad views.

    Returns d loss / d input, or None when ``need_input_grad`` is False.
    """
    g = grad_out
    for i in range(len(layers) - 1, -1, -1):
        layer, y, a = layers[i], acts[i + 1], acts[i]
        if layer.activation == "sigmoid":
            g = g * y * (1.0 - y)
        elif layer.activation == "relu":
            g = _threshold_backward(g, y, 0.0)
        if layer.grad_weight is not None:
            # a^T g is faster than g^T a when the input is the narrower side (MKL, skinny shapes)
            if a.shape[1] < g.shape[1]:
                layer.grad_weight.add_((a.t() @ g).t())
            else:
                layer.grad_weight.addmm_(g.t(), a)
            if layer.grad_bias is not None:
                layer.grad_bias.add_(g.sum(0))
        if i > 0 or need_input_grad:
            g = g @ layer.weight
        else:
            return None
    return g


def mlp_apply(layers: Sequence[Dense], x: torch.Tensor) -> torch.Tensor:
    """The same network with autograd-friendly ops (the specification and the readable path)."""
    for layer in layers:
        if layer.weight.dim() == 3:
            x = _affine(layer, x)
        else:
            x = torch.nn.functional.linear(x, layer.weight, layer.bias)
        if layer.activation == "relu":
            x = torch.relu(x)
        elif layer.activation == "sigmoid":
            x = torch.sigmoid(x)
    return x


class NumpyMLP:
    """A trained network y = M(z, v) in float64 NumPy: its value and its Jacobians, for control.

    The first layer's inputs are split into ``z`` (the first ``state_width`` columns) and ``v``
    (the rest), so a caller never concatenates. The layers are copied: later training does not
    reach this object.
    """

    def __init__(self, layers: Sequence[Dense], state_width: int) -> None:
        if any(layer.weight.dim() != 2 for layer in layers):
            raise ValueError("NumpyMLP takes shared weights, not one layer per batch row")
        weights = [layer.weight.detach().double().numpy() for layer in layers]
        self.biases = [
            np.zeros(w.shape[0]) if layer.bias is None else layer.bias.detach().double().numpy()
            for w, layer in zip(weights, layers, strict=True)
        ]
        self.activations = [layer.activation for layer in layers]
        self.weights = [np.ascontiguousarray(w) for w in weights]
        # Row-vector products a @ Wᵀ with contiguous Wᵀ; the first layer split into z and v.
        self.transposed = [np.ascontiguousarray(w.T) for w in weights]
        self.first_z = self.transposed[0][:state_width]
        self.first_v = self.transposed[0][state_width:]
        self.state_width = state_width

    def __call__(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """M(z, v) for z (..., state_width), v (..., inputs) -> (..., out)."""
        a = z @ self.first_z + v @ self.first_v + self.biases[0]
        _activate(a, self.activations[0], slope=False)
        for w_t, b, activation in zip(
            self.transposed[1:], self.biases[1:], self.activations[1:], strict=True
        ):
            a = a @ w_t
            a += b
            _activate(a, activation, slope=False)
        return a

    def jacobian(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M, ∂M/∂z, ∂M/∂v) at K points z (K, state_width), v (K, inputs): (K, out),
        (K, out, state_width), (K, out, inputs).

        Reverse mode (the output is the narrow side): ∂M/∂(z, v) = D_L W_L ⋯ D_1 W_1 with
        D_l the activation's derivative at layer l (ReLU: its on/off mask), one product of the
        (K·out) rows with each layer's W over all K points.
        """
        a = z @ self.first_z + v @ self.first_v + self.biases[0]
        slopes = [_activate(a, self.activations[0], slope=True)]
        for w_t, b, activation in zip(
            self.transposed[1:], self.biases[1:], self.activations[1:], strict=True
        ):
            a = a @ w_t
            a += b
            slopes.append(_activate(a, activation, slope=True))
        points, out = a.shape
        rows = np.broadcast_to(self.weights[-1], (points, *self.weights[-1].shape))
        if slopes[-1] is not None:
            rows = slopes[-1][:, :, None] * rows
        for w, slope in zip(self.weights[-2::-1], slopes[-2::-1], strict=True):
            if slope is not None:
                rows = rows * slope[:, None, :]
            rows = (rows.reshape(points * out, -1) @ w).reshape(points, out, -1)
        return a, rows[:, :, : self.state_width], rows[:, :, self.state_width :]


def _activate(a: np.ndarray, activation: str, *, slope: bool) -> np.ndarray | None:
    """Apply ``activation`` to ``a`` in place; with ``slope``, return its derivative there
    (None: 1, the linear layer's, or not asked)."""
    if activation == "relu":
        np.maximum(a, 0.0, out=a)
        return a > 0.0 if slope else None
    if activation == "sigmoid":
        np.negative(a, out=a)
        np.exp(a, out=a)
        a += 1.0
        np.reciprocal(a, out=a)
        return a * (1.0 - a) if slope else None
    return None
