"""p-step training windows cut from normalized episodes, as index arithmetic on one array.

Reading of the paper (Sec. VI-B): a training sample is a window of p + 1 consecutive states and
the p inputs between them (the "state and control sequences with time information" of the
multi-step losses). Windows tile each episode with stride p starting from an offset drawn
uniformly in [0, p] per episode and per epoch ("we randomly generated the sampling starting point
in the range of [0 p] ... before each training epoch"). Validation windows start at offset 0.

"Every two adjacent state samples were concatenated as new state data" is read as forming the
snapshot pairs (x_k, x_{k+1}) of EDMD, i.e. consecutive samples make a window, not as a
delay-embedded state [x_k; x_{k-1}]: the paper's encoder input is n = 3 wide, its MPC lifts
chi_t = phi_e(x_t) from one state, and its decoder outputs n = 3 values.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from harness.core.episode import Episode, MinMaxNormalizer

__all__ = ["WindowData"]


@dataclass(frozen=True)
class WindowData:
    """Normalized states (N_total, n) and inputs (N_total, m) of episodes laid end to end."""

    states: torch.Tensor
    inputs: torch.Tensor
    episode_starts: np.ndarray
    episode_lengths: np.ndarray

    @classmethod
    def from_episodes(cls, episodes: Sequence[Episode], normalizer: MinMaxNormalizer) -> WindowData:
        states = np.concatenate([normalizer.states(e.states) for e in episodes])
        inputs = np.concatenate([normalizer.inputs(e.inputs) for e in episodes])
        lengths = np.array([len(e) for e in episodes])
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        return cls(
            torch.from_numpy(states.astype(np.float32)),
            torch.from_numpy(inputs.astype(np.float32)),
            starts,
            lengths,
        )

    def window_starts(self, horizon: int, offsets: np.ndarray | None = None) -> np.ndarray:
        """Global start index of every window of ``horizon`` steps, tiling with stride horizon.

        A window starting at s uses x_s .. x_{s+p} and u_s .. u_{s+p-1}, inside one episode.
        """
        offsets = np.zeros(len(self.episode_lengths), int) if offsets is None else offsets
        parts = [
            start + np.arange(offset, length - horizon, horizon)
            for start, length, offset in zip(
                self.episode_starts, self.episode_lengths, offsets, strict=True
            )
        ]
        return np.concatenate(parts) if parts else np.zeros(0, int)

    def gather(self, starts: np.ndarray, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
        """X (B, p + 1, n) and V (B, p, m) of the windows starting at ``starts``."""
        index = torch.from_numpy(np.asarray(starts))[:, None] + torch.arange(horizon + 1)
        return self.states[index], self.inputs[index[:, :-1]]

    def fingerprint(self) -> str:
        """A hash of the data, so a checkpoint is never resumed on other data."""
        digest = hashlib.sha1()
        for array in (self.states.numpy(), self.inputs.numpy(), self.episode_lengths):
            digest.update(np.ascontiguousarray(array).tobytes())
        return digest.hexdigest()
