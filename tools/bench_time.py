"""Time (issue 32): the timeless model, the time model and the thesis method against board speed.

    python tools/bench_time.py WORKDIR [--layout race] [--frames 20] [--seed 31]
        [--speeds 0 0.1 0.3 0.5] [--offset-ms 16] [--readout-ms 25] [--no-timestamps]
        [--burst 3 --acceleration 1 100] [--frame-rate 30] [--readouts 0 25]
        [--methods timeless default thesis] [--links auto 100]

Renders (once, into WORKDIR; reused by later runs) the rig with the board moving at each speed
(turning at 100 deg/s per m/s), cameras' clocks drawn in +-``--offset-ms`` and, in a second
render per speed, a rolling-shutter readout of ``--readout-ms``; synth's defaults otherwise
(timestamps.csv with 0.5 ms jitter, colour noise 2 DN, blur 0.6 px). On each it runs
``calibrate --refine none`` three ways: the timeless model (``bundle.time: fixed``, the rest
auto), the default (``bundle.time: auto``: the evidence ladder decides) and the thesis method
(tools/peers.py), and prints one markdown table row per render and method: worst camera error
against ground_truth.yaml, RMS of error/sigma over the non-reference cameras, the model the
ladder chose, the worst clock-offset and readout errors, and the bundle stage's time.
``--no-timestamps`` calibrates a copy of each render without its timestamps.csv. ``--burst N``
renders each board position as N consecutive frame sets (a continuous recording, 1/30 s apart)
with the board accelerating at ``--acceleration`` (m/s^2, deg/s^2) within the burst: the time
model's motion prior then ties consecutive sets (``bundle.time_link_ms``). ``--frame-rate``
spaces a burst's sets 1/FPS s apart; ``--links`` runs the default once per
``bundle.time_link_ms`` given (a number of ms or ``auto``), labelled ``default, link X``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from rgbd_calib import CalibrationConfig, FolderDataset, calibrate
from rgbd_calib.core.config import BundleConfig
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.model.board import thesis_board
from rgbd_calib.synth.render import SynthParams, load_ground_truth, synthesize

sys.path.insert(0, str(Path(__file__).parent))
from peers import thesis_method  # noqa: E402

DPS_PER_MPS = 100.0  # the board turns at this rate per unit of speed (a hand's wave)


def render(workdir: Path, layout: str, frames: int, seed: int, speed: float, offset_ms: float,
           readout_ms: float, timestamps: bool, burst: int = 1,
           acceleration: tuple[float, float] = (0.0, 0.0), frame_rate: float = 30.0) -> Path:
    name = f"{layout}_s{speed:g}_rs{readout_ms:g}_f{frames}_seed{seed}"
    if burst > 1:
        name += f"_b{burst}_a{acceleration[0]:g}_{acceleration[1]:g}"
    if frame_rate != 30.0:
        name += f"_fps{frame_rate:g}_o{offset_ms:g}"
    out = workdir / name
    if not (out / "ground_truth.yaml").exists():
        shutil.rmtree(out, ignore_errors=True)
        params = SynthParams(motion=(speed, DPS_PER_MPS * speed), sync_offset_ms=offset_ms,
                             rolling_shutter_ms=readout_ms, burst=burst,
                             acceleration=acceleration if speed else (0.0, 0.0),
                             frame_rate=frame_rate)
        synthesize(out, layout, frames, seed, thesis_board(), params)
    if timestamps:
        return out
    bare = workdir / (name + "_no_timestamps")
    if not bare.exists():
        shutil.copytree(out, bare)
        for f in bare.glob("*/timestamps.csv"):
            f.unlink()
    return bare


def row(data: Path, method: str, result, seconds: float) -> str:
    gt = load_ground_truth(data)
    ref = result.extrinsics.reference
    worst_mm = worst_deg = 0.0
    z = []
    for c, cam in result.extrinsics.cameras.items():
        deg, mm = transform_error(cam.T_ref_cam, gt.T_ref_cam[c])
        worst_mm, worst_deg = max(worst_mm, mm), max(worst_deg, deg)
        if c != ref and cam.sigma_translation_mm > 0:
            z.append(mm / cam.sigma_translation_mm)
    n = len(gt.T_ref_cam)
    missing = n - len(result.extrinsics.cameras)
    ladder = result.self_calibration
    chosen = ladder.chosen.name if ladder is not None else "-"
    clock = result.bundle.time if result.bundle is not None else None
    off = ro = "-"
    if clock is not None:
        off_ms = max(abs(clock.total_offset_ms(c) - gt.offset_ms.get(c, 0.0))
                     for c in clock.offset_ms)
        ro_ms = max(abs(clock.readout_ms[c] - gt.readout_ms.get(c, 0.0))
                    for c in clock.readout_ms)
        off, ro = f"{off_ms:.2f}", f"{ro_ms:.2f}"
    bundle_s = result.timings_s.get("bundle", float("nan"))
    return (f"| {method} | {worst_mm:.3f} / {worst_deg:.4f}"
            + (f" ({missing} of {n} not calibrated)" if missing else "")
            + f" | {np.sqrt(np.mean(np.square(z))) if z else float('nan'):.2f} | {chosen} | "
            f"{off} | {ro} | {bundle_s:.1f} | {seconds:.0f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--layout", default="race")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--seed", type=int, default=31)
    ap.add_argument("--speeds", type=float, nargs="+", default=[0.0, 0.1, 0.3, 0.5])
    ap.add_argument("--offset-ms", type=float, default=16.0)
    ap.add_argument("--readout-ms", type=float, default=25.0)
    ap.add_argument("--no-timestamps", action="store_true")
    ap.add_argument("--readouts", type=float, nargs="+", default=None,
                    help="the readouts to render (ms; default: 0 and --readout-ms)")
    ap.add_argument("--burst", type=int, default=1)
    ap.add_argument("--acceleration", type=float, nargs=2, default=[0.0, 0.0],
                    metavar=("MPS2", "DPS2"))
    ap.add_argument("--methods", nargs="+", default=["timeless", "default", "thesis"],
                    choices=["timeless", "default", "thesis"])
    ap.add_argument("--no-thesis", action="store_true")
    ap.add_argument("--frame-rate", type=float, default=30.0)
    ap.add_argument("--links", nargs="+", default=None,
                    help="bundle.time_link_ms values to run the default with (ms or auto)")
    args = ap.parse_args()
    if args.no_thesis and "thesis" in args.methods:
        args.methods.remove("thesis")
    args.workdir.mkdir(parents=True, exist_ok=True)
    board = thesis_board()
    print(f"{args.layout}, {args.frames} frame sets, seed {args.seed}, offsets in "
          f"+-{args.offset_ms:g} ms, timestamps {'removed' if args.no_timestamps else 'kept'}"
          + (f", bursts of {args.burst} sets, acceleration {args.acceleration[0]:g} m/s^2 / "
             f"{args.acceleration[1]:g} deg/s^2" if args.burst > 1 else "")
          + (f", {args.frame_rate:g} fps" if args.frame_rate != 30.0 else ""))
    print("| speed, shutter | method | worst mm / deg | RMS err/sigma | model chosen | "
          "offset err ms | readout err ms | bundle s | total s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for speed in args.speeds:
        for readout in (args.readouts if args.readouts is not None else (0.0, args.readout_ms)):
            data = render(args.workdir, args.layout, args.frames, args.seed, speed,
                          args.offset_ms, readout, not args.no_timestamps, args.burst,
                          tuple(args.acceleration), args.frame_rate)
            label = f"{speed:g} m/s, " + (f"{readout:g} ms rolling" if readout else "global")
            cache = data.parent / (data.name + "_cache")
            runs = [(m, c) for m, c in
                    [("timeless", CalibrationConfig(refine="none",
                                                    bundle=BundleConfig(time="fixed"))),
                     ("default", CalibrationConfig(refine="none")),
                     ("thesis", None)] if m in args.methods]
            if args.links is not None and "default" in args.methods:
                at = [m for m, _ in runs].index("default")
                runs[at:at + 1] = [(f"default, link {link}", CalibrationConfig(
                    refine="none", bundle=BundleConfig(
                        time_link_ms=link if link == "auto" else float(link))))
                    for link in args.links]
            for method, config in runs:
                t0 = time.perf_counter()
                result = (thesis_method(FolderDataset(data), board, cache_dir=cache)
                          if config is None else
                          calibrate(FolderDataset(data), board, config, cache_dir=cache))
                if method.startswith("default, link"):  # the window used
                    method += f" = {result.config.bundle.time_model.time_link_ms:g} ms"
                print(f"| {label} " + row(data, method, result, time.perf_counter() - t0),
                      flush=True)


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
