"""Issue 14, real data: ``refine`` on frame pairs of a TUM RGB-D sequence (Kinect v1, mocap
truth), each pair converted by ``tools/make_real_rgbd_sample.py`` and started off the truth.

Usage: python tools/measure_tum_pairs.py SEQUENCE [--min-mm 50] [--max-mm 150] [--every K]
[--seeds 0 1] [--method colored-icp] [--pairs I,J ...] [--known-scale]
[--set key=value ...] (DepthConfig overrides)

Prints per pair: mocap baseline, start error, error after refine (mm / deg), the result's
sigma_translation_mm, error/sigma, the pair's normalised RMS and acceptance; then
RMS(error / sigma) over the pairs.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rgbd_calib.core.config import DepthConfig
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.model.results import load_extrinsics
from rgbd_calib.pipelines.refine import refine_extrinsics
from rgbd_calib.synth.render import load_ground_truth

TOOLS = Path(__file__).resolve().parent


def _tool():
    spec = importlib.util.spec_from_file_location("make_real_rgbd_sample",
                                                  TOOLS / "make_real_rgbd_sample.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["make_real_rgbd_sample"] = mod
    spec.loader.exec_module(mod)
    return mod


def _value(v: str):
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return v


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--min-mm", type=float, default=50.0)
    ap.add_argument("--max-mm", type=float, default=150.0)
    ap.add_argument("--every", type=int, default=1, help="take every K-th candidate pair")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--method", default="colored-icp")
    ap.add_argument("--pairs", nargs="*", default=None, help="I,J frame indices")
    ap.add_argument("--known-scale", action="store_true",
                    help="give refine depth-scale factors 1 (else unknown: marginalised)")
    ap.add_argument("--set", dest="overrides", nargs="*", default=[],
                    help="DepthConfig overrides key=value")
    args = ap.parse_args(argv)
    config = DepthConfig(**{k: _value(v) for k, v in (o.split("=", 1) for o in args.overrides)})
    tool = _tool()
    frames = tool.load_frames(args.sequence, 0.02, 0.02)
    if args.pairs:
        pairs = [tuple(int(x) for x in p.split(",")) for p in args.pairs]
    else:
        pairs = [(i, j) for i in range(len(frames)) for j in range(i + 1, len(frames))
                 if args.min_mm <= 1000 * np.linalg.norm(
                     tool.relative(frames[i], frames[j])[:3, 3]) <= args.max_mm]
        pairs = pairs[:: args.every]
    zs, errs = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i, j in pairs:
            for seed in args.seeds:
                out = Path(tmp) / f"p{i}_{j}_{seed}"
                tool.main([str(args.sequence), "--out", str(out), "--pair", str(i), str(j),
                           "--seed", str(seed)])
                gt = load_ground_truth(out)
                init = load_extrinsics(out / "init_extrinsics.yaml")
                t0 = time.perf_counter()
                ext, depth = refine_extrinsics(FolderDataset(out), init, args.method, config,
                                               workers=1, depth_scales={"a": 1.0, "b": 1.0}
                                               if args.known_scale else None)
                dt = time.perf_counter() - t0
                base = 1000 * np.linalg.norm(gt.T_ref_cam["b"][:3, 3])
                deg0, mm0 = transform_error(init.T_ref_cam("b"), gt.T_ref_cam["b"])
                deg1, mm1 = transform_error(ext.T_ref_cam("b"), gt.T_ref_cam["b"])
                e = ext.cameras["b"]
                p = depth.pairs[0] if depth.pairs else {}
                z = mm1 / e.sigma_translation_mm if np.isfinite(e.sigma_translation_mm) \
                    else float("nan")
                if np.isfinite(z):
                    zs.append(z)
                errs.append((mm1, deg1))
                print(f"{i:2d}-{j:2d} s{seed} base {base:5.1f} mm start {mm0:4.1f}/{deg0:.2f} "
                      f"-> {mm1:5.2f} mm / {deg1:.3f} deg  sigma {e.sigma_translation_mm:5.2f} mm"
                      f" / {e.sigma_rotation_deg:.3f} deg  err/sig {z:5.2f}  "
                      f"nrms {p.get('normalised_rms', float('nan')):.2f} "
                      f"rmse {p.get('rmse_after_mm', float('nan')):.1f} "
                      f"fit {p.get('fitness', float('nan')):.2f} "
                      f"acc {p.get('accepted')} {dt:.1f}s {p.get('reason') or ''}", flush=True)
    errs_a = np.array(errs)
    print(f"pairs {len(errs)}: error mm median {np.median(errs_a[:, 0]):.2f} max "
          f"{errs_a[:, 0].max():.2f}; deg max {errs_a[:, 1].max():.3f}; within 5 mm / 1 deg "
          f"{int(np.sum((errs_a[:, 0] <= 5) & (errs_a[:, 1] <= 1)))}; "
          f"RMS(err/sigma) {np.sqrt(np.mean(np.square(zs))) if zs else float('nan'):.2f}")
    return 0


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
