"""The depth stage: static clouds, depth-scale bias, overlap, pairwise ICP and the fused cloud.

Pipeline, one function per step::

    static_cloud          per camera: temporal median of depth, board and motion masked
    estimate_depth_scale  per camera: measured depth on the board face vs the calibrated pose
    find_overlapping_pairs  which cameras see common surfaces under the current extrinsics
    register_pair         colored ICP (Park et al. 2017) or kiss-icp, with a 6x6 information
    fuse_clouds                     all cameras in the reference frame, per-point camera index
    overlap_error         point-to-plane distances between two cameras' clouds (report maps)

Depth noise follows a disparity model, ``sigma_z = z^2 * s / (f * B)`` with the disparity error
``s`` (px), the focal length ``f`` (px) and the baseline ``B`` (m) of the depth sensor: Intel's
D435 model (RealSense "Depth camera tuning / depth quality" white paper, RMS error) by default,
or a Kinect v1 (structured light) for a camera whose rig.yaml entry says
``depth_noise: kinect-v1`` (:func:`depth_noise`).

This is the only module that imports open3d and kiss_icp.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field, replace
from itertools import combinations
from typing import Any, Literal

import numpy as np
import open3d as o3d
from kiss_icp.mapping import VoxelHashMap
from kiss_icp.registration import Registration
from kiss_icp.voxelization import voxel_down_sample
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ..core.camera import CameraIntrinsics
from ..core.config import DepthConfig
from ..core.errors import DatasetError
from ..core.geometry import (
    covariance_sigmas,
    invert_transform,
    matrix_to_rotvec,
    skew,
    transform_error,
    transform_points,
)
from ..model.board import Board
from ..model.dataset import FolderDataset

Method = Literal["colored-icp", "geometric"]
INFORMATION_FRAME = (
    "right perturbation of T_b_a: T_b_a_true = T_b_a @ Exp(xi), xi = [omega (rad), v (m)] in "
    "camera a's frame (GTSAM Pose3 local coordinates; BetweenFactorPose3(key_ref_b, key_ref_a, "
    "T_b_a) uses exactly this tangent space)"
)
_MEDIAN_EFFICIENCY = math.pi / 2.0  # var(median of n Gaussian samples) ~ pi/2 * sigma^2 / n


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class CloudStats:
    """Pixel accounting of a static cloud (pixels of the image; a pixel counts once)."""

    n_frames: int
    n_pixels: int
    n_points: int
    n_board_masked: int  # covered by the board in at least one frame read
    n_no_depth: int  # too few valid samples
    n_moving: int  # depth spread above motion_k sigma
    n_edge: int  # depth-edge (flying) pixels
    n_out_of_range: int

    def to_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class CameraCloud:
    """The static scene seen by one camera, in that camera's frame.

    ``points`` (N,3) metres, ``colors`` (N,3) RGB in [0,1], ``sigma_z`` (N,) metres: noise-model
    sigma of the median depth, ``pixels`` (N,2) integer ``(u, v)`` of each point, ``normals``
    (N,3) unit vectors facing the camera or None (see :func:`with_normals`)."""

    camera: str
    intrinsics: CameraIntrinsics
    points: np.ndarray
    colors: np.ndarray
    sigma_z: np.ndarray
    pixels: np.ndarray
    stats: CloudStats
    frames: tuple[str, ...]
    depth_scale_factor: float = 1.0
    normals: np.ndarray | None = None
    correlation_px: float = 1.0  # pixels within this square share their depth error
    # variance (px^2 / unitless^2) of the parameters of ``intrinsics`` that were estimated
    # (e.g. refined in the bundle adjustment): name -> variance; empty means exact
    intrinsics_variance: dict[str, float] = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    def select(self, keep: np.ndarray) -> CameraCloud:
        """A cloud with the points where ``keep`` (bool mask or indices) selects."""
        return replace(
            self,
            points=self.points[keep],
            colors=self.colors[keep],
            sigma_z=self.sigma_z[keep],
            pixels=self.pixels[keep],
            normals=None if self.normals is None else self.normals[keep],
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "camera": self.camera,
            "n_points": self.n_points,
            "frames": list(self.frames),
            "depth_scale_factor": self.depth_scale_factor,
            "stats": self.stats.to_dict(),
        }


@dataclass(frozen=True)
class DepthScaleEstimate:
    """Multiplicative depth-scale error of one camera: ``z_measured ~ factor * z_true``.

    ``sigma`` is the 1-sigma standard error of ``factor`` (spread over frames)."""

    camera: str
    factor: float
    sigma: float
    n_frames: int
    n_points: int
    frame_factors: dict[str, float]

    def to_dict(self) -> dict[str, Any]:
        return {
            "camera": self.camera,
            "factor": self.factor,
            "sigma": self.sigma,
            "n_frames": self.n_frames,
            "n_points": self.n_points,
        }


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
        }


# --------------------------------------------------------------------------- camera model
def d435_sigma_z(z_m: np.ndarray, focal_px: float, subpixel_px: float = 0.08,
                 baseline_m: float = 0.050) -> np.ndarray:
    """D435 depth RMS error (m) at depth ``z_m``: ``z^2 s / (f B)`` (Intel depth white paper)."""
    z = np.asarray(z_m, dtype=float)
    return z * z * subpixel_px / (focal_px * baseline_m)


@dataclass(frozen=True)
class DepthNoise:
    """Per-pixel depth noise of a disparity sensor: ``sigma_z = z^2 s / (f B)``.

    ``correlation_px`` is the side of the image square over which pixels share their error: a
    mean of ``k`` neighbouring pixels holds ``max(1, k / correlation_px^2)`` independent
    errors, not ``k``. Stereo matching and structured light both correlate over their matching
    window; the synthetic D435 noise is drawn per pixel (1)."""

    subpixel_px: float
    baseline_m: float
    focal_px: float
    correlation_px: float = 1.0

    @property
    def disparity_sigma(self) -> float:
        """Sigma of the inverse depth (1/m): ``s / (f B)``."""
        return self.subpixel_px / (self.focal_px * self.baseline_m)

    def sigma_z(self, z_m: np.ndarray) -> np.ndarray:
        """Single-frame, single-pixel depth sigma (m) at depth ``z_m``."""
        return d435_sigma_z(z_m, self.focal_px, self.subpixel_px, self.baseline_m)


# Kinect v1 (structured light, IR camera f ~ 580 px, projector-camera baseline 7.5 cm;
# Khoshelham & Elberink, Sensors 2012). Measured on planar patches of the TUM fr1/xyz frames
# (docs/depth.md): 1.6 mm per pixel at 0.74 m (2.9e-3 z^2; Khoshelham & Elberink report
# 1.4e-3 z^2, without the 1/8 px disparity quantisation), and an 8x8 pixel mean only 1.7-2.2x
# less noisy than one pixel, not 8x: about one independent error per 4x4 pixels.
KINECT_V1_NOISE = DepthNoise(subpixel_px=0.125, baseline_m=0.075, focal_px=580.0,
                             correlation_px=4.0)


def depth_noise(intr: CameraIntrinsics, config: DepthConfig) -> DepthNoise:
    """The depth noise model of a camera: its rig.yaml ``depth_noise`` (``kinect-v1``: the
    :data:`KINECT_V1_NOISE` constants), else the D435 model with ``config``'s ``subpixel_px``
    and ``baseline_m`` at ``depth_focal_px`` (default: the colour fx, depth being aligned to
    colour)."""
    if intr.depth_noise == "kinect-v1":
        return KINECT_V1_NOISE
    return DepthNoise(config.subpixel_px, config.baseline_m, config.depth_focal_px or intr.fx)


def _noise_name(*clouds: CameraCloud) -> str:
    """The noise models of clouds, for a message: 'D435', 'Kinect v1' or 'D435 / Kinect v1'."""
    names = {"d435": "D435", "kinect-v1": "Kinect v1"}
    return " / ".join(dict.fromkeys(names.get(c.intrinsics.depth_noise, c.intrinsics.depth_noise)
                                    for c in clouds))


def _median_efficiency(n: np.ndarray) -> np.ndarray:
    """var(median of n Gaussian samples) * n / sigma^2: pi/2 for many samples, 1 for one or two
    (their median is their mean)."""
    return np.where(np.asarray(n) <= 2, 1.0, _MEDIAN_EFFICIENCY)


def _in_view(intr: CameraIntrinsics, points_cam: np.ndarray, margin_px: float,
             min_z: float, max_z: float) -> np.ndarray:
    """Which camera-frame points lie in the image (grown by ``margin_px``) and depth range."""
    z = points_cam[:, 2]
    ok = (z > min_z) & (z < max_z)
    uv = np.full((points_cam.shape[0], 2), -1e9)
    if np.any(ok):
        uv[ok] = intr.project(points_cam[ok])
    return (
        ok
        & (uv[:, 0] > -0.5 - margin_px)
        & (uv[:, 0] < intr.width - 0.5 + margin_px)
        & (uv[:, 1] > -0.5 - margin_px)
        & (uv[:, 1] < intr.height - 0.5 + margin_px)
    )


# --------------------------------------------------------------------------- static clouds
def target_box(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box ``(lo, hi)`` (board frame, m) holding the target: a flat board's panel
    from its front (z = 0) to its back (z = -thickness); for a multi-face target each face's
    panel and the plate ``thickness`` behind it, and its ``body``."""
    sheets = board.sheets or (None,)
    pts = []
    for s in sheets:
        x0, x1, y0, y1 = board.panel if s is None else s.board.panel
        local = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1)
                          for z in (0.0, -board.thickness)])
        pts.append(local if s is None else transform_points(s.T_board_face, local))
    if board.body is not None:
        pts.append(np.array(board.body))
    allp = np.concatenate(pts)
    return allp.min(axis=0), allp.max(axis=0)


