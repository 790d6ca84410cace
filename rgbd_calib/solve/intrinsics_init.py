"""Intrinsics from scratch: the first estimate of a camera whose rig.yaml gives only its size.

Each such camera is calibrated on its own from its board views (Zhang's method as OpenCV's
``cv2.calibrateCamera`` implements it: closed-form pinhole from the views' homographies, then
Levenberg-Marquardt on pinhole + Brown-Conrady ``k1 k2 p1 p2 k3``; Zhang, "A flexible new
technique for camera calibration", PAMI 2000). That estimate starts everything that needs a
camera model before the bundle adjustment (PnP, the pose graph), and is the prior of the joint
refinement in the bundle adjustment (``bundle.intrinsics: refine``, the usual prior sigmas
``bundle.intrinsics_prior_*`` around it), which sees every camera's views at once.

Why the usual prior, not a looser one (measured, docs/accuracy.md "Intrinsics from scratch"):
on the 4 unsynchronised webcams of shared/data/caliscope-charuco-4cam the cameras disagree
about where the board was by 1-3 px (held out), the bundle has one board pose per frame set,
and priors 10x wider let the intrinsics soak that up (cam_1: fx 780 -> 946 px, cy 388 -> 630
px; held-out cross-camera RMS 3.18 px); at the usual sigmas 2.99 px, and 1.06 instead of
1.37 px on cam_3. On a synthetic render both give fx within 0.2 % of the truth.

The measurements are the detected marker corners (a ChArUco board's are its saddle corners,
each once per view). A view gives one face of the board (the face with most corners), so its
points are planar, as Zhang's initialisation needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.errors import CalibrationError
from ..core.geometry import invert_transform, transform_points
from ..detect.markers import MarkerDetections
from ..model.board import Board
from ..model.rig import Rig

MIN_VIEWS = 4  # views with MIN_CORNERS corners a camera needs to be calibrated from scratch
MIN_CORNERS = 6
INIT_FLAGS = cv2.CALIB_FIX_K3  # k3 starts at 0; the bundle frees it when intrinsics_params has it
COVERAGE_GRID = (32, 18)  # sample points across, down, for the image fraction the corners reach


@dataclass(frozen=True)
class InitialIntrinsics:
    """One camera's intrinsics as first estimated from its own views alone."""

    camera: str
    intrinsics: CameraIntrinsics
    views: int  # views used
    corners: int  # corners used (each saddle / marker corner once per view)
    rms_px: float  # reprojection RMS of the single-camera calibration
    image_fraction: float  # of the image inside the convex hull of some view's corners

    def to_dict(self) -> dict[str, Any]:
        i = self.intrinsics
        return {"views": self.views, "corners": self.corners, "rms_px": self.rms_px,
                "image_fraction": self.image_fraction, "fx": i.fx, "fy": i.fy, "cx": i.cx,
                "cy": i.cy, "distortion": list(i.distortion)}


