"""Has a camera moved since the calibration? And if so, put it back (depth alone, no board).

A rig gets bumped: a camera knocked on its mount, a bracket that creeps. ``check`` takes one
frame set of the rig as it is now (or a few: their temporal median) and the calibration, and
decides per camera whether it is where the calibration says, from the depth clouds alone:

1. a static cloud per camera, with the calibration's depth-scale factors;
2. every overlapping pair registered (:func:`register_robust`): colored ICP from the
   calibrated relative pose and, when that does not fit the depth noise model (a camera
   knocked 5 cm / 5 deg is outside ICP's basin), the same ICP with a wider basin, then from a
   global alignment guided by the calibration (FPFH features + RANSAC, Rusu et al. ICRA 2009 /
   Open3D);
3. a pose graph (GTSAM) of the measured pairs and one prior per camera at its calibrated pose
   with the calibration's sigmas. A camera that moved makes every pair it is in disagree with
   those priors. Which cameras moved is found greedily (:func:`locate_moved`): free the
   camera whose prior costs most (the drop in chi-square when it is removed), as long as
   that drop is significant and the camera's move is beyond the tolerance; the majority that
   agrees with the calibration stays in place. Each camera's move is then estimated with its
   own prior removed, with a sigma from the graph's marginal plus the calibration's own.

:func:`fix_moved` re-registers only the moved cameras against the others (from the check's
estimate, so from a start centimetres off) and solves for them with the others held at their
calibration. The reference camera is no exception: if it moved, the rest is re-expressed in
its new frame (the reference frame is, by contract, the reference camera's).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import gtsam
import numpy as np
import open3d as o3d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..core.config import DepthConfig
from ..core.geometry import covariance_sigmas, invert_transform, transform_error
from ..core.progress import Progress, start
from ..depth.registration import (
    ICP_ERRORS,
    CameraCloud,
    PairRegistration,
    failed_registration,
    find_overlapping_pairs,
    one_line_error,
    register_pair,
    voxel_mean,
)
from ..model.dataset import FolderDataset
from ..model.results import CameraExtrinsics, Extrinsics
from ..solve.posegraph import RelativePose

Status = Literal["in_place", "moved", "unknown"]

MOVED_CHI2 = 22.46  # chi-square, 6 dof, 0.1 %: a camera's prior is dropped only beyond this


@dataclass(frozen=True)
class Tolerance:
    """A move smaller than both of these is not reported as moved, however significant
    (the depth pairs resolve 0.3-4 mm; a rig re-checked nightly should not alarm on noise)."""

    mm: float = 2.0
    deg: float = 0.2


@dataclass(frozen=True)
class CameraCheck:
    """One camera now against its calibration: ``moved_mm`` / ``moved_deg`` (camera centre in
    the reference frame, rotation angle) with 1-sigma ``sigma_mm`` / ``sigma_deg`` (graph
    marginal plus the calibration's), ``chi2``: how much the camera's calibrated pose
    disagrees with the depth (the drop in the graph's chi-square when its prior is removed,
    ~chi2(6) when it did not move), ``T_ref_cam_now``: its estimated pose now (in the
    calibration's reference frame), ``reason`` when the status is unknown."""

    camera: str
    status: Status
    moved_mm: float = float("nan")
    moved_deg: float = float("nan")
    sigma_mm: float = float("nan")
    sigma_deg: float = float("nan")
    chi2: float = float("nan")
    n_pairs: int = 0
    T_ref_cam_now: np.ndarray | None = None
    covariance_now: np.ndarray | None = None  # 6x6 body [rot, trans] of T_ref_cam_now
    reason: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "status": self.status, "moved_mm": self.moved_mm, "moved_deg": self.moved_deg,
            "sigma_mm": self.sigma_mm, "sigma_deg": self.sigma_deg, "chi2": self.chi2,
            "n_pairs": self.n_pairs, "reason": self.reason,
            "T_ref_cam_now": None if self.T_ref_cam_now is None else self.T_ref_cam_now.tolist(),
        }


@dataclass(frozen=True)
class CheckResult:
    """Per camera :class:`CameraCheck`, the pairs (report-ready dicts, see
    docs/report_schema.md) and the moved cameras in the order they were found."""

    cameras: dict[str, CameraCheck]
    pairs: list[dict[str, Any]]
    tolerance: Tolerance
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def moved(self) -> list[str]:
        return [c for c, r in self.cameras.items() if r.status == "moved"]

    @property
    def unknown(self) -> list[str]:
        return [c for c, r in self.cameras.items() if r.status == "unknown"]

    def to_dict(self) -> dict[str, Any]:
        return {
            "moved": self.moved, "unknown": self.unknown,
            "tolerance": {"mm": self.tolerance.mm, "deg": self.tolerance.deg},
            "moved_chi2": MOVED_CHI2,
            "cameras": {c: r.to_dict() for c, r in self.cameras.items()},
            "pairs": self.pairs, "timings_s": self.timings_s,
        }


# --------------------------------------------------------------------------- registration
def _fpfh_cloud(cloud: CameraCloud, voxel: float, config: DepthConfig):
    """Voxel means of the well-measured points with normals and FPFH features."""
    keep = cloud.sigma_z <= config.icp_max_sigma_z_m  # the points registration uses
    pts, _, _ = voxel_mean(cloud.points[keep].astype(float), voxel)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    pcd.orient_normals_towards_camera_location(np.zeros(3))
    feature = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100))
    return pcd, feature


