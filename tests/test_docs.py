"""The documentation a reader relies on: generated pages current, every command named, and pages
short enough to read (`make docs` builds the site strictly; these hold without it)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from harness.core.paths import CONF_DIR, REPO_ROOT

DOCS = REPO_ROOT / "docs"
# Written from data, not by hand: the config and data-schema references, the studies' pages.
GENERATED = ("reference/config.md", "guide/data_schema.md", "results/")
WORDS_IN_ALL = 35_000
WORDS_A_PAGE = 4_000
README_LINES = 200
# A fenced block or a table row is counted; a link target or a block a study generates
# (``<!-- NAME: generated ... -->`` to ``<!-- NAME end -->``) is not hand-written prose.
_LINK_TARGET = re.compile(r"\]\([^)]*\)")
_GENERATED_BLOCK = re.compile(r"<!-- ([^:>]+): generated .*?<!-- \1 end -->", re.DOTALL)


def _hand_written() -> list[Path]:
    pages = [p for p in DOCS.rglob("*.md") if not str(p.relative_to(DOCS)).startswith(GENERATED)]
    return [*sorted(pages), REPO_ROOT / "README.md"]


def _words(path: Path) -> int:
    text = _GENERATED_BLOCK.sub("", path.read_text())
    return len(_LINK_TARGET.sub("]", text).split())


def test_the_hand_written_docs_fit_their_word_budget() -> None:
    counts = {str(p.relative_to(REPO_ROOT)): _words(p) for p in _hand_written()}
    too_long = {page: n for page, n in counts.items() if n > WORDS_A_PAGE}
    assert not too_long, f"pages over {WORDS_A_PAGE} words (split or cut them): {too_long}"
    assert sum(counts.values()) <= WORDS_IN_ALL, f"{sum(counts.values())} words in all"


def test_the_readme_is_one_page() -> None:
    lines = (REPO_ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_LINES, f"README.md has {len(lines)} lines"


def test_the_config_reference_is_generated_from_conf() -> None:
    from harness.config_reference import PAGE, reference

    assert PAGE.read_text() == reference(), "run python -m harness.config_reference"
    text = PAGE.read_text()
    for group in ("plant", "data", "learner", "controller", "task"):
        for preset in (CONF_DIR / group).glob("*.yaml"):
            assert f"### {group}={preset.stem}" in text, f"{group}={preset.stem} is not listed"


def test_a_key_is_documented_by_the_comment_of_the_file_that_sets_it(tmp_path: Path) -> None:
    from harness.config_reference import key_comments

    yaml = tmp_path / "preset.yaml"
    yaml.write_text(
        "# The preset's own header.\n"
        "defaults:\n  - base\n"
        "ridge: 1.0e-4   # chosen on the validation drives\n"
        "# The observables.\n"
        "dictionary:\n"
        "  num_centers: 100   # K centres: '#' inside quotes is not a comment\n"
        "  name: 'a # b'\n"
    )
    assert key_comments(yaml) == {
        "ridge": "chosen on the validation drives",
        "dictionary": "The observables.",
        "dictionary.num_centers": "K centres: '#' inside quotes is not a comment",
        "dictionary.name": "",
    }


def test_every_command_line_is_on_the_cli_page() -> None:
    page = (DOCS / "reference" / "cli.md").read_text()
    modules = []
    for folder in ("harness", "bench", "learners", "controllers"):
        for path in (REPO_ROOT / folder).rglob("*.py"):
            if 'if __name__ == "__main__"' in path.read_text():
                parts = path.relative_to(REPO_ROOT).with_suffix("").parts
                modules.append(".".join(parts[:-1] if parts[-1] == "__main__" else parts))
    missing = [m for m in modules if f"python -m {m}" not in page]
    assert modules and not missing, f"not on docs/reference/cli.md: {missing}"


@pytest.mark.parametrize("page", ["README.md", "docs/index.md"])
def test_every_question_a_user_asks_is_a_link_away(page: str) -> None:
    """Running on your own logs, what every preset does, what a metric means, and why the
    paper's model misses vx: each linked from the first page a reader opens."""
    text = (REPO_ROOT / page).read_text()
    for target in ("data_schema.md", "config.md", "metrics.md", "deep_edmd_vx.md"):
        assert target in text, f"{page} does not link {target}"
