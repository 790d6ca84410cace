"""The tools' entry point: a benchmark given bad input (a missing folder, a file that is not
what it should be) ends in one line naming the tool and the problem and a non-zero exit, as
`rgbd-calib` does, not in a traceback. Errors that are bugs still show their traceback."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

from rgbd_calib.core.errors import RgbdCalibError

BAD_INPUT = 2
FAILED_STEP = 1


class ToolError(Exception):
    """A step of a tool failed (a command it ran exited non-zero): said in one line (with the
    log to read), not as a traceback."""


def run_tool(main: Callable[[], int | None]) -> None:
    """Run ``main`` and exit with its code; bad input (``RgbdCalibError``, a file or folder
    that is missing or unreadable) prints ``error: TOOL: what`` and exits 2, a failed step
    (:class:`ToolError`) the same and exits 1."""
    name = Path(sys.argv[0]).name
    try:
        code = main()
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        sys.exit(130)
    except (RgbdCalibError, FileNotFoundError, NotADirectoryError, IsADirectoryError,
            PermissionError) as exc:
        print(f"error: {name}: {exc}", file=sys.stderr)
        sys.exit(BAD_INPUT)
    except ToolError as exc:
        print(f"error: {name}: {exc}", file=sys.stderr)
        sys.exit(FAILED_STEP)
    sys.exit(code or 0)
