"""Pairs of cameras: overlap, pairwise ICP with an information, robust registration.

    find_overlapping_pairs  which cameras see common surfaces under the current extrinsics
    register_pair           colored ICP (Park et al. 2017) or kiss-icp, with a 6x6 information
    register_robust         register_pair, then a wider basin, then a global alignment
    overlap_error           point-to-plane distances between two cameras' clouds (report maps)
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, replace
from itertools import combinations
from typing import Any

import numpy as np
import open3d as o3d
from kiss_icp.mapping import VoxelHashMap
from kiss_icp.registration import Registration
from kiss_icp.voxelization import voxel_down_sample
from scipy.spatial import cKDTree

from ..core.camera import CameraIntrinsics
from ..core.config import REGISTRATION_METHODS, DepthConfig, RegistrationMethod
from ..core.geometry import covariance_sigmas, invert_transform, transform_error, transform_points
from .clouds import (
    CameraCloud,
    NormalField,
    VoxelLevel,
    in_view,
    voxel_level,
    voxel_mean,
    voxel_pick,
    with_normals,
)
from .information import (
    INFORMATION_FRAME,
    Matches,
    color_gradients,
    conditioning,
    disparity_covariance,
    nearest_matches,
    noise_model_information,
    normalised_rms,
    rmse_mm,
    tangent_error,
    whitened_rows,
    with_covariance,
)

# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class PairOverlap:
    """Fraction of each camera's points that the other camera also sees (near its surface)."""

    cam_a: str
    cam_b: str
    overlap_fraction: float  # min(fraction_ab, fraction_ba)
    n_points: int  # overlapping points (of the overlap-voxel clouds), min over both directions
    fraction_ab: float  # of a's points, the fraction near b's cloud
    fraction_ba: float

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


# Why a pair is rejected, one kind per test (``PairRegistration.rejected_by``; report.json
# ``pairs[].rejected_by``, schema 1.18), so that readers act on the kind, not the wording:
REJECTION_KINDS = (
    "correspondences",  # too few correspondences at the finest level
    "fitness",  # too small a fraction of a's points near b's surface
    "rmse",  # point-to-plane RMSE beyond the limit
    "residuals",  # residuals beyond the depth noise model
    "conditioning",  # a direction the common surfaces leave unconstrained
    "patches",  # too few surface patches to estimate the pair's uncertainty
    "correction",  # moved beyond the limit from the initial guess
    "not_significant",  # fits, but its move is within its own uncertainty (``agrees``)
    "information",  # the information matrix is not finite
    "failed",  # the registration could not run or failed (its reason says how)
    "beyond_extrinsics",  # moved beyond the board's uncertainty and the pair's
    "fix_reach",  # refine --fix-others: moved beyond a fix's reach from check's estimate
    "not_used",  # accepted, then left out of the joint solve (the stage's fallback)
)


