"""Benchmark: 4 real webcams calibrated from scratch (intrinsics and extrinsics) against
Caliscope's own result on the same session (shared/data/caliscope-charuco-4cam).

Steps: ``rgbd-calib convert`` of the four videos (timestamps CSV, frames with the board still);
the frame sets split into even and odd sync indices; calibrate on the even half (rig.yaml with
the image sizes only: intrinsics from scratch) and, for the parameter comparison, on all sets;
then on the odd half (held out), per camera, the corner reprojection RMS of

- ``joint``: the board pose of each held-out set solved from every camera that saw it, and
- ``cross``: the board pose solved from the OTHER cameras only, reprojected into this one
  (tests the extrinsics and both cameras' intrinsics together),

with our solve and with Caliscope's ``camera_array.toml`` (its convention, checked here:
``rotation``/``translation`` map world points into the camera, ``x_cam = R x_world + t``;
relative poses compared camera to camera, so the worlds need not agree). Caliscope's result
was computed on every frame, the held-out half included.

Usage::

    PYTHONPATH=. python tools/bench_caliscope.py [--work /tmp/bench_caliscope] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.config import CalibrationConfig, DetectionConfig
from rgbd_calib.core.geometry import (
    invert_transform,
    make_transform,
    matrix_to_rotvec,
    rotation_angle_deg,
    rotvec_to_matrix,
    transform_points,
)
from rgbd_calib.detect.run import detect_dataset
from rgbd_calib.model.board_file import load_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.pipelines.calibrate import calibrate
from rgbd_calib.solve.intrinsics_init import view_points
from rgbd_calib.solve.ladder import refined_rig

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("RGBD_CALIB_SHARED_DATA", REPO.parent / "shared" / "data")) / (
    "caliscope-charuco-4cam")
BOARD = REPO / "configs" / "board_charuco_caliscope.yaml"
PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def convert(work: Path) -> Path:
    out = work / "converted"
    if not (out / "rig.yaml").is_file():
        shutil.rmtree(out, ignore_errors=True)
        cmd = [sys.executable, "-m", "rgbd_calib.cli", "convert",
               *[str(DATA / f"cam_{i}.mp4") for i in range(4)],
               "--timestamps", str(DATA / "timestamps.csv"), "--board", str(BOARD),
               "--out", str(out)]
        subprocess.run(cmd, check=True, env={**os.environ, "PYTHONPATH": str(REPO)},
                       stdout=subprocess.DEVNULL)
    return out


def split(converted: Path, work: Path, parity: int | None) -> Path:
    """A view of ``converted`` with the sets of even (0) or odd (1) sync index (symlinks), each
    camera's ``timestamps.csv`` with it (its rows of other sets are not read)."""
    name = {0: "even", 1: "odd", None: "all"}[parity]
    out = work / name
    if out.exists():
        return out
    out.mkdir()
    shutil.copy(converted / "rig.yaml", out / "rig.yaml")
    for cam in sorted(p for p in converted.iterdir() if p.is_dir()):
        (out / cam.name / "color").mkdir(parents=True)
        if (cam / "timestamps.csv").is_file():
            shutil.copy(cam / "timestamps.csv", out / cam.name / "timestamps.csv")
        for img in sorted((cam / "color").iterdir()):
            if parity is None or int(img.stem) % 2 == parity:
                (out / cam.name / "color" / img.name).symlink_to(img)
    return out


def caliscope() -> tuple[dict[str, CameraIntrinsics], dict[str, np.ndarray]]:
    """Caliscope's intrinsics and ``T_cam0_cam`` per camera (``cam_<id>``)."""
    data = tomllib.loads((DATA / "camera_array.toml").read_text())
    intr, T_cam_world = {}, {}
    for key, c in data["cameras"].items():
        K = np.array(c["matrix"], dtype=float)
        w, h = c["size"]
        intr[f"cam_{key}"] = CameraIntrinsics(int(w), int(h), K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                                              tuple(map(float, c["distortions"])))
        T_cam_world[f"cam_{key}"] = make_transform(np.array(c["rotation"]), c["translation"])
    return intr, {c: T_cam_world["cam_0"] @ invert_transform(T) for c, T in T_cam_world.items()}


