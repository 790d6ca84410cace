"""The same calibration through the local process pool and through a 2-worker Dask
``LocalCluster`` (issue 17, item 3): wall times (medians of ``--repeats``) and whether the
extrinsics are identical.

A thesis-line rig (4 cameras, ``--frames`` frame sets at 1280x720, rendered once into
``--data``) is calibrated with the defaults except ``depth.uncertainty.board_weak_sigma_mm`` /
``_deg`` = 0, so that the depth stage registers every overlapping pair (through the executor)
instead of skipping a rig the board already holds. No detection cache: each run detects
every image. The cluster (processes, 1 thread each) is started once, before the timed runs;
its start-up is reported on its own.

Usage::

    python tools/bench_dask.py [--data /tmp/bench_dask] [--frames 30] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("/tmp/bench_dask"))
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()

    from distributed import LocalCluster

    from rgbd_calib.core.config import load_config
    from rgbd_calib.model.board import thesis_board
    from rgbd_calib.model.dataset import FolderDataset
    from rgbd_calib.pipelines.calibrate import calibrate
    from rgbd_calib.synth.render import SynthParams, synthesize

    data = args.data / f"thesis-line-{args.frames}"
    if not (data / "rig.yaml").is_file():
        synthesize(data, "thesis-line", args.frames, 5, thesis_board(), SynthParams(),
                   workers=args.workers)
    ds = FolderDataset(data)
    board = thesis_board()
    loads = [open("/proc/loadavg").read().split()[0]]

    def run(scheduler: str | None):
        config = load_config(None, workers=args.workers, scheduler=scheduler,
                             **{"depth.uncertainty.board_weak_sigma_mm": 0,
                                "depth.uncertainty.board_weak_sigma_deg": 0})
        t0 = time.perf_counter()
        result = calibrate(ds, board, config)
        return time.perf_counter() - t0, result

    t0 = time.perf_counter()
    with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                      dashboard_address=":0", silence_logs=50) as cluster:
        t_cluster = time.perf_counter() - t0
        rows = {"local pool": [], "LocalCluster": []}
        results = {}
        for _ in range(args.repeats):  # interleaved, so that load changes hit both alike
            for name, scheduler in (("local pool", None),
                                    ("LocalCluster", cluster.scheduler_address)):
                wall, result = run(scheduler)
                rows[name].append((wall, result.timings_s))
                results.setdefault(name, []).append(result)
                loads.append(open("/proc/loadavg").read().split()[0])
    first = results["local pool"][0]
    same = all(
        np.array_equal(r.extrinsics.cameras[c].T_ref_cam, first.extrinsics.cameras[c].T_ref_cam)
        for rs in results.values() for r in rs for c in first.extrinsics.cameras)
    n_pairs = len(first.depth.pairs) if first.depth is not None else 0
    n_images = sum(len(fs.color) for fs in ds.frame_sets())
    print(f"{data}: {n_images} images, {n_pairs} depth pairs registered; "
          f"{args.workers} workers; medians of {args.repeats}; load average (1 min) during: "
          f"{', '.join(loads)}")
    print(f"LocalCluster start-up (not in the times below): {t_cluster:.1f} s")
    print("| executor | wall (s) | detection (s) | depth (s) | runs (s) |")
    print("|---|---|---|---|---|")
    for name, runs in rows.items():
        med = statistics.median(w for w, _ in runs)
        det = statistics.median(t["detection"] for _, t in runs)
        dep = statistics.median(t.get("depth", 0.0) for _, t in runs)
        print(f"| {name} | {med:.1f} | {det:.1f} | {dep:.1f} | "
              f"{', '.join(f'{w:.1f}' for w, _ in runs)} |")
    print(f"extrinsics identical (bit for bit) across all {2 * args.repeats} runs: {same}")


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
