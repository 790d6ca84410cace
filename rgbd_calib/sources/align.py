"""librealsense's calibration conventions, and depth aligned to colour the way it does it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.errors import DatasetError


def extrinsics_matrix(rotation: Sequence[float], translation: Sequence[float]) -> np.ndarray:
    """``T_to_from`` (4x4, metres) of a librealsense ``rs2_extrinsics`` from->to.

    librealsense stores ``rotation`` column-major (rs_sensor.h; realsense-ros copies it
    verbatim into its Extrinsics message), so the 9 numbers are R's columns, not its rows."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(rotation, dtype=float).reshape(3, 3).T
    T[:3, 3] = np.asarray(translation, dtype=float)
    return T


def distortion_from_realsense(model: str, coeffs: Sequence[float], where: str) -> tuple:
    """OpenCV ``k1 k2 p1 p2 k3`` from a librealsense distortion model.

    librealsense orders Brown-Conrady coefficients ``[k1, k2, p1, p2, k3]`` (rs_types.h), the
    OpenCV order. D400 colour streams report "inverse Brown-Conrady" with coefficients that
    realsense-ros publishes unchanged as ``plumb_bob`` (and librealsense PR #13833 argues they
    are forward Brown-Conrady): they are passed through as the OpenCV model. Modified
    Brown-Conrady differs from OpenCV only in second-order tangential terms."""
    name = model.split(".")[-1]
    if name == "none":
        return (0.0,) * 5
    if name in ("brown_conrady", "inverse_brown_conrady", "modified_brown_conrady"):
        return tuple(float(c) for c in list(coeffs)[:5])
    raise DatasetError(
        f"{where}: colour distortion model {name!r} is not a Brown-Conrady model; "
        "rgbd-calib supports D400 colour streams only"
    )


def align_depth_to_color(
    depth: np.ndarray,
    depth_intr: CameraIntrinsics,
    color_intr: CameraIntrinsics,
    T_color_depth: np.ndarray,
    depth_scale: float,
) -> np.ndarray:
    """Depth counts ``(H_d,W_d)`` uint16 re-rendered in the colour camera ``(H_c,W_c)``.

    ``T_color_depth`` (4x4, metres) maps depth-camera points into the colour camera. Follows
    librealsense's ``align_z_to_other`` (src/proc/align.cpp): each depth pixel's footprint,
    its corners at +-0.5 px deprojected at its depth, is projected into the colour image and
    every colour pixel it covers takes the nearest depth (z-buffer). 0 = no depth."""
    depth = np.asarray(depth)
    out_w, out_h = color_intr.width, color_intr.height
    if same_geometry(depth_intr, color_intr, T_color_depth):
        return depth.astype(np.uint16, copy=True)
    v, u = np.nonzero(depth)
    counts = depth[v, u].astype(np.uint16)
    z = counts * float(depth_scale)

    def corner_pixels(offset: float) -> np.ndarray:
        uv = np.column_stack([u + offset, v + offset]).astype(float)
        xy = depth_intr.rays(uv[:, 0], uv[:, 1])[:, :2]
        p_depth = np.column_stack([xy * z[:, None], z])
        p_color = p_depth @ T_color_depth[:3, :3].T + T_color_depth[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.trunc(color_intr.project(p_color) + 0.5)

    x0, y0 = corner_pixels(-0.5).T
    x1, y1 = corner_pixels(0.5).T
    ok = (x0 >= 0) & (y0 >= 0) & (x1 < out_w) & (y1 < out_h) & (x1 >= x0) & (y1 >= y0)
    x0, y0, x1, y1, counts = (a[ok].astype(np.int64) for a in (x0, y0, x1, y1, counts))
    flat = np.full(out_w * out_h, np.iinfo(np.uint16).max, dtype=np.uint16)
    w, h = x1 - x0, y1 - y0
    for dy in range(int(h.max(initial=-1)) + 1):
        for dx in range(int(w.max(initial=-1)) + 1):
            sel = (dx <= w) & (dy <= h)
            np.minimum.at(flat, (y0[sel] + dy) * out_w + x0[sel] + dx, counts[sel])
    flat[flat == np.iinfo(np.uint16).max] = 0
    return flat.reshape(out_h, out_w)


def same_geometry(a: CameraIntrinsics, b: CameraIntrinsics, T_b_a: np.ndarray) -> bool:
    """Depth already in colour geometry: alignment is the identity (no resampling)."""
    same_k = (a.width, a.height) == (b.width, b.height) and np.allclose(
        [a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=0, atol=1e-6
    )
    n = max(a.dist.size, b.dist.size)
    same_d = np.allclose(np.pad(a.dist, (0, n - a.dist.size)), np.pad(b.dist, (0, n - b.dist.size)))
    return bool(same_k and same_d and np.allclose(T_b_a, np.eye(4), atol=1e-9))
