"""ArUco detection and the edge-fit corner refinement against exact synthetic ground truth.

Views are rendered with :mod:`rgbd_calib.synth.render` (exact area coverage of the board texture): a
640x360 camera at the origin, a textured wall behind, the board 0.5-0.85 m away (markers of
14-24 px), tilted up to 35 deg. Ground-truth corners are the board corners projected through
the true ``T_cam_board``. "Inward" is the offset of a detected corner towards its marker's
centre along the corner diagonal (OpenCV's refinements are biased inwards).
"""

from __future__ import annotations

import json
import pickle
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.geometry import make_transform, rotvec_to_matrix, transform_points
from rgbd_calib.detect.edge_fit import edge_residual_bound, refine_corners_edges
from rgbd_calib.detect.markers import (
    DetectionConfig,
    MarkerDetections,
    _gray_float,
    detect_markers,
    marker_pattern,
)
from rgbd_calib.model.board import BACK, FRONT, Board
from rgbd_calib.model.board_file import load_board
from rgbd_calib.synth import render as synth
from rgbd_calib.synth.scene import rect

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
WIDTH, HEIGHT = 640, 360
N_VIEWS = 8
NOISY = synth.SynthParams(blur_sigma_px=0.6, color_noise_dn=2.0)
NOISE_FREE = synth.SynthParams(blur_sigma_px=0.0, color_noise_dn=0.0)
MAX_EDGE_BIAS_PX = 0.03  # mean inward offset of edge-fitted corners
MAX_EDGE_MEAN_OFFSET_PX = 0.05  # mean offset per image axis
MIN_SUBPIX_BIAS_PX = 0.1  # OpenCV's SUBPIX corners sit at least this far inside, on average
MAX_EDGE_RMS_NOISY_PX = 0.06
GROSS_PX = 3.0  # a corner this far off is a wrong detection, not a refinement error


def make_camera(width: int = WIDTH, height: int = HEIGHT) -> synth.SynthCamera:
    f = 633.0 * width / 1280.0
    K = CameraIntrinsics(width, height, f, f, width / 2 + 1.7, height / 2 - 1.1)
    return synth.SynthCamera("cam", K, np.eye(4))


def random_board_pose(
    board: Board, rng: np.random.Generator, face: int, cam: synth.SynthCamera, z_range=(0.5, 0.85)
) -> np.ndarray:
    """``T_cam_board`` showing ``face`` to a camera at the origin looking along +z, fully in
    view, tilted up to 35 deg and rolled up to 25 deg."""
    # board axes in the camera: x right, y up, and the seen face's outward normal towards us
    base = np.diag([1.0, -1.0, -1.0]) if face == FRONT else np.diag([-1.0, -1.0, 1.0])
    centre_b = np.array(
        [
            (board.panel[0] + board.panel[1]) / 2,
            (board.panel[2] + board.panel[3]) / 2,
            -board.thickness / 2,
        ]
    )
    K = cam.intrinsics
    for _ in range(1000):
        axis = rng.normal(size=3)
        axis[2] = 0.0
        axis /= np.linalg.norm(axis)
        R = (
            rotvec_to_matrix(axis * np.radians(rng.uniform(0, 35)))
            @ rotvec_to_matrix([0, 0, np.radians(rng.uniform(-25, 25))])
            @ base
        )
        centre = np.array(
            [rng.uniform(-0.05, 0.05), rng.uniform(-0.03, 0.03), rng.uniform(*z_range)]
        )
        T = make_transform(R, centre - R @ centre_b)
        uv = K.project(transform_points(T, board.corners.reshape(-1, 3)))
        if np.all((uv > 8) & (uv < [K.width - 8, K.height - 8])):
            return T
    raise AssertionError("no board pose in view")


def render_views(
    board: Board, n: int, seed: int, faces=(FRONT, BACK), cam: synth.SynthCamera | None = None
):
    """Noise-free float renders (HxWx3 BGR in [0,1]) and their ``T_cam_board``."""
    cam = cam or make_camera()
    rng = np.random.default_rng(seed)
    wall = [rect((-6, -4, 3.0), (12, 0, 0), (0, 8, 0), (0.45, 0.5, 0.55), 7, 0.08)]
    background = synth.render_background(wall, cam, samples=1)
    model = synth._BoardModel(board)
    views = []
    for k in range(n):
        T = random_board_pose(board, rng, faces[k % len(faces)], cam)
        color, _ = synth.render_board(model, cam, background, T)
        views.append((color, T))
    return cam, views


