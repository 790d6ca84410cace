"""A depth pair registered from clouds that are not corrected for their depth sensors' poses
carries those poses' error: the covariance it gains, checked against the real depth model
and a rigid registration of its clouds."""

from __future__ import annotations

import numpy as np

from rgbd_calib.core.config import DepthConfig
from rgbd_calib.core.depth_model import PARAMETERS, DepthModel
from rgbd_calib.core.geometry import adjoint, invert_transform, make_transform, rotvec_to_matrix
from rgbd_calib.depth.depth_model_fit import DepthModelFit, applied_pose_moment
from rgbd_calib.depth.information import tangent_error, with_covariance
from rgbd_calib.depth.registration import PairRegistration
from rgbd_calib.depth.stage import applied_pose_moments, fit_pose_moments, with_sensor_poses


def _fit(camera: str, pose: dict[str, float], sigma: float = 0.0) -> DepthModelFit:
    model = DepthModel(50.0, dict(pose), ("pose",))
    cov = np.diag([sigma**2 if p in ("rx", "ry", "rz", "tx", "ty", "tz") else 1e-6
                   for p in PARAMETERS])
    return DepthModelFit(camera, DepthModel(50.0), (), (), 10, 1000, 1.0,
                         law_model=model, law_names=PARAMETERS, law_cov=cov)


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The rigid T with T src = dst (least squares)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - ms).T @ (dst - md))
    R = Vt.T @ np.diag([1, 1, np.linalg.det(Vt.T @ U.T)]) @ U.T
    return make_transform(R, md - R @ ms)


