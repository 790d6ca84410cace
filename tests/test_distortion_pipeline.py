"""Lens distortion right everywhere: a rig rendered through a distorted lens, with the true
coefficients in rig.yaml, calibrates end to end like a pinhole rig.

One small render (thesis-line, 640x360, 8 frames) with the issue's lens (with this wide view,
fx ~315 px, undistorting moves the image corners by ~120 px) serves three checks: the
edge-fit corners are unbiased against the true distorted projection of the board corners,
depth back-projects through the model (board depth on the true plane, the depth-scale
estimate unbiased), and ``rgbd-calib calibrate`` with the depth stage on runs through every
output (extrinsics, report.json/html, exports, fused.ply) with every camera kept and the
pinhole rig's accuracy.
"""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbd_calib.cli.commands import app
from rgbd_calib.core.geometry import invert_transform, transform_error, transform_points
from rgbd_calib.depth.clouds import board_mask, estimate_depth_scale
from rgbd_calib.detect.markers import detect_markers
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset, read_color_image
from rgbd_calib.model.results import load_extrinsics
from rgbd_calib.synth.render import SynthParams, load_ground_truth, synthesize

DISTORTION = (0.08, -0.15, 5e-4, -5e-4, 0.03)  # the "mild unlisted" lens, now listed
PARAMS = dict(resolution=(640, 360), distortion=DISTORTION)
# Measured on this render (seed 3, 2488 edge-fit corners): median signed error per axis
# 0.0001 / 0.001 px, median |error| 0.04 px. Bounds: 0.02 px signed, 0.1 px absolute.
CORNER_SIGNED_PX = 0.02
CORNER_ABS_PX = 0.1
# Board depth (its camera's depth bias divided out) minus the true face plane along each ray,
# 156k pixels of 4 frames x 4 cameras: measured median -0.004 mm, median |.| 2.6 mm (D435
# noise and 1 mm counts at ~1.5 m); pinhole rays give median |.| 4.1 mm, p95 19 mm (model:
# 10 mm). Bound on the median 0.5 mm; the model must beat pinhole rays. Scale as test_depth.
PLANE_MEDIAN_MM = 0.5
SCALE_ATOL = 0.002
# End to end, --refine geometric, measured: the same rig rendered without distortion gives
# worst 0.10 mm / 0.005 deg; distorted with the true model 0.34 mm / 0.015 deg (every camera
# kept, error/sigma <= 1.8). Bounds at ~2.5x the distorted run, inside test_cli's 1 mm.
WORST_MM, WORST_DEG = 0.8, 0.04
# rig.yaml listing zeros for that lens (seed 3): default auto chooses fx fy cx cy k1 k2 p1 p2 k3,
# detects again, all 4 kept, worst 1.76 mm / 0.087 deg at sigmas of 1.2-2.0 mm / 0.045-0.069 deg
# (error / sigma <= 1.03 in translation, 1.3 in rotation: 8 frames do not pin a lens down);
# intrinsics fixed: 6.8 mm / 0.45 deg. (Before the bundle solved every camera jointly when
# refining intrinsics, the pose graph's sound cameras were solved first: 1.03 mm, but with
# rotation errors 2.5x the claimed sigma; seeds 4 and 5 take the joint solve either way.)
UNLISTED_WORST_MM = 2.0
UNLISTED_GAIN = 3.0  # fixed / auto worst translation error
UNLISTED_ERR_SIGMA = 3.0


@pytest.fixture(scope="module")
def distorted(tmp_path_factory):
    out = tmp_path_factory.mktemp("distortion") / "line"
    params = SynthParams(**PARAMS, rig_distortion="truth")
    synthesize(out, "thesis-line", 8, 3, thesis_board(), params, workers=2)
    return out, FolderDataset(out), load_ground_truth(out)


def test_the_render_is_distorted_and_rig_yaml_says_so(distorted):
    _, ds, gt = distorted
    for cam in ds.cameras:
        assert ds.rig.cameras[cam].has_distortion
        assert np.allclose(ds.rig.cameras[cam].dist[:5], DISTORTION)
        assert np.allclose(gt.intrinsics[cam].dist[:5], DISTORTION)


