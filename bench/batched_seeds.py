"""Where a network's training could go faster: a GPU, and several seeds trained as one batch.

``python -m bench.batched_seeds [--devices cpu cuda] [--seeds 1 4 16] [--batches 50]`` prints one
table. The model is the DNN's training step as the harness runs it (a residual MLP rolled out
open loop over a window, squared error over the window, Adam), written with its weights stacked
over S seeds, so that S models train in one pass of batched matrix products (``torch.baddbmm``):
S = 1 is one job; S > 1 is what training a sweep's seeds in one process would cost. Data are
random tensors of the harness's shapes (speed does not depend on the values). Two networks:
the main job's (``learner=dnn``: [5, 128, 128, 128, 3], windows of 100 steps) and the paper's
(``learner=dnn_paper``: [5, 32, 64, 128, 128, 64, 32, 3], 41 steps); batches of 64 windows.

Read the last column: ms per batch per model. A device or an S that does not lower it does not
make a sweep faster. The CPU runs on one thread (``harness.core.threads``), as a job does.
"""

from __future__ import annotations

import argparse
import itertools
import time

import torch

from bench.machine import describe

NETWORKS = {
    "dnn (ours)": ([5, 128, 128, 128, 3], 100),
    "dnn_paper": ([5, 32, 64, 128, 128, 64, 32, 3], 41),
}
BATCH = 64


def _parameters(seeds: int, widths: list[int], device: str) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    params = []
    for fan_in, fan_out in itertools.pairwise(widths):
        weight = torch.randn(seeds, fan_in, fan_out, generator=generator) / fan_in**0.5
        params += [
            weight.to(device).requires_grad_(),
            torch.zeros(seeds, 1, fan_out, device=device),
        ]
        params[-1].requires_grad_()
    return params


def _step(params: list[torch.Tensor], x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """One residual step of every seed's MLP: x (S, B, 3), u (S, B, 2)."""
    h = torch.cat([x, u], dim=-1)
    layers = len(params) // 2
    for k in range(layers):
        h = torch.baddbmm(params[2 * k + 1], h, params[2 * k])
        if k < layers - 1:
            h = torch.tanh(h)
    return x + 0.01 * h


def ms_per_batch(device: str, seeds: int, widths: list[int], horizon: int, batches: int) -> float:
    params = _parameters(seeds, widths, device)
    optimizer = torch.optim.Adam(params, lr=1e-3)
    generator = torch.Generator().manual_seed(1)
    x = torch.randn(seeds, BATCH, horizon + 1, 3, generator=generator).to(device)
    u = torch.randn(seeds, BATCH, horizon, 2, generator=generator).to(device)

    def train_batch() -> None:
        optimizer.zero_grad(set_to_none=True)
        state, loss = x[:, :, 0], torch.zeros((), device=device)
        for i in range(horizon):
            state = _step(params, state, u[:, :, i])
            loss = loss + ((state - x[:, :, i + 1]) ** 2).mean()
        loss.backward()
        optimizer.step()

    for _ in range(5):  # warm-up: allocator, kernels, the CUDA context
        train_batch()
    if device == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(batches):
        train_batch()
    if device == "cuda":
        torch.cuda.synchronize()
    return 1e3 * (time.perf_counter() - start) / batches


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", nargs="+", default=["cpu"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 4, 16])
    parser.add_argument("--batches", type=int, default=50)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(describe())
    if "cuda" in args.devices:
        print(f"GPU: {torch.cuda.get_device_name(0)}, torch {torch.__version__}")
    print("\n| network | device | seeds at once | ms per batch | ms per batch per seed |")
    print("|---|---|---|---|---|")
    for name, (widths, horizon) in NETWORKS.items():
        for device in args.devices:
            for seeds in args.seeds:
                ms = ms_per_batch(device, seeds, widths, horizon, args.batches)
                print(f"| {name} | {device} | {seeds} | {ms:.1f} | {ms / seeds:.2f} |")


if __name__ == "__main__":
    main()
