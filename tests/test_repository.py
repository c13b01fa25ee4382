"""The repository speaks of the harness: no file tells the story of its own making."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from harness.core.paths import REPO_ROOT

# How the work was organised, not what the harness is: its sittings, its ticket numbers, who
# keeps it. Topics name findings; commits date them.
DIARY = re.compile(
    r"\bsessions?\b|\bissues? #?[0-9]+|\bthe maintainers\b|\bissues?'", re.IGNORECASE
)
PYTEST_SCOPE = 'scope="session"'  # pytest's own word for a fixture shared by the whole run
TEXT = (".md", ".py", ".yaml", ".yml", ".toml", ".txt", ".cfg", ".c", ".xml", "")


@pytest.mark.skipif(shutil.which("git") is None, reason="lists the tracked files with git")
def test_no_tracked_file_tells_how_the_project_was_made() -> None:
    listed = subprocess.run(
        ["git", "ls-files"], cwd=REPO_ROOT, capture_output=True, text=True, check=False
    )
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    found = []
    for name in listed.stdout.splitlines():
        path = REPO_ROOT / name
        if name == "tests/test_repository.py" or path.suffix not in TEXT or not path.is_file():
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if DIARY.search(line) and PYTEST_SCOPE not in line:
                found.append(f"{name}:{number}: {line.strip()[:100]}")
    assert not found, "name the topic and date it by commit instead:\n" + "\n".join(found)
