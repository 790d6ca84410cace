"""The camera model (rgbd_calib.core.camera): OpenCV agreement over whole images, exact inverses,
the old back-projection, numerical Jacobians, and the distorted path of the calibration."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from rgbd_calib.core.camera import (
    DISTORTION_NAMES,
    CameraIntrinsics,
    pinhole_point_jacobian,
    pinhole_pose_jacobian,
    project_pinhole,
    undistort_normalized,
)
from rgbd_calib.core.geometry import skew

OPENCV_PX = 1e-6  # agreement with cv2.projectPoints / cv2.undistortPoints (px)
ROUND_TRIP_PX = 1e-8  # distort(undistort(u)) = u (px)
OLD_RAYS_PX = 1e-6  # against the old fixed-point back-projection, where it had converged
JACOBIAN_REL = 1e-6  # analytic vs central differences, relative to the largest entry
WIDTH, HEIGHT = 1280, 720
# iterate cv2.undistortPoints to convergence (its default stops after a few iterations)
CV_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)

DISTORTIONS = {
    "d435-mild": (0.1, -0.2, 1e-3, -1e-3, 0.05),
    "strong-barrel": (-0.3, 0.1, 5e-4, 2e-4, -0.01),
    "pincushion": (0.2, 0.05, -5e-4, 3e-4, 0.0),
    "four-terms": (0.1, -0.05, 1e-3, 2e-3),
    "rational-8": (0.3, -0.1, 1e-3, -1e-3, 0.02, 0.25, -0.05, 0.01),
    "thin-prism-12": (0.1, -0.2, 1e-3, -1e-3, 0.05, 0.02, 0.01, -0.01, 1e-3, -2e-4, -1e-3, 3e-4),
    "tilted-14": (
        0.1, -0.2, 1e-3, -1e-3, 0.05, 0.02, 0.01, -0.01, 1e-3, -2e-4, -1e-3, 3e-4, 0.01, -0.02,
    ),
}  # fmt: skip
distortions = pytest.mark.parametrize("dist", DISTORTIONS.values(), ids=DISTORTIONS.keys())


def camera(dist=(0.0,) * 5) -> CameraIntrinsics:
    return CameraIntrinsics(WIDTH, HEIGHT, 640.0, 638.5, 641.3, 359.2, tuple(dist))


def image_grid(step: float = 10.0) -> np.ndarray:
    """Pixels ``(N,2)`` over the whole image, its outer pixel edges included."""
    u = np.append(np.arange(-0.5, WIDTH - 0.5, step), WIDTH - 0.5)
    v = np.append(np.arange(-0.5, HEIGHT - 0.5, step), HEIGHT - 0.5)
    uu, vv = np.meshgrid(u, v)
    return np.column_stack([uu.ravel(), vv.ravel()])


def cv_undistort(cam: CameraIntrinsics, px: np.ndarray) -> np.ndarray:
    out = cv2.undistortPoints(
        px.reshape(-1, 1, 2), cam.K, cam.dist, R=None, P=cam.K, criteria=CV_CRITERIA
    )
    return out.reshape(-1, 2)


def points_seen_over_the_image(cam: CameraIntrinsics, rng) -> np.ndarray:
    """Camera-frame points (0.3-5 m) whose distorted pixels cover the whole image."""
    ideal = cv_undistort(cam, image_grid())
    xy = (ideal - [cam.cx, cam.cy]) / [cam.fx, cam.fy]
    z = rng.uniform(0.3, 5.0, len(xy))
    return np.column_stack([xy * z[:, None], z])


def old_normalized_rays(intr: CameraIntrinsics, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``depth.normalized_rays`` before the camera model: 20 fixed-point iterations."""
    xd = (np.asarray(u, dtype=float) - intr.cx) / intr.fx
    yd = (np.asarray(v, dtype=float) - intr.cy) / intr.fy
    x, y = xd.copy(), yd.copy()
    if intr.has_distortion:
        d = intr.dist
        k1, k2, p1, p2 = d[:4]
        k3 = d[4] if d.size > 4 else 0.0
        for _ in range(20):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x = (xd - dx) / radial
            y = (yd - dy) / radial
    return np.column_stack([x, y, np.ones_like(x)])


