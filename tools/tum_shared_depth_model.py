"""Issue 33, real data: one depth model for the one Kinect of the TUM frames, estimated from
the overlaps of its frame pairs, then ``refine`` again with it (docs/depth.md, "Real data: one
depth model for the TUM Kinect").

    python tools/tum_shared_depth_model.py SEQUENCE [--min-mm 50] [--max-mm 150] [--every K]

Pass 1: every frame pair with a mocap baseline of ``--min-mm`` to ``--max-mm`` is converted
(``tools/make_real_rgbd_sample.py``: two frames as two cameras ``a``, ``b``, started 2 cm / 2 deg
off the truth) and refined (colored ICP, depth scale unknown: the ``refine`` default). Its static
clouds at refine's own result give each pair's overlap samples (a's points against b's surface
and b's against a's; ``tools/experiment_joint_depth.py``). Then one depth model, shared by every
frame (one physical camera), is fitted to all the overlaps at once: Gauss-Newton with Huber
weights over the disparity field's terms (gradient, curvature; the scale and the constant offset
shift every frame's depth alike and two frames 5-15 cm apart cannot see them), each term kept by
a cluster-robust Wald test with the pairs as clusters, as the board fit does. ``--oracle`` fits at
the mocap poses instead (information the calibration does not have: an upper bound only).

Pass 2: every pair refined again with that model for both frames; both passes' errors against
the mocap are printed per pair and summarised (median, within 5 mm / 1 deg, RMS(error / sigma)).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np
from experiment_joint_depth import overlap_residual, overlap_samples
from measure_tum_pairs import _tool
from scipy.stats import f as f_dist

from rgbd_calib.core.config import DepthConfig
from rgbd_calib.core.depth_model import TERMS, DepthModel, identity_model
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.depth.depth_model_fit import STEP
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.model.results import load_extrinsics
from rgbd_calib.pipelines.refine import refine_extrinsics
from rgbd_calib.synth.render import load_ground_truth

FIELD_TERMS = ("gradient", "curvature")  # what overlaps of one camera's frames can see
HUBER_K = 1.5
P_FALSE_TERM = 1e-3


def _refine(folder: Path, model: DepthModel | None):
    """refine of one converted pair: (error mm, error deg, sigma mm, extrinsics, depth)."""
    gt = load_ground_truth(folder)
    init = load_extrinsics(folder / "init_extrinsics.yaml")
    scales = None if model is None else {"a": model, "b": model}
    ext, depth = refine_extrinsics(FolderDataset(folder), init, "colored-icp", DepthConfig(),
                                   workers=1, depth_scales=scales)
    deg, mm = transform_error(ext.T_ref_cam("b"), gt.T_ref_cam["b"])
    return mm, deg, ext.cameras["b"].sigma_translation_mm, ext, depth, gt


def _residuals(model: DepthModel, samples) -> tuple[np.ndarray, np.ndarray]:
    """Every overlap residual (over its noise) under the shared ``model``, and its cluster
    (the pair's index)."""
    r, cl = [], []
    for k, (o, T) in enumerate(samples):
        x = overlap_residual(model, model, o, T[o.cam_a], T[o.cam_b])
        r.append(x)
        cl.append(np.full(x.size, k))
    return np.concatenate(r), np.concatenate(cl)


def fit_shared(base: DepthModel, samples, names: tuple[str, ...], iterations: int = 6):
    """Gauss-Newton with Huber IRLS of ``names`` of one model shared by every frame; returns
    the model, the cluster-robust covariance (pairs as clusters, never below the model-based
    one) and the number of clusters."""
    model = base
    for it in range(iterations + 1):
        r, cl = _residuals(model, samples)
        ok = np.isfinite(r)
        a = np.abs(np.where(ok, r, 0.0))
        w = np.where(ok, np.where(a <= HUBER_K, 1.0, HUBER_K / np.maximum(a, 1e-12)), 0.0)
        r0 = np.where(ok, r, 0.0)
        if not names:
            return model, np.zeros((0, 0)), int(cl.max()) + 1
        J = np.zeros((r.size, len(names)))
        for j, p in enumerate(names):
            up = _residuals(model.with_values({p: model.value(p) + STEP[p]}), samples)[0]
            dn = _residuals(model.with_values({p: model.value(p) - STEP[p]}), samples)[0]
            J[:, j] = np.where(ok & np.isfinite(up) & np.isfinite(dn), (up - dn) / (2 * STEP[p]),
                               0.0)
        H = J.T @ (w[:, None] * J)
        if it == iterations:
            break
        step = np.linalg.lstsq(H, -(J.T @ (w * r0)), rcond=None)[0]
        model = model.with_values({p: model.value(p) + d for p, d in zip(names, step)})
    Hinv = np.linalg.pinv(H)
    n_cl = int(cl.max()) + 1
    G = np.zeros((n_cl, len(names)))
    np.add.at(G, cl, J * (w * r0)[:, None])
    dof = max(int(np.count_nonzero(ok)) - len(names), 1)
    model_based = Hinv * max(float(np.sum(w * r0 * r0)) / dof, 1.0)
    sandwich = Hinv @ (G.T @ G) @ Hinv * (n_cl / max(n_cl - 1, 1))
    e, V = np.linalg.eigh(sandwich - model_based)
    return model, model_based + (V * np.maximum(e, 0.0)) @ V.T, n_cl


def select_shared(base: DepthModel, samples) -> tuple[DepthModel, dict[str, float], list[str]]:
    """Forward selection over :data:`FIELD_TERMS` by the cluster-robust Wald test."""
    chosen: list[str] = []
    model, cov = base, np.zeros((0, 0))
    lines = []
    while True:
        added = False
        for term in FIELD_TERMS:
            if term in chosen:
                continue
            names = tuple(p for t in [*chosen, term] for p in TERMS[t])
            m, c, n_cl = fit_shared(model, samples, names)
            idx = [names.index(p) for p in TERMS[term]]
            theta = np.array([m.value(p) for p in TERMS[term]])
            wald = float(theta @ np.linalg.pinv(c[np.ix_(idx, idx)]) @ theta)
            k = len(idx)
            thr = max(k * float(f_dist.ppf(1 - P_FALSE_TERM, k, max(n_cl - len(names), 1))),
                      k * math.log(max(n_cl, 2)))
            lines.append(f"{term}: Wald {wald:.1f} against {thr:.1f} with {chosen or 'none'}")
            if wald > thr:
                chosen.append(term)
                model, cov = m, c
                added = True
                break
        if not added:
            break
    names = tuple(p for t in chosen for p in TERMS[t])
    sig = {p: float(math.sqrt(max(cov[i, i], 0.0))) for i, p in enumerate(names)}
    return model, sig, lines


def _summary(label: str, rows: list[tuple[float, float, float]]) -> str:
    a = np.array(rows)
    z = a[:, 0] / a[:, 2]
    z = z[np.isfinite(z)]
    return (f"{label}: {len(a)} pairs, error median {np.median(a[:, 0]):.1f} mm, max "
            f"{a[:, 0].max():.1f} mm / {a[:, 1].max():.2f} deg, within 5 mm and 1 deg "
            f"{int(np.sum((a[:, 0] <= 5) & (a[:, 1] <= 1)))}, RMS(error / sigma) "
            f"{math.sqrt(np.mean(z * z)) if z.size else float('nan'):.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--min-mm", type=float, default=50.0)
    ap.add_argument("--max-mm", type=float, default=150.0)
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--oracle", action="store_true",
                    help="fit the model at the mocap poses (an upper bound, not a calibration)")
    args = ap.parse_args(argv)
    tool = _tool()
    frames = tool.load_frames(args.sequence, 0.02, 0.02)
    pairs = [(i, j) for i in range(len(frames)) for j in range(i + 1, len(frames))
             if args.min_mm <= 1000 * np.linalg.norm(
                 tool.relative(frames[i], frames[j])[:3, 3]) <= args.max_mm][:: args.every]
    with tempfile.TemporaryDirectory() as tmp:
        folders, first, samples = {}, {}, []
        for i, j in pairs:
            out = Path(tmp) / f"p{i}_{j}"
            tool.main([str(args.sequence), "--out", str(out), "--pair", str(i), str(j),
                       "--seed", "0"])
            folders[i, j] = out
            mm, deg, sig, ext, depth, gt = _refine(out, None)
            first[i, j] = (mm, deg, sig)
            T = dict(gt.T_ref_cam) if args.oracle else {c: ext.T_ref_cam(c) for c in "ab"}
            if len(depth.clouds) == 2:
                for o in overlap_samples(depth.clouds, T, [("a", "b"), ("b", "a")], {}):
                    samples.append((o, T))
            print(f"pass 1 {i:2d}-{j:2d}: {mm:5.1f} mm / {deg:.2f} deg, sigma {sig:.1f} mm",
                  flush=True)
        intr = FolderDataset(next(iter(folders.values()))).rig.cameras["a"]
        model, sig, lines = select_shared(identity_model(intr), samples)
        print(f"shared model from {len(samples)} overlap samples of {len(pairs)} pairs"
              f"{' (oracle: mocap poses)' if args.oracle else ''}:")
        for line in lines:
            print("  ", line)
        print("   terms:", [t for t in FIELD_TERMS if TERMS[t][0] in sig] or "identity",
              {p: f"{model.value(p):+.3f} +- {s:.3f} px" for p, s in sig.items()})
        second = {}
        for (i, j), out in folders.items():
            mm, deg, s, *_ = _refine(out, model if sig else None)
            second[i, j] = (mm, deg, s)
            print(f"pass 2 {i:2d}-{j:2d}: {first[i, j][0]:5.1f} -> {mm:5.1f} mm, "
                  f"{first[i, j][1]:.2f} -> {deg:.2f} deg, sigma {s:.1f} mm", flush=True)
        print(_summary("identity model", list(first.values())))
        print(_summary("shared model  ", list(second.values())))
    return 0


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
