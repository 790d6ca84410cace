"""The synthetic renderer is geometrically right: corners, depth, ground truth, dataset form."""

import cv2
import numpy as np
import pytest
import yaml

from rgbd_calib.core.errors import ConfigError
from rgbd_calib.core.geometry import invert_transform, is_rigid, transform_points
from rgbd_calib.model.board import FRONT, thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.synth.render import (
    SynthParams,
    _BoardModel,
    finish_color,
    finish_depth,
    load_ground_truth,
    make_rig,
    marker_visibility,
    render_background,
    render_board,
    sample_board_poses,
)

MEAN_OFFSET_PX = 0.05  # issue 2: detected minus true corners, mean per axis, noise-free


@pytest.fixture(scope="module")
def line_views():
    """Noise-free renders: thesis-line at 1280x720, 4 cameras x 4 board poses."""
    board = thesis_board()
    params = SynthParams(blur_sigma_px=0.0, color_noise_dn=0.0, depth_dropout=0.0)
    rig = make_rig("thesis-line", 3, params)
    poses = sample_board_poses(rig, board, 4, np.random.default_rng(5))
    model = _BoardModel(board)
    views = []
    for cam in rig.cameras:
        bg = render_background(rig.scene, cam)
        for T_world_board in poses:
            T_cam_board = invert_transform(cam.T_world_cam) @ T_world_board
            views.append((cam, T_cam_board, *render_board(model, cam, bg, T_cam_board)))
    return board, params, views


def test_noise_free_corners_match_projection(line_views):
    board, params, views = line_views
    detector = cv2.aruco.ArucoDetector(board.aruco_dict)
    offsets, inward = [], []
    for cam, T_cam_board, color, _ in views:
        img = finish_color(color, params, np.random.default_rng(0))
        corners, ids, _ = detector.detectMarkers(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
        if ids is None:
            continue
        for c, i in zip(corners, ids.ravel()):
            truth = cam.intrinsics.project(
                transform_points(T_cam_board, board.object_points([i])[0]))
            d = c.reshape(4, 2) - truth
            offsets.append(d)
            out = truth - truth.mean(axis=0)
            inward.append(-(d * out / np.linalg.norm(out, axis=1, keepdims=True)).sum(axis=1))
    offsets = np.concatenate(offsets)
    assert len(offsets) > 400
    mean = offsets.mean(axis=0)
    assert np.all(np.abs(mean) < MEAN_OFFSET_PX), mean
    # OpenCV's own (CORNER_REFINE_NONE) corners sit inside the true corner: its bias,
    # not the renderer's; measured ~0.5 px here (reported in docs/renderer.md)
    assert 0.2 < np.mean(np.concatenate(inward)) < 0.8


def test_board_depth_matches_plane_within_noise_model(line_views):
    board, params, views = line_views
    rng = np.random.default_rng(1)
    normalised = []
    for cam, T_cam_board, _, depth in views[:8]:
        counts = finish_depth(depth, cam, params, rng)
        K = cam.intrinsics
        v, u = np.nonzero(counts)
        z = counts[v, u] * K.depth_scale
        rays = np.column_stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(z)])
        # true depth of the board's front plane along each pixel ray
        n = T_cam_board[:3, :3] @ np.array([0.0, 0, 1])
        p0 = T_cam_board[:3, 3]
        t = (p0 @ n) / (rays @ n)
        x, y = (transform_points(invert_transform(T_cam_board), rays * t[:, None])[:, :2].T)
        x0, x1, y0, y1 = board.panel
        margin = 0.01
        on_board = (x > x0 + margin) & (x < x1 - margin) & (y > y0 + margin) & (y < y1 - margin)
        if np.dot(n, p0) > 0:  # camera sees the back face: skip (plane at -thickness)
            continue
        sel = on_board & (t > 0)
        sigma = t[sel] ** 2 * params.depth_subpixel_px / (K.fx * params.depth_baseline_m)
        sigma = np.sqrt(sigma**2 + K.depth_scale**2 / 12)  # + 1-count quantisation
        normalised.append((z[sel] - t[sel]) / sigma)
    r = np.concatenate(normalised)
    assert r.size > 10000
    assert abs(r.mean()) < 0.05 and 0.85 < r.std() < 1.15, (r.mean(), r.std())


