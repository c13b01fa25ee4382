"""Driving data: episodes, the synthetic driver, the dataset store with its splits."""

from harness.data.episode import Episode, MinMaxNormalizer, pedal_scale, pedal_unscale

__all__ = ["Episode", "MinMaxNormalizer", "pedal_scale", "pedal_unscale"]
