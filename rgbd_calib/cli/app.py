"""What every command shares: the typer ``app`` with click's plain type names in ``--help``,
``--version``, the exit codes, the wrapper that turns a user's mistake into one ``error:`` line
and an exit code (:func:`user_errors`), and the checks of arguments that fail before any long
step."""

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

# The exit codes of every command (README, "Exit codes"): a script can tell a result it may
# use from one it must not, and both from a mistake in the input.
EXIT_OK = 0  # done; calibrate / refine: verdict GOOD or CHECK; check: every camera in place
EXIT_MOVED = 1  # check: some camera moved (named on the console and in check.json)
EXIT_INPUT = 2  # bad input or options: one error line, nothing written (click's usage errors too)
EXIT_POOR = 3  # calibrate / refine / demo: written, but the verdict is POOR (unless --accept-poor)
EXIT_UNCHECKED = 4  # check: none moved, but some camera could not be checked ("unknown")
EXIT_CHECK = 5  # calibrate / refine / demo with --strict: written, but the verdict is CHECK
EXIT_INTERRUPTED = 130  # Ctrl-C: earlier results untouched

ACCEPT_POOR_OPTION = typer.Option(
    "--accept-poor", help=f"Exit {EXIT_OK} even when the verdict is POOR (default: exit "
    f"{EXIT_POOR}; the verdict is written into extrinsics.yaml and the exports either way).")


STRICT_OPTION = typer.Option(
    "--strict", help=f"Exit {EXIT_CHECK} when the verdict is CHECK (default: exit {EXIT_OK}), "
    "so that 'calibrate --strict ... && deploy' deploys only a GOOD result.")


def verdict_exit(grade: str | None, accept_poor: bool = False, strict: bool = False) -> int:
    """The exit code of a written result with verdict ``grade`` (None: not judged):
    :data:`EXIT_POOR` for POOR unless ``accept_poor``, :data:`EXIT_CHECK` for CHECK with
    ``strict``, else :data:`EXIT_OK`."""
    if grade == "poor" and not accept_poor:
        return EXIT_POOR
    return EXIT_CHECK if grade == "check" and strict else EXIT_OK


def check_exit(moved: list[str], unknown: list[str]) -> int:
    """``check``'s exit code: a moved camera first, then cameras that could not be checked;
    exit 0 only when every camera was checked and is in place."""
    return EXIT_MOVED if moved else EXIT_UNCHECKED if unknown else EXIT_OK


def exit_on_poor(out: Path, accept_poor: bool, show: bool = False, strict: bool = False) -> None:
    """End a command that wrote ``out/extrinsics.yaml`` with the exit code of the verdict
    written in it (``show``: print the verdict line first; ``strict``: CHECK exits
    :data:`EXIT_CHECK`)."""
    from rich.markup import escape

    from ..model.results import load_extrinsics

    verdict = load_extrinsics(Path(out) / "extrinsics.yaml").verdict
    if verdict is None:
        return
    if show:
        console.print(f"verdict: {escape(verdict.line)}", highlight=False, soft_wrap=True)
    code = verdict_exit(verdict.grade, accept_poor, strict)
    if code == EXIT_CHECK:
        console.print(f"[bold yellow]exit {code}[/]: the verdict is CHECK and --strict asks "
                      "for GOOD; read the warnings before using these extrinsics",
                      highlight=False, soft_wrap=True)
        raise typer.Exit(code)
    if code != EXIT_OK:
        console.print(f"[bold red]exit {code}[/]: the verdict is POOR (recorded in "
                      "extrinsics.yaml); do not deploy these extrinsics as they are "
                      "(--accept-poor exits 0)", highlight=False, soft_wrap=True)
        raise typer.Exit(code)