@dataclass(frozen=True)
class PairRegistration:
    """Result of registering camera a's static cloud to camera b's.

    ``T_b_a`` (4x4, metres) maps points of camera a into camera b. ``information`` (6x6) is the
    inverse of the cluster-robust covariance of ``T_b_a`` at the finest level
    (:func:`noise_model_information`: point-to-plane residuals over their noise-model sigma,
    plus the photometric term for colored ICP, grouped by surface patch), in GTSAM order
    [rotation (rad), translation (m)] for a right perturbation (see
    ``information_frame``): for the joint graph, use
    ``BetweenFactorPose3(key(T_ref_b), key(T_ref_a), Pose3(T_b_a),
    noiseModel.Gaussian.Information(information))``. ``conditioning`` is the smallest over the
    largest eigenvalue of that information normalised after Gelfand et al. (2003)."""

    cam_a: str
    cam_b: str
    method: str
    T_b_a: np.ndarray
    T_b_a_initial: np.ndarray
    information: np.ndarray
    information_frame: str
    fitness: float
    inlier_rmse_mm: float
    rmse_before_mm: float  # point-to-plane, over correspondences within eval_distance_m
    rmse_after_mm: float
    conditioning: float
    n_correspondences: int
    correction_deg: float  # rotation between T_b_a_initial and T_b_a
    correction_mm: float
    accepted: bool
    reason: str | None
    time_s: float
    normalised_rms: float = float("nan")  # RMS(point-to-plane residual / model sigma)
    improvement_chi2: float = 0.0  # move^T information move: the Wald statistic of the move
    n_patches: int = 0  # surface patches of the sandwich covariance
    start: str = "given"  # ICP started from the given extrinsics, or "global" (FPFH + RANSAC)
    # registered cleanly, and rejected only because ICP's move is within the pair's own
    # uncertainty: the depth agrees with the extrinsics it started from (a confirmation)
    agrees: bool = False
    rejected_by: tuple[str, ...] = ()  # the REJECTION_KINDS of ``reason``'s clauses, in order
    # what the clouds' uncorrected disparity offsets add to the covariance (6x6, same frame;
    # None: none): left out of ``information`` and the gates, which judge the registration by
    # its own noise; :meth:`solve_information` adds it for the joint solve
    disparity_covariance: np.ndarray | None = None

    def solve_information(self) -> np.ndarray:
        """``information`` with :attr:`disparity_covariance` added to its covariance: the
        weight the pair has in a joint solve."""
        if self.disparity_covariance is None:
            return self.information
        return with_covariance(self.information, self.disparity_covariance)

    @property
    def covariance(self) -> np.ndarray:
        """6x6 covariance in the same frame and order as ``information`` (pseudo-inverse)."""
        return np.linalg.pinv(self.information)

    @property
    def sigma_rotation_deg(self) -> float:
        """1-sigma rotation (root of the trace of the rotation block: all three axes)."""
        return covariance_sigmas(self.covariance)[0]

    @property
    def sigma_translation_mm(self) -> float:
        """1-sigma translation (root of the trace of the translation block)."""
        return covariance_sigmas(self.covariance)[1]

    def to_dict(self) -> dict[str, Any]:
        return {
            "cam_a": self.cam_a,
            "cam_b": self.cam_b,
            "method": self.method,
            "T_b_a": np.asarray(self.T_b_a).tolist(),
            "information": np.asarray(self.information).tolist(),
            "information_frame": self.information_frame,
            "fitness": self.fitness,
            "inlier_rmse_mm": self.inlier_rmse_mm,
            "rmse_before_mm": self.rmse_before_mm,
            "rmse_after_mm": self.rmse_after_mm,
            "conditioning": self.conditioning,
            "n_correspondences": self.n_correspondences,
            "correction_deg": self.correction_deg,
            "correction_mm": self.correction_mm,
            "sigma_rotation_deg": self.sigma_rotation_deg,
            "sigma_translation_mm": self.sigma_translation_mm,
            "accepted": self.accepted,
            "reason": self.reason,
            "time_s": self.time_s,
            "normalised_rms": self.normalised_rms,
            "improvement_chi2": self.improvement_chi2,
            "n_patches": self.n_patches,
            "start": self.start,
            "agrees": self.agrees,
            "rejected_by": list(self.rejected_by),
        }


@dataclass(frozen=True)
class DepthPair:
    """One camera pair as the depth stage, ``check`` and ``refine`` report it: its
    registration, the overlap it was found by (None where the pairs were given), its
    point-to-plane RMSE at the final extrinsics once measured (``finished``;
    :func:`rgbd_calib.depth.stage.finish_pairs`) and, for ``refine --fix``, the moved
    cameras it was registered again for. :meth:`to_dict` is its report-ready entry
    (report.json ``pairs[]``, check.json, refine_report.json)."""

    registration: PairRegistration
    overlap: PairOverlap | None = None
    rmse_final_mm: float | None = None
    finished: bool = False
    re_registered_for: tuple[str, ...] | None = None

    @property
    def cam_a(self) -> str:
        return self.registration.cam_a

    @property
    def cam_b(self) -> str:
        return self.registration.cam_b

    @property
    def accepted(self) -> bool:
        return self.registration.accepted

    @property
    def agrees(self) -> bool:
        return self.registration.agrees

    @property
    def reason(self) -> str | None:
        return self.registration.reason

    def unused(self, why: str) -> DepthPair:
        """This pair, when accepted, marked left out of the solve (``not_used``)."""
        if not self.accepted:
            return self
        reg = replace(self.registration, accepted=False, reason=f"not used: {why}",
                      rejected_by=("not_used",))
        return replace(self, registration=reg)

    def to_dict(self) -> dict[str, Any]:
        out = {**(self.overlap.to_dict() if self.overlap is not None else {}),
               **self.registration.to_dict()}
        if self.finished:
            out["rmse_final_mm"] = self.rmse_final_mm
        if self.re_registered_for is not None:
            out["re_registered_for"] = list(self.re_registered_for)
        return out


def pair_dicts(pairs: list[DepthPair]) -> list[dict[str, Any]]:
    """The report-ready entries of ``pairs`` (:meth:`DepthPair.to_dict`)."""
    return [p.to_dict() for p in pairs]


