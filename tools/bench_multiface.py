"""Accuracy of multi-face targets (a cube, an L) on synthetic rigs with ground truth.

    python tools/bench_multiface.py --data mf_data --boards configs/board_cube.yaml \
        configs/board_cube_charuco.yaml configs/board_L.yaml --layouts race ring \
        --seeds 11 23 --frames 40 --workers 2

Renders every board x layout x seed once with the synth defaults (blur 0.6 px, colour noise
2 DN; cached under ``--data``, reused when the render is the same), calibrates it with the
default bundle adjustment and the depth stage off (``refine="none"``, as the ArUco board's
figures in docs/accuracy.md) and compares each camera's ``T_ref_cam`` with
``ground_truth.yaml``: the worst and median error over the non-reference cameras, against
the ArUco board's bounds (race: 1.0 mm / 0.1 deg, ring: 0.5 mm / 0.05 deg on every camera).

``--face-error MM DEG`` renders the faces off their board-file poses (``synth
--face-error``) and calibrates with ``bundle.board: refine``: then the recovered face poses
are compared with the true ones too (shift of each face's marker centre, mm; angle, deg).
``--json`` writes every run's numbers.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from rgbd_calib.core.config import BundleConfig, CalibrationConfig
from rgbd_calib.core.geometry import invert_transform, transform_error, transform_points
from rgbd_calib.model.board_file import load_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.pipelines.calibrate import calibrate
from rgbd_calib.synth.render import SynthParams, load_ground_truth, synthesize_cached

BOUNDS = {"race": (0.1, 1.0), "race16": (0.1, 1.0), "ring": (0.05, 0.5),
          "thesis-line": (0.05, 0.5)}  # (deg, mm) on every camera, as the ArUco board's


def run(board_file: Path, layout: str, seed: int, frames: int, data: Path, workers: int,
        face_error: tuple[float, float]) -> dict:
    board = load_board(board_file)
    params = SynthParams(face_error=tuple(face_error))
    tag = f"{board.name}-{layout}-f{frames}-s{seed}"
    if any(face_error):
        tag += f"-face{face_error[0]:g}_{face_error[1]:g}"
    path, reused = synthesize_cached(data / tag, layout, frames, seed, board, params, workers)
    gt = load_ground_truth(path)
    bundle = BundleConfig(board="refine" if any(face_error) else "auto")
    config = CalibrationConfig(refine="none", workers=workers, bundle=bundle)
    t0 = time.perf_counter()
    result = calibrate(FolderDataset(path), board, config, cache_dir=data / "cache" / tag)
    seconds = time.perf_counter() - t0
    errors = {}
    for cam, e in result.extrinsics.cameras.items():
        if cam == gt.reference:
            continue
        rot, trans = transform_error(e.T_ref_cam, gt.T_ref_cam[cam])
        errors[cam] = {"rot_deg": rot, "trans_mm": trans,
                       "sigma_rot_deg": e.sigma_rotation_deg,
                       "sigma_trans_mm": e.sigma_translation_mm}
    faces = {}
    for f in (result.bundle.faces if result.bundle is not None else ()):
        true = gt.T_board_face.get(f.label, board.T_board_face(f.label))
        # the shift of the face's marker centre and the angle between estimate and truth
        c = f.T_nominal[:3, :3] @ f.centre + f.T_nominal[:3, 3]
        local = transform_points(invert_transform(f.T_nominal), c[None])[0]
        shift = (transform_points(f.T_board_face, local[None])[0]
                 - transform_points(true, local[None])[0]) * 1000.0
        rot, _ = transform_error(f.T_board_face, true)
        faces[f.label] = {"held": f.held, "shift_mm": float(np.linalg.norm(shift)),
                          "rot_deg": rot, "sigmas": None if f.held else f.sigmas}
    worst_r = max(v["rot_deg"] for v in errors.values())
    worst_t = max(v["trans_mm"] for v in errors.values())
    bound_r, bound_t = BOUNDS[layout]
    return {"board": board.name, "layout": layout, "seed": seed, "frames": frames,
            "face_error": list(face_error), "cameras": len(errors) + 1,
            "calibrated": len(result.extrinsics.cameras), "rig_cameras": len(gt.T_ref_cam),
            "worst_rot_deg": worst_r, "worst_trans_mm": worst_t,
            "median_rot_deg": float(np.median([v["rot_deg"] for v in errors.values()])),
            "median_trans_mm": float(np.median([v["trans_mm"] for v in errors.values()])),
            "within_bounds": bool(worst_r <= bound_r and worst_t <= bound_t
                                  and len(result.extrinsics.cameras) == len(gt.T_ref_cam)),
            "errors": errors, "faces": faces, "seconds": seconds, "reused_render": reused,
            "views": len(result.observations), "rejected": len(result.rejected)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("mf_data"))
    ap.add_argument("--boards", type=Path, nargs="+", default=[Path("configs/board_cube.yaml")])
    ap.add_argument("--layouts", nargs="+", default=["race", "ring"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[11, 23])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--face-error", type=float, nargs=2, default=(0.0, 0.0),
                    metavar=("MM", "DEG"))
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = []
    print("| board | layout | seed | cameras | worst rot (deg) | worst trans (mm) | "
          "median rot (deg) | median trans (mm) | bound | faces: worst shift (mm) / "
          "angle (deg) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for board_file in args.boards:
        for layout in args.layouts:
            for seed in args.seeds:
                r = run(board_file, layout, seed, args.frames, args.data, args.workers,
                        tuple(args.face_error))
                rows.append(r)
                solved = [f for f in r["faces"].values() if not f["held"]]
                faces = (f"{max(f['shift_mm'] for f in solved):.3f} / "
                         f"{max(f['rot_deg'] for f in solved):.4f}" if solved else "-")
                b = BOUNDS[layout]
                print(f"| {r['board']} | {layout} | {seed} | {r['calibrated']}/"
                      f"{r['rig_cameras']} | {r['worst_rot_deg']:.4f} | "
                      f"{r['worst_trans_mm']:.3f} | {r['median_rot_deg']:.4f} | "
                      f"{r['median_trans_mm']:.3f} | {b[1]} mm / {b[0]} deg: "
                      f"{'ok' if r['within_bounds'] else 'FAILED'} | {faces} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0 if all(r["within_bounds"] for r in rows) else 1


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
