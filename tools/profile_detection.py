"""Per-image timing of ``detect_markers`` by stage, against a baseline version of the module.

    python tools/profile_detection.py --baseline-rev 5b7b74f --images 40 --repeats 3 --check

Loads ``rgbd_calib/detect/markers.py`` as it is in the working tree ("new") and as it is at
``--baseline-rev`` ("old", via ``git show``), then times both on the same grey images of the
synthetic sets ``<data>/thesis-line-f40-s0`` (1280x720) and ``<data>/race-f40-s0`` (848x480)
(decoded once, as the calibration's detection job does), interleaved image by image and
alternating which goes first, so that machine load hits both alike; one process, one OpenCV
thread. Stages are measured by wrapping the module's helpers: ``setup`` builds the detector,
``aruco`` is ``detectMarkers`` (the remainder of the total), ``board`` is
``refineDetectedMarkers``, ``gray`` the image for the edge fit, ``edges`` the edge-model
refinement, ``subpix`` the fallback. Per image the minimum over repeats is kept; reported are
medians over the images with markers and (in brackets) means over all images. ``--check``
also compares the corners of both versions.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rgbd_calib.model.board import thesis_board  # noqa: E402

sys.path.insert(0, str(ROOT / "tools"))
from baseline import load_module, module_at  # noqa: E402

SETS = {"1280x720": "thesis-line-f40-s0", "848x480": "race-f40-s0"}
STAGES = ("_detector", "_refine_with_board", "_gray_float", "refine_corners_edges")
LABELS = {
    "_detector": "setup",
    "_refine_with_board": "board",
    "_gray_float": "gray",
    "refine_corners_edges": "edges",
    "_subpix_fallback": "subpix",
}


def instrument(mod) -> dict[str, float]:
    """Wrap the module's stage functions with timers; returns the accumulator."""
    acc: dict[str, float] = {}
    for name in (*STAGES, "_subpix_fallback"):
        fn = getattr(mod, name)

        def wrapped(*a, _fn=fn, _name=name, **k):
            t0 = time.perf_counter()
            try:
                return _fn(*a, **k)
            finally:
                acc[_name] = acc.get(_name, 0.0) + time.perf_counter() - t0

        setattr(mod, name, wrapped)
    return acc


def images(folder: str, n: int) -> list[Path]:
    paths = sorted(Path(folder).glob("*/color/*.png"))
    step = max(len(paths) // n, 1)
    return paths[::step][:n]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline-rev", default="HEAD", help="git revision of the baseline")
    ap.add_argument("--baseline-file", type=Path, help="baseline markers.py (overrides rev)")
    ap.add_argument("--data", type=Path, default=Path("/tmp/bench_data"), help="synthetic sets")
    ap.add_argument("--images", type=int, default=20, help="images per resolution")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--check", action="store_true", help="compare corners old vs new")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    versions = {
        "old": (
            load_module("detect._markers_old", args.baseline_file)
            if args.baseline_file
            else module_at(args.baseline_rev, "rgbd_calib/detect/markers.py", "detect._markers_old")
        ),
        "new": load_module("detect._markers_new", ROOT / "rgbd_calib" / "detect" / "markers.py"),
    }
    acc = {k: instrument(m) for k, m in versions.items()}
    board = thesis_board()
    for res, folder in SETS.items():
        paths = images(str(args.data / folder), args.images)
        rows = {k: [] for k in versions}
        decode = []
        worst, n_both, n_diff = 0.0, 0, 0
        for p in paths:
            t0 = time.perf_counter()
            gray = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            decode.append(time.perf_counter() - t0)
            best: dict[str, dict[str, float]] = {}
            dets = {}
            for r in range(args.repeats):
                order = list(versions.items())
                for k, mod in order[::-1] if r % 2 else order:  # alternate who goes first
                    acc[k].clear()
                    t0 = time.perf_counter()
                    dets[k] = mod.detect_markers(gray, board)
                    total = time.perf_counter() - t0
                    split = {LABELS[s]: acc[k].get(s, 0.0) for s in (*STAGES, "_subpix_fallback")}
                    split["aruco"] = total - sum(split.values())
                    split["total"] = total
                    if k not in best or total < best[k]["total"]:
                        best[k] = split
            for k in versions:
                rows[k].append(best[k] | {"markers": len(dets[k])})
            if args.check:
                a, b = dets["old"], dets["new"]
                if not np.array_equal(a.ids, b.ids):
                    print(f"{p}: ids differ")
                    continue
                both = a.refined & b.refined
                n_both += int(both.sum())
                n_diff += int((a.refined != b.refined).sum())
                if both.any():
                    worst = max(worst, float(np.abs(a.corners_px - b.corners_px)[both].max()))
        cols = ("setup", "aruco", "board", "gray", "edges", "subpix", "total")
        dec = 1e3 * statistics.median(decode)
        seen = [i for i, r in enumerate(rows["old"]) if r["markers"]]
        print(
            f"\n{res}: {len(paths)} images, {len(seen)} with markers; ms per image: median over "
            f"those with markers (mean over all); PNG decode (grey) {dec:.1f} ms"
        )
        print("version " + "".join(f"{c:>14}" for c in cols))
        for k in versions:
            med = [1e3 * statistics.median(rows[k][i][c] for i in seen) for c in cols]
            mean = [1e3 * statistics.fmean(r[c] for r in rows[k]) for c in cols]
            print(f"{k:<8}" + "".join(f"{v:7.2f} ({u:5.1f})" for v, u in zip(med, mean)))
        if args.check:
            print(
                f"corners refined by both: {n_both}, refined by one only: {n_diff}, "
                f"max |diff| {worst:.2e} px"
            )


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