def global_alignment(cloud_a: CameraCloud, cloud_b: CameraCloud, T_b_a_guess: np.ndarray,
                     config: DepthConfig, voxel: float = 0.05, search_m: float = 0.4,
                     max_move_m: float = 0.5, max_move_deg: float = 30.0,
                     seed: int = 0) -> np.ndarray | None:
    """``T_b_a`` from FPFH features and RANSAC (Rusu et al. 2009; Open3D), outside ICP's
    basin but guided by ``T_b_a_guess``: each of a's points is matched to the point of b with
    the nearest feature among those within ``search_m`` of where the guess puts it. A knocked
    camera moves centimetres and turns a few degrees (0.26 m at 3 m for 5 deg), not across the
    room: unguided matching in a room of walls and floor finds its symmetric aliases metres
    away (measured: 2-4 m off on the ring rig at RANSAC fitness 0.8-0.9). None when RANSAC
    finds nothing or lands further than ``max_move_m`` / ``max_move_deg`` from the guess.
    Seeded: the same answer on every run."""
    if cloud_a.n_points < 100 or cloud_b.n_points < 100:
        return None
    o3d.utility.random.seed(seed)
    src, f_src = _fpfh_cloud(cloud_a, voxel, config)
    tgt, f_tgt = _fpfh_cloud(cloud_b, voxel, config)
    p_src, p_tgt = np.asarray(src.points), np.asarray(tgt.points)
    if len(p_src) < 10 or len(p_tgt) < 10:
        return None
    F_src, F_tgt = np.asarray(f_src.data).T, np.asarray(f_tgt.data).T
    moved = p_src @ T_b_a_guess[:3, :3].T + T_b_a_guess[:3, 3]
    near = cKDTree(p_tgt).query_ball_point(moved, search_m, workers=-1)
    pairs = []
    for i, cand in enumerate(near):
        if cand:
            cand = np.asarray(cand)
            j = cand[np.argmin(np.sum((F_tgt[cand] - F_src[i]) ** 2, axis=1))]
            pairs.append((i, j))
    if len(pairs) < 10:
        return None
    reg = o3d.pipelines.registration
    distance = 1.5 * voxel
    result = reg.registration_ransac_based_on_correspondence(
        src, tgt, o3d.utility.Vector2iVector(np.asarray(pairs, dtype=np.int32)), distance,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    T = np.asarray(result.transformation, dtype=float)
    if result.fitness <= 0 or not np.all(np.isfinite(T)):
        return None
    deg, mm = transform_error(T, T_b_a_guess)
    if mm > 1000.0 * max_move_m or deg > max_move_deg:
        return None
    return T


def wide_config(config: DepthConfig) -> DepthConfig:
    """``config`` with a wider basin: two coarser ICP levels first (0.16 and 0.08 m voxels,
    each its own correspondence distance: a 5 deg turn moves a wall 2 m away by 0.17 m) and
    a 100 px wider crop (the crop to the other camera's view is made under the wrong guess)."""
    levels = [v for v in (0.16, 0.08) if v > config.voxel_schedule_m[0]]
    return config.model_copy(update={
        "voxel_schedule_m": levels + list(config.voxel_schedule_m),
        "iterations": [40] * len(levels) + list(config.iterations),
        "crop_margin_px": config.crop_margin_px + 100.0})


def _better(first: PairRegistration, second: PairRegistration) -> PairRegistration:
    """The registration that fits: accepted before rejected, then more of the source points
    matched (fitness), then smaller residuals against the noise model."""
    def key(r: PairRegistration):
        rms = r.normalised_rms if r.normalised_rms is not None and math.isfinite(
            r.normalised_rms) else math.inf
        return (r.accepted, round(r.fitness, 2), -rms)
    return second if key(second) > key(first) else first


def register_robust(cloud_a: CameraCloud, cloud_b: CameraCloud, T_ref_a: np.ndarray,
                    T_ref_b: np.ndarray, method: str = "colored-icp",
                    config: DepthConfig | None = None,
                    free_scale: tuple[bool, bool] = (False, False)) -> PairRegistration:
    """Register a to b from the given extrinsics; if that registration does not fit (a
    rejected pair: residuals far above the noise model, low fitness), again with a wider
    basin (:func:`wide_config`), and if that does not fit either, from a
    :func:`global_alignment`; the best fit wins (:func:`_better`). The returned registration's
    ``T_b_a_initial`` is always the one of the given extrinsics, so its correction is the
    move from them. No exception escapes: a failure rejects the pair."""
    config = config or DepthConfig()
    T_b_a0 = invert_transform(T_ref_b) @ np.asarray(T_ref_a, dtype=float)
    try:
        local = register_pair(cloud_a, cloud_b, T_ref_a, T_ref_b, method, config, free_scale)
        if local.accepted:
            return local
        best, start_kind = local, "given"
        wide = register_pair(cloud_a, cloud_b, T_ref_a, T_ref_b, method, wide_config(config),
                             free_scale)
        if _better(best, wide) is wide:
            best, start_kind = wide, "wide"
        T_start = None if best.accepted else global_alignment(cloud_a, cloud_b, T_b_a0, config)
        if T_start is not None:
            again = register_pair(cloud_a, cloud_b, T_ref_b @ T_start, T_ref_b, method, config,
                                  free_scale)
            if _better(best, again) is again:
                best, start_kind = again, "global"
    except ICP_ERRORS + (MemoryError,) as exc:
        return failed_registration(cloud_a.camera, cloud_b.camera, method, T_b_a0,
                                   f"registration failed: {one_line_error(exc)}")
    if best is local:
        return local
    deg, mm = transform_error(best.T_b_a, T_b_a0)
    return replace(best, T_b_a_initial=T_b_a0, correction_deg=deg, correction_mm=mm,
                   start=start_kind)


# --------------------------------------------------------------------------- inference
@dataclass(frozen=True)
class _Solution:
    T: dict[str, np.ndarray]
    chi2: float
    covariance: dict[str, np.ndarray]


def prior_covariance(e: CameraExtrinsics, floor_mm: float = 0.01,
                     floor_deg: float = 0.001) -> np.ndarray:
    """6x6 [rot, trans] covariance of a calibrated pose: its full marginal when the
    calibration kept one, else diagonal from its sigmas (each the root of a 3-axis trace, so
    up to sqrt(3) too wide per axis: never tighter than the calibration claimed); at least
    ``floor_mm`` / ``floor_deg`` per axis (the reference camera has no sigma)."""
    floor = np.r_[np.full(3, math.radians(floor_deg) ** 2), np.full(3, (floor_mm / 1e3) ** 2)]
    if e.covariance is not None and np.all(np.isfinite(e.covariance)):
        return np.asarray(e.covariance, dtype=float) + np.diag(floor)
    s_rot, s_mm = e.sigma_rotation_deg, e.sigma_translation_mm
    var = np.r_[np.full(3, math.radians(s_rot if math.isfinite(s_rot) else 0.0) ** 2),
                np.full(3, (s_mm if math.isfinite(s_mm) else 0.0) ** 2 / 1e6)]
    return np.diag(np.maximum(var, floor))


def _solve(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
           pairs: list[RelativePose], free: set[str]) -> _Solution:
    """Pose graph: a prior on every camera not in ``free``, every pair as a between factor;
    the free cameras start from a pair's measurement to a held camera."""
    names = sorted(T_prior)
    key = {c: i for i, c in enumerate(names)}
    graph = gtsam.NonlinearFactorGraph()
    for c in names:
        if c not in free:
            graph.add(gtsam.PriorFactorPose3(key[c], gtsam.Pose3(T_prior[c]),
                                             gtsam.noiseModel.Gaussian.Covariance(cov_prior[c])))
    for r in pairs:
        graph.add(gtsam.BetweenFactorPose3(key[r.cam_b], key[r.cam_a], gtsam.Pose3(r.T_b_a),
                                           gtsam.noiseModel.Gaussian.Information(r.information)))
    start = {c: T_prior[c] for c in names}
    for c in free:  # from a held neighbour's measurement (centimetres closer than the prior)
        for r in pairs:
            if r.cam_a == c and r.cam_b not in free:
                start[c] = T_prior[r.cam_b] @ r.T_b_a
                break
            if r.cam_b == c and r.cam_a not in free:
                start[c] = T_prior[r.cam_a] @ invert_transform(r.T_b_a)
                break
    values = gtsam.Values()
    for c in names:
        values.insert(key[c], gtsam.Pose3(start[c]))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    marginals = gtsam.Marginals(graph, result)
    T = {c: result.atPose3(key[c]).matrix() for c in names}
    cov = {c: marginals.marginalCovariance(key[c]) for c in names}
    return _Solution(T, 2.0 * graph.error(result), cov)


def _try_solve(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
               pairs: list[RelativePose], free: set[str]) -> _Solution | None:
    """:func:`_solve`, or None when the pairs leave a free camera undetermined (GTSAM's
    indeterminate system: e.g. one pair whose information lacks the direction an unknown
    depth scale explains)."""
    try:
        return _solve(T_prior, cov_prior, pairs, free)
    except RuntimeError:
        return None


def _components(names: list[str], pairs: list[RelativePose]) -> list[set[str]]:
    """The groups of cameras connected by pairs (scipy's connected components)."""
    index = {c: i for i, c in enumerate(names)}
    edges = np.array([[index[r.cam_a], index[r.cam_b]] for r in pairs], dtype=int).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                       shape=(len(names), len(names)))
    _, label = connected_components(graph, directed=False)
    return [{c for c, k in zip(names, label) if k == g} for g in np.unique(label)]


