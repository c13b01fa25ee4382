"""controllers.blas: one BLAS thread inside a controller's block, the caller's count after it."""

import pytest

from controllers.blas import single_threaded
from harness.core.threads import openblas


def test_single_threaded_runs_every_openblas_on_one_thread_and_restores_the_count() -> None:
    libraries = openblas()
    if not libraries:
        pytest.skip("no OpenBLAS is loaded in this process")
    original = [int(get()) for _, get in libraries]
    try:
        for set_threads, _ in libraries:
            set_threads(2)
        before = [int(get()) for _, get in libraries]  # 2, or what this machine allows
        with single_threaded():
            assert [int(get()) for _, get in libraries] == [1] * len(libraries)
        assert [int(get()) for _, get in libraries] == before
        with pytest.raises(RuntimeError), single_threaded():  # restored on an error as well
            raise RuntimeError("inside the block")
        assert [int(get()) for _, get in libraries] == before
    finally:
        for (set_threads, _), count in zip(libraries, original, strict=True):
            set_threads(count)
