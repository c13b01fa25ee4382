"""The Hydra app behind ``python -m harness``: compose the config, build the parts, run a task."""

from __future__ import annotations

import hashlib
import logging
import sys
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from harness.config import register_configs, validate
from harness.metrics import update_metrics, write_json_atomic
from harness.paths import CONF_DIR

log = logging.getLogger(__name__)

JOB_DIRNAME_BYTES = 200  # file names may have 255 bytes; Hydra adds nothing to the sweep subdir


def job_dirname(overrides: str, limit: int = JOB_DIRNAME_BYTES) -> str:
    """A sweep job's directory: its overrides with ``/`` (a path in a value) as ``_``, cut to
    ``limit`` bytes plus a hash when longer (the full list is in ``.hydra/overrides.yaml``)."""
    raw = overrides.replace("/", "_").encode()
    if len(raw) <= limit:
        return raw.decode()
    digest = hashlib.sha256(raw).hexdigest()[:10]
    return raw[: limit - len(digest) - 1].decode(errors="ignore") + "~" + digest


OmegaConf.register_new_resolver("job_dirname", job_dirname, replace=True)
register_configs()  # before @hydra.main composes: the YAML files extend these schemas


def run(cfg: DictConfig, output_dir: Path) -> dict:
    """Build plant, recorder and task from ``cfg``; run the task; return its metrics sections."""
    task_name = HydraConfig.get().runtime.choices["task"]
    validate(cfg)  # every range check of every block, before anything is built or run
    plant = instantiate(cfg.plant)
    make_recorder = instantiate(cfg.recorder)
    task = instantiate(cfg.task)
    with make_recorder(path=output_dir / f"{task_name}.rrd") as recorder:
        sections = task(plant=plant, recorder=recorder, output_dir=output_dir)
    for section, values in sections.items():
        document = update_metrics(output_dir / "metrics.json", section, values)
    log.info("wrote %s (%s)", output_dir / "metrics.json", ", ".join(document))
    return sections


def _one_line(error: BaseException) -> str:
    while isinstance(error, InstantiationException) and error.__cause__ is not None:
        error = error.__cause__
    return f"{type(error).__name__}: {error}".splitlines()[0]


def _record_failure(output_dir: Path, error: BaseException) -> str:
    """Leave the reason in the run directory, so a sweep's report can name the failed job."""
    message = _one_line(error)
    write_json_atomic(
        output_dir / "error.json",
        {"error": message, "traceback": "".join(traceback.format_exception(error))},
    )
    return message


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def main(cfg: DictConfig) -> None:
    hydra_cfg = HydraConfig.get()
    output_dir = Path(hydra_cfg.runtime.output_dir)
    try:
        run(cfg, output_dir)
    except Exception as error:
        message = _record_failure(output_dir, error)
        log.error(message)
        if hydra_cfg.mode == RunMode.MULTIRUN:
            return  # recorded in error.json; the other jobs of the sweep go on
        if isinstance(error, (ValueError, InstantiationException, RuntimeError)):
            print(f"error: {message}", file=sys.stderr)
            sys.exit(2)
        raise