def held_out_points(odd: Path, board) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """``frame -> camera -> (board points, pixels)`` of the held-out sets."""
    dets = detect_dataset(FolderDataset(odd), board, DetectionConfig(), workers=1)
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for (cam, frame), det in dets.items():
        obj, px = view_points(det, board)
        if len(obj) >= 4:
            out.setdefault(frame, {})[cam] = (obj, px)
    return out


def solve_board(views: dict[str, tuple[np.ndarray, np.ndarray]],
                intr: dict[str, CameraIntrinsics], T_ref_cam: dict[str, np.ndarray]) -> np.ndarray:
    """``T_ref_board`` minimising the corner reprojection over ``views`` (camera -> points)."""
    import cv2

    first = max(views, key=lambda c: len(views[c][0]))
    obj, px = views[first]
    i = intr[first]
    _, rvec, tvec = cv2.solvePnP(obj, px, i.K, i.dist, flags=cv2.SOLVEPNP_SQPNP)
    T0 = T_ref_cam[first] @ make_transform(rotvec_to_matrix(rvec.ravel()), tvec.ravel())

    def residual(x):
        T_ref_board = make_transform(rotvec_to_matrix(x[:3]), x[3:])
        return np.concatenate([
            (intr[c].project(transform_points(invert_transform(T_ref_cam[c]) @ T_ref_board, o))
             - p).ravel() for c, (o, p) in views.items()])

    x0 = np.r_[matrix_to_rotvec(T0[:3, :3]), T0[:3, 3]]
    x = least_squares(residual, x0, method="lm").x
    return make_transform(rotvec_to_matrix(x[:3]), x[3:])


def reprojection(points, intr, T_ref_cam) -> dict[str, dict[str, float]]:
    """Per camera the held-out corner RMS (px), ``joint`` and ``cross`` (module docstring)."""
    sq: dict[str, dict[str, list[float]]] = {c: {"joint": [], "cross": []} for c in T_ref_cam}
    for views in points.values():
        views = {c: v for c, v in views.items() if c in T_ref_cam}
        if not views:
            continue
        T = solve_board(views, intr, T_ref_cam)
        for c, (o, p) in views.items():
            r = intr[c].project(transform_points(invert_transform(T_ref_cam[c]) @ T, o)) - p
            sq[c]["joint"] += np.sum(r**2, axis=1).tolist()
            others = {k: v for k, v in views.items() if k != c}
            if others:
                To = solve_board(others, intr, T_ref_cam)
                r = intr[c].project(transform_points(invert_transform(T_ref_cam[c]) @ To, o)) - p
                sq[c]["cross"] += np.sum(r**2, axis=1).tolist()
    return {c: {k: (float(np.sqrt(np.mean(v))) if v else float("nan"), len(v))
                for k, v in d.items()} for c, d in sq.items()}


