"""The one model file format: a learner's class, hyperparameters, normalizer and fitted arrays.

A file is a ``torch.save`` of plain data and tensors only (read back with ``weights_only``, so a
file can never run code), headed by :data:`FORMAT` and :data:`FORMAT_VERSION`:
:func:`write` refuses a diverged fit before anything is written, :func:`load` refuses a file
that is not a learner's, models another car's states or inputs, or holds arrays of the wrong
shape or not finite, each in one line naming the file. :func:`check_same_learner` says whether a
loaded model is the learner a run configures; only classes of the ``learners`` package are ever
built from a file or a config (:func:`package_class`).
"""

from __future__ import annotations

import importlib
import pickle
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch

from harness.core import contracts
from harness.core.episode import MinMaxNormalizer
from harness.core.files import write_atomic
from learners.training import RUN_SETTINGS

if TYPE_CHECKING:  # the base class writes through this module: no import at run time
    from learners.base import Learner

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "INPUT_DIM",
    "RUN_SETTINGS",
    "STATE_DIM",
    "Dim",
    "Shape",
    "array_problem",
    "check_inputs",
    "check_same_learner",
    "learner_class",
    "load",
    "package_class",
    "write",
]

FORMAT = "koopman-vehicle-harness/learner"
FORMAT_VERSION = 1
# Classes that files of this version may name and that now live elsewhere (one EDMD class with
# a dictionary replaced ELM-EDMD's own class; EDMD.from_hyperparameters reads its keywords).
_MOVED = {"learners.elm_edmd.ELMEDMD": "learners.edmd.EDMD"}
STATE_DIM = 3  # vx, vy, yaw_rate
INPUT_DIM = 2  # the sedan's: steer_wheel_deg, pedal (a dataset of logs has its own)


class Dim(NamedTuple):
    """A size that follows from the hyperparameters, named in messages (``N = 33``)."""

    name: str
    size: int
    means: str = ""


Shape = tuple[int | Dim, ...]


def write(learner: Learner, path: str | Path, provenance: Mapping[str, Any] | None = None) -> Path:
    """``learner`` to one file at ``path`` (atomically), read back by :func:`load`.

    ``provenance``: plain values in the caller's words (plant, dataset); None keeps what the
    file it was loaded from said.

    Raises:
        ValueError: (one line) when a fitted array is NaN, infinite or mis-shaped: a diverged
            fit is reported, never saved as a model.
    """
    path = Path(path)
    _require_fitted(learner)
    state = learner._state()
    n, m = learner.normalizer_.state_min.shape[0], learner.normalizer_.input_min.shape[0]
    normalizer = learner.normalizer_.to_dict()
    problem = _normalizer_problem(normalizer, n, m) or array_problem(
        state, learner._state_shapes(n, m)
    )
    if problem is not None:
        raise ValueError(
            f"{learner.name}: the fitted model's {problem}: the fit diverged or failed, so it "
            f"is not saved to {path}; check the training data and the learner's settings"
        )
    payload = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "class": f"{type(learner).__module__}.{type(learner).__qualname__}",
        "hyperparameters": learner.hyperparameters,
        "state_dim": int(n),
        "input_dim": int(m),
        "normalizer": normalizer,
        "tensors": {k: torch.as_tensor(np.asarray(v)) for k, v in state.items()},
        "provenance": dict(learner.provenance_ if provenance is None else provenance),
    }
    return write_atomic(path, lambda handle: torch.save(payload, handle))


def _first_words(error: BaseException, limit: int = 80) -> str:
    """An error's first line, cut at a word within ``limit`` characters (never mid-word)."""
    line = str(error).splitlines()[0] if str(error) else type(error).__name__
    if len(line) <= limit:
        return line
    return line[:limit].rsplit(" ", 1)[0].rstrip(",;:") + " …"