# ----------------------------------------------------------------------------- against OpenCV
@distortions
def test_project_matches_opencv_over_the_whole_image(dist, rng):
    cam = camera(dist)
    pts = points_seen_over_the_image(cam, rng)
    ours = cam.project(pts)
    theirs, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), rtol=0, atol=OPENCV_PX)
    # the points do reach every border of the image
    assert ours.min(axis=0) == pytest.approx([-0.5, -0.5], abs=1e-6)
    assert ours.max(axis=0) == pytest.approx([WIDTH - 0.5, HEIGHT - 0.5], abs=1e-6)


@distortions
def test_undistort_pixels_matches_opencv_over_the_whole_image(dist):
    cam = camera(dist)
    px = image_grid()
    np.testing.assert_allclose(cam.undistort_pixels(px), cv_undistort(cam, px), rtol=0,
                               atol=OPENCV_PX)  # fmt: skip


@distortions
def test_distort_pixels_matches_opencv(dist):
    """distort_pixels is what detection's edge fit used cv2.projectPoints of (x, y, 1) for."""
    cam = camera(dist)
    ideal = cv_undistort(cam, image_grid())
    rays = np.column_stack([(ideal - [cam.cx, cam.cy]) / [cam.fx, cam.fy], np.ones(len(ideal))])
    theirs, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(cam.distort_pixels(ideal), theirs.reshape(-1, 2), rtol=0,
                               atol=OPENCV_PX)  # fmt: skip


@distortions
def test_distort_and_undistort_are_inverse(dist):
    cam = camera(dist)
    px = image_grid()
    np.testing.assert_allclose(cam.distort_pixels(cam.undistort_pixels(px)), px, rtol=0,
                               atol=ROUND_TRIP_PX)  # fmt: skip
    xy = cam.undistort((px - [cam.cx, cam.cy]) / [cam.fx, cam.fy])
    np.testing.assert_allclose(cam.undistort(cam.distort(xy)), xy, rtol=0,
                               atol=ROUND_TRIP_PX / cam.fx)  # fmt: skip
    # shapes (...,2) are kept, as the edge fit's (M,4,3,2) arrays need
    grid = px[:24].reshape(2, 3, 4, 2)
    assert cam.undistort_pixels(grid).shape == grid.shape
    np.testing.assert_allclose(cam.undistort_pixels(grid).reshape(-1, 2),
                               cam.undistort_pixels(px[:24]), rtol=0, atol=0)  # fmt: skip


@distortions
def test_rays_back_project_to_their_pixels(dist, rng):
    cam = camera(dist)
    u, v = image_grid().T
    rays = cam.rays(u, v)
    assert rays.shape == (len(u), 3) and np.all(rays[:, 2] == 1.0)
    z = rng.uniform(0.3, 5.0, len(u))[:, None]
    np.testing.assert_allclose(cam.project(rays * z), np.column_stack([u, v]), rtol=0,
                               atol=ROUND_TRIP_PX)  # fmt: skip


def test_newton_stops_on_unreachable_and_nan_points():
    """Strong barrel folds back beyond some radius: no preimage there, the iteration must
    still end (bounded) and a NaN stays NaN."""
    dist = np.array([-0.5, 0.0, 0.0, 0.0, 0.0])  # r_d = r (1 - 0.5 r^2) peaks at r_d = 0.54
    xy_d = np.array([[0.3, 0.1], [2.0, 1.5], [np.nan, 0.0]])
    xy = undistort_normalized(xy_d, dist)
    assert np.all(np.isfinite(xy[:2])) and np.isnan(xy[2, 0])
    r2 = np.sum(xy[0] ** 2)
    np.testing.assert_allclose(xy[0] * (1 - 0.5 * r2), xy_d[0], atol=1e-12)


# ----------------------------------------------------------------------------- old behaviour
def test_zero_distortion_is_the_old_pinhole_bit_for_bit(rng):
    cam = camera()
    assert not cam.has_distortion
    pts = rng.uniform([-1, -1, 0.5], [1, 1, 4], (500, 3))
    old = np.column_stack([cam.fx * (pts[:, 0] / pts[:, 2]) + cam.cx,
                           cam.fy * (pts[:, 1] / pts[:, 2]) + cam.cy])  # fmt: skip
    assert np.array_equal(cam.project(pts), old)
    px = image_grid()
    assert np.array_equal(cam.undistort_pixels(px), px)
    assert np.array_equal(cam.distort_pixels(px), px)
    assert np.array_equal(cam.rays(*px.T), old_normalized_rays(cam, *px.T))


