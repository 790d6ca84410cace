"""Per-view board pose: exact recovery, accuracy on noisy renders, an honest covariance, gates.

Views are rendered with :mod:`rgbd_calib.synth` as in ``test_detection.py``: a 640x360 camera at
the origin, the board 0.5-0.85 m away showing its front or its back. The pose error of a view is
``xi = Log(T_true^-1 T_est)`` (right perturbation, ``[omega, v]``), the convention of the
covariance (GTSAM Pose3, board/body frame).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.config import DetectionConfig
from rgbd_calib.core.geometry import (
    invert_transform,
    make_transform,
    matrix_to_rotvec,
    rotvec_to_matrix,
    skew,
    transform_error,
    transform_points,
)
from rgbd_calib.detect.markers import MarkerDetections, detect_markers
from rgbd_calib.model.board import BACK, FRONT, Board
from rgbd_calib.model.board_file import load_board
from rgbd_calib.solve.pose import (
    BoardObservation,
    PoseConfig,
    RejectedView,
    estimate_board_pose,
    model_error_covariance,
    pose_jacobian,
    pose_jacobian_numeric,
    reprojection_residuals,
    se3_exp,
)
from rgbd_calib.synth import render as synth
from rgbd_calib.synth.scene import rect

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
N_VIEWS = 16
NOISY = synth.SynthParams(blur_sigma_px=0.6, color_noise_dn=2.0)
EXACT_MM, EXACT_DEG = 1e-6, 1e-5  # the angle comes from an arccos: ~1e-6 deg resolution
MAX_EDGES_MEDIAN_MM = 0.06  # per-view translation error with edge-fitted corners, 0.5-0.85 m
MAX_EDGES_WORST_MM = 0.3
NORMALISED_RMS_RANGE = (0.5, 2.0)  # RMS of translation error / predicted sigma, per axis


def make_camera(distortion=(0.0, 0.0, 0.0, 0.0, 0.0)) -> synth.SynthCamera:
    K = CameraIntrinsics(640, 360, 316.5, 316.5, 321.7, 178.9, tuple(distortion))
    return synth.SynthCamera("cam", K, np.eye(4))


def random_board_pose(
    board: Board, rng: np.random.Generator, face: int, K: CameraIntrinsics
) -> np.ndarray:
    """``T_cam_board`` showing ``face``, fully in view, tilted <= 35 deg, rolled <= 25 deg."""
    base = np.diag([1.0, -1.0, -1.0]) if face == FRONT else np.diag([-1.0, -1.0, 1.0])
    centre_b = np.array(
        [
            (board.panel[0] + board.panel[1]) / 2,
            (board.panel[2] + board.panel[3]) / 2,
            -board.thickness / 2,
        ]
    )
    for _ in range(1000):
        axis = np.append(rng.normal(size=2), 0.0)
        axis /= np.linalg.norm(axis)
        R = (
            rotvec_to_matrix(axis * np.radians(rng.uniform(0, 35)))
            @ rotvec_to_matrix([0, 0, np.radians(rng.uniform(-25, 25))])
            @ base
        )
        centre = np.array(
            [rng.uniform(-0.05, 0.05), rng.uniform(-0.03, 0.03), rng.uniform(0.5, 0.85)]
        )
        T = make_transform(R, centre - R @ centre_b)
        uv = K.project(transform_points(T, board.corners.reshape(-1, 3)))
        if np.all((uv > 8) & (uv < [K.width - 8, K.height - 8])):
            return T
    raise AssertionError("no board pose in view")


def log_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """``xi = [omega, v]`` with ``T_est = T_true Exp(xi)`` (first order)."""
    D = invert_transform(T_true) @ T_est
    return np.concatenate([matrix_to_rotvec(D[:3, :3]), D[:3, 3]])


@pytest.fixture(scope="module")
def board() -> Board:
    return load_board(CONFIGS / "board_thesis.yaml")


@pytest.fixture(scope="module")
def views(board):
    """Noisy renders: (image, T_cam_board, intrinsics), alternating front and back."""
    cam = make_camera()
    rng = np.random.default_rng(11)
    wall = [rect((-6, -4, 3.0), (12, 0, 0), (0, 8, 0), (0.45, 0.5, 0.55), 7, 0.08)]
    background = synth.render_background(wall, cam, samples=1)
    model = synth._BoardModel(board)
    out = []
    for k in range(N_VIEWS):
        T = random_board_pose(board, rng, (FRONT, BACK)[k % 2], cam.intrinsics)
        color, _ = synth.render_board(model, cam, background, T)
        out.append((synth.finish_color(color, NOISY, rng), T, cam.intrinsics))
    return out


@pytest.fixture(scope="module")
def solved(board, views):
    """Per refinement method: the observations of all views (and the truth)."""
    out = {}
    for method in ("edges", "subpix"):
        config = DetectionConfig(refinement=method)
        out[method] = [
            (
                estimate_board_pose(
                    detect_markers(img, board, config), board, K, camera="cam", frame=f"{k:06d}"
                ),
                T,
            )
            for k, (img, T, K) in enumerate(views)
        ]
    return out


def exact_detections(board: Board, T: np.ndarray, K: CameraIntrinsics, face: int):
    ids = board.face_ids(face)
    uv = K.project(transform_points(T, board.object_points(ids).reshape(-1, 3)))
    return MarkerDetections(ids, uv.reshape(-1, 4, 2), np.ones((len(ids), 4), bool))


# --------------------------------------------------------------------------- exact maths
def test_se3_exp_matches_the_matrix_exponential(rng):
    for _ in range(20):
        xi = rng.normal(size=6) * [0.5, 0.5, 0.5, 0.3, 0.3, 0.3]
        twist = np.zeros((4, 4))
        twist[:3, :3] = skew(xi[:3])
        twist[:3, 3] = xi[3:]
        np.testing.assert_allclose(se3_exp(xi), expm(twist), atol=1e-10)


@pytest.mark.parametrize("face", [FRONT, BACK])
def test_exact_corners_give_the_exact_pose(board, rng, face):
    K = make_camera((0.05, -0.02, 0.001, -0.001, 0.0)).intrinsics
    T = random_board_pose(board, rng, face, K)
    ob = estimate_board_pose(exact_detections(board, T, K, face), board, K)
    assert isinstance(ob, BoardObservation), ob
    err_deg, err_mm = transform_error(ob.T_cam_board, T)
    assert err_mm < EXACT_MM and err_deg < EXACT_DEG
    assert ob.face == face and ob.n_markers == 28
    assert ob.reprojection_rms_px < 1e-6
    np.testing.assert_allclose(
        reprojection_residuals(T, ob.object_points, ob.corners_px, K), 0.0, atol=1e-6
    )
    assert np.all(np.linalg.eigvalsh(ob.covariance) > 0)
    json.dumps(ob.to_dict())


def test_jacobian_is_for_the_right_perturbation(board, rng):
    K = make_camera().intrinsics
    T = random_board_pose(board, rng, FRONT, K)
    pts = board.object_points(board.face_ids(FRONT)[:5]).reshape(-1, 3)
    J = pose_jacobian(T, pts, K)
    xi = rng.normal(size=6) * 1e-5
    base = K.project(transform_points(T, pts))
    right = K.project(transform_points(T @ se3_exp(xi), pts)) - base  # T * Exp(xi): body frame
    left = K.project(transform_points(se3_exp(xi) @ T, pts)) - base  # Exp(xi) * T: camera frame
    scale = np.linalg.norm(J @ xi)
    assert np.linalg.norm(right.reshape(-1) - J @ xi) < 1e-3 * scale
    assert np.linalg.norm(left.reshape(-1) - J @ xi) > 0.1 * scale


@pytest.mark.parametrize("dist", [(0.0,) * 5, (0.12, -0.25, 0.002, -0.003, 0.08)])
def test_closed_form_jacobian_equals_central_differences(board, rng, dist):
    """cv2.projectPoints' own derivative, chained with dX/dxi = [-R [P]x, R], is the central
    difference Jacobian (the distortion model included) to its truncation error."""
    K = make_camera(dist).intrinsics
    T = random_board_pose(board, rng, FRONT, K)
    pts = board.object_points(board.face_ids(FRONT)).reshape(-1, 3)
    J, J_num = pose_jacobian(T, pts, K), pose_jacobian_numeric(T, pts, K)
    assert J.shape == J_num.shape == (2 * len(pts), 6)
    assert np.abs(J - J_num).max() < 1e-6 * np.abs(J_num).max()


# --------------------------------------------------------------------------- noisy renders
def test_edges_pose_beats_subpix_on_noisy_views(solved):
    assert all(isinstance(ob, BoardObservation) for ob, _ in solved["edges"])
    errors = {
        m: np.array(
            [
                transform_error(ob.T_cam_board, T)[1]
                for ob, T in results
                if isinstance(ob, BoardObservation)
            ]
        )
        for m, results in solved.items()
    }
    report = {m: (len(e), float(np.median(e)), float(e.max())) for m, e in errors.items()}
    assert np.median(errors["edges"]) < 0.5 * np.median(errors["subpix"]), report
    assert np.median(errors["edges"]) < MAX_EDGES_MEDIAN_MM, report
    assert errors["edges"].max() < MAX_EDGES_WORST_MM, report


def test_covariance_is_honest(solved):
    """Translation errors divided by the predicted sigma have an RMS near 1 per axis, and the
    Mahalanobis distances of the full 6-vector look like chi2(6) (mean 6). The corner-noise
    part: the per-view model-error floor (``model_error_px``, off by default) allows for a
    misfit renders do not have (with 0.5 px the RMS is ~0.004: conservative by design)."""
    normalised, mahalanobis = [], []
    for ob, T in solved["edges"]:
        xi = log_error(ob.T_cam_board, T)
        floor = ob.model_error_covariance
        cov = ob.covariance if floor is None else ob.covariance - floor
        normalised.append(xi[3:] / np.sqrt(np.diag(cov)[3:]))
        mahalanobis.append(float(xi @ np.linalg.solve(cov, xi)))
    rms = float(np.sqrt(np.mean(np.square(normalised))))
    assert NORMALISED_RMS_RANGE[0] < rms < NORMALISED_RMS_RANGE[1], (rms, mahalanobis)
    assert 2.0 < np.mean(mahalanobis) < 15.0, mahalanobis


def test_back_face_views_solve_with_detection_order_corners(solved, views):
    backs = [(ob, T) for ob, T in solved["edges"] if ob.face == BACK]
    assert len(backs) == N_VIEWS // 2
    for ob, T in backs:
        assert np.all(ob.ids >= 28)
        err_deg, err_mm = transform_error(ob.T_cam_board, T)
        assert err_mm < MAX_EDGES_WORST_MM and err_deg < 0.1
        assert ob.reprojection_rms_px < 0.2


# --------------------------------------------------------------------------- gates
def test_too_few_markers_is_rejected(board, views):
    img, _, K = views[0]
    det = detect_markers(img, board)
    few = det.subset(np.arange(3))
    out = estimate_board_pose(few, board, K, PoseConfig(min_markers=4), "cam", "000007")
    assert isinstance(out, RejectedView)
    assert (out.reason, out.n_markers, out.camera, out.frame) == (
        "too_few_markers",
        3,
        "cam",
        "000007",
    )


def test_charuco_views_need_corners_not_four_quads():
    """A ChArUco view is judged by its distinct saddle corners (``min_charuco_corners``), not
    by ``min_markers`` quads: two whole squares (8 corners) give a pose, one (4) does not, and
    two overlapping squares (6 corners) do not either."""
    from rgbd_calib.model.board import cover_quads
    from rgbd_calib.model.board_file import load_board

    cboard = load_board(CONFIGS / "board_charuco_caliscope.yaml")  # 3 x 4 corners, 6 quads
    K = make_camera().intrinsics
    R = rotvec_to_matrix(np.array([0.15, -0.1, 0.05])) @ rotvec_to_matrix(np.array([np.pi, 0, 0]))
    T = make_transform(R, [-0.1, 0.13, 0.6])  # the printed face towards the camera
    quads = cboard.charuco.quads()

    def view(corner_ids):
        q = cover_quads(quads, np.array(corner_ids))
        uv = K.project(transform_points(T, cboard.object_points(q).reshape(-1, 3)))
        return MarkerDetections(q, uv.reshape(-1, 4, 2), np.ones((len(q), 4), bool),
                                refinement="charuco")

    two = estimate_board_pose(view([0, 1, 3, 4, 6, 7, 9, 10]), cboard, K, PoseConfig())
    assert not isinstance(two, RejectedView) and two.n_markers == 2
    assert np.abs(two.T_cam_board[:3, 3] - T[:3, 3]).max() < 1e-6
    for ids, n in (([0, 1, 3, 4], 4), ([0, 1, 2, 3, 4, 5], 6)):
        out = estimate_board_pose(view(ids), cboard, K, PoseConfig())
        assert isinstance(out, RejectedView) and out.reason == "too_few_markers"
        assert out.detail == f"{n} corners < min_charuco_corners 8"
    assert not isinstance(estimate_board_pose(view([0, 1, 2, 3, 4, 5]), cboard, K,
                                              PoseConfig(min_charuco_corners=6)), RejectedView)


def test_stray_marker_is_dropped(board, views):
    img, T, K = views[2]
    det = detect_markers(img, board)
    corners = det.corners_px.copy()
    corners[4] += [20.0, -20.0]  # a stray detection carrying a board id
    moved = MarkerDetections(det.ids, corners, det.refined, refinement=det.refinement)
    ob = estimate_board_pose(moved, board, K)
    assert isinstance(ob, BoardObservation), ob
    assert ob.dropped["outlier"] == [int(det.ids[4])]
    assert int(det.ids[4]) not in ob.ids.tolist()
    assert transform_error(ob.T_cam_board, T)[1] < MAX_EDGES_WORST_MM


def test_markers_of_both_faces_keep_the_majority_face(board, views):
    img, T, K = views[0]  # a front view
    det = detect_markers(img, board)
    assert np.all(det.ids < 28)
    fake_ids = np.array([40, 41])  # back-face ids "seen" where two front markers are
    ids = np.concatenate([det.ids, fake_ids])
    corners = np.concatenate([det.corners_px, det.corners_px[:2] + 3.0])
    both = MarkerDetections(ids, corners, np.ones((len(ids), 4), bool))
    ob = estimate_board_pose(both, board, K)
    assert isinstance(ob, BoardObservation), ob
    assert ob.face == FRONT and sorted(ob.dropped["minority_face"]) == [40, 41]
    assert transform_error(ob.T_cam_board, T)[1] < MAX_EDGES_WORST_MM

    tie = MarkerDetections(np.array([0, 1, 40, 41]), det.corners_px[:4], np.ones((4, 4), bool))
    out = estimate_board_pose(tie, board, K, PoseConfig(min_markers=2))
    assert isinstance(out, RejectedView) and out.reason == "both_faces"


def test_unrefined_markers_are_left_out_unless_asked(board, views):
    img, T, K = views[1]
    det = detect_markers(img, board)
    refined = det.refined.copy()
    refined[0, 2] = False
    flagged = MarkerDetections(det.ids, det.corners_px, refined, refinement="edges")
    ob = estimate_board_pose(flagged, board, K)
    assert ob.dropped["unrefined"] == [int(det.ids[0])] and ob.n_markers == len(det) - 1
    kept = estimate_board_pose(flagged, board, K, PoseConfig(use_unrefined_corners=True))
    assert kept.n_markers == len(det) and "unrefined" not in kept.dropped


def test_fixed_pixel_sigma_scales_the_covariance(board, views):
    img, _, K = views[3]
    det = detect_markers(img, board)
    one = estimate_board_pose(det, board, K, PoseConfig(pixel_sigma_px=0.1, model_error_px=0))
    two = estimate_board_pose(det, board, K, PoseConfig(pixel_sigma_px=0.2, model_error_px=0))
    np.testing.assert_allclose(two.covariance, 4.0 * one.covariance, rtol=1e-9)
    assert one.sigma_px == 0.1


# --------------------------------------------------------------------------- model-error floor
KERNEL_THRESHOLD = 4.1  # the pose graph's default outlier bound on a whitened edge norm


def test_model_error_floor_whitens_an_affine_misfit_to_its_size(board, rng):
    """A common 2-D affine misfit of the view's corners (here an offset of k sigmas) moves the
    pose by exactly ``G A x``; under the floor's covariance alone its whitened norm is |x| / s."""
    K = make_camera((0.05, -0.02, 0.001, -0.001, 0.0)).intrinsics
    T = random_board_pose(board, rng, FRONT, K)
    pts = board.object_points(board.face_ids(FRONT)).reshape(-1, 3)
    J = pose_jacobian(T, pts, K)
    uv = K.project(transform_points(T, pts))
    s = 0.3
    cov = model_error_covariance(J, uv, s)
    assert np.all(np.linalg.eigvalsh(cov) > 0)  # 6 affine terms: full rank on a planar board
    shift = np.tile([3 * s, 0.0], len(uv))  # every corner 0.9 px to the right
    xi = np.linalg.solve(J.T @ J, J.T @ shift)  # the least-squares pose's move
    assert np.sqrt(xi @ np.linalg.solve(cov, xi)) == pytest.approx(3.0, rel=1e-6)
    np.testing.assert_allclose(model_error_covariance(J, uv, 2 * s), 4 * cov, rtol=1e-12)


