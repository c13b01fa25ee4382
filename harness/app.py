"""The Hydra app behind ``python -m harness``: compose the config, build the parts, run a task."""

from __future__ import annotations

import errno
import json
import logging
import os
import sys
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException, MissingConfigException
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from harness.config import register_configs, validate
from harness.core.checks import integer
from harness.core.files import (
    DirectoryInUseError,
    lock_directory,
    unlock_directory,
    write_json_atomic,
)
from harness.core.kernels import in_force, why_not_same_everywhere
from harness.core.paths import CONF_DIR
from harness.core.phases import seconds
from harness.core.threads import threads_in_use, use_threads
from harness.output import update_metrics
from harness.report.jobs import FINISHED, config_digest, job_dirname
from harness.report.summary import summary, title

log = logging.getLogger(__name__)

OmegaConf.register_new_resolver("job_dirname", job_dirname, replace=True)  # a sweep subdir
register_configs()  # before @hydra.main composes: the YAML files extend these schemas


def run(cfg: DictConfig, output_dir: Path) -> dict:
    """Build plant, recorder and task from ``cfg``; run the task; return its metrics sections."""
    task_name = HydraConfig.get().runtime.choices["task"]
    validate(cfg)  # every range check of every block, before anything is built or run
    threads = cfg.get("threads")
    if threads is not None:
        integer("threads", threads, 1)
    # Before any work: the same numbers whatever OMP_NUM_THREADS says (harness/core/threads.py).
    threads_set = use_threads(threads)
    kernels = in_force()  # the same digits on every machine, where they are the pinned set
    if not kernels["same_everywhere"]:
        log.warning("kernels: %s", why_not_same_everywhere(kernels))
    plant = instantiate(cfg.plant)
    make_recorder = instantiate(cfg.recorder)
    task = instantiate(cfg.task)
    start = time.perf_counter()
    with make_recorder(path=output_dir / f"{task_name}.rrd") as recorder:
        sections = task(plant=plant, recorder=recorder, output_dir=output_dir)
    sections["run"] = {"threads": threads_in_use(), "kernels": kernels}
    for section, values in sections.items():
        document = update_metrics(output_dir / "metrics.json", section, values)
    log.info(
        "wrote %s (%s); task=%s took %s on %d thread%s",
        output_dir / "metrics.json",
        ", ".join(document),
        task_name,
        seconds(time.perf_counter() - start),
        threads_set,
        "s" if threads_set > 1 else "",
    )
    if "tracking" in document or "prediction" in document:
        choices = HydraConfig.get().runtime.choices
        logs = (document.get("data") or {}).get("source") == "logs"  # the report's label
        plant = f"logs: {choices.get('data')}" if logs else choices.get("plant")
        heading = title(choices.get("learner"), cfg.get("seed"), plant)
        log.info("summary of %s\n%s", output_dir, summary(document, heading))
    return sections


def _one_line(error: BaseException) -> str:
    while isinstance(error, InstantiationException) and error.__cause__ is not None:
        error = error.__cause__
    if isinstance(error, OSError) and error.filename and error.errno in UNWRITABLE:
        key = "KOOPMAN_HARNESS_CACHE (the caches) or data.root (the datasets)"
        return unwritable(error, key)
    return f"{type(error).__name__}: {error}".splitlines()[0]


def composition_error(error: BaseException) -> str:
    """One line for an error Hydra raises before the job starts (a wrong override, a missing
    option, a value of the wrong type), naming the key where OmegaConf names one."""
    if isinstance(error, MissingConfigException):
        options = [o for o in error.options or [] if not o.endswith("_schema")]
        first = str(error).strip().splitlines()[0]
        return f"{first}; options: {', '.join(options)}" if options else first
    lines = [line.strip() for line in str(error).strip().splitlines() if line.strip()]
    message = lines[0].rstrip(".") if lines else type(error).__name__
    if message.endswith("composing config:") and len(lines) > 1:  # the reason is below it
        message = f"{message} {lines[1].rstrip('.')}"
        key = next((line for line in lines if line.startswith("full_key:")), None)
        if key is not None:
            message = f"{message} (key {key.removeprefix('full_key:').strip()})"
    cause = error.__cause__
    if isinstance(cause, OmegaConfBaseException):
        reason = (cause.msg or "").strip().splitlines()
        if reason and reason[0] not in message:
            message = f"{message}: {reason[0]}"
        if cause.full_key and cause.full_key not in message:
            message = f"{message} (key {cause.full_key})"
    elif "not in struct" in str(error) or "Could not override" in message:
        message = "; ".join(line for line in lines if not line.startswith(("full_key", "object")))
    return message


