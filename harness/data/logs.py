"""A dataset from a user's driving logs: CSV, Parquet, NumPy ``.npz`` or MATLAB ``.mat`` files.

``conf/data/<name>.yaml`` with ``- logs_schema`` first in its defaults says where the files are,
which column is which state and input (with a scale to the harness's units), the sampling
period, the model period and the split. :func:`import_logs` checks every file before any work
(a missing column, a NaN or inf with the file and row, time that does not increase, a model
period that the sampling period does not divide: one line naming the file), and writes the
episodes into the same content-addressed store as collected drives (``<root>/<key>/``, the key a
hash of this config and of every file's bytes), so :func:`harness.data.store.load`, the learners,
the pipeline and the report work on them unchanged.

Formats: CSV with a header row (columns by name) or without one (columns by 0-based index);
``.npz`` and ``.mat`` (MATLAB v4-v7, read by SciPy) holding either one variable per column
(columns by variable name) or one 2-D array (``array``: its name; columns by index); Parquet
(columns by name) when ``pyarrow`` is installed. MATLAB v7.3 files are HDF5 and are not read:
save them with ``save(..., '-v7')`` or export CSV.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import hashlib
import json
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from harness.core.checks import integer, positive
from harness.core.contracts import STATE_NAMES
from harness.core.episode import (
    POSE_NAMES,
    Episode,
    InputChannel,
    MinMaxNormalizer,
    check_role,
)
from harness.core.files import write_atomic
from harness.data.store import (
    SPLITS,
    DatasetError,
    dataset_root,
    file_sha256,
    locked,
    read_manifest,
    remove_temporaries,
    verify_episodes,
    write_manifest,
)

__all__ = ["Column", "LogsConfig", "import_logs", "read_log"]

FORMAT = "logs/1"
SUFFIXES = (".csv", ".parquet", ".npz", ".mat")
PERIOD_TOLERANCE = 1e-3  # a sampling step off its period by more than this share is refused


@dataclass
class Column:
    """Where one quantity is in a log and how to bring it to the harness's unit.

    ``column``: a name (CSV header, Parquet column, ``.npz``/``.mat`` variable) or a 0-based
    index (a CSV without header, or the columns of ``LogsConfig.array``). ``scale`` multiplies
    the values (1/3.6 for km/h, pi/180 for degrees to rad). An input may say what it is:
    ``role`` (steering_wheel, road_wheel, drive, brake or pedal) and ``unit`` after ``scale``
    (deg or rad for steering; any word otherwise, such as N*m or bar): the physics baseline
    needs the roles, and the figures draw inputs of one unit on one axis.
    """

    column: Any = field(
        default=None,
        metadata={"doc": "a column name, or a 0-based index (quote a name that starts with #)"},
    )
    scale: float = field(
        default=1.0, metadata={"doc": "multiplies the values: 1/3.6 for km/h, pi/180 for deg"}
    )
    role: str | None = field(
        default=None,
        metadata={"doc": "inputs only: steering_wheel, road_wheel, drive, brake or pedal"},
    )
    unit: str | None = field(
        default=None,
        metadata={"doc": "inputs only, after scale: deg or rad for steering; N*m, bar, … else"},
    )

    def check(self, key: str) -> None:
        index = isinstance(self.column, int) and not isinstance(self.column, bool)
        if not ((index and self.column >= 0) or (isinstance(self.column, str) and self.column)):
            raise ValueError(f"{key}.column must be a column name or an index >= 0")
        if not (isinstance(self.scale, int | float) and math.isfinite(self.scale) and self.scale):
            raise ValueError(f"{key}.scale must be a finite number other than 0")
        if self.role is not None and not key.startswith("data.inputs."):
            raise ValueError(f"{key}.role: only inputs have a role (states and time do not)")
        check_role(key, self.role, self.unit)

    def content(self) -> dict[str, Any]:
        """Its fields, without a role or unit left undeclared (so the store keys of logs from
        before roles were described stay as they were)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None or k == "column"}


