"""Every committed study's tables are its data's: re-rendered here, they equal what is committed
(``docs/results/<study>.md`` and its CSVs), so a hand-edited or stale number fails."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import pytest

from harness.core.paths import REPO_ROOT
from harness.report.headline import (
    BLOCKS,
    LANE_CHANGE,
    PAPER,
    begin,
    headline,
    logs,
    main_job,
    paper_model,
    paper_reported,
    replace_blocks,
)
from harness.report.studies import DOCS_DIR, RESULTS_DIR, render, studies
from tests.helpers import learner_config

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


def test_no_generated_page_holds_a_path_outside_the_repository() -> None:
    """The report is rendered in a scratch copy: none of its paths may leak into the pages."""
    scratch = tempfile.gettempdir()
    leaked = [
        path
        for path in sorted(DOCS_DIR.rglob("*"))
        if path.suffix in (".md", ".csv") and scratch in path.read_text()
    ]
    assert not leaked, f"{scratch} in {leaked[:3]}"


@pytest.mark.parametrize("damage", ["truncated", "removed"])
def test_an_incomplete_study_is_not_published(tmp_path: Path, damage: str) -> None:
    """A job's metrics.json torn, or a seed's directory gone: refused naming the job, nothing
    written (its tables and the headline would have counted fewer seeds under the same text)."""
    study = tmp_path / "main_job"
    shutil.copytree(RESULTS_DIR / "main_job", study)
    job = study / "dnn_s1"
    if damage == "truncated":
        text = (job / "metrics.json").read_text()
        (job / "metrics.json").write_text(text[: len(text) // 2])
    else:
        shutil.rmtree(job)
    refused = r"main_job is incomplete: .*(dnn_s1|seed=1).*rerun or restore"
    with pytest.raises(ValueError, match=refused):
        render(study, tmp_path / "docs")
    assert not (tmp_path / "docs").exists()


def copied_study(name: str, tmp_path: Path) -> Path:
    """A committed study copied to edit (its generated report left behind)."""
    study = tmp_path / name
    shutil.copytree(RESULTS_DIR / name, study, ignore=shutil.ignore_patterns("report"))
    return study


@pytest.mark.parametrize("name", BLOCKS)
def test_every_generated_table_of_the_readme_and_docs_is_its_studys_data(name: str) -> None:
    study, _, document = BLOCKS[name]
    text = (REPO_ROOT / document).read_text()
    assert begin(name, study) in text, f"{document} has no {name} block"
    assert replace_blocks(text, RESULTS_DIR) == text, (
        f"{document}'s generated tables differ from their data: run "
        "python -m harness.report.studies"
    )


def test_the_logs_table_counts_a_diverged_seed_instead_of_averaging_it(tmp_path: Path) -> None:
    """One seed's whole run diverged: its learner's whole-run cells say so and average the
    others; its windows (finite) still count every seed."""
    study = copied_study(BLOCKS["logs"][0], tmp_path)
    before = logs(study)
    job = study / "input_edmd_s0"
    metrics = json.loads((job / "metrics.json").read_text())
    metrics["prediction"][metrics["data"]["split"]["test"][0]]["diverged"] = True
    (job / "metrics.json").write_text(json.dumps(metrics))
    after = logs(study)
    whole = after.split("**whole runs**")[1]
    row = next(line for line in whole.splitlines() if line.startswith("| input_edmd |"))
    assert row.count("(1 of 3 seeds diverged)") == 3
    assert after.split("**whole runs**")[0] == before.split("**whole runs**")[0]


def test_the_logs_table_counts_the_runs_that_do_not_beat_persistence(tmp_path: Path) -> None:
    """A verdict in one job's metrics marks its learner's cell of that window and state, and
    nothing else: jobs without the verdict (before it existed) read as they did."""
    study = copied_study(BLOCKS["logs"][0], tmp_path)
    before = logs(study)
    job = study / "elm_edmd_s0"  # its jobs predate the verdict
    metrics = json.loads((job / "metrics.json").read_text())
    tests = metrics["data"]["split"]["test"]
    metrics["prediction"][tests[0]]["beats_persistence"] = {
        "3s": {"vx": True, "vy": False, "yaw_rate": True}
    }
    (job / "metrics.json").write_text(json.dumps(metrics))
    after = logs(study)
    windows = after.split("**1.5 s windows**")[0]
    row = next(line for line in windows.splitlines() if line.startswith("| elm_edmd |"))
    runs = 3 * len(tests)  # three seeds
    assert row.count(f"(worse than persistence on 1 of {runs} runs)") == 1
    assert row.split(" | ")[3].endswith(f"(worse than persistence on 1 of {runs} runs)")  # vy
    assert after.replace(f" (worse than persistence on 1 of {runs} runs)", "") == before


def test_the_headline_counts_a_lane_change_that_no_longer_passed(tmp_path: Path) -> None:
    """The check above can fail: one seed's 80 km/h pass turned into a fail moves its cell."""
    study = copied_study(BLOCKS["headline"][0], tmp_path)
    before = headline(study)
    job = next(p.parent for p in sorted(study.rglob("metrics.json")) if "input_edmd" in str(p))
    metrics = json.loads((job / "metrics.json").read_text())
    runs = metrics["tracking"]["controllers"][PAPER][LANE_CHANGE]
    runs["path"]["passed"] = not runs["path"]["passed"]
    (job / "metrics.json").write_text(json.dumps(metrics))
    assert headline(study) != before


