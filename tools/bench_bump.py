"""Benchmark: can `check` and `refine --fix-others` damage a calibration? (issue 34)

    python tools/bench_bump.py --out /tmp/bench_bump [--layout race] [--seed 0]
        [--bumps 0 2 5 10 50] [--json docs/bump_bench.json]
    python tools/bench_bump.py --table docs/bump_bench.json

A rig is rendered (16 frame sets, still board) and calibrated with the default `calibrate`, as
a user does, once with true depth and once with each camera's depth scale off by up to
+-0.4 % (`--depth-bias 0.004`, the demo's). Then, per bump of one camera (``--bump
CAM:MM:DEG`` with DEG = MM / 10: 0, 2 mm / 0.2 deg, ..., 50 mm / 5 deg) and per recording
(``still``: 4 frame sets, the board held still in each; ``moving``: the board moving at
0.3 m/s / 30 deg/s while unsynchronised cameras capture it, up to +-16 ms apart), the rig as it
is now is rendered with the same seed (same cameras, same depth errors) and checked against
the calibration with the library's ``check`` (what the command runs: the calibration's depth
models, its board), then fixed with ``fix_moved`` as ``refine --fix-others`` does.

Reported per row: the cameras named moved and unknown, the exit code ``check`` gives, and
against the truth now: the worst camera the fix did not mean to move ("damage": its error
after the fix minus before, mm), and the bumped camera's error after the fix with its sigma,
and the fix's verdict.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from rgbd_calib.cli.app import check_exit
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.results import load_extrinsics
from rgbd_calib.pipelines.check import check, fix_moved
from rgbd_calib.pipelines.refine import fix_verdict
from rgbd_calib.synth.render import SynthParams, load_ground_truth, synthesize_cached

MOVING = {"motion": (0.3, 30.0), "sync_offset_ms": 16.0}
# issue 33's depth errors beside the scale (``--depth-errors``): a disparity offset within
# +-0.2 px, its gradients and curvature within +-0.05 px, the depth-to-colour pose within
# +-0.2 deg / +-1 mm per axis
DEPTH_ERRORS = {"depth_disparity_offset_px": 0.2, "depth_disparity_field_px": 0.05,
                "depth_pose_error": (0.2, 1.0)}


def calibrated(root: Path, layout: str, seed: int, bias: float, depth_errors: bool) -> Path:
    """The rig's calibration (16 still sets, default calibrate), rendered and run once."""
    tag = f"{layout}_s{seed}_b{bias}" + ("_de" if depth_errors else "")
    data, _ = synthesize_cached(root / f"cal_{tag}", layout, 16, seed, thesis_board(),
                                SynthParams(depth_bias=bias,
                                            **(DEPTH_ERRORS if depth_errors else {})))
    out = root / f"cal_{tag}_out"
    if not (out / "extrinsics.yaml").is_file():
        subprocess.run([sys.executable, "-m", "rgbd_calib.cli", "calibrate", str(data), "--out",
                        str(out), "--accept-poor"], check=True, capture_output=True)
    return out


def errors(ext, truth) -> dict[str, tuple[float, float]]:
    return {c: transform_error(e.T_ref_cam, truth[c])[::-1] for c, e in ext.cameras.items()}


