"""``python -m harness.report SWEEP_DIR``: the paper's tables and figures from a sweep.

Every job directory of a Hydra multirun is read into a run (``jobs.py``: the learner, plant and
controller Hydra chose for it, its seed, its overrides, and its metrics or error); the runs make
the tables (``tables.py``; numbers are mean ± std over the runs that differ only by seed, and any
other override that differs within the sweep names a ``variant``) and the figures
(``figures.py``). Writes ``report.md``, one CSV per table and the figures into
``SWEEP_DIR/report/``; failed jobs (an ``error.json``) and unfinished ones (no
``metrics.json``) are listed by name, never dropped silently. Every sweep runs it at its end
(:class:`WriteReport`, a Hydra callback); rerun it by hand on a sweep still in progress.
"""

from __future__ import annotations

import argparse
import csv
import logging
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from harness.report.figures import figures
from harness.report.jobs import HYDRA_FILE, Run, read_runs
from harness.report.tables import Table, tables

log = logging.getLogger(__name__)

__all__ = ["Run", "Table", "WriteReport", "main", "read_runs", "report"]


def report(sweep_dir: Path) -> Path:
    """Write the tables and figures for ``sweep_dir``; return the Markdown file."""
    runs = read_runs(sweep_dir)
    if not runs:
        raise ValueError(f"{sweep_dir} holds no Hydra job directories ({HYDRA_FILE})")
    finished = [r for r in runs if r.metrics is not None and r.error is None]
    out = sweep_dir / "report"
    out.mkdir(exist_ok=True)
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
        with (out / f"{name}.csv").open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(table.columns)
            writer.writerows(table.rows)
    written = figures(finished, out)
    if written:
        sections += ["### Figures", ""]
        sections += [f"![{p.stem}]({p.relative_to(out).as_posix()})" for p in written]
        sections.append("")
    markdown = out / "report.md"
    markdown.write_text("\n".join(sections))
    return markdown


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
