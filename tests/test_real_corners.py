"""Marker corners on real photos against the ChArUco saddle reference (issue 16, item 5):
Caliscope's webcam video (shared data), measured by ``tools/real_corner_bias.py``.

Bounds are the full measurement (docs/accuracy.md, "Corners on real photos": all 444 frames,
162 views with >= 6 saddle corners) with margin; the frames below are a few of those views,
from the sharpest camera (0) and the two where the fixed residual bound once rejected
nearly every edge (2, 3)."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest
from conftest import REPO, SHARED_DATA, shared_data_missing

from rgbd_calib.detect.corner_bias import (
    apply_homography,
    corner_components,
    fit_homography,
    predict_local,
    saddle_self_consistency,
)

DATA = SHARED_DATA / "caliscope-charuco-4cam"
FRAMES = {0: [84, 96], 2: [84, 96], 3: [84, 96]}

# measured on all views (edge-fit corners only): normal bias +0.05..+0.16 px per camera,
# +0.10 overall; scatter 0.10-0.12 px normal, 0.10 px tangent
EDGE_BIAS_PX = (-0.05, 0.30)
EDGE_SCATTER_PX = 0.20
MIN_EDGE_SET = 0.90  # share of corners the edge fit sets (measured 0.96; 0.30 with the fixed
#                      residual bound, 0.005 on camera 2)
CONTOUR_BIAS_PX = (-0.60, -0.30)  # OpenCV CONTOUR sits inside: measured -0.41..-0.49 px
SADDLE_FLOOR_RMS_PX = 0.35  # the reference predicting its own corners: measured 0.17-0.21
EDGE_POSE_MM = 3.0  # edge-fit PnP vs saddle PnP, median: measured 0.99 mm


def _tool():
    spec = importlib.util.spec_from_file_location("real_corner_bias",
                                                  REPO / "tools" / "real_corner_bias.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # (its dataclasses look their module up)
    spec.loader.exec_module(module)
    return module


# ----------------------------------------------------------------------------- pure maths
def test_homography_and_corner_components_recover_a_known_shift(rng):
    """A homography from noise-free points is exact; a marker grown by 0.2 px per edge and
    turned reads +0.2 normal and a tangent of the turn's sign."""
    H = np.array([[80.0, 5.0, 300.0], [-4.0, 75.0, 200.0], [0.05, -0.02, 1.0]])
    xy = rng.uniform(0, 1, size=(12, 2))
    np.testing.assert_allclose(fit_homography(xy, apply_homography(H, xy)) * 1.0, H, rtol=1e-8)
    square = np.array([[[0.0, 0.0], [30.0, 0.0], [30.0, 30.0], [0.0, 30.0]]])  # y down
    grown = square + 0.2 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    normal, tangent = corner_components(grown, square)
    np.testing.assert_allclose(normal, 0.2, atol=1e-12)
    np.testing.assert_allclose(tangent, 0.0, atol=1e-12)
    turned = square + 0.1 * np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # along corner order
    normal, tangent = corner_components(turned, square)
    np.testing.assert_allclose(tangent, 0.05, atol=1e-12)
    # a saddle grid seen through H: leave-one-out residuals vanish, predictions are exact
    grid = np.stack(np.meshgrid(np.arange(3.0), np.arange(4.0)), -1).reshape(-1, 2)
    px = apply_homography(H, grid)
    assert np.abs(saddle_self_consistency(grid, px, 2.0)).max() < 1e-8
    np.testing.assert_allclose(predict_local(grid, px, grid[:2], 2.0), px[:2], atol=1e-8)


# ----------------------------------------------------------------------------- real video
@pytest.fixture(scope="module")
def measured():
    if not DATA.is_dir():
        pytest.skip(shared_data_missing("caliscope-charuco-4cam"))
    tool = _tool()
    views = []
    for cam, frames in FRAMES.items():
        views += tool.run(DATA, [cam], frames=frames, methods=("edges", "contour"))
    return views, tool.summarise(views, ("edges", "contour"))["all"]


def test_every_frame_is_a_view(measured):
    views, summary = measured
    assert summary["views"] == sum(len(f) for f in FRAMES.values()), summary["views"]
    assert summary["saddle_floor"]["rms_px"] < SADDLE_FLOOR_RMS_PX, summary["saddle_floor"]


def test_edge_fit_sets_the_corners_and_keeps_the_views(measured):
    """Item 5: the residual bound adapts to the webcam images, so the edge fit sets nearly
    every corner and no view is lost as too_few_markers."""
    views, summary = measured
    s = summary["methods"]
    share = s["edges:set"]["corners"] / s["edges"]["corners"]
    assert share >= MIN_EDGE_SET, (share, summary["edge_fallback"])
    assert s["edges"]["pose_views"] == {"kept": len(views)}, s["edges"]["pose_views"]


