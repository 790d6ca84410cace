"""Process pools that are safe with OpenCV, GTSAM (TBB) and Open3D loaded.

Forking a process that already runs library thread pools copies locks held by threads that do
not exist in the child: OpenCV's ``setNumThreads`` then deadlocks in the child (seen in the test
suite). Workers therefore start from a clean ``forkserver`` process.
"""

from __future__ import annotations

import multiprocessing
from multiprocessing.context import BaseContext


def process_context() -> BaseContext:
    """The multiprocessing context every pool of the package uses."""
    return multiprocessing.get_context("forkserver")
