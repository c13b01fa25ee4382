"""``metrics.json``: the harness's public result, merged by section and written atomically."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from harness.files import plain, write_json_atomic


def update_metrics(path: Path, section: str, values: Mapping[str, Any]) -> dict[str, Any]:
    """Set ``section`` in ``path`` (keeping the other sections) and return the whole document."""
    document: dict[str, Any] = {}
    if path.exists():
        try:
            document = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise ValueError(
                f"{path} is not valid JSON ({error}); move it away and rerun"
            ) from error
    document[section] = plain(values)
    write_json_atomic(path, document)
    return document
