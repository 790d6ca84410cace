"""The command line: ``commands`` (the typer app, thin: each command calls the library) and
``console`` (rich progress bars and tables). The top layer: nothing in the library imports it."""

from .commands import app

__all__ = ["app"]
