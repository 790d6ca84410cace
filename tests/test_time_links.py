"""The motion prior of a continuous recording (issue 32): consecutive frame sets' board poses
and twists tied by white-noise acceleration (rgbd_calib/solve/time_model.py MotionPrior,
motion_link_factor), which makes clock offsets observable with a global shutter where each
set alone (two cameras, its twist free) is not.

Scenes: the exact-corner scenes of tests/test_time_model.py, each board position held for a
burst of three sets 1000/30 ms apart along a trajectory with 1 m/s^2 and 100 deg/s^2 of
acceleration (the solve's prior assumes none), every set seen by the reference and one other
camera, global shutter, corners at 0.1 px, offsets anchored by timestamps good to 0.5 ms."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from test_time_model import (
    HEIGHT,
    WIDTH,
    K,
    _central_differences,
    board_points,
    make_scene,
    perturbed,
)

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.config import BundleConfig
from rgbd_calib.core.geometry import (
    invert_transform,
    make_transform,
    pose_after_twist,
    rotvec_to_matrix,
    transform_error,
)
from rgbd_calib.solve.bundle import BundleProblem, MarkerMeasurement, bundle_adjust
from rgbd_calib.solve.runs import frame_period_ms, link_window_ms
from rgbd_calib.solve.time_model import (
    MotionPrior,
    TimePrior,
    acceleration_stencils,
    motion_link_factor,
    motion_links,
    project_timed,
    set_times_ms,
    timed_view_factor,
)

FRAME_S = 1.0 / 30.0


def test_the_link_factor_jacobians_match_central_differences():
    rng = np.random.default_rng(3)
    values = gtsam.Values()
    T_f = make_transform(rotvec_to_matrix(rng.normal(0, 0.5, 3)), rng.normal(0, 1, 3))
    T_g = T_f @ make_transform(rotvec_to_matrix([0.01, 0.02, -0.03]), [0.01, 0.0, 0.02])
    values.insert(1, gtsam.Pose3(T_f))
    values.insert(2, rng.normal(0, 0.5, 6))
    values.insert(3, gtsam.Pose3(T_g))
    values.insert(4, rng.normal(0, 0.5, 6))
    factor = motion_link_factor(1, 2, 3, 4, FRAME_S, MotionPrior())
    A, _ = factor.linearize(values).jacobian()  # whitened
    noise = factor.noiseModel()
    col = 0
    for key, pose in ((1, True), (2, False), (3, True), (4, False)):
        numeric = _central_differences(factor, values, key, 6, pose, np.full(6, 1e-6))
        whitened = np.stack([noise.whiten(numeric[:, j]) for j in range(6)], axis=1)
        np.testing.assert_allclose(A[:, col:col + 6], whitened, rtol=1e-5,
                                   atol=1e-5 * np.abs(whitened).max(), err_msg=f"key {key}")
        col += 6


def test_an_accelerating_board_projects_where_it_was():
    """``project_timed`` with an acceleration puts each corner where the constant-acceleration
    trajectory (``pose_after_twist`` with ``a`` and ``alpha`` along the turn) had it at the
    corner's own time (offset + readout x row), to 1e-9 px."""
    T_cam = make_transform(rotvec_to_matrix([0.1, -0.2, 0.05]), [0.3, 0.1, -0.2])
    T_board = make_transform(rotvec_to_matrix([np.pi + 0.2, 0.1, -0.3]), [-0.2, -0.1, 1.3])
    w, v = np.array([0.3, -0.2, 0.4]), np.array([0.2, 0.1, -0.25])
    alpha, a = 2.0 * w, np.array([1.0, -0.5, 0.3])
    P_b = board_points().reshape(-1, 3)
    s_row = np.linspace(0.0, 1.0, len(P_b))
    time_ms = np.array([-14.0, 25.0])
    uv = project_timed(T_cam, T_board, np.r_[w, v], time_ms, K, P_b, s_row, False,
                       accel=np.r_[alpha, a])[0]
    for i, (P, s) in enumerate(zip(P_b, s_row)):
        tau = 1e-3 * (time_ms[0] + time_ms[1] * s)
        T = pose_after_twist(T_board, v, w, tau, a, alpha)
        p = invert_transform(T_cam) @ T @ np.r_[P, 1.0]
        expected = (K @ p[:3])[:2] / p[2]
        np.testing.assert_allclose(uv[i], expected, atol=1e-9)


