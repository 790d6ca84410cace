"""How well the cameras' depth agrees where their clouds overlap: the fused cloud's quality in
millimetres, before and after each camera's depth model (issue 33, item 4).

For an overlapping pair ``(a, b)`` at the final extrinsics, each of a's points is matched to
b's surface there (projected into b's image: the plane of b's points in a 5 x 5 pixel window
around, where b's ray through a's point meets it, b's normal; :class:`Surface`) and its
*signed surface distance* taken along that normal: positive when a's point lies beyond b's
surface as both cameras see it (a's depth reads long against b's). Over the pair: the
median (the pair's bias) and the p90 of |distance|, against what the depth noise predicts
(each camera's ``sigma_z`` projected on the normal, b's averaged over the window's points,
the p90 of that mixture of Gaussians; 0 for the median, with a standard error from the spread of
the medians of blocks of the image, since neighbouring pixels share their depth error).
"Before" is the same pair with each camera's depth model undone
(:meth:`~rgbd_calib.core.depth_model.DepthModel.measured_points`).

A pair is *off* when its bias is both beyond 3 standard errors and beyond ``bias_tol_mm``.
Each camera's own bias comes from all pairs at once (:func:`blame`), and a camera is named when
it is off beyond the same bounds."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from ..core.camera import CameraIntrinsics
from ..core.depth_model import DepthModel
from ..core.geometry import transform_points
from .clouds import CameraCloud

MAX_POINTS = 20_000  # a's points per pair (a random subset: the medians need no more)
BLOCKS = 8  # image blocks per side for the median's standard error
NORMAL_VOXEL_M = 0.02  # normals on this grid, over 3 of its cells (6 cm: planes, not noise)
EDGE_SIGMAS = 4.0  # a point or window this many noise sigmas off its surface is not on it
WINDOW = 2  # b's surface at a's point: the plane of a 5 x 5 pixel window of b
BIAS_TOL_MM = 1.0  # a pair whose bias is below this agrees, however significant


@dataclass(frozen=True)
class SurfaceDistances:
    """Signed surface distances of one pair in one state (before or after the models)."""

    n: int  # matched points
    median_mm: float  # signed: + = a's depth beyond b's surface
    median_se_mm: float  # standard error of the median (blocks of a's image)
    p90_mm: float  # p90 of |distance|

    def to_dict(self) -> dict[str, float | int]:
        return {"n": self.n, "median_mm": self.median_mm, "median_se_mm": self.median_se_mm,
                "p90_mm": self.p90_mm}


@dataclass(frozen=True)
class PairAgreement:
    """One overlapping pair: its surface distances after (and before) the depth models, the
    p90 the depth noise predicts, and whether it is off beyond the noise."""

    cam_a: str
    cam_b: str
    after: SurfaceDistances
    before: SurfaceDistances | None  # None: neither camera has a depth model to undo
    noise_p90_mm: float
    off: bool

    def to_dict(self) -> dict[str, Any]:
        return {"cam_a": self.cam_a, "cam_b": self.cam_b, "after": self.after.to_dict(),
                "before": self.before.to_dict() if self.before is not None else None,
                "noise_p90_mm": self.noise_p90_mm, "off": self.off}


@dataclass(frozen=True)
class FusedAgreement:
    """Every overlapping pair's agreement and the cameras the off pairs point to."""

    pairs: list[PairAgreement] = field(default_factory=list)
    off_cameras: list[str] = field(default_factory=list)  # named: their depth is off
    ambiguous: list[tuple[str, str]] = field(default_factory=list)  # off pairs, either camera
    # camera -> its depth's bias against the rig (mm, + = reads long), groups of 3+ cameras
    camera_bias_mm: dict[str, float] = field(default_factory=dict)

    def worst_bias_mm(self, before: bool = False) -> float | None:
        vals = [abs((p.before if before and p.before is not None else p.after).median_mm)
                for p in self.pairs]
        return max(vals) if vals else None

    def to_dict(self) -> dict[str, Any]:
        return {"pairs": [p.to_dict() for p in self.pairs],
                "worst_bias_mm": self.worst_bias_mm(),
                "worst_bias_before_mm": self.worst_bias_mm(before=True),
                "camera_bias_mm": dict(self.camera_bias_mm),
                "off_cameras": list(self.off_cameras),
                "ambiguous": [list(p) for p in self.ambiguous]}


