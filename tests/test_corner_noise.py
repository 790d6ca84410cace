"""A marker's corner noise split into its centre and its shape (rgbd_calib/solve/corner_noise.py)
and the bundle's ``corner_noise: marker`` that weighs them apart."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from test_bundle import K, perturb, scene

from rgbd_calib.core.config import BundleConfig
from rgbd_calib.core.geometry import make_transform, rotvec_to_matrix
from rgbd_calib.depth.information import tangent_error
from rgbd_calib.solve.bundle import BundleProblem, bundle_adjust
from rgbd_calib.solve.bundle_factors import view_factor
from rgbd_calib.solve.corner_noise import (
    MIN_MARKERS,
    CornerNoise,
    estimate_corner_noise,
    first_noise,
    scale_covariance,
)
from rgbd_calib.solve.ladder import held_corner_ratio

P_CENTRE = np.kron(np.full((4, 4), 0.25), np.eye(2))  # the corners' mean, broadcast


def structured(rng, n, sigma_shape, sigma_centre):
    """``n`` markers' corner errors (n, 4, 2): shape noise ``sigma_shape`` per dimension of its
    6-dimensional subspace, centre noise ``sigma_centre`` per dimension of its 2 (the
    corners' mean errs by half of it per axis)."""
    z = rng.normal(0, sigma_shape, (n, 8)) @ (np.eye(8) - P_CENTRE)
    c = rng.normal(0, sigma_centre / 2, (n, 2))
    return (z.reshape(n, 4, 2) + c[:, None, :])


def test_whitening_is_the_inverse_square_root_of_the_centre_and_shape_covariance():
    noise = CornerNoise(0.04, 0.3)
    cov = 0.04**2 * (np.eye(8) - P_CENTRE) + (0.04 * 0.3) ** 2 * P_CENTRE
    W = np.vstack([noise.whiten(row[None])[0] for row in np.eye(8)]).T  # columns: W e_i
    np.testing.assert_allclose(W.T @ W, np.linalg.inv(cov), rtol=1e-10)
    rng = np.random.default_rng(1)
    J = rng.normal(size=(24, 5))
    np.testing.assert_allclose(noise.whiten_rows(J),
                               np.vstack([W @ J[8 * i:8 * i + 8] for i in range(3)]))
    assert np.array_equal(CornerNoise(0.5).whiten(np.ones((2, 8))), np.full((2, 8), 2.0))


def test_the_view_factor_whitens_each_markers_residuals_with_the_noise():
    rng = np.random.default_rng(2)
    T_ref_cam, boards, meas = scene(rng, 2, 1)
    ms = [m for m in meas if m.camera == "c1"][:3]
    obj = np.stack([m.object_points for m in ms])
    px = np.stack([m.corners_px for m in ms]) + 0.3  # off the projection
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3(T_ref_cam["c1"]))
    values.insert(1, gtsam.Pose3(boards[ms[0].view]))
    noise = CornerNoise(0.05, 0.25)
    plain = view_factor(0, 1, K, obj, px, 1.0, "none", 1.0).unwhitenedError(values)
    split = view_factor(0, 1, K, obj, px, noise, "none", 1.0).unwhitenedError(values)
    np.testing.assert_allclose(split, noise.whiten(plain.reshape(-1, 8)).ravel(), rtol=1e-9)


def test_both_sigmas_are_read_from_the_residuals_and_few_markers_keep_one():
    rng = np.random.default_rng(3)
    est = estimate_corner_noise(structured(rng, 4000, 0.04, 0.012), 200)
    assert abs(est.sigma_px / 0.04 - 1) < 0.03, est
    assert abs(est.centre_ratio / 0.3 - 1) < 0.05, est
    same = estimate_corner_noise(rng.normal(0, 0.03, (4000, 4, 2)), 100)
    assert abs(same.centre_ratio - 1) < 0.05 and abs(same.sigma_px / 0.03 - 1) < 0.03, same
    few = estimate_corner_noise(structured(rng, MIN_MARKERS - 1, 0.04, 0.012), 10)
    assert few.independent


