"""``python -m harness.report SWEEP_DIR``: the paper's tables and figures from a sweep.

For a query of your own, :func:`load` (``harness/report/frame.py``) returns the same runs as one
pandas table, a row per job × controller × reference, every metric a column.

Every job directory of a Hydra multirun is read into a run (``jobs.py``: the learner, plant and
controller Hydra chose for it, its seed, its overrides, and its metrics or error); the runs make
the tables (``tables.py``; numbers are mean ± std over the runs that differ only by seed, and any
other override that differs within the sweep names a ``variant``) and the figures
(``figures.py``). Writes ``report.md``, one CSV per table and the figures into
``SWEEP_DIR/report/``; failed jobs (an ``error.json``), unfinished ones (no ``metrics.json``),
unreadable ones and those the sweep never started (``multirun.yaml`` names them) are listed by
name, never dropped silently. Every sweep runs it at its end (:class:`WriteReport`, a Hydra
callback); rerun it by hand on a sweep still in progress.

The report owns ``SWEEP_DIR/report/``: each run builds it anew beside it and swaps it in, so no
file of an earlier report outlives it (a table that is empty now, a figure of a job since
gone), and a report killed while it writes leaves the previous one in place. Half-written
files killed jobs left (``.NAME.XXXX.tmp``) are removed from every job directory no run holds.

May import ``harness.core``, ``harness.output``, ``harness.references`` and
``harness.evaluation`` (to redraw the runs' arrays).
"""

from __future__ import annotations

import argparse
import csv
import io
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from harness.core.files import remove_stale_temporaries, try_lock, umask, write_text_atomic
from harness.report.figures import figures
from harness.report.frame import load
from harness.report.jobs import HYDRA_FILE, Run, read_runs
from harness.report.tables import Table, tables

log = logging.getLogger(__name__)

__all__ = ["Run", "Table", "WriteReport", "load", "main", "read_runs", "report"]


REPORT_LOCK = ".report.lock"  # in the sweep directory: one report of a sweep at a time


def report(sweep_dir: Path) -> Path:
    """Write the tables and figures for ``sweep_dir``; return the Markdown file."""
    if not sweep_dir.is_dir():
        state = "is not a directory" if sweep_dir.exists() else "does not exist"
        raise ValueError(f"{sweep_dir} {state}; give the sweep's directory (hydra.sweep.dir)")
    runs = read_runs(sweep_dir)
    if not runs:
        raise ValueError(f"{sweep_dir} holds no Hydra job directories ({HYDRA_FILE})")
    lock = try_lock(sweep_dir / REPORT_LOCK)
    if lock is None:
        raise ValueError(
            f"another process is writing the report of {sweep_dir} (it holds "
            f"{sweep_dir / REPORT_LOCK}); wait for it to end"
        )
    try:
        for run in runs:
            if run.path.is_dir():
                for path in remove_stale_temporaries(run.path) or []:
                    log.info("removed %s (left by a killed writer)", path)
        for leftover in sweep_dir.glob(".report.*.tmp"):  # of a killed report; we hold the lock
            shutil.rmtree(leftover, ignore_errors=True)
        out = sweep_dir / "report"
        staging = Path(tempfile.mkdtemp(dir=sweep_dir, prefix=".report.", suffix=".tmp"))
        try:
            os.chmod(staging, 0o777 & ~umask())  # mkdtemp's 0700 would hide it from colleagues
            _write(sweep_dir, runs, staging)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        previous = staging.with_suffix(".old.tmp")
        if out.exists():
            out.rename(previous)
        staging.rename(out)
        shutil.rmtree(previous, ignore_errors=True)
    finally:
        os.close(lock)
    return out / "report.md"


def _write(sweep_dir: Path, runs: list[Run], out: Path) -> None:
    """``report.md``, the tables' CSVs and the figures of ``runs`` into the empty ``out``."""
    finished = [r for r in runs if r.metrics is not None and r.error is None]
    sections = [
        f"# Sweep report: {sweep_dir}",
        "",
        f"{len(finished)} of {len(runs)} jobs finished.",
        "",
    ]
    for name, table in tables(runs).items():
        if not table.rows:
            continue
        sections.append(table.markdown())
        rows = io.StringIO(newline="")
        writer = csv.writer(rows)
        writer.writerow(table.columns)
        writer.writerows(table.rows)
        write_text_atomic(out / f"{name}.csv", rows.getvalue())
    written = figures(finished, out)
    if written:
        sections += ["### Figures", ""]
        sections += [f"![{p.stem}]({p.relative_to(out).as_posix()})" for p in written]
        sections.append("")
    write_text_atomic(out / "report.md", "\n".join(sections))


class WriteReport(Callback):
    """Every sweep ends with its report (``hydra.callbacks.report`` in ``conf/config.yaml``)."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            log.info("sweep report: %s", report(sweep_dir))
        except Exception as error:  # the jobs' results stand; the report can be rerun by hand
            log.error("no report (%s); run: python -m harness.report %s", error, sweep_dir)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep_dir", type=Path)
    args = parser.parse_args(argv)
    try:
        path = report(args.sweep_dir)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(path.read_text())
    return 0