def test_the_view_factor_jacobians_with_an_acceleration_stencil(rng):
    """A view factor whose acceleration is a central difference of its neighbours' twists
    (and a one-sided one including its own): every block, the stencil's twists included,
    equals central differences of the error."""
    from test_time_model import _factor_values
    values = _factor_values(rng)
    values.insert(5, values.atVector(3) + rng.normal(0, 0.05, 6))
    values.insert(6, values.atVector(3) + rng.normal(0, 0.05, 6))
    obj = board_points()
    px = project_timed(values.atPose3(1).matrix(), values.atPose3(2).matrix(),
                       values.atVector(3), values.atVector(4), K, obj.reshape(-1, 3),
                       np.zeros(48), False)[0].reshape(-1, 4, 2) + rng.normal(0, 2.0, (12, 4, 2))
    for stencil in (((6, 15.0), (5, -15.0)), ((6, 30.0), (3, -30.0))):
        factor = timed_view_factor(1, 2, 3, 4, K, HEIGHT, obj, px, 0.5, "none", 3.0,
                                   accel=stencil)
        A, _ = factor.linearize(values).jacobian()
        keys = [(1, 6, True), (2, 6, True), (3, 6, False), (4, 2, False)]
        keys += [(k, 6, False) for k, _ in stencil if k != 3]
        col = 0
        for key, dim, pose in keys:
            numeric = _central_differences(factor, values, key, dim, pose, np.full(dim, 1e-6))
            scale = np.abs(numeric).max()
            assert scale > 1e-4, f"key {key}: the data do not depend on it"
            np.testing.assert_allclose(A[:, col:col + dim], numeric, rtol=1e-5,
                                       atol=1e-5 * scale, err_msg=f"{stencil} key {key}")
            col += dim


def test_acceleration_stencils():
    links = (("a", "b", 0.03), ("b", "c", 0.04))
    st = acceleration_stencils(links)
    assert st["a"] == (("b", 1 / 0.03), ("a", -1 / 0.03))
    assert st["b"] == (("c", 1 / 0.07), ("a", -1 / 0.07))
    assert st["c"] == (("c", 1 / 0.04), ("b", -1 / 0.04))
    assert acceleration_stencils(()) == {}


def test_a_constant_twist_trajectory_has_zero_error():
    T_f = make_transform(rotvec_to_matrix([0.3, -0.2, 0.1]), [0.1, 0.2, 1.0])
    twist = np.array([0.2, -0.4, 0.3, 0.3, -0.1, 0.05])
    T_g = pose_after_twist(T_f, twist[3:], twist[:3], FRAME_S)
    values = gtsam.Values()
    for key, value in ((1, gtsam.Pose3(T_f)), (3, gtsam.Pose3(T_g))):
        values.insert(key, value)
    values.insert(2, twist)
    values.insert(4, twist)
    assert np.abs(motion_link_factor(1, 2, 3, 4, FRAME_S).unwhitenedError(values)).max() < 1e-12


def test_set_times_and_links_from_timestamps():
    """A set's time is the reference's stamp, or another camera's minus its median
    difference to the reference; sets at most 100 ms apart are linked, in time order."""
    stamps = {"ref": {"a": 0.0, "b": 33.3, "d": 1000.0},
              "cam": {"a": 5.0, "b": 38.3, "c": 71.6, "d": 1005.0},
              "bare": None}
    times = set_times_ms(stamps, "ref")
    assert times == pytest.approx({"a": 0.0, "b": 33.3, "c": 66.6, "d": 1000.0})
    links = motion_links(times, ["d", "c", "b", "a"])
    assert [(f, g) for f, g, _ in links] == [("a", "b"), ("b", "c")]
    assert links[0][2] == pytest.approx(0.0333)
    assert set_times_ms(stamps, "bare") == {}
    assert motion_links(times, ["a", "b"], max_ms=0.0) == ()


