"""Ctrl-C around the steps that must not be cut in half, and what a run has already finished.

A command may be interrupted (KeyboardInterrupt) anywhere, and that is safe wherever it only
loses work in progress. Renaming a set of files into place is the exception: cut in the middle,
a folder would hold half of one run and half of another. :func:`sigint_deferred` holds Ctrl-C
back for such a block and raises it once the block is done. :func:`mark_committed` records an
output folder the process has finished writing, so the message after an interrupt can say
the truth: the results are complete, rather than "left untouched".
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_COMMITTED: list[Path] = []  # this process's finished output folders, in order


@contextmanager
def sigint_deferred() -> Iterator[None]:
    """Hold Ctrl-C back until the block is done (main thread only), then raise it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, _frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


def mark_committed(folder: Path) -> None:
    """Record that ``folder`` now holds this process's complete results."""
    folder = Path(folder)
    if folder not in _COMMITTED:
        _COMMITTED.append(folder)


def committed() -> tuple[Path, ...]:
    """The output folders this process has finished writing (:func:`mark_committed`)."""
    return tuple(_COMMITTED)
