"""One line per phase of a run, with its elapsed time: what a user reads while the job works.

A phase says what it did at its end (``data: data=default, 12 drives (34,446 frames) found in
the cache at … (0.9 s)``); the details a phase finds along the way are DEBUG lines
(``hydra.verbose=[harness,controllers]`` shows them).
"""

from __future__ import annotations

import logging
import time
from types import TracebackType

log = logging.getLogger("harness")


def seconds(elapsed_s: float) -> str:
    """``0.4 s``, ``71 s``, ``3 min 12 s``: a duration as a person reads it."""
    if elapsed_s < 10:
        return f"{elapsed_s:.1f} s"
    if elapsed_s < 120:
        return f"{elapsed_s:.0f} s"
    minutes, rest = divmod(round(elapsed_s), 60)
    return f"{minutes} min {rest} s"


class Phase:
    """``with Phase("training") as phase: ...; phase.done = "what it did"``: logs
    ``training: what it did (71 s)`` when the block ends without an error (a failure is the
    run's error line instead)."""

    def __init__(self, name: str) -> None:
        self.name, self.done = name, ""
        self.start = 0.0

    def __enter__(self) -> Phase:
        self.start = time.perf_counter()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if kind is None:
            elapsed = seconds(time.perf_counter() - self.start)
            log.info("%s: %s (%s)", self.name, self.done or "done", elapsed)
