"""One line naming the machine a benchmark ran on (benchmarks on shared machines need it)."""

from __future__ import annotations

import os
import platform
from pathlib import Path

# x86-64 CPU families by vendor and family number: a virtual machine's model name is often just
# "AMD EPYC", and two such machines of different generations differ 2-3x in a Python-bound step
# (docs/findings/real_time.md, "The machine matters").
_GENERATIONS = {
    ("AuthenticAMD", 23): "Zen 1/2",
    ("AuthenticAMD", 25): "Zen 3/4",
    ("AuthenticAMD", 26): "Zen 5",
}


def cpu_fields(text: str) -> dict[str, str]:
    """The first processor's ``key: value`` fields of a /proc/cpuinfo text."""
    fields: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            break  # the first processor's block ends at the first blank line
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    return fields


def cpu_name(fields: dict[str, str]) -> str:
    """Model name, with family/model/stepping, the generation where known, and the clock."""
    name = fields.get("model name", platform.processor() or platform.machine())
    if "cpu family" not in fields:
        return name
    family = int(fields["cpu family"])
    generation = _GENERATIONS.get((fields.get("vendor_id", ""), family))
    model, stepping = fields.get("model", "?"), fields.get("stepping", "?")
    detail = f"family {family} model {model} stepping {stepping}"
    if generation:
        detail += f", {generation}"
    if "cpu MHz" in fields:
        detail += f", {float(fields['cpu MHz']):.0f} MHz"
    return f"{name} ({detail})"


def describe() -> str:
    cpuinfo = Path("/proc/cpuinfo")
    fields = cpu_fields(cpuinfo.read_text()) if cpuinfo.exists() else {}
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{cpu_name(fields)}, {cores} cores available, Python {platform.python_version()}"
