"""How big the parts a newcomer opens may grow.

No function over 80 lines and no class over 300 lines or 20 methods in ``harness/``,
``learners/`` and ``controllers/``; no module of ``controllers/`` over 400 lines. The parts
bigger than that today are listed with their size (lines, and methods for a class): they may
shrink, never grow, and none may join them. The list is the work left; a part that shrinks
under the limit leaves it.
"""

from __future__ import annotations

import ast
from pathlib import Path

from harness.core.paths import REPO_ROOT

PACKAGES = ("harness", "learners", "controllers")
FUNCTION_LINES, CLASS_LINES, CLASS_METHODS, CONTROLLER_MODULE_LINES = 80, 300, 20, 400
# (kind, where): (lines, methods)
KNOWN: dict[tuple[str, str], tuple[int, int]] = {}


def oversized(root: Path = REPO_ROOT) -> dict[tuple[str, str], tuple[int, int]]:
    """Every part over its limit, with its size."""
    found: dict[tuple[str, str], tuple[int, int]] = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            name = str(path.relative_to(root))
            text = path.read_text()
            for node in ast.walk(ast.parse(text)):
                lines = (
                    (node.end_lineno or node.lineno) - node.lineno + 1
                    if hasattr(node, "lineno")
                    else 0
                )
                if (
                    isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
                    and lines > FUNCTION_LINES
                ):
                    found["function", f"{name}:{node.name}"] = (lines, 0)
                elif isinstance(node, ast.ClassDef):
                    methods = sum(
                        isinstance(b, ast.FunctionDef | ast.AsyncFunctionDef) for b in node.body
                    )
                    if lines > CLASS_LINES or methods > CLASS_METHODS:
                        found["class", f"{name}:{node.name}"] = (lines, methods)
            if package == "controllers" and len(text.splitlines()) > CONTROLLER_MODULE_LINES:
                found["module", name] = (len(text.splitlines()), 0)
    return found


def test_no_part_grows_past_its_limit_and_the_known_ones_only_shrink() -> None:
    found = oversized()
    new = {key: size for key, size in found.items() if key not in KNOWN}
    assert not new, f"over the limit (split it): {new}"
    grown = {key: (KNOWN[key], size) for key, size in found.items() if size > KNOWN[key]}
    assert not grown, f"grew (known size, now): {grown}"
    done = sorted(set(KNOWN) - set(found))
    assert not done, f"now within the limits: take them off KNOWN: {done}"


def test_the_check_sees_a_long_function(tmp_path: Path) -> None:
    """The measure itself: a 90-line function in a package is found, with its length."""
    package = tmp_path / "learners"
    package.mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(89))
    (package / "long.py").write_text(f"def long():\n{body}\n")
    assert oversized(tmp_path) == {("function", "learners/long.py:long"): (90, 0)}
