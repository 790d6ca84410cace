"""Bundle adjustment on marker corners: Jacobians, accuracy, honest marginals, outliers."""

import gtsam
import numpy as np
import pytest
from conftest import assert_transforms_close

from rgbd_calib.core.config import BundleConfig
from rgbd_calib.core.geometry import (
    invert_transform,
    look_at,
    make_transform,
    rotvec_to_matrix,
    transform_error,
)
from rgbd_calib.model.board import thesis_board
from rgbd_calib.solve.bundle import BundleProblem, MarkerMeasurement, bundle_adjust
from rgbd_calib.solve.bundle_factors import view_factor

K = np.array([[600.0, 0, 640], [0, 600.0, 360], [0, 0, 1]])


def scene(rng, n_cams=4, n_views=25, sigma_px=0.2):
    board = thesis_board()
    T_world_cam = {f"c{i}": look_at([0.5 * i, 0, 1.2] + rng.normal(0, .02, 3), [0.4, 1.6, 1.0])
                   for i in range(n_cams)}
    T_ref_cam = {c: invert_transform(T_world_cam["c0"]) @ T for c, T in T_world_cam.items()}
    boards, meas = {}, []
    for v in range(n_views):
        R = rotvec_to_matrix([np.pi / 2, 0, 0]) @ rotvec_to_matrix(rng.normal(0, 0.3, 3))
        T_world_board = make_transform(R, [rng.uniform(0, 1), rng.uniform(1.2, 2), 1.0])
        T_ref_board = invert_transform(T_world_cam["c0"]) @ T_world_board
        view = f"{v:06d}"
        boards[view] = T_ref_board
        for c, T in T_ref_cam.items():
            T_cam_board = invert_transform(T) @ T_ref_board
            for face in (1, -1):
                if face * (T_cam_board[:3, :3] @ [0, 0, 1]) @ T_cam_board[:3, 3] > 0:
                    continue  # that face looks away from the camera
                sel = board.faces == face
                for i, P in zip(board.ids[sel], board.corners[sel]):
                    p = P @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
                    uv = (p[:, :2] / p[:, 2:]) * [K[0, 0], K[1, 1]] + K[:2, 2]
                    if np.all((uv > 0) & (uv < [1280, 720])):
                        meas.append(MarkerMeasurement(c, view, int(i),
                                                      uv + rng.normal(0, sigma_px, uv.shape), P))
    return T_ref_cam, boards, meas


def perturb(T, rng, deg=1.0, m=0.02):
    return T @ make_transform(rotvec_to_matrix(rng.normal(0, np.radians(deg), 3)),
                              rng.normal(0, m, 3))


def test_analytic_jacobians_match_numerical(rng):
    T_ref_cam, boards, meas = scene(rng, 2, 2)
    m = next(x for x in meas if x.camera == "c1")
    # the bundle's own factor, one marker, no kernel, sigma 1: residuals in pixels
    f = view_factor(0, 1, K, m.object_points[None], m.corners_px[None], 1.0, "none", 1.0)
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3(T_ref_cam["c1"]))
    values.insert(1, gtsam.Pose3(boards[m.view]))
    J = f.linearize(values).jacobian()[0]
    eps = 1e-6
    e0 = f.unwhitenedError(values)
    for k, key in enumerate((0, 1)):
        for j in range(6):
            d = np.zeros(6)
            d[j] = eps
            v2 = gtsam.Values(values)
            v2.update(key, values.atPose3(key).retract(d))
            num = (f.unwhitenedError(v2) - e0) / eps
            # linearize() returns -J (A x = b form with b = -error): compare magnitudes
            np.testing.assert_allclose(np.abs(J[:, 6 * k + j]), np.abs(num), atol=1e-3)


def test_recovers_truth_with_honest_sigmas():
    errors = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        T_ref_cam, boards, meas = scene(rng)
        init_cam = {c: (T if c == "c0" else perturb(T, rng)) for c, T in T_ref_cam.items()}
        init_board = {v: perturb(T, rng) for v, T in boards.items()}
        res = bundle_adjust(BundleProblem(meas, dict.fromkeys(T_ref_cam, K), "c0", init_cam,
                                          init_board, BundleConfig(pixel_sigma=0.5)))
        assert res.pixel_sigma_estimated == pytest.approx(0.2, rel=0.1)
        for c in ("c1", "c2", "c3"):
            assert_transforms_close(res.T_ref_cam[c], T_ref_cam[c], atol_mm=0.5, atol_deg=0.05)
            d = res.T_ref_cam[c][:3, 3] - T_ref_cam[c][:3, 3]
            S = T_ref_cam[c][:3, :3] @ res.covariance[c][3:, 3:] @ T_ref_cam[c][:3, :3].T
            errors.append(d @ np.linalg.solve(S, d) / 3)  # Mahalanobis^2 per dof
    rms = float(np.sqrt(np.mean(errors)))
    assert 0.5 < rms < 2.0, rms


def test_wrong_markers_are_rejected(rng):
    T_ref_cam, boards, meas = scene(rng)
    bad = set(rng.choice(len(meas), size=len(meas) // 20, replace=False).tolist())
    corrupted = [MarkerMeasurement(m.camera, m.view, m.marker_id,
                                   m.corners_px + (rng.normal(0, 15, 2) if i in bad else 0),
                                   m.object_points) for i, m in enumerate(meas)]
    Ks = dict.fromkeys(T_ref_cam, K)
    clean = bundle_adjust(BundleProblem(meas, Ks, "c0", T_ref_cam, boards))
    res = bundle_adjust(BundleProblem(corrupted, Ks, "c0", T_ref_cam, boards))
    plain = bundle_adjust(BundleProblem(corrupted, Ks, "c0", T_ref_cam, boards,
                                        BundleConfig(robust="none", outlier_px=1e9)))
    for c in ("c1", "c2", "c3"):
        # the robust result stays at the clean one; plain least squares is pulled away
        assert_transforms_close(res.T_ref_cam[c], clean.T_ref_cam[c], atol_mm=0.1,
                                atol_deg=0.005)
    worst_plain = max(transform_error(plain.T_ref_cam[c], T_ref_cam[c])[1] for c in Ks)
    worst_clean = max(transform_error(clean.T_ref_cam[c], T_ref_cam[c])[1] for c in Ks)
    assert worst_plain > 2 * worst_clean
    assert len(res.outliers) >= 0.9 * len(bad)


def test_fixed_camera_stays_put(rng):
    T_ref_cam, boards, meas = scene(rng)
    held = perturb(T_ref_cam["c2"], rng, 0.0, 0.0)
    res = bundle_adjust(BundleProblem(meas, dict.fromkeys(T_ref_cam, K), "c0", T_ref_cam, boards,
                                      fixed_cameras={"c2": held}))
    assert_transforms_close(res.T_ref_cam["c2"], held, atol_mm=1e-3, atol_deg=1e-4)
