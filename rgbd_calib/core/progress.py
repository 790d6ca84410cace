"""The library's one progress protocol, and stage timing (standard library only).

A long-running library function takes ``progress: Progress | None``. For each stage it calls
``tick = progress(label, total, done)`` once (``total`` may be None when unknown, ``done`` is
the work already done, e.g. cached), then ``tick(n)`` after every ``n`` units of work. The CLI
turns this into rich bars on a terminal and plain lines otherwise; the library never prints.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Protocol

from .interrupts import raise_if_interrupted

Tick = Callable[[int], None]


class Progress(Protocol):
    def __call__(self, label: str, total: int | None, done: int = 0) -> Tick: ...


def _no_tick(n: int = 1) -> None:
    return None


def start(progress: Progress | None, label: str, total: int | None, done: int = 0) -> Tick:
    """``progress(label, total, done)``, or a tick that does nothing when there is no progress."""
    if progress is None:
        return _no_tick
    return progress(label, total, done)


@contextmanager
def timed(timings: dict[str, float], stage: str) -> Iterator[None]:
    """Add the wall time (s) of the ``with`` block to ``timings[stage]``, also on an error.
    A stage does not begin after a Ctrl-C that a library swallowed (:mod:`.interrupts`)."""
    raise_if_interrupted()
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - t0