def test_four_and_five_zero_terms_are_the_same_camera(rng):
    pts = rng.uniform([-1, -1, 0.5], [1, 1, 4], (100, 3))
    four = camera((0.1, -0.05, 1e-3, 2e-3))
    five = camera((0.1, -0.05, 1e-3, 2e-3, 0.0))
    fourteen = camera((0.1, -0.05, 1e-3, 2e-3) + (0.0,) * 10)
    assert np.array_equal(four.project(pts), five.project(pts))
    np.testing.assert_allclose(fourteen.project(pts), five.project(pts), rtol=0, atol=1e-9)


@pytest.mark.parametrize("dist", [DISTORTIONS["d435-mild"], DISTORTIONS["strong-barrel"],
                                  DISTORTIONS["pincushion"]])  # fmt: skip
def test_rays_match_the_old_back_projection_where_it_had_converged(dist):
    """``depth.normalized_rays`` ran 20 fixed-point iterations: where those had converged
    the new rays are the same; where not (image corners) the new ones are closer to OpenCV."""
    cam = camera(dist)
    px = image_grid(4.0)
    new, old = cam.rays(*px.T), old_normalized_rays(cam, *px.T)
    old_error = np.linalg.norm(cam.project(old) - px, axis=1)  # px
    converged = old_error < 1e-9
    assert converged.mean() > 0.5, converged.mean()
    diff_px = np.abs(new - old)[:, :2] * [cam.fx, cam.fy]
    assert diff_px[converged].max() < OLD_RAYS_PX
    new_error = np.linalg.norm(cam.project(new) - px, axis=1)
    assert np.all(new_error <= np.maximum(old_error, ROUND_TRIP_PX))


# ----------------------------------------------------------------------------- Jacobians
def numeric_jacobian(f, x0: np.ndarray, step) -> np.ndarray:
    """Central differences of ``f`` (-> (N,2)) in each entry of ``x0``: ``(N,2,len(x0))``."""
    steps = np.broadcast_to(np.asarray(step, dtype=float), x0.shape)
    cols = []
    for i in range(len(x0)):
        dx = np.zeros_like(x0)
        dx[i] = steps[i]
        cols.append((f(x0 + dx) - f(x0 - dx)) / (2 * steps[i]))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("dist", [(0.0,) * 5, *DISTORTIONS.values()],
                         ids=["none", *DISTORTIONS.keys()])  # fmt: skip
def test_project_jacobian_in_the_point(dist, rng):
    cam = camera(dist)
    pts = points_seen_over_the_image(cam, rng)[::97]
    uv, J = cam.project_jacobian(pts)
    np.testing.assert_allclose(uv, cam.project(pts), rtol=0, atol=1e-9)
    for k, p in enumerate(pts):
        num = numeric_jacobian(lambda q: cam.project(q[None]), p, 1e-6)[0]
        assert np.abs(J[k] - num).max() <= JACOBIAN_REL * np.abs(num).max(), (k, J[k], num)


@distortions
def test_intrinsics_jacobian(dist, rng):
    cam = camera(dist)
    pts = points_seen_over_the_image(cam, rng)[::97]
    J = cam.intrinsics_jacobian(pts)
    assert J.shape == (len(pts), 2, 4 + len(dist))
    assert cam.parameter_names == ("fx", "fy", "cx", "cy") + DISTORTION_NAMES[: len(dist)]

    def project_with(theta: np.ndarray) -> np.ndarray:
        fx, fy, cx, cy = theta[:4]
        return replace(cam, fx=fx, fy=fy, cx=cx, cy=cy, distortion=tuple(theta[4:])).project(pts)

    theta = np.array([cam.fx, cam.fy, cam.cx, cam.cy, *dist])
    steps = np.r_[[1e-3] * 4, [1e-6] * len(dist)]  # px for fx fy cx cy, unitless for the rest
    num = numeric_jacobian(project_with, theta, steps)
    scale = np.abs(num).max(axis=(0, 1))  # per parameter: entries range from 1 to 1e4 px
    assert np.all(np.abs(J - num).max(axis=(0, 1)) <= JACOBIAN_REL * scale)


def test_intrinsics_jacobian_without_distortion_still_has_the_coefficient_columns(rng):
    """The next issue refines the distortion too: its columns exist when it is zero."""
    cam = camera()
    pts = rng.uniform([-1, -1, 1], [1, 1, 3], (20, 3))
    J = cam.intrinsics_jacobian(pts)
    xy = pts[:, :2] / pts[:, 2:]
    r2 = np.sum(xy**2, axis=1)
    np.testing.assert_allclose(J[:, 0, 0], xy[:, 0])
    np.testing.assert_allclose(J[:, 0, 4], cam.fx * xy[:, 0] * r2)  # du/dk1
    np.testing.assert_allclose(J[:, 1, 8], cam.fy * xy[:, 1] * r2**3)  # dv/dk3