@dataclass
class LogsConfig:
    """``conf/data/<logs>.yaml``: a user's logs as a dataset (module docstring).

    ``path`` is the directory the globs of ``files`` and ``split`` are relative to. ``states``
    maps vx, vy, yaw_rate (m/s, m/s, rad/s after ``scale``) to their columns; ``inputs`` maps
    each input's name to its column, in the order the models take them; ``poses`` (X, Y, yaw:
    m, m, rad) is optional and only drawn. Give ``time`` (s) or ``period_s``; ``model_period_s``
    (default: the sampling period) must be a whole multiple of it: every k-th sample is kept and
    its input held over the model period. ``split`` lists file globs per split, or gives
    fractions (or whole counts, which must sum to the files) that ``seed`` deals the files into.
    """

    name: str = field(default="logs", metadata={"doc": "the dataset's name in tables and titles"})
    path: str = field(
        default="???", metadata={"doc": "the directory `files` and `split` are relative to"}
    )
    files: list[str] = field(
        default_factory=lambda: ["*.csv"], metadata={"doc": "file names or globs under `path`"}
    )
    array: str | None = field(
        default=None,
        metadata={"doc": "`.npz`/`.mat`: the one 2-D variable holding every column (by index)"},
    )
    time: Column | None = field(
        default=None, metadata={"doc": "the time column (s after `scale`); or give `period_s`"}
    )
    period_s: float | None = field(
        default=None, metadata={"doc": "the sampling period (s) of logs without a time column"}
    )
    model_period_s: float | None = field(
        default=None,
        metadata={
            "doc": "the models' period (s), a whole multiple of the sampling period: every k-th "
            "sample is kept and its input held; null: the sampling period"
        },
    )
    states: dict[str, Column] = field(
        default_factory=dict,
        metadata={"doc": "exactly vx, vy, yaw_rate: each a column (m/s, m/s, rad/s after scale)"},
    )
    inputs: dict[str, Column] = field(
        default_factory=dict,
        metadata={"doc": "any number of inputs, named by you, in the order the models take them"},
    )
    poses: dict[str, Column] = field(
        default_factory=dict,
        metadata={"doc": "optional X, Y, yaw (m, m, rad): only drawn"},
    )
    split: dict[str, Any] = field(
        default_factory=lambda: {"train": 0.8, "validation": 0.1, "test": 0.1},
        metadata={
            "doc": "train, validation, test: each a list of file globs, or all three fractions, "
            "or all three whole counts of files (summing to the files found), dealt by `seed`"
        },
    )
    seed: int = field(default=0, metadata={"doc": "deals the files into a split by fractions"})
    root: str | None = field(
        default=None,
        metadata={"doc": "the dataset store; null: $KOOPMAN_HARNESS_CACHE/datasets"},
    )
    record_every: int = field(default=1, metadata={"doc": "decimation of the recording only"})
    state_limits: dict[str, Any] = field(
        default_factory=lambda: {
            "vx": [-100.0, 150.0],
            "vy": [-50.0, 50.0],
            "yaw_rate": [-10.0, 10.0],
        },
        metadata={
            "doc": "the plausible [low, high] of each state (SI): a value outside it (a logger's "
            "999999, km/h read as m/s) is refused naming its file and row"
        },
    )

    def __post_init__(self) -> None:
        # Hydra hands dicts of Column as plain mappings when built without the schema.
        for group in ("states", "inputs", "poses"):
            blocks = getattr(self, group)
            setattr(self, group, {k: _column(v) for k, v in dict(blocks).items()})
        if self.time is not None:
            self.time = _column(self.time)
        if not isinstance(self.path, str) or not self.path or self.path == "???":
            raise ValueError("data.path must name the directory that holds the logs")
        if not self.files or any(not isinstance(f, str) or not f for f in self.files):
            raise ValueError("data.files must list at least one file name or glob")
        if set(self.states) != set(STATE_NAMES):
            raise ValueError(
                f"data.states must map exactly {', '.join(STATE_NAMES)} to columns "
                f"(got {', '.join(self.states) or 'none'})"
            )
        if not self.inputs:
            raise ValueError("data.inputs must map at least one input name to its column")
        if self.poses and set(self.poses) != set(POSE_NAMES):
            raise ValueError(f"data.poses must map {', '.join(POSE_NAMES)} or nothing")
        for group in ("states", "inputs", "poses"):
            for key, column in getattr(self, group).items():
                column.check(f"data.{group}.{key}")
        if self.time is not None:
            self.time.check("data.time")
        if (self.time is None) == (self.period_s is None):
            raise ValueError("data: give either data.time (a time column) or data.period_s")
        for key in ("period_s", "model_period_s"):
            if getattr(self, key) is not None:
                positive(f"data.{key}", getattr(self, key))
        self.state_limits = {k: list(v) for k, v in dict(self.state_limits).items()}
        for key, limits in self.state_limits.items():
            if key not in STATE_NAMES:
                raise ValueError(
                    f"data.state_limits.{key}: no such state (states: {', '.join(STATE_NAMES)})"
                )
            ok = len(limits) == 2 and all(isinstance(v, int | float) for v in limits)
            if not ok or not limits[0] < limits[1]:
                raise ValueError(f"data.state_limits.{key} must be [low, high], low < high")
        self.seed = integer("data.seed", self.seed, 0)
        self.record_every = integer("data.record_every", self.record_every)
        _check_split(self.split)

    @property
    def channels(self) -> tuple[InputChannel, ...]:
        return tuple(
            InputChannel(name, role=column.role, unit=column.unit)
            for name, column in self.inputs.items()
        )

    def content(self) -> dict[str, Any]:
        """The fields that determine the episodes (not where the files or the store are)."""
        values = dataclasses.asdict(self)
        for transient in ("root", "record_every", "name", "path", "state_limits"):
            values.pop(transient)
        for group in ("states", "inputs", "poses"):
            values[group] = {k: c.content() for k, c in getattr(self, group).items()}
        if self.time is not None:
            values["time"] = self.time.content()
        return values