def _chi2_over_6(res, truth):
    out = []
    for c in ("c1", "c2", "c3"):
        xi = tangent_error(res.T_ref_cam[c], truth[c])
        out.append(float(xi @ np.linalg.solve(res.covariance[c], xi)) / 6)
    return float(np.mean(out))


def test_the_marker_model_claims_honest_sigmas_where_one_sigma_per_corner_claims_too_wide():
    """Corners whose shape errs 4x more than their centre (edge-fitted markers: measured
    0.030 px against 0.0065 px for their mean on renders): over 6 synthetic rigs the
    independent model's covariance is several times too wide (mean chi-square / 6 below 0.5)
    while the marker model's is honest (0.5-1.8) and its extrinsics closer to the truth."""
    chi_ind, chi_mk, err_ind, err_mk = [], [], [], []
    for seed in range(6):
        rng = np.random.default_rng(100 + seed)
        truth, boards, meas = scene(rng, n_cams=4, n_views=12, sigma_px=0.0)
        e = structured(rng, len(meas), 0.08, 0.02)
        meas = [replace(m, corners_px=m.corners_px + d) for m, d in zip(meas, e)]
        init = {c: T if c == "c0" else perturb(T, rng) for c, T in truth.items()}
        problem = BundleProblem(meas, dict.fromkeys(truth, K), "c0", init, boards,
                                BundleConfig(pixel_sigma=0.1))
        ind = bundle_adjust(problem)
        mk = bundle_adjust(replace(problem, config=BundleConfig(pixel_sigma=0.1,
                                                                corner_noise="marker")))
        chi_ind.append(_chi2_over_6(ind, truth))
        chi_mk.append(_chi2_over_6(mk, truth))
        err_ind += [np.linalg.norm(tangent_error(ind.T_ref_cam[c], truth[c])) for c in truth]
        err_mk += [np.linalg.norm(tangent_error(mk.T_ref_cam[c], truth[c])) for c in truth]
        assert abs(mk.corner_noise.centre_ratio / 0.25 - 1) < 0.15, mk.corner_noise
        assert ind.corner_noise is not None and not mk.corner_noise.independent
    assert np.mean(chi_ind) < 0.5, chi_ind
    assert 0.5 < np.mean(chi_mk) < 1.8, chi_mk
    assert np.sqrt(np.mean(np.square(err_mk))) < 0.9 * np.sqrt(np.mean(np.square(err_ind)))


def test_the_rig_scale_sigma_is_the_move_of_a_scaled_rig_along_one_direction():
    T = make_transform(rotvec_to_matrix([0.3, -1.2, 0.4]), [1.7, -0.2, 2.4])
    scaled = make_transform(T[:3, :3], T[:3, 3] * (1 + 20e-6))
    xi = tangent_error(scaled, T)  # what a 20 ppm larger rig moves this camera by
    C = scale_covariance(T, 20e-6)
    assert np.linalg.matrix_rank(C, tol=1e-20) == 1
    np.testing.assert_allclose(np.outer(xi, xi), C, atol=1e-16)


def test_the_marker_model_adds_the_rig_scale_to_every_solved_cameras_covariance():
    rng = np.random.default_rng(9)
    truth, boards, meas = scene(rng, n_cams=3, n_views=6, sigma_px=0.0)
    e = structured(rng, len(meas), 0.08, 0.02)
    meas = [replace(m, corners_px=m.corners_px + d) for m, d in zip(meas, e)]
    problem = BundleProblem(meas, dict.fromkeys(truth, K), "c0", truth, boards,
                            BundleConfig(pixel_sigma=0.1, corner_noise="marker"))
    with_scale = bundle_adjust(problem)
    without = bundle_adjust(replace(problem, config=BundleConfig(
        pixel_sigma=0.1, corner_noise="marker", scale_sigma_ppm=0.0)))
    assert with_scale.scale_sigma_ppm == 25.0 and without.scale_sigma_ppm == 0.0
    for c in ("c1", "c2"):
        np.testing.assert_allclose(with_scale.covariance[c] - without.covariance[c],
                                   scale_covariance(with_scale.T_ref_cam[c], 25e-6),
                                   atol=1e-14)
    assert not with_scale.covariance["c0"].any()
    independent = bundle_adjust(replace(problem, config=BundleConfig(pixel_sigma=0.1)))
    assert independent.scale_sigma_ppm == 0.0