# --------------------------------------------------------------------------- overlap
def _overlap_fraction(points_a: np.ndarray, T_b_a: np.ndarray, intr_b: CameraIntrinsics,
                      tree_b: cKDTree, distance: float) -> tuple[float, int]:
    if points_a.shape[0] == 0:
        return 0.0, 0
    p_b = transform_points(T_b_a, points_a)
    view = in_view(intr_b, p_b, 0.0, 0.05, np.inf)
    if not np.any(view):
        return 0.0, 0
    d, _ = tree_b.query(p_b[view], distance_upper_bound=distance, workers=-1)
    near = int(np.count_nonzero(np.isfinite(d)))
    return near / points_a.shape[0], near


# threads of one registration: all (0 / Open3D's default) when it runs alone; one in a worker
# process of a pool or Dask cluster, where the processes already use the cores. The same count
# everywhere also keeps the result bit-identical on any worker: parallel reductions sum in an
# order that depends on the thread count (~1e-15 apart)
_THREADS: dict[str, int] = {"kiss": 0}


def limit_registration_threads(threads: int) -> None:
    """Threads Open3D and kiss-icp may use in each registration of this process (>= 1)."""
    o3d.utility.set_max_threads(threads)
    _THREADS["kiss"] = threads


def find_overlapping_pairs(
    clouds: dict[str, CameraCloud],
    T_ref_cam: dict[str, np.ndarray],
    intrinsics: dict[str, CameraIntrinsics] | None = None,
    config: DepthConfig | None = None,
) -> list[PairOverlap]:
    """Pairs of cameras whose static clouds overlap under the current extrinsics, best first.

    For a pair (a, b), a's points (one per ``overlap_voxel_m`` voxel) are moved into b with
    ``T_b_a = inv(T_ref_b) @ T_ref_a``; those inside b's image that have a point of b's cloud
    within ``overlap_distance_m`` overlap. The pair's ``overlap_fraction`` is the smaller of
    the two directions' fractions, and pairs below ``min_overlap`` are left out. Facing
    cameras that see a common floor or object overlap like neighbours do."""
    config = config or DepthConfig()
    names = [c for c in clouds if c in T_ref_cam]
    intrinsics = intrinsics or {c: clouds[c].intrinsics for c in names}
    voxel = config.registration.overlap_voxel_m
    sample = {c: clouds[c].points[voxel_pick(clouds[c].points, voxel)].astype(float)
              for c in names}
    trees = {c: cKDTree(sample[c]) for c in names}
    pairs = []
    for a, b in combinations(names, 2):
        T_b_a = invert_transform(T_ref_cam[b]) @ T_ref_cam[a]
        f_ab, n_ab = _overlap_fraction(sample[a], T_b_a, intrinsics[b], trees[b],
                                       config.registration.overlap_distance_m)
        f_ba, n_ba = _overlap_fraction(sample[b], invert_transform(T_b_a), intrinsics[a],
                                       trees[a], config.registration.overlap_distance_m)
        frac = min(f_ab, f_ba)
        if frac >= config.registration.min_overlap and min(n_ab, n_ba) > 0:
            pairs.append(PairOverlap(a, b, frac, min(n_ab, n_ba), f_ab, f_ba))
    return sorted(pairs, key=lambda p: -p.overlap_fraction)


# --------------------------------------------------------------------------- ICP levels
def _faces_camera(points: np.ndarray, normals: NormalField, T_other_cam: np.ndarray,
                  max_incidence_deg: float) -> np.ndarray:
    """Which points (camera frame, normals towards their camera) the other camera, at
    ``T_other_cam``, sees from the front at an incidence below ``max_incidence_deg``."""
    p = points.astype(float)
    n_other = normals(p) @ T_other_cam[:3, :3].T
    p_other = transform_points(T_other_cam, p)
    cos_inc = -np.einsum("ij,ij->i", n_other, p_other) / np.linalg.norm(p_other, axis=1)
    return cos_inc > math.cos(math.radians(max_incidence_deg))


def _legacy_cloud(level: VoxelLevel) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(level.points))
    pcd.colors = o3d.utility.Vector3dVector(level.colors)
    pcd.normals = o3d.utility.Vector3dVector(level.normals)
    return pcd


def _tensor_cloud(level: VoxelLevel) -> o3d.t.geometry.PointCloud:
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(level.points.astype(np.float32)))
    pcd.point.colors = o3d.core.Tensor(level.colors.astype(np.float32))
    pcd.point.normals = o3d.core.Tensor(level.normals.astype(np.float32))
    return pcd