def _column(value: Any) -> Column:
    if isinstance(value, Column):
        return value
    if isinstance(value, Mapping):
        return Column(**dict(value))
    return Column(column=value)  # a bare name or index


def _check_split(split: Mapping[str, Any]) -> None:
    if set(split) != set(SPLITS):
        raise ValueError(f"data.split needs train, validation and test (got {', '.join(split)})")
    values = [split[s] for s in SPLITS]
    if all(isinstance(v, Sequence) and not isinstance(v, str) for v in values):
        if any(not v for v in values):
            raise ValueError("data.split: every split needs at least one file or glob")
        return
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        raise ValueError("data.split gives lists of files for every split, or a number for each")
    if any(v <= 0 or not math.isfinite(v) for v in values):
        raise ValueError(f"data.split numbers must be > 0 (got {list(values)})")


class _Table:
    """One log file's columns, by name or by index (see the module docstring)."""

    def __init__(self, path: Path, array: str | None) -> None:
        self.path = path
        suffix = path.suffix.lower()
        self.named: dict[str, np.ndarray] = {}
        self.matrix: np.ndarray | None = None
        if suffix == ".csv":
            self._read_csv()
        elif suffix == ".parquet":
            self._read_parquet()
        elif suffix in (".npz", ".mat"):
            self._read_arrays(self._load_arrays(suffix), array)
        else:
            raise ValueError(f"is a {suffix or 'suffix-less'} file; logs are {', '.join(SUFFIXES)}")

    def _read_csv(self) -> None:
        with self.path.open() as handle:
            first = handle.readline().strip()
        fields = [f.strip().strip('"').lstrip("\ufeff") for f in first.split(",")]
        if not first:
            raise ValueError("is empty")
        texts = sum(_not_a_number(f) for f in fields)
        if 0 < texts < len(fields):  # a header names every column; a data row is numbers
            raise ValueError(
                f"has a first line of numbers and text ({first[:60]}): a header names every "
                "column, a data row holds numbers only"
            )
        header = texts == len(fields)
        if header:
            seen: dict[str, int] = {}
            for j, name in enumerate(fields):
                if name in seen:
                    raise ValueError(
                        f"has two columns named {name!r} (columns {seen[name]} and {j}, "
                        "0-based): rename one"
                    )
                seen[name] = j
        try:
            with warnings.catch_warnings():  # no rows: said below, in one line
                warnings.filterwarnings("ignore", message="genfromtxt: Empty input file")
                values = np.genfromtxt(
                    self.path,
                    delimiter=",",
                    skip_header=1 if header else 0,
                    dtype=float,
                    ndmin=2,
                    encoding="utf-8-sig",
                )
        except ValueError as error:  # numpy's first line says only "Some errors were detected"
            reasons = [line.strip() for line in str(error).splitlines()[1:] if line.strip()]
            more = f" and {len(reasons) - 1} more" if len(reasons) > 1 else ""
            raise ValueError(
                f"is not a table of numbers: {reasons[0] if reasons else error}{more}"
            ) from None
        if values.size == 0 or values.shape[0] == 0:
            raise ValueError("has a header and no data rows" if header else "has no data rows")
        if header:
            if values.shape[1] != len(fields):
                raise ValueError(f"has {len(fields)} header names for {values.shape[1]} columns")
            self.named = {name: values[:, j] for j, name in enumerate(fields)}
        self.matrix = values

    def _read_parquet(self) -> None:
        try:
            import pyarrow.parquet as parquet
        except ImportError:
            raise ValueError(
                "is Parquet, which needs pyarrow: pip install pyarrow (or export CSV)"
            ) from None
        table = parquet.read_table(self.path)
        # Columns as they are: only those the config names are read as numbers (column()), so
        # a text column beside them (a driver's name) is no error.
        self.named = {name: table.column(name).to_numpy() for name in table.column_names}

    def _load_arrays(self, suffix: str) -> dict[str, np.ndarray]:
        if suffix == ".npz":
            with np.load(self.path, allow_pickle=False) as arrays:
                return {k: np.asarray(arrays[k]) for k in arrays.files}
        from scipy.io import loadmat

        try:
            arrays = loadmat(self.path)
        except NotImplementedError:
            raise ValueError(
                "is a MATLAB v7.3 (HDF5) file, which is not read: save it with "
                "save(..., '-v7') or export CSV"
            ) from None
        return {k: np.asarray(v) for k, v in arrays.items() if not k.startswith("__")}

    def _read_arrays(self, arrays: dict[str, np.ndarray], array: str | None) -> None:
        if array is not None:
            if array not in arrays:
                raise ValueError(f"has no array {array!r} (it has {', '.join(sorted(arrays))})")
            self.matrix = np.atleast_2d(np.asarray(arrays[array], dtype=float))
            rows, columns = self.matrix.shape
            if rows < columns:  # a row per signal: every "column" would be one sample
                raise ValueError(
                    f"has {array!r} of {rows} rows and {columns} columns: a table holds a row per "
                    "sample (transposed? save its transpose)"
                )
            return
        # A column per variable: 1-D, or a MATLAB column or row vector (T x 1, 1 x T); a
        # variable of text or a struct is kept as it is and refused only if a column names it.
        self.named = {
            k: np.asarray(v).reshape(-1)
            for k, v in arrays.items()
            if v.ndim == 1 or (v.ndim == 2 and 1 in v.shape)
        }
        numeric = {k: v for k, v in arrays.items() if _numeric(v)}
        matrices = [k for k, v in numeric.items() if v.ndim == 2 and min(v.shape) > 1]
        if len(matrices) == 1:  # one table: columns by index too
            self.matrix = np.asarray(arrays[matrices[0]], dtype=float)

    def column(self, key: str, column: Column) -> np.ndarray:
        name = column.column
        if isinstance(name, str):
            if name not in self.named:
                known = ", ".join(sorted(self.named)[:12]) or "none: give 0-based indices"
                raise ValueError(f"has no column {name!r} for {key} (columns: {known})")
            values = self.named[name]
            if not _numeric(values):
                kind = _kind(values)
                raise ValueError(
                    f"has {kind}, not numbers, in {name!r} for {key}: export that column as "
                    "numbers (a MATLAB struct: save its fields as variables)"
                )
        else:
            if self.matrix is None:
                raise ValueError(f"has no table to take column {name} from for {key}: name it")
            if name >= self.matrix.shape[1]:
                raise ValueError(f"has {self.matrix.shape[1]} columns; {key} asks for index {name}")
            values = self.matrix[:, name]
        return np.asarray(values, dtype=float) * column.scale


