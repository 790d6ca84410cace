"""Experiment (not in the package; docs/depth.md "What was tried and not adopted"): every
camera's depth model from the board and the scene's overlaps at once (issue 33, item 2): the
board fixes each camera's depth where the board was, the overlaps tie the cameras' depth
together over the whole scene they share.

    python tools/experiment_joint_depth.py RENDER_DIR WORKDIR [fixed] [full] [select]

calibrates the synthetic render (default config), then fits the models jointly with the terms
the board chose (``fixed``), every term free (``full``) or chosen by forward selection
(``select``, slow), and prints per camera the median signed distance of its corrected cloud to
the true scene surfaces (``rgbd_calib.synth.surfaces``) by distance band, and the parameters
against the truth in sigmas.

With the extrinsics fixed by the board (colour), two cameras that see one surface must put it
in the same place. For an overlapping pair ``(a, b)`` each sampled point of a is matched once
(at the board-fitted models) to a window of b's pixels around its projection
(:class:`~.agreement.Surface`: chosen by pixel, not by depth, so the noise picks nothing). The
residual is the distance along b's normal between a's corrected point and the plane of b's
corrected window where b's ray through a's point meets it, over the depth noise; it is a
function of both cameras' depth models. Together with each camera's board residuals
(:mod:`.depth_model_fit`) one Gauss-Newton with Huber weights solves every camera's free
parameters; the covariance is the cluster-robust sandwich (clusters: board views, and blocks of
a's image per pair) with the model-based one as its floor, as for the board alone.

Which terms are free is chosen as for the board alone (forward selection in ladder order by a
cluster-robust Wald test), one camera at a time, every other camera's terms held at their
current choice."""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from bench_fused import true_rig

from rgbd_calib.core.config import CalibrationConfig, DepthConfig
from rgbd_calib.core.depth_model import PARAMETERS, TERMS, DepthModel, identity_model
from rgbd_calib.depth.clouds import board_faces
from rgbd_calib.depth.depth_model_fit import (
    STEP,
    BoardSamples,
    TermTest,
    _huber,
    _threshold,
    board_samples,
    predicted_depth_m,
)
from rgbd_calib.depth.overlap_models import (
    OverlapSamples,
    measured_rays,
    overlap_samples,
    signed_distances,
)
from rgbd_calib.depth.registration import find_overlapping_pairs
from rgbd_calib.depth.stage import board_views_per_camera
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.pipelines.calibrate import calibrate
from rgbd_calib.synth.surfaces import surface_distances

GN_ITERATIONS = 6


# --------------------------------------------------------------------------- residuals
def board_residual(model: DepthModel, s: BoardSamples) -> np.ndarray:
    pred = predicted_depth_m(model, s)
    return np.where(pred > 0, s.z_measured - pred, np.nan) / s.sigma_z


def overlap_residual(ma: DepthModel, mb: DepthModel, o: OverlapSamples,
                     T_ref_a: np.ndarray, T_ref_b: np.ndarray) -> np.ndarray:
    """a's corrected point against the plane of b's corrected window where b's ray through
    it meets it, along b's normal, over the noise (+ = a's depth beyond b's surface)."""
    return signed_distances(ma, mb, o, np.linalg.inv(T_ref_b) @ T_ref_a)[0] / o.sigma_m


@dataclass(frozen=True)
class JointSolve:
    models: dict[str, DepthModel]
    names: dict[str, tuple[str, ...]]  # camera -> its free parameters
    index: dict[tuple[str, str], int]  # (camera, parameter) -> column
    cov: np.ndarray
    chi2: float
    dof: int

    def sigma(self, camera: str, p: str) -> float:
        k = self.index[camera, p]
        return float(math.sqrt(max(self.cov[k, k], 0.0)))


def joint_solve(models: dict[str, DepthModel], names: dict[str, tuple[str, ...]],
                board: dict[str, BoardSamples], overlaps: list[OverlapSamples],
                T_ref_cam: dict[str, np.ndarray], huber_k: float,
                iterations: int = GN_ITERATIONS) -> JointSolve:
    """Gauss-Newton with Huber IRLS of the free parameters ``names`` of every camera (the
    others held at ``models``) on the board and overlap residuals, and their cluster-robust
    covariance."""
    index = {(c, p): k for k, (c, p) in enumerate((c, p) for c in sorted(names)
                                                  for p in names[c])}
    n = len(index)
    models = dict(models)
    for it in range(iterations + 1):
        H, g, scores, chi2, count = _normal_equations(models, names, index, board, overlaps,
                                                      T_ref_cam, huber_k, with_jacobian=n > 0)
        if n == 0 or it == iterations:
            break
        step = np.linalg.lstsq(H, -g, rcond=None)[0]
        for (c, p), k in index.items():
            models[c] = models[c].with_values({p: models[c].value(p) + step[k]})
        if np.all(np.abs(step) < 1e-3 * np.array([STEP[p] for _, p in index])):
            H, g, scores, chi2, count = _normal_equations(
                models, names, index, board, overlaps, T_ref_cam, huber_k, True)
            break
    dof = max(count - n, 1)
    if n == 0:
        return JointSolve(models, names, index, np.zeros((0, 0)), chi2, dof)
    Hinv = np.linalg.pinv(H)
    G = np.array(list(scores.values()))
    m = G.shape[0]
    sandwich = Hinv @ (G.T @ G) @ Hinv * (m / max(m - 1, 1))
    model_based = Hinv * max(chi2 / dof, 1.0)
    e, V = np.linalg.eigh(sandwich - model_based)
    return JointSolve(models, names, index, model_based + (V * np.maximum(e, 0.0)) @ V.T,
                      chi2, dof)


