"""Per-image time of what a detection worker does (decode + checks + ``detect_markers``),
against decoding alone, for one source tree.

    python tools/profile_detection_job.py --tree /tmp/wt-base --data /tmp/split_data
    python tools/profile_detection_job.py --tree . --data /tmp/split_data

``--tree`` is the repository whose ``rgbd_calib`` is timed (an old revision: ``git worktree
add --detach /tmp/wt-base REV``); run the trees alternately to share the machine's load.
On the synthetic sets ``<data>/thesis-line-f40-s0`` (1280x720) and ``<data>/race-f40-s0``
(848x480), 40 images each, one process, one OpenCV thread: per image the best of 3 calls of
``detection.detect_job`` and of ``cv2.imdecode`` (BGR) of the same bytes (the floor every
pipeline pays), medians over the images and their ratio, i.e. the detection stage's share of
``tools/bench_speed.py``'s calibrate / decode without the pool.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

SETS = {"1280x720": ("thesis-line-f40-s0", 1280, 720), "848x480": ("race-f40-s0", 848, 480)}


def best_of(n: int, fn) -> float:
    """Shortest of ``n`` timed calls of ``fn`` (s)."""
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tree", type=Path, required=True, help="repository to time")
    ap.add_argument("--data", type=Path, default=Path("/tmp/bench_data"), help="synthetic sets")
    ap.add_argument("--images", type=int, default=40)
    args = ap.parse_args()
    sys.path.insert(0, str(args.tree.resolve()))
    import cv2
    import numpy as np

    from rgbd_calib.core.config import DetectionConfig
    from rgbd_calib.detect import markers as detection
    from rgbd_calib.model.board import thesis_board

    cv2.setNumThreads(1)
    detection.init_detector(thesis_board(), DetectionConfig(), 1)
    print(f"tree {args.tree} ({detection.__file__})")
    for res, (folder, w, h) in SETS.items():
        paths = sorted((args.data / folder).glob("*/color/*.png"))
        paths = paths[:: max(len(paths) // args.images, 1)][: args.images]
        detection.detect_job(("c", "f", str(paths[0]), w, h))  # imports, numba cache load
        job, dec = [], []
        for p in paths:
            task = ("c", "f", str(p), w, h)
            job.append(best_of(3, lambda task=task: detection.detect_job(task)))
            data = np.fromfile(p, np.uint8)
            dec.append(best_of(3, lambda data=data: cv2.imdecode(data, cv2.IMREAD_COLOR)))
        j, d = statistics.median(job), statistics.median(dec)
        print(f"{res}: job {1e3 * j:.2f} ms, decode (BGR) {1e3 * d:.2f} ms, ratio {j / d:.2f}")


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