def _colored_icp_level(src: VoxelLevel, tgt: VoxelLevel, T: np.ndarray, distance: float,
                       iterations: int, config: DepthConfig) -> np.ndarray:
    """One level of colored ICP (Park, Zhou, Koltun: "Colored Point Cloud Registration
    Revisited", ICCV 2017): the joint objective ``(1 - lambda) E_C + lambda E_G`` of a
    photometric term on the target's tangent planes and the point-to-plane term, with
    ``lambda = lambda_geometric``. Returns ``T_target_source``."""
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        return _colored_icp_call(src, tgt, T, distance, iterations, config)


def _colored_icp_call(src: VoxelLevel, tgt: VoxelLevel, T: np.ndarray, distance: float,
                      iterations: int, config: DepthConfig) -> np.ndarray:
    if config.registration.icp_backend == "tensor":
        reg = o3d.t.pipelines.registration
        result = reg.icp(
            _tensor_cloud(src), _tensor_cloud(tgt), distance,
            o3d.core.Tensor(T),
            reg.TransformationEstimationForColoredICP(config.registration.lambda_geometric),
            reg.ICPConvergenceCriteria(1e-6, 1e-6, iterations),
        )
        return result.transformation.numpy().astype(float)
    reg = o3d.pipelines.registration
    result = reg.registration_colored_icp(
        _legacy_cloud(src), _legacy_cloud(tgt), distance, T,
        reg.TransformationEstimationForColoredICP(lambda_geometric=config.registration.lambda_geometric),
        reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6,
                                   max_iteration=iterations),
    )
    return np.asarray(result.transformation, dtype=float)


def _geometric_icp_level(src: VoxelLevel, tgt: VoxelLevel, T: np.ndarray, voxel: float,
                         config: DepthConfig, registration: Registration) -> np.ndarray:
    """One level of kiss-icp's robust point-to-point ICP (Vizzo et al., "KISS-ICP", RA-L 2023):
    the target in a voxel hash map of this level's size (its neighbour search reaches adjacent
    voxels only, hence the coarse-to-fine levels), the source thinned to 1.5 voxels as
    kiss-icp's own pipeline does."""
    voxel_map = VoxelHashMap(voxel_size=voxel, max_distance=1e6,
                             max_points_per_voxel=config.registration.kiss_max_points_per_voxel)
    voxel_map.add_points(np.ascontiguousarray(tgt.points, dtype=np.float64))
    source = voxel_down_sample(np.ascontiguousarray(src.points, dtype=np.float64), 1.5 * voxel)
    return np.asarray(
        registration.align_points_to_map(
            points=source, voxel_map=voxel_map, initial_guess=T,
            max_correspondance_distance=config.registration.max_correspondence_factor * voxel,
            kernel=config.registration.kiss_kernel_factor * voxel,
        ),
        dtype=float,
    )


# --------------------------------------------------------------------------- pair registration
def _noise_name(*clouds: CameraCloud) -> str:
    """The noise models of clouds, for a message: 'D435', 'Kinect v1' or 'D435 / Kinect v1'."""
    names = {"d435": "D435", "kinect-v1": "Kinect v1"}
    return " / ".join(dict.fromkeys(names.get(c.intrinsics.depth_noise, c.intrinsics.depth_noise)
                                    for c in clouds))


def _common_surfaces(cloud_a: CameraCloud, cloud_b: CameraCloud, T_b_a0: np.ndarray,
                     config: DepthConfig):
    """Points of each cloud the other camera can see (in view, low noise, facing it), with
    their normal fields; the selection is made once, at the initial ``T_b_a0``."""
    T_a_b0 = invert_transform(T_b_a0)
    reg = config.registration
    # 1. what each camera can see of the other's cloud
    keep_a = in_view(cloud_b.intrinsics, transform_points(T_b_a0, cloud_a.points),
                     reg.crop_margin_px, 0.05, np.inf)
    keep_b = in_view(cloud_a.intrinsics, transform_points(T_a_b0, cloud_b.points),
                     reg.crop_margin_px, 0.05, np.inf)
    keep_a &= cloud_a.sigma_z <= reg.icp_max_sigma_z_m
    keep_b &= cloud_b.sigma_z <= reg.icp_max_sigma_z_m
    normals_a = NormalField(cloud_a.points[keep_a].astype(float), reg.normal_voxel_m,
                            reg.normal_radius_m)
    normals_b = NormalField(cloud_b.points[keep_b].astype(float), reg.normal_voxel_m,
                            reg.normal_radius_m)
    # surfaces the other camera sees from behind (the far side of a rail, a post) or at a
    # grazing angle are not common to both views: drop them
    keep_a[keep_a] &= _faces_camera(cloud_a.points[keep_a], normals_a, T_b_a0,
                                    reg.max_incidence_deg)
    keep_b[keep_b] &= _faces_camera(cloud_b.points[keep_b], normals_b, T_a_b0,
                                    reg.max_incidence_deg)
    return keep_a, keep_b, normals_a, normals_b