def _record_failure(output_dir: Path, error: BaseException) -> str:
    """Leave the reason in the run directory, so a sweep's report can name the failed job."""
    message = _one_line(error)
    write_json_atomic(
        output_dir / "error.json",
        {"error": message, "traceback": "".join(traceback.format_exception(error))},
    )
    return message


class LockOutputDir(Callback):
    """A run holds ``hydra.run.dir``, a sweep ``hydra.sweep.dir``, from before Hydra writes its
    config there until it ends: a second run into it stops at once, in one line, before it has
    overwritten anything (``hydra.callbacks.lock`` in ``conf/config.yaml``)."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        _hold_or_exit(config, "hydra.run.dir")

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        unlock_directory(str(config.hydra.run.dir))

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        _hold_or_exit(config, "hydra.sweep.dir")

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        unlock_directory(str(config.hydra.sweep.dir))


def _hold_or_exit(config: DictConfig, key: str) -> None:
    try:
        directory = str(OmegaConf.select(config, key))
    except OmegaConfBaseException:  # needs ${hydra:...}, set only in the job: _job locks it
        return
    try:
        lock_directory(directory, key)
    except DirectoryInUseError as error:
        # Hydra turns a callback's exception into a warning and goes on: stop here instead.
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
    except OSError as error:  # a directory that cannot be made or written
        print(f"error: {unwritable(error, key)}", file=sys.stderr)
        sys.exit(2)


UNWRITABLE = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.ENOSPC, errno.EDQUOT}


def unwritable(error: OSError, key: str) -> str:
    """One line for a directory the harness cannot make or write, naming the setting to change:
    the run's (``key``), the cache's (KOOPMAN_HARNESS_CACHE) or the datasets' (data.root)."""
    where = error.filename or "a directory"
    return f"cannot write {where} ({error.strerror or error}): choose another {key}"


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def _job(cfg: DictConfig) -> None:
    """``python -m harness``'s job: :func:`job` on the config Hydra composed and set."""
    job(cfg)


def job(cfg: DictConfig) -> None:
    """One job: its failure is recorded in ``error.json`` and, outside a sweep, printed in one
    line (exit 2 for the config's and the run's errors, 1 for anything else).

    The job holds its directory while it runs (a sweep's jobs each their own): a directory
    another run holds is left untouched, the job refused in one line. Apart from ``@hydra.main``
    so that tests run it in process on a config they composed (``tests/helpers.py``).
    """
    hydra_cfg = HydraConfig.get()
    output_dir = Path(hydra_cfg.runtime.output_dir)
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    try:
        taken = lock_directory(output_dir, "hydra.sweep.dir" if multirun else "hydra.run.dir")
    except DirectoryInUseError as error:
        log.error("%s", error)
        if multirun:
            return  # the other run's directory: no error.json of this job may land there
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
    try:
        _run_and_record(cfg, output_dir, multirun)
    finally:
        if taken:
            unlock_directory(output_dir)


def finished_before(digest: str, output_dir: Path) -> bool:
    """Whether ``output_dir`` holds the finished job of the config with ``digest``: its
    metrics.json, no error, and a ``finished.json`` with that digest."""
    try:
        record = json.loads((output_dir / FINISHED).read_text())
    except (OSError, ValueError):
        return False
    return (
        isinstance(record, dict)
        and record.get("config_sha256") == digest
        and (output_dir / "metrics.json").is_file()
        and not (output_dir / "error.json").exists()
    )