def _numeric(values: np.ndarray) -> bool:
    """Numbers or booleans (a column of text, objects or a MATLAB struct is not)."""
    return bool(np.issubdtype(values.dtype, np.number) or values.dtype == np.bool_)


def _kind(values: np.ndarray) -> str:
    """What a column that is not numbers holds, in words: text, a struct or objects."""
    first = values.flat[0] if values.size else None
    if values.dtype.names or (isinstance(first, np.ndarray) and first.dtype.names):
        return "a struct"
    if values.dtype.kind in "US" or isinstance(first, str | bytes):
        return "text"
    return "objects"


def _not_a_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return bool(text)
    return False


def read_log(path: Path, logs: LogsConfig) -> Episode:
    """One log file as an episode at the model period, checked (one ``ValueError`` clause)."""
    table = _Table(path, logs.array)
    states = np.stack([table.column(f"states.{k}", logs.states[k]) for k in STATE_NAMES], -1)
    inputs = np.stack([table.column(f"inputs.{k}", c) for k, c in logs.inputs.items()], -1)
    if logs.poses:
        poses = np.stack([table.column(f"poses.{k}", logs.poses[k]) for k in POSE_NAMES], -1)
    else:
        poses = np.zeros((len(states), 3))
    if logs.time is not None:
        time_s = table.column("time", logs.time)
    else:
        time_s = np.arange(len(states)) * float(logs.period_s or 0.0)
    names = {"states": STATE_NAMES, "inputs": tuple(logs.inputs), "poses": POSE_NAMES}
    arrays = {"time": time_s, "states": states, "inputs": inputs, "poses": poses}
    for what, values in arrays.items():
        grid = values.reshape(len(values), -1)
        bad = np.argwhere(~np.isfinite(grid))
        if bad.size:
            row, col = int(bad[0][0]), int(bad[0][1])
            name = names[what][col] if what in names else "time"
            raise ValueError(f"has a non-finite {name} ({grid[row, col]}) in data row {row + 1}")
    for j, name in enumerate(STATE_NAMES):
        low, high = logs.state_limits.get(name, (-math.inf, math.inf))
        outside = np.flatnonzero((states[:, j] < low) | (states[:, j] > high))
        if outside.size:
            row = int(outside[0])
            raise ValueError(
                f"has {name} = {states[row, j]:g} in data row {row + 1}, outside "
                f"[{low:g}, {high:g}] (data.state_limits.{name}): a logger's sentinel, or a "
                f"unit to scale (data.states.{name}.scale)?"
            )
    if len(time_s) < 2:
        raise ValueError(f"has {len(time_s)} rows; a drive needs at least 2")
    steps = np.diff(time_s)
    if np.any(steps <= 0):
        row = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise ValueError(
            f"has time that does not increase at data row {row + 1} (t = {time_s[row]:g} s)"
        )
    period = float(np.median(steps))
    if period >= 1.0:  # no vehicle is logged that slowly: a time column in ms, us or ns
        raise ValueError(
            f"is sampled every {period:g} s: is its time in ms or ns? scale it to seconds "
            "(data.time.scale: 1e-3 for ms, 1e-9 for ns)"
        )
    if np.max(np.abs(steps - period)) > PERIOD_TOLERANCE * period:
        row = int(np.argmax(np.abs(steps - period))) + 1
        raise ValueError(
            f"is not sampled at one period ({period:g} s; {steps[row - 1]:g} s before data row "
            f"{row + 1}): resample it"
        )
    every = decimation(period, logs.model_period_s)
    if (len(time_s) + every - 1) // every < 2:  # one sample: no step to learn, no period
        raise ValueError(
            f"has {len(time_s)} rows, {(len(time_s) + every - 1) // every} at the model period "
            f"({period * every:g} s): a drive needs at least 2"
        )
    kept = slice(0, None, every)
    time_s = time_s[kept] - time_s[0]
    return Episode(path.stem, time_s, states[kept], inputs[kept], poses[kept], logs.channels)


