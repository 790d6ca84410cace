"""The depth-model fit alone on a synthetic camera (issue 59 item 2): median seconds of
``fit_depth_model`` over repeats, and the model it chose.

    python tools/bench_depth_fit.py [--views 40] [--pixels 1500] [--repeats 3]

The camera's board views are drawn at 0.8-2 m, tilted at random, their depth measured with a
scale and disparity-offset error and D435-like noise, each view's plane with a small pose
covariance (the random effects of the fit); every term is then free (15 views or more).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from toolmain import run_tool  # noqa: E402

from rgbd_calib.core.camera import CameraIntrinsics  # noqa: E402
from rgbd_calib.core.depth_model import DepthModel  # noqa: E402
from rgbd_calib.depth.depth_model_fit import BoardSamples, fit_depth_model  # noqa: E402


def samples(views: int, pixels: int, seed: int = 0) -> BoardSamples:
    rng = np.random.default_rng(seed)
    truth = DepthModel(30.0, {"scale": 1.004, "d0": 0.2, "dx": 0.1, "tz": 2.0})
    parts = []
    for v in range(views):
        n = np.array([rng.normal(0, 0.2), rng.normal(0, 0.2), 1.0])
        n /= np.linalg.norm(n)
        d = rng.uniform(0.8, 2.0)
        rays = np.column_stack([rng.uniform(-0.5, 0.5, pixels), rng.uniform(-0.3, 0.3, pixels),
                                np.ones(pixels)])
        z = d / (rays @ n)
        zm = truth.measured_depth(rays[:, 0], rays[:, 1], z) + rng.normal(0, 1e-3, pixels) * z * z
        parts.append((rays, zm, np.tile(n, (pixels, 1)), np.full(pixels, d), 1e-3 * z * z,
                      np.full(pixels, v)))
    c = [np.concatenate([p[i] for p in parts]) for i in range(6)]
    cov = np.tile(np.eye(3)[None] * 1e-6, (views, 1, 1))
    return BoardSamples(c[0], c[1], c[2], c[3], c[4], c[5].astype(int),
                        tuple(f"f{v}" for v in range(views)), np.zeros((len(c[0]), 2)), cov)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--pixels", type=int, default=1500, help="board pixels per view")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    intr = CameraIntrinsics(fx=600, fy=600, cx=424, cy=240, width=848, height=480)
    s = samples(args.views, args.pixels)
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        fit = fit_depth_model("c", s, intr)
        times.append(time.perf_counter() - t0)
    print(f"fit_depth_model, {args.views} views x {args.pixels} pixels: median "
          f"{sorted(times)[len(times) // 2]:.2f} s over {args.repeats}; terms "
          f"{'+'.join(fit.model.terms) or 'identity'}")
    return 0


if __name__ == "__main__":
    run_tool(main)
