"""Saddle-corner bias and scatter of each ChArUco corner method on a rendered set, against the
true projection of each corner (docs/accuracy.md, "ChArUco boards").

    python tools/charuco_corners.py DATASET --board configs/board_charuco_a3.yaml \
        [--methods painted,subpix,opencv] [--calibrate]

DATASET is a ``rgbd-calib synth`` folder rendered with that board (its ``ground_truth.yaml``
gives the true poses and intrinsics). Per method: detected minus true corner (px), mean (bias)
and standard deviation (scatter) per axis, RMS, worst, the mean radial error (towards +/away
from the view's corner centroid) and the median per-view scale error (ppm; a print-scale-like
bias). ``--calibrate`` also runs the calibration (board only, fixed intrinsics) per method and
prints each camera's error against the truth with its claimed sigma.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from rgbd_calib import CalibrationConfig, FolderDataset, load_board
from rgbd_calib.core.config import DetectionConfig
from rgbd_calib.core.geometry import invert_transform, transform_error
from rgbd_calib.detect.markers import detect_charuco
from rgbd_calib.pipelines.calibrate import calibrate
from rgbd_calib.synth.render import load_ground_truth


def corner_stats(path: Path, board, method: str) -> dict[str, float]:
    gt = load_ground_truth(path)
    errs, radial, scale = [], [], []
    for cam, K in gt.intrinsics.items():
        for frame, T_ref_board in gt.T_ref_board.items():
            image = path / cam / "color" / f"{frame}.png"
            if not image.is_file():
                continue
            det = detect_charuco(cv2.imread(str(image)), board, corners=method)
            if len(det) == 0:
                continue
            T_cam_board = invert_transform(gt.T_ref_cam[cam]) @ T_ref_board
            P = board.corners[det.ids].reshape(-1, 3)
            uv = K.project(P @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]).reshape(-1, 2)
            e = det.corners_px.reshape(-1, 2) - uv
            d = uv - uv.mean(axis=0)
            r = np.linalg.norm(d, axis=1)
            errs.append(e)
            radial.append(np.sum(e * d, axis=1) / np.maximum(r, 1e-9))
            scale.append(np.sum(e * d) / np.sum(d * d))
    e = np.concatenate(errs)
    return {
        "views": len(errs), "corners": len(e),
        "bias_x": e[:, 0].mean(), "bias_y": e[:, 1].mean(),
        "std_x": e[:, 0].std(), "std_y": e[:, 1].std(),
        "rms": float(np.sqrt((e**2).sum(axis=1).mean())), "max": float(np.abs(e).max()),
        "radial": float(np.concatenate(radial).mean()),
        "scale_ppm": float(1e6 * np.median(scale)),
    }


def calibration_errors(path: Path, board, method: str) -> list[str]:
    gt = load_ground_truth(path)
    config = CalibrationConfig(workers=2, refine="none",
                               detection=DetectionConfig(charuco_corners=method))
    result = calibrate(FolderDataset(path), board, config)
    out = []
    for c, e in result.extrinsics.cameras.items():
        if c == gt.reference:
            continue
        deg, mm = transform_error(e.T_ref_cam, gt.T_ref_cam[c])
        out.append(f"{c} {deg:.4f} deg {mm:.3f} mm (sigma {e.sigma_translation_mm:.3f} mm)")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--board", type=Path, required=True)
    ap.add_argument("--methods", default="painted,subpix,opencv")
    ap.add_argument("--calibrate", action="store_true")
    args = ap.parse_args()
    board = load_board(args.board)
    print("| method | views | corners | bias x / y (px) | scatter x / y (px) | RMS (px) | "
          "worst (px) | radial (px) | scale (ppm) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for method in args.methods.split(","):
        s = corner_stats(args.dataset, board, method)
        print(f"| {method} | {s['views']} | {s['corners']} | {s['bias_x']:+.4f} / "
              f"{s['bias_y']:+.4f} | {s['std_x']:.4f} / {s['std_y']:.4f} | {s['rms']:.4f} | "
              f"{s['max']:.3f} | {s['radial']:+.4f} | {s['scale_ppm']:+.0f} |")
    if args.calibrate:
        for method in args.methods.split(","):
            print(method + ": " + "; ".join(calibration_errors(args.dataset, board, method)))


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