def _anchored(names: list[str], pairs: list[RelativePose], free: set[str]) -> bool:
    """Every connected group of cameras keeps at least one prior (else its pose is free)."""
    return all(group - free for group in _components(names, pairs))


def _camera_check(c: str, sol: _Solution, T_prior: dict[str, np.ndarray],
                  cov_prior: dict[str, np.ndarray], chi2: float, n_pairs: int,
                  status: Status, s2: float = 1.0) -> CameraCheck:
    deg, mm = transform_error(sol.T[c], T_prior[c])
    sigma_deg, sigma_mm = covariance_sigmas(s2 * sol.covariance[c] + cov_prior[c])
    return CameraCheck(
        c, status, moved_mm=mm, moved_deg=deg, sigma_mm=sigma_mm, sigma_deg=sigma_deg,
        chi2=chi2, n_pairs=n_pairs, T_ref_cam_now=sol.T[c],
        covariance_now=s2 * sol.covariance[c])


def variance_factor(sol: _Solution, n_pairs: int, n_free: int) -> float:
    """A-posteriori variance factor of a solve, at least 1: chi-square over its redundancy
    (6 per pair beyond the free cameras' 6). The pairs' sigmas come from the D435 noise model
    and miss what it leaves out (surfaces that slide along rails and floors, a noisy single
    frame); this scales them up by what the residuals show, as a bundle adjustment's
    sigma_0 does, so a few millimetres of pair error is not taken for a knocked camera."""
    dof = 6 * (n_pairs - n_free)
    return max(1.0, sol.chi2 / dof) if dof > 0 else 1.0