def view_points(det: MarkerDetections, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Board-frame points ``(N,3)`` (m) and their pixels ``(N,2)`` of one view: the corners of
    its markers on the face with most of them, each point once (a ChArUco board's quads share
    saddle corners); a multi-face target's in that face's frame (z = 0)."""
    if len(det) == 0:
        return np.zeros((0, 3)), np.zeros((0, 2))
    faces = np.array([board.faces[board.index_of[int(i)]] for i in det.ids])
    face = board.most_seen_face(faces)
    keep = faces == face
    obj = board.object_points(det.ids[keep]).reshape(-1, 3)
    if board.sheets:  # a multi-face target: in that face's own frame
        obj = transform_points(invert_transform(board.T_board_face(face)), obj)
    px = np.asarray(det.corners_px[keep], dtype=float).reshape(-1, 2)
    _, first = np.unique(np.round(obj, 6), axis=0, return_index=True)
    first = np.sort(first)
    return obj[first], px[first]


def image_fraction(views_px: list[np.ndarray], width: int, height: int) -> float:
    """Fraction of the image (on a grid of sample points) inside the convex hull of some
    view's corner pixels: 1 when the board reached everywhere, small when it stayed in one
    place, where a lens model is fitted and everywhere else extrapolated."""
    gx, gy = COVERAGE_GRID
    u, v = np.meshgrid((np.arange(gx) + 0.5) * width / gx, (np.arange(gy) + 0.5) * height / gy)
    samples = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float32)
    inside = np.zeros(len(samples), dtype=bool)
    for px in views_px:
        hull = cv2.convexHull(px.astype(np.float32))
        inside |= np.array([cv2.pointPolygonTest(hull, (float(a), float(b)), False) >= 0
                            for a, b in samples])
    return float(inside.mean())


def initialise_camera(camera: str, views: list[tuple[np.ndarray, np.ndarray]],
                      base: CameraIntrinsics) -> InitialIntrinsics:
    """Calibrate one camera from its views ``(board points (N,3) m, pixels (N,2))``;
    ``base`` gives the image size and the depth settings kept. Raises CalibrationError (what
    to do) when there are fewer than :data:`MIN_VIEWS` views of :data:`MIN_CORNERS` corners."""
    usable = [(o, p) for o, p in views if len(o) >= MIN_CORNERS]
    if len(usable) < MIN_VIEWS:
        raise CalibrationError(
            f"camera {camera!r} has no fx/fy/cx/cy in rig.yaml and only {len(usable)} board "
            f"view(s) with >= {MIN_CORNERS} corners (>= {MIN_VIEWS} needed to calibrate its "
            "intrinsics from scratch); record more views of the board with it, at several "
            "tilts, or give its intrinsics in rig.yaml"
        )
    size = (base.width, base.height)
    obj = [o.astype(np.float32) for o, _ in usable]
    img = [p.astype(np.float32).reshape(-1, 1, 2) for _, p in usable]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    try:
        rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, size, None, None, flags=INIT_FLAGS,
                                                 criteria=criteria)
    except cv2.error as exc:
        raise CalibrationError(
            f"camera {camera!r}: calibrating its intrinsics from scratch failed on "
            f"{len(usable)} views ({str(exc).strip().splitlines()[-1]}); record views with the "
            "board tilted towards the camera, or give its intrinsics in rig.yaml"
        ) from exc
    d = np.asarray(dist, dtype=float).ravel()[:5]
    intr = CameraIntrinsics(base.width, base.height, float(K[0, 0]), float(K[1, 1]),
                            float(K[0, 2]), float(K[1, 2]), tuple(map(float, d)),
                            base.depth_scale, base.depth_noise)
    if not (0 < intr.cx < base.width and 0 < intr.cy < base.height and intr.fx > 0
            and intr.fy > 0 and np.all(np.isfinite(d))):
        raise CalibrationError(
            f"camera {camera!r}: calibrating its intrinsics from scratch gave an impossible "
            f"model (fx {intr.fx:.0f}, cx {intr.cx:.0f}, cy {intr.cy:.0f} px) from "
            f"{len(usable)} views; record more views at several tilts and distances, or give "
            "its intrinsics in rig.yaml"
        )
    return InitialIntrinsics(camera, intr, len(usable), int(sum(len(o) for o in obj)),
                             float(rms), image_fraction([p for _, p in usable], *size))


def initialise_intrinsics(detections: dict[tuple[str, str], MarkerDetections], board: Board,
                          rig: Rig) -> dict[str, InitialIntrinsics]:
    """The first intrinsics of every camera of ``rig.unknown_intrinsics`` from its views in
    ``detections`` (``(camera, frame) -> markers``)."""
    out = {}
    for cam in sorted(rig.unknown_intrinsics):
        views = [view_points(det, board) for (c, _), det in sorted(detections.items())
                 if c == cam]
        out[cam] = initialise_camera(cam, views, rig.cameras[cam])
    return out
