"""The time model on real unsynchronised webcams: shared/data/caliscope-charuco-4cam with
every frame kept (not only the still ones), calibrated from scratch with each
``bundle.time_link_ms`` given (0: frame sets never linked; the videos are 6 fps, sets ~164 ms
apart, so a fixed 100 ms links none; ``auto``, the default, 1.5 frame periods), against
Caliscope's own camera poses.

    python tools/bench_caliscope_time.py WORKDIR [--links 0 250 auto]

Converts the four videos with their timestamps CSV and no ``--board`` (every frame set kept)
into WORKDIR/all once, calibrates (``--refine none``, intrinsics from scratch, detections
cached in WORKDIR/cache) and prints per link setting the model chosen, each camera's clock
offset and readout (+- sigma), the run-correlation variance factors, and each camera's pose
against Caliscope's (tools/bench_caliscope.py reads its convention) with our sigma.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from rgbd_calib import CalibrationConfig, FolderDataset, calibrate
from rgbd_calib.core.geometry import invert_transform, rotation_angle_deg
from rgbd_calib.model.board_file import load_board

sys.path.insert(0, str(Path(__file__).parent))
from bench_caliscope import BOARD, DATA, caliscope  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--links", nargs="+", default=["0", "250"],
                    help="bundle.time_link_ms values (ms, or auto)")
    args = ap.parse_args()
    data = args.workdir / "all"
    if not (data / "rig.yaml").is_file():
        subprocess.run([sys.executable, "-m", "rgbd_calib.cli", "convert",
                        *[str(DATA / f"cam_{i}.mp4") for i in range(4)],
                        "--timestamps", str(DATA / "timestamps.csv"), "--out", str(data)],
                       check=True, stdout=subprocess.DEVNULL)
    board = load_board(BOARD)
    _, theirs = caliscope()
    for link in args.links:
        config = CalibrationConfig.model_validate(
            {"refine": "none",
             "bundle": {"time_link_ms": link if link == "auto" else float(link)}})
        t0 = time.perf_counter()
        r = calibrate(FolderDataset(data), board, config, cache_dir=args.workdir / "cache")
        clock = r.bundle.time
        print(f"\ntime_link_ms {link} (= {r.config.bundle.time_model.time_link_ms:g} ms): "
              f"{time.perf_counter() - t0:.0f} s, chosen "
              f"{r.self_calibration.chosen.name}, {len(r.observations)} views, "
              f"{clock.linked_sets if clock else 0} sets linked")
        print("| camera | offset ms | readout ms | run factor | vs Caliscope deg / mm "
              "| sigma deg / mm |")
        print("|---|---|---|---|---|---|")
        for c, cam in r.extrinsics.cameras.items():
            d = invert_transform(theirs[c]) @ cam.T_ref_cam
            run = r.bundle.run_correlation.get(c)
            clk = (f"{clock.total_offset_ms(c):+.1f} +- {clock.sigma_offset_ms[c]:.1f} | "
                   f"{clock.readout_ms[c]:.1f} +- {clock.sigma_readout_ms[c]:.1f}"
                   if clock else "- | -")
            print(f"| {c} | {clk} | {run.factor if run else 1.0:.2f} | "
                  f"{rotation_angle_deg(d[:3, :3]):.2f} / "
                  f"{1000 * np.linalg.norm(cam.T_ref_cam[:3, 3] - theirs[c][:3, 3]):.1f} | "
                  f"{cam.sigma_rotation_deg:.2f} / {cam.sigma_translation_mm:.1f} |", flush=True)


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
