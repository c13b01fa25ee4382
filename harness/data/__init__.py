"""Driving data: the synthetic driver, collection on the plant, the dataset store with its splits
and coverage. The episode and its normalizer are core types (``harness.core.episode``).

May import ``harness.core``, ``harness.plant``, ``harness.output`` and ``harness.recorder``."""
