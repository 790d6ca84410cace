"""Process pools that are safe with OpenCV, GTSAM (TBB) and Open3D loaded.

Forking a process that already runs library thread pools copies locks held by threads that do
not exist in the child: OpenCV's ``setNumThreads`` then deadlocks in the child (seen in the test
suite). Workers therefore start from a clean ``forkserver`` process.

A worker started that way re-imports the script that started it (as Python's multiprocessing
does for ``spawn`` and ``forkserver``): a script that calls the library at import time, without
an ``if __name__ == "__main__":`` guard, would calibrate again in every worker, which fails with
a long ``BrokenProcessPool`` traceback. :func:`process_context` stops that with one clear line.
"""

from __future__ import annotations

import multiprocessing
import sys
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing.context import BaseContext
from pathlib import Path

from .errors import ConfigError, RgbdCalibError

GUARD = 'if __name__ == "__main__":'


def check_entry_point() -> None:
    """Refuse to start worker processes from a script without a ``__main__`` guard.

    In a worker that is still re-importing the script (the script called the library at import
    time anyway), exit quietly: the parent reports it. In the parent, a ``.py`` main script
    whose text has no ``__main__`` at all is refused before any worker starts."""
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        raise SystemExit(1)
    path = getattr(sys.modules.get("__main__"), "__file__", None)
    if not path or not str(path).endswith(".py"):
        return  # interactive, python -c, a notebook, a frozen entry point
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return
    if "__main__" not in text:
        raise ConfigError(
            f"{path}: calls rgbd-calib at import time, but its worker processes re-import this "
            f"script; put the calls in a function called under `{GUARD}` (README, Library use)"
        )


def process_context() -> BaseContext:
    """The multiprocessing context every pool of the package uses (after
    :func:`check_entry_point`)."""
    check_entry_point()
    return multiprocessing.get_context("forkserver")


class WorkerPool(ProcessPoolExecutor):
    """The package's process pool: :func:`process_context` workers, and a worker that dies
    (the script re-imported without its guard, or the system out of memory) is one clear
    error instead of a ``BrokenProcessPool`` traceback."""

    def __init__(self, max_workers: int | None = None, **kwargs) -> None:
        super().__init__(max_workers, mp_context=process_context(), **kwargs)

    def map(self, fn, *iterables, timeout=None, chunksize=1) -> Iterator:
        results = super().map(fn, *iterables, timeout=timeout, chunksize=chunksize)

        def explained() -> Iterator:
            try:
                yield from results
            except BrokenProcessPool:
                raise RgbdCalibError(
                    "a worker process stopped: when this runs from a script, put its calls "
                    f"in a function called under `{GUARD}` (README, Library use); otherwise "
                    "the machine may be out of memory: use fewer workers"
                ) from None

        return explained()