def pair_rmse_mm(cloud_a: CameraCloud, cloud_b: CameraCloud, T_ref_a_initial: np.ndarray,
                 T_ref_b_initial: np.ndarray, T_ref_a: np.ndarray, T_ref_b: np.ndarray,
                 config: DepthConfig | None = None) -> float:
    """Point-to-plane RMSE (mm) of a pair at extrinsics ``T_ref_a``, ``T_ref_b``, measured
    exactly as :func:`register_pair` reports ``rmse_before_mm`` / ``rmse_after_mm`` (same
    common surfaces, chosen at the initial extrinsics; finest voxel; eval distance)."""
    config = config or DepthConfig()
    T_b_a0 = invert_transform(T_ref_b_initial) @ np.asarray(T_ref_a_initial, dtype=float)
    keep_a, keep_b, normals_a, normals_b = _common_surfaces(cloud_a, cloud_b, T_b_a0, config)
    voxel = config.registration.voxel_schedule_m[-1]
    src = voxel_level(cloud_a, keep_a, voxel, normals_a)
    tgt = voxel_level(cloud_b, keep_b, voxel, normals_b)
    if src.points.shape[0] == 0 or tgt.points.shape[0] < 3:
        return float("nan")
    T_b_a = invert_transform(T_ref_b) @ np.asarray(T_ref_a, dtype=float)
    return rmse_mm(nearest_matches(src, tgt, cKDTree(tgt.points), T_b_a,
                                   config.registration.eval_distance_m))


@dataclass(frozen=True)
class _Fit:
    """How a registration fits at the finest level (the numbers :class:`PairRegistration`
    reports; see there)."""

    n_correspondences: int
    fitness: float
    inlier_rmse_mm: float
    rmse_before_mm: float
    rmse_after_mm: float
    normalised_rms: float
    conditioning: float
    information: np.ndarray
    n_patches: int
    correction_deg: float
    correction_mm: float
    improvement_chi2: float
    disparity_covariance: np.ndarray | None = None


def register_pair(
    cloud_a: CameraCloud,
    cloud_b: CameraCloud,
    T_ref_a: np.ndarray,
    T_ref_b: np.ndarray,
    method: RegistrationMethod = "colored-icp",
    config: DepthConfig | None = None,
    free_scale: tuple[bool, bool] = (False, False),
) -> PairRegistration:
    """Register camera a's static cloud to camera b's, starting from the current extrinsics
    ``T_ref_a``, ``T_ref_b`` (4x4, metres); returns the measured ``T_b_a`` with its
    information (see :class:`PairRegistration`).

    1. crop each cloud to the other camera's view under the initial ``T_b_a``, to surfaces
       that face the other camera and to points with depth sigma below
       ``icp_max_sigma_z_m``;
    2. coarse to fine over ``voxel_schedule_m``: voxel means with normals (estimated once
       within ``normal_radius_m``), then one ICP level ("colored-icp": Open3D colored ICP,
       Park et al. 2017; "geometric": kiss-icp robust point-to-point);
    3. at the finest level: correspondences, fitness, RMSE, the residuals against the depth
       noise model, the information (:func:`noise_model_information`) and its conditioning;
       accept only a pair that fits the noise model and moved significantly (Wald test under
       its own information) from the initial ``T_b_a``, else reject with a reason.
    """
    config = config or DepthConfig()
    if method not in REGISTRATION_METHODS:
        raise ValueError(f"unknown registration method {method!r}; use "
                         f"{' or '.join(map(repr, REGISTRATION_METHODS))}")
    t_start = time.perf_counter()
    T_b_a0 = invert_transform(T_ref_b) @ np.asarray(T_ref_a, dtype=float)
    # 1. the surfaces both cameras see
    keep_a, keep_b, normals_a, normals_b = _common_surfaces(cloud_a, cloud_b, T_b_a0, config)
    # 2. coarse to fine
    T, (src, tgt), failure = _coarse_to_fine(cloud_a, cloud_b, (keep_a, keep_b),
                                             (normals_a, normals_b), T_b_a0, method, config)
    if failure is not None:
        return failed_registration(cloud_a.camera, cloud_b.camera, method, T_b_a0, failure,
                                   t_start)
    # 3. quality at the finest level, and the verdict
    fit = _finest_fit(src, tgt, T, T_b_a0, (cloud_a, cloud_b), method, config, free_scale)
    reasons, agrees = _verdict(fit, (cloud_a, cloud_b), config, free_scale)
    return PairRegistration(
        cam_a=cloud_a.camera,
        cam_b=cloud_b.camera,
        method=method,
        T_b_a=T,
        T_b_a_initial=T_b_a0,
        information=fit.information,
        information_frame=INFORMATION_FRAME,
        fitness=float(fit.fitness),
        inlier_rmse_mm=fit.inlier_rmse_mm,
        rmse_before_mm=fit.rmse_before_mm,
        rmse_after_mm=fit.rmse_after_mm,
        conditioning=fit.conditioning,
        n_correspondences=fit.n_correspondences,
        correction_deg=fit.correction_deg,
        correction_mm=fit.correction_mm,
        accepted=not reasons,
        reason="; ".join(text for _, text in reasons) or None,
        time_s=time.perf_counter() - t_start,
        disparity_covariance=fit.disparity_covariance,
        normalised_rms=fit.normalised_rms,
        improvement_chi2=fit.improvement_chi2,
        n_patches=fit.n_patches,
        agrees=bool(agrees),
        rejected_by=tuple(kind for kind, _ in reasons),
    )


