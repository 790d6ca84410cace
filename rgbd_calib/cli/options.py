"""Options and helpers more than one command module shares: the recordings options
(``--names``, ``--sync-tolerance-ms``), the Dask scheduler and opening a dataset folder or
recordings."""

from __future__ import annotations

from pathlib import Path

import typer

from .console import console, stage_progress

NAMES_OPTION = typer.Option(
    help="Recordings only: comma-separated camera names, in source order "
    "(default: serial / ROS namespace)."
)
SYNC_OPTION = typer.Option(
    help="Recordings only: largest timestamp gap between cameras of one frame set (ms); "
    "default half a frame period."
)


def name_list(names: str | None) -> list[str] | None:
    """``--names a,b,c`` as a list (each name is checked where it is used)."""
    return names.split(",") if names else None


def open_dataset(sources: list[Path], out: Path, names: str | None, sync_tolerance_ms):
    """A dataset folder as it is, or recordings converted once under OUT/cache/recordings
    (with a progress bar and the per-camera frame counts of the conversion)."""
    from ..model.dataset import FolderDataset
    from ..sources import cached_report, dataset_folder
    from .console import print_conversion_report

    with stage_progress() as progress:
        folder = dataset_folder(
            sources,
            out / "cache" / "recordings",
            name_list(names),
            sync_tolerance_ms,
            progress,
        )
    report = cached_report(folder)
    if report is not None:
        print_conversion_report(report)
        console.print(f"recordings as a dataset folder: {folder}", highlight=False)
    return FolderDataset(folder)


SCHEDULER_OPTION = typer.Option(
    "--scheduler",
    help="Address of a Dask scheduler (tcp://HOST:8786): its workers run the detection and "
    "the depth pair registrations instead of local processes; they must see the dataset at "
    "the same path (docs/reference.md, 'Running on a Dask cluster').",
)
