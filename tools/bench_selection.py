"""A long continuous recording thinned to ``bundle.max_sets`` frame sets: accuracy and bundle
time against the sets kept.

    python tools/bench_selection.py WORKDIR [--layout race] [--frames 15] [--burst 20]
        [--seed 53] [--speed 0.3] [--max-sets 0 150 60]

Renders (once, into WORKDIR) ``--frames`` board positions, each held for ``--burst``
consecutive frame sets of a continuous recording (1/30 s apart; positions 1 s apart), the
board moving at ``--speed`` (m/s, turning 100 deg/s per m/s) and accelerating 1 m/s^2 /
100 deg/s^2 through each burst, cameras' clocks in +-16 ms, a 25 ms rolling shutter,
timestamps with 0.5 ms jitter (tools/bench_time.py's render). Then ``calibrate --refine none``
with each ``bundle.max_sets`` (0: every set) and one markdown row each: the sets kept, the
worst camera against ground_truth.yaml, RMS error/sigma, the model chosen, the clocks'
worst errors, the bundle stage's time and the whole calibration's.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from rgbd_calib import CalibrationConfig, FolderDataset, calibrate
from rgbd_calib.model.board import thesis_board

sys.path.insert(0, str(Path(__file__).parent))
from bench_time import render, row  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--layout", default="race")
    ap.add_argument("--frames", type=int, default=15)
    ap.add_argument("--burst", type=int, default=20)
    ap.add_argument("--seed", type=int, default=53)
    ap.add_argument("--speed", type=float, default=0.3)
    ap.add_argument("--max-sets", type=int, nargs="+", default=[0, 150, 60])
    args = ap.parse_args()
    data = render(args.workdir, args.layout, args.frames, args.seed, args.speed, 16.0, 25.0,
                  True, args.burst, (1.0, 100.0))
    print(f"{args.layout}, {args.frames} positions x {args.burst} consecutive sets, seed "
          f"{args.seed}, {args.speed} m/s, +-16 ms, 25 ms rolling shutter, timestamps")
    print("| max_sets | sets kept | worst mm / deg | RMS err/sigma | model chosen | offset err ms "
          "| readout err ms | bundle s | total s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for max_sets in args.max_sets:
        config = CalibrationConfig.model_validate(
            {"refine": "none", "bundle": {"max_sets": max_sets}})
        t0 = time.perf_counter()
        result = calibrate(FolderDataset(data), thesis_board(), config)
        seconds = time.perf_counter() - t0
        sel = result.set_selection
        kept = (f"{len(sel.kept)} of {sel.total}" if sel is not None
                else str(len({o.frame for o in result.observations})))
        print(row(data, f"{max_sets} | {kept}", result, seconds), flush=True)


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