def test_common_pixel_offset_is_an_outlier_without_the_floor_only(board, rng):
    """A view whose corners are all 0.5 px off (plus 0.05 px noise): its pose error whitened by
    the PnP covariance is far beyond the pose graph's outlier bound; with a 0.3 px floor it is
    within it, and the floor hardly moves a view without misfit (noise only)."""
    K = make_camera().intrinsics
    T = random_board_pose(board, rng, FRONT, K)
    det = exact_detections(board, T, K, FRONT)
    noise = rng.normal(0.0, 0.05, det.corners_px.shape)
    shifted = MarkerDetections(det.ids, det.corners_px + noise + [0.5, 0.0], det.refined)
    clean = MarkerDetections(det.ids, det.corners_px + noise, det.refined)

    def whitened(d, model_error_px):
        ob = estimate_board_pose(d, board, K, PoseConfig(model_error_px=model_error_px))
        xi = log_error(ob.T_cam_board, T)
        return float(np.sqrt(xi @ np.linalg.solve(ob.covariance, xi)))

    assert whitened(shifted, 0.0) > 5 * KERNEL_THRESHOLD
    assert whitened(shifted, 0.3) < KERNEL_THRESHOLD
    assert whitened(clean, 0.3) < whitened(clean, 0.0) < KERNEL_THRESHOLD
