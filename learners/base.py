"""The learner contract shared by EDMD, ELM-EDMD, DNN and Deep EDMD, and the one model file format.

Every learner models x_{k+1} = f(x_k, u_k) for x = (vx, vy, yaw_rate) [m/s, m/s, rad/s] and
u = (steer_wheel_deg, pedal). Learners train in the min-max normalized coordinates of
:class:`~harness.core.episode.MinMaxNormalizer` (fitted on the training episodes only) and speak
physical units at their interface.

Koopman learners additionally expose a lifted linear model for the MPC::

    z_0     = lift(x_0)                                  (N,)
    z_{k+1} = A_ @ z_k + B_ @ normalizer_.inputs(u_k)
    x_hat_k = normalizer_.states_inverse(C_ @ z_k)

In every Koopman learner of this package the lifted state starts with the normalized state
itself, z = [normalizer_.states(x); ...], so ``C_ = [I 0]`` exactly (EDMD's "the lifted state
includes x"); Deep EDMD with ``lifted_includes_state=false`` is the one exception and fits
``C_`` by least squares (the paper's eq. for C).
"""

from __future__ import annotations

import importlib
import pickle
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Any, ClassVar, NamedTuple, Self

import numpy as np
import torch

from harness.core import contracts
from harness.core.contracts import STATE_NAMES
from harness.core.episode import Episode, InputChannel, MinMaxNormalizer
from harness.core.files import write_atomic