def locate_moved(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
                 pairs: list[RelativePose], tolerance: Tolerance = Tolerance(),
                 chi2_threshold: float = MOVED_CHI2) -> dict[str, CameraCheck]:
    """Which cameras moved, from the calibrated poses ``T_prior`` (camera -> T_ref_cam) with
    their covariances and the measured ``pairs``: greedily free the camera whose prior the
    pairs contradict most, while that is significant (the chi-square drop, over the variance
    factor of the solve without that prior, above ``chi2_threshold``) and its move exceeds
    ``tolerance``; then every camera's move with its own prior removed (the moved ones stay
    free), its covariance scaled by the final variance factor. A camera in no pair is
    ``unknown``. When another camera's release explains the pairs about as well (its drop
    within ``chi2_threshold`` of the chosen one's), the chosen camera's ``reason`` names it:
    the depth cannot tell which of them moved."""
    names = sorted(T_prior)
    n_pairs = {c: sum(c in (r.cam_a, r.cam_b) for r in pairs) for c in names}
    checkable = [c for c in names if n_pairs[c]]
    moved: list[str] = []
    ambiguous: dict[str, list[str]] = {}
    s2 = 1.0
    base = _try_solve(T_prior, cov_prior, pairs, set()) if pairs else None
    if base is not None:
        s2 = variance_factor(base, len(pairs), 0)
        while True:
            drops: dict[str, tuple[float, _Solution]] = {}
            for c in checkable:
                free = set(moved) | {c}
                if c in moved or not _anchored(names, pairs, free):
                    continue
                sol = _try_solve(T_prior, cov_prior, pairs, free)
                if sol is None:
                    continue
                drop = (base.chi2 - sol.chi2) / variance_factor(sol, len(pairs), len(free))
                drops[c] = (drop, sol)
            if not drops:
                break
            c = max(drops, key=lambda k: drops[k][0])
            drop, sol = drops[c]
            if drop <= chi2_threshold:
                break
            deg, mm = transform_error(sol.T[c], T_prior[c])
            if mm <= tolerance.mm and deg <= tolerance.deg:
                break
            # another camera whose release explains the pairs about as well: the depth cannot
            # tell which of them moved (e.g. two cameras that overlap only each other)
            rivals = sorted(k for k, (d, _) in drops.items()
                            if k != c and d > chi2_threshold and d >= drop - chi2_threshold)
            if rivals:
                ambiguous[c] = rivals
            moved.append(c)
            base = sol
            s2 = variance_factor(sol, len(pairs), len(moved))
    out: dict[str, CameraCheck] = {}
    for c in names:
        if not n_pairs[c]:
            out[c] = CameraCheck(c, "unknown", reason="no overlapping camera's depth fits its "
                                 "own (no accepted pair): cannot be checked")
            continue
        held = set(moved) - {c}
        if c in moved:
            with_prior = _try_solve(T_prior, cov_prior, pairs, held)
            sol = base
            status: Status = "moved"
        elif _anchored(names, pairs, held | {c}):
            with_prior = base
            sol = _try_solve(T_prior, cov_prior, pairs, held | {c})
            status = "in_place"
        else:  # its group has no other held camera: the move is relative to nothing
            out[c] = CameraCheck(c, "in_place", n_pairs=n_pairs[c], chi2=0.0,
                                 reason="the only held camera of its overlapping group")
            continue
        if sol is None or with_prior is None:
            out[c] = CameraCheck(c, "moved" if c in moved else "unknown", n_pairs=n_pairs[c],
                                 reason="its pairs leave its pose undetermined (e.g. one pair "
                                 "and an unknown depth scale): cannot be measured alone")
            continue
        out[c] = _camera_check(c, sol, T_prior, cov_prior,
                               max(with_prior.chi2 - sol.chi2, 0.0) / s2, n_pairs[c], status, s2)
        rivals = [k for k in ambiguous.get(c, []) if k not in moved]  # a moved one is no rival
        if rivals:
            out[c] = replace(out[c], reason=(
                f"or {', '.join(rivals)}: the depth cannot tell which moved (releasing "
                "either explains the pairs about as well; they overlap too few other cameras)"))
    return out