def _normal_equations(models, names, index, board, overlaps, T_ref_cam, huber_k,
                      with_jacobian: bool):
    n = len(index)
    H, g = np.zeros((n, n)), np.zeros(n)
    scores: dict[tuple, np.ndarray] = {}
    chi2, count = 0.0, 0

    def add(r: np.ndarray, cols: list[tuple[int, np.ndarray]], clusters: np.ndarray, key):
        nonlocal chi2, count
        ok = np.isfinite(r)
        for _, col in cols:
            ok &= np.isfinite(col)
        r0 = np.where(ok, r, 0.0)
        w = np.where(ok, _huber(r0, huber_k), 0.0)
        chi2 += float(np.sum(w * r0 * r0))
        count += int(np.count_nonzero(ok))
        if not cols:
            return
        idx = [k for k, _ in cols]
        J = np.column_stack([np.where(ok, col, 0.0) for _, col in cols])
        H[np.ix_(idx, idx)] += J.T @ (w[:, None] * J)
        wr = w * r0
        g[idx] += J.T @ wr
        contrib = J * wr[:, None]
        for cl in np.unique(clusters[ok]):
            vec = scores.setdefault((key, int(cl)), np.zeros(n))
            vec[idx] += contrib[clusters == cl].sum(axis=0)

    def columns(fun, cams):
        out = []
        if not with_jacobian:
            return out
        for c in cams:
            for p in names.get(c, ()):
                h = STEP[p]
                saved = models[c]
                models[c] = saved.with_values({p: saved.value(p) + h})
                up = fun()
                models[c] = saved.with_values({p: saved.value(p) - h})
                dn = fun()
                models[c] = saved
                out.append((index[c, p], (up - dn) / (2 * h)))
        return out

    def board_fun(c: str, s: BoardSamples):
        return lambda: board_residual(models[c], s)

    def pair_fun(o: OverlapSamples):
        return lambda: overlap_residual(models[o.cam_a], models[o.cam_b], o,
                                        T_ref_cam[o.cam_a], T_ref_cam[o.cam_b])

    for c, s in board.items():
        if c in models:
            fun = board_fun(c, s)
            add(fun(), columns(fun, [c]), s.view, ("board", c))
    for o in overlaps:
        if o.cam_a in models and o.cam_b in models:
            fun = pair_fun(o)
            add(fun(), columns(fun, [o.cam_a, o.cam_b]), o.block, ("pair", o.cam_a, o.cam_b))
    return H, g, scores, chi2, count


def _wald(solve: JointSolve, camera: str, term: str) -> float:
    idx = [solve.index[camera, p] for p in TERMS[term]]
    theta = np.array([solve.models[camera].value(p) - (1.0 if p == "scale" else 0.0)
                      for p in TERMS[term]])
    return float(theta @ np.linalg.pinv(solve.cov[np.ix_(idx, idx)]) @ theta)


def fit_joint(base: dict[str, DepthModel], board: dict[str, BoardSamples],
              overlaps: list[OverlapSamples], T_ref_cam: dict[str, np.ndarray],
              config: DepthConfig | None = None,
              start_terms: dict[str, tuple[str, ...]] | None = None,
              ) -> tuple[JointSolve, dict[str, dict[str, TermTest]]]:
    """Every camera's terms chosen and parameters solved on the board and the overlaps (see
    the module docstring). ``base`` are the identity models; ``start_terms`` the terms to
    start from (default none). Returns the final solve and each camera's term tests."""
    config = config or DepthConfig()
    k = config.model_fit.scale_huber_k
    terms = {c: list(start_terms.get(c, ())) if start_terms else [] for c in base}

    def names_of(t: dict[str, list[str]]) -> dict[str, tuple[str, ...]]:
        return {c: tuple(p for term in TERMS if term in t[c] for p in TERMS[term]) for c in t}

    current = joint_solve(base, names_of(terms), board, overlaps, T_ref_cam, k)
    tests: dict[str, dict[str, TermTest]] = {c: {} for c in base}
    clusters = _clusters(board, overlaps)
    changed = True
    while changed:
        changed = False
        for c in sorted(base):
            for term in TERMS:
                if term in terms[c]:
                    continue
                trial_terms = {**terms, c: [*terms[c], term]}
                trial = joint_solve(current.models, names_of(trial_terms), board, overlaps,
                                    T_ref_cam, k, iterations=3)
                wald = _wald(trial, c, term)
                thr = _threshold(term, clusters.get(c, 0), len(names_of(trial_terms)[c]))
                tests[c][term] = TermTest(term, wald, thr, False)
                if wald > thr:  # the first in the ladder's order that passes
                    terms = trial_terms
                    current = trial
                    tests[c][term] = replace(tests[c][term], kept=True)
                    changed = True
                    break
    final = joint_solve(current.models, names_of(terms), board, overlaps, T_ref_cam, k)
    return final, tests