def decimation(period_s: float, model_period_s: float | None) -> int:
    """k with model period = k x sampling period; refuses a model period that is not whole."""
    if model_period_s is None:
        return 1
    ratio = model_period_s / period_s
    k = round(ratio)
    # The sampling period's own tolerance (read_log): a logger's microsecond jitter passes both.
    if k < 1 or abs(ratio - k) > PERIOD_TOLERANCE * max(ratio, 1.0):
        raise ValueError(
            f"is sampled every {period_s:g} s, which does not divide data.model_period_s = "
            f"{model_period_s:g} s (ratio {ratio:.6g})"
        )
    return k


def _files(logs: LogsConfig) -> list[Path]:
    root = Path(logs.path).expanduser()
    if not root.is_dir():
        raise DatasetError(f"data.path {root} is not a directory")
    found: dict[str, Path] = {}
    for pattern in logs.files:
        matched = sorted(p for p in root.glob(pattern) if p.is_file())
        if not matched:
            raise DatasetError(f"data.files: {pattern!r} matches no file in {root}")
        found.update((str(p.relative_to(root)), p) for p in matched)
    stems: dict[str, str] = {}
    for relative, path in found.items():
        if path.stem in stems:
            raise DatasetError(
                f"data.files: {relative} and {stems[path.stem]} have the same name {path.stem!r}"
            )
        stems[path.stem] = relative
    return [found[k] for k in sorted(found)]