def true_corners(
    board: Board, ids: np.ndarray, T_cam_board: np.ndarray, K: CameraIntrinsics
) -> np.ndarray:
    pts = transform_points(T_cam_board, board.object_points(ids).reshape(-1, 3))
    return K.project(pts).reshape(-1, 4, 2)


def corner_errors(det: MarkerDetections, board: Board, T: np.ndarray, K: CameraIntrinsics):
    """Offsets ``(N*4,2)`` of detected minus true corners and their inward components."""
    gt = true_corners(board, det.ids, T, K)
    off = det.corners_px - gt
    diag = gt - gt.mean(axis=1, keepdims=True)
    diag /= np.linalg.norm(diag, axis=-1, keepdims=True)
    return off.reshape(-1, 2), -(off * diag).sum(-1).reshape(-1)


def error_stats(images, board, config):
    offs, inward, n_gross = [], [], 0
    for image, T, K in images:
        det = detect_markers(image, board, config)
        off, inw = corner_errors(det, board, T, K)
        gross = np.linalg.norm(off, axis=1) > GROSS_PX
        n_gross += int(gross.sum())
        offs.append(off[~gross])
        inward.append(inw[~gross])
    offs, inward = np.concatenate(offs), np.concatenate(inward)
    return {
        "n": len(offs),
        "inward": float(inward.mean()),
        "mean": offs.mean(axis=0),
        "rms": float(np.sqrt((offs**2).sum(1).mean())),
        "gross": n_gross,
    }


@pytest.fixture(scope="module")
def board() -> Board:
    return load_board(CONFIGS / "board_thesis.yaml")


@pytest.fixture(scope="module")
def rendered(board):
    return render_views(board, N_VIEWS, seed=3)


def finished(rendered, params, seed=0):
    cam, views = rendered
    rng = np.random.default_rng(seed)
    return [(synth.finish_color(c, params, rng), T, cam.intrinsics) for c, T in views]


def test_edges_unbiased_on_noise_free_renders_subpix_is_not(board, rendered):
    images = finished(rendered, NOISE_FREE)
    edges = error_stats(images, board, DetectionConfig(refinement="edges"))
    subpix = error_stats(images, board, DetectionConfig(refinement="subpix"))
    report = f"edges {edges}, subpix {subpix}"
    assert edges["n"] > 300 and edges["gross"] == 0, report
    assert abs(edges["inward"]) < MAX_EDGE_BIAS_PX, report
    assert np.all(np.abs(edges["mean"]) < MAX_EDGE_MEAN_OFFSET_PX), report
    # documents OpenCV's bias: SUBPIX corners sit inside the marker
    assert subpix["inward"] > MIN_SUBPIX_BIAS_PX, report
    assert edges["rms"] < subpix["rms"], report


def test_edges_beat_subpix_on_noisy_renders(board, rendered):
    images = finished(rendered, NOISY, seed=1)
    edges = error_stats(images, board, DetectionConfig(refinement="edges"))
    subpix = error_stats(images, board, DetectionConfig(refinement="subpix"))
    none = error_stats(images, board, DetectionConfig(refinement="none"))
    report = f"edges {edges}, subpix {subpix}, none {none}"
    assert abs(edges["inward"]) < MAX_EDGE_BIAS_PX, report
    assert edges["rms"] < MAX_EDGE_RMS_NOISY_PX, report
    assert edges["rms"] < 0.5 * subpix["rms"], report
    assert none["inward"] > 0.3, report  # the unrefined contour corners: ~0.5 px inside


def test_every_corner_refined_or_flagged(board, rendered):
    images = finished(rendered, NOISY, seed=2)
    for image, T, K in images:
        det = detect_markers(image, board)
        off, _ = corner_errors(det, board, T, K)
        err = np.linalg.norm(off, axis=1).reshape(-1, 4)
        assert det.refined.mean() > 0.95
        assert np.all(err[det.refined] < 0.5), err[det.refined].max()