def load(
    path: str | Path, *, state_dim: int = STATE_DIM, inputs: Sequence[str] | None = None
) -> Learner:
    """Load any learner written by :meth:`Learner.save`, checking it models this harness's sizes.

    ``inputs``: the input names the caller's data has (None: whatever the file models); a model
    of other inputs is refused, since its predictions would read one column as another.

    Raises:
        ValueError: (one line) when the file is not a learner file, or models another number of
            states than ``state_dim`` or other inputs than ``inputs``.
    """
    path = Path(path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:  # weights_only refused an object: it is not ours
        raise ValueError(
            f"{path} is not a learner file (it holds Python objects besides tensors and plain "
            "data, which could run code; not loaded)"
        ) from None
    except Exception as error:  # any unreadable file gets the same one-line answer
        raise ValueError(f"{path} is not a learner file ({_first_words(error)})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path} is not a learner file (no '{FORMAT}' header)")
    if payload.get("version") != FORMAT_VERSION:
        raise ValueError(
            f"{path} is learner format version {payload.get('version')}, "
            f"this harness reads version {FORMAT_VERSION}"
        )
    if payload.get("state_dim") != state_dim:
        raise ValueError(
            f"{path} models {payload.get('state_dim')} states; expected {state_dim} states"
        )
    input_dim = payload.get("input_dim")
    if not isinstance(input_dim, int) or input_dim < 1:
        raise ValueError(f"{path} is not a learner file (input_dim {input_dim!r})")
    learner = learner_class(str(payload["class"]), str(path)).from_hyperparameters(
        payload["hyperparameters"]
    )
    normalizer, tensors = payload.get("normalizer"), payload.get("tensors")
    if not (isinstance(normalizer, Mapping) and isinstance(tensors, Mapping)):
        raise ValueError(f"{path} is not a learner file (no normalizer or tensors)")
    problem = _normalizer_problem(normalizer, state_dim, input_dim) or array_problem(
        tensors, learner._state_shapes(state_dim, input_dim)
    )
    if problem is not None:
        raise ValueError(f"{path}: {problem}: retrain the model, or choose another model file")
    learner.normalizer_ = MinMaxNormalizer.from_dict(normalizer)
    if inputs is not None:
        check_inputs(learner, inputs, str(path))
    learner._set_state(tensors)
    provenance = payload.get("provenance")
    learner.provenance_ = dict(provenance) if isinstance(provenance, Mapping) else {}
    return learner


def package_class(name: str, kind: type, what: str, source: str) -> Any:
    """The class ``name`` (``learners.<module>.<Class>``) if it lives in this package and is a
    ``kind``; refused in one line naming ``source`` and ``what`` it should be otherwise: a file
    or config never makes the harness import or build anything else."""
    module_name, _, class_name = name.rpartition(".")
    if not module_name.startswith("learners."):
        raise ValueError(f"{source} names class {name!r} outside the learners package")
    try:
        module = importlib.import_module(module_name)
    except ImportError:
        raise ValueError(f"{source} names {name!r}, whose module cannot be imported") from None
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, kind)):
        raise ValueError(f"{source} names {name!r}, which is not {what}")
    return cls


def learner_class(name: str, source: str) -> type[Learner]:
    """The learner class a file names (``learners.deep_edmd.DeepEDMD``; a moved one where it
    lives now), by :func:`package_class`: a class of the package that builds itself from its
    hyperparameters and reads its fitted arrays back (what :func:`load` calls)."""
    cls = package_class(_MOVED.get(name, name), object, "a learner class", source)
    if not all(callable(getattr(cls, a, None)) for a in _LEARNER_CLASS):
        raise ValueError(f"{source} names {name!r}, which is not a learner class")
    return cls


# What load calls on the class a file names.
_LEARNER_CLASS = ("from_hyperparameters", "_state_shapes", "_set_state", "predict")


def check_inputs(learner: contracts.Learner, inputs: Sequence[str], source: str) -> None:
    """Refuse, in one line, a model fitted on other inputs than ``inputs`` (names in order)."""
    modelled = learner.normalizer_.input_names
    if tuple(inputs) != modelled:
        raise ValueError(
            f"{source} models inputs ({', '.join(modelled)}), but the data has inputs "
            f"({', '.join(inputs)}): fit the learner on this data, or use a model of its inputs"
        )


def array_problem(
    arrays: Mapping[str, Any], shapes: Mapping[str, Shape], kind: str = "tensor"
) -> str | None:
    """What is wrong with a model's arrays, as one clause naming the array (``tensor 'A' has
    NaN at (3, 4)``), or None: one missing or not in ``shapes``, not numeric, of another shape
    than ``shapes`` gives, or not finite. A NaN or a wrong size does not fail where it is read:
    it turns every prediction, figure and tracking run after it into garbage."""
    for key in shapes:
        if key not in arrays:
            return f"{kind} '{key}' is missing"
    for key, value in arrays.items():
        if key not in shapes:
            return f"{kind} '{key}' is not one of this learner's ({', '.join(shapes)})"
        array = value.numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
        if not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_):
            return f"{kind} '{key}' holds {array.dtype} values, not numbers"
        expected = shapes[key]
        if array.shape != tuple(int(d.size) if isinstance(d, Dim) else d for d in expected):
            return f"{kind} '{key}' has shape {array.shape}, expected {_shape_text(expected)}"
        bad = ~np.isfinite(array)
        if bad.any():
            index = tuple(int(i) for i in np.argwhere(bad)[0])
            what = "NaN" if np.isnan(array[index]) else "inf"
            return f"{kind} '{key}' has {what} at {index}"
    return None


