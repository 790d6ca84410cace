"""The time model (issue 32) on a rendered rig, before it is wired into ``calibrate``.

    rgbd-calib synth DATA --layout race --frames 30 --seed 5 --motion 0.3 30 \
        --sync-offset-ms 16 --rolling-shutter-ms 25
    python tools/bench_time.py DATA [--offset-sigma-ms 1] [--twist-prior 0.5 60]

Runs the default calibration (``refine: none``: the timeless pose graph and bundle
adjustment), then :func:`rgbd_calib.solve.time_model.solve_timed` on the same detections
(every marker of every view the pose graph kept, outlier views too: a timing error makes
views disagree) from the bundle's poses, and prints each camera's error against
``ground_truth.yaml`` for both, with the clock offsets and readouts recovered.

The offsets' priors are what the cameras' timestamps give (``<camera>/timestamps.csv``: the
median over the frame sets of the camera's time minus the reference camera's), with
``--offset-sigma-ms``; without timestamps the truth plus Gaussian noise of
``--jitter-ms`` stands in for them (say so in any figure quoted). They anchor the time scale,
which the images alone do not fix (docs/conventions.md, "Time"). Every camera's readout is
free (a weak prior at 0 +- 50 ms) when the truth has a rolling shutter, else held at 0.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from rgbd_calib import CalibrationConfig, FolderDataset, calibrate, load_ground_truth
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.detect.run import detect_dataset
from rgbd_calib.model.board import thesis_board
from rgbd_calib.solve.ladder import camera_matrices, marker_measurements
from rgbd_calib.solve.pose import board_poses
from rgbd_calib.solve.time_model import TimePrior, TwistPrior, solve_timed


def offset_priors(dataset: FolderDataset, gt, sigma_ms: float, jitter_ms: float,
                  seed: int) -> tuple[dict[str, TimePrior], str]:
    """Each camera's offset prior from its timestamps, else from the truth plus noise."""
    rig = dataset.rig
    ref = dataset.timestamps_ms(rig.reference)
    priors, source = {}, "timestamps.csv"
    rng = np.random.default_rng(seed)
    for c in rig.names:
        times = dataset.timestamps_ms(c)
        if ref is not None and times is not None:
            diffs = [times[f] - ref[f] for f in times if f in ref]
            mean = float(np.median(diffs)) if diffs else 0.0
        else:
            source = f"the truth + N(0, {jitter_ms} ms) (no timestamps.csv)"
            mean = gt.offset_ms.get(c, 0.0) + (0.0 if c == rig.reference
                                                else rng.normal(0.0, jitter_ms))
        priors[c] = TimePrior(offset_ms=mean, offset_sigma_ms=sigma_ms)
    return priors, source


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="a rendered dataset folder (rgbd-calib synth)")
    ap.add_argument("--offset-sigma-ms", type=float, default=1.0)
    ap.add_argument("--jitter-ms", type=float, default=0.5)
    ap.add_argument("--twist-prior", type=float, nargs=2, default=(0.5, 60.0),
                    metavar=("MPS", "DPS"), help="1-sigma of each set's board twist")
    ap.add_argument("--pixel-sigma", type=float, default=0.05, help="corner noise (px)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    dataset, board = FolderDataset(args.data), thesis_board()
    gt, rig = load_ground_truth(args.data), dataset.rig
    cache = args.data.parent / f"{args.data.name}_bench_time_cache"
    config = CalibrationConfig(refine="none")
    timeless = calibrate(dataset, board, config, cache_dir=cache)
    detections = detect_dataset(dataset, board, config.detection,
                                cache / "detections.json", config.workers)
    observations, _ = board_poses(detections, board, rig, config.pose)
    measurements = marker_measurements(observations, timeless.posegraph, rig, False, board,
                                       keep_outlier_views=True)
    priors, source = offset_priors(dataset, gt, args.offset_sigma_ms, args.jitter_ms,
                                   args.seed)
    rolling = [c for c in rig.names if gt.readout_ms.get(c, 0.0) > 0.0]
    bundle = timeless.bundle
    solved = solve_timed(
        measurements, camera_matrices(rig), {c: rig.cameras[c].height for c in rig.names},
        rig.reference, {**timeless.posegraph.T_ref_cam, **bundle.T_ref_cam},
        {**timeless.posegraph.T_ref_board, **bundle.T_ref_board}, rolling_shutter=rolling,
        time_priors=priors, twist_sigma=TwistPrior(*args.twist_prior),
        pixel_sigma=args.pixel_sigma, robust="huber", robust_k=3.0)

    print(f"{args.data}: offsets' priors from {source}, sigma {args.offset_sigma_ms} ms; "
          f"twist prior {args.twist_prior[0]} m/s, {args.twist_prior[1]} deg/s; readout "
          f"{'free' if rolling else 'held at 0'}")
    print("camera   timeless mm  deg    | time model mm  deg     sigma mm | offset ms est/true"
          "        | readout ms est/true")
    worst = {"timeless": 0.0, "time": 0.0}
    z = []
    for c in rig.names:
        e0 = transform_error(timeless.extrinsics.cameras[c].T_ref_cam, gt.T_ref_cam[c])
        e1 = transform_error(solved.T_ref_cam[c], gt.T_ref_cam[c])
        worst["timeless"] = max(worst["timeless"], e0[1])
        worst["time"] = max(worst["time"], e1[1])
        s = solved.sigma_translation_mm[c]
        if c != rig.reference:
            z.append(e1[1] / s)
        print(f"{c:8s} {e0[1]:9.3f} {e0[0]:7.4f} | {e1[1]:10.3f} {e1[0]:7.4f} {s:9.3f} | "
              f"{solved.offset_ms[c]:+7.2f}/{gt.offset_ms.get(c, 0.0):+7.2f} "
              f"+-{solved.sigma_offset_ms[c]:.2f} | {solved.readout_ms[c]:6.2f}/"
              f"{gt.readout_ms.get(c, 0.0):6.2f} +-{solved.sigma_readout_ms[c]:.2f}")
    print(f"worst: timeless {worst['timeless']:.3f} mm, time model {worst['time']:.3f} mm; "
          f"RMS error/sigma {np.sqrt(np.mean(np.square(z))):.2f}; corner RMS "
          f"{solved.residual_rms_px:.3f} px, {solved.iterations} iterations")


if __name__ == "__main__":
    sys.exit(main())
