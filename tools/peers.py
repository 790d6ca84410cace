"""Peer methods the benchmarks compare against (not part of the package).

- ``thesis_method``: the seed thesis's pipeline: OpenCV's default ArUco corners (no
  refinement), per-view PnP, a pose graph with fixed isotropic edge noise and plain least
  squares (its G2O/MATLAB setup), initialised like ours (it had hand-measured guesses).
- ``opencv_multiview``: OpenCV 5's ``cv2.calibrateMultiview`` with the intrinsics held fixed
  (``CALIB_USE_INTRINSIC_GUESS``; ``CALIB_FIX_INTRINSIC`` alone is ignored, api-notes.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rgbd_calib.core.config import CalibrationConfig, DetectionConfig, PoseGraphConfig
from rgbd_calib.core.geometry import invert_transform, make_transform
from rgbd_calib.detect.markers import MarkerDetections
from rgbd_calib.model.board import Board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.pipelines.calibrate import CalibrationResult, calibrate


def thesis_config(refinement: str = "none", workers: int | None = None) -> CalibrationConfig:
    return CalibrationConfig(
        detection=DetectionConfig(refinement=refinement),
        graph=PoseGraphConfig(kernel="none", reject_outliers=False, estimate_default_sigmas=False),
        method="posegraph",
        edge_covariance=False,  # the thesis weighted every edge alike
        workers=workers,
    )


def thesis_method(
    dataset: FolderDataset, board: Board, cache_dir: Path | None = None, workers: int | None = None
) -> CalibrationResult:
    """Per-view PnP + plain pose graph. Its sigmas come from the fixed default edge noise
    (0.2 deg, 2 mm per edge), not from the data: the thesis reported none."""
    return calibrate(dataset, board, thesis_config(workers=workers), cache_dir=cache_dir)


@dataclass(frozen=True)
class MultiviewResult:
    """``cv2.calibrateMultiview`` output: ``T_ref_cam`` (4x4, metres) per camera and the RMS
    reprojection error (px) OpenCV reports."""

    T_ref_cam: dict[str, np.ndarray]
    rms_px: float
    views: int  # camera-frame pairs passed in the detection mask


def opencv_multiview(
    dataset: FolderDataset,
    board: Board,
    detections: dict[tuple[str, str], MarkerDetections],
    min_markers: int = 4,
) -> MultiviewResult:
    """``cv2.calibrateMultiview`` on the same detections as ours.

    Every marker corner of the (double-sided) board is one pattern point; corners a view does
    not see are ``(-1, -1)``; a view enters the detection mask with ``min_markers`` markers or
    more. Poses come back mapping camera 0 to camera i (``x_i = R_i x_0 + t_i``), i.e.
    ``T_cami_cam0``; they are re-expressed as ``T_ref_cam``.

    Raises RuntimeError when OpenCV raises (e.g. isolated cameras). It does not raise when it
    diverges: check ``rms_px`` (it needs every point of a view visible, api-notes.md)."""
    cams = dataset.cameras
    frames = dataset.frames
    index = {int(i): k for k, i in enumerate(board.ids)}
    n_pts = 4 * len(board.ids)
    obj = board.corners.reshape(-1, 3).astype(np.float32)
    image_points = []
    mask = np.zeros((len(cams), len(frames)), np.uint8)
    for ci, c in enumerate(cams):
        per_frame = []
        for fi, f in enumerate(frames):
            pts = np.full((n_pts, 2), -1.0, np.float32)
            det = detections.get((c, f))
            if det is not None and len(det.ids) >= min_markers:
                for i, corners in zip(det.ids, det.corners_px):
                    k = index.get(int(i))
                    if k is not None:
                        pts[4 * k : 4 * k + 4] = corners
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
            obj_points,
            image_points,
            sizes,
            mask,
            models,
            Ks,
            dists,
            None,
            None,
            flags=cv2.CALIB_USE_INTRINSIC_GUESS,
        )
    except cv2.error as exc:
        lines = [s for s in str(exc).splitlines() if s.strip()]
        raise RuntimeError(f"calibrateMultiview raised: {lines[-1] if lines else exc}") from exc
    T_cam_cam0 = {
        c: make_transform(
            cv2.Rodrigues(np.asarray(R, dtype=float))[0], np.asarray(t, dtype=float).ravel()
        )
        for c, R, t in zip(cams, Rs, Ts)
    }
    T_ref_cam0 = T_cam_cam0[dataset.rig.reference]
    T_ref_cam = {c: T_ref_cam0 @ invert_transform(T_cam_cam0[c]) for c in cams}
    return MultiviewResult(T_ref_cam, float(rms), int(mask.sum()))