def check_config(config: DepthConfig | None) -> DepthConfig:
    """The depth settings of a check: every pair that fits is a measurement, also one that
    confirms the calibration (``min_improvement_chi2`` 0), and a knocked camera's pair may
    move far (``max_correction`` 0.5 m / 30 deg: the correction of ``T_b_a`` is the knock's
    turn times the baseline, 0.15 m for 5 deg across a 1.7 m ring, beyond calibrate's
    wrong-minimum guard; here the noise-model fit guards against wrong minima)."""
    return (config or DepthConfig()).model_copy(update={
        "min_improvement_chi2": 0.0,
        "max_correction_m": max((config or DepthConfig()).max_correction_m, 0.5),
        "max_correction_deg": max((config or DepthConfig()).max_correction_deg, 30.0)})


def _jobs(pairs: list[tuple[str, str]], T: dict[str, np.ndarray],
          unknown_scale: set[str]) -> list:
    return [(a, b, T[a], T[b], (a in unknown_scale, b in unknown_scale)) for a, b in pairs]


def check_rig(clouds: dict[str, CameraCloud], calib: Extrinsics,
              overlaps: list[tuple[str, str]], method: str = "colored-icp",
              config: DepthConfig | None = None, tolerance: Tolerance = Tolerance(),
              unknown_scale: set[str] = frozenset(), workers: int | None = None,
              tick=None, scheduler: str | None = None) -> CheckResult:
    """:func:`register_robust` for each overlapping ``(cam_a, cam_b)`` from the calibrated
    extrinsics (in a process pool of ``workers``, or on the Dask cluster of ``scheduler``),
    then :func:`locate_moved` on the pairs that fit (``accepted``; the check needs the
    measurements that confirm the calibration too, so ``min_improvement_chi2`` is 0). Cameras
    in ``unknown_scale`` have no depth-scale factor: their pairs leave out what a scale error
    explains. Cameras of ``calib`` without a cloud are ``unknown``."""
    from .refine import register_pairs

    config = check_config(config)
    t0 = time.perf_counter()
    T = {c: e.T_ref_cam for c, e in calib.cameras.items()}
    regs = register_pairs(clouds, _jobs(overlaps, T, set(unknown_scale)), method, config,
                          workers, tick, robust=True, scheduler=scheduler)
    t_reg = time.perf_counter() - t0
    pairs = [RelativePose(r.cam_a, r.cam_b, r.T_b_a, r.information) for r in regs if r.accepted]
    held = {c: T[c] for c in clouds if c in T}
    cov = {c: prior_covariance(calib.cameras[c]) for c in held}
    cams = locate_moved(held, cov, pairs, tolerance)
    for c in calib.cameras:
        if c not in cams:
            cams[c] = CameraCheck(c, "unknown", reason="no depth cloud (no depth frames or "
                                  "none usable)")
    return CheckResult(cams, [r.to_dict() for r in regs], tolerance,
                       {"registration": t_reg, "total": time.perf_counter() - t0})