def _clusters(board: dict[str, BoardSamples], overlaps: list[OverlapSamples]) -> dict[str, int]:
    """Per camera the clusters its parameters are judged over: its board views and the image
    blocks of its pairs."""
    out = {c: len(s.frames) for c, s in board.items()}
    for o in overlaps:
        n = len(np.unique(o.block))
        for c in (o.cam_a, o.cam_b):
            out[c] = out.get(c, 0) + n
    return out


# --------------------------------------------------------------------------- the experiment
BANDS = ((0.0, 1.5), (1.5, 2.5), (2.5, 3.5), (3.5, 9.0))


def truth_line(name: str, model: DepthModel, rays: np.ndarray, z: np.ndarray,
               T_world_cam: np.ndarray, rig) -> str:
    p = model.correct_points(rays, z)
    ok = np.isfinite(p[:, 0])
    pw = p[ok] @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    s = surface_distances(rig.scene, pw, T_world_cam[:3, 3]).signed_m * 1e3
    zz = p[ok][:, 2]
    bands = [np.nanmedian(s[(zz >= lo) & (zz < hi)]) if np.any((zz >= lo) & (zz < hi))
             else np.nan for lo, hi in BANDS]
    return f"{name} {np.nanmedian(s):+.2f} [" + " ".join(f"{b:+.1f}" for b in bands) + "]"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("render", type=Path, help="a synthetic render (synth's folder)")
    ap.add_argument("work", type=Path, help="the calibration's cache folder")
    ap.add_argument("modes", nargs="*", default=["fixed", "full"],
                    choices=["fixed", "full", "select"])
    args = ap.parse_args()
    render, work, modes = args.render, args.work, args.modes
    ds = FolderDataset(render)
    res = calibrate(ds, thesis_board(), CalibrationConfig(), cache_dir=work)
    rig, gt = true_rig(render)
    T = {c: e.T_ref_cam for c, e in res.extrinsics.cameras.items()}
    clouds, fits = res.depth.clouds, res.depth.depth_models
    m0 = {c: f.model for c, f in fits.items()}
    views = board_views_per_camera(res.observations, T, res.bundle.T_ref_board)
    config = DepthConfig()
    board = {c: board_samples(ds.rig.cameras[c], board_faces(ds, c, views[c], res.board,
                                                              config), config)
             for c in clouds if c in views}
    pairs = [(o.cam_a, o.cam_b) for o in find_overlapping_pairs(clouds, T)]
    overlaps = overlap_samples(clouds, T, pairs, m0)
    base = {c: identity_model(ds.rig.cameras[c]) for c in clouds}
    solved = {}
    for mode in modes:
        if mode == "select":
            sol, _ = fit_joint(base, board, overlaps, T, config)
        else:
            names = {c: (tuple(PARAMETERS) if mode == "full"
                         else tuple(p for p in PARAMETERS if p in m0[c].sigmas)) for c in base}
            start = {c: base[c].with_values({p: m0[c].value(p) for p in names[c]})
                     for c in base}
            sol = joint_solve(start, names, board, overlaps, T, config.model_fit.scale_huber_k)
        solved[mode] = sol
    cams = {c.name: c for c in rig.cameras}
    print("camera: median signed distance to the true surfaces (mm) [by band "
          + " ".join(f"{lo}-{hi} m" for lo, hi in BANDS) + "]")
    for c in sorted(clouds):
        rays, z = measured_rays(clouds[c], m0.get(c))
        ok = np.isfinite(z)
        Tw = cams[c].T_world_cam
        parts = [truth_line("true-model", gt.depth_model[c], rays[ok], z[ok], Tw, rig),
                 truth_line("board", m0[c], rays[ok], z[ok], Tw, rig)]
        parts += [truth_line(m, s.models[c], rays[ok], z[ok], Tw, rig)
                  for m, s in solved.items()]
        print(c, " | ".join(parts))
        for m, s in solved.items():
            zs = {p: round((s.models[c].value(p) - gt.depth_model[c].value(p))
                           / max(s.sigma(c, p), 1e-12), 1) for p in s.names[c]}
            print(f"   {m}: parameters - truth in sigmas {zs}")


if __name__ == "__main__":
    from toolmain import run_tool

    run_tool(main)
