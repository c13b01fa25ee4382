"""The reference of every config group and preset, generated from ``conf/``.

``python -m harness.config_reference`` writes ``docs/reference/config.md``. For each group of
``conf/`` it lists the group's default preset with every key it composes to (its value, and the
comment the YAML gives it), then each other preset with what it changes against that default:
the keys whose composed value differs, each with the comment of the file that sets it. The
comments are the YAML files' own, so a key is documented once, where it is set. A test keeps
the committed page equal to what this module writes.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
import typing
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from hydra.utils import get_class
from omegaconf import DictConfig, ListConfig, OmegaConf

from harness.core.files import write_text_atomic
from harness.core.paths import CONF_DIR, REPO_ROOT

__all__ = ["GROUPS", "PAGE", "field_comments", "key_comments", "reference"]

PAGE = REPO_ROOT / "docs" / "reference" / "config.md"

# The groups a user chooses on the command line, in the order a run composes them, each with the
# package it lands in and one line of what it is.
GROUPS: dict[str, str] = {
    "plant": "the simulated car the data comes from and the controllers drive",
    "data": "the driving data: collected from the plant, or read from logs",
    "learner": "the model fitted to the data",
    "training": "a part of a trained learner's preset: how it trains "
    "(`- /training@training: recipe`)",
    "controller": "the run's own controller (`tracking.*` in metrics.json)",
    "disturbance": "the disturbance estimator of an offset-free controller "
    "(`disturbance@controller.disturbance=<name>`)",
    "horizon": "a part of a controller preset: its horizons (`- /horizon@_here_: long`)",
    "tracking": "a part of a controller preset: what it tracks (`- /tracking@_here_: path`)",
    "task": "what the run does: the whole pipeline, a characterization, or a collection",
    "reference": "what a controller tracks (`+reference@task.references.<name>=<preset>`)",
    "recorder": "where the run's recording goes",
}
# Groups chosen as a whole: their files are shown as written (they override other groups' keys).
GLOBAL_GROUPS = ("experiment",)
_FIELD = re.compile(r"^    (?P<name>[A-Za-z_]\w*): [^=]+?(?P<rest>( = .*)?)$")
_KEY = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_][\w.]*|'[^']*'|\"[^\"]*\"):(?P<rest>.*)$")


def _yaml(group: str, preset: str) -> DictConfig:
    """``conf/<group>/<preset>.yaml`` as written (not composed)."""
    node = OmegaConf.load(CONF_DIR / group / f"{preset}.yaml")
    assert isinstance(node, DictConfig), f"conf/{group}/{preset}.yaml is not a mapping"
    return node


def _comment(text: str) -> str:
    """The text after a YAML comment's ``#``, outside quotes; empty if none."""
    quote = ""
    for i, char in enumerate(text):
        if char in "'\"" and not quote:
            quote = char
        elif char == quote:
            quote = ""
        elif char == "#" and not quote and (i == 0 or text[i - 1] in " \t"):
            return text[i + 1 :].strip()
    return ""


def header(path: Path) -> str:
    """The comment block a YAML file opens with, as one paragraph."""
    lines = []
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        text = line.lstrip("#").strip()
        if not text.startswith("@package"):
            lines.append(text)
    return " ".join(lines).strip()


def key_comments(path: Path) -> dict[str, str]:
    """Each dotted key a YAML file sets, with its inline comment, or the comment lines just
    above it (``defaults`` and list items are not keys)."""
    comments: dict[str, str] = {}
    stack: list[tuple[int, str]] = []
    above: list[str] = []
    in_header = True
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            if not in_header:
                above.append(stripped.lstrip("#").strip())
            continue
        in_header = False
        match = _KEY.match(line)
        if not stripped or stripped.startswith("-") or match is None:
            above = [] if not stripped else above
            continue
        indent, key = len(match["indent"]), match["key"].strip("'\"")
        while stack and stack[-1][0] >= indent:
            stack.pop()
        dotted = ".".join([k for _, k in stack] + [key])
        stack.append((indent, key))
        text = _comment(match["rest"]) or " ".join(above)
        if not dotted.startswith(("defaults", "hydra")):
            comments[dotted] = text
        above = []
    return comments