def test_depth_scale_bias_is_applied():
    params = SynthParams(depth_dropout=0.0, depth_bias=0.006)
    rig = make_rig("ring", 2, params)
    cam = rig.cameras[1]
    truth = np.full((cam.intrinsics.height, cam.intrinsics.width), 2.0)
    counts = finish_depth(truth, cam, params, np.random.default_rng(0))
    ratio = np.median(counts[counts > 0]) * cam.intrinsics.depth_scale / 2.0
    assert ratio == pytest.approx(cam.depth_scale_bias, abs=6e-4)
    biases = [c.depth_scale_bias for c in rig.cameras]
    assert max(abs(b - 1) for b in biases) <= 0.006 and len(set(biases)) == len(biases)


@pytest.mark.parametrize("layout", ["thesis-line", "race", "ring"])
def test_every_board_pose_is_seen_by_two_cameras(layout):
    board = thesis_board()
    rig = make_rig(layout, 4, SynthParams())
    poses = sample_board_poses(rig, board, 12, np.random.default_rng(4))
    distances = []
    for T in poses:
        seen = [marker_visibility(board, c, T) for c in rig.cameras]
        assert sum(s >= 6 for s in seen) >= 2
        distances += [np.linalg.norm(T[:3, 3] - c.T_world_cam[:3, 3]) for c in rig.cameras]
    assert np.ptp(distances) > 0.3  # varied distances


def test_race_rows_see_opposite_faces():
    board = thesis_board()
    rig = make_rig("race", 0, SynthParams())
    poses = sample_board_poses(rig, board, 20, np.random.default_rng(0))
    for T in poses:
        normal = T[:3, :3] @ np.array([0.0, 0, 1])
        sides = {np.sign((c.T_world_cam[:3, 3] - T[:3, 3]) @ normal)
                 for c in rig.cameras if marker_visibility(board, c, T) >= 6}
        if len(sides) == 2:
            break
    else:
        pytest.fail("no board pose seen from both rows of the race")
    assert FRONT in board.faces


def test_synthesized_dataset_follows_the_folder_contract(small_race):
    path = small_race.path
    ds = FolderDataset(path)
    assert ds.cameras == [c.name for c in small_race.rig.cameras]
    assert ds.frames == ["000000", "000001", "000002"]
    summary = ds.summary()
    assert sum(len(m) for m in summary.missing.values()) > 0  # drop_rate=0.1 dropped some
    for cam in ds.cameras:
        for frame in ds.frames:
            if ds.color_path(cam, frame) is None:
                continue
            img = ds.read_color(cam, frame)
            depth = ds.read_depth(cam, frame)
            assert img.shape == (480, 848, 3) and img.dtype == np.uint8
            assert depth.shape == (480, 848) and depth.dtype == np.uint16
    gt = load_ground_truth(path)
    assert gt.reference == ds.rig.reference
    np.testing.assert_allclose(gt.T_ref_cam[gt.reference], np.eye(4), atol=1e-12)
    assert all(is_rigid(T) for T in gt.T_ref_cam.values())
    assert set(gt.T_ref_board) == set(ds.frames)
    assert any(abs(b - 1) > 1e-4 for b in gt.depth_scale_bias.values())
    raw = yaml.safe_load((path / "ground_truth.yaml").read_text())
    assert len(raw["T_ref_cam"][gt.reference]) == 4


def test_synthesize_refuses_a_non_empty_folder(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not empty"):
        from rgbd_calib.synth.render import synthesize

        synthesize(tmp_path / "x", "race", 1, 0, thesis_board())
    assert (tmp_path / "x" / "keep.txt").read_text() == "mine"


def test_compiled_cast_equals_the_numpy_reference():
    """scene.cast's numba kernels give the numpy version's hits bit for bit: a pinhole race
    camera's whole pixel grid (the row/column path; rectangles crossing the camera plane take
    the every-ray path) and a distorting lens's pixel grid (the bounding-box path)."""
    from rgbd_calib.synth.render import _grid, camera_rays
    from rgbd_calib.synth.scene import cast

    for params in (SynthParams(), SynthParams(distortion=(0.05, -0.1, 0.0003, 0.0002, 0.02))):
        rig = make_rig("race", 4, params)
        for cam in rig.cameras[:3]:
            K = cam.intrinsics
            vs, us = np.mgrid[0:K.height, 0:K.width].astype(float)
            grid = _grid(K, us.shape)
            assert (grid is None) == K.has_distortion
            rays = camera_rays(K, us.ravel(), vs.ravel())
            T_cam_world = invert_transform(cam.T_world_cam)
            fast = cast(rig.scene, T_cam_world, rays, grid=grid)
            ref = cast(rig.scene, T_cam_world, rays, grid=grid, compiled=False)
            assert np.any(fast.index >= 0)
            for name in ("depth", "index", "a", "b"):
                np.testing.assert_array_equal(getattr(fast, name), getattr(ref, name), name)
