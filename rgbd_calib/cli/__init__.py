"""The command line: ``app`` (the typer app, its help format, the one-line errors and the
argument checks every command shares), ``commands`` (the commands, thin: each calls the
library) and ``console`` (rich progress bars and tables). The top layer: nothing in the library
imports it."""

from .commands import app

__all__ = ["app"]