def run(folder: Path, board, config: CalibrationConfig):
    t = time.time()
    result = calibrate(FolderDataset(folder), board, config, cache_dir=folder.parent / (
        folder.name + "_cache"))
    rig = refined_rig(result.rig, result.bundle)
    T = {c: e.T_ref_cam for c, e in result.extrinsics.cameras.items()}
    return result, rig, T, time.time() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_caliscope"))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--params", default=None,
                    help="bundle.intrinsics_params, space-separated (default: the config's)")
    ap.add_argument("--intrinsics", default="auto", choices=("auto", "fixed", "refine"),
                    help="bundle.intrinsics (auto: refined, the cameras are from scratch; "
                    "fixed: the single-camera first estimates held)")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    board = load_board(BOARD)
    converted = convert(args.work)
    config = CalibrationConfig(workers=1, refine="none")
    config = config.model_copy(update={"bundle": config.bundle.model_copy(
        update={"intrinsics": args.intrinsics})})
    if args.params:
        config = config.model_copy(update={"bundle": config.bundle.model_copy(
            update={"intrinsics_params": args.params.split()})})
    even, odd, every = (split(converted, args.work, p) for p in (0, 1, None))
    theirs_intr, theirs_T = caliscope()
    res_even, rig_even, T_even, s_even = run(even, board, config)
    res_all, rig_all, T_all, s_all = run(every, board, config)
    points = held_out_points(odd, board)
    out = {"held_out_sets": len(points), "seconds": {"even": s_even, "all": s_all},
           "cameras": {}}
    ours_rms = reprojection(points, rig_even.cameras, T_even)
    their_rms = reprojection(points, theirs_intr, theirs_T)
    print(f"held-out sets: {len(points)}; solve {s_even:.0f} s (even half), {s_all:.0f} s (all)")
    print("\n| camera | views even/all | held-out RMS px joint: ours / Caliscope | cross: ours / "
          "Caliscope (corners) | rel. pose vs Caliscope, all sets: deg / mm "
          "| even half: deg / mm |")
    print("|---|---|---|---|---|---|")
    for cam in sorted(theirs_T):
        row: dict = {"held_out": {"ours": ours_rms.get(cam), "caliscope": their_rms.get(cam)}}
        pose = {}
        for label, T in (("all", T_all), ("even", T_even)):
            if cam in T:
                d = invert_transform(theirs_T[cam]) @ T[cam]
                pose[label] = (rotation_angle_deg(d[:3, :3]),
                               1000 * float(np.linalg.norm(T[cam][:3, 3] - theirs_T[cam][:3, 3])))
        row["pose_vs_caliscope"] = pose
        o, t = ours_rms.get(cam, {}), their_rms.get(cam, {})
        fmt = "{:.2f} / {:.2f}"
        views = (sum(1 for ob in res_even.observations if ob.camera == cam),
                 sum(1 for ob in res_all.observations if ob.camera == cam))
        print(f"| {cam} | {views[0]}/{views[1]} | "
              + (fmt.format(o["joint"][0], t["joint"][0]) if o else "-") + " | "
              + (fmt.format(o["cross"][0], t["cross"][0]) + f" ({o['cross'][1]})" if o else "-")
              + " | " + " | ".join(f"{pose[k][0]:.2f} / {pose[k][1]:.0f}" if k in pose else "-"
                                   for k in ("all", "even")) + " |")
        intr = {}
        for label, rig in (("all", rig_all), ("even", rig_even)):
            mine, ref = rig.cameras[cam].parameters, theirs_intr[cam].parameters
            res = res_all if label == "all" else res_even
            sig = res.bundle.intrinsics_sigma.get(cam, {}) if res.bundle else {}
            intr[label] = {p: {"ours": mine.get(p, 0.0), "sigma": sig.get(p),
                               "caliscope": ref.get(p, 0.0)} for p in PARAMS}
        row["intrinsics"] = intr
        row["initial"] = res_all.initial_intrinsics[cam].to_dict()
        out["cameras"][cam] = row
    print("\n| camera | param | ours (all sets) +- sigma | Caliscope | ours - Caliscope |")
    print("|---|---|---|---|---|")
    for cam, row in out["cameras"].items():
        for p in PARAMS:
            e = row["intrinsics"]["all"][p]
            s = f" +- {e['sigma']:.3g}" if e["sigma"] is not None else ""
            print(f"| {cam} | {p} | {e['ours']:.4g}{s} | {e['caliscope']:.4g} | "
                  f"{e['ours'] - e['caliscope']:+.3g} |")
    print("\nwarnings (all sets):", sorted({w for w in _codes(res_all)}))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1, default=float))


def _codes(result) -> list[str]:
    from rgbd_calib.outputs.report import report_dict

    return [w["code"] for w in report_dict(result, result.rig)["warnings"]]


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