__all__ = [
    "FORMAT",
    "Dim",
    "KoopmanLearner",
    "Learner",
    "array_problem",
    "check_same_learner",
    "load",
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


class Learner(contracts.Learner, ABC):
    """The ABC that implements :class:`harness.core.contracts.Learner`: a model of
    x_{k+1} = f(x_k, u_k) learned from episodes, saved to and loaded from one file format.

    Subclasses set ``name`` (their config-group name, used in messages and file names) and
    keep their hyperparameters as constructor keywords, so that a config maps 1:1 to the code.
    """

    name: ClassVar[str]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        abstract = any(
            getattr(getattr(cls, attr, None), "__isabstractmethod__", False) for attr in dir(cls)
        )
        if not abstract and not isinstance(getattr(cls, "name", None), str):
            raise TypeError(f"{cls.__qualname__} must set the class attribute `name`")

    @abstractmethod
    def fit(
        self,
        train: Sequence[Episode],
        validation: Sequence[Episode],
        normalizer: MinMaxNormalizer,
    ) -> Self:
        """As :meth:`harness.core.contracts.Learner.fit`."""

    @abstractmethod
    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """As :meth:`harness.core.contracts.Learner.predict`."""

    def save(self, path: str | Path, provenance: Mapping[str, Any] | None = None) -> Path:
        """As :meth:`harness.core.contracts.Learner.save`; the file is read back by :func:`load`.

        ``provenance``: plain values in the caller's words (plant, dataset); None keeps what
        the file it was loaded from said.

        Raises:
            ValueError: (one line) when a fitted array is NaN, infinite or mis-shaped: a
                diverged fit is reported, never saved as a model.
        """
        path = Path(path)
        _require_fitted(self)
        state = self._state()
        n, m = self.normalizer_.state_min.shape[0], self.normalizer_.input_min.shape[0]
        problem = _normalizer_problem(self.normalizer_.to_dict(), n, m) or array_problem(
            state, self._state_shapes(n, m)
        )
        if problem is not None:
            raise ValueError(
                f"{self.name}: the fitted model's {problem}: the fit diverged or failed, so it "
                f"is not saved to {path}; check the training data and the learner's settings"
            )
        payload = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "class": f"{type(self).__module__}.{type(self).__qualname__}",
            "hyperparameters": self.hyperparameters,
            "state_dim": int(self.normalizer_.state_min.shape[0]),
            "input_dim": int(self.normalizer_.input_min.shape[0]),
            "normalizer": self.normalizer_.to_dict(),
            "tensors": {k: torch.as_tensor(np.asarray(v)) for k, v in state.items()},
            "provenance": dict(self.provenance_ if provenance is None else provenance),
        }
        return write_atomic(path, lambda handle: torch.save(payload, handle))

    @classmethod
    def load(cls, path: str | Path) -> Learner:
        """Read a file written by :meth:`save` (of this class or, from ``Learner``, any class)."""
        learner = load(path)
        if not isinstance(learner, cls):
            raise ValueError(f"{path} holds a {type(learner).__name__}, not a {cls.__name__}")
        return learner

    @classmethod
    def from_hyperparameters(cls, hyperparameters: Mapping[str, Any]) -> Self:
        """The learner a model file's ``hyperparameters`` describe (unfitted)."""
        return cls(**hyperparameters)

    def check_size(self, episode_frames: int, n: int = STATE_DIM, m: int = INPUT_DIM) -> None:
        """Refuse, in one line naming the key, sizes whose fit on episodes of up to
        ``episode_frames`` frames cannot fit in this machine's memory (see
        :mod:`harness.core.budget`); called before any data is collected. The default checks
        nothing: a learner that can be configured too big overrides it."""
        del episode_frames, n, m

    def check_inputs(self, channels: Sequence[InputChannel]) -> None:
        """Refuse, in one line, inputs this learner cannot be fitted on (``channels``, in order,
        as the data config gives them: names, and roles where declared); called before any
        data is collected. The default takes any inputs: a learner that needs a particular one
        overrides it."""
        del channels

    @property
    def redraws_random_layer(self) -> bool:
        """Whether ``predict(..., random_layer_seed=s)`` draws a fresh random layer each call (the
        paper's robustness experiment): only such learners get repeated predictions."""
        return False

    @property
    def core(self) -> Learner:
        """The learner that trains and holds the state matrices: itself, or the one a wrapper
        fits (:class:`learners.split_pedal.SplitPedal`); a run reports its loss curves and
        spectrum."""
        return self

    @property
    def hyperparameters(self) -> dict[str, Any]:
        """The constructor keywords this learner was built with (what its config holds)."""
        return dict(self._hyperparameters)

    @property
    def fit_summary(self) -> dict[str, Any]:
        """Empty unless a learner chooses something, as input EDMD its ridge."""
        return {}

    # -- for subclasses -------------------------------------------------------------------------

    _hyperparameters: dict[str, Any]
    # What the model was trained on, as its file said (plant, dataset; empty for a model fitted
    # here, or a file from before it was recorded): the caller compares it with its own run.
    provenance_: Mapping[str, Any] = MappingProxyType({})

    @abstractmethod
    def _state(self) -> dict[str, np.ndarray | torch.Tensor]:
        """The fitted arrays that, with the hyperparameters and normalizer, define the model."""

    @abstractmethod
    def _state_shapes(self, n: int, m: int) -> dict[str, Shape]:
        """The shape of every array of :meth:`_state`, from the hyperparameters alone (n states,
        m inputs): what a model file is checked against before :meth:`_set_state` reads it."""

    @abstractmethod
    def _set_state(self, state: Mapping[str, torch.Tensor]) -> None:
        """Restore what :meth:`_state` returned (called on a freshly constructed learner)."""


class KoopmanLearner(Learner, contracts.LiftedModel):
    """A learner whose model is linear in a lifted state (see the module docstring): fitted, it
    is a :class:`~harness.core.contracts.LiftedModel` (``A_``, ``B_``, ``C_`` as float64 arrays,
    ``normalizer_``, ``lift``)."""

    dynamics: ClassVar[contracts.Dynamics] = "linear"


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
    cls = getattr(importlib.import_module(module_name), class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, kind)):
        raise ValueError(f"{source} names {name!r}, which is not {what}")
    return cls


def learner_class(name: str, source: str) -> type[Learner]:
    """The learner class a file names (``learners.deep_edmd.DeepEDMD``; a moved one where it
    lives now), by :func:`package_class`."""
    cls: type[Learner] = package_class(_MOVED.get(name, name), Learner, "a learner class", source)
    return cls


def check_inputs(learner: Learner, inputs: Sequence[str], source: str) -> None:
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


# Training settings that say how long or how a model was trained, not which model it is: a
# model file trained with another budget still is the configured learner, and a training may
# resume from its checkpoint with them changed (learners/trained.py).
RUN_SETTINGS = (
    "max_steps",
    "max_epochs",
    "patience",
    "progress",
    "num_threads",
    "checkpoint_every_steps",
)