def _facing_face(board: Board, T_cam_board: np.ndarray):
    """The face the camera looks at most squarely, as ``(T_cam_face, panel, z_face)``: the
    face's pose in the camera, its panel (face frame) and the z of its printed plane; None when
    the camera sees no face from its front (a flat board: front at z = 0 or back at
    z = -thickness, in the board frame)."""
    if not board.sheets:
        centre_b = invert_transform(T_cam_board)[:3, 3]  # camera centre in the board frame
        if centre_b[2] > 0:
            return T_cam_board, board.panel, 0.0
        if centre_b[2] < -board.thickness:
            return T_cam_board, board.panel, -board.thickness
        return None
    best, best_cos = None, 0.0
    for s in board.sheets:
        T_cf = T_cam_board @ s.T_board_face
        x0, x1, y0, y1 = s.board.panel
        centre_c = T_cf[:3, :3] @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0]) + T_cf[:3, 3]
        cos = -float(T_cf[:3, 2] @ centre_c) / float(np.linalg.norm(centre_c))
        if cos > best_cos:
            best, best_cos = (T_cf, s.board.panel, 0.0), cos
    return best


def board_mask(intr: CameraIntrinsics, T_cam_board: np.ndarray, board: Board,
               margin_m: float = 0.03, dilate_px: float = 3.0) -> np.ndarray:
    """Pixels ``(H,W)`` bool covered by the target's box (:func:`target_box`: a flat board's
    panel, both faces and the edges; every face and the body of a multi-face target) grown by
    ``margin_m``, at pose ``T_cam_board`` (4x4, metres), dilated by ``dilate_px``.

    The box is convex, so its image is the convex hull of its eight projected corners. A board
    crossing the camera plane masks the whole image."""
    lo, hi = target_box(board)
    m = margin_m
    box_b = np.array([[x, y, z] for x in (lo[0] - m, hi[0] + m) for y in (lo[1] - m, hi[1] + m)
                      for z in (hi[2] + m, lo[2] - m)])
    box_c = transform_points(T_cam_board, box_b)
    mask = np.zeros((intr.height, intr.width), dtype=bool)
    if np.all(box_c[:, 2] <= 0.02):
        return mask
    if np.any(box_c[:, 2] <= 0.02):
        mask[:] = True
        return mask
    uv = intr.project(box_c)
    try:
        hull = ConvexHull(uv)
    except QhullError:
        return mask
    u0 = max(int(np.floor(uv[:, 0].min() - dilate_px)), 0)
    u1 = min(int(np.ceil(uv[:, 0].max() + dilate_px)), intr.width - 1)
    v0 = max(int(np.floor(uv[:, 1].min() - dilate_px)), 0)
    v1 = min(int(np.ceil(uv[:, 1].max() + dilate_px)), intr.height - 1)
    if u0 > u1 or v0 > v1:
        return mask
    vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
    # hull.equations rows are [a, b, c] with unit (a, b): a u + b v + c <= 0 inside
    eq = hull.equations
    signed = uu[..., None] * eq[:, 0] + vv[..., None] * eq[:, 1] + eq[:, 2]
    mask[v0 : v1 + 1, u0 : u1 + 1] = signed.max(axis=-1) <= dilate_px
    return mask


def _even_sample(items: list[str], n: int) -> list[str]:
    if len(items) <= n:
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, n)).astype(int))
    return [items[i] for i in idx]