# A run's directory holds one run's results: what a run before it left there moves here first.
PREVIOUS = "previous"
RESULTS = ("metrics.json", FINISHED, "error.json")  # a run was here that ended (or failed)
KEPT = (".lock", ".log", ".ckpt")  # the lock, Hydra's log of this job, training checkpoints


def move_previous_results(output_dir: Path, inputs: Sequence[Path] = ()) -> Path | None:
    """Where the files a run before this one left in ``output_dir`` went (``previous/<time>/``),
    or None when no run ended there. Its metrics.json, finished.json, error.json, figures,
    arrays, recordings and model move; the training checkpoints (a killed run resumes from
    them), Hydra's ``.hydra/`` and log, the lock, and ``inputs`` (files this run reads: a model
    file of ``task.model_path`` left there) stay."""
    if not any((output_dir / name).exists() for name in RESULTS):
        return None
    kept = {Path(p).resolve() for p in inputs}
    stamp = time.strftime("%Y%m%dT%H%M%S")
    target = output_dir / PREVIOUS / stamp
    suffix = 1
    while target.exists():
        target, suffix = output_dir / PREVIOUS / f"{stamp}_{suffix}", suffix + 1
    target.mkdir(parents=True)
    for path in sorted(output_dir.iterdir()):
        if path.is_file() and not path.name.endswith(KEPT) and path.resolve() not in kept:
            path.rename(target / path.name)
    return target


def _run_and_record(cfg: DictConfig, output_dir: Path, multirun: bool) -> None:
    digest = config_digest(cfg)  # before the run: building the parts may touch the config
    if multirun and finished_before(digest, output_dir):
        log.info(
            "skipped %s: it finished before with the same config (its metrics.json stays; "
            "delete %s to run it again)",
            output_dir.name,
            output_dir / FINISHED,
        )
        return
    model_path = OmegaConf.select(cfg, "task.model_path", default=None)
    moved = move_previous_results(output_dir, [Path(model_path)] if model_path else [])
    if moved is not None:
        log.warning(
            "%s held the results of another run (another config, a failure or a rerun): moved "
            "to %s, so that its metrics.json is this run's alone",
            output_dir,
            moved,
        )
    try:
        run(cfg, output_dir)
        write_json_atomic(
            output_dir / FINISHED,
            {"config_sha256": digest, "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")},
        )
    except Exception as error:
        message = _record_failure(output_dir, error)
        log.error(message)
        if multirun:
            return  # recorded in error.json; the other jobs of the sweep go on
        if isinstance(error, (ValueError, InstantiationException, RuntimeError)):
            print(f"error: {message}", file=sys.stderr)
            sys.exit(2)
        print(f"error: {message} (traceback in {output_dir / 'error.json'})", file=sys.stderr)
        sys.exit(1)


def main() -> None:
    """``python -m harness``: the Hydra app, every failure in one line ``error: ...``.

    Hydra prints its own errors (an override of the wrong type, a missing option, an unknown
    key: found while composing, before the job starts) over several lines and exits 1. With
    ``HYDRA_FULL_ERROR=1`` it raises them instead; this wrapper sets it, prints them in one line
    and exits 2. A user who sets ``HYDRA_FULL_ERROR=1`` gets Hydra's full traceback as before.
    """
    if os.environ.get("HYDRA_FULL_ERROR") == "1":
        _job()
        return
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        _job()
    except KeyboardInterrupt:  # Ctrl-C: every file is written atomically, a training resumes
        print(  # on its own line: a progress bar may have been cut mid-line
            "\ninterrupted: what finished is in the run directory; the same command resumes "
            "(a training from its checkpoint, a sweep from its unfinished jobs)",
            file=sys.stderr,
        )
        sys.exit(130)
    except Exception as error:
        print(f"error: {composition_error(error)}", file=sys.stderr)
        sys.exit(2)
    finally:
        os.environ.pop("HYDRA_FULL_ERROR", None)