def _burst_scene(seed: int, n_positions: int = 8, burst: int = 3):
    """make_scene's rig and positions (global shutter), each held for ``burst`` sets on a
    constant-acceleration trajectory; each set seen by cam0 and one other camera in turn."""
    base = make_scene(seed, n_sets=n_positions, readout_ms=0.0)
    rng = np.random.default_rng(seed + 7)
    cams = list(base.T_ref_cam)
    P_b = board_points().reshape(-1, 3)
    P_h = np.c_[P_b, np.ones(len(P_b))].T
    meas, boards, set_ms = [], {}, {}
    for j, (view, T_mid) in enumerate(base.T_ref_board.items()):
        w0, v0 = base.twist[view][:3], base.twist[view][3:]
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        alpha = w0 / np.linalg.norm(w0) * np.radians(100.0) * rng.choice([-1.0, 1.0])
        for k in range(burst):
            s = (k - (burst - 1) / 2) * FRAME_S
            name = f"{view}_{k}"
            boards[name] = T_s = pose_after_twist(T_mid, v0, w0, s, a, alpha)
            w, v = w0 + alpha * s, v0 + a * s
            set_ms[name] = j * 1000.0 + k * 1000.0 * FRAME_S
            for c in ("cam0", cams[1 + j % (len(cams) - 1)]):
                T = pose_after_twist(T_s, v, w, 1e-3 * base.offset_ms[c], a, alpha)
                p = (invert_transform(base.T_ref_cam[c]) @ T @ P_h)[:3].T
                uv = p[:, :2] / p[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
                uv += rng.normal(0, 0.1, uv.shape)
                meas += [MarkerMeasurement(c, name, m, uv[4 * m:4 * m + 4], P_b[4 * m:4 * m + 4])
                         for m in range(len(P_b) // 4)]
    return base, boards, set_ms, meas


def _solve(base, boards, meas, set_ms, seed):
    rng = np.random.default_rng(seed + 99)
    cams = list(base.T_ref_cam)
    config = BundleConfig(time="refine", board="fixed", intrinsics="fixed", pixel_sigma=0.1)
    model = CameraIntrinsics(WIDTH, HEIGHT, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    priors = {c: TimePrior(offset_ms=base.offset_ms[c] + rng.normal(0, 0.5), offset_sigma_ms=1.0,
                           readout_sigma_ms=1e-6) for c in cams}  # timestamps; global shutter
    result = bundle_adjust(BundleProblem(
        meas, dict.fromkeys(cams, K), "cam0",
        {c: perturbed(T, rng) for c, T in base.T_ref_cam.items()},
        {v: perturbed(T, rng, 0.003, 0.003) for v, T in boards.items()}, config,
        intrinsics=dict.fromkeys(cams, model), time_priors=priors, set_ms=set_ms))
    errors = np.array([(transform_error(result.T_ref_cam[c], base.T_ref_cam[c])[1],
                        result.sigma_translation_mm[c]) for c in cams[1:]])
    return errors[:, 0].max(), float(np.sqrt(np.mean((errors[:, 0] / errors[:, 1]) ** 2)))


def test_consecutive_sets_make_offsets_with_a_global_shutter_observable():
    """Without the links each set's twist is free and the camera poses are off by several mm
    (measured 7.6, 3.7, 2.7 mm on seeds 0-2); with them (and the acceleration they give)
    1.15, 1.08, 1.06 mm, several times better (two cameras per set, eight positions: the data
    limit it), and the sigmas honest (RMS error/sigma 0.85, 0.70, 1.20 measured)."""
    for seed in (0, 1):
        base, boards, set_ms, meas = _burst_scene(seed)
        alone, _ = _solve(base, boards, meas, None, seed)
        linked, z = _solve(base, boards, meas, set_ms, seed)
        assert linked < 0.5 * alone and linked < 1.5, (seed, alone, linked)
        assert 0.4 < z < 1.8, (seed, z)


def test_the_link_window_follows_the_frame_rate():
    """``bundle.time_link_ms: auto``: 1.5 frame periods of the recording (the median gap
    between consecutive sets up to 200 ms), at least the 100 ms of before; separate poses
    (gaps of a second) or no timestamps keep 100 ms; a number is used as given."""
    def recording(fps, positions=4, burst=3):
        return {f"{j * burst + k:06d}": j * 1000.0 + k * 1000.0 / fps
                for j in range(positions) for k in range(burst)}
    assert frame_period_ms(recording(30)) == pytest.approx(1000 / 30)
    assert link_window_ms("auto", recording(30)) == 100.0  # 30 fps links as before
    assert link_window_ms("auto", recording(10)) == pytest.approx(150.0)
    assert link_window_ms("auto", recording(6)) == pytest.approx(250.0)
    assert frame_period_ms(recording(4)) is None  # 250 ms apart: poses, not a trajectory
    assert link_window_ms("auto", recording(4)) == 100.0
    assert link_window_ms("auto", {f"{i}": 1000.0 * i for i in range(9)}) == 100.0
    assert link_window_ms("auto", {}) == 100.0
    assert link_window_ms(40.0, recording(6)) == 40.0
    # the window links a 6 fps burst's sets, and not the next position's
    links = motion_links(recording(6), list(recording(6)), link_window_ms("auto", recording(6)))
    assert len(links) == 4 * 2