def _nan_median(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median over axis 0 ignoring NaN, and the count of valid samples (fast: one sort)."""
    count = np.sum(~np.isnan(stack), axis=0)
    s = np.sort(stack, axis=0)  # NaN sort last
    lo = np.maximum(count - 1, 0) // 2
    hi = count // 2
    a = np.take_along_axis(s, lo[None], axis=0)[0]
    b = np.take_along_axis(s, np.minimum(hi, stack.shape[0] - 1)[None], axis=0)[0]
    med = np.where(count > 0, 0.5 * (a + b), np.nan)
    return med, count


def static_cloud(
    dataset: FolderDataset,
    camera: str,
    T_ref_board: dict[str, np.ndarray],
    T_ref_cam: np.ndarray,
    board: Board,
    config: DepthConfig | None = None,
    depth_scale_factor: float = 1.0,
) -> CameraCloud:
    """The static scene of one camera: per-pixel temporal median of depth over up to
    ``config.max_frames`` frames sampled evenly (read one at a time).

    ``T_ref_board`` maps frame -> board pose (4x4, metres, reference frame; may be empty) and
    ``T_ref_cam`` is this camera's current extrinsics: together they place the board in each
    frame, and its pixels (grown by a margin) are left out of that frame's sample. Pixels whose
    depth spreads over frames by more than ``motion_k`` sigma_z (:func:`depth_noise`) are
    moving and dropped; so are depth edges and depths out of range. Depth is divided by
    ``depth_scale_factor`` (the camera's :func:`estimate_depth_scale` factor) before anything
    else. Points are back-projected with the rig intrinsics (depth_scale from the rig); the
    intrinsics the rig marks as estimated (``rig.sigmas``) give the cloud its
    ``intrinsics_variance``, their sigma times ``config.lens_sigma_factor``."""
    config = config or DepthConfig()
    intr = dataset.rig.cameras[camera]
    frames = [
        f for f in dataset.frames
        if dataset.depth_path(camera, f) is not None and dataset.color_path(camera, f) is not None
    ]
    if not frames:
        raise DatasetError(
            f"{dataset.path / camera}: no frame with both colour and depth; "
            "depth steps need <camera>/depth/<frame>.png aligned to colour"
        )
    picked = _even_sample(frames, config.max_frames)
    n, H, W = len(picked), intr.height, intr.width
    metres_per_count = intr.depth_scale / depth_scale_factor
    depth = np.full((n, H, W), np.nan, dtype=np.float32)
    color = np.zeros((n, H, W, 3), dtype=np.uint8)
    masked = np.zeros((H, W), dtype=np.int32)
    T_cam_ref = invert_transform(T_ref_cam)
    for k, frame in enumerate(picked):
        z = dataset.read_depth(camera, frame).astype(np.float32) * np.float32(metres_per_count)
        z[z <= 0] = np.nan
        if frame in T_ref_board:
            m = board_mask(intr, T_cam_ref @ T_ref_board[frame], board,
                           config.board_mask_margin_m, config.board_mask_dilate_px)
            z[m] = np.nan
            masked += m
        depth[k] = z
        color[k] = dataset.read_color(camera, frame)[..., ::-1]  # BGR -> RGB

    # 1. temporal median and robust spread (1.4826 MAD) of the valid samples
    med, count = _nan_median(depth)
    dev = np.abs(depth - med[None])
    mad, _ = _nan_median(dev)
    spread = 1.4826 * mad
    # 2. single-frame model sigma at the median depth (+ depth quantisation)
    noise = depth_noise(intr, config)
    sigma1 = np.sqrt(noise.sigma_z(med) ** 2 + metres_per_count**2 / 12.0)
    # 3. masks: enough samples, not moving, in range, not a depth edge
    # a pixel needs min_samples valid samples, or all its board-free frames when fewer, but
    # never fewer than 2 when 2 frames or more were read (one sample cannot show motion)
    unmasked = n - masked
    need = np.maximum(np.minimum(config.min_samples, unmasked), min(2, n))
    enough = (count >= need) & (count >= config.min_valid_fraction * unmasked)
    moving = enough & (n > 1) & (spread > config.motion_k * sigma1)
    with np.errstate(invalid="ignore"):
        in_range = (med >= config.min_range_m) & (med <= config.max_range_m)
    edge = np.zeros((H, W), dtype=bool)
    if config.edge_jump_sigmas is not None:
        disp = np.where(enough & ~moving, 1.0 / np.where(med > 0, med, np.nan), np.nan)
        thr = config.edge_jump_sigmas * noise.disparity_sigma
        with np.errstate(invalid="ignore"):
            jump_x = np.abs(np.diff(disp, axis=1)) > thr
            jump_y = np.abs(np.diff(disp, axis=0)) > thr
        edge[:, 1:] |= jump_x
        edge[:, :-1] |= jump_x
        edge[1:, :] |= jump_y
        edge[:-1, :] |= jump_y
    keep = enough & ~moving & in_range & ~edge
    # 4. colour: mean of the samples that agree with the median
    inlier = dev <= config.motion_k * sigma1[None]  # NaN compares False
    n_in = np.maximum(inlier.sum(axis=0), 1)
    rgb = np.zeros((H, W, 3), dtype=np.float32)
    for k in range(n):  # frame by frame: no float copy of the whole colour stack
        rgb += np.where(inlier[k, ..., None], color[k], 0).astype(np.float32)
    rgb /= 255.0 * n_in[..., None]
    # 5. back-projection
    vs, us = np.nonzero(keep)
    z = med[vs, us].astype(float)
    points = intr.rays(us, vs) * z[:, None]
    sigma_z = sigma1[vs, us] * np.sqrt(_median_efficiency(n_in[vs, us]) / n_in[vs, us])
    stats = CloudStats(
        n_frames=n,
        n_pixels=H * W,
        n_points=int(vs.size),
        n_board_masked=int(np.count_nonzero(masked)),
        n_no_depth=int(np.count_nonzero(~enough)),
        n_moving=int(np.count_nonzero(moving)),
        n_edge=int(np.count_nonzero(edge & enough & ~moving)),
        n_out_of_range=int(np.count_nonzero(enough & ~moving & ~edge & ~in_range)),
    )
    return CameraCloud(
        camera=camera,
        intrinsics=intr,
        points=points.astype(np.float32),
        colors=np.clip(rgb[vs, us], 0.0, 1.0).astype(np.float32),
        sigma_z=sigma_z.astype(np.float32),
        pixels=np.column_stack([us, vs]).astype(np.int32),
        stats=stats,
        frames=tuple(picked),
        depth_scale_factor=float(depth_scale_factor),
        correlation_px=noise.correlation_px,
        intrinsics_variance={name: (config.lens_sigma_factor * sigma) ** 2
                             for name, sigma in dataset.rig.sigmas.get(camera, {}).items()},
    )


def with_normals(cloud: CameraCloud, radius_m: float = 0.03, max_nn: int = 30) -> CameraCloud:
    """The cloud with unit normals (hybrid KNN within ``radius_m``) oriented to its camera."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points.astype(np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=max_nn))
    pcd.orient_normals_towards_camera_location(np.zeros(3))
    return replace(cloud, normals=np.asarray(pcd.normals).astype(np.float32))


# --------------------------------------------------------------------------- depth scale
def _huber_weights(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))


def _fit_scale(z_meas: np.ndarray, z_true: np.ndarray, sigma: np.ndarray, k: float,
               iterations: int = 10) -> tuple[float, float]:
    """IRLS fit of ``z_meas = f z_true`` with Huber weights on ``(z_meas - f z_true)/sigma``:
    returns ``f`` and its formal 1-sigma error."""
    f = float(np.median(z_meas / z_true))
    w = np.ones_like(z_meas)
    for _ in range(iterations):
        r = (z_meas - f * z_true) / sigma
        w = _huber_weights(r, k) / sigma**2
        f_new = float(np.sum(w * z_meas * z_true) / np.sum(w * z_true**2))
        if abs(f_new - f) < 1e-10:
            f = f_new
            break
        f = f_new
    return f, float(1.0 / np.sqrt(np.sum(w * z_true**2)))


def estimate_depth_scale(
    dataset: FolderDataset,
    camera: str,
    T_cam_board: dict[str, np.ndarray],
    board: Board,
    config: DepthConfig | None = None,
) -> DepthScaleEstimate:
    """Depth-scale error ``factor`` of one camera (``z_measured ~ factor * z_true``).

    ``T_cam_board`` maps frame -> the board pose in this camera (4x4, metres) from the
    calibration (metric through the printed board, so unbiased in scale). In each frame the
    board face towards the camera (front at z = 0 or back at z = -thickness, board frame) gives
    the true depth of every pixel ray that hits it inside the panel minus
    ``scale_face_margin_m``; the measured depth there is compared with it. Per frame ``f`` is an
    IRLS fit (Huber, weights 1/sigma_z^2 of the noise model); frames are combined by a Huber-
    weighted random-effects mean (weights 1/(sigma_k^2 + tau^2), tau^2 the spread between
    frames beyond their formal errors), and ``sigma`` is its standard error, inflated by the
    scatter over frames when that exceeds the weights."""
    config = config or DepthConfig()
    intr = dataset.rig.cameras[camera]
    noise = depth_noise(intr, config)
    mg = config.scale_face_margin_m
    cos_max = math.cos(math.radians(config.scale_max_view_angle_deg))
    frames, factors, errors, n_points = [], [], [], 0
    for frame in _even_sample(sorted(T_cam_board), config.scale_max_frames):
        T = np.asarray(T_cam_board[frame], dtype=float)
        raw = dataset.read_depth(camera, frame)
        if raw is None:
            continue
        facing = _facing_face(board, T)
        if facing is None:
            continue
        T, (x0, x1, y0, y1), z_face = facing  # a multi-face target: in the face's frame
        face = np.array([[x, y, z_face] for x, y in
                         ((x0 + mg, y0 + mg), (x1 - mg, y0 + mg), (x1 - mg, y1 - mg),
                          (x0 + mg, y1 - mg))])
        face_c = transform_points(T, face)
        if np.any(face_c[:, 2] <= 0.05):
            continue
        n_c = T[:3, 2]  # face normal (board z) in the camera
        p0 = face_c[0]
        to_face = face_c.mean(axis=0)
        if abs(n_c @ to_face) / np.linalg.norm(to_face) < cos_max:
            continue
        uv = intr.project(face_c)
        u0 = max(int(np.floor(uv[:, 0].min())), 0)
        u1 = min(int(np.ceil(uv[:, 0].max())), intr.width - 1)
        v0 = max(int(np.floor(uv[:, 1].min())), 0)
        v1 = min(int(np.ceil(uv[:, 1].max())), intr.height - 1)
        if u0 > u1 or v0 > v1:
            continue
        sub = raw[v0 : v1 + 1, u0 : u1 + 1]
        vs, us = np.nonzero(sub > 0)
        us, vs = us + u0, vs + v0
        rays = intr.rays(us, vs)
        # ray-plane intersection: z_true = (n . p0) / (n . ray) is the camera z-depth
        z_true = (n_c @ p0) / (rays @ n_c)
        hit_b = transform_points(invert_transform(T), rays * z_true[:, None])
        inside = (
            (z_true > 0)
            & (hit_b[:, 0] > x0 + mg) & (hit_b[:, 0] < x1 - mg)
            & (hit_b[:, 1] > y0 + mg) & (hit_b[:, 1] < y1 - mg)
        )
        if np.count_nonzero(inside) < config.scale_min_points:
            continue
        z_true = z_true[inside]
        z_meas = raw[vs[inside], us[inside]].astype(float) * intr.depth_scale
        sigma = np.sqrt(noise.sigma_z(z_true) ** 2 + intr.depth_scale**2 / 12.0)
        f, err = _fit_scale(z_meas, z_true, sigma, config.scale_huber_k)
        frames.append(frame)
        factors.append(f)
        errors.append(err)
        n_points += int(z_true.size)
    if not factors:
        raise DatasetError(
            f"{dataset.path / camera}: no frame shows a board face to this camera's depth "
            f"(at least {config.scale_min_points} pixels); cannot estimate its depth scale"
        )
    fk, sk = np.asarray(factors), np.asarray(errors)
    factor, sigma = _combine_frames(fk, sk, config.scale_huber_k)
    return DepthScaleEstimate(camera, factor, sigma, len(fk), n_points,
                              dict(zip(frames, map(float, fk))))


def _combine_frames(fk: np.ndarray, sk: np.ndarray, k: float) -> tuple[float, float]:
    """Random-effects, Huber-weighted mean of per-frame factors ``fk`` with formal errors
    ``sk``; returns the mean and its standard error."""
    if fk.size == 1:
        return float(fk[0]), float(sk[0])
    med = float(np.median(fk))
    robust_var = (1.4826 * np.median(np.abs(fk - med))) ** 2
    tau2 = max(robust_var - float(np.median(sk**2)), 0.0)
    base = 1.0 / (sk**2 + tau2)
    mean = med
    w = base
    for _ in range(20):
        r = (fk - mean) * np.sqrt(base)
        w = base * _huber_weights(r, k)
        new = float(np.sum(w * fk) / np.sum(w))
        if abs(new - mean) < 1e-12:
            mean = new
            break
        mean = new
    se = 1.0 / np.sqrt(np.sum(w))
    chi2_dof = float(np.sum(w * (fk - mean) ** 2) / (fk.size - 1))
    return mean, float(se * np.sqrt(max(chi2_dof, 1.0)))


# --------------------------------------------------------------------------- voxels
def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 key per point's voxel (21 bits per axis, origin-shifted)."""
    idx = np.floor(points / voxel).astype(np.int64)
    idx -= idx.min(axis=0)
    if np.any(idx >= 1 << 21):
        raise ValueError("cloud too large for the voxel size")
    return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]


