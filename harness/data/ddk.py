"""The DDK CarSim runs (the paper's authors' public data, ``yongqianxiao/DDK``): their split.

``CarsimDatasets/data_unit_<i>.mat`` are the 38 raw runs (``conf/data/ddk_carsim.yaml`` reads
them). The authors' train / validation / test split is only in their normalized copies,
``MPC/CarsimDClassSUVDatasets/Carsim_DClassSUV_{<i>,val_<i>,test_<i>}.mat``, whose ``Pos``
(X, Y, yaw) is the raw runs' columns 2-4 unchanged: :func:`authors_split` matches each copy to
the one raw run with exactly that pose track, and ``python -m harness.data.ddk <clone>`` prints
the split the preset lists.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
from scipy.io import loadmat

RAW = "CarsimDatasets"
NORMALIZED = "MPC/CarsimDClassSUVDatasets"
_ROLE = re.compile(r"Carsim_DClassSUV_(?:(val|test)_)?\d+\.mat")


def authors_split(clone: Path | str) -> dict[str, list[str]]:
    """Raw file names (``data_unit_<i>.mat``) per split, matched exactly by their pose tracks.

    Raises ``ValueError`` (one line) when a normalized copy matches no raw run, or more than one.
    """
    clone = Path(clone)
    raw = {p.name: loadmat(p)["data"][:, 1:4] for p in sorted((clone / RAW).glob("*.mat"))}
    split: dict[str, list[str]] = {"train": [], "validation": [], "test": []}
    for path in sorted((clone / NORMALIZED).glob("*.mat")):
        role = _ROLE.fullmatch(path.name)
        if role is None:
            continue
        pose = loadmat(path)["Pos"]
        matches = [name for name, track in raw.items() if np.array_equal(track, pose)]
        if len(matches) != 1:
            raise ValueError(
                f"{path} matches {len(matches)} raw runs of {clone / RAW} ({', '.join(matches)})"
            )
        split[{"val": "validation", "test": "test", None: "train"}[role.group(1)]] += matches
    return {name: sorted(files, key=_number) for name, files in split.items()}


def _number(name: str) -> int:
    return int(re.sub(r"\D", "", name) or 0)


if __name__ == "__main__":
    for name, files in authors_split(sys.argv[1]).items():
        print(f"{name} ({len(files)}): {files}")