@dataclass(frozen=True)
class CheckRun:
    """A check with what it was measured from (the clouds and the overlapping pairs), so a
    fix reuses them."""

    result: CheckResult
    clouds: dict[str, CameraCloud]
    overlaps: list[tuple[str, str]]
    scale_source: dict[str, str]  # camera -> "given" (the calibration's factor) / "unknown"


def check_dataset(dataset: FolderDataset, calib: Extrinsics,
                  depth_scales: dict[str, float] | None = None, method: str = "colored-icp",
                  config: DepthConfig | None = None, tolerance: Tolerance = Tolerance(),
                  workers: int | None = None, progress: Progress | None = None,
                  scheduler: str | None = None) -> CheckRun:
    """Check ``dataset`` (one or a few frame sets of the rig as it is now; no board needed,
    anything in view is scene) against ``calib``: a static cloud per calibrated camera with
    depth (its ``depth_scales`` factor from the calibration), the pairs that overlap under
    the calibration (with a wider overlap search, 0.15 m, than calibrate's: a knocked camera's
    cloud lies centimetres off), then :func:`check_rig`."""
    config = config or DepthConfig()
    scales = depth_scales or {}
    cams = [c for c in dataset.cameras if c in calib.cameras and dataset.has_depth(c)]
    from .refine import static_clouds

    clouds, skipped = static_clouds(
        dataset, [(c, calib.T_ref_cam(c), scales.get(c, 1.0)) for c in cams], {}, None, config,
        workers, start(progress, "static clouds", len(cams)), scheduler)
    T = {c: calib.T_ref_cam(c) for c in clouds}
    wide = config.model_copy(update={"overlap_distance_m": max(config.overlap_distance_m,
                                                               0.15)})
    overlaps = [(o.cam_a, o.cam_b) for o in find_overlapping_pairs(
        clouds, T, {c: dataset.rig.cameras[c] for c in clouds}, wide)]
    tick = start(progress, f"registering pairs ({method})", len(overlaps))
    unknown = {c for c in clouds if c not in scales}
    result = check_rig(clouds, calib, overlaps, method, config, tolerance, unknown, workers,
                       tick, scheduler)
    for c, why in skipped.items():
        result.cameras[c] = CameraCheck(c, "unknown", reason=f"no depth cloud: {why}")
    return CheckRun(result, clouds, overlaps,
                    {c: "unknown" if c in unknown else "given" for c in clouds})


