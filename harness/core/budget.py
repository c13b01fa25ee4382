"""What a config asks of the machine, estimated before any work, and refused when absurd.

A config can ask for more memory than any machine has (``learner.dictionary.num_centers=1e9``,
``controller.Np=100000``): the run would collect data and then grow until killed, or end in a
traceback about a failed allocation. Each part estimates its own peak (the learner from its
sizes and the longest episode, the controller from its horizons) and :func:`check_memory`
refuses, in one line naming the key, an estimate beyond this machine's physical memory. The
estimates are lower bounds of the big arrays alone, so a refusal is never a false alarm.
"""

from __future__ import annotations

import os

__all__ = ["check_memory", "physical_memory_bytes", "readable_bytes"]


def physical_memory_bytes() -> int:
    """This machine's RAM; 2**62 where the OS does not say (then nothing is refused)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, OSError, ValueError):
        return 2**62


def readable_bytes(count: float) -> str:
    """``447 GiB``: a byte count as a person reads it."""
    value = float(min(count, 10**300))  # an absurd integer stays printable
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if value < 1024 or unit == "PiB":
            return f"{value:.3g} {unit}"
        value /= 1024
    raise AssertionError("unreachable")


def check_memory(key: str, what: str, needed_bytes: float) -> None:
    """Refuse ``needed_bytes`` beyond physical memory, naming the config ``key`` that sets it."""
    total = physical_memory_bytes()
    if needed_bytes > total:
        raise ValueError(
            f"{key}: {what} needs at least {readable_bytes(needed_bytes)} of memory, more than "
            f"this machine's {readable_bytes(total)}"
        )