def _flatten(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(node, DictConfig | ListConfig):  # unresolved: ``???`` and ``${...}`` as written
        node = OmegaConf.to_container(node, resolve=False)
    if isinstance(node, Mapping) and len(node) > 0:
        for key, value in node.items():
            yield from _flatten(value, f"{prefix}.{key}" if prefix else str(key))
    elif prefix:  # a file that sets no key has none to list
        yield prefix, node


def _value(node: Any) -> str:
    text = "null" if node is None else str(node).replace("'", "")
    if isinstance(node, bool):
        text = str(node).lower()
    return f"`{text}`".replace("|", "\\|")


def _composed(group: str, preset: str, chosen_at_top: bool) -> dict[str, Any]:
    """The preset's keys as a run composes them; a group the top level does not choose
    (``chosen_at_top`` false: ``disturbance``, ``reference``, the parts) as its file gives them."""
    from hydra import compose

    if not chosen_at_top:
        node = _yaml(group, preset)
        node.pop("defaults", None)
        return dict(_flatten(node))
    return dict(_flatten(compose(config_name="config", overrides=[f"{group}={preset}"])[group]))


def _chain(group: str, preset: str) -> list[Path]:
    """The preset's file and the files of the same group it builds on (``defaults``), the
    nearest first: where a key's comment is looked for."""
    path = CONF_DIR / group / f"{preset}.yaml"
    files = [path]
    for entry in _yaml(group, preset).get("defaults", []):
        if isinstance(entry, str) and (CONF_DIR / group / f"{entry}.yaml").exists():
            files += _chain(group, entry)
    return files


def field_comments(cls: type, prefix: str = "") -> dict[str, str]:
    """Each field of a settings dataclass with the comment its source gives it (inline, or the
    lines just above), nested dataclasses' fields under their field's name."""
    if not dataclasses.is_dataclass(cls):
        return {}
    hints = typing.get_type_hints(cls)
    comments: dict[str, str] = {}
    for base in reversed([c for c in cls.__mro__ if dataclasses.is_dataclass(c)]):
        above: list[str] = []
        for line in inspect.getsource(base).splitlines()[1:]:
            stripped = line.strip()
            if stripped.startswith("#"):
                above.append(stripped.lstrip("#").strip())
                continue
            match = _FIELD.match(line)
            if match is not None:
                comments[prefix + match["name"]] = _comment(match["rest"]) or " ".join(above)
            above = []
    for field in dataclasses.fields(cls):
        nested = hints.get(field.name)
        if isinstance(nested, type) and dataclasses.is_dataclass(nested):
            comments.update(field_comments(nested, f"{prefix}{field.name}."))
        if field.metadata.get("doc"):
            comments[prefix + field.name] = field.metadata["doc"]
    return comments


def _schemas() -> dict[str, type]:
    """The dataclasses behind the schemas ``harness.config`` stores, by their stored name."""
    from controllers.bicycle_mpc import BicycleMPCConfig
    from controllers.de_mpc import DEMPCConfig
    from harness.config import SedanConfig, learner_classes
    from harness.data.logs import LogsConfig
    from harness.data.store import DataConfig
    from harness.tasks.characterize import Characterize

    return {
        "sedan_schema": SedanConfig,
        "data_schema": DataConfig,
        "logs_schema": LogsConfig,
        "de_mpc_schema": DEMPCConfig,
        "bicycle_mpc_schema": BicycleMPCConfig,
        "characterize_schema": Characterize,
        **{f"{learner.name}_schema": learner.config_class for learner in learner_classes()},
    }


def _settings_class(group: str, preset: str) -> type | None:
    """The dataclass a preset is checked against: the schema it composes (itself or through the
    preset it builds on), else its ``_target_`` if that is a dataclass."""
    node = _yaml(group, preset)
    for entry in node.get("defaults", []):
        if isinstance(entry, str) and entry.endswith("_schema"):
            return _schemas().get(entry)
        if isinstance(entry, str) and (CONF_DIR / group / f"{entry}.yaml").exists():
            return _settings_class(group, entry)
    target = node.get("_target_")
    if isinstance(target, str):
        try:
            cls = get_class(target)
        except (ImportError, ValueError):
            return None
        return cls if dataclasses.is_dataclass(cls) else None
    return None


def _notes(group: str, preset: str) -> dict[str, str]:
    cls = _settings_class(group, preset)
    notes: dict[str, str] = {k: v for k, v in field_comments(cls).items() if v} if cls else {}
    for path in reversed(_chain(group, preset)):
        notes.update(_part_comments(path))
        notes.update({k: v for k, v in key_comments(path).items() if v})
    return notes


def _part_comments(path: Path) -> dict[str, str]:
    """The key comments of the parts a file composes (``- /training@training: recipe``), each
    key under the package the part lands in."""
    comments: dict[str, str] = {}
    node = OmegaConf.load(path)
    for entry in node.get("defaults", []) if isinstance(node, DictConfig) else []:
        if not isinstance(entry, DictConfig):
            continue
        for name, option in entry.items():
            group, _, package = str(name).removeprefix("override ").partition("@")
            part = CONF_DIR / group.strip("/") / f"{option}.yaml"
            if not group.startswith("/") or not part.exists():
                continue
            prefix = "" if package in ("", "_here_") else package + "."
            comments.update({prefix + k: v for k, v in key_comments(part).items() if v})
    return comments


def _defaults() -> dict[str, str]:
    chosen: dict[str, str] = {}
    for entry in _yaml("", "config").defaults:
        if isinstance(entry, DictConfig):
            chosen.update({str(k): str(v) for k, v in entry.items()})
    return chosen


def _presets(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def _group_section(group: str, about: str, default: str | None) -> list[str]:
    presets = _presets(group)
    base = default if default in presets else presets[0]
    lines = [
        f"## {group}",
        "",
        f"`{group}=<preset>`: {about}. Presets: " + ", ".join(f"`{p}`" for p in presets) + ".",
        "",
    ]
    base_values = _composed(group, base, default is not None)
    notes = _notes(group, base)
    role = "the default" if base == default else "the first"
    lines += [f"### {group}={base}", "", f"{header(CONF_DIR / group / f'{base}.yaml')}", ""]
    if base_values:
        lines += [f"Every key ({role} preset):", "", "| key | value | what it is |"]
        lines.append("|---|---|---|")
    else:
        lines.append("It sets no key: every value is its schema's default.")
    lines += [f"| `{k}` | {_value(v)} | {notes.get(k, '')} |" for k, v in base_values.items()]
    for preset in presets:
        if preset == base:
            continue
        values = _composed(group, preset, default is not None)
        notes = _notes(group, preset)
        changed = [
            (k, v)
            for k, v in values.items()
            if k not in base_values or _value(base_values[k]) != _value(v)
        ]
        lines += ["", f"### {group}={preset}", "", header(CONF_DIR / group / f"{preset}.yaml"), ""]
        if not changed:
            lines.append(f"The same keys as `{group}={base}`.")
            continue
        lines += [f"Against `{group}={base}`:", "", "| key | value | what it is |", "|---|---|---|"]
        lines += [f"| `{k}` | {_value(v)} | {notes.get(k, '')} |" for k, v in changed]
    return [*lines, ""]


def reference() -> str:
    """The whole page, as ``python -m harness.config_reference`` writes it."""
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return _page()


def _page() -> str:
    chosen = _defaults()
    lines = [
        "# Config groups and presets",
        "",
        "Generated by `python -m harness.config_reference` from `conf/` (do not edit by hand).",
        "Choose a preset with `<group>=<preset>`, change one key with `<group>.<key>=<value>`",
        "(a key a preset does not list needs a leading `+`). For each group: its default preset",
        "with every key it composes to, then what each other preset changes against it. The notes",
        "are the YAML files' own comments. Logs of your own car: [the data schema]"
        "(../guide/data_schema.md).",
        "",
        "Top level: `seed` (default `0`) seeds the data's driver, the learner and the",
        "dictionaries; `threads` (default `1`) is the job's PyTorch and BLAS threads, set before",
        "any work.",
        "",
    ]
    for group, about in GROUPS.items():
        lines += _group_section(group, about, chosen.get(group))
    for group in GLOBAL_GROUPS:
        lines += [
            f"## {group}",
            "",
            f"`{group}=<preset>` overrides keys of several groups at once; each file as written:",
            "",
        ]
        for preset in _presets(group):
            path = CONF_DIR / group / f"{preset}.yaml"
            body = "\n".join(
                line for line in path.read_text().splitlines() if not line.startswith("# @package")
            )
            lines += [f"### {group}={preset}", "", "```yaml", body.rstrip(), "```", ""]
    return "\n".join(lines).rstrip() + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="fail if the page is not current")
    args = parser.parse_args(argv)
    from harness.config import register_configs

    register_configs()
    text = reference()
    if args.check:
        if not PAGE.exists() or PAGE.read_text() != text:
            raise SystemExit(f"{PAGE} is not current: run python -m harness.config_reference")
        return
    PAGE.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(PAGE, text)
    print(f"wrote {PAGE}")


if __name__ == "__main__":
    main()