def test_edge_fit_corners_unbiased_under_distortion(distorted):
    """Detected corners (edge fit with the lens model) minus the true distorted projection of
    the board corners: no bias along either axis, sub-0.15 px scatter."""
    _, ds, gt = distorted
    board = thesis_board()
    errors = []
    for cam in ds.cameras:
        intr = ds.rig.cameras[cam]
        for frame in ds.frames:
            det = detect_markers(ds.read_color(cam, frame), board, intrinsics=intr)
            if len(det.ids) == 0:
                continue
            T_cam_board = invert_transform(gt.T_ref_cam[cam]) @ gt.T_ref_board[frame]
            truth = intr.project(transform_points(T_cam_board, board.object_points(det.ids)))
            errors.append((det.corners_px - truth).reshape(-1, 2)[det.refined.reshape(-1)])
    err = np.concatenate(errors)
    assert len(err) > 500
    assert np.all(np.abs(np.median(err, axis=0)) < CORNER_SIGNED_PX), np.median(err, axis=0)
    assert np.median(np.linalg.norm(err, axis=1)) < CORNER_ABS_PX


def _board_depth_error_mm(ds, gt, cam, frame, rays_of) -> np.ndarray:
    """Measured board depth (bias removed) minus the true face plane along each pixel's ray."""
    board = thesis_board()
    intr = ds.rig.cameras[cam]
    depth = ds.read_depth(cam, frame)
    T_cam_board = invert_transform(gt.T_ref_cam[cam]) @ gt.T_ref_board[frame]
    mask = board_mask(intr, T_cam_board, board, margin_m=0.0, dilate_px=-6.0)
    vs, us = np.nonzero(mask & (depth > 0))
    z = depth[vs, us] * intr.depth_scale / gt.depth_scale_bias[cam]
    rays = rays_of(intr, us, vs)
    n_cam = T_cam_board[:3, :3] @ np.array([0.0, 0.0, 1.0])
    # the face towards the camera: the front (z = 0) or the back (z = -thickness)
    face_z = 0.0 if n_cam @ T_cam_board[:3, 3] < 0 else -board.thickness
    p0 = transform_points(T_cam_board, np.array([[0.0, 0.0, face_z]]))[0]
    z_true = (n_cam @ p0) / (rays @ n_cam)
    return (z - z_true) * 1000.0


def test_depth_back_projects_through_the_lens_model(distorted):
    """Board depth lies on the true plane along the model's rays (pinhole rays do not), and the
    depth-scale estimate on distorted frames recovers each camera's bias."""
    _, ds, gt = distorted
    frames = [f for f in ds.frames][:4]
    model, pinhole = [], []
    for cam in ds.cameras:
        for frame in frames:
            model.append(_board_depth_error_mm(ds, gt, cam, frame,
                                               lambda K, u, v: K.rays(u, v)))
            pinhole.append(_board_depth_error_mm(
                ds, gt, cam, frame,
                lambda K, u, v: np.column_stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy,
                                                 np.ones(len(u))])))
    model_err, pinhole_err = np.concatenate(model), np.concatenate(pinhole)
    assert len(model_err) > 10_000
    assert abs(np.median(model_err)) < PLANE_MEDIAN_MM
    assert np.median(np.abs(model_err)) < np.median(np.abs(pinhole_err))
    board = thesis_board()
    for cam in ds.cameras:
        T_cam_board = {f: invert_transform(gt.T_ref_cam[cam]) @ T
                       for f, T in gt.T_ref_board.items()}
        est = estimate_depth_scale(ds, cam, T_cam_board, board)
        assert abs(est.factor - gt.depth_scale_bias[cam]) < SCALE_ATOL, (cam, est.factor)