def _coarse_to_fine(cloud_a: CameraCloud, cloud_b: CameraCloud,
                    keep: tuple[np.ndarray, np.ndarray], normals: tuple[NormalField, NormalField],
                    T_b_a0: np.ndarray, method: str, config: DepthConfig,
                    ) -> tuple[np.ndarray, tuple[VoxelLevel, VoxelLevel], str | None]:
    """Step 2 of :func:`register_pair`: one ICP level per ``voxel_schedule_m`` voxel, from
    ``T_b_a0``; ``(T_b_a, (src, tgt), failure)`` with the finest level's clouds and why a level
    failed or diverged (None when none did)."""
    T = T_b_a0.copy()
    finest: tuple[VoxelLevel, VoxelLevel] | None = None
    reg = config.registration
    kiss = Registration(max_num_iterations=reg.kiss_max_iterations,
                        convergence_criterion=1e-5, max_num_threads=_THREADS["kiss"])
    for voxel, iterations in zip(reg.voxel_schedule_m, reg.iterations):
        src = voxel_level(cloud_a, keep[0], voxel, normals[0])
        tgt = voxel_level(cloud_b, keep[1], voxel, normals[1])
        finest = (src, tgt)
        if src.points.shape[0] < 10 or tgt.points.shape[0] < 10:
            break
        distance = reg.max_correspondence_factor * voxel
        try:
            if method == "colored-icp":
                T = _colored_icp_level(src, tgt, T, distance, iterations, config)
            else:
                T = _geometric_icp_level(src, tgt, T, voxel, config, kiss)
        except ICP_ERRORS as exc:  # e.g. Open3D: "No correspondences found between ..."
            return T, finest, (f"{method} failed at voxel {voxel * 1000:.0f} mm: "
                               f"{one_line_error(exc)}")
        if not np.all(np.isfinite(T)):
            return T, finest, (f"{method} diverged at voxel {voxel * 1000:.0f} mm "
                               "(non-finite transform)")
    assert finest is not None
    return T, finest, None


