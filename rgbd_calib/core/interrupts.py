"""Ctrl-C around the steps that must not be cut in half, and what a run has already finished.

A command may be interrupted (KeyboardInterrupt) anywhere, and that is safe wherever it only
loses work in progress. Renaming a set of files into place is the exception: cut in the middle,
a folder would hold half of one run and half of another. :func:`sigint_deferred` holds Ctrl-C
back for such a block and raises it once the block is done. :func:`mark_committed` records an
output folder the process has finished writing, so the message after an interrupt can say
the truth: the results are complete, rather than "left untouched".

A KeyboardInterrupt raised where Python cannot pass it on (a weakref callback or ``__del__``,
e.g. a figure's garbage collection while the report is drawn) is printed as "Exception
ignored" and the command goes on as if no Ctrl-C had come. :func:`sigint_noted` notes every
Ctrl-C as it raises it, until code that means to catch one says so (:func:`interrupt_handled`),
so the next stage (:func:`raise_if_interrupted`) or the command's end can still stop as
interrupted.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_COMMITTED: list[Path] = []  # this process's finished output folders, in order
_PENDING: list[int] = []  # Ctrl-C raised under sigint_noted and not yet handled


def _note_and_raise(signum: int, _frame) -> None:
    _PENDING.append(signum)
    raise KeyboardInterrupt


@contextmanager
def sigint_noted() -> Iterator[None]:
    """Ctrl-C raises KeyboardInterrupt as usual and is noted until handled
    (:func:`interrupt_handled`), so one that a library swallowed is still seen. For a command's
    whole run (the CLI); outside it nothing is noted, so a library caller that catches the
    interrupt itself is not stopped again later. Only where Ctrl-C has Python's default handler
    (main thread; an ignored or custom handler is left as it is)."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return
    _PENDING.clear()
    signal.signal(signal.SIGINT, _note_and_raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def interrupt_handled() -> None:
    """Code that catches KeyboardInterrupt on purpose (a recording's stop, the command's
    message) says so here: the Ctrl-C has done what it was for."""
    _PENDING.clear()


def raise_if_interrupted() -> None:
    """Raise KeyboardInterrupt again if a Ctrl-C was swallowed before it reached its handler:
    called where a stage begins, so the command stops there instead of running to its end."""
    if _PENDING:
        raise KeyboardInterrupt


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
