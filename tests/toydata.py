"""Small driving datasets for the learners' tests, examples and benchmarks.

The harness's dataset store (``harness.data``) produces the paper-scale data; this module only
makes a few short, varied episodes quickly (about 0.3 s of wall time per 30 s episode), so that a
learner can be fitted and checked on real plant dynamics inside a unit test.
"""

from __future__ import annotations

import functools

import numpy as np

from harness.core.episode import Episode
from harness.core.limits import BRAKE_MAX_MPA, THROTTLE_MAX
from harness.plant import Sedan
from harness.plant.rollout import simulate


class RandomDriver:
    """Smooth random steering and one-pedal-at-a-time throttle/brake phases, seeded.

    Steering is a sum of three sinusoids (0.05-0.4 Hz) whose amplitude shrinks with speed so the
    car stays below the friction limit most of the time; the pedal alternates between throttle
    and braking phases of 2-8 s, low-pass filtered (0.5 s) like a human foot.
    """

    def __init__(self, seed: int, dt: float, max_steer_deg: float = 200.0) -> None:
        rng = np.random.default_rng(seed)
        self.dt = dt
        self.freqs_hz = rng.uniform(0.05, 0.4, 3)
        self.phases = rng.uniform(0, 2 * np.pi, 3)
        self.amps_deg = rng.uniform(0.2, 1.0, 3) * max_steer_deg / 2
        self.rng = rng
        self.pedal = 0.0
        self.target = 0.0
        self.phase_end_s = 0.0

    def __call__(self, t: float, x: np.ndarray) -> tuple[float, float]:
        if t >= self.phase_end_s:
            self.phase_end_s = t + self.rng.uniform(2.0, 8.0)
            throttle = self.rng.random() < 0.6 or x[0] < 3.0
            self.target = (
                self.rng.uniform(0.05, 1.0) * THROTTLE_MAX
                if throttle
                else -self.rng.uniform(0.05, 0.4) * BRAKE_MAX_MPA
            )
        self.pedal += (self.target - self.pedal) * min(1.0, self.dt / 0.5)
        speed_scale = 1.0 / (1.0 + max(float(x[0]), 0.0) / 10.0)
        steer = speed_scale * float(
            np.sum(self.amps_deg * np.sin(2 * np.pi * self.freqs_hz * t + self.phases))
        )
        return steer, self.pedal


@functools.cache
def _drive(seed: int, duration_s: float) -> Episode:
    plant = Sedan()
    plant.reset(seed=seed)
    traj = simulate(plant, RandomDriver(seed, plant.dt), duration_s)
    return Episode(f"random_drive_{seed}", traj.time_s, traj.states, traj.inputs, traj.poses)


def drive_episodes(count: int, duration_s: float = 30.0, first_seed: int = 0) -> list[Episode]:
    """``count`` episodes of the dry sedan under :class:`RandomDriver`, seeds from ``first_seed``.

    Episodes are cached per (seed, duration) for the life of the process, so tests share them.
    """
    return [_drive(first_seed + k, float(duration_s)) for k in range(count)]
