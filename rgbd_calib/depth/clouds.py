"""Per camera: the static cloud, the depth-scale bias, voxel means and levels, the fused cloud.

    static_cloud          temporal median of depth, board and motion masked
    estimate_depth_scale  measured depth on the board face vs the calibrated pose
    voxel_level           voxel means with normals and their noise-model sigma (one ICP level)
    fuse_clouds           all cameras in the reference frame, per-point camera index
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ..core.camera import CameraIntrinsics
from ..core.config import DepthConfig
from ..core.depth_model import DepthModel
from ..core.errors import DatasetError
from ..core.geometry import invert_transform, transform_points
from ..model.board import Board
from ..model.dataset import FolderDataset
from .noise import DepthNoise, depth_noise, median_efficiency

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
    n_beyond_model: int = 0  # the depth model's correction beyond its physical bounds: dropped

    def to_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class DisparityMoment:
    """What a cloud's depths keep of their camera's disparity offset ``delta(x, y) = d0 + dx x
    + dy y + dxx x^2 + dxy x y + dyy y^2`` (px, at ray coordinates ``x = X/Z, y = Y/Z``;
    :class:`~rgbd_calib.core.depth_model.DepthModel`) when they were not corrected for it:
    the six coefficients' second moment about zero (6x6, px^2, in that order: the estimate's
    outer product plus its covariance), and ``focal_baseline_px_m`` (f B), which turns an
    offset into the relative depth error ``z delta / (f B)``."""

    focal_baseline_px_m: float
    second_moment: np.ndarray


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
    # the disparity offset its depths were not corrected for (calibrate registers clouds
    # divided by their depth-scale factor alone): every point of it off together; None: none
    disparity: DisparityMoment | None = None

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


# --------------------------------------------------------------------------- static clouds
def in_view(intr: CameraIntrinsics, points_cam: np.ndarray, margin_px: float,
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


def target_corners(board: Board, margin_m: float = 0.0) -> np.ndarray:
    """The eight corners ``(8,3)`` (board frame, m) of :func:`target_box` grown by
    ``margin_m`` on every side."""
    lo, hi = target_box(board)
    lo, hi = lo - margin_m, hi + margin_m
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                     for z in (lo[2], hi[2])])


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
    box_c = transform_points(T_cam_board, target_corners(board, margin_m))
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
    depth_model: DepthModel | None = None,
) -> CameraCloud:
    """The static scene of one camera: per-pixel temporal median of depth over up to
    ``config.clouds.max_frames`` frames sampled evenly (read one at a time).

    ``T_ref_board`` maps frame -> board pose (4x4, metres, reference frame; may be empty) and
    ``T_ref_cam`` is this camera's current extrinsics: together they place the board in each
    frame, and its pixels (grown by a margin) are left out of that frame's sample. Pixels whose
    depth spreads over frames by more than ``motion_k`` sigma_z (:func:`depth_noise`) are
    moving and dropped; so are depth edges and depths out of range. Depth is divided by
    ``depth_scale_factor`` (the camera's :func:`estimate_depth_scale` factor) before anything
    else; or, with ``depth_model`` (the camera's
    :class:`~rgbd_calib.core.depth_model.DepthModel`, its scale included), each median depth is
    corrected by the model as it is back-projected (the factor is then ignored; the pixels
    its bound holds are dropped and counted). Points are back-projected with the rig
    intrinsics (depth_scale from the rig); the intrinsics the rig marks as estimated
    (``rig.sigmas``) give the cloud its ``intrinsics_variance``, their sigma times
    ``config.uncertainty.lens_sigma_factor``."""
    config = config or DepthConfig()
    intr = dataset.rig.cameras[camera]
    frames = [f for f in dataset.frames if dataset.depth_path(camera, f) is not None
              and dataset.color_path(camera, f) is not None]
    if not frames:
        raise DatasetError(
            f"{dataset.path / camera}: no frame with both colour and depth; "
            "depth steps need <camera>/depth/<frame>.png aligned to colour"
        )
    picked = _even_sample(frames, config.clouds.max_frames)
    n, H, W = len(picked), intr.height, intr.width
    if depth_model is not None:
        depth_scale_factor = depth_model.value("scale")
    metres_per_count = intr.depth_scale / (1.0 if depth_model is not None else depth_scale_factor)
    depth = np.full((n, H, W), np.nan, dtype=np.float32)
    color = np.zeros((n, H, W, 3), dtype=np.uint8)
    masked = np.zeros((H, W), dtype=np.int32)
    T_cam_ref = invert_transform(T_ref_cam)
    for k, frame in enumerate(picked):
        z = dataset.read_depth(camera, frame).astype(np.float32) * np.float32(metres_per_count)
        z[z <= 0] = np.nan
        if frame in T_ref_board:
            m = board_mask(intr, T_cam_ref @ T_ref_board[frame], board,
                           config.clouds.board_mask_margin_m, config.clouds.board_mask_dilate_px)
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
    need = np.maximum(np.minimum(config.clouds.min_samples, unmasked), min(2, n))
    enough = (count >= need) & (count >= config.clouds.min_valid_fraction * unmasked)
    moving = enough & (n > 1) & (spread > config.clouds.motion_k * sigma1)
    with np.errstate(invalid="ignore"):
        in_range = (med >= config.clouds.min_range_m) & (med <= config.clouds.max_range_m)
    edge = np.zeros((H, W), dtype=bool)
    if config.clouds.edge_jump_sigmas is not None:
        disp = np.where(enough & ~moving, 1.0 / np.where(med > 0, med, np.nan), np.nan)
        thr = config.clouds.edge_jump_sigmas * noise.disparity_sigma
        with np.errstate(invalid="ignore"):
            jump_x = np.abs(np.diff(disp, axis=1)) > thr
            jump_y = np.abs(np.diff(disp, axis=0)) > thr
        edge[:, 1:] |= jump_x
        edge[:, :-1] |= jump_x
        edge[1:, :] |= jump_y
        edge[:-1, :] |= jump_y
    keep = enough & ~moving & in_range & ~edge
    # 4. colour: mean of the samples that agree with the median
    inlier = dev <= config.clouds.motion_k * sigma1[None]  # NaN compares False
    n_in = np.maximum(inlier.sum(axis=0), 1)
    rgb = np.zeros((H, W, 3), dtype=np.float32)
    for k in range(n):  # frame by frame: no float copy of the whole colour stack
        rgb += np.where(inlier[k, ..., None], color[k], 0).astype(np.float32)
    rgb /= 255.0 * n_in[..., None]
    # 5. back-projection
    n_kept, (vs, us, points) = (int(np.count_nonzero(keep)),  # before it drops any
                                _back_project(intr, keep, med, depth_model))
    sigma_z = sigma1[vs, us] * np.sqrt(median_efficiency(n_in[vs, us]) / n_in[vs, us])
    stats = CloudStats(
        n_frames=n,
        n_pixels=H * W,
        n_points=int(vs.size),
        n_board_masked=int(np.count_nonzero(masked)),
        n_no_depth=int(np.count_nonzero(~enough)),
        n_moving=int(np.count_nonzero(moving)),
        n_edge=int(np.count_nonzero(edge & enough & ~moving)),
        n_out_of_range=int(np.count_nonzero(enough & ~moving & ~edge & ~in_range)),
        n_beyond_model=n_kept - int(vs.size),
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
        intrinsics_variance={name: (config.uncertainty.lens_sigma_factor * sigma) ** 2
                             for name, sigma in dataset.rig.sigmas.get(camera, {}).items()},
    )


def _back_project(intr: CameraIntrinsics, keep: np.ndarray, med: np.ndarray,
                  depth_model: DepthModel | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns and camera-frame points (m) of the ``keep`` pixels of the median depth
    ``med`` (m), corrected by ``depth_model`` (pixels it has no answer for, or whose correction
    leaves the model's physical bounds (:meth:`~rgbd_calib.core.depth_model.DepthModel.
    beyond_bounds`), are dropped, and cleared in ``keep``)."""
    vs, us = np.nonzero(keep)
    rays = intr.rays(us, vs)
    z = med[vs, us].astype(float)
    if depth_model is None:
        return vs, us, rays * z[:, None]
    points = depth_model.correct_points(rays, z, drop_beyond_bounds=True)
    bad = ~np.isfinite(points[:, 0])
    keep[vs[bad], us[bad]] = False
    return vs[~bad], us[~bad], points[~bad]


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


@dataclass(frozen=True)
class BoardFacePixels:
    """The depth pixels of one view on the board face towards the camera: pixel ``us``,
    ``vs``, their measured depth (m), the depth of the face along each pixel's ray through the
    colour solve's board pose (m), the face plane ``n . p = d`` in the camera (unit normal,
    m)."""

    us: np.ndarray
    vs: np.ndarray
    z_measured: np.ndarray
    z_true: np.ndarray
    normal: np.ndarray
    distance_m: float


def board_face_pixels(raw: np.ndarray, intr: CameraIntrinsics, T_cam_board: np.ndarray,
                      board: Board, config: DepthConfig,
                      detected: bool = True) -> BoardFacePixels | None:
    """The pixels of depth image ``raw`` (counts) that see the board face towards the camera
    inside its panel minus ``scale_face_margin_m``, when the face is in front of the camera,
    seen within ``scale_max_view_angle_deg`` of its normal, with at least
    ``scale_min_points`` such pixels (else None). ``T_cam_board``: the board pose in the camera
    (4x4, m) from the calibration. Pixels whose depth-to-face ratio is off the view's median
    ratio by more than ``board_depth_gate`` are something else (a hand, a mixed edge pixel)
    and left out; the median itself may be off 1 (a board printed at the wrong scale must show
    as a common depth scale) unless the camera did not detect the board in this view
    (``detected`` False: placed by the other cameras, it may be hidden from this one), where
    a median off 1 by more than the gate means the face is hidden (None)."""
    mg = config.model_fit.scale_face_margin_m
    facing = _facing_face(board, T_cam_board)
    if facing is None:
        return None
    T, (x0, x1, y0, y1), z_face = facing  # a multi-face target: in the face's frame
    face = np.array([[x, y, z_face] for x, y in
                     ((x0 + mg, y0 + mg), (x1 - mg, y0 + mg), (x1 - mg, y1 - mg),
                      (x0 + mg, y1 - mg))])
    face_c = transform_points(T, face)
    if np.any(face_c[:, 2] <= 0.05):
        return None
    n_c = T[:3, 2]  # face normal (board z) in the camera
    p0 = face_c[0]
    to_face = face_c.mean(axis=0)
    cos_max = math.cos(math.radians(config.model_fit.scale_max_view_angle_deg))
    if abs(n_c @ to_face) / np.linalg.norm(to_face) < cos_max:
        return None
    uv = intr.project(face_c)
    u0 = max(int(np.floor(uv[:, 0].min())), 0)
    u1 = min(int(np.ceil(uv[:, 0].max())), intr.width - 1)
    v0 = max(int(np.floor(uv[:, 1].min())), 0)
    v1 = min(int(np.ceil(uv[:, 1].max())), intr.height - 1)
    if u0 > u1 or v0 > v1:
        return None
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
    z_meas = raw[vs, us].astype(float) * intr.depth_scale
    if np.count_nonzero(inside) < config.model_fit.scale_min_points:
        return None
    ratio = z_meas / np.where(inside, z_true, 1.0)
    centre = float(np.median(ratio[inside]))  # a gate about the face itself would cut the
    # noise of a camera whose depth reads 1-2 % short on one side only: a bias
    if not detected and abs(centre - 1.0) > config.model_fit.board_depth_gate:
        return None  # most of the face's pixels are something else: the board is hidden
    inside &= np.abs(ratio - centre) <= config.model_fit.board_depth_gate
    if np.count_nonzero(inside) < config.model_fit.scale_min_points:
        return None
    return BoardFacePixels(us[inside], vs[inside], z_meas[inside], z_true[inside], n_c.copy(),
                           float(n_c @ p0))


def board_faces(dataset: FolderDataset, camera: str, T_cam_board: dict[str, np.ndarray],
                board: Board, config: DepthConfig,
                detected: bool = True) -> list[tuple[str, BoardFacePixels]]:
    """``(frame, face pixels)`` of up to ``scale_max_frames`` of ``camera``'s views, sampled
    evenly (``T_cam_board``: frame -> board pose in the camera, 4x4 m, from the colour
    solve), each depth image read once; views with no usable face are left out
    (:func:`board_face_pixels`)."""
    intr = dataset.rig.cameras[camera]
    out = []
    for frame in _even_sample(sorted(T_cam_board), config.model_fit.scale_max_frames):
        raw = dataset.read_depth(camera, frame)
        if raw is None:
            continue
        face = board_face_pixels(raw, intr, np.asarray(T_cam_board[frame], dtype=float),
                                 board, config, detected)
        if face is not None:
            out.append((frame, face))
    return out


def face_sigma_z(noise: DepthNoise, intr: CameraIntrinsics, z_true: np.ndarray) -> np.ndarray:
    """1-sigma depth error (m) of board pixels at true depth ``z_true``: the noise model's and
    the depth unit's rounding."""
    return np.sqrt(noise.sigma_z(z_true) ** 2 + intr.depth_scale**2 / 12.0)


def estimate_depth_scale(
    dataset: FolderDataset,
    camera: str,
    T_cam_board: dict[str, np.ndarray],
    board: Board,
    config: DepthConfig | None = None,
    faces: list[tuple[str, BoardFacePixels]] | None = None,
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
    scatter over frames when that exceeds the weights. ``faces`` (:func:`board_faces`, when the
    caller read them already) replaces reading them here."""
    config = config or DepthConfig()
    if faces is None:
        faces = board_faces(dataset, camera, T_cam_board, board, config)
    intr = dataset.rig.cameras[camera]
    noise = depth_noise(intr, config)
    frames, factors, errors, n_points = [], [], [], 0
    for frame, face in faces:
        z_true = face.z_true
        z_meas = face.z_measured
        sigma = face_sigma_z(noise, intr, z_true)
        f, err = _fit_scale(z_meas, z_true, sigma, config.model_fit.scale_huber_k)
        frames.append(frame)
        factors.append(f)
        errors.append(err)
        n_points += int(z_true.size)
    if not factors:
        raise DatasetError(
            f"{dataset.path / camera}: no frame shows a board face to this camera's depth "
            f"(at least {config.model_fit.scale_min_points} pixels); cannot estimate its depth "
            "scale"
        )
    fk, sk = np.asarray(factors), np.asarray(errors)
    factor, sigma = _combine_frames(fk, sk, config.model_fit.scale_huber_k)
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
def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 key per point's voxel: equal keys, equal voxels (21 bits per axis,
    origin-shifted; a cloud spanning more than 2^21 voxels on an axis gets the rank of its
    voxel among the cloud's instead). Points must be finite."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    idx = np.floor(np.asarray(points, dtype=float) / voxel).astype(np.int64)
    idx -= idx.min(axis=0)
    if np.any(idx >= 1 << 21):
        return np.unique(idx, axis=0, return_inverse=True)[1].ravel().astype(np.int64)
    return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]


def voxel_mean(points: np.ndarray, voxel: float, *values: np.ndarray,
               ) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Average points (and per-point ``values``) per voxel; returns the means, the averaged
    values and the count per voxel."""
    if points.shape[0] == 0:
        return points.astype(float), [v.astype(float) for v in values], np.zeros(0, int)
    _, inverse, counts = np.unique(voxel_keys(points, voxel), return_inverse=True,
                                   return_counts=True)
    inverse = inverse.ravel()

    def mean(a: np.ndarray) -> np.ndarray:
        a = np.asarray(a, dtype=float)
        if a.ndim == 1:
            return np.bincount(inverse, a, counts.size) / counts
        return np.column_stack([np.bincount(inverse, a[:, j], counts.size) / counts
                                for j in range(a.shape[1])])

    return mean(points), [mean(v) for v in values], counts


def voxel_pick(points: np.ndarray, voxel: float) -> np.ndarray:
    """Index of one point per occupied voxel (the first)."""
    if points.shape[0] == 0:
        return np.zeros(0, dtype=int)
    _, first = np.unique(voxel_keys(points, voxel), return_index=True)
    return first


@dataclass(frozen=True)
class VoxelLevel:
    """One voxel level of a cloud: points, colours, normals, sigma_z along the viewing ray."""

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray
    sigma_z: np.ndarray


class NormalField:
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


def voxel_level(cloud: CameraCloud, keep: np.ndarray, voxel: float,
                normals: NormalField) -> VoxelLevel:
    pts, (col, var), counts = voxel_mean(
        cloud.points[keep].astype(float), voxel, cloud.colors[keep],
        cloud.sigma_z[keep].astype(float) ** 2,
    )
    # the mean of `counts` neighbouring pixels' depths: independent errors only one per
    # correlation_px^2 pixels (a voxel's pixels are neighbours in the image)
    independent = np.maximum(counts / cloud.correlation_px**2, 1.0)
    sigma = np.sqrt(var / independent)
    return VoxelLevel(pts, col, normals(pts), sigma)


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
