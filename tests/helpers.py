"""What many tests need, written once: compose a config, run the app on it, make episodes of a
known system.

- :func:`compose`: a config as ``python -m harness`` composes it (``as_app``: with Hydra's own
  node, so ``${hydra:...}`` resolves and the app's entry function can run on it);
- :func:`run_app`: the app's entry function (:func:`harness.app.run`) in this process, as
  lightning-hydra-template tests its ``train(cfg)``; :func:`run_job`: the whole job
  ``python -m harness`` runs (:func:`harness.app.job`: the lock, earlier results moved aside,
  ``finished.json`` or ``error.json``, a failure's one line and exit status), in this process
  too; what needs the real command line (its one-line errors, signals, sweeps, the thread
  environment) starts it in a subprocess (``tests/test_app.py``);
- :func:`synthetic_episodes`: drives of x_n⁺ = step(x_n, v) in normalized units, written out in
  physical ones, so a learner's fit can be checked against the system that made them.
"""

from __future__ import annotations

import copy
import json
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal

import numpy as np
from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from harness.app import job, run
from harness.core.episode import Episode, MinMaxNormalizer
from harness.core.paths import CONF_DIR
from harness.core.threads import openblas


def compose(*overrides: str, as_app: bool = False) -> DictConfig:
    """``conf/config.yaml`` with ``overrides``; ``as_app``: as the app holds it (Hydra's node
    set, so ``${hydra:runtime.choices.learner}`` resolves)."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra_compose(
            config_name="config", overrides=list(overrides), return_hydra_config=as_app
        )
    if as_app:
        HydraConfig.instance().set_config(cfg)
    return cfg


def learner_config(name: str, *overrides: str) -> DictConfig:
    """The composed ``learner`` node of ``learner=<name>`` with ``overrides``."""
    return compose(f"learner={name}", *overrides).learner


def run_app(run_dir: Path, *overrides: str) -> dict[str, Any]:
    """Run the app's job on ``overrides`` into ``run_dir`` in this process; its metrics.json."""
    run_dir.mkdir(parents=True, exist_ok=True)
    with _threads_kept():
        run(compose(*overrides, as_app=True), run_dir)
    return json.loads((run_dir / "metrics.json").read_text())


def run_job(run_dir: Path, *overrides: str, cwd: Path | None = None) -> dict[str, Any]:
    """``python -m harness <overrides> hydra.run.dir=<run_dir>`` in this process, started in
    ``cwd``; its metrics.json. The config reaches :func:`harness.app.job` as Hydra's
    ``run_job`` (``hydra/core/utils.py``) hands it over: Hydra's node set with
    ``runtime.output_dir``, taken off the job's config, the directory made and ``.hydra/``
    written (the report reads it). A failed job raises ``SystemExit`` with the command's exit
    status, its one line on stderr, as the command does; Hydra's job log is not written."""
    started_in = Path.cwd()
    try:
        os.chdir(cwd or started_in)  # Hydra's runtime.cwd, and where a stray file would land
        cfg = compose(*overrides, f"hydra.run.dir={run_dir}", "hydra.mode=RUN", as_app=True)
        with read_write(cfg.hydra.runtime), open_dict(cfg.hydra.runtime):
            cfg.hydra.runtime.output_dir = os.path.abspath(run_dir)
        HydraConfig.instance().set_config(cfg)
        task_cfg = copy.deepcopy(cfg)
        with read_write(task_cfg), open_dict(task_cfg):
            del task_cfg["hydra"]
        saved = run_dir / cfg.hydra.output_subdir
        saved.mkdir(parents=True, exist_ok=True)
        (saved / "config.yaml").write_text(OmegaConf.to_yaml(task_cfg))
        (saved / "hydra.yaml").write_text(OmegaConf.to_yaml(HydraConfig.instance().cfg))
        (saved / "overrides.yaml").write_text(OmegaConf.to_yaml(cfg.hydra.overrides.task))
        with _threads_kept():
            job(task_cfg)
        return json.loads((run_dir / "metrics.json").read_text())
    finally:
        os.chdir(started_in)


@contextmanager
def _threads_kept() -> Iterator[None]:
    """The job sets the process's PyTorch and OpenBLAS thread counts: the next test gets them
    back as they were."""
    import torch

    torch_threads = torch.get_num_threads()
    blas = [(set_threads, int(get())) for set_threads, get in openblas()]
    try:
        yield
    finally:
        torch.set_num_threads(torch_threads)
        for set_threads, count in blas:
            set_threads(count)


def synthetic_episodes(
    step: Callable[[np.ndarray, np.ndarray], np.ndarray],
    normalizer: MinMaxNormalizer,
    *,
    count: int = 4,
    steps: int = 400,
    seed: int = 0,
    inputs: Literal["uniform", "smooth"] = "uniform",
    start: tuple[float, float] = (0.0, 1.0),
    name: str = "toy",
    dt: float = 0.01,
) -> list[Episode]:
    """``count`` drives of x_n⁺ = step(x_n, v), in normalized units, under inputs v drawn
    uniformly in the normalized box each step (``uniform``) or smooth sums of sines
    (``smooth``), from a start drawn in ``start``; written out through ``normalizer``'s inverse,
    so the system is exactly what a learner sees (the pedal's two slopes included)."""
    rng = np.random.default_rng(seed)
    episodes = []
    for k in range(count):
        time_s = np.arange(steps) * dt
        if inputs == "uniform":
            v = rng.uniform(0.0, 1.0, (steps, 2))
        else:
            freqs, phases = rng.uniform(0.2, 2.0, (2, 3)), rng.uniform(0, 2 * np.pi, (2, 3))
            v = 0.5 + 0.5 * np.mean(np.sin(2 * np.pi * freqs * time_s[:, None, None] + phases), -1)
        x = np.empty((steps, 3))
        x[0] = rng.uniform(*start, 3)
        for i in range(steps - 1):
            x[i + 1] = step(x[i], v[i])
        states, physical_inputs = normalizer.states_inverse(x), normalizer.inputs_inverse(v)
        episodes.append(
            Episode(f"{name}_{k}", time_s, states, physical_inputs, np.zeros((steps, 3)))
        )
    return episodes