def split_files(logs: LogsConfig, files: Sequence[Path]) -> dict[str, list[str]]:
    """Episode names (file stems) per split: by the globs of ``data.split``, or dealt by seed."""
    root = Path(logs.path).expanduser()
    relative = {str(p.relative_to(root)): p.stem for p in files}
    lists = isinstance(logs.split["train"], Sequence) and not isinstance(logs.split["train"], str)
    if lists:
        chosen: dict[str, list[str]] = {}
        owner: dict[str, str] = {}
        for split in SPLITS:
            names: list[str] = []
            for pattern in logs.split[split]:
                matched = [r for r in relative if fnmatch.fnmatch(r, str(pattern))]
                if not matched:
                    raise DatasetError(
                        f"data.split.{split}: {pattern!r} matches none of data.files"
                    )
                for r in matched:
                    if owner.setdefault(r, split) != split:
                        raise DatasetError(f"data.split: {r} is in {owner[r]} and in {split}")
                    names.append(relative[r])
            chosen[split] = sorted(set(names))
        return chosen
    names = sorted(relative.values())
    given = [logs.split[s] for s in SPLITS]
    if all(isinstance(v, int) for v in given) and sum(given) != len(names):
        # Whole numbers are counts of files: taken as proportions they would move files
        # between splits unasked (2/1/1 of 5 files would have been 3/1/1).
        raise DatasetError(
            f"data.split counts {'/'.join(map(str, given))} sum to {sum(given)}, but data.files "
            f"match {len(names)} files: give counts that sum to {len(names)}, or fractions"
        )
    weights = np.array([float(v) for v in given])
    counts = _counts(weights, len(names))
    order = np.random.default_rng([logs.seed, 3]).permutation(len(names))
    shuffled = [names[i] for i in order]
    bounds = np.cumsum([0, *counts])
    return {s: sorted(shuffled[bounds[i] : bounds[i + 1]]) for i, s in enumerate(SPLITS)}


