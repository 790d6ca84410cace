"""The command line: ``app`` (the typer app, its help format, the one-line errors and the
argument checks every command shares), ``commands`` and ``commands_depth`` (the commands,
thin: each calls the library; ``options``: the options they share) and ``console`` (rich
progress bars and tables). The top layer: nothing in the library imports it."""

# commands first (the help lists the commands in the order they are registered)
from .commands import app  # noqa: I001
from . import commands_depth  # noqa: F401 (registers refine and check on the app)

__all__ = ["app"]
