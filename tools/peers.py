"""Peer methods the benchmarks compare against (not part of the package).

- ``thesis_method``: the seed thesis's pipeline: OpenCV's default ArUco corners (no
  refinement), per-view PnP, a pose graph with fixed isotropic edge noise and plain least
  squares (its G2O/MATLAB setup), initialised like ours (it had hand-measured guesses).
- ``opencv_multiview``: OpenCV 5's ``cv2.calibrateMultiview`` with the intrinsics held fixed
  (``CALIB_USE_INTRINSIC_GUESS``; ``CALIB_FIX_INTRINSIC`` alone is ignored, api-notes.md).
"""

from __future__ import annotations

import cv2
import numpy as np

from rgbd_calib.board import Board
from rgbd_calib.calibrate import CalibrationConfig, calibrate
from rgbd_calib.dataset import FolderDataset
from rgbd_calib.detection import DetectionConfig
from rgbd_calib.geometry import invert_transform, make_transform
from rgbd_calib.graph import PoseGraphConfig


def thesis_config(refinement: str = "none") -> CalibrationConfig:
    return CalibrationConfig(
        detection=DetectionConfig(refinement=refinement),
        graph=PoseGraphConfig(kernel="none", reject_outliers=False,
                              estimate_default_sigmas=False),
        method="posegraph",
        edge_covariance=False,  # the thesis weighted every edge alike
    )


def thesis_method(dataset: FolderDataset, board: Board, cache_dir=None):
    """Per-view PnP + plain pose graph; returns ``{camera: T_ref_cam}``."""
    result = calibrate(dataset, board, thesis_config(), cache_dir=cache_dir)
    return {c: e.T_ref_cam for c, e in result.extrinsics.cameras.items()}


def opencv_multiview(dataset: FolderDataset, board: Board, detections) -> dict[str, np.ndarray]:
    """``cv2.calibrateMultiview`` on the same detections (``{(camera, frame): MarkerDetections}``).

    Raises RuntimeError when OpenCV fails outright (it needs every point of a view visible)."""
    cams = dataset.cameras
    frames = dataset.frames
    ids = board.ids
    n_pts = 4 * len(ids)
    obj = board.corners.reshape(-1, 3).astype(np.float32)
    index = {int(i): k for k, i in enumerate(ids)}
    image_points, mask = [], np.zeros((len(cams), len(frames)), np.uint8)
    for ci, c in enumerate(cams):
        per_frame = []
        for fi, f in enumerate(frames):
            pts = np.full((n_pts, 2), -1.0, np.float32)
            det = detections.get((c, f))
            if det is not None and len(det.ids) >= 4:
                for i, corners in zip(det.ids, det.corners_px):
                    k = index.get(int(i))
                    if k is not None:
                        pts[4 * k:4 * k + 4] = corners
                mask[ci, fi] = 1
            per_frame.append(pts)
        image_points.append(per_frame)
    obj_points = np.repeat(obj[None], len(frames), axis=0)
    sizes = [(dataset.rig.cameras[c].width, dataset.rig.cameras[c].height) for c in cams]
    Ks = [dataset.rig.cameras[c].K.astype(np.float64) for c in cams]
    dists = [np.zeros((1, 5)) for _ in cams]
    models = np.zeros(len(cams), np.uint8)  # pinhole
    try:
        rms, Ks, dists, Rs, Ts = cv2.calibrateMultiview(
            obj_points, image_points, sizes, mask, models, Ks, dists, None, None,
            flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    except cv2.error as exc:
        raise RuntimeError(f"calibrateMultiview failed: {str(exc).splitlines()[-1]}") from exc
    out = {}
    ref = dataset.rig.reference
    T_cam_cam0 = {c: make_transform(cv2.Rodrigues(np.asarray(R))[0], np.asarray(t).ravel())
                  for c, R, t in zip(cams, Rs, Ts)}
    T_ref_cam0 = T_cam_cam0[ref]
    for c in cams:
        out[c] = T_ref_cam0 @ invert_transform(T_cam_cam0[c])
    out["_rms"] = rms
    return out