# --------------------------------------------------------------------------- fix
def _sigmas(c: str, T: np.ndarray, C: np.ndarray) -> CameraExtrinsics:
    return CameraExtrinsics(c, T, *covariance_sigmas(C), C)


def reexpress(cams: dict[str, CameraExtrinsics], ref: str,
              covariance: dict[str, np.ndarray]) -> dict[str, CameraExtrinsics]:
    """The rig in the frame of its reference camera as it is now (``cams[ref]`` is where it
    moved to, in the old frame): ``T_new_c = inv(T_ref_now) @ T_c``. Each camera's covariance
    (body frame, [rot, trans]) gains the reference's: a right perturbation ``xi`` of
    ``T_ref_now`` is ``-Ad(inv(T_new_c)) xi`` of ``T_new_c``; ``covariance`` gives the other
    cameras' own (the calibration's for the cameras in place)."""
    T_now = cams[ref].T_ref_cam
    C_ref = cams[ref].covariance
    if C_ref is None or not np.all(np.isfinite(C_ref)):
        C_ref = np.full((6, 6), np.nan)
    T_new_old = invert_transform(T_now)
    out = {}
    for c, e in cams.items():
        if c == ref:
            out[c] = CameraExtrinsics(c, np.eye(4), 0.0, 0.0)  # exact by definition
            continue
        T = T_new_old @ e.T_ref_cam
        Ad = gtsam.Pose3(invert_transform(T)).AdjointMap()
        own = covariance.get(c, e.covariance)
        own = own if own is not None else np.zeros((6, 6))
        out[c] = _sigmas(c, T, Ad @ C_ref @ Ad.T + own)
    return out