def _shape_text(shape: Shape) -> str:
    """``(N, N) with N = 33 (lifted states)``: the names and the sizes they stand for."""
    names = [d.name if isinstance(d, Dim) else str(d) for d in shape]
    text = f"({names[0]},)" if len(names) == 1 else f"({', '.join(names)})"
    dims = list(dict.fromkeys(d for d in shape if isinstance(d, Dim)))
    if dims:
        text += " with " + ", ".join(
            f"{d.name} = {d.size}" + (f" ({d.means})" if d.means else "") for d in dims
        )
    return text


def _normalizer_problem(values: Mapping[str, Any], n: int, m: int) -> str | None:
    """A normalizer of the wrong size, with NaN or inf (``state_max=inf``), or min above max."""
    shapes: dict[str, Shape] = {"state_min": (n,), "state_max": (n,)}
    shapes |= {"input_min": (m,), "input_max": (m,)}
    ranges = {k: v for k, v in values.items() if k != "inputs"}
    problem = array_problem(ranges, shapes, kind="normalizer")
    if problem is not None:
        return problem
    described = values.get("inputs")
    if described is not None and (
        not isinstance(described, Sequence)
        or len(described) != m
        or not all(isinstance(c, Mapping) and isinstance(c.get("name"), str) for c in described)
    ):
        return f"normalizer 'inputs' does not describe its {m} inputs ({described!r:.80})"
    for low, high in (("state_min", "state_max"), ("input_min", "input_max")):
        below = np.flatnonzero(np.asarray(values[high]) < np.asarray(values[low]))
        if below.size:
            return f"normalizer '{high}' is below '{low}' at ({int(below[0])},)"
    return None


def check_same_learner(
    loaded: contracts.Described, configured: contracts.Described, source: str, name: str
) -> None:
    """Refuse a loaded model that is not the configured learner ``name`` (one line, both named).

    A run reports its model under the configured learner's name (metrics, ``model_<name>.pt``,
    a sweep's tables): an EDMD file run as ``learner=dnn``, or a seed-0 file as ``seed=1``,
    would be reported as what it is not. The class and every hyperparameter must agree, except
    the training budget and runtime settings (``RUN_SETTINGS``).
    """
    if type(loaded) is not type(configured):
        raise ValueError(
            f"task.model_path {source} holds a {type(loaded).__name__} model ({loaded.name}), "
            f"but learner={name} configures a {type(configured).__name__}: choose the "
            "learner the file was trained as, or another file"
        )
    difference = _first_difference(
        _identity(loaded.hyperparameters), _identity(configured.hyperparameters)
    )
    if difference is not None:
        key, saved, wanted = difference
        raise ValueError(
            f"task.model_path {source} was trained with learner.{key}={saved!r}, but "
            f"learner={name} sets learner.{key}={wanted!r}: set it to match, or use another file"
        )


def _identity(hyperparameters: Mapping[str, Any]) -> dict[str, Any]:
    values = dict(hyperparameters)
    if isinstance(values.get("training"), Mapping):
        values["training"] = {k: v for k, v in values["training"].items() if k not in RUN_SETTINGS}
    if isinstance(values.get("inner"), Mapping):  # a wrapped learner's (learners.split_pedal)
        values["inner"] = _identity(values["inner"])
    return values


def _first_difference(saved: Any, wanted: Any, key: str = "") -> tuple[str, Any, Any] | None:
    """(dotted key, saved, wanted) of the first value that differs; lists compare as lists."""
    if isinstance(saved, Mapping) and isinstance(wanted, Mapping):
        for name in sorted(set(saved) | set(wanted), key=str):
            found = _first_difference(
                saved.get(name), wanted.get(name), f"{key}.{name}" if key else str(name)
            )
            if found is not None:
                return found
        return None
    if isinstance(saved, list | tuple) and isinstance(wanted, list | tuple):
        saved, wanted = list(saved), list(wanted)
    return None if saved == wanted else (key, saved, wanted)


def _require_fitted(learner: Learner) -> None:
    if not hasattr(learner, "normalizer_"):
        raise ValueError(f"{learner.name} is not fitted yet: call fit() first")