@pytest.mark.parametrize(
    ("preset", "model"),
    [
        ("deep_edmd", "Deep EDMD"),
        ("deep_edmd_paper", "Deep EDMD"),
        ("deep_edmd_random_layer", "Deep EDMD, random layer"),
        ("dnn", "DNN"),
        ("dnn_random_layer", "DNN, random layer"),
        ("edmd", "EDMD"),
        ("elm_edmd", "ELM-EDMD"),
        ("bilinear_deep_edmd", None),
        ("deep_edmd_split", None),
        ("input_edmd", None),
        ("single_track", None),
    ],
)
def test_a_preset_is_the_papers_model_by_what_it_builds(preset: str, model: str | None) -> None:
    """The learner's class (and EDMD's dictionary) names the paper's model, whatever the
    preset's recipe; an extended or wrapped model (bilinear, the pedal split) and ours are not
    the paper's."""
    assert paper_model(learner_config(preset)) == model


def test_the_headline_sets_each_paper_model_beside_the_papers_own_numbers() -> None:
    """Deep EDMD's cell is the mean of the paper's two test episodes, (0.75, 0.04, 0.02) and
    (1.15, 0.08, 0.05); a model that is not the paper's has none."""
    assert paper_reported("Deep EDMD") == "0.95 / 0.06 / 0.035"
    assert paper_reported(None) == "—"
    table = headline(RESULTS_DIR / BLOCKS["headline"][0])
    rows = {r.split(" | ")[0].lstrip("| "): r.split(" | ") for r in table.splitlines()[2:]}
    assert rows["deep_edmd"][3] == rows["deep_edmd_paper"][3] == paper_reported("Deep EDMD")
    assert rows["elm_edmd"][3] == paper_reported("ELM-EDMD") != rows["edmd"][3]
    assert rows["bilinear_deep_edmd"][3] == rows["input_edmd"][3] == "—"


def test_a_readme_without_a_generated_block_is_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match="no generated block") as error:
        replace_blocks("# a README\n", RESULTS_DIR)
    assert "\n" not in str(error.value)


def test_the_main_job_table_marks_a_state_not_better_than_persistence(tmp_path: Path) -> None:
    study = copied_study(BLOCKS["main job"][0], tmp_path)
    for path in study.glob("*/metrics.json"):  # every verdict gone, as in jobs before it
        metrics = json.loads(path.read_text())
        for result in metrics["prediction"].values():
            result.pop("beats_persistence", None)
        path.write_text(json.dumps(metrics))
    assert "†" not in main_job(study)  # no verdict: unmarked
    job = study / "deep_edmd_s1"
    metrics = json.loads((job / "metrics.json").read_text())
    test = metrics["data"]["split"]["test"][0]
    metrics["prediction"][test]["beats_persistence"] = {
        "open_loop": {"vx": False, "vy": True, "yaw_rate": True}
    }
    (job / "metrics.json").write_text(json.dumps(metrics))
    after = main_job(study)
    row = next(line for line in after.splitlines() if line.startswith("| deep_edmd |"))
    assert row.split(" | ")[2].split(" / ")[0].endswith("†")  # vx, open loop
    assert row.split(" | ")[2].count("†") == 1
    assert "†: not better than persistence (the state held) on at least one test drive." in after