def fix_moved(clouds: dict[str, CameraCloud], calib: Extrinsics, check: CheckResult,
              overlaps: list[tuple[str, str]], method: str = "colored-icp",
              config: DepthConfig | None = None, max_passes: int = 3,
              unknown_scale: set[str] = frozenset(), workers: int | None = None,
              scheduler: str | None = None,
              ) -> tuple[Extrinsics, list[dict[str, Any]]]:
    """Re-register the moved cameras of ``check`` against the others and solve for them with
    the others held at their calibration (priors with its sigmas); only pairs with a moved
    camera count. Each moved camera starts from the check's estimate (its pairs' ICP, after
    the global alignment where needed) and is re-registered from each new estimate, up to
    ``max_passes`` times, until it moves less than 0.1 mm / 0.01 deg: ICP crops each cloud to
    the other camera's view under the start, so a start centimetres off leaves points out.
    Covariances are the graph marginals times its variance factor. Returns the extrinsics (the
    cameras in place keep their calibration exactly; if the reference moved, everything is
    re-expressed in its new frame) and the last pass's pairs."""
    from .refine import register_pairs

    config = check_config(config)
    moved = set(check.moved)
    if not moved:
        return calib, []
    T_now = {c: e.T_ref_cam for c, e in calib.cameras.items()}
    cov_now: dict[str, np.ndarray | None] = {}
    for c in moved:
        T_now[c] = check.cameras[c].T_ref_cam_now
        cov_now[c] = check.cameras[c].covariance_now
    jobs = [(a, b) for a, b in overlaps
            if (a in moved or b in moved) and a in clouds and b in clouds]
    held = [c for c in clouds if c in T_now]
    cov = {c: prior_covariance(calib.cameras[c]) for c in held}
    regs: list[PairRegistration] = []
    for _ in range(max_passes):
        regs = register_pairs(clouds, _jobs(jobs, T_now, set(unknown_scale)), method, config,
                              workers, robust=True, scheduler=scheduler)
        pairs = [RelativePose(r.cam_a, r.cam_b, r.T_b_a, r.information)
                 for r in regs if r.accepted]
        free = {c for c in moved if any(c in (r.cam_a, r.cam_b) for r in pairs)}
        if not free or not _anchored(sorted(held), pairs, free):
            break
        sol = _try_solve({c: T_now[c] for c in held}, cov, pairs, free)
        if sol is None:
            break
        s2 = variance_factor(sol, len(pairs), len(free))
        steps = [transform_error(sol.T[c], T_now[c]) for c in free]  # (deg, mm) each
        for c in free:
            T_now[c], cov_now[c] = sol.T[c], s2 * sol.covariance[c]
        if all(mm < 0.1 and deg < 0.01 for deg, mm in steps):
            break
    cams = dict(calib.cameras)
    for c in moved:
        C = cov_now.get(c)
        cams[c] = _sigmas(c, T_now[c], C if C is not None else np.full((6, 6), np.nan))
    ref = calib.reference
    if ref in moved:
        cams = reexpress(cams, ref, {c: cov[c] for c in cov if c not in moved})
    out = Extrinsics(ref, cams, dict(calib.unconnected))
    return out, [{**r.to_dict(), "re_registered_for": sorted({r.cam_a, r.cam_b} & moved)}
                 for r in regs]
