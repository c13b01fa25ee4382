"""A recorded test drive as the tracking reference, the paper's choice (section VI).

``conf/reference/test_episode.yaml``: the controller follows the states the synthetic driver
produced on a held-out episode, so the reference is one the plant is known to be able to drive.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from harness.core.episode import Episode


def from_episode(episode: Episode) -> np.ndarray:
    """The recorded states of an episode, as the paper does with its test episodes."""
    return np.array(episode.states, dtype=float)


class HeldOutEpisode:
    """The first of the test drives, recorded at the plant's step (every row one control step).

    A plain class, not a dataclass: Hydra keeps built objects in a config node, which would turn
    a dataclass back into a config.
    """

    def label(self, name: str, episodes: Sequence[Episode]) -> str:
        """``<name>/<episode>``: the report and the metrics name the drive that was tracked."""
        return f"{name}/{_first(episodes).name}"

    def build(self, dt: float, episodes: Sequence[Episode]) -> np.ndarray:
        return from_episode(_first(episodes))


def _first(episodes: Sequence[Episode]) -> Episode:
    if not episodes:
        raise ValueError("the test_episode reference needs at least one test episode")
    return episodes[0]
