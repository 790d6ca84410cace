"""The command line's output: rich progress bars, live displays and tables.

The library reports through :mod:`rgbd_calib.progress` and typed results and never imports
rich; this module turns those into terminal output for :mod:`rgbd_calib.cli`. Bars draw only
on a terminal (stderr); tables and notes are printed either way.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from rich.console import Console

from .progress import Progress

console = Console(stderr=True)


# --------------------------------------------------------------------------- progress
def progress_bar():
    """A rich bar with counts and times, shown only when stderr is a terminal."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
    from rich.progress import Progress as RichProgress

    return RichProgress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        disable=not sys.stderr.isatty(),
    )


@contextlib.contextmanager
def stage_progress() -> Iterator[Progress]:
    """The library's progress protocol, ``progress(label, total, done) -> tick(n=1)``, as one
    rich bar per stage (``total`` None: a bar without an end)."""
    with progress_bar() as bar:

        def progress(label: str, total: int | None, done: int = 0):
            task = bar.add_task(label, total=total, completed=done)
            return lambda n=1: bar.advance(task, n)

        yield progress


# --------------------------------------------------------------------------- convert
def print_conversion_report(report) -> None:
    """The per-camera counts of a :class:`~rgbd_calib.sources.ConversionReport` as a table,
    then its notes."""
    from rich.table import Table

    table = Table(
        title=f"{report.out}: {report.frames_written} frame sets "
        f"(sync tolerance {report.sync_tolerance_ms:.1f} ms)"
    )
    for col in ("camera", "read", "matched", "unmatched", "dropped", "no depth", "depth"):
        table.add_column(col, justify="right" if col not in ("camera", "depth") else "left")
    for name in report.cameras:
        c = report.counts[name]
        table.add_row(
            name,
            str(c.frames_read),
            str(c.matched),
            str(c.unmatched),
            str(c.dropped),
            str(c.without_depth),
            report.depth_source[name],
        )
    console.print(table)
    for note in report.notes:
        console.print(f"[yellow]note:[/] {note}", highlight=False)


def cli_convert(
    sources: Sequence[Path],
    out: Path,
    names: Sequence[str] | None = None,
    sync_tolerance_ms: float | None = None,
):
    """Run :func:`~rgbd_calib.sources.convert` with progress bars and print a table of the
    result."""
    from .sources import convert

    with stage_progress() as progress:
        report = convert(sources, out, names, sync_tolerance_ms, progress)
    print_conversion_report(report)
    return report


# --------------------------------------------------------------------------- record
def cli_record(
    out: Path,
    n_sets: int | None = None,
    mode: tuple[int, int, int] | None = None,
    hardware_sync: bool = False,
    board=None,
    names: Sequence[str] | None = None,
    device_source=None,
):
    """Run :func:`~rgbd_calib.record.record` with a live table of board markers per camera."""
    from rich.live import Live
    from rich.table import Table

    from .record import DEFAULT_MODE, RecordStatus, record

    def table(status: RecordStatus) -> Table:
        t = Table(title=f"recording into {out}  (Ctrl-C to stop)")
        t.add_column("camera")
        t.add_column("markers", justify="right")
        for name, n in status.markers.items():
            t.add_row(name, "-" if n < 0 else str(n))
        t.caption = f"{status.sets_written} set(s) written; cameras {status.spread_ms:.1f} ms apart"
        return t

    live: Live | None = None

    def show(status: RecordStatus) -> None:
        nonlocal live
        if live is None:  # only once the cameras stream: errors stay one clean line
            live = Live(table(status), console=console, refresh_per_second=4)
            live.start()
        live.update(table(status))

    try:
        report = record(
            out,
            n_sets,
            mode or DEFAULT_MODE,
            hardware_sync,
            board,
            names,
            device_source,
            status_callback=show,
        )
    finally:
        if live is not None:
            live.stop()
    how = "stopped by Ctrl-C" if report.interrupted else "done"
    console.print(
        f"{how}: {report.sets_written} set(s) of {len(report.cameras)} camera(s) in {report.out}"
    )
    for note in report.notes:
        console.print(f"[yellow]note:[/] {note}", highlight=False)
    return report