def undone(cloud: CameraCloud, model: DepthModel | None) -> CameraCloud | None:
    """``cloud`` (corrected by ``model``) as the camera measured it, or None when there is
    no model to undo."""
    if model is None or model.is_identity:
        return None
    pts = model.measured_points(cloud.points.astype(float))
    ok = np.isfinite(pts[:, 0])
    return CameraCloud(cloud.camera, cloud.intrinsics, pts[ok].astype(np.float32),
                       cloud.colors[ok], cloud.sigma_z[ok], cloud.pixels[ok], cloud.stats,
                       cloud.frames)


MIN_POINTS = 30  # a cloud with fewer points (a depth model that left physics on all) has no surface


@dataclass(frozen=True)
class NormalGrid:
    """A camera's surface normals on a grid of :data:`NORMAL_VOXEL_M` (camera frame, m): the
    voxels' centres ``(M,3)`` and unit normals ``(M,3)`` facing the camera. Estimated once
    per camera (Open3D's ``estimate_normals``, the costliest call of the depth stage's
    surfaces) and carried through each change of the cloud's depth correction by
    :meth:`moved`."""

    centres: np.ndarray
    normals: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray) -> NormalGrid:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
            np.asarray(points, dtype=float))).voxel_down_sample(NORMAL_VOXEL_M)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * NORMAL_VOXEL_M,
                                                                  max_nn=30))
        pcd.orient_normals_towards_camera_location(np.zeros(3))
        return cls(np.asarray(pcd.points), np.asarray(pcd.normals))

    def moved(self, old: DepthModel | None, new: DepthModel | None) -> NormalGrid:
        """The grid of the same cloud corrected by ``new`` instead of ``old`` (None: as
        measured): each centre back to its measured depth on its ray and through ``new``
        (as :func:`~.overlap_models.recorrected` moves the points), each normal by the
        inverse transpose of the correction's derivative there
        (:meth:`~rgbd_calib.core.depth_model.DepthModel.warp_jacobian`)."""
        pts, n = self.centres, self.normals
        if old is not None and not old.is_identity:
            pts = old.measured_points(pts)
            n = np.einsum("nji,nj->ni", old.warp_jacobian(pts), n)  # J^T n
        if new is not None and not new.is_identity:
            n = np.linalg.solve(np.transpose(new.warp_jacobian(pts), (0, 2, 1)),
                                n[..., None])[..., 0]  # J^-T n
            z = pts[:, 2]
            rays = pts / np.where(np.isfinite(z) & (z > 0), z, np.nan)[:, None]
            pts = new.correct_points(rays, z)
        ok = np.isfinite(pts).all(axis=1) & np.isfinite(n).all(axis=1)
        pts, n = pts[ok], n[ok]
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        n *= np.where(np.einsum("ij,ij->i", n, pts) > 0, -1.0, 1.0)[:, None]  # facing the camera
        return NormalGrid(pts, n)