def test_calibrate_end_to_end_with_distortion(distorted, tmp_path):
    """Through the CLI with the depth stage: every camera kept, pinhole-rig accuracy, every
    output written, no camera flagged for a model error."""
    path, ds, gt = distorted
    out = tmp_path / "out"
    result = CliRunner().invoke(
        app, ["calibrate", str(path), "--out", str(out), "--refine", "geometric",
              "--workers", "1"])
    assert result.exit_code == 0, result.output
    ex = load_extrinsics(out / "extrinsics.yaml")
    assert set(ex.cameras) == set(ds.cameras)
    for cam in ds.cameras:
        deg, mm = transform_error(ex.cameras[cam].T_ref_cam, gt.T_ref_cam[cam])
        assert mm < WORST_MM and deg < WORST_DEG, (cam, mm, deg)
    report = json.loads((out / "report.json").read_text())
    codes = {w["code"] for w in report["warnings"]}
    assert not codes & {"not_calibrated", "inconsistent_camera", "camera_model_error"}, codes
    assert report["pose_graph"]["model_error"] == []
    assert all(report["cameras"][c]["depth_scale_factor"] is not None for c in ds.cameras)
    for name in ("report.html", "fused.ply"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert any((out / "exports").iterdir())


def test_pipeline_detection_bends_the_edge_fit(distorted):
    """``detect_dataset`` (the pipeline's pool) hands each distorted camera's lens to the edge
    fit: its corners equal ``detect_markers(..., intrinsics=...)`` (before, the pool fitted
    straight lines along the curved edges whatever rig.yaml said)."""
    from rgbd_calib.core.config import DetectionConfig
    from rgbd_calib.detect.run import detect_dataset

    _, ds, _ = distorted
    board = thesis_board()
    dets = detect_dataset(ds, board, DetectionConfig(), None, workers=1)
    cam, frame = ds.cameras[1], ds.frames[2]
    intr = ds.rig.cameras[cam]
    gray = read_color_image(ds.color_path(cam, frame), intr.width, intr.height, gray=True)
    direct = detect_markers(gray, board, intrinsics=intr)
    straight = detect_markers(gray, board)
    np.testing.assert_allclose(dets[(cam, frame)].corners_px, direct.corners_px, atol=1e-9)
    assert np.abs(dets[(cam, frame)].corners_px - straight.corners_px).max() > 0.01


def test_unlisted_distortion_self_calibrated(distorted):
    """The same render with rig.yaml listing NO distortion (the D435 colour stream reports
    zeros): the default ``auto`` finds the camera-level model error, frees the intrinsics
    with the lens, detects the markers again with the refined lens, and lands near the
    truth; with the intrinsics held the same data is far off."""
    from dataclasses import replace

    from rgbd_calib.core.config import load_config
    from rgbd_calib.model.rig import Rig
    from rgbd_calib.pipelines.calibrate import calibrate

    path, ds, gt = distorted
    pinhole = Rig({c: replace(i, distortion=(0.0,) * 5) for c, i in ds.rig.cameras.items()},
                  ds.rig.reference)
    runs = {}
    for mode in ("fixed", "auto"):
        cfg = load_config(None, workers=1, refine="none", **{"bundle.intrinsics": mode})
        runs[mode] = calibrate(FolderDataset(path, pinhole), thesis_board(), cfg)

    def worst(result):
        return max(transform_error(e.T_ref_cam, gt.T_ref_cam[c])[1]
                   for c, e in result.extrinsics.cameras.items())

    auto = runs["auto"]
    ladder = auto.self_calibration
    assert ladder.chosen.distortion and ladder.redetected, [f.to_dict() for f in ladder.fits]
    assert len(auto.extrinsics.cameras) == len(ds.cameras)
    assert worst(auto) < UNLISTED_WORST_MM, worst(auto)
    assert worst(runs["fixed"]) > UNLISTED_GAIN * worst(auto), (worst(runs["fixed"]), worst(auto))
    for c, e in auto.extrinsics.cameras.items():
        if c != ds.rig.reference:
            t = transform_error(e.T_ref_cam, gt.T_ref_cam[c])[1]
            assert t < UNLISTED_ERR_SIGMA * e.sigma_translation_mm, (c, t, e.sigma_translation_mm)
