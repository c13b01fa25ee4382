"""Every committed study's tables are its data's: re-rendered here, they equal what is committed
(``docs/results/<study>.md`` and its CSVs), so a hand-edited or stale number fails."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from harness.report.studies import DOCS_DIR, render, studies

STUDIES = studies()


def test_there_is_a_committed_study() -> None:
    assert STUDIES, "results/ holds no study (a folder with README.md beside its jobs)"


@pytest.mark.parametrize("study", STUDIES, ids=lambda path: path.name)
def test_a_committed_study_renders_to_exactly_its_committed_tables(
    study: Path, tmp_path: Path
) -> None:
    markdown = render(study, tmp_path)
    committed = DOCS_DIR / markdown.name
    assert markdown.read_text() == committed.read_text(), (
        f"{committed} differs from its data: run python -m harness.report.studies {study.name}"
    )
    rendered = sorted(p.name for p in (tmp_path / study.name).glob("*.csv"))
    assert rendered == sorted(p.name for p in (DOCS_DIR / study.name).glob("*.csv"))
    for name in rendered:
        assert (tmp_path / study.name / name).read_text() == (
            DOCS_DIR / study.name / name
        ).read_text(), name


def test_a_number_changed_in_a_study_changes_its_tables(tmp_path: Path) -> None:
    """The check above can fail: one job's RMSE moved, the rendered table moves with it."""
    study = tmp_path / STUDIES[0].name
    shutil.copytree(STUDIES[0], study, ignore=shutil.ignore_patterns("report"))
    job = next(path.parent for path in sorted(study.glob("*/metrics.json")))
    metrics = json.loads((job / "metrics.json").read_text())
    episode = metrics["data"]["split"]["test"][0]
    metrics["prediction"][episode]["rmse_window_41"]["vx"] += 1.0
    (job / "metrics.json").write_text(json.dumps(metrics))
    changed = render(study, tmp_path / "docs").read_text()
    assert changed != (DOCS_DIR / f"{study.name}.md").read_text()