# --------------------------------------------------------------------------- flat test cards
def paste_marker(
    canvas: np.ndarray, dictionary: str, marker_id: int, x0: int, y0: int, cell_px: int
) -> np.ndarray:
    """Paste an axis-aligned marker whose top-left pixel is (x0, y0); returns its true
    corners (TL, TR, BR, BL) in OpenCV pixel coordinates (pixel centres at integers)."""
    cells = marker_pattern(dictionary, marker_id)
    img = np.kron(cells.astype(np.uint8) * 200 + 20, np.ones((cell_px, cell_px), np.uint8))
    n = img.shape[0]
    canvas[y0 : y0 + n, x0 : x0 + n] = img
    lo, hi = -0.5, n - 0.5
    return np.array(
        [[x0 + lo, y0 + lo], [x0 + hi, y0 + lo], [x0 + hi, y0 + hi], [x0 + lo, y0 + hi]]
    )


def card(board: Board, placements, blur: float = 0.8, shape=(240, 400)):
    canvas = np.full(shape, 220, np.uint8)
    truth = {}
    for marker_id, x0, y0 in placements:
        truth.setdefault(marker_id, []).append(
            paste_marker(canvas, board.dictionary, marker_id, x0, y0, 6)
        )
    image = canvas.astype(np.float32)
    if blur > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), truth


def test_foreign_and_duplicate_ids_are_set_aside(board):
    foreign = int(max(board.ids)) + 10  # in DICT_4X4_100 but not on the board
    image, truth = card(
        board, [(3, 20, 20), (5, 120, 20), (5, 220, 20), (foreign, 20, 120), (8, 120, 120)]
    )
    det = detect_markers(image, board)
    assert det.ids.tolist() == [3, 8]
    assert det.foreign_ids.tolist() == [foreign]
    assert det.duplicate_ids.tolist() == [5]
    for marker_id, corners in zip(det.ids, det.corners_px):
        np.testing.assert_allclose(corners, truth[int(marker_id)][0], atol=0.05)


def test_detections_round_trip_through_json(board):
    image, _ = card(board, [(3, 20, 20), (8, 120, 120)])
    det = detect_markers(image, board)
    back = MarkerDetections.from_dict(json.loads(json.dumps(det.to_dict())))
    np.testing.assert_array_equal(back.ids, det.ids)
    np.testing.assert_array_equal(back.corners_px, det.corners_px)
    np.testing.assert_array_equal(back.refined, det.refined)
    assert back.image_size == det.image_size == (400, 240)
    assert back.refinement == "edges"


def test_occluded_quiet_zone_falls_back_with_a_flag(board):
    """A dark object over the quiet zone along a marker's right edge: its corners are either
    still right or flagged unrefined, never silently wrong."""
    image, truth = card(board, [(3, 40, 40)], blur=0.0)
    x_edge = 40 + 36  # first column right of the marker
    image[50:70, x_edge : x_edge + 4] = 35  # covers the middle of the edge, one pixel from it
    image = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 0.8)
    det = detect_markers(np.clip(np.rint(image), 0, 255).astype(np.uint8), board)
    assert det.ids.tolist() == [3]
    err = np.linalg.norm(det.corners_px[0] - truth[3][0], axis=1)
    assert np.all(err[det.refined[0]] < 0.1), (err, det.refined)


def test_marker_at_image_border_keeps_a_valid_result(board):
    """Marker 3 starts 4 px from the image border, so part of its fitting band lies outside
    the image: its corners are still refined and accurate."""
    image, truth = card(board, [(3, 4, 60), (8, 200, 60)])
    det = detect_markers(image, board)
    assert det.ids.tolist() == [3, 8] and det.refined.all()
    for marker_id, corners in zip(det.ids, det.corners_px):
        np.testing.assert_allclose(corners, truth[int(marker_id)][0], atol=0.05)