def run_one(root: Path, layout: str, seed: int, bias: float, recording: str, mm: float,
            camera: str, frames: int, depth_errors: bool = False) -> dict:
    calib_dir = calibrated(root, layout, seed, bias, depth_errors)
    calib = load_extrinsics(calib_dir / "extrinsics.yaml")
    params = SynthParams(depth_bias=bias, bump=((camera, mm, mm / 10.0),) if mm else (),
                         **(MOVING if recording == "moving" else {}),
                         **(DEPTH_ERRORS if depth_errors else {}))
    de = "_de" if depth_errors else ""
    path, _ = synthesize_cached(root / f"now_{layout}_s{seed}_b{bias}{de}_{recording}_{mm:g}",
                                layout, frames, seed, thesis_board(), params)
    truth = load_ground_truth(path).T_ref_cam
    t0 = time.perf_counter()
    run = check(path, calib_dir / "extrinsics.yaml")
    t_check = time.perf_counter() - t0
    unknown_scale = {c for c, k in run.scale_source.items() if k == "unknown"}
    t0 = time.perf_counter()
    fix = fix_moved(run.clouds, calib, run.result, run.overlaps, unknown_scale=unknown_scale,
                    links=run.links, sensor_poses=run.sensor_poses)
    t_fix = time.perf_counter() - t0
    verdict = fix_verdict(calib, fix.extrinsics, run.moved, fix.pairs, fix.unconfirmed)
    before, after = errors(calib, truth), errors(fix.extrinsics, truth)
    others = [c for c in calib.cameras if c != camera or not mm]
    damage = max(after[c][0] - before[c][0] for c in others)
    row = {"layout": layout, "seed": seed, "depth_bias": bias, "depth_errors": depth_errors,
           "recording": recording,
           "bump_mm": mm, "bump_deg": mm / 10.0, "camera": camera if mm else None,
           "moved": run.moved, "unknown": run.unknown,
           "exit": check_exit(run.moved, run.unknown),
           "damage_mm": damage, "worst_other_after_mm": max(after[c][0] for c in others),
           "verdict": verdict["verdict"],
           "board_frame_sets": run.result.board.get("frame_sets", 0),
           "variance_factors": run.result.variance_factors,
           "check_s": t_check, "fix_s": t_fix}
    if mm:
        e = fix.extrinsics.cameras[camera]
        row |= {"bumped_after_mm": after[camera][0], "bumped_after_deg": after[camera][1],
                "bumped_sigma_mm": e.sigma_translation_mm,
                "bumped_sigma_deg": e.sigma_rotation_deg}
    return row


def table(rows: list[dict]) -> str:
    out = ["| depth bias | recording | bump (mm / deg) | named moved | unknown | exit | "
           "others after the fix: worst error (damage) mm | bumped camera after the fix: "
           "mm / deg (sigma) | fix verdict | check / fix (s) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        bumped = (f"{r['bumped_after_mm']:.2f} / {r['bumped_after_deg']:.3f} "
                  f"({r['bumped_sigma_mm']:.2f} / {r['bumped_sigma_deg']:.3f})"
                  if r["bump_mm"] else "-")
        out.append(
            f"| {r['depth_bias'] * 100:.1f} %{' + DE' if r.get('depth_errors') else ''} "
            f"| {r['recording']} | {r['bump_mm']:g} / "
            f"{r['bump_deg']:g} ({r['camera'] or 'none'}) | {', '.join(r['moved']) or 'none'} | "
            f"{', '.join(r['unknown']) or 'none'} | {r['exit']} | "
            f"{r['worst_other_after_mm']:.2f} ({r['damage_mm']:+.2f}) | {bumped} | "
            f"{r['verdict']} | {r['check_s']:.0f} / {r['fix_s']:.0f} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_bump"))
    ap.add_argument("--layout", default="race")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--camera", default="right1")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--bumps", type=float, nargs="+", default=[0, 2, 5, 10, 50])
    ap.add_argument("--biases", type=float, nargs="+", default=[0.0, 0.004])
    ap.add_argument("--recordings", nargs="+", default=["still", "moving"])
    ap.add_argument("--depth-errors", action="store_true",
                    help="issue 33's depth errors beside each depth bias (DEPTH_ERRORS)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--table", type=Path, help="print the table of a --json file and stop")
    args = ap.parse_args()
    if args.table:
        print(table(json.loads(args.table.read_text())))
        return
    rows = []
    for bias in args.biases:
        for recording in args.recordings:
            for mm in args.bumps:
                row = run_one(args.out, args.layout, args.seed, bias, recording, mm,
                              args.camera, args.frames, args.depth_errors)
                rows.append(row)
                print(table([row]).splitlines()[-1], flush=True)
                if args.json:
                    args.json.write_text(json.dumps(rows, indent=1) + "\n")
    print(table(rows))


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
