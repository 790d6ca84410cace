"""The renderer gives each camera the depth errors of its true depth model (issue 33 item 5).

A tiny ring (2 facing cameras, 640x360, 2 frame sets, a 3x3-marker board) rendered with a
disparity offset, its field over the image, a depth-scale bias and a depth-to-colour pose
error: on the board the depth images say what the true :class:`DepthModel` in
``ground_truth.yaml`` predicts, within the D435 noise; without the options the renders are
those of before.
"""

import cv2
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from rgbd_calib.cli.commands import app
from rgbd_calib.core.depth_model import DepthModel, distort_depth_image
from rgbd_calib.core.errors import ConfigError
from rgbd_calib.core.geometry import invert_transform, transform_points
from rgbd_calib.model.board import board_from_grid
from rgbd_calib.synth.images import _depth_errors
from rgbd_calib.synth.render import (
    SynthCamera,
    SynthParams,
    finish_depth,
    load_ground_truth,
    make_rig,
    synthesize,
)

GRID_BOARD = dict(dictionary="DICT_4X4_50", rows=3, cols=3, marker_length=0.09, separation=0.02,
                  thickness=0.006, front_first_id=0, back_first_id=9)  # fmt: skip
# at 640x360 f B is ~16 px m: disparity errors of up to 0.3 px move the board (1.5-2 m away)
# by 14-36 mm (measured), far beyond the noise of a median over the board (1-2 mm: D435
# sigma ~20 mm per pixel there, 2000-4000 pixels)
ERRORS = dict(depth_bias=0.004, depth_disparity_offset_px=0.3, depth_disparity_field_px=0.3)
POSE = dict(depth_disparity_offset_px=0.3, depth_disparity_field_px=0.3,
            depth_pose_error=(1.0, 10.0))
ZEROS = dict(depth_bias=0.0, depth_disparity_offset_px=0.0, depth_disparity_field_px=0.0,
             depth_pose_error=(0.0, 0.0))  # fmt: skip
MEDIAN_SE = 4.0  # a median residual over one board view within this many standard errors
MIN_PIXELS = 500  # board views with fewer valid pixels are not judged
BOARD_MARGIN_M = 0.015  # pixels this far inside the panel (a pose error shifts the image)


def _synth(path, **options):
    params = SynthParams(resolution=(640, 360), cameras=2, **options)
    return synthesize(path, "ring", 2, 11, board_from_grid(**GRID_BOARD), params, workers=1)


def _pngs(path, stream="*"):
    return {p.relative_to(path): p.read_bytes() for p in sorted(path.glob(f"*/{stream}/*.png"))}


@pytest.fixture(scope="module")
def rings(tmp_path_factory):
    root = tmp_path_factory.mktemp("depth_model")
    options = {"default": {}, "zeros": ZEROS, "errors": ERRORS, "pose": POSE}
    return {name: _synth(root / name, **o) for name, o in options.items()}


def _board_pixels(path, gt, name, frame, board):
    """The depth pixels that see the board well inside its panel: their rays ``(N,3)``
    (z = 1), measured depth (m) and the true z ``(N,)`` of the board point each sees, and the
    seen face's plane ``(n, p0)`` (camera frame; nominal board: no print options).

    With a depth-to-colour pose error ``T = T_true_measured`` a pixel's ray ``r`` sees the
    true points ``T (s r)``: that line is cut with the plane, so pixels near the panel's edge
    are judged by where they really look."""
    K, T = gt.intrinsics[name], gt.depth_model[name].T_true_measured()
    counts = cv2.imread(str(path / name / "depth" / f"{frame}.png"), cv2.IMREAD_UNCHANGED)
    T_cam_board = invert_transform(gt.T_ref_cam[name]) @ gt.T_ref_board[frame]
    n = T_cam_board[:3, 2]
    seen_face_z = 0.0 if n @ T_cam_board[:3, 3] < 0 else -board.thickness  # front or back
    p0 = T_cam_board[:3, 3] + seen_face_z * n
    v, u = np.nonzero(counts)
    rays = K.rays(u.astype(float), v.astype(float))
    s = ((p0 - T[:3, 3]) @ n) / (rays @ T[:3, :3].T @ n)
    hit = rays * s[:, None] @ T[:3, :3].T + T[:3, 3]  # true board point seen, camera frame
    xy = transform_points(invert_transform(T_cam_board), hit)[:, :2]
    x0, x1, y0, y1 = board.panel
    m = BOARD_MARGIN_M
    inside = (xy[:, 0] > x0 + m) & (xy[:, 0] < x1 - m) & (xy[:, 1] > y0 + m) & (xy[:, 1] < y1 - m)
    inside &= s > 0
    return rays[inside], counts[v, u][inside] * K.depth_scale, hit[inside, 2], (n, p0)


