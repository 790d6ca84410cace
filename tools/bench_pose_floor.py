"""Pose-graph outliers on real webcams, with and without the per-view model-error floor.

On ``shared/data/caliscope-charuco-4cam`` (converted and split as tools/bench_caliscope.py
does), calibrates the even sync indices with the intrinsics from scratch (rig.yaml of image
sizes) or with Caliscope's (``camera_array.toml``, distortion included, written into
rig.yaml), the board as ChArUco or as an ArUco board of its own markers, for each value of
``pose.model_error_px``; reports the pose-graph outlier edges and their whitened norms, the
views the bundle adjustment leaves out, the cameras cut off, and the held-out (odd sets)
corner reprojection RMS per camera (``cross``: the board pose from the other cameras only).

Usage::

    PYTHONPATH=. python tools/bench_pose_floor.py --work /tmp/bench_caliscope \
        --model-error-px 0 0.3 --intrinsics scratch caliscope [--board charuco aruco]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_caliscope as bc  # noqa: E402

from rgbd_calib.core.config import CalibrationConfig  # noqa: E402
from rgbd_calib.model.board import marker_board  # noqa: E402
from rgbd_calib.model.board_file import load_board  # noqa: E402
from rgbd_calib.model.dataset import FolderDataset  # noqa: E402
from rgbd_calib.model.rig import Rig, load_rig, save_rig  # noqa: E402
from rgbd_calib.pipelines.calibrate import calibrate  # noqa: E402
from rgbd_calib.solve.ladder import refined_rig  # noqa: E402


def with_caliscope_intrinsics(folder: Path) -> Path:
    """A copy of ``folder`` (symlinked images) whose rig.yaml holds Caliscope's intrinsics."""
    out = folder.parent / (folder.name + "_caliscope")
    if out.exists():
        return out
    out.mkdir()
    for cam in sorted(p for p in folder.iterdir() if p.is_dir()):
        (out / cam.name).symlink_to(cam.resolve())
    rig = load_rig(folder / "rig.yaml")
    theirs, _ = bc.caliscope()
    save_rig(Rig({c: theirs[c] for c in rig.names}, rig.reference), out / "rig.yaml")
    return out


def summary(result) -> dict:
    pg = result.posegraph
    flagged = [r for r in pg.residuals if r.outlier and not r.stale]
    used_views = ({(r[0], r[1]) for r in result.bundle.residuals_px} if result.bundle else set())
    in_graph = {(r.camera, r.view) for r in pg.residuals if np.isfinite(r.whitened_norm)}
    left_out = sorted(in_graph - used_views) if result.bundle else []
    norms = sorted(r.whitened_norm for r in flagged)
    return {
        "views": len(result.observations),
        "edges_in_graph": len(in_graph),
        "outlier_edges": len(flagged),
        "outlier_norms": [round(float(x), 1) for x in norms],
        "model_error_cameras": sorted(pg.model_error),
        "bundle_left_out_views": len(left_out),
        "cameras": sorted(result.extrinsics.cameras),
        "cut_off": dict(result.extrinsics.unconnected),
        **estimated_floor(pg),
    }


