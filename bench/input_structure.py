"""Where the input enters, the one thing changed: whole-drive prediction of five model structures.

``python -m bench.input_structure [--seeds 0,1,2] [--pedal signed|split|both] [--window-s W]
[data=... overrides]`` fits on ``data=default`` (collected once into the dataset cache, as the main
job does), or on the data the overrides name (a user's logs too: ``data=ddk_carsim
data.path=<clone>``), and prints the open-loop RMSE of the test drives, whole or in windows of W
seconds each started from the measured state, persistence (the state held) first:

- EDMD: z+ = A z + B v on thin-plate RBFs of x (lifted-linear, the paper's);
- bilinear EDMD: z+ = A z + B v + sum_j vbar_j H_j z, as configured (``bilinear_edmd.yaml``);
- affine, re-lifted: input EDMD's fit and predictor (centres on data points, columns scaled,
  the ridge chosen on the validation rollouts, the state lifted again each step) with observables
  [z; v] of z = [x; 1; phi(x)]: x+ = f(x) + G v, one constant input gain, as Deep EDMD's B;
- bilinear, re-lifted: the same with bilinear observables [z; v; vbar_j z], affine in the input
  with a gain that moves with the state;
- input EDMD: the same with observables of y = [x; v] — nonlinear in the input.

The last three differ only in where the input enters; their column counts are matched (about 500
a state: 500 RBFs of x give 3 + 1 + 500 + m; 160 of x give 3 (3 + 1 + 160) + 2 = 494 bilinear
columns, 120 with the pedal split, 4 (3 + 1 + 120) + 3 = 499; 500 RBFs of (x, v) give 506).
``--pedal split`` fits every structure on throttle and brake as two inputs
(:class:`~learners.split_pedal.SplitPedal`), one slope for each side of the pedal; data without
a signed ``pedal`` input (the DDK runs have throttle and brake already) take ``--pedal signed``,
their inputs as recorded. A drive is reported as "diverged" where the prediction leaves
[-20, 20] in normalized units.
"""

from __future__ import annotations

import argparse
import itertools
from typing import Any

import numpy as np

from bench.machine import describe
from bench.network_training import Persistence, _compose, _dataset
from harness.core.episode import Episode
from harness.evaluation.prediction import open_loop, rmse, windowed
from learners import EDMD, ThinPlateRBF
from learners.base import Learner
from learners.bilinear import BilinearEDMD
from learners.input_edmd import InputEDMD
from learners.split_pedal import SplitPedal


class _StateObservables(InputEDMD):
    """Input EDMD's fit and predictor with observables of the state alone, z = [x; 1; phi(x)],
    and the input outside them (the subclasses say how)."""

    def _dictionary_points(self, x_n: np.ndarray, v: np.ndarray) -> np.ndarray:
        return x_n

    def _lifted(self, x_n: np.ndarray) -> np.ndarray:
        return np.concatenate([x_n, np.ones((*x_n.shape[:-1], 1)), self.dictionary(x_n)], -1)

    def linearize(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError("a prediction-only structure of this benchmark")


class AffineRelifted(_StateObservables):
    """Observables [z; v]: one constant input gain."""

    name = "affine_relifted"

    def _observables(self, x_n: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.concatenate([self._lifted(x_n), v], -1)

    def regressor_count(self, n: int = 3, m: int = 2) -> int:
        return n + 1 + self.dictionary.size[1] + m


class BilinearRelifted(_StateObservables):
    """Bilinear observables [z; v; vbar_j z]: affine in v, with a gain that moves with x."""

    name = "bilinear_relifted"

    def _observables(self, x_n: np.ndarray, v: np.ndarray) -> np.ndarray:
        z = self._lifted(x_n)
        vbar = v - self.normalizer_.inputs(np.zeros(v.shape[-1]))
        return np.concatenate([z, v, *(vbar[..., j : j + 1] * z for j in range(v.shape[-1]))], -1)

    def regressor_count(self, n: int = 3, m: int = 2) -> int:
        return (m + 1) * (n + 1 + self.dictionary.size[1]) + m


def structures(seed: int, split: bool) -> dict[str, Learner]:
    """Each structure with about 500 columns a state; on throttle and brake where ``split``."""
    learners: dict[str, Learner] = {
        "EDMD (linear)": EDMD(ThinPlateRBF(100), seed=seed),
        "bilinear EDMD": BilinearEDMD(ThinPlateRBF(100), seed=seed),
        "affine, re-lifted": AffineRelifted(ThinPlateRBF(500, "samples"), seed=seed),
        "bilinear, re-lifted": BilinearRelifted(
            ThinPlateRBF(120 if split else 160, "samples"), seed=seed
        ),
        "input EDMD": InputEDMD(ThinPlateRBF(500, "samples"), seed=seed),
    }
    if not split:
        return learners
    return {label: SplitPedal(learner) for label, learner in learners.items()}


def _cell(learner: Any, episode: Episode, window_steps: int | None, normalizer: Any) -> str:
    """vx / vy / r RMSE of ``episode`` predicted whole or in windows; "diverged" past 20."""
    rows: np.ndarray | None = None  # whole drives: every row but the given first
    if window_steps is None:
        predicted = open_loop(learner, episode)
    else:
        predicted, rows = windowed(learner, episode, window_steps)
    bound = np.abs(normalizer.states(predicted)).max()
    if not np.isfinite(bound) or bound > 20:
        return "diverged"
    error = rmse(predicted, episode.states, rows)
    return " / ".join(f"{error[k]:.3f}" for k in ("vx", "vy", "yaw_rate"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--pedal", choices=("signed", "split", "both"), default="both")
    parser.add_argument("--window-s", type=float, default=None, help="W s windows")
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. data=ddk_carsim")
    args = parser.parse_args()
    pedals = ("signed", "split") if args.pedal == "both" else (args.pedal,)
    cfg = _compose(args.overrides)
    dataset = _dataset(cfg)
    window_steps = None if args.window_s is None else round(args.window_s / dataset.period_s)
    print(describe())
    what = "whole test drives" if window_steps is None else f"{args.window_s:g} s windows"
    data = " ".join(args.overrides) or "data=default"
    print(f"{data} ({dataset.key}); open-loop RMSE of {what}, vx / vy / r\n")
    names = [e.name for e in dataset.test]
    print(f"| structure | pedal | seed | {' | '.join(names)} |")
    print("|---|---|---|" + "---|" * len(names))
    held = [_cell(Persistence(), e, window_steps, dataset.normalizer) for e in dataset.test]
    print(f"| persistence | | | {' | '.join(held)} |")
    for pedal, seed in itertools.product(pedals, (int(s) for s in args.seeds.split(","))):
        for label, learner in structures(seed, split=pedal == "split").items():
            try:
                learner.fit(dataset.train, dataset.validation, dataset.normalizer)
            except ValueError as error:  # every ridge diverged; no pedal to split
                print(f"| {label} | {pedal} | {seed} | {error} |")
                continue
            cells = [_cell(learner, e, window_steps, dataset.normalizer) for e in dataset.test]
            print(f"| {label} | {pedal} | {seed} | {' | '.join(cells)} |", flush=True)


if __name__ == "__main__":
    main()
