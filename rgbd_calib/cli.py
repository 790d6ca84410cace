"""The ``rgbd-calib`` command line: thin wrappers around the library API.

Heavy imports happen inside the commands so ``--help`` stays fast. Every user mistake is a
:class:`~rgbd_calib.errors.RgbdCalibError`, printed as one line with a non-zero exit.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from . import __version__
from .errors import RgbdCalibError

app = typer.Typer(
    name="rgbd-calib",
    help="Extrinsic calibration of multi-camera RGB-D rigs with a double-sided ArUco board.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)
console = Console(stderr=True)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"rgbd-calib {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print version.")
    ] = False,
) -> None:
    """rgbd-calib: record a calibration set, run one command, trust the result."""


def user_errors(fn):
    """Turn library errors into one clear line and a non-zero exit (no traceback)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except RgbdCalibError as exc:
            console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
            raise typer.Exit(2) from None
        except PermissionError as exc:
            console.print(f"[bold red]error:[/] {exc.filename}: permission denied; choose a "
                          "writable folder", highlight=False, soft_wrap=True)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            console.print("[yellow]interrupted[/]: earlier results were left untouched")
            raise typer.Exit(130) from None

    return wrapper


def progress_bar():
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                               TimeElapsedColumn, TimeRemainingColumn)

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), TimeRemainingColumn(), console=console,
                    disable=not sys.stderr.isatty())


def _parse_resolution(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise typer.BadParameter(f"{text!r}: expected WIDTHxHEIGHT, e.g. 848x480") from None
    return w, h


@app.command()
@user_errors
def board(
    board_file: Annotated[Path, typer.Argument(help="Board YAML (grid or explicit form).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("board_print"),
    dpi: Annotated[int, typer.Option(help="Resolution of the PNG files (dots per inch).")] = 300,
    page: Annotated[str | None, typer.Option(help="Page size, e.g. A3 or A4-landscape; "
                                             "default: the smallest A size that fits.")] = None,
    fix_winding: Annotated[bool, typer.Option(help="Reorder mirrored markers instead of "
                                              "rejecting them.")] = False,
) -> None:
    """Write the board's faces as true-scale PDFs and PNGs, ready to print and glue."""
    from .board import load_board
    from .printing import write_printable_board

    b = load_board(board_file, fix_winding=fix_winding)
    result = write_printable_board(b, out, dpi=dpi, page=page)
    for path in result.files:
        typer.echo(path)


@app.command()
@user_errors
def synth(
    out: Annotated[Path, typer.Argument(help="Output dataset folder (must not exist or be "
                                        "empty).")],
    layout: Annotated[str, typer.Option(help="thesis-line, race or ring.")] = "race",
    frames: Annotated[int, typer.Option(help="Number of synchronised frame sets.")] = 40,
    seed: Annotated[int, typer.Option(help="Random seed (rig jitter, board motion, noise).")] = 0,
    resolution: Annotated[str | None, typer.Option(help="WIDTHxHEIGHT; default: 848x480 for "
                                                   "race, 1280x720 otherwise.")] = None,
    board_file: Annotated[Path | None, typer.Option("--board", help="Board YAML; default: "
                                                    "the thesis board.")] = None,
    depth_bias: Annotated[float, typer.Option(help="Max |relative depth-scale error| per camera, "
                                              "e.g. 0.006 for +-0.6%.")] = 0.0,
    blur: Annotated[float, typer.Option(help="Lens blur sigma (px).")] = 0.6,
    noise: Annotated[float, typer.Option(help="Colour noise sigma (8-bit DN).")] = 2.0,
    depth_dropout: Annotated[float, typer.Option(help="Fraction of depth pixels lost.")] = 0.02,
    drop_rate: Annotated[float, typer.Option(help="Probability a camera misses a frame.")] = 0.0,
    cameras: Annotated[int | None, typer.Option(help="Camera count (ring layout).")] = None,
    workers: Annotated[int | None, typer.Option(help="Processes; default all cores.")] = None,
) -> None:
    """Render a synthetic RGB-D rig with ground truth (dataset folder + ground_truth.yaml)."""
    from .board import load_board, thesis_board
    from .synth import SynthParams, synthesize

    params = SynthParams(resolution=_parse_resolution(resolution), blur_sigma_px=blur,
                         color_noise_dn=noise, depth_bias=depth_bias,
                         depth_dropout=depth_dropout, drop_rate=drop_rate, cameras=cameras)
    b = load_board(board_file) if board_file else thesis_board()
    with progress_bar() as bar:
        task = bar.add_task("rendering frame sets", total=frames)
        ds = synthesize(out, layout, frames, seed, b, params, workers,
                        progress=lambda: bar.advance(task))
    console.print(f"wrote {len(ds.rig.cameras)} cameras x {frames} frames to {ds.path}")


if __name__ == "__main__":  # pragma: no cover
    app()
