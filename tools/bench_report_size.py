"""report.json size and write/read time for a large rig (issue 17, item 4).

Fabricates a report of ``--views`` per-view entries (default 30 000: 20 cameras x 1500
frames) from the schema's own view keys with random values, then times medians of
``--repeats`` runs of:

- ``inline``: today's report.json, every view in it (``dump_report``);
- ``ndjson``: report.json without the views + ``report_views.ndjson`` (stdlib json, one view a
  line), what :func:`rgbd_calib.outputs.report.write_report_json` writes above its threshold;
- ``ndjson.gz``: the same side file gzip-compressed (level 6), written and read back by
  :func:`rgbd_calib.outputs.report.write_report_json` /
  :func:`~rgbd_calib.outputs.report.load_report`;
- ``parquet``: the same rows as a Parquet table (pyarrow, zstd), when pyarrow is importable
  (``--extra-path`` adds a folder it was installed into with ``pip install --target``).

Usage::

    python tools/bench_report_size.py [--views 30000] [--repeats 3] [--extra-path /tmp/pa]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def fabricate(n_views: int, n_cameras: int = 20, seed: int = 0) -> dict:
    """A report dict with ``n_views`` views (the other per-view lists scaled to match)."""
    from rgbd_calib.outputs.report.schema import REPORT_SCHEMA_VERSION

    rng = np.random.default_rng(seed)
    cams = [f"cam{i:02d}" for i in range(n_cameras)]
    n_frames = max(1, n_views // n_cameras)
    views = []
    for k in range(n_views):
        u0, v0 = rng.uniform(0, 600, 2)
        status = rng.choice(["used", "used", "used", "outlier", "unused"])
        edge = status != "unused"
        views.append({
            "camera": cams[k % n_cameras], "frame": f"{k // n_cameras:06d}",
            "markers": int(rng.integers(4, 48)), "reprojection_rms_px": float(rng.gamma(2, 0.1)),
            "face": str(rng.choice(["front", "back"])), "distance_m": float(rng.uniform(0.5, 4)),
            "tilt_deg": float(rng.uniform(0, 70)),
            "image_bbox_px": [float(u0), float(v0), float(u0 + rng.uniform(50, 600)),
                              float(v0 + rng.uniform(50, 400))],
            "pnp_sigma_rotation_deg": float(rng.gamma(2, 0.01)),
            "pnp_sigma_translation_mm": float(rng.gamma(2, 0.2)),
            "edge_status": str(status),
            "edge_translation_mm": float(rng.gamma(2, 0.5)) if edge else None,
            "edge_rotation_deg": float(rng.gamma(2, 0.02)) if edge else None,
            "edge_whitened_norm": float(rng.gamma(2, 1)) if edge else None,
            "final_reprojection_rms_px": float(rng.gamma(2, 0.1)),
            "final_reprojection_max_px": float(rng.gamma(3, 0.1)),
            "excluded_markers": int(rng.integers(0, 3)),
        })
    T = np.eye(4)
    board_views = [{"frame": f"{f:06d}", "T_ref_board": (T + rng.normal(0, 0.1, (4, 4))
                                                           * [[1] * 4] * 3 + [[0] * 4]).tolist(),
                    "cameras": cams[: int(rng.integers(1, n_cameras))],
                    "final_reprojection_rms_px": float(rng.gamma(2, 0.1))}
                   for f in range(n_frames)]
    return {"schema_version": REPORT_SCHEMA_VERSION, "cameras": {c: {} for c in cams},
            "board_views": board_views, "views": views,
            "dropped_views": [{"camera": cams[k % n_cameras], "frame": f"{k:06d}",
                               "reason": "too_few_markers"} for k in range(n_views // 20)]}


def timed(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=30000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--extra-path", help="folder with pyarrow (pip install --target)")
    args = ap.parse_args()
    if args.extra_path:
        sys.path.append(args.extra_path)
    from rgbd_calib.outputs.report.schema import dump_report

    report = fabricate(args.views)
    rest = {k: v for k, v in report.items() if k != "views"}
    rows = report["views"]
    tmp = Path(tempfile.mkdtemp())
    results = []

    def measure(name, write, read, files):
        t_write = timed(write, args.repeats)
        t_read = timed(read, args.repeats)
        size = sum(os.path.getsize(tmp / f) for f in files)
        results.append((name, size, os.path.getsize(tmp / files[0]), t_write, t_read))

    def write_inline():
        (tmp / "inline.json").write_text(dump_report(report))

    measure("inline (today)", write_inline,
            lambda: json.loads((tmp / "inline.json").read_text()), ["inline.json"])

    def write_ndjson():
        (tmp / "report.json").write_text(dump_report(rest))
        with open(tmp / "views.ndjson", "w") as f:
            f.writelines(json.dumps(r, separators=(",", ":")) + "\n" for r in rows)

    def read_ndjson():
        json.loads((tmp / "report.json").read_text())
        with open(tmp / "views.ndjson") as f:
            [json.loads(line) for line in f]

    measure("ndjson (stdlib json)", write_ndjson, read_ndjson, ["report.json", "views.ndjson"])

    from rgbd_calib.outputs.report.storage import VIEWS_FILE, load_report, write_report_json

    (tmp / "side").mkdir()
    measure("ndjson.gz (stdlib; what write_report_json writes)",
            lambda: write_report_json(report, tmp / "side"),
            lambda: load_report(tmp / "side" / "report.json"),
            ["side/report.json", f"side/{VIEWS_FILE}"])
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        pa = None
    if pa is not None:
        def write_parquet():
            (tmp / "report.json").write_text(dump_report(rest))
            pq.write_table(pa.Table.from_pylist(rows), tmp / "views.parquet",
                           compression="zstd")

        def read_parquet():
            json.loads((tmp / "report.json").read_text())
            pq.read_table(tmp / "views.parquet").to_pylist()

        measure(f"parquet (pyarrow {pa.__version__}, zstd)", write_parquet, read_parquet,
                ["report.json", "views.parquet"])
    load = " ".join(open("/proc/loadavg").read().split()[:3])
    print(f"{args.views} views, medians of {args.repeats}, load average {load}")
    print("| format | all files (MB) | report.json (MB) | write (s) | read back (s) |")
    print("|---|---|---|---|---|")
    for name, size, main_size, tw, tr in results:
        print(f"| {name} | {size / 1e6:.2f} | {main_size / 1e6:.2f} | {tw:.2f} | {tr:.2f} |")


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
