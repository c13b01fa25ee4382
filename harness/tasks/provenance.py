"""What a model was trained on, against what this run has: ``training.provenance``.

A model file (``task.model_path``) trained on another plant or dataset runs without complaint:
its normalizer maps this run's states into the ranges of other drives, and its predictions and
tracking are those of another car. A model file records its plant, the plant's fingerprint and
the dataset's key (:meth:`learners.base.Learner.save`, ``provenance``) beside its normalizer; a
run that loads one compares them with its own, warns in one line naming what differs, and
writes both to ``metrics.json``. Files from before the record load as before: what they do not
say is ``null`` and not compared.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Mapping
from typing import Any

from harness.core.episode import MinMaxNormalizer
from harness.data.store import Dataset
from harness.plant import Sedan

__all__ = ["check_period", "compare", "of_logs", "of_run"]

log = logging.getLogger(__name__)

# What a model file records (the normalizer it holds anyway): compared in this order.
RECORDED = ("plant", "plant_fingerprint", "dataset")


def of_run(plant: Sedan, dataset: Dataset) -> dict[str, Any]:
    """This run's plant (its name and a hash of its fingerprint) and dataset (its key): what
    a model trained here records in its file."""
    text = json.dumps(plant.fingerprint, sort_keys=True, default=list)
    return {
        "plant": plant.params.name,
        "plant_fingerprint": hashlib.sha256(text.encode()).hexdigest()[:16],
        "dataset": dataset.key,
        "period_s": dataset.period_s,
    }


def of_logs(dataset: Dataset) -> dict[str, Any]:
    """What a model fitted on a user's logs records: no plant, the dataset's key and period."""
    return {
        "plant": None,
        "plant_fingerprint": None,
        "dataset": dataset.key,
        "period_s": dataset.period_s,
    }


def check_period(source: str, recorded: Mapping[str, Any], period_s: float) -> None:
    """Refuse, in one line, a model fitted at another period than the data's: it steps once per
    period, so at another one every prediction is of another time. A file from before the
    period was recorded is not checked."""
    trained = recorded.get("period_s")
    if trained is not None and not math.isclose(float(trained), period_s, rel_tol=1e-6):
        raise ValueError(
            f"task.model_path {source} was fitted at a period of {float(trained):g} s, but the "
            f"data's is {period_s:g} s: fit the learner on this data, or use a model of its period"
        )


def compare(
    source: str,
    recorded: Mapping[str, Any],
    trained_normalizer: MinMaxNormalizer,
    this_run: Mapping[str, Any],
    normalizer: MinMaxNormalizer,
) -> dict[str, Any]:
    """``{trained_on, this_run, differs}``; one warning naming ``source`` if anything differs.

    ``recorded`` is what the model file says it was trained on (:func:`of_run` of that run,
    or less in an older file) and ``trained_normalizer`` the normalizer it holds; ``differs``
    lists ``plant`` (its name or its fingerprint), ``dataset`` and ``normalizer`` where they
    differ from this run's (``[]`` when none); what a file does not record is not compared.
    """
    trained_on = {key: recorded.get(key) for key in RECORDED}
    trained_on["normalizer"] = trained_normalizer.to_dict()
    ours = {**{key: this_run.get(key) for key in RECORDED}, "normalizer": normalizer.to_dict()}
    differs = [
        name
        for name, keys in (("plant", ("plant", "plant_fingerprint")), ("dataset", ("dataset",)))
        if any(trained_on[k] is not None and trained_on[k] != ours[k] for k in keys)
    ]
    if not trained_normalizer.same_as(normalizer):
        differs.append("normalizer")
    if differs:
        what = " and ".join([", ".join(differs[:-1]), differs[-1]] if differs[:-1] else differs)
        log.warning(
            "task.model_path %s was trained on plant %s, dataset %s; this run has plant %s, "
            "dataset %s: %s differ%s (training.provenance), so its results describe that model "
            "away from the data it was fitted on",
            source,
            trained_on["plant"] or "(not recorded)",
            trained_on["dataset"] or "(not recorded)",
            ours["plant"],
            ours["dataset"],
            what,
            "s" if len(differs) == 1 else "",
        )
    return {"trained_on": trained_on, "this_run": ours, "differs": differs}
