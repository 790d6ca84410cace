"""The command line: ``app`` (the typer app, its help format, the one-line errors and the
argument checks every command shares), ``commands`` and ``commands_depth`` (the commands,
thin: each calls the library; ``options``: the options they share) and ``console`` (rich
progress bars and tables). The top layer: nothing in the library imports it."""

import os

# numpy's OpenBLAS splits even an (N,3) @ (3,3) product over its threads; beside the process
# pools and threads the pipeline runs, and on a loaded machine, those threads wait on each
# other (the demo's calibrate on a loaded 2-core machine: 36.9 s with OpenBLAS's default,
# 27.5 s with one thread; docs/benchmarks.md). Set before numpy loads (the pools' workers
# inherit it); a user's own setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# commands first (the help lists the commands in the order they are registered)
from .commands import app  # noqa: E402, I001
from . import commands_depth  # noqa: F401 (registers refine and check on the app)

__all__ = ["app"]