def _sigma_m(model, K, z_m, params=SynthParams()):
    """Each pixel's depth noise (m): the D435 sigma of its true depth, scaled with the depth
    by the model's scale, and the 1-count quantisation."""
    sigma = model.value("scale") * z_m**2 * params.depth_subpixel_px / (
        K.fx * params.depth_baseline_m)
    return np.sqrt(sigma**2 + K.depth_scale**2 / 12)


def _median_tolerance_m(sigma_m):
    """A median of ``N`` pixels of noise ``sigma_m`` has a standard error ``1.2533 sigma /
    sqrt(N)``; the bound is :data:`MEDIAN_SE` of them."""
    return MEDIAN_SE * 1.2533 * np.median(sigma_m) / np.sqrt(len(sigma_m))


def test_board_depth_is_what_the_true_model_predicts(rings):
    """(a) Without a pose error each board pixel reports ``measured_depth`` of the camera's
    true model (scale included) at the true depth, plus the unchanged D435 noise."""
    path = rings["errors"].path
    gt, board = load_ground_truth(path), board_from_grid(**GRID_BOARD)
    normalised, effects = [], []
    for frame in gt.T_ref_board:
        for name, K in gt.intrinsics.items():
            model = gt.depth_model[name]
            rays, z, t, _ = _board_pixels(path, gt, name, frame, board)
            if len(z) < MIN_PIXELS:
                continue
            predicted = model.measured_depth(rays[:, 0], rays[:, 1], t)
            sigma = _sigma_m(model, K, t)
            tol = _median_tolerance_m(sigma)
            effect, off = np.median(predicted - t), np.median(z - predicted)
            assert abs(off) < tol  # the rendered depth is the model's ...
            effects.append(abs(effect) / tol)
            normalised.append((z - predicted) / sigma)
    assert len(normalised) >= 3 and max(effects) > 10  # ... whose effect is plain to see
    r = np.concatenate(normalised)
    assert 0.9 < r.std() < 1.1, r.std()  # the noise is the D435 model's, as before


def test_the_true_model_undoes_a_pose_error(rings):
    """(a) With a depth-to-colour pose error too, the true model's ``correct_points`` puts the
    rendered board pixels back onto the true board plane; the raw depth is far off it."""
    path = rings["pose"].path
    gt, board = load_ground_truth(path), board_from_grid(**GRID_BOARD)
    raw_off = []
    for frame in gt.T_ref_board:
        for name, K in gt.intrinsics.items():
            model = gt.depth_model[name]
            rays, z, t, (n, p0) = _board_pixels(path, gt, name, frame, board)
            if len(z) < MIN_PIXELS:
                continue
            tol = _median_tolerance_m(_sigma_m(model, K, t))  # along the ray, >= along n
            off = np.median((model.correct_points(rays, z) - p0) @ n)
            raw = np.median((rays * z[:, None] - p0) @ n)
            assert abs(off) < tol
            raw_off.append(abs(raw) / tol)
    assert len(raw_off) >= 3 and max(raw_off) > 10


def test_the_pose_error_is_rendered_as_the_model_composes_it():
    """finish_depth's two steps (pose warp, then disparity field) are the model's
    ``distort_depth_image`` without its scale, and the noise follows the surface each pixel
    sees after the warp (here a step in depth)."""
    params = SynthParams(resolution=(160, 90), cameras=2, **POSE)
    cam = make_rig("ring", 4, params).cameras[1]
    truth = np.full((90, 160), 2.0)
    truth[:, 80:] = 3.0
    z, z_seen = _depth_errors(truth, cam)
    whole = distort_depth_image(cam.depth_model.with_values({"scale": 1.0}), truth,
                                cam.intrinsics)
    np.testing.assert_array_equal(z, whole)
    seen = distort_depth_image(DepthModel(cam.depth_model.focal_baseline_px_m).with_values(
        {p: cam.depth_model.value(p) for p in ("rx", "ry", "rz", "tx", "ty", "tz")}),
        truth, cam.intrinsics)
    np.testing.assert_array_equal(z_seen, np.where(z > 0, seen, 0.0))
    assert np.any((np.abs(z_seen - truth) > 0.5) & (z > 0))  # the step moved


