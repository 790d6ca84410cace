"""Time ``bundle_adjust`` against a baseline revision of ``rgbd_calib/solve/bundle.py``.

    python tools/profile_bundle.py --baseline-rev d0ab723 --data /tmp/bench_data \\
        --cache /tmp/bundle_cache --sets thesis-line-f40-s0 race-f40-s0 --repeats 3

For each set, runs the calibration once up to the bundle stage (detections cached under
``--cache/<set>``, so only the first run pays detection) and captures the first
:class:`~rgbd_calib.solve.bundle.BundleProblem` solved. Then calls the working-tree
``bundle_adjust`` ("new") and the one at ``--baseline-rev`` ("old", loaded with ``git show``;
a revision whose ``bundle_adjust`` takes a ``BundleProblem``, 2026-11 on) on the same inputs,
interleaved and alternating which goes first so that machine load hits both alike, and
reports the median time of each, the split of each (LM solves, marginals, rest) and the
largest differences of the results: camera poses (mm, deg), sigmas (relative), estimated pixel
sigma, marker residuals, iterations and outliers. ``--calibrate`` also reports the
calibration's own ``timings_s["bundle"]`` (which includes building the marker measurements)
with either version patched in, interleaved.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import rgbd_calib.pipelines.calibrate as cal  # noqa: E402
import rgbd_calib.solve.ladder as ladder  # noqa: E402
from rgbd_calib.core.config import CalibrationConfig  # noqa: E402
from rgbd_calib.core.geometry import transform_error  # noqa: E402
from rgbd_calib.model.board import thesis_board  # noqa: E402
from rgbd_calib.model.dataset import FolderDataset  # noqa: E402
from rgbd_calib.solve import bundle as new  # noqa: E402
from rgbd_calib.solve.bundle import BundleProblem  # noqa: E402

sys.path.insert(0, str(ROOT / "tools"))
from baseline import module_at  # noqa: E402


def capture_inputs(data: Path, cache: Path) -> BundleProblem:
    """The first problem the calibration's ``bundle_adjust`` solves on ``data`` (no depth
    refine)."""
    captured: dict = {}
    original = ladder.bundle_adjust

    def spy(problem):
        captured.setdefault("problem", problem)
        return original(problem)

    ladder.bundle_adjust = spy
    try:
        cache.mkdir(parents=True, exist_ok=True)
        cal.calibrate(FolderDataset(data), thesis_board(),
                      CalibrationConfig(refine="none", workers=2), cache_dir=cache)
    finally:
        ladder.bundle_adjust = original
    return captured["problem"]


def solver(mod):
    """``mod.bundle_adjust``: a function of a problem, the working tree's and a baseline's
    alike (revisions before ``BundleProblem`` took loose parameters: not supported)."""
    return mod.bundle_adjust


def calibrate_bundle_time(data: Path, cache: Path, bundle_adjust) -> float:
    """``timings_s["bundle"]`` of a calibration run with ``bundle_adjust`` (a function of a
    problem) patched in."""
    original = ladder.bundle_adjust
    ladder.bundle_adjust = bundle_adjust
    try:
        res = cal.calibrate(FolderDataset(data), thesis_board(),
                            CalibrationConfig(refine="none", workers=2), cache_dir=cache)
    finally:
        ladder.bundle_adjust = original
    return res.timings_s["bundle"]


def timed_split(mod, problem: BundleProblem) -> tuple[float, dict[str, float], object]:
    """Run ``mod.bundle_adjust`` with the LM solves and the marginals timed."""
    split = {"lm": 0.0, "marginals": 0.0}
    gt = mod.gtsam
    lm_cls, marg_cls = gt.LevenbergMarquardtOptimizer, gt.Marginals

    class LM:
        def __init__(self, *a):
            self._o = lm_cls(*a)

        def optimize(self):
            t = time.perf_counter()
            out = self._o.optimize()
            split["lm"] += time.perf_counter() - t
            return out

        def iterations(self):
            return self._o.iterations()

    def marginals(*a):
        t = time.perf_counter()
        out = marg_cls(*a)
        split["marginals"] += time.perf_counter() - t
        return out

    class Proxy:  # the module's gtsam with the two entry points wrapped
        def __getattr__(self, name):
            return {"LevenbergMarquardtOptimizer": LM, "Marginals": marginals}.get(
                name, getattr(gt, name))

    mod.gtsam = Proxy()
    try:
        t = time.perf_counter()
        res = solver(mod)(problem)
        total = time.perf_counter() - t
    finally:
        mod.gtsam = gt
    split["rest"] = total - split["lm"] - split["marginals"]
    return total, split, res


def compare(a, b) -> dict[str, float]:
    dmm = ddeg = dsig = 0.0
    for c, T in a.T_ref_cam.items():
        _, mm = transform_error(T, b.T_ref_cam[c])
        # chordal angle |R_a - R_b|_F / sqrt(2): no arccos round-off floor (~1e-6 deg)
        deg = np.degrees(np.linalg.norm(T[:3, :3] - b.T_ref_cam[c][:3, :3]) / np.sqrt(2))
        dmm, ddeg = max(dmm, mm), max(ddeg, deg)
        for s_a, s_b in ((a.sigma_rotation_deg[c], b.sigma_rotation_deg[c]),
                         (a.sigma_translation_mm[c], b.sigma_translation_mm[c])):
            if s_a > 0:
                dsig = max(dsig, abs(s_a - s_b) / s_a)
    return {"pose_mm": dmm, "pose_deg": ddeg, "sigma_rel": dsig,
            "pixel_sigma_rel": abs(a.pixel_sigma_estimated - b.pixel_sigma_estimated)
            / a.pixel_sigma_estimated,
            "residual_px": max((abs(x[3] - y[3]) for x, y in zip(a.residuals_px, b.residuals_px)),
                               default=0.0),
            "same_markers": [x[:3] for x in a.residuals_px] == [y[:3] for y in b.residuals_px],
            "iterations": f"{a.iterations}/{b.iterations}",
            "outliers_equal": [o[:3] for o in a.outliers] == [o[:3] for o in b.outliers]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline-rev", required=True)
    ap.add_argument("--data", type=Path, default=Path("/tmp/bench_data"))
    ap.add_argument("--cache", type=Path, required=True, help="detection cache root (writable)")
    ap.add_argument("--sets", nargs="+", default=["thesis-line-f40-s0", "race-f40-s0"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--calibrate", action="store_true",
                    help="also time whole calibrations (timings_s['bundle'])")
    opts = ap.parse_args()
    old = module_at(opts.baseline_rev, "rgbd_calib/solve/bundle.py", "solve.bundle_baseline")
    for name in opts.sets:
        problem = capture_inputs(opts.data / name, opts.cache / name)
        times: dict[str, list[float]] = {"old": [], "new": []}
        splits: dict[str, list[dict]] = {"old": [], "new": []}
        results = {}
        for r in range(opts.repeats):
            order = ("old", "new") if r % 2 == 0 else ("new", "old")
            for tag in order:
                t, split, res = timed_split(old if tag == "old" else new, problem)
                times[tag].append(t)
                splits[tag].append(split)
                results[tag] = res
        n = len(problem.measurements)
        print(f"{name}: {n} markers")
        for tag in ("old", "new"):
            med = {k: statistics.median(s[k] for s in splits[tag]) for k in splits[tag][0]}
            print(f"  {tag}: median {statistics.median(times[tag]):.3f} s  "
                  f"(runs {', '.join(f'{t:.2f}' for t in times[tag])}; "
                  + ", ".join(f"{k} {v:.3f}" for k, v in med.items()) + ")")
        print(f"  speed-up {statistics.median(times['old']) / statistics.median(times['new']):.2f}x"
              f"  differences {compare(results['old'], results['new'])}")
        if opts.calibrate:
            cal_times: dict[str, list[float]] = {"old": [], "new": []}
            for r in range(opts.repeats):
                for tag in (("old", "new") if r % 2 == 0 else ("new", "old")):
                    fn = solver(old if tag == "old" else new)
                    cal_times[tag].append(
                        calibrate_bundle_time(opts.data / name, opts.cache / name, fn))
            print("  calibrate timings_s['bundle'] median: " + ", ".join(
                f"{tag} {statistics.median(v):.3f} s" for tag, v in cal_times.items()))


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