def test_pose_jacobian_is_the_point_jacobian_times_dp_dxi(rng):
    """solve.bundle_factors.project_board's camera Jacobian: right perturbation
    T_ref_cam Exp(xi) moves camera points by dp/dxi = [[p]x, -I]."""
    pts = rng.uniform([-1, -1, 1], [1, 1, 3], (30, 3))
    J_point = pinhole_point_jacobian(pts, 600.0, 610.0)
    J_pose = pinhole_pose_jacobian(pts, 600.0, 610.0)
    for k, p in enumerate(pts):
        np.testing.assert_allclose(J_pose[k], J_point[k] @ np.hstack([skew(p), -np.eye(3)]),
                                   rtol=1e-12, atol=1e-9)  # fmt: skip
    cam = CameraIntrinsics(1280, 720, 600.0, 610.0, 640.0, 360.0)
    assert np.array_equal(project_pinhole(pts, 600.0, 610.0, 640.0, 360.0), cam.project(pts))


# ----------------------------------------------------------------------------- the pipeline
# Measured on small_line warped through d435-mild: worst 0.0061 deg / 0.165 mm (the same
# renders unwarped: 0.0009 deg / 0.044 mm; warped but calibrated as pinhole: 1.3 deg / 30 mm).
DISTORTED_MAX_ROTATION_DEG = 0.02
DISTORTED_MAX_TRANSLATION_MM = 0.5


@pytest.fixture(scope="module")
def distorted_line(small_line, tmp_path_factory):
    """The session's small thesis-line rig with its colour and depth images warped through a
    D435-like lens distortion, and that distortion in its rig.yaml."""
    import shutil

    from rgbd_calib.model.rig import Rig, load_rig, save_rig

    out = tmp_path_factory.mktemp("distorted") / "line"
    shutil.copytree(small_line.path, out)
    rig = load_rig(out / "rig.yaml")
    cameras = {}
    for name, pinhole in rig.cameras.items():
        cam = replace(pinhole, distortion=DISTORTIONS["d435-mild"])
        v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(float)
        # each distorted pixel shows what the pinhole render has at its ideal position
        ideal = cam.undistort_pixels(np.stack([u, v], axis=-1)).astype(np.float32)
        for kind, interpolation in (("color", cv2.INTER_LINEAR), ("depth", cv2.INTER_NEAREST)):
            for path in sorted((out / name / kind).glob("*.png")):
                image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                warped = cv2.remap(image, ideal[..., 0], ideal[..., 1], interpolation)
                cv2.imwrite(str(path), warped)
        cameras[name] = cam
    save_rig(Rig(cameras, rig.reference), out / "rig.yaml")
    return out


def test_calibration_of_distorted_images(distorted_line):
    """The whole pipeline on distorted images: detection's curved edge fit, PnP with the
    distortion, undistorted corners into the bundle adjustment (the path that crashed on
    ``cv2.undistortPointsIter`` before the camera model)."""
    from rgbd_calib.core.config import CalibrationConfig
    from rgbd_calib.core.geometry import transform_error
    from rgbd_calib.model.board import thesis_board
    from rgbd_calib.model.dataset import FolderDataset
    from rgbd_calib.pipelines.calibrate import calibrate
    from rgbd_calib.synth.render import load_ground_truth

    dataset = FolderDataset(distorted_line)
    assert all(c.has_distortion for c in dataset.rig.cameras.values())
    gt = load_ground_truth(distorted_line)
    result = calibrate(dataset, thesis_board(), CalibrationConfig(workers=2, refine="none"))
    assert result.bundle is not None  # the bundle adjustment ran on undistorted corners
    assert not result.extrinsics.unconnected
    assert set(result.extrinsics.cameras) == set(dataset.cameras)
    for c, e in result.extrinsics.cameras.items():
        deg, mm = transform_error(e.T_ref_cam, gt.T_ref_cam[c])
        assert deg <= DISTORTED_MAX_ROTATION_DEG, (c, deg)
        assert mm <= DISTORTED_MAX_TRANSLATION_MM, (c, mm)