@dataclass(frozen=True)
class Surface:
    """A camera's cloud ready to be measured against. A point is matched to the cloud's
    surface through the cloud's own image: it is projected into it and the window of
    ``(2 WINDOW + 1)^2`` pixels around gives the surface there (:func:`surface_on_rays`; the
    normal of a 2 cm voxel grid, facing the camera: :class:`NormalGrid`). Chosen by pixel, not
    by 3D distance, so the choice does not depend on either camera's depth noise (nearest
    neighbours in 3D pick the noise that lies closest and read surfaces apart as nearer)."""

    cloud: CameraCloud
    points: np.ndarray  # (N,3) float64, camera frame
    index_image: np.ndarray  # (H,W) int: the point seen at each pixel, -1 none
    normal_tree: cKDTree
    normals: np.ndarray

    @classmethod
    def of(cls, cloud: CameraCloud, grid: NormalGrid | None = None) -> Surface:
        """``cloud``'s surface, its normals from ``grid`` (the cloud's :class:`NormalGrid`,
        estimated here when None)."""
        pts = cloud.points.astype(float)
        intr = cloud.intrinsics
        index = np.full((intr.height, intr.width), -1, dtype=np.int64)
        index[cloud.pixels[:, 1], cloud.pixels[:, 0]] = np.arange(len(pts))
        grid = grid if grid is not None else NormalGrid.of(pts)
        return cls(cloud, pts, index, cKDTree(grid.centres), grid.normals)

    def normals_at(self, points: np.ndarray) -> np.ndarray:
        return self.normals[self.normal_tree.query(points)[1]]

    def windows(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For points ``(M,3)`` in this camera's frame: the indices ``(M, (2W+1)^2)`` of the
        cloud's points in the window around each one's pixel (-1: none there) and which rows
        have at least half the window and lie in front of the camera."""
        intr = self.cloud.intrinsics
        front = points_cam[:, 2] > 0.05
        uv = np.full((len(points_cam), 2), -1e6)
        if front.any():
            uv[front] = intr.project(points_cam[front])
        u0, v0 = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
        offs = np.arange(-WINDOW, WINDOW + 1)
        du, dv = np.meshgrid(offs, offs)
        uu, vv = u0[:, None] + du.ravel(), v0[:, None] + dv.ravel()
        inside = (uu >= 0) & (uu < intr.width) & (vv >= 0) & (vv < intr.height)
        idx = np.where(inside, self.index_image[np.clip(vv, 0, intr.height - 1),
                                                np.clip(uu, 0, intr.width - 1)], -1)
        ok = front & (np.count_nonzero(idx >= 0, axis=1) * 2 >= idx.shape[1])
        return idx, ok


def surface_on_rays(points: np.ndarray, idx: np.ndarray, xy: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Where each window's surface meets the ray ``(x, y, 1)`` of ``xy`` ``(M,2)``: ``1/z`` of
    a plane is affine in the ray's ``x, y``, so it is fitted to the window's points (``idx``,
    -1 left out) and evaluated there. Returns the points ``(M,3)``, which rows have a fit and
    each window's largest depth residual off its plane (m)."""
    valid = idx >= 0
    return plane_on_rays(points[np.where(valid, idx, 0)], valid, xy)


def plane_on_rays(q: np.ndarray, valid: np.ndarray, xy: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`surface_on_rays` of window points ``q`` ``(M,K,3)`` (``valid`` ``(M,K)``)."""
    w = np.where(valid, 1.0 / np.where(valid, q[..., 2], 1.0), 0.0)
    dx = np.where(valid, q[..., 0] * w - xy[:, :1], 0.0)
    dy = np.where(valid, q[..., 1] * w - xy[:, 1:], 0.0)
    A = np.stack([valid.astype(float), dx, dy], axis=-1)  # (M,K,3), invalid rows zero
    AtA = np.einsum("mki,mkj->mij", A, A) + 1e-12 * np.eye(3)
    coef = np.linalg.solve(AtA, np.einsum("mki,mk->mi", A, w)[..., None])[..., 0]
    ok = coef[:, 0] > 1e-3
    z = 1.0 / np.where(ok, coef[:, 0], 1.0)
    # the window's worst point off its plane (m): a depth edge in the window if large
    off = np.where(valid, np.abs(w - np.einsum("mki,mi->mk", A, coef)), 0.0).max(axis=1)
    return np.column_stack([xy * z[:, None], z]), ok, off * z * z


@dataclass(frozen=True)
class Matches:
    """a's points matched to b's surface (:func:`match_points`): per match a's point index
    ``ia``, b's window ``idx`` ``(M,K)`` (-1: none), the signed distance ``d`` along b's normal
    (m, + = beyond b's surface), that normal ``normal_b`` (b's frame) and the noise ``sigma``
    of ``d`` (m)."""

    ia: np.ndarray
    idx: np.ndarray
    d: np.ndarray
    normal_b: np.ndarray
    sigma: np.ndarray


def match_points(a: CameraCloud, surf_b: Surface, T_b_a: np.ndarray, pick: np.ndarray,
                 max_distance_m: float) -> Matches:
    """a's points ``pick`` matched to b's surface (see :class:`Surface`): windows without a
    depth edge, points within ``max_distance_m`` and 4 noise sigmas (at least 1 cm) of it."""
    b = surf_b.cloud
    p = transform_points(T_b_a, a.points[pick].astype(float))
    idx, ok = surf_b.windows(p)
    p, idx, ia = p[ok], idx[ok], pick[ok]
    centre, ok, off = surface_on_rays(surf_b.points, idx, p[:, :2] / p[:, 2:])
    sigma_b = b.sigma_z[np.where(idx >= 0, idx, 0)].max(axis=1)
    ok &= off < EDGE_SIGMAS * sigma_b + 0.005  # no depth edge inside b's window
    p, idx, ia, centre, sigma_b = p[ok], idx[ok], ia[ok], centre[ok], sigma_b[ok]
    n_b = surf_b.normals_at(centre)  # facing camera b
    d = -np.einsum("ij,ij->i", p - centre, n_b)  # + = beyond b's surface
    # each camera's depth noise along the normal: its z noise along its ray, onto the normal
    ray_a = p - T_b_a[:3, 3]
    pa = a.points[ia].astype(float)
    cos_a = (np.abs(np.einsum("ij,ij->i", ray_a, n_b)) / np.linalg.norm(ray_a, axis=1)
             * np.linalg.norm(pa, axis=1) / pa[:, 2])
    cos_b = np.abs(np.einsum("ij,ij->i", centre, n_b)) / centre[:, 2]
    n_win = np.count_nonzero(idx >= 0, axis=1)
    sigma = np.hypot(a.sigma_z[ia] * cos_a, sigma_b * cos_b / np.sqrt(n_win))
    # else another surface (an occluder), a mixed pixel at an edge, an outlier
    keep = np.abs(d) < np.minimum(max_distance_m, np.maximum(EDGE_SIGMAS * sigma, 0.01))
    return Matches(ia[keep], idx[keep], d[keep], n_b[keep], sigma[keep])


def surface_distances(a: CameraCloud, surf_b: Surface, T_ref_a: np.ndarray,
                      T_ref_b: np.ndarray, max_distance_m: float,
                      rng: np.random.Generator) -> tuple[SurfaceDistances, float] | None:
    """a's points against b's surface: the distances and the noise-predicted p90 (mm), or
    None when fewer than 100 points match."""
    pick = (rng.choice(a.n_points, MAX_POINTS, replace=False) if a.n_points > MAX_POINTS
            else np.arange(a.n_points))
    m = match_points(a, surf_b, np.linalg.inv(T_ref_b) @ T_ref_a, pick, max_distance_m)
    if m.d.size < 100:
        return None
    # the p90 of |N(0, sigma_i)| over the points (near and far ones mixed): drawn once
    noise = float(np.percentile(np.abs(rng.standard_normal(m.sigma.size) * m.sigma), 90))
    return SurfaceDistances(int(m.d.size), 1e3 * float(np.median(m.d)),
                            1e3 * median_se(m.d, image_blocks(a.pixels[m.ia], a.intrinsics)),
                            1e3 * float(np.percentile(np.abs(m.d), 90))), 1e3 * noise


def image_blocks(pixels: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    """Each pixel's block of a :data:`BLOCKS` x :data:`BLOCKS` grid over the image (pixels of
    one block share their depth errors: the clusters of a median's or a fit's uncertainty)."""
    return (np.minimum(pixels[:, 0] * BLOCKS // max(intr.width, 1), BLOCKS - 1) * BLOCKS
            + np.minimum(pixels[:, 1] * BLOCKS // max(intr.height, 1), BLOCKS - 1))


def median_se(d: np.ndarray, block: np.ndarray) -> float:
    """Standard error of the median of ``d`` from the spread of its blocks' medians
    (:func:`image_blocks`)."""
    meds = np.array([np.median(d[block == k]) for k in np.unique(block)
                     if np.count_nonzero(block == k) >= 20])
    if meds.size < 3:
        return float(np.percentile(np.abs(d - np.median(d)), 90))  # too few blocks: wide
    return float(1.2533 * meds.std(ddof=1) / np.sqrt(meds.size))


def fused_agreement(clouds: dict[str, CameraCloud], T_ref_cam: dict[str, np.ndarray],
                    pairs: list[tuple[str, str]], models: dict[str, DepthModel],
                    max_distance_m: float = 0.05, bias_tol_mm: float = BIAS_TOL_MM,
                    seed: int = 0, grids: dict[str, NormalGrid] | None = None,
                    ) -> FusedAgreement:
    """The agreement of every overlapping pair of ``pairs`` at ``T_ref_cam``, the clouds as
    corrected by ``models`` (after) and with the models undone (before); ``grids`` the
    clouds' :class:`NormalGrid` where known (else estimated here), the models undone from
    them for the surfaces before."""
    rng = np.random.default_rng(seed)
    used = {x for p in pairs for x in p}
    named = [c for c in clouds if c in T_ref_cam and c in used
             and len(clouds[c].points) >= MIN_POINTS]
    grids = {c: (grids or {}).get(c) or NormalGrid.of(clouds[c].points) for c in named}
    surf = {c: Surface.of(clouds[c], grids[c]) for c in named}
    raw = {c: undone(clouds[c], models.get(c)) for c in named}
    raw = {c: r if r is None or len(r.points) >= MIN_POINTS else None for c, r in raw.items()}
    raw_surf = {c: Surface.of(r, grids[c].moved(models.get(c), None))
                for c, r in raw.items() if r is not None}
    out = []
    for a, b in pairs:
        if a not in surf or b not in surf:
            continue
        after = surface_distances(clouds[a], surf[b], T_ref_cam[a], T_ref_cam[b],
                                  max_distance_m, rng)
        if after is None:
            continue
        before = None
        if a in raw_surf or b in raw_surf:
            got = surface_distances(raw[a] or clouds[a], raw_surf.get(b, surf[b]), T_ref_cam[a],
                                    T_ref_cam[b], max_distance_m, rng)
            before = got[0] if got is not None else None
        dist, noise = after
        off = (abs(dist.median_mm) > bias_tol_mm
               and abs(dist.median_mm) > 3.0 * dist.median_se_mm)
        out.append(PairAgreement(a, b, dist, before, noise, off))
    cams, either, biases = blame(out, bias_tol_mm)
    return FusedAgreement(out, cams, either, biases)


def blame(pairs: list[PairAgreement], bias_tol_mm: float = BIAS_TOL_MM
          ) -> tuple[list[str], list[tuple[str, str]], dict[str, float]]:
    """Per camera its depth's bias against the rig, from the pairs' biases: least squares of
    ``bias_a - bias_b = median_ab`` (weights 1 / se^2, se at least 0.2 mm) in each connected
    group of three or more cameras, the group's median camera taken as right (most cameras'
    depth is). Named: cameras whose bias is beyond ``bias_tol_mm`` and 3 of its sigmas; an off
    pair in a group of two is ambiguous (either camera). Returns (named, ambiguous, biases)."""
    names = sorted({c for p in pairs for c in (p.cam_a, p.cam_b)})
    groups = _groups(names, pairs)
    named: list[str] = []
    either: list[tuple[str, str]] = []
    biases: dict[str, float] = {}
    for group in groups:
        inside = [p for p in pairs if p.cam_a in group]
        if len(group) < 3:
            either += [(p.cam_a, p.cam_b) for p in inside if p.off]
            continue
        idx = {c: k for k, c in enumerate(group)}
        A = np.zeros((len(inside) + 1, len(group)))
        y = np.zeros(len(inside) + 1)
        w = np.ones(len(inside) + 1)
        for r, p in enumerate(inside):
            A[r, idx[p.cam_a]], A[r, idx[p.cam_b]] = 1.0, -1.0
            y[r], w[r] = p.after.median_mm, 1.0 / max(p.after.median_se_mm, 0.2)
        A[-1, :] = 1.0  # gauge: sum 0 (shifted to the median below)
        sol, *_ = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)
        cov = np.linalg.pinv((A[:-1] * w[:-1, None]).T @ (A[:-1] * w[:-1, None]))
        sol = sol - np.median(sol)
        for c, k in idx.items():
            biases[c] = float(sol[k])
            sigma = float(np.sqrt(max(cov[k, k], 0.0)))
            if abs(sol[k]) > bias_tol_mm and abs(sol[k]) > 3.0 * sigma:
                named.append(c)
    return sorted(named), either, biases


def _groups(names: list[str], pairs: list[PairAgreement]) -> list[list[str]]:
    """Connected groups of cameras by their pairs."""
    left, out = set(names), []
    while left:
        todo, group = [left.pop()], set()
        while todo:
            c = todo.pop()
            group.add(c)
            for p in pairs:
                for x, y in ((p.cam_a, p.cam_b), (p.cam_b, p.cam_a)):
                    if x == c and y in left:
                        left.discard(y)
                        todo.append(y)
        out.append(sorted(group))
    return out