def _finest_fit(src: VoxelLevel, tgt: VoxelLevel, T: np.ndarray, T_b_a0: np.ndarray,
                clouds: tuple[CameraCloud, CameraCloud], method: str, config: DepthConfig,
                free_scale: tuple[bool, bool]) -> _Fit:
    """Step 3 of :func:`register_pair`: correspondences of the finest level at ``T`` (and at
    ``T_b_a0`` for the RMSE before), their fit and the information of ``T``."""
    cloud_a, cloud_b = clouds
    reg = config.registration
    fine_distance = reg.max_correspondence_factor * reg.voxel_schedule_m[-1]
    if src.points.shape[0] > 0 and tgt.points.shape[0] >= 3:
        tree = cKDTree(tgt.points)
        final = nearest_matches(src, tgt, tree, T, fine_distance)
        before = nearest_matches(src, tgt, tree, T_b_a0, config.registration.eval_distance_m)
        after = nearest_matches(src, tgt, tree, T, config.registration.eval_distance_m)
    else:
        empty = np.zeros((0, 3))
        none = np.zeros(0, dtype=int)
        final = before = after = Matches(empty, empty, empty, np.zeros(0), np.ones(0),
                                         np.zeros(0), none, none)
    n_corr = int(final.residual.size)
    colour = None
    if method == "colored-icp" and config.registration.lambda_geometric < 1.0 and n_corr >= 7:
        colour = (src, tgt, color_gradients(tgt.points, tgt.normals, tgt.colors,
                                            at=final.tgt_index))
    rows = whitened_rows(final, T, config.uncertainty.information_patch_m, colour, free_scale,
                         ((cloud_a.intrinsics, cloud_a.intrinsics_variance),
                          (cloud_b.intrinsics, cloud_b.intrinsics_variance)),
                         (cloud_a.disparity, cloud_b.disparity))
    # the noise model's Gauss-Newton information says which directions the overlap
    # constrains (conditioning); the sandwich over patches says how well (information)
    cond = conditioning(rows.J[:, :6].T @ rows.J[:, :6], final.src) if n_corr else 0.0
    information = noise_model_information(rows)
    fitness = n_corr / src.points.shape[0] if src.points.shape[0] else 0.0
    inlier_rmse_mm = (float(1000.0 * np.sqrt(np.mean(final.distance**2))) if n_corr
                      else float("nan"))
    corr_deg, corr_mm = transform_error(T, T_b_a0)
    # Wald statistic of the move: ~ chi^2(6) if the initial T_b_a were already right
    move = tangent_error(T, T_b_a0)
    improvement = float(move @ information @ move)
    return _Fit(n_corr, fitness, inlier_rmse_mm, rmse_mm(before), rmse_mm(after),
                normalised_rms(final), cond, information, rows.n_patches, corr_deg, corr_mm,
                improvement, disparity_covariance(rows) if n_corr else None)


def _verdict(fit: _Fit, clouds: tuple[CameraCloud, CameraCloud], config: DepthConfig,
             free_scale: tuple[bool, bool]) -> tuple[list[tuple[str, str]], bool]:
    """Why a pair is rejected, as ``(kind, sentence)`` (:data:`REJECTION_KINDS`; empty:
    accepted), and whether it agrees with the extrinsics it started from (it fits, and only
    its move is not significant)."""
    n_corr, fitness, rmse_after = fit.n_correspondences, fit.fitness, fit.rmse_after_mm
    noise_rms, cond, improvement = fit.normalised_rms, fit.conditioning, fit.improvement_chi2
    corr_deg, corr_mm = fit.correction_deg, fit.correction_mm
    reasons = []
    gate = config.acceptance
    if n_corr < gate.min_correspondences:
        reasons.append(("correspondences",
                        f"{n_corr} correspondences < {gate.min_correspondences}"))
    if fitness < gate.min_fitness:
        reasons.append(("fitness", f"fitness {fitness:.2f} < {gate.min_fitness}"))
    if not rmse_after <= gate.max_rmse_mm:
        reasons.append(("rmse", f"point-to-plane RMSE {rmse_after:.1f} mm > "
                                f"{gate.max_rmse_mm} mm"))
    if n_corr and not noise_rms <= gate.max_normalised_rms:
        reasons.append((
            "residuals",
            f"residuals {noise_rms:.1f}x the {_noise_name(*clouds)} noise model (limit "
            f"{gate.max_normalised_rms}x): the surfaces do not fit (a wrong local minimum, "
            "a moving scene or a depth error)"))
    if cond < gate.min_conditioning:
        reasons.append((
            "conditioning",
            f"poorly conditioned overlap ({cond:.3g} < {gate.min_conditioning}): "
            "the common surfaces leave a direction unconstrained (e.g. a single plane)"
        ))
    if n_corr and fit.n_patches < gate.min_patches:
        reasons.append(("patches", f"{fit.n_patches} surface patches of "
                        f"{config.uncertainty.information_patch_m} m < {gate.min_patches}: "
                        "too few to estimate the pair's uncertainty"))
    if corr_mm > 1000.0 * gate.max_correction_m or corr_deg > gate.max_correction_deg:
        reasons.append((
            "correction",
            f"moved {corr_mm:.0f} mm / {corr_deg:.1f} deg from the initial guess (limit "
            f"{1000.0 * gate.max_correction_m:.0f} mm / {gate.max_correction_deg} deg)"
        ))
    agrees = not reasons and not improvement >= gate.min_improvement_chi2
    if agrees:
        reasons.append((
            "not_significant",
            f"no significant improvement on the current extrinsics: ICP moved "
            f"{corr_mm:.2f} mm / {corr_deg:.3f} deg, chi2 {improvement:.1f} < "
            f"{config.acceptance.min_improvement_chi2} (6 dof) under its own uncertainty"
            + (" (depth scale unknown: a move a depth-scale error explains does not count)"
               if any(free_scale) else "")))
    if not np.all(np.isfinite(fit.information)):
        reasons.append(("information", "information matrix not finite"))
        agrees = False
    return reasons, agrees