def voxel_mean(points: np.ndarray, voxel: float, *values: np.ndarray,
               ) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Average points (and per-point ``values``) per voxel; returns the means, the averaged
    values and the count per voxel."""
    if points.shape[0] == 0:
        return points.astype(float), [v.astype(float) for v in values], np.zeros(0, int)
    _, inverse, counts = np.unique(_voxel_keys(points, voxel), return_inverse=True,
                                   return_counts=True)
    inverse = inverse.ravel()

    def mean(a: np.ndarray) -> np.ndarray:
        a = np.asarray(a, dtype=float)
        if a.ndim == 1:
            return np.bincount(inverse, a, counts.size) / counts
        return np.column_stack([np.bincount(inverse, a[:, j], counts.size) / counts
                                for j in range(a.shape[1])])

    return mean(points), [mean(v) for v in values], counts


def _voxel_pick(points: np.ndarray, voxel: float) -> np.ndarray:
    """Index of one point per occupied voxel (the first)."""
    if points.shape[0] == 0:
        return np.zeros(0, dtype=int)
    _, first = np.unique(_voxel_keys(points, voxel), return_index=True)
    return first


# --------------------------------------------------------------------------- overlap
def _overlap_fraction(points_a: np.ndarray, T_b_a: np.ndarray, intr_b: CameraIntrinsics,
                      tree_b: cKDTree, distance: float) -> tuple[float, int]:
    if points_a.shape[0] == 0:
        return 0.0, 0
    p_b = transform_points(T_b_a, points_a)
    view = _in_view(intr_b, p_b, 0.0, 0.05, np.inf)
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
    sample = {
        c: clouds[c].points[_voxel_pick(clouds[c].points, config.overlap_voxel_m)].astype(float)
        for c in names
    }
    trees = {c: cKDTree(sample[c]) for c in names}
    pairs = []
    for a, b in combinations(names, 2):
        T_b_a = invert_transform(T_ref_cam[b]) @ T_ref_cam[a]
        f_ab, n_ab = _overlap_fraction(sample[a], T_b_a, intrinsics[b], trees[b],
                                       config.overlap_distance_m)
        f_ba, n_ba = _overlap_fraction(sample[b], invert_transform(T_b_a), intrinsics[a],
                                       trees[a], config.overlap_distance_m)
        frac = min(f_ab, f_ba)
        if frac >= config.min_overlap and min(n_ab, n_ba) > 0:
            pairs.append(PairOverlap(a, b, frac, min(n_ab, n_ba), f_ab, f_ba))
    return sorted(pairs, key=lambda p: -p.overlap_fraction)


# --------------------------------------------------------------------------- registration
@dataclass(frozen=True)
class _Level:
    """One voxel level of a cloud: points, colours, normals, sigma_z along the viewing ray."""

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray
    sigma_z: np.ndarray


class _NormalField:
    """Normals of a cloud estimated once on coarse voxel means (noise averaged over
    ``radius``), looked up by nearest neighbour for the points of any level."""

    def __init__(self, points: np.ndarray, voxel: float, radius: float):
        pts, _, _ = voxel_mean(points, voxel)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        if pts.shape[0] >= 3:
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=60))
            pcd.orient_normals_towards_camera_location(np.zeros(3))
            self.normals = np.asarray(pcd.normals)
        else:
            self.normals = np.tile([0.0, 0.0, -1.0], (pts.shape[0], 1))
        self.tree = cKDTree(pts) if pts.shape[0] else None

    def __call__(self, points: np.ndarray) -> np.ndarray:
        if self.tree is None:
            return np.tile([0.0, 0.0, -1.0], (points.shape[0], 1))
        _, j = self.tree.query(points, workers=-1)
        return self.normals[j]


def _faces_camera(points: np.ndarray, normals: _NormalField, T_other_cam: np.ndarray,
                  max_incidence_deg: float) -> np.ndarray:
    """Which points (camera frame, normals towards their camera) the other camera, at
    ``T_other_cam``, sees from the front at an incidence below ``max_incidence_deg``."""
    p = points.astype(float)
    n_other = normals(p) @ T_other_cam[:3, :3].T
    p_other = transform_points(T_other_cam, p)
    cos_inc = -np.einsum("ij,ij->i", n_other, p_other) / np.linalg.norm(p_other, axis=1)
    return cos_inc > math.cos(math.radians(max_incidence_deg))


def _make_level(cloud: CameraCloud, keep: np.ndarray, voxel: float,
                normals: _NormalField) -> _Level:
    pts, (col, var), counts = voxel_mean(
        cloud.points[keep].astype(float), voxel, cloud.colors[keep],
        cloud.sigma_z[keep].astype(float) ** 2,
    )
    # the mean of `counts` neighbouring pixels' depths: independent errors only one per
    # correlation_px^2 pixels (a voxel's pixels are neighbours in the image)
    independent = np.maximum(counts / cloud.correlation_px**2, 1.0)
    sigma = np.sqrt(var / independent)
    return _Level(pts, col, normals(pts), sigma)


def _legacy_cloud(level: _Level) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(level.points))
    pcd.colors = o3d.utility.Vector3dVector(level.colors)
    pcd.normals = o3d.utility.Vector3dVector(level.normals)
    return pcd


def _tensor_cloud(level: _Level) -> o3d.t.geometry.PointCloud:
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(level.points.astype(np.float32)))
    pcd.point.colors = o3d.core.Tensor(level.colors.astype(np.float32))
    pcd.point.normals = o3d.core.Tensor(level.normals.astype(np.float32))
    return pcd


def _colored_icp_level(src: _Level, tgt: _Level, T: np.ndarray, distance: float,
                       iterations: int, config: DepthConfig) -> np.ndarray:
    """One level of colored ICP (Park, Zhou, Koltun: "Colored Point Cloud Registration
    Revisited", ICCV 2017): the joint objective ``(1 - lambda) E_C + lambda E_G`` of a
    photometric term on the target's tangent planes and the point-to-plane term, with
    ``lambda = lambda_geometric``. Returns ``T_target_source``."""
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        return _colored_icp_call(src, tgt, T, distance, iterations, config)


def _colored_icp_call(src: _Level, tgt: _Level, T: np.ndarray, distance: float,
                      iterations: int, config: DepthConfig) -> np.ndarray:
    if config.icp_backend == "tensor":
        reg = o3d.t.pipelines.registration
        result = reg.icp(
            _tensor_cloud(src), _tensor_cloud(tgt), distance,
            o3d.core.Tensor(T), reg.TransformationEstimationForColoredICP(config.lambda_geometric),
            reg.ICPConvergenceCriteria(1e-6, 1e-6, iterations),
        )
        return result.transformation.numpy().astype(float)
    reg = o3d.pipelines.registration
    result = reg.registration_colored_icp(
        _legacy_cloud(src), _legacy_cloud(tgt), distance, T,
        reg.TransformationEstimationForColoredICP(lambda_geometric=config.lambda_geometric),
        reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6,
                                   max_iteration=iterations),
    )
    return np.asarray(result.transformation, dtype=float)


def _geometric_icp_level(src: _Level, tgt: _Level, T: np.ndarray, voxel: float,
                         config: DepthConfig, registration: Registration) -> np.ndarray:
    """One level of kiss-icp's robust point-to-point ICP (Vizzo et al., "KISS-ICP", RA-L 2023):
    the target in a voxel hash map of this level's size (its neighbour search reaches adjacent
    voxels only, hence the coarse-to-fine levels), the source thinned to 1.5 voxels as
    kiss-icp's own pipeline does."""
    voxel_map = VoxelHashMap(voxel_size=voxel, max_distance=1e6,
                             max_points_per_voxel=config.kiss_max_points_per_voxel)
    voxel_map.add_points(np.ascontiguousarray(tgt.points, dtype=np.float64))
    source = voxel_down_sample(np.ascontiguousarray(src.points, dtype=np.float64), 1.5 * voxel)
    return np.asarray(
        registration.align_points_to_map(
            points=source, voxel_map=voxel_map, initial_guess=T,
            max_correspondance_distance=config.max_correspondence_factor * voxel,
            kernel=config.kiss_kernel_factor * voxel,
        ),
        dtype=float,
    )


