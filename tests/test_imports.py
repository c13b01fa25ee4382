"""The import graph of our packages has no circle and follows the layers: every module can be read
(and imported) after the modules it uses, a newcomer can read the tree bottom-up, and a learner or
a controller is usable without the simulator."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from harness.core.paths import REPO_ROOT

PACKAGES = ("harness", "learners", "controllers")


def module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking_only(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def imported(
    tree: ast.AST, module: str, is_package: bool, known: set[str], types: bool = False
) -> set[str]:
    """Our modules that ``module`` imports anywhere (a function-level import closes a circle at
    run time too), except under ``if TYPE_CHECKING:`` unless ``types``."""
    found: set[str] = set()
    stack: list[ast.AST] = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _type_checking_only(node) and not types:
            stack.extend(node.orelse)
            continue
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package that holds this module
                anchor = module.split(".")
                anchor = anchor[: len(anchor) - node.level + (1 if is_package else 0)]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                found.add(submodule if submodule in known else base)
        stack.extend(ast.iter_child_nodes(node))
    return {name for name in found if name in known and name != module}


def import_graph(root: Path = REPO_ROOT, types: bool = False) -> dict[str, set[str]]:
    files = {
        module_name(path, root): path
        for package in PACKAGES
        for path in sorted((root / package).rglob("*.py"))
    }
    known = set(files)
    return {
        name: imported(ast.parse(path.read_text()), name, path.name == "__init__.py", known, types)
        for name, path in files.items()
    }


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One circle of ``graph`` as a list of modules (first == last), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def test_the_import_graph_has_no_circle() -> None:
    graph = import_graph()
    assert {"harness.tasks.pipeline", "learners.base", "controllers.de_mpc"} <= set(graph)
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle or [])


def test_the_core_has_no_circle_even_through_type_only_imports() -> None:
    """The layers' floor reads straight: the contracts and the episodes (whose names live in
    harness/core/names.py) do not import each other, not even for type hints."""
    graph = import_graph(types=True)
    core = {name: {m for m in to if m.startswith("harness.core")} for name, to in graph.items()}
    core = {name: to for name, to in core.items() if name.startswith("harness.core")}
    cycle = find_cycle(core)
    assert cycle is None, " -> ".join(cycle or [])


def test_a_circle_through_a_function_level_import_is_found(tmp_path: Path) -> None:
    """The check sees what the old report had: a module-level import one way, a function-level
    one back; an import only for type checking is no circle."""
    package = tmp_path / "harness"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from harness.b import f\n")
    (package / "b.py").write_text("def f():\n    from harness.a import g\n")
    (package / "c.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from harness.a import g\n"
    )
    for name in ("learners", "controllers"):
        (tmp_path / name).mkdir()
    graph = import_graph(tmp_path)
    assert find_cycle(graph) == ["harness.a", "harness.b", "harness.a"]
    assert graph["harness.c"] == set()


# The layers: each unit (a top-level package, or a package or module of ``harness``) and the units
# it may import. Written once, here; each package's ``__init__`` docstring says the same.
ALLOWED: dict[str, set[str]] = {
    "harness.core": set(),
    "learners": {"harness.core"},
    "controllers": {"harness.core", "learners"},
    "harness.plant": {"harness.core"},
    "harness.output": {"harness.core"},
    "harness.recorder": set(),
    "harness.references": {"harness.core", "harness.output", "harness.recorder"},
    "harness.data": {"harness.core", "harness.plant", "harness.output", "harness.recorder"},
    "harness.evaluation": {
        "harness.core",
        "harness.plant",
        "harness.output",
        "harness.recorder",
        "harness.references",
        "learners",
    },
    # The composition root: it knows every schema.
    "harness.config": {
        "harness.core",
        "harness.plant",
        "harness.data",
        "harness.tasks",
        "learners",
        "controllers",
    },
    # The config reference page: reads conf/ and the schemas' dataclasses (docs tooling).
    "harness.config_reference": {
        "harness.core",
        "harness.config",
        "harness.data",
        "harness.tasks",
        "controllers",
    },
    "harness.tasks": {
        "harness.core",
        "harness.plant",
        "harness.output",
        "harness.recorder",
        "harness.references",
        "harness.data",
        "harness.evaluation",
        "learners",
        "controllers",
    },
    "harness.report": {
        "harness.core",
        "harness.output",
        "harness.references",
        "harness.evaluation",
    },
    "harness.app": {"harness.core", "harness.output", "harness.config", "harness.report"},
    "harness.__main__": {"harness.app"},
    # The package itself pins the numerical kernels before any layer loads NumPy.
    "harness": {"harness.core"},
}


def unit(module: str) -> str:
    """The layer unit a module belongs to: ``learners.edmd`` -> ``learners``,
    ``harness.core.files`` -> ``harness.core``, ``harness.app`` -> ``harness.app``."""
    parts = module.split(".")
    return ".".join(parts[:2]) if parts[0] == "harness" else parts[0]


def arrows(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The graph between units, each unit's imports of itself left out."""
    found: dict[str, set[str]] = {}
    for module, imports in graph.items():
        found.setdefault(unit(module), set()).update(unit(m) for m in imports)
    return {name: targets - {name} for name, targets in found.items()}


def test_every_import_follows_an_allowed_arrow() -> None:
    graph = import_graph()
    units = arrows(graph)
    assert set(units) == set(ALLOWED), "a unit was added or removed: list it in ALLOWED"
    against = {
        f"{module} imports {target}"
        for module, imports in graph.items()
        for target in imports
        if unit(target) != unit(module) and unit(target) not in ALLOWED[unit(module)]
    }
    assert against == set()


def test_the_allowed_arrows_form_layers() -> None:
    """No circle between units, and the core imports nothing of the project."""
    assert find_cycle(ALLOWED) is None
    assert ALLOWED["harness.core"] == set()


def test_an_arrow_against_the_layers_is_caught(tmp_path: Path) -> None:
    """A learner that imports the plant is what the layer test exists to refuse."""
    for package in ("harness", "harness/core", "harness/plant", "learners", "controllers"):
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "harness/plant/sedan.py").write_text("import numpy\n")
    (tmp_path / "learners/edmd.py").write_text("from harness.plant.sedan import numpy\n")
    graph = import_graph(tmp_path)
    wrong = [
        (m, t) for m, ts in graph.items() for t in ts if unit(t) not in ALLOWED[unit(m)] | {unit(m)}
    ]
    assert wrong == [("learners.edmd", "harness.plant.sedan")]


@pytest.mark.parametrize(
    "package", ["learners", "controllers", "harness.plant", "harness.report", "harness.tasks"]
)
def test_each_package_says_what_it_may_import(package: str) -> None:
    import importlib

    docstring = importlib.import_module(package).__doc__ or ""
    assert "May import" in docstring or "may import" in docstring
    for target in ALLOWED[package]:
        assert f"``{target}``" in docstring, f"{package}'s docstring does not name {target}"


def test_learners_and_controllers_load_neither_the_simulator_nor_the_recorder() -> None:
    """In a fresh interpreter: the layers hold at run time, not only in the source."""
    code = (
        "import sys, learners, controllers\n"
        "print(sorted(m for m in ('mujoco', 'rerun', 'matplotlib') if m in sys.modules))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert result.stdout.strip() == "[]"