def test_tiny_markers_keep_opencv_corners(board):
    image, _ = card(board, [(3, 20, 20), (8, 120, 20)])
    small = cv2.resize(image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    det = detect_markers(
        small, board, DetectionConfig(min_edge_length_px=30.0, min_marker_perimeter_px=20.0)
    )
    assert len(det) == 2 and not det.refined.any()


def distorted_view(rendered):
    """The first view through a barrel-distorting lens: (image, T_cam_board, intrinsics)."""
    cam, views = rendered
    K0 = cam.intrinsics
    K = CameraIntrinsics(
        K0.width, K0.height, K0.fx, K0.fy, K0.cx, K0.cy, (-0.25, 0.08, 0.0, 0.0, 0.0)
    )
    color, T = views[0]
    # distorted image: each distorted pixel samples the pinhole render at its ideal position
    grid = np.stack(np.meshgrid(np.arange(K.width), np.arange(K.height)), -1).astype(float)
    ideal = cv2.undistortPoints(grid.reshape(-1, 1, 2), K.K, K.dist, P=K.K).reshape(grid.shape)
    warped = cv2.remap(
        (color * 255).astype(np.float32),
        ideal[..., 0].astype(np.float32),
        ideal[..., 1].astype(np.float32),
        cv2.INTER_CUBIC,
    )
    image = synth.finish_color(
        warped / 255.0,
        synth.SynthParams(blur_sigma_px=0.5, color_noise_dn=1.0),
        np.random.default_rng(0),
    )
    return image, T, K


def test_edges_with_lens_distortion(board, rendered):
    """Barrel-distorted view: with the intrinsics the edge fit follows the curved edges."""
    image, T, K = distorted_view(rendered)
    plain = detect_markers(image, board)
    aware = detect_markers(image, board, intrinsics=K)

    def rms(det):
        gt = K.project(transform_points(T, board.object_points(det.ids).reshape(-1, 3)))
        d = det.corners_px.reshape(-1, 2) - gt
        return float(np.sqrt((d[det.refined.reshape(-1)] ** 2).sum(1).mean()))

    assert len(aware) > 15 and aware.refined.mean() > 0.9
    assert rms(aware) < 0.1 and rms(aware) <= rms(plain), (rms(aware), rms(plain))


def test_residual_bound_adapts_to_poor_images_only(board, rendered):
    """The edge residual bound: the fixed max_edge_residual where edges fit the model (renders:
    median relative residual 0.01-0.02, corners identical to the fixed bound), 1.5x the
    image's median where every edge fits worse (webcams: ~0.10, tests/test_real_corners.py),
    never above the cap."""
    config = DetectionConfig()
    assert edge_residual_bound(np.full(8, 0.015), config) == config.edges.max_edge_residual
    assert edge_residual_bound(np.full(8, 0.10), config) == pytest.approx(0.15)
    assert edge_residual_bound(np.full(8, 0.5), config) == config.edges.max_edge_residual_cap
    assert edge_residual_bound(np.zeros(0), config) == config.edges.max_edge_residual
    fixed = DetectionConfig(edge_residual_factor=None)
    for image, _, _ in finished(rendered, NOISY, seed=2):
        a, b = detect_markers(image, board), detect_markers(image, board, fixed)
        np.testing.assert_array_equal(a.corners_px, b.corners_px)
        np.testing.assert_array_equal(a.refined, b.refined)


def test_compiled_edge_fit_equals_the_numpy_reference(board, rendered):
    """The numba edge fit (default) gives the numpy reference's corners to 1e-6 px, with and
    without lens distortion (the curved edge model)."""
    views = [(img, None) for img, _, _ in finished(rendered, NOISY, seed=5)]
    image, _, K = distorted_view(rendered)
    views.append((image, K))
    config = DetectionConfig()
    n_corners = 0
    for image, intrinsics in views:
        det = detect_markers(image, board, DetectionConfig(refinement="none"))
        white = np.stack([marker_pattern(board.dictionary, int(i)) for i in det.ids])
        gray = _gray_float(image)
        ref, ok_ref = refine_corners_edges(
            gray, det.corners_px, white, config, intrinsics, compiled=False
        )
        fast, ok_fast = refine_corners_edges(gray, det.corners_px, white, config, intrinsics)
        assert np.array_equal(ok_ref, ok_fast)
        assert np.abs(fast - ref)[ok_ref].max() < 1e-6
        n_corners += int(ok_ref.sum())
    assert n_corners > 400


def _detect_in_worker(args):
    image, board, config = args
    return detect_markers(image, board, config).to_dict()


def test_detect_markers_runs_in_a_process_pool(board, rendered):
    fresh = load_board(CONFIGS / "board_thesis.yaml")  # never touched by the renderer
    images = finished(rendered, NOISY, seed=4)[:2]
    config = DetectionConfig()
    local = [detect_markers(img, fresh, config).to_dict() for img, _, _ in images]
    pickle.dumps(fresh)  # detect_markers must not cache unpicklable cv2 objects on the board
    with ProcessPoolExecutor(1) as pool:
        remote = list(pool.map(_detect_in_worker, [(img, fresh, config) for img, _, _ in images]))
    assert remote == local