def renders(values: list[float], work: Path, sets: list[str]) -> None:
    """The same sweep on renders with ground truth: worst camera error, worst error over its
    claimed sigma, pose-graph outlier edges and the pose graph's own worst error."""
    from rgbd_calib.core.geometry import transform_error
    from rgbd_calib.model.board import thesis_board
    from rgbd_calib.synth.render import load_ground_truth, synthesize_cached

    for spec in sets:
        layout, frames, seed = spec.split(":")
        path, _ = synthesize_cached(work / f"{layout}-f{frames}-s{seed}", layout, int(frames),
                                    int(seed), thesis_board(), workers=1)
        gt = load_ground_truth(path)
        for s in values:
            config = CalibrationConfig(workers=1, refine="none")
            config = config.model_copy(update={
                "pose": config.pose.model_copy(update={"model_error_px": s})})
            result = calibrate(FolderDataset(path), thesis_board(), config,
                               cache_dir=work / f"cache_{layout}-f{frames}-s{seed}")
            err = {c: transform_error(e.T_ref_cam, gt.T_ref_cam[c])
                   for c, e in result.extrinsics.cameras.items() if c != gt.reference}
            ratio = max(err[c][1] / result.extrinsics.cameras[c].sigma_translation_mm
                        for c in err)
            pg_mm = max(transform_error(e.T_ref_cam, gt.T_ref_cam[c])[1]
                        for c, e in result.posegraph.cameras.items() if c != gt.reference)
            pg = result.posegraph
            print(json.dumps({
                "render": spec, "model_error_px": s, "cameras": len(result.extrinsics.cameras),
                "worst_mm": round(max(v[1] for v in err.values()), 4),
                "worst_deg": round(max(v[0] for v in err.values()), 5),
                "worst_err_over_sigma": round(ratio, 2),
                "outlier_edges": len(pg.outlier_edges),
                "model_error_cameras": sorted(pg.model_error),
                "pose_graph_worst_mm": round(pg_mm, 3), **estimated_floor(pg)}), flush=True)


def floor_value(text: str) -> float | str:
    return text if text == "auto" else float(text)


def estimated_floor(pg) -> dict:
    """What ``model_error_px: auto`` estimated (empty for a fixed value)."""
    got = pg.stats.get("view_floor")
    return {} if got is None else {"estimated_px": round(got["model_error_px"], 3),
                                   "misfit_ratio": round(got["misfit_ratio"], 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_caliscope"))
    ap.add_argument("--model-error-px", type=floor_value, nargs="+", default=[0.0],
                    help="values of pose.model_error_px: numbers (px) or auto")
    ap.add_argument("--intrinsics", nargs="+", default=["scratch", "caliscope"],
                    choices=("scratch", "caliscope"))
    ap.add_argument("--board", nargs="+", default=["charuco"], choices=("charuco", "aruco"))
    ap.add_argument("--no-reject", action="store_true", help="graph.reject_outliers: false")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--render", nargs="*", default=None,
                    help="instead: renders layout:frames:seed (e.g. thesis-line:6:3 race:10:0)")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    if args.render is not None:
        renders(args.model_error_px, args.work, args.render)
        return
    converted = bc.convert(args.work)
    even, odd = (bc.split(converted, args.work, p) for p in (0, 1))
    charuco = load_board(bc.BOARD)
    boards = {"charuco": charuco, "aruco": marker_board(charuco)}
    points = {name: bc.held_out_points(odd, b) for name, b in boards.items()
              if name in args.board}
    rows = []
    for intr in args.intrinsics:
        folder = even if intr == "scratch" else with_caliscope_intrinsics(even)
        for bname in args.board:
            for s in args.model_error_px:
                config = CalibrationConfig(workers=1, refine="none")
                config = config.model_copy(update={
                    "pose": config.pose.model_copy(update={"model_error_px": s}),
                    "graph": config.graph.model_copy(
                        update={"reject_outliers": not args.no_reject})})
                cache = args.work / f"cache_{folder.name}_{bname}"
                t = time.time()
                result = calibrate(FolderDataset(folder), boards[bname], config, cache_dir=cache)
                rig = refined_rig(result.rig, result.bundle) if result.bundle else result.rig
                T = {c: e.T_ref_cam for c, e in result.extrinsics.cameras.items()}
                rms = bc.reprojection(points[bname], rig.cameras, T)
                row = {"intrinsics": intr, "board": bname, "model_error_px": s,
                       "seconds": round(time.time() - t, 1), **summary(result),
                       "held_out_cross_rms_px": {c: round(v["cross"][0], 2)
                                                 for c, v in sorted(rms.items())}}
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    shutil.rmtree(args.work / "unused", ignore_errors=True)


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
