"""An analytic RGB-D scene for depth-stage tests: textured rectangles ray-cast in numpy with
D435 depth noise (no rendering, a fraction of a second per camera)."""

from __future__ import annotations

import numpy as np

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.geometry import make_transform, rotvec_to_matrix
from rgbd_calib.depth import clouds as DC
from rgbd_calib.depth import noise as DN

INTR = CameraIntrinsics(width=320, height=180, fx=230.0, fy=230.0, cx=159.5, cy=89.5)
NOISE_FOCAL_PX = 640.0  # depth noise of a 848x480 D435 stream (a small image, realistic noise)
MEDIAN_GAIN = np.sqrt(np.pi / 2 / 15)  # the static cloud is a median of 15 frames


# --------------------------------------------------------------------------- analytic scene
def look_at(eye, target) -> np.ndarray:
    """T_world_cam of a camera at ``eye`` looking at ``target`` (z forward, world z up)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.column_stack([x, y, z]), np.asarray(eye, float))


# rectangles: origin, edge 1, edge 2 (world, metres); textured by their local coordinates
FLOOR = (np.array([-1.0, -1.0, 0.0]), np.array([4.0, 0.0, 0.0]), np.array([0.0, 3.0, 0.0]))
WALL = (np.array([3.0, -1.0, 0.0]), np.array([0.0, 3.0, 0.0]), np.array([0.0, 0.0, 2.0]))
SIDE = (np.array([-1.0, 2.0, 0.0]), np.array([4.0, 0.0, 0.0]), np.array([0.0, 0.0, 2.0]))
BOX = (np.array([1.2, 0.3, 0.0]), np.array([0.5, 0.0, 0.0]), np.array([0.0, 0.0, 0.4]))
BOX_SIDE = (np.array([1.2, 0.3, 0.0]), np.array([0.0, 0.4, 0.0]), np.array([0.0, 0.0, 0.4]))


def scene_cloud(name: str, T_world_cam: np.ndarray, rects, rng, textured: bool = True,
                ) -> DC.CameraCloud:
    """The cloud camera ``name`` sees of ``rects``: nearest hit per pixel, D435 depth noise
    (``d435_sigma_z``), colours a smooth texture of each rectangle's coordinates."""
    vs, us = np.mgrid[0:INTR.height, 0:INTR.width]
    rays_c = INTR.rays(us.ravel(), vs.ravel())
    R_wc, c = T_world_cam[:3, :3], T_world_cam[:3, 3]
    rays_w = rays_c @ R_wc.T
    best = np.full(rays_c.shape[0], np.inf)
    colour = np.zeros(rays_c.shape[0])
    for k, (o, e1, e2) in enumerate(rects):
        n = np.cross(e1, e2)
        denom = rays_w @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((o - c) @ n) / denom
        hit = c + t[:, None] * rays_w
        a = (hit - o) @ e1 / (e1 @ e1)
        b = (hit - o) @ e2 / (e2 @ e2)
        ok = (t > 0.2) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1) & (t < best)
        best[ok] = t[ok]
        ua, ub = a * np.linalg.norm(e1), b * np.linalg.norm(e2)
        tex = 0.5 + 0.2 * np.sin(9.0 * ua + k) * np.cos(7.0 * ub) + 0.1 * np.sin(23.0 * ua * ub)
        colour[ok] = tex[ok] if textured else 0.5
    keep = np.isfinite(best)
    z = best[keep]
    sigma = DN.d435_sigma_z(z, NOISE_FOCAL_PX) * MEDIAN_GAIN
    z = z + rng.normal(0.0, 1.0, z.size) * sigma
    points = rays_c[keep] * z[:, None]
    stats = DC.CloudStats(1, INTR.width * INTR.height, int(keep.sum()), 0, 0, 0, 0, 0)
    return DC.CameraCloud(
        camera=name, intrinsics=INTR, points=points.astype(np.float32),
        colors=np.repeat(colour[keep, None], 3, axis=1).astype(np.float32),
        sigma_z=sigma.astype(np.float32),
        pixels=np.column_stack([us.ravel()[keep], vs.ravel()[keep]]).astype(np.int32),
        stats=stats, frames=("000000",))


CAM_A = look_at([0.0, 0.0, 1.4], [1.8, 0.8, 0.3])
CAM_B = look_at([0.0, 1.6, 1.4], [1.8, 0.2, 0.3])


def nudge(T: np.ndarray, mm: float = 10.0, deg: float = 0.5) -> np.ndarray:
    return T @ make_transform(rotvec_to_matrix(np.radians(deg) * np.array([0.6, 0.0, 0.8])),
                              np.array([0.6, -0.8, 0.0]) * mm / 1000.0)


RECTS = (FLOOR, WALL, SIDE, BOX, BOX_SIDE)