def warn_if_poor(extrinsics, path: Path) -> None:
    """A calibration read back (``--init``, ``--calib``, ``--fix``) whose verdict was POOR:
    say so before using it."""
    from rich.markup import escape

    verdict = getattr(extrinsics, "verdict", None)
    if verdict is not None and verdict.grade == "poor":
        console.print(f"[yellow]warning[/]: {escape(str(path))}: its verdict is POOR "
                      f"({escape(verdict.reason)}); results built on it inherit that",
                      highlight=False, soft_wrap=True)


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
        from ..core.interrupts import raise_if_interrupted, sigint_noted

        try:
            with sigint_noted():
                result = fn(*args, **kwargs)
            raise_if_interrupted()  # a Ctrl-C a library swallowed ("Exception ignored")
            return result
        except RgbdCalibError as exc:
            error_line(" ".join(str(exc).split("\n")))
            raise typer.Exit(EXIT_INPUT) from None
        except PermissionError as exc:
            error_line(f"{exc.filename}: permission denied; choose a writable folder")
            raise typer.Exit(EXIT_INPUT) from None
        except OSError as exc:  # disk full, a file where a folder should be, ...
            if exc.filename is None:
                raise
            error_line(f"{exc.filename}: {exc.strerror or exc}; check the path and the free space")
            raise typer.Exit(EXIT_INPUT) from None
        except KeyboardInterrupt:
            from rich.markup import escape

            from ..core.interrupts import committed, interrupt_handled

            interrupt_handled()
            done = committed()
            if done:  # the Ctrl-C came after the results were in place: say so
                message = ("[yellow]interrupted[/] after the results were written: "
                           f"{escape(', '.join(str(p) for p in done))} complete; nothing to "
                           "run again")
            else:
                message = ("[yellow]interrupted[/]: earlier results were left untouched; run "
                           "the same command again to finish")
            console.print(message, highlight=False, soft_wrap=True)
            raise typer.Exit(EXIT_INTERRUPTED) from None

    return wrapper


def check_method(method: str) -> None:
    """``--method`` of the depth-only commands: a registration method, not ``none``."""
    from ..core.config import REGISTRATION_METHODS
    from ..core.errors import ConfigError

    if method not in REGISTRATION_METHODS:
        raise ConfigError(f"--method {method!r}: use {' or '.join(REGISTRATION_METHODS)}")


FORCE_OPTION = typer.Option(
    "--force", help="Write into --out even when its extrinsics.yaml was not written by "
    "rgbd-calib (default: refuse, so that a file of yours is never overwritten).")


def check_output_folder(out: Path, option: str = "--out",
                        inputs: tuple[tuple[Path, str], ...] = (),
                        force: bool | None = None) -> None:
    """Fail before any long step when ``out`` cannot become a folder: it is a file, or the
    first existing folder above it is a file or not writable; or it is one of the folders
    ``inputs`` (``(folder, what it is)``: the dataset, a calibration read) or inside one,
    where the results would mix with, or overwrite, what the run reads; or (``force`` False,
    a command that writes extrinsics.yaml) it holds an extrinsics.yaml rgbd-calib did not
    write."""
    from ..core.errors import ConfigError

    out = Path(out)
    where = out.resolve()
    mine = out / "extrinsics.yaml"
    if force is False and mine.is_file() and not _ours(mine):
        raise ConfigError(f"{mine}: not written by rgbd-calib (no '# rgbd-calib' header); "
                          "this run would overwrite it: choose another --out, or pass --force")
    for folder, what in inputs:
        folder = Path(folder)
        if not folder.is_dir():
            continue
        inside = folder.resolve()
        # a dataset takes nothing inside it; a calibration read, no result over it
        if where == inside or (what == "dataset" and inside in where.parents):
            raise ConfigError(
                f"{out}: {option} is {'the' if where == inside else 'inside the'} {what} "
                f"{folder}; the results would mix with what this run reads: give a folder "
                "outside it")
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


def _ours(path: Path) -> bool:
    """Whether the extrinsics file ``path`` carries rgbd-calib's header comment in its first
    lines (a comment a user added above it keeps it ours)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            return any(fh.readline().startswith("# rgbd-calib") for _ in range(5))
    except OSError:
        return False


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