@dataclass(frozen=True)
class _Matches:
    """Nearest-neighbour correspondences of source (a) points in the target (b) cloud."""

    src: np.ndarray  # source points in a, (M,3)
    tgt: np.ndarray  # target points in b
    normals_b: np.ndarray  # target normals in b
    residual: np.ndarray  # point-to-plane residual (m)
    sigma: np.ndarray  # its noise-model sigma (m)
    distance: np.ndarray  # point-to-point distance (m)
    src_index: np.ndarray  # indices into the source level
    tgt_index: np.ndarray  # indices into the target level


def _match(src: _Level, tgt: _Level, tree: cKDTree, T_b_a: np.ndarray,
           max_distance: float) -> _Matches:
    p_b = transform_points(T_b_a, src.points)
    d, j = tree.query(p_b, distance_upper_bound=max_distance, workers=-1)
    ok = np.isfinite(d)
    i, j = np.nonzero(ok)[0], j[ok]
    n_b = tgt.normals[j]
    r = np.einsum("ij,ij->i", n_b, p_b[i] - tgt.points[j])
    # depth noise moves a point along its viewing ray: its normal component scales by
    # |n . p| / z (p/z is the ray with z = 1)
    m_a = n_b @ T_b_a[:3, :3]  # target normal in a's frame
    sa = src.sigma_z[i] * np.abs(np.einsum("ij,ij->i", m_a, src.points[i])) / src.points[i, 2]
    q = tgt.points[j]
    sb = tgt.sigma_z[j] * np.abs(np.einsum("ij,ij->i", n_b, q)) / q[:, 2]
    return _Matches(src.points[i], q, n_b, r, np.sqrt(sa**2 + sb**2 + 1e-12), d[ok], i, j)


def _intensity(colors: np.ndarray) -> np.ndarray:
    return np.asarray(colors, dtype=float).mean(axis=1)  # as Open3D's colored ICP: (r+g+b)/3


def color_gradients(points: np.ndarray, normals: np.ndarray, colors: np.ndarray,
                    k: int = 16, at: np.ndarray | None = None) -> np.ndarray:
    """Gradient (N,3) of the intensity on each point's tangent plane, fitted by least squares
    to its ``k`` nearest neighbours projected onto the plane (Park et al. 2017: the
    continuous colour function ``C_p(u) = C(p) + d_p^T (u - p)`` with ``d_p . n_p = 0``).
    ``at`` (indices) limits the fit to those points; the others get zeros."""
    n_pts = points.shape[0]
    out = np.zeros_like(points, dtype=float)
    if n_pts < 4:
        return out
    idx = np.arange(n_pts) if at is None else np.unique(at)
    k = min(k, n_pts)
    _, nb = cKDTree(points).query(points[idx], k=k, workers=-1)
    intensity = _intensity(colors)
    n = normals[idx]
    # orthonormal tangent basis per point
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    d = points[nb] - points[idx, None]  # (M,k,3)
    a = np.stack([np.einsum("nkj,nj->nk", d, t1), np.einsum("nkj,nj->nk", d, t2)], axis=-1)
    b = intensity[nb] - intensity[idx, None]
    ata = np.einsum("nki,nkj->nij", a, a) + 1e-9 * np.eye(2)
    atb = np.einsum("nki,nk->ni", a, b)
    g2 = np.linalg.solve(ata, atb[..., None])[..., 0]
    out[idx] = g2[:, :1] * t1 + g2[:, 1:] * t2
    return out


def point_to_plane_information(matches: _Matches, T_b_a: np.ndarray) -> np.ndarray:
    """Gauss-Newton information (6x6, [rot, trans]) of the point-to-plane residuals
    ``r = n_b . (T_b_a Exp(xi) p_a - q_b)`` for a right perturbation ``xi`` of ``T_b_a``.

    With ``m = R_b_a^T n_b`` (the normal in a's frame) the Jacobian row is
    ``[p_a x m, m]``. Weights are 1/sigma^2 of the D435 model; the whole matrix is divided by
    the residuals' variance factor chi^2/dof when that exceeds 1 (residuals larger than the
    noise model: sampling and registration error)."""
    if matches.residual.size < 6:
        return np.zeros((6, 6))
    m = matches.normals_b @ T_b_a[:3, :3]
    J = np.hstack([np.cross(matches.src, m), m])
    w = 1.0 / matches.sigma**2
    H = (J * w[:, None]).T @ J
    dof = max(matches.residual.size - 6, 1)
    chi2_dof = float(np.sum(w * matches.residual**2) / dof)
    return H / max(chi2_dof, 1.0)


