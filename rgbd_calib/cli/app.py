"""What every command shares: the typer ``app`` with click's plain type names in ``--help``,
``--version``, the wrapper that turns a user's mistake into one ``error:`` line and an exit
code (:func:`user_errors`), and the checks of arguments that fail before any long step."""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Annotated

import typer

from .. import __version__
from ..core.errors import RgbdCalibError
from .console import console

app = typer.Typer(
    name="rgbd-calib",
    help="Extrinsic calibration of multi-camera RGB-D rigs with a double-sided ArUco board.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)


class _PlainHelpCommand(typer.core.TyperCommand):
    """``--help`` with click's plain type names (PATH, INT, PATH...) instead of typer's
    ``<path>``, ``<list[Path]>``, and nothing for on/off flags (typer shows ``<bool>``)."""

    def get_params(self, ctx):
        params = super().get_params(ctx)
        for param in params:
            if getattr(param, "metavar", None) is None:
                param.display_type_rich = functools.partial(_plain_type, param)
        return params


def _plain_type(param, ctx) -> str | None:
    if getattr(param, "is_flag", False):
        return None
    label = type(param).display_type_rich(param, ctx) or ""
    label = label.strip("<>")
    many = label.startswith("list[")
    label = label.removeprefix("list[").removesuffix("]").removesuffix("...")
    label = {"str": "TEXT", "float": "NUMBER"}.get(label.lower(), label.upper())
    return label + ("..." if many else "")


command = functools.partial(app.command, cls=_PlainHelpCommand)


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


def error_line(message: str) -> None:
    """Print one ``error:`` line (the message is text, never rich markup: paths and YAML
    snippets may hold brackets)."""
    from rich.markup import escape

    console.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)


def user_errors(fn):
    """Turn library errors into one clear line and a non-zero exit (no traceback)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except RgbdCalibError as exc:
            error_line(" ".join(str(exc).split("\n")))
            raise typer.Exit(2) from None
        except PermissionError as exc:
            error_line(f"{exc.filename}: permission denied; choose a writable folder")
            raise typer.Exit(2) from None
        except OSError as exc:  # disk full, a file where a folder should be, ...
            if exc.filename is None:
                raise
            error_line(f"{exc.filename}: {exc.strerror or exc}; check the path and the free space")
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            from rich.markup import escape

            from ..core.interrupts import committed

            done = committed()
            if done:  # the Ctrl-C came after the results were in place: say so
                message = ("[yellow]interrupted[/] after the results were written: "
                           f"{escape(', '.join(str(p) for p in done))} complete; nothing to "
                           "run again")
            else:
                message = ("[yellow]interrupted[/]: earlier results were left untouched; run "
                           "the same command again to finish")
            console.print(message, highlight=False, soft_wrap=True)
            raise typer.Exit(130) from None

    return wrapper


def check_method(method: str) -> None:
    """``--method`` of the depth-only commands: a registration method, not ``none``."""
    from ..core.config import REGISTRATION_METHODS
    from ..core.errors import ConfigError

    if method not in REGISTRATION_METHODS:
        raise ConfigError(f"--method {method!r}: use {' or '.join(REGISTRATION_METHODS)}")


def check_output_folder(out: Path, option: str = "--out") -> None:
    """Fail before any long step when ``out`` cannot become a folder: it is a file, or the
    first existing folder above it is a file or not writable."""
    from ..core.errors import ConfigError

    out = Path(out)
    if out.exists():
        if not out.is_dir():
            raise ConfigError(f"{out}: {option} is a file, not a folder; choose a folder path")
        parent = out
    else:
        parent = next((p for p in out.parents if p.exists()), Path("."))
        if not parent.is_dir():
            raise ConfigError(
                f"{out}: cannot create {option} there because {parent} is a file; "
                "choose another folder"
            )
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{out}: {parent} is not writable; choose another {option} folder")


def workers_ignore_ctrl_c() -> None:
    """Start the worker server with SIGINT ignored, so every pool worker inherits that and
    Ctrl-C reaches only this process: it stops cleanly with one line, the workers do not
    print their own tracebacks. (Python keeps SIGINT ignored in a child started with it
    ignored; the forkserver hands its original disposition to each worker.)"""
    import multiprocessing.forkserver
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        multiprocessing.forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, previous)


def parse_resolution(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise typer.BadParameter(f"{text!r}: expected WIDTHxHEIGHT, e.g. 848x480") from None
    return w, h