def _counts(weights: np.ndarray, files: int) -> list[int]:
    """Files per split in proportion to ``weights``, at least one each (largest remainders);
    counts that sum to ``files`` are kept as they are."""
    if files < len(weights):
        raise DatasetError(f"data.split needs at least {len(weights)} files, found {files}")
    exact = weights / weights.sum() * files
    counts = np.maximum(np.floor(exact).astype(int), 1)
    while counts.sum() < files:
        counts[int(np.argmax(exact - counts))] += 1
    while counts.sum() > files:
        counts[int(np.argmax(np.where(counts > 1, counts - exact, -np.inf)))] -= 1
    return [int(c) for c in counts]


def content_key(logs: LogsConfig, files: Sequence[Path]) -> tuple[str, dict[str, str]]:
    """The store key (a hash of the config and of every file's bytes) and the files' SHA-256."""
    digests = {path.name: file_sha256(path) for path in files}
    identity = {"format": FORMAT, "logs": logs.content(), "files": digests}
    text = json.dumps(identity, sort_keys=True, default=list)
    return hashlib.sha256(text.encode()).hexdigest()[:16], digests


def import_logs(logs: LogsConfig) -> Path:
    """Check and store the logs (once: a stored dataset of the same files and config is reused);
    return the dataset's directory, which :func:`harness.data.store.load` reads. Every file is
    read and checked before anything is written: a bad file leaves the store as it was."""
    files = _files(logs)
    key, digests = content_key(logs, files)
    split = split_files(logs, files)
    directory = dataset_root(logs) / key
    if directory.is_dir():
        with locked(directory):
            if _stored(directory):
                return directory
    episodes = {}
    sources = {}
    for path in files:
        try:
            episode = read_log(path, logs)
        except ValueError as error:
            raise DatasetError(f"data: {path} {error}") from None
        episodes[episode.name], sources[episode.name] = episode, path.name
    period = _common_period(episodes, sources)
    directory.mkdir(parents=True, exist_ok=True)
    with locked(directory):
        remove_temporaries(directory)
        if _stored(directory):  # another job stored it while this one read
            return directory
        entries: dict[str, dict[str, Any]] = {}
        for name, episode in episodes.items():
            target = directory / f"{name}.npz"
            _write_episode(target, episode)
            entries[name] = {
                "file": target.name,
                "sha256": file_sha256(target),
                "steps": len(episode),
                "spun": False,
                "source": sources[name],
            }
        train = [episodes[name] for name in split["train"]]
        manifest = {
            "format": 1,
            "key": key,
            "source": "logs",
            "data": logs.content(),
            "files": digests,
            "period_s": period,
            "inputs": [c.to_dict() for c in logs.channels],
            "episodes": dict(sorted(entries.items())),
            "split": split,
            "normalizer": MinMaxNormalizer.fit(train).to_dict(),
            "complete": True,
        }
        write_manifest(directory, manifest)
    return directory


def _stored(directory: Path) -> bool:
    """A complete dataset whose episode files are intact (call under the lock)."""
    try:
        stored = read_manifest(directory)
    except Exception:  # damaged: rebuilt from the logs, which are the truth
        return False
    return (
        stored is not None
        and bool(stored.get("complete"))
        and not verify_episodes(directory, stored["episodes"])
    )


def _common_period(episodes: Mapping[str, Episode], sources: Mapping[str, str]) -> float:
    """The model period all logs share, or one line naming the log that differs."""
    periods = {name: float(np.median(np.diff(e.time_s))) for name, e in episodes.items()}
    period = float(np.median(list(periods.values())))
    for name, value in periods.items():
        if not math.isclose(value, period, rel_tol=1e-3):
            raise DatasetError(
                f"data: {sources[name]} has model period {value:g} s, the other logs "
                f"{period:g} s: set data.model_period_s to one they all divide"
            )
    return period


def _write_episode(path: Path, e: Episode) -> None:
    """The store's episode file (``time_s``, ``states``, ``inputs``, ``poses``), atomically."""
    write_atomic(
        path,
        lambda handle: np.savez(
            handle, time_s=e.time_s, states=e.states, inputs=e.inputs, poses=e.poses
        ),
    )