def check_same_learner(loaded: Learner, configured: Learner, source: str, name: str) -> None:
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


def check_episodes(
    episodes: Sequence[Episode], role: str, normalizer: MinMaxNormalizer, min_length: int = 2
) -> None:
    """Refuse empty, too short, mis-shaped or non-finite episodes in one line naming the episode."""
    if not episodes:
        raise ValueError(f"no {role} episodes")
    n, m = normalizer.state_min.shape[0], normalizer.input_min.shape[0]
    for e in episodes:
        if e.states.ndim != 2 or e.states.shape[1] != n or e.inputs.shape[1:] != (m,):
            raise ValueError(
                f"{role} episode {e.name!r}: states {e.states.shape} / inputs {e.inputs.shape} "
                f"do not match the normalizer's {n} states and {m} inputs"
            )
        if len(e) < min_length:
            raise ValueError(f"{role} episode {e.name!r} has {len(e)} samples, need {min_length}")
        for field in ("states", "inputs"):
            if not np.all(np.isfinite(getattr(e, field))):
                raise ValueError(f"{role} episode {e.name!r}: {field} contain NaN or inf")


def check_fit_data(
    train: Sequence[Episode],
    validation: Sequence[Episode],
    normalizer: MinMaxNormalizer,
    learner: str,
) -> None:
    """What every ``fit`` checks first: the training episodes, and the validation ones if any;
    and that every state and input varies in the training ones (``learner`` names the fit)."""
    check_episodes(train, "train", normalizer)
    if validation:
        check_episodes(validation, "validation", normalizer)
    check_varied(train, learner)


# A training column whose range is below this, in its unit (relative to its size where that is
# above 1), never varied: no model learns what it does, and min-max scaling by that range sends
# any other value a million spans and more away (a steering wheel held within 1e-9 deg gave input
# EDMD NaN predictions, and DE-MPC a QP that failed, far from the cause).
MIN_TRAINING_RANGE = 1e-6


def check_varied(train: Sequence[Episode], learner: str) -> None:
    """Refuse, in one line naming the learner and the column, training drives in which a state or
    an input stays (all but) constant (see ``MIN_TRAINING_RANGE``)."""
    for field, names in (("states", STATE_NAMES), ("inputs", train[0].input_names)):
        values = np.concatenate([getattr(e, field) for e in train])
        low, high = values.min(0), values.max(0)
        size = np.maximum(np.maximum(np.abs(low), np.abs(high)), 1.0)
        constant = np.flatnonzero(high - low < MIN_TRAINING_RANGE * size)
        if constant.size:
            column = int(constant[0])
            name = names[column] if values.shape[1] == len(names) else f"{field}[{column}]"
            drives = ", ".join(e.name for e in train[:3]) + (", ..." if len(train) > 3 else "")
            raise ValueError(
                f"{learner} cannot learn from the training drives ({drives}): {name} stays at "
                f"{low[column]:.6g} (range {high[column] - low[column]:.1e} over {len(values)} "
                f"frames), so what it does is not in the data; train on drives that vary {name} "
                "(collected: data.driver.*; logs: the files of data.split.train)"
            )


def check_rollout_args(x0: np.ndarray, inputs: np.ndarray, n: int, m: int) -> tuple:
    """Validate predict() arguments; returns float64 arrays (x0 (..., n), inputs (..., T, m))."""
    x0 = np.asarray(x0, dtype=np.float64)
    inputs = np.asarray(inputs, dtype=np.float64)
    if x0.shape[-1:] != (n,) or inputs.ndim < 2 or inputs.shape[-1] != m:
        raise ValueError(
            f"predict needs x0 (..., {n}) and inputs (..., T, {m}); "
            f"got {x0.shape} and {inputs.shape}"
        )
    if inputs.shape[:-2] != x0.shape[:-1]:
        raise ValueError(f"predict: batch shapes differ, x0 {x0.shape} vs inputs {inputs.shape}")
    return x0, inputs


def _require_fitted(learner: Learner) -> None:
    if not hasattr(learner, "normalizer_"):
        raise ValueError(f"{learner.name} is not fitted yet: call fit() first")
