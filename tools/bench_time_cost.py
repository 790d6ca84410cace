"""What the time model costs where it is not needed (issue 32: a still board or simultaneous
capture keeps today's result for at most 20 % more bundle-stage time).

    python tools/bench_time_cost.py DATASET... [--repeats 5]

Each dataset (a render with ground_truth.yaml) is calibrated ``--repeats`` times each way,
alternating: ``bundle.time: fixed`` (the timeless model: what calibrate did before time
existed) and the default (``bundle.time: auto``), both ``--refine none`` with the detections
cached (a first, untimed run fills the cache). Printed per dataset: the median bundle-stage
time of each (``timings_s["bundle"]``), their ratio, the model the ladder chose and the worst
camera's error against the truth for each. Medians of alternated runs: the machine is shared.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from rgbd_calib import CalibrationConfig, FolderDataset, calibrate
from rgbd_calib.core.config import BundleConfig
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.model.board import thesis_board
from rgbd_calib.synth.render import load_ground_truth

CONFIGS = {"timeless": CalibrationConfig(refine="none", bundle=BundleConfig(time="fixed")),
           "default": CalibrationConfig(refine="none")}


def worst_mm(result, data: Path) -> float:
    gt = load_ground_truth(data)
    return max(transform_error(cam.T_ref_cam, gt.T_ref_cam[c])[1]
               for c, cam in result.extrinsics.cameras.items())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("datasets", type=Path, nargs="+")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    board = thesis_board()
    print("| dataset | timeless bundle s (median) | default bundle s (median) | ratio | "
          "chosen (default) | worst mm timeless / default |")
    print("|---|---|---|---|---|---|")
    for data in args.datasets:
        with tempfile.TemporaryDirectory() as cache:
            calibrate(FolderDataset(data), board, CONFIGS["timeless"], cache_dir=cache)
            seconds: dict[str, list[float]] = {m: [] for m in CONFIGS}
            last = {}
            for _ in range(args.repeats):
                for method, config in CONFIGS.items():
                    last[method] = calibrate(FolderDataset(data), board, config,
                                             cache_dir=cache)
                    seconds[method].append(last[method].timings_s["bundle"])
        med = {m: statistics.median(s) for m, s in seconds.items()}
        ladder = last["default"].self_calibration
        print(f"| {data.name} | {med['timeless']:.2f} | {med['default']:.2f} | "
              f"{med['default'] / med['timeless']:.2f} | "
              f"{ladder.chosen.name if ladder is not None else '-'} | "
              f"{worst_mm(last['timeless'], data):.3f} / {worst_mm(last['default'], data):.3f} |",
              flush=True)


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