def test_edge_and_contour_corner_bias_within_measured_bounds(measured):
    _, summary = measured
    e, c = summary["methods"]["edges:set"], summary["methods"]["contour"]
    assert EDGE_BIAS_PX[0] < e["normal_bias_px"] < EDGE_BIAS_PX[1], e
    assert e["normal_scatter_px"] < EDGE_SCATTER_PX and e["tangent_scatter_px"] < EDGE_SCATTER_PX
    assert abs(e["tangent_bias_px"]) < 0.05, e
    assert CONTOUR_BIAS_PX[0] < c["normal_bias_px"] < CONTOUR_BIAS_PX[1], c
    assert summary["methods"]["edges"]["pose_mm_median"] < EDGE_POSE_MM, summary["methods"]


# ----------------------------------------------------------------------------- model-error floor
REAL_CAMERA_FLOOR_PX = 0.5  # pose.model_error_px recommended for real cameras (default 0)
FLOOR_SETS = {99, 100, 101, 102, 104, 105, 106, 107, 111, 112, 113, 114, 115, 116}  # sync indices


def _caliscope_views(sync_indices) -> dict[tuple[str, str], np.ndarray]:
    """``(camera, sync index) -> image`` read from the videos through timestamps.csv."""
    import csv

    import cv2

    wanted: dict[int, dict[int, str]] = {}
    with open(DATA / "timestamps.csv") as f:
        for row in csv.DictReader(f):
            if int(row["sync_index"]) in sync_indices:
                wanted.setdefault(int(row["cam_id"]), {})[int(row["frame_index"])] = (
                    f"{int(row['sync_index']):06d}")
    images = {}
    for cam, frames in wanted.items():
        cap = cv2.VideoCapture(str(DATA / f"cam_{cam}.mp4"))
        for index in range(max(frames) + 1):
            ok, img = cap.read()
            if not ok:
                break
            if index in frames:
                images[(f"cam_{cam}", frames[index])] = img
        cap.release()
    return images


def test_model_error_floor_keeps_real_views_in(tmp_path):
    """Item 5 on real webcams (14 frame sets, Caliscope's intrinsics, ChArUco saddle quads):
    without the per-view floor the pose graph's outlier test flags half the edges (16 of 30;
    the PnP covariances hold only the corner noise, not the misfit a view's corners share);
    with the 0.5 px recommended for real cameras 3. With the camera model-error rule on (the
    default), 6 -> 2
    (measured on all 43 converted sets, first version of the floor: 35 -> 4 of 122 edges)."""
    if not DATA.is_dir():
        pytest.skip(shared_data_missing("caliscope-charuco-4cam"))
    sys.path.insert(0, str(REPO / "tools"))
    import bench_caliscope

    from rgbd_calib.core.config import CalibrationConfig, PoseConfig
    from rgbd_calib.detect.markers import detect_markers
    from rgbd_calib.model.board_file import load_board
    from rgbd_calib.solve.pose import BoardObservation, estimate_board_pose, pose_edges
    from rgbd_calib.solve.posegraph import PoseGraphConfig, calibrate_pose_graph

    board = load_board(REPO / "configs" / "board_charuco_caliscope.yaml")
    intrinsics, _ = bench_caliscope.caliscope()
    detections = {k: detect_markers(img, board) for k, img in _caliscope_views(FLOOR_SETS).items()}
    flagged = {}
    for floor_px in (0.0, REAL_CAMERA_FLOOR_PX):
        config = PoseConfig(model_error_px=floor_px)
        views = [estimate_board_pose(d, board, intrinsics[cam], config, cam, frame)
                 for (cam, frame), d in sorted(detections.items())]
        views = [v for v in views if isinstance(v, BoardObservation)]
        for model_error in (False, True):
            pg = calibrate_pose_graph(pose_edges(views, CalibrationConfig()), "cam_0",
                                      PoseGraphConfig(camera_model_error=model_error))
            flagged[floor_px, model_error] = sum(r.outlier for r in pg.residuals)
        assert len(pg.cameras) == 4
    n_edges = sum(np.isfinite(r.whitened_norm) for r in pg.residuals)
    assert flagged[0.0, False] > 0.4 * n_edges, (flagged, n_edges)  # measured 16 of 30
    assert flagged[0.5, False] <= 0.15 * n_edges, (flagged, n_edges)  # measured 3
    assert flagged[0.5, True] < flagged[0.0, True], flagged  # measured 6 -> 2
