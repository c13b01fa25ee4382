"""One BLAS thread while a controller computes: small products must not wait for busy cores.

NumPy and SciPy each bundle an OpenBLAS that, by default, splits every product above a few
thousand multiply-adds over all cores. For the time-varying DE-MPC, which rebuilds matrices of
a few hundred rows every 10 ms, that is a loss even on an idle machine and a disaster on a
shared one: measured on the 2 shared cores of this project (load 4.9), a 60/50 step on a
four-state bilinear model took 200 ms with the default threads and 7 ms with one.
:func:`single_threaded` sets every loaded OpenBLAS to one thread for the duration of a block
and restores the previous count (the libraries' own setters: ``harness.core.threads.openblas``).
"""

from __future__ import annotations

from harness.core.threads import openblas


class single_threaded:  # noqa: N801  (used as a function: ``with single_threaded():``)
    """Every loaded OpenBLAS at one thread inside the block (a no-op where none is found).

    A class, not a generator: it is entered twice in every control step, and the generator
    machinery of ``contextmanager`` cost as much as the thread switch; a library already at
    one thread is left alone."""

    __slots__ = ("_before",)

    def __enter__(self) -> None:
        libraries = openblas()
        self._before = [int(get()) for _, get in libraries]
        for (set_threads, _), count in zip(libraries, self._before, strict=True):
            if count != 1:
                set_threads(1)

    def __exit__(self, *_: object) -> None:
        for (set_threads, _), count in zip(openblas(), self._before, strict=True):
            if count != 1:
                set_threads(count)