def test_with_covariance_adds_to_the_covariance():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    W = A @ A.T + np.eye(6)
    b = rng.normal(size=(6, 1)) * 0.1
    B = b @ b.T + np.diag(rng.uniform(0, 0.01, 6))
    np.testing.assert_allclose(with_covariance(W, B), np.linalg.inv(np.linalg.inv(W) + B),
                               rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(with_covariance(W, b @ b.T),  # rank one
                               np.linalg.inv(np.linalg.inv(W) + b @ b.T), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(with_covariance(W, np.zeros((6, 6))), W)


def test_the_moved_pair_is_what_the_sensor_poses_predict():
    """Clouds measured through depth sensors off by 0.1-0.2 deg and 0.5-1 mm, registered
    rigidly, give the T_b_a that Ad(T_a_b) eps_b - eps_a predicts; the pair's covariance gains
    that move's second moment."""
    rng = np.random.default_rng(7)
    T_b_a = make_transform(rotvec_to_matrix([0.1, 2.9, -0.2]), [0.3, -0.1, 3.2])
    fits = {"a": _fit("a", {"rx": 0.1, "ry": -0.2, "rz": 0.15, "tx": 1.0, "tz": -0.5}, 0.05),
            "b": _fit("b", {"ry": 0.12, "rz": -0.1, "ty": 0.8}, 0.03)}
    true_a = rng.uniform([-1, -1, 1.0], [1, 1, 3.0], size=(500, 3))
    true_b = true_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    seen_a = fits["a"].law_model.measured_points(true_a)  # what each camera's depth reads
    seen_b = fits["b"].law_model.measured_points(true_b)
    registered = _kabsch(seen_a, seen_b)
    eps_a, _ = fits["a"].sensor_pose_moment()
    eps_b, _ = fits["b"].sensor_pose_moment()
    predicted = adjoint(invert_transform(T_b_a)) @ eps_b - eps_a
    # to first order: the second (|eps|^2 x 3 m) is 0.05 mm at most
    np.testing.assert_allclose(tangent_error(T_b_a, registered), predicted, atol=3e-5)

    W = np.diag([1e8] * 3 + [1e6] * 3)  # a pair of 0.006 deg / 1 mm
    reg = PairRegistration("a", "b", "colored-icp", registered, T_b_a, W, "right", 0.9, 1.0,
                           1.0, 1.0, 0.5, 1000, 0.0, 0.0, True, None, 0.0)
    wide = with_sensor_poses(reg, fit_pose_moments(fits, (0.0, 0.0)))
    cov = np.linalg.inv(wide.information) - np.linalg.inv(W)
    Ad = adjoint(invert_transform(registered))
    _, C_a = fits["a"].sensor_pose_moment()
    _, C_b = fits["b"].sensor_pose_moment()
    beta = Ad @ eps_b - eps_a
    np.testing.assert_allclose(cov, np.outer(beta, beta) + C_a + Ad @ C_b @ Ad.T,
                               rtol=1e-5, atol=1e-14)
    # the move itself, in the pair's own sigmas, was far beyond them before and is within now
    move = tangent_error(T_b_a, registered)
    assert move @ W @ move > 100 and move @ wide.information @ move < 2.0
    assert with_sensor_poses(reg, {}) is reg
    # a camera without a fit is known to the prior alone
    prior_only = with_sensor_poses(reg, fit_pose_moments({"a": None}, (0.1, 1.0)))
    np.testing.assert_allclose(np.linalg.inv(prior_only.information) - np.linalg.inv(W),
                               np.diag([np.radians(0.1) ** 2] * 3 + [1e-6] * 3), atol=1e-12)


def test_a_prior_holds_a_sensor_pose_the_views_leave_free():
    """A fit that leaves the pose nearly free (few views) is held by the prior: the estimate
    shrinks towards zero and the covariance to the prior's; a fit far tighter than the prior
    keeps its own."""
    loose = _fit("a", {"rx": 1.4, "tz": -27.0}, 50.0)  # 1.4 deg, 27 mm, at +-50
    eps, C = loose.sensor_pose_moment(0.1, 1.0)
    assert np.degrees(abs(eps[0])) < 0.001 and abs(eps[5]) < 2e-5  # 27 mm x 1 / 2501
    np.testing.assert_allclose(np.sqrt(np.diag(C)),
                               [np.radians(0.1)] * 3 + [1e-3] * 3, rtol=1e-3)
    tight = _fit("b", {"rx": 0.15, "tz": -0.8}, 0.01)
    eps, C = tight.sensor_pose_moment(0.1, 1.0)
    assert abs(np.degrees(eps[0]) + 0.15) < 0.002 and abs(eps[5] - 0.8e-3) < 2e-5
    eps0, C0 = tight.sensor_pose_moment()
    np.testing.assert_allclose(C, C0, rtol=0.02)


def test_a_corrected_cloud_keeps_what_its_correction_did_not_take_out():
    """check and refine register clouds corrected by the calibration's depth models: a model
    that freed the pose leaves its estimate's error (its sigmas), one that held the pose at the
    factory value, a depth-scale factor or nothing leave the prior; both prior sigmas at 0 take
    the poses as exact (no widening at all)."""
    sig = {"rx": 0.05, "ry": 0.02, "rz": 0.03, "tx": 0.4, "ty": 0.5, "tz": 0.6}
    posed = DepthModel(50.0, {"rx": 0.1, "tz": 1.0}, ("scale", "offset", "pose"),
                       {"scale": 1e-4, "d0": 0.01, **sig})
    eps, C = applied_pose_moment(posed, 0.1, 1.0)
    np.testing.assert_array_equal(eps, np.zeros(6))
    np.testing.assert_allclose(np.sqrt(np.diag(C)), [np.radians(0.05), np.radians(0.02),
                                                     np.radians(0.03), 4e-4, 5e-4, 6e-4])
    prior = np.diag([np.radians(0.1) ** 2] * 3 + [1e-6] * 3)
    unposed = DepthModel(50.0, {"scale": 1.002}, ("scale", "offset"), {"scale": 1e-4})
    for correction in (unposed, 1.003, None):
        np.testing.assert_allclose(applied_pose_moment(correction, 0.1, 1.0)[1], prior)
    moments = applied_pose_moments({"a": posed, "b": 1.003}, ["a", "b", "c"], DepthConfig())
    assert set(moments) == {"a", "b", "c"}
    np.testing.assert_allclose(moments["c"][1], prior)  # the config's default prior
    assert applied_pose_moments({"a": posed}, ["a"], DepthConfig(
        sensor_pose_sigma_deg=0.0, sensor_pose_sigma_mm=0.0)) == {}
    # a pair of two prior-held cameras gains both priors (a's directly, b's through the pair)
    T_b_a = make_transform(rotvec_to_matrix(np.radians([0, 30, 0])), np.array([1.0, 0, 0.2]))
    W = np.diag([1e8] * 3 + [1e6] * 3)
    reg = PairRegistration("b", "c", "colored-icp", T_b_a, T_b_a, W, "right", 0.9, 1.0,
                           1.0, 1.0, 0.5, 1000, 0.0, 0.0, True, None, 0.0)
    Ad = adjoint(invert_transform(T_b_a))
    np.testing.assert_allclose(np.linalg.inv(with_sensor_poses(reg, moments).information)
                               - np.linalg.inv(W), prior + Ad @ prior @ Ad.T, atol=1e-12)