def test_the_depth_errors_change_the_depth_images_only(rings):
    """(b) The options at 0 render the defaults byte for byte, and the depth errors leave the
    colour images, rig and board poses of the seed alone (a stream of their own)."""
    default, zeros = rings["default"], rings["zeros"]
    assert _pngs(zeros.path) == _pngs(default.path) and len(_pngs(default.path)) == 8
    assert (zeros.path / "ground_truth.yaml").read_bytes() == \
        (default.path / "ground_truth.yaml").read_bytes()
    raw = yaml.safe_load((default.path / "ground_truth.yaml").read_text())
    assert "depth_model" not in raw and "depth_pose_error" not in raw["params"]
    pose = rings["pose"]
    assert _pngs(pose.path, "color") == _pngs(default.path, "color")
    assert all(_pngs(pose.path, "depth")[k] != v for k, v in _pngs(default.path, "depth").items())
    for a, b in zip(default.board_poses, pose.board_poses, strict=True):
        np.testing.assert_array_equal(a, b)


def test_an_identity_model_renders_as_no_model():
    """(b) finish_depth skips an identity model: the same counts as a camera without one."""
    rig = make_rig("ring", 2, SynthParams(resolution=(320, 180), cameras=2))
    cam = rig.cameras[0]
    assert cam.depth_model is not None and cam.depth_model.is_identity
    bare = SynthCamera(cam.name, cam.intrinsics, cam.T_world_cam)
    truth = np.full((180, 320), 1.5)
    truth[:, :100] = np.inf
    a = finish_depth(truth, cam, SynthParams(), np.random.default_rng(3))
    b = finish_depth(truth, bare, SynthParams(), np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="depth_scale_bias"):
        SynthCamera("c", cam.intrinsics, cam.T_world_cam, 1.01, depth_model=cam.depth_model)


def test_ground_truth_round_trips_the_true_models(rings):
    """(c) ground_truth.yaml holds each camera's true model, the one the render used, and the
    settings; a file without the key loads with no models."""
    ds = rings["pose"]
    gt = load_ground_truth(ds.path)
    assert set(gt.depth_model) == {c.name for c in ds.rig.cameras}
    deg, mm = POSE["depth_pose_error"]
    for cam in ds.rig.cameras:
        loaded = gt.depth_model[cam.name]
        assert isinstance(loaded, DepthModel)
        assert loaded.to_dict() == cam.depth_model.to_dict()
        assert loaded.focal_baseline_px_m == pytest.approx(cam.intrinsics.fx * 0.05)
        assert loaded.terms == ("offset", "gradient", "curvature", "pose")
        v = loaded.vector()
        assert v[0] == 1.0 and np.all(np.abs(v[1:6]) <= 0.3) and np.any(v[1:6] != 0)
        assert np.all(np.abs(v[6:9]) <= deg) and np.all(np.abs(v[9:]) <= mm)
    raw = yaml.safe_load((ds.path / "ground_truth.yaml").read_text())
    assert raw["params"]["depth_pose_error"] == [1.0, 10.0]
    assert load_ground_truth(rings["default"].path).depth_model == {}
    biased = load_ground_truth(rings["errors"].path)  # the scale is the depth_scale_bias
    assert {c: m.value("scale") for c, m in biased.depth_model.items()} == \
        biased.depth_scale_bias


def test_depth_error_settings_are_checked():
    for bad in (dict(depth_disparity_offset_px=-0.1), dict(depth_disparity_field_px=np.nan),
                dict(depth_pose_error=(0.5, -1.0)), dict(depth_disparity_offset_px=50.0)):
        with pytest.raises(ConfigError, match="--depth-"):
            make_rig("ring", 0, SynthParams(resolution=(320, 180), cameras=2, **bad))


@pytest.mark.parametrize(
    "args, option",
    [(["--depth-disparity-offset", "-0.2"], "--depth-disparity-offset"),
     (["--depth-disparity-field", "-1"], "--depth-disparity-field"),
     (["--depth-pose-error", "-1", "0"], "--depth-pose-error"),
     (["--depth-pose-error", "0.5", "-2"], "--depth-pose-error")],
)
def test_cli_rejects_a_negative_depth_error(tmp_path, args, option):
    """(d) One line naming the option, a non-zero exit, nothing written."""
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "s"), "--frames", "1", *args])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and option in lines[0] and "Traceback" not in result.output, \
        result.output
    assert not (tmp_path / "s").exists()