def test_a_held_ratio_solves_once_as_the_ratio_read_would():
    """calibrate reads the centre-to-shape ratio in its first bundle adjustment and holds it
    for the rest of the run (ladder.held_corner_ratio): solved at the held ratio, the same
    cameras as the solve that read it."""
    rng = np.random.default_rng(11)
    truth, boards, meas = scene(rng, n_cams=3, n_views=8, sigma_px=0.0)
    e = structured(rng, len(meas), 0.08, 0.02)
    meas = [replace(m, corners_px=m.corners_px + d) for m, d in zip(meas, e)]
    marker = BundleConfig(pixel_sigma=0.1, corner_noise="marker")
    problem = BundleProblem(meas, dict.fromkeys(truth, K), "c0", truth, boards, marker)
    read = bundle_adjust(problem)
    held = held_corner_ratio(marker, read)
    assert held.corners.corner_centre_ratio == read.corner_noise.centre_ratio
    assert first_noise(held) == CornerNoise(0.1, held.corners.corner_centre_ratio)
    assert first_noise(marker) == 0.1 and first_noise(BundleConfig()) == BundleConfig().pixel_sigma
    again = bundle_adjust(replace(problem, config=held))
    for c in ("c1", "c2"):
        assert np.linalg.norm(tangent_error(again.T_ref_cam[c], read.T_ref_cam[c])) < 1e-7
    assert held_corner_ratio(held, read) is held  # a ratio given is kept
    assert held_corner_ratio(BundleConfig(), read) == BundleConfig()  # independent: none


def test_the_boards_printed_size_sigma_is_added_to_every_solved_cameras_covariance():
    """A board file's print_scale_sigma (the printed size's relative 1 sigma) scales the whole
    rig: it is added like the marker model's scale term, in quadrature with it, to every
    camera but the reference; 0 (stated exact) or unstated adds nothing."""
    rng = np.random.default_rng(9)
    truth, boards, meas = scene(rng, n_cams=3, n_views=6, sigma_px=0.05)
    problem = BundleProblem(meas, dict.fromkeys(truth, K), "c0", truth, boards,
                            BundleConfig(pixel_sigma=0.1))
    exact = bundle_adjust(problem)
    printed = bundle_adjust(replace(problem, board_scale_sigma=0.002))
    assert exact.scale_sigma_ppm == 0.0 and printed.scale_sigma_ppm == pytest.approx(2000.0)
    for c in ("c1", "c2"):
        np.testing.assert_allclose(printed.covariance[c] - exact.covariance[c],
                                   scale_covariance(printed.T_ref_cam[c], 0.002), atol=1e-14)
        # 0.2 % of the camera's distance from the reference, in quadrature with the corners'
        d_mm = 1e3 * np.linalg.norm(printed.T_ref_cam[c][:3, 3])
        assert printed.sigma_translation_mm[c] == pytest.approx(
            np.hypot(exact.sigma_translation_mm[c], 0.002 * d_mm), rel=0.05)
    assert not printed.covariance["c0"].any()
    both = bundle_adjust(replace(problem, board_scale_sigma=0.0001, config=BundleConfig(
        pixel_sigma=0.1, corner_noise="marker", corner_centre_ratio=0.4)))
    assert both.scale_sigma_ppm == pytest.approx(np.hypot(25.0, 100.0))