def photometric_information(matches: _Matches, src: _Level, tgt: _Level,
                            gradients_b: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    """Gauss-Newton information (6x6, [rot, trans], right perturbation of ``T_b_a``) of the
    colour residuals of colored ICP (Park et al. 2017):
    ``r = C(q) + d_q . (T_b_a Exp(xi) p - q) - C(p)`` with the target's tangent-plane
    gradient ``d_q``. With ``g = R_b_a^T d_q`` the Jacobian row is ``[p x g, g]``; the
    residual variance is taken from the residuals themselves (colours have no noise model)."""
    if matches.residual.size < 7:
        return np.zeros((6, 6))
    d_q = gradients_b[matches.tgt_index]
    p_b = transform_points(T_b_a, matches.src)
    r = (_intensity(tgt.colors[matches.tgt_index]) + np.einsum("ij,ij->i", d_q, p_b - matches.tgt)
         - _intensity(src.colors[matches.src_index]))
    variance = max(float(np.sum(r**2) / (r.size - 6)), 1e-12)
    g = d_q @ T_b_a[:3, :3]
    J = np.hstack([np.cross(matches.src, g), g])
    return J.T @ J / variance


def conditioning(information: np.ndarray, points_a: np.ndarray) -> float:
    """Smallest over largest eigenvalue of ``information`` (right perturbation of ``T_b_a``,
    [rot, trans]) re-expressed about the centroid ``c`` of the overlap ``points_a`` (a's frame)
    with rotations scaled by their RMS radius ``L``, so both blocks are in metres (Gelfand,
    Ikemoto, Rusinkiewicz, Levoy: "Geometrically Stable Sampling for the ICP Algorithm", 3DIM
    2003). Near 0: a direction the overlap does not constrain (a single plane, ...).

    With ``xi = M xi'``, ``xi' = [L omega, v + omega x c]``: ``M = [[I/L, 0], [[c]x / L, I]]``
    and the normalised information is ``M^T I M``."""
    if points_a.shape[0] < 6 or not np.any(information):
        return 0.0
    c = points_a.mean(axis=0)
    L = float(np.sqrt(np.mean(np.sum((points_a - c) ** 2, axis=1)))) or 1.0
    M = np.eye(6)
    M[:3, :3] /= L
    M[3:, :3] = skew(c) / L
    ev = np.linalg.eigvalsh(M.T @ information @ M)
    return float(max(ev[0], 0.0) / ev[-1]) if ev[-1] > 0 else 0.0


# --------------------------------------------------------------------------- noise model
@dataclass(frozen=True)
class _WhitenedRows:
    """Residuals of a registration divided by their sigma, with their Jacobian rows (right
    perturbation of ``T_b_a``, [rot, trans]) and the surface patch each one comes from."""

    J: np.ndarray  # (M,6)
    r: np.ndarray  # (M,)
    patch: np.ndarray  # (M,) patch index in [0, n_patches)
    n_patches: int
    n_geometric: int  # the first n_geometric rows are point-to-plane, the rest photometric
    # d(whitened residual)/d(lens parameter) (M,P) and the parameters' variances (P,): the
    # intrinsics the two clouds were back-projected with are uncertain (None: exact)
    D: np.ndarray | None = None
    lens_variance: np.ndarray | None = None


def back_projection_jacobian(points: np.ndarray, intr: CameraIntrinsics,
                             names: list[str]) -> np.ndarray:
    """d p / d theta ``(N,3,P)`` of points ``p = z * ray(u, v)`` back-projected from fixed
    pixels at fixed depth, for the intrinsics ``names`` (fx fy cx cy k1 k2 p1 p2 k3), to
    first order in the distortion: a pixel's normalised coordinates are
    ``x = (u - cx) / fx - delta_x(x, y)`` with the Brown-Conrady offset ``delta``, so e.g.
    ``dX/dfx = -X / fx``, ``dX/dcx = -Z / fx`` and ``d(X, Y)/dk1 = -r^2 (X, Y)``."""
    p = np.asarray(points, dtype=float)
    X, Y, Z = p[:, 0], p[:, 1], p[:, 2]
    x, y = X / Z, Y / Z
    r2 = x * x + y * y
    zero = np.zeros_like(X)
    cols = {
        "fx": (-X / intr.fx, zero), "fy": (zero, -Y / intr.fy),
        "cx": (-Z / intr.fx, zero), "cy": (zero, -Z / intr.fy),
        "k1": (-X * r2, -Y * r2), "k2": (-X * r2**2, -Y * r2**2),
        "k3": (-X * r2**3, -Y * r2**3),
        "p1": (-Z * 2 * x * y, -Z * (r2 + 2 * y * y)),
        "p2": (-Z * (r2 + 2 * x * x), -Z * 2 * x * y),
    }
    out = np.zeros((p.shape[0], 3, len(names)))
    for k, name in enumerate(names):
        out[:, 0, k], out[:, 1, k] = cols[name]
    return out


Lens = tuple[CameraIntrinsics, dict[str, float]]


def _lens_columns(v_b: np.ndarray, T_b_a: np.ndarray, src: np.ndarray, tgt: np.ndarray,
                  lenses: tuple[Lens, Lens]) -> np.ndarray:
    """d r / d theta of residuals ``r = v_b . (T_b_a p_a - q_b) + ...`` (``v_b``: the target
    normal, or the colour gradient) for the uncertain intrinsics of a, then of b."""
    (intr_a, var_a), (intr_b, var_b) = lenses
    cols = []
    if var_a:
        v_a = v_b @ T_b_a[:3, :3]
        cols.append(np.einsum("ij,ijk->ik", v_a, back_projection_jacobian(src, intr_a,
                                                                           list(var_a))))
    if var_b:
        cols.append(-np.einsum("ij,ijk->ik", v_b, back_projection_jacobian(tgt, intr_b,
                                                                            list(var_b))))
    return np.hstack(cols) if cols else np.zeros((src.shape[0], 0))


def whitened_rows(matches: _Matches, T_b_a: np.ndarray, patch_m: float,
                  colour: tuple[_Level, _Level, np.ndarray] | None = None,
                  free_scale: tuple[bool, bool] = (False, False),
                  lenses: tuple[Lens, Lens] | None = None) -> _WhitenedRows:
    """Point-to-plane residuals over their noise-model sigma (:func:`_match`), and, with
    ``colour = (src, tgt, gradients_b)``, the photometric residuals of colored ICP over their
    RMS (colour has no noise model: its variance comes from the residuals). Rows are grouped
    by the ``patch_m`` voxel of their source point.

    ``free_scale`` adds a column per camera (a, b) whose depth scale is unknown: the
    derivative of the residual for ``p_a -> (1 + d_a) p_a`` (``m . p_a``) or
    ``q_b -> (1 + d_b) q_b`` (``-n_b . q_b``).

    ``lenses`` ``((intrinsics_a, variance_a), (intrinsics_b, variance_b))``: each camera's
    intrinsics and the variances of those that were estimated (name -> variance; empty:
    exact); their derivatives (:func:`back_projection_jacobian`) become ``D`` for
    :func:`noise_model_information`."""
    lenses = lenses if lenses is not None and (lenses[0][1] or lenses[1][1]) else None
    m = matches.normals_b @ T_b_a[:3, :3]
    cols = [np.cross(matches.src, m), m]
    if free_scale[0]:
        cols.append(np.einsum("ij,ij->i", m, matches.src)[:, None])
    if free_scale[1]:
        cols.append(-np.einsum("ij,ij->i", matches.normals_b, matches.tgt)[:, None])
    J = np.hstack(cols) / matches.sigma[:, None]
    r = matches.residual / matches.sigma
    D = (_lens_columns(matches.normals_b, T_b_a, matches.src, matches.tgt, lenses)
         / matches.sigma[:, None] if lenses is not None else None)
    n_geo = r.size
    if colour is not None and r.size >= 7:
        src, tgt, gradients_b = colour
        d_q = gradients_b[matches.tgt_index]
        p_b = transform_points(T_b_a, matches.src)
        rc = (_intensity(tgt.colors[matches.tgt_index])
              + np.einsum("ij,ij->i", d_q, p_b - matches.tgt)
              - _intensity(src.colors[matches.src_index]))
        sigma_c = max(float(np.sqrt(np.mean(rc**2))), 1e-6)
        g = d_q @ T_b_a[:3, :3]
        cols = [np.cross(matches.src, g), g]
        if free_scale[0]:
            cols.append(np.einsum("ij,ij->i", g, matches.src)[:, None])
        if free_scale[1]:
            cols.append(-np.einsum("ij,ij->i", d_q, matches.tgt)[:, None])
        J = np.vstack([J, np.hstack(cols) / sigma_c])
        r = np.concatenate([r, rc / sigma_c])
        if D is not None:
            D = np.vstack([D, _lens_columns(d_q, T_b_a, matches.src, matches.tgt, lenses)
                           / sigma_c])
    variance = (np.array([*lenses[0][1].values(), *lenses[1][1].values()], dtype=float)
                if lenses is not None else None)
    if n_geo == 0:
        return _WhitenedRows(np.zeros((0, J.shape[1])), np.zeros(0), np.zeros(0, int), 0, 0)
    _, patch = np.unique(_voxel_keys(matches.src, patch_m), return_inverse=True)
    patch = patch.ravel()
    n_patches = int(patch.max()) + 1
    # a photometric row belongs to the patch of its point-to-plane row
    return _WhitenedRows(J, r, np.tile(patch, r.size // n_geo), n_patches, n_geo, D, variance)


def noise_model_information(rows: _WhitenedRows) -> np.ndarray:
    """Information (6x6) of a registration from the depth noise model and its residuals.

    With whitened rows ``J_i``, ``r_i`` (:func:`whitened_rows`) the Gauss-Newton information
    ``H = sum J_i^T J_i`` is the inverse covariance of the estimate only if the residuals are
    independent with unit variance. They are neither: the normals, the voxel means and the
    differences between two cameras' samplings of a surface make residuals of one surface
    patch err together. The estimate's covariance is therefore the cluster-robust sandwich
    (Liang & Zeger 1986; White 1980)::

        Cov = H^-1 M H^-1,   M = G/(G-1) sum_k g_k g_k^T,   g_k = sum_{i in patch k} J_i^T r_i

    over the G patches. If the noise model held exactly and residuals were independent,
    E[M] = H and Cov = H^-1; residuals larger than the model grow M by their variance factor,
    and residuals correlated within a patch by its effective size; residuals smaller than the
    model (nearest-neighbour matching picks the closest noisy point, so the whitened
    point-to-plane residuals' mean square ``s^2`` is ~0.5 on the synthetic pairs) do not make
    the estimate better than the noise allows: M is divided by ``min(s^2, 1)``. The per-row meat
    ``sum (r_i J_i)^T (r_i J_i)`` over G is added to M so that a direction no patch's score
    happened to span keeps a finite variance.

    Intrinsics that were estimated (``rows.D``, ``rows.lens_variance``) move every point of a
    cloud together, so their error does not average out over points: the estimate moves by
    ``S dtheta`` with ``S = -H^-1 J^T D`` (the Gauss-Newton step for residuals changed by
    ``D dtheta``), which adds ``S diag(var) S^T`` to ``Cov``. The result is the inverse of
    ``Cov``'s pose block."""
    k = rows.J.shape[1]
    if rows.n_geometric < k or rows.n_patches < 2:
        return np.zeros((6, 6))
    H = rows.J.T @ rows.J
    scores = np.zeros((rows.n_patches, k))
    np.add.at(scores, rows.patch, rows.J * rows.r[:, None])
    G = rows.n_patches
    row_scores = rows.J * rows.r[:, None]
    M = G / (G - 1) * scores.T @ scores + row_scores.T @ row_scores / G
    # nearest-neighbour correspondences make residuals look smaller than the noise they carry
    # (each point takes the closest of the other cloud's noisy points): a whitened residual's
    # variance is at least the noise model's, 1
    s2 = float(np.mean(rows.r[: rows.n_geometric] ** 2))
    M = M / min(max(s2, 1e-6), 1.0)
    try:
        H_inv = np.linalg.inv(H)
        cov = H_inv @ M @ H_inv
        if rows.D is not None and rows.lens_variance is not None:
            S = H_inv @ (rows.J.T @ rows.D)
            cov = cov + (S * rows.lens_variance) @ S.T
        # columns beyond the pose (free depth scales) are marginalised: pose block of Cov
        info = np.linalg.inv(cov[:6, :6])
    except np.linalg.LinAlgError:
        return np.zeros((6, 6))
    return 0.5 * (info + info.T)


def normalised_rms(matches: _Matches) -> float:
    """RMS of the point-to-plane residuals over their noise-model sigma (1 when the residuals
    are the depth noise alone)."""
    if matches.residual.size == 0:
        return float("nan")
    return float(np.sqrt(np.mean((matches.residual / matches.sigma) ** 2)))


def tangent_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """``xi`` (6, [rot rad, trans m]) with ``T_true ~ T_est Exp(xi)``: the right-perturbation
    error of ``T_est`` in the frame of :data:`INFORMATION_FRAME`."""
    D = invert_transform(np.asarray(T_est, dtype=float)) @ np.asarray(T_true, dtype=float)
    return np.concatenate([matrix_to_rotvec(D[:3, :3]), D[:3, 3]])


def _rmse_mm(matches: _Matches) -> float:
    if matches.residual.size == 0:
        return float("nan")
    return float(1000.0 * np.sqrt(np.mean(matches.residual**2)))


def _common_surfaces(cloud_a: CameraCloud, cloud_b: CameraCloud, T_b_a0: np.ndarray,
                     config: DepthConfig):
    """Points of each cloud the other camera can see (in view, low noise, facing it), with
    their normal fields; the selection is made once, at the initial ``T_b_a0``."""
    T_a_b0 = invert_transform(T_b_a0)
    # 1. what each camera can see of the other's cloud
    keep_a = _in_view(cloud_b.intrinsics, transform_points(T_b_a0, cloud_a.points),
                      config.crop_margin_px, 0.05, np.inf)
    keep_b = _in_view(cloud_a.intrinsics, transform_points(T_a_b0, cloud_b.points),
                      config.crop_margin_px, 0.05, np.inf)
    keep_a &= cloud_a.sigma_z <= config.icp_max_sigma_z_m
    keep_b &= cloud_b.sigma_z <= config.icp_max_sigma_z_m
    normals_a = _NormalField(cloud_a.points[keep_a].astype(float), config.normal_voxel_m,
                             config.normal_radius_m)
    normals_b = _NormalField(cloud_b.points[keep_b].astype(float), config.normal_voxel_m,
                             config.normal_radius_m)
    # surfaces the other camera sees from behind (the far side of a rail, a post) or at a
    # grazing angle are not common to both views: drop them
    keep_a[keep_a] &= _faces_camera(cloud_a.points[keep_a], normals_a, T_b_a0,
                                    config.max_incidence_deg)
    keep_b[keep_b] &= _faces_camera(cloud_b.points[keep_b], normals_b, T_a_b0,
                                    config.max_incidence_deg)
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
    voxel = config.voxel_schedule_m[-1]
    src = _make_level(cloud_a, keep_a, voxel, normals_a)
    tgt = _make_level(cloud_b, keep_b, voxel, normals_b)
    if src.points.shape[0] == 0 or tgt.points.shape[0] < 3:
        return float("nan")
    T_b_a = invert_transform(T_ref_b) @ np.asarray(T_ref_a, dtype=float)
    return _rmse_mm(_match(src, tgt, cKDTree(tgt.points), T_b_a, config.eval_distance_m))


def register_pair(
    cloud_a: CameraCloud,
    cloud_b: CameraCloud,
    T_ref_a: np.ndarray,
    T_ref_b: np.ndarray,
    method: Method = "colored-icp",
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
    if method not in ("colored-icp", "geometric"):
        raise ValueError(f"unknown registration method {method!r}; use 'colored-icp' or "
                         "'geometric'")
    t_start = time.perf_counter()
    T_b_a0 = invert_transform(T_ref_b) @ np.asarray(T_ref_a, dtype=float)
    keep_a, keep_b, normals_a, normals_b = _common_surfaces(cloud_a, cloud_b, T_b_a0, config)
    T = T_b_a0.copy()
    finest: tuple[_Level, _Level] | None = None
    kiss = Registration(max_num_iterations=config.kiss_max_iterations,
                        convergence_criterion=1e-5, max_num_threads=_THREADS["kiss"])
    # 2. coarse to fine
    for voxel, iterations in zip(config.voxel_schedule_m, config.iterations):
        src = _make_level(cloud_a, keep_a, voxel, normals_a)
        tgt = _make_level(cloud_b, keep_b, voxel, normals_b)
        finest = (src, tgt)
        if src.points.shape[0] < 10 or tgt.points.shape[0] < 10:
            break
        distance = config.max_correspondence_factor * voxel
        try:
            if method == "colored-icp":
                T = _colored_icp_level(src, tgt, T, distance, iterations, config)
            else:
                T = _geometric_icp_level(src, tgt, T, voxel, config, kiss)
        except ICP_ERRORS as exc:  # e.g. Open3D: "No correspondences found between ..."
            return failed_registration(
                cloud_a.camera, cloud_b.camera, method, T_b_a0,
                f"{method} failed at voxel {voxel * 1000:.0f} mm: {one_line_error(exc)}", t_start)
        if not np.all(np.isfinite(T)):
            return failed_registration(cloud_a.camera, cloud_b.camera, method, T_b_a0,
                                       f"{method} diverged at voxel {voxel * 1000:.0f} mm "
                                       "(non-finite transform)", t_start)
    assert finest is not None
    src, tgt = finest
    # 3. quality at the finest level
    fine_distance = config.max_correspondence_factor * config.voxel_schedule_m[-1]
    if src.points.shape[0] > 0 and tgt.points.shape[0] >= 3:
        tree = cKDTree(tgt.points)
        final = _match(src, tgt, tree, T, fine_distance)
        before = _match(src, tgt, tree, T_b_a0, config.eval_distance_m)
        after = _match(src, tgt, tree, T, config.eval_distance_m)
    else:
        empty = np.zeros((0, 3))
        none = np.zeros(0, dtype=int)
        final = before = after = _Matches(empty, empty, empty, np.zeros(0), np.ones(0),
                                          np.zeros(0), none, none)
    n_corr = int(final.residual.size)
    colour = None
    if method == "colored-icp" and config.lambda_geometric < 1.0 and n_corr >= 7:
        colour = (src, tgt, color_gradients(tgt.points, tgt.normals, tgt.colors,
                                            at=final.tgt_index))
    rows = whitened_rows(final, T, config.information_patch_m, colour, free_scale,
                         ((cloud_a.intrinsics, cloud_a.intrinsics_variance),
                          (cloud_b.intrinsics, cloud_b.intrinsics_variance)))
    # the noise model's Gauss-Newton information says which directions the overlap
    # constrains (conditioning); the sandwich over patches says how well (information)
    cond = conditioning(rows.J[:, :6].T @ rows.J[:, :6], final.src) if n_corr else 0.0
    information = noise_model_information(rows)
    fitness = n_corr / src.points.shape[0] if src.points.shape[0] else 0.0
    inlier_rmse_mm = (float(1000.0 * np.sqrt(np.mean(final.distance**2))) if n_corr
                      else float("nan"))
    rmse_after = _rmse_mm(after)
    corr_deg, corr_mm = transform_error(T, T_b_a0)
    noise_rms = normalised_rms(final)
    # Wald statistic of the move: ~ chi^2(6) if the initial T_b_a were already right
    move = tangent_error(T, T_b_a0)
    improvement = float(move @ information @ move)
    reasons = []
    if n_corr < config.min_correspondences:
        reasons.append(f"{n_corr} correspondences < {config.min_correspondences}")
    if fitness < config.min_fitness:
        reasons.append(f"fitness {fitness:.2f} < {config.min_fitness}")
    if not rmse_after <= config.max_rmse_mm:
        reasons.append(f"point-to-plane RMSE {rmse_after:.1f} mm > {config.max_rmse_mm} mm")
    if n_corr and not noise_rms <= config.max_normalised_rms:
        reasons.append(
            f"residuals {noise_rms:.1f}x the {_noise_name(cloud_a, cloud_b)} noise model (limit "
            f"{config.max_normalised_rms}x): the surfaces do not fit (a wrong local minimum, "
            "a moving scene or a depth error)")
    if cond < config.min_conditioning:
        reasons.append(
            f"poorly conditioned overlap ({cond:.3g} < {config.min_conditioning}): "
            "the common surfaces leave a direction unconstrained (e.g. a single plane)"
        )
    if n_corr and rows.n_patches < config.min_patches:
        reasons.append(f"{rows.n_patches} surface patches of {config.information_patch_m} m "
                       f"< {config.min_patches}: too few to estimate the pair's uncertainty")
    if corr_mm > 1000.0 * config.max_correction_m or corr_deg > config.max_correction_deg:
        reasons.append(
            f"moved {corr_mm:.0f} mm / {corr_deg:.1f} deg from the initial guess (limit "
            f"{1000.0 * config.max_correction_m:.0f} mm / {config.max_correction_deg} deg)"
        )
    agrees = not reasons and not improvement >= config.min_improvement_chi2
    if agrees:
        reasons.append(
            f"no significant improvement on the current extrinsics: ICP moved "
            f"{corr_mm:.2f} mm / {corr_deg:.3f} deg, chi2 {improvement:.1f} < "
            f"{config.min_improvement_chi2} (6 dof) under its own uncertainty"
            + (" (depth scale unknown: a move a depth-scale error explains does not count)"
               if any(free_scale) else ""))
    if not np.all(np.isfinite(information)):
        reasons.append("information matrix not finite")
        agrees = False
    return PairRegistration(
        cam_a=cloud_a.camera,
        cam_b=cloud_b.camera,
        method=method,
        T_b_a=T,
        T_b_a_initial=T_b_a0,
        information=information,
        information_frame=INFORMATION_FRAME,
        fitness=float(fitness),
        inlier_rmse_mm=inlier_rmse_mm,
        rmse_before_mm=_rmse_mm(before),
        rmse_after_mm=rmse_after,
        conditioning=cond,
        n_correspondences=n_corr,
        correction_deg=corr_deg,
        correction_mm=corr_mm,
        accepted=not reasons,
        reason="; ".join(reasons) or None,
        time_s=time.perf_counter() - t_start,
        normalised_rms=noise_rms,
        improvement_chi2=improvement,
        n_patches=rows.n_patches,
        agrees=bool(agrees),
    )



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
        reason=reason,
        time_s=0.0 if t_start is None else time.perf_counter() - t_start,
    )


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


# --------------------------------------------------------------------------- fused cloud
def fuse_clouds(
    clouds: dict[str, CameraCloud],
    T_ref_cam: dict[str, np.ndarray],
    voxel_size: float = 0.005,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All cameras' clouds in the reference frame: ``points_ref`` (N,3) metres, ``colors`` (N,3)
    RGB [0,1] and ``camera_index`` (N,) into the cameras of ``clouds`` that have a
    ``T_ref_cam`` (in ``clouds`` order). Each camera is averaged per ``voxel_size`` voxel on its
    own (0 keeps every point), so every point keeps the camera it came from."""
    names = [c for c in clouds if c in T_ref_cam]
    pts, cols, idx = [], [], []
    for k, name in enumerate(names):
        cloud = clouds[name]
        p = transform_points(T_ref_cam[name], cloud.points)
        c = cloud.colors.astype(float)
        if voxel_size > 0 and p.shape[0]:
            p, (c,), _ = voxel_mean(p, voxel_size, c)
        pts.append(p)
        cols.append(c)
        idx.append(np.full(p.shape[0], k, dtype=np.int32))
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int32)
    return np.concatenate(pts), np.concatenate(cols), np.concatenate(idx)
