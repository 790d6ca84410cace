"""Where the report draws things (numpy only): the display frame of the top and side views,
camera frusta, board outlines and the rig's size, all in the reference frame (m).
"""

from __future__ import annotations

from typing import Any

import numpy as np


def display_frame(report: dict[str, Any]) -> np.ndarray:
    """Rows ``(e1, e2, up)``: the axes of the top and side views, in the reference frame.

    ``up`` is minus the mean of the cameras' image-down (y) axes (cameras are mounted roughly
    upright); ``e1`` is the horizontal direction along which the cameras spread most."""
    Ts = [
        np.asarray(c["T_ref_cam"], float)
        for c in report["cameras"].values()
        if c["T_ref_cam"] is not None
    ]
    ys = np.array([T[:3, 1] for T in Ts])
    up = -ys.mean(0)
    if np.linalg.norm(up) < 0.3:
        centres = np.array([T[:3, 3] for T in Ts])
        _, _, vt = np.linalg.svd(centres - centres.mean(0))
        up = vt[2]
    up /= np.linalg.norm(up)
    pts = np.array(
        [T[:3, 3] for T in Ts]
        + [np.asarray(b["T_ref_board"], float)[:3, 3] for b in report["board_views"]]
    )
    flat = pts - np.outer(pts @ up, up)
    flat -= flat.mean(0)
    _, _, vt = np.linalg.svd(flat)
    e1 = vt[0] - (vt[0] @ up) * up
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(up, [0.0, 0.0, 1.0]) if abs(up[2]) < 0.9 else np.cross(up, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    if e1[0] < 0 or (abs(e1[0]) < 1e-9 and e1[1] < 0):
        e1 = -e1
    e2 = np.cross(up, e1)
    return np.array([e1, e2, up])


def frustum(cam: dict[str, Any], depth_m: float) -> np.ndarray:
    """Centre and the 4 image-corner rays at ``depth_m`` of a camera, reference frame (5,3)."""
    intr = cam["intrinsics"]
    T = np.asarray(cam["T_ref_cam"], float)
    uv = [(0, 0), (intr["width"], 0), (intr["width"], intr["height"]), (0, intr["height"])]
    rays = (
        np.array(
            [[(u - intr["cx"]) / intr["fx"], (v - intr["cy"]) / intr["fy"], 1.0] for u, v in uv]
        )
        * depth_m
    )
    return np.vstack([T[:3, 3], rays @ T[:3, :3].T + T[:3, 3]])


def board_outline(report: dict[str, Any], T_ref_board: np.ndarray) -> np.ndarray:
    """The 4 corners (4,3) of the seen marker extent at ``T_ref_board``, reference frame."""
    ext = report["board"]["extent_m"] or [0.0, 0.3, 0.0, 0.3]
    x0, x1, y0, y1 = ext
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    return corners @ T_ref_board[:3, :3].T + T_ref_board[:3, 3]


def rig_size(report: dict[str, Any]) -> float:
    """Largest axis span (m) of the calibrated camera centres, at least 0.3 m."""
    centres = np.array(
        [
            np.asarray(c["T_ref_cam"], float)[:3, 3]
            for c in report["cameras"].values()
            if c["T_ref_cam"] is not None
        ]
    )
    span = float(np.ptp(centres, axis=0).max()) if len(centres) > 1 else 1.0
    return max(span, 0.3)