# --------------------------------------------------------------------------- failures
# Open3D and kiss-icp report failures as RuntimeError (pybind11), bad inputs as ValueError;
# a singular system surfaces from numpy as LinAlgError. Any of them rejects the pair only.
ICP_ERRORS: tuple[type[BaseException], ...] = (RuntimeError, ValueError,
                                               np.linalg.LinAlgError)


def one_line_error(exc: BaseException) -> str:
    """The error's message on one line, without terminal colour codes (Open3D adds them)."""
    text = " ".join(re.sub(r"\x1b\[[0-9;]*m", "", str(exc)).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def failed_registration(cam_a: str, cam_b: str, method: str, T_b_a_initial: np.ndarray,
                        reason: str, t_start: float | None = None) -> PairRegistration:
    """A rejected :class:`PairRegistration` for a pair whose registration could not run or
    failed (``reason`` says why): no measurement, zero information, the initial ``T_b_a``."""
    nan = float("nan")
    T0 = np.asarray(T_b_a_initial, dtype=float)
    return PairRegistration(
        cam_a=cam_a, cam_b=cam_b, method=method, T_b_a=T0, T_b_a_initial=T0,
        information=np.zeros((6, 6)), information_frame=INFORMATION_FRAME, fitness=0.0,
        inlier_rmse_mm=nan, rmse_before_mm=nan, rmse_after_mm=nan, conditioning=0.0,
        n_correspondences=0, correction_deg=0.0, correction_mm=0.0, accepted=False,
        reason=reason, rejected_by=("failed",),
        time_s=0.0 if t_start is None else time.perf_counter() - t_start,
    )


# --------------------------------------------------------------------------- robust registration
def _fpfh_cloud(cloud: CameraCloud, voxel: float, config: DepthConfig):
    """Voxel means of the well-measured points with normals and FPFH features."""
    keep = cloud.sigma_z <= config.registration.icp_max_sigma_z_m  # the points registration uses
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
    away (measured: docs/depth.md). None when RANSAC
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
    reg = config.registration
    levels = [v for v in (0.16, 0.08) if v > reg.voxel_schedule_m[0]]
    return config.replaced(voxel_schedule_m=levels + list(reg.voxel_schedule_m),
                           iterations=[40] * len(levels) + list(reg.iterations),
                           crop_margin_px=reg.crop_margin_px + 100.0)


def _better(first: PairRegistration, second: PairRegistration) -> PairRegistration:
    """The registration that fits: accepted before rejected, then more of the source points
    matched (fitness), then smaller residuals against the noise model."""
    def key(r: PairRegistration):
        rms = r.normalised_rms if r.normalised_rms is not None and math.isfinite(
            r.normalised_rms) else math.inf
        return (r.accepted, round(r.fitness, 2), -rms)
    return second if key(second) > key(first) else first


def register_robust(cloud_a: CameraCloud, cloud_b: CameraCloud, T_ref_a: np.ndarray,
                    T_ref_b: np.ndarray, method: RegistrationMethod = "colored-icp",
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


# --------------------------------------------------------------------------- overlap error
def overlap_error(
    cloud_a: CameraCloud,
    cloud_b: CameraCloud,
    T_ref_a: np.ndarray,
    T_ref_b: np.ndarray,
    max_distance_m: float = 0.05,
    normal_radius_m: float = 0.03,
) -> np.ndarray:
    """Signed point-to-plane distance (m) of each of a's points to b's surface, ``(N_a,)``.

    a's points go into b with ``inv(T_ref_b) @ T_ref_a``; each takes its nearest point of b
    (NaN when none lies within ``max_distance_m``) and the distance along b's normal (positive
    towards camera b). b's normals are estimated when the cloud has none. Index the result with
    ``cloud_a.pixels`` for an error map over a's image."""
    if cloud_b.normals is None:
        cloud_b = with_normals(cloud_b, normal_radius_m)
    out = np.full(cloud_a.n_points, np.nan)
    if cloud_a.n_points == 0 or cloud_b.n_points == 0:
        return out
    T_b_a = invert_transform(T_ref_b) @ np.asarray(T_ref_a, dtype=float)
    p_b = transform_points(T_b_a, cloud_a.points)
    tree = cKDTree(cloud_b.points)
    d, j = tree.query(p_b, distance_upper_bound=max_distance_m, workers=-1)
    ok = np.isfinite(d)
    q = cloud_b.points[j[ok]].astype(float)
    out[ok] = np.einsum("ij,ij->i", cloud_b.normals[j[ok]].astype(float), p_b[ok] - q)
    return out
