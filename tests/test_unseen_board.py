"""The board where a camera did not detect it, for its depth model (issue 33): the board placed
by the other cameras, seen in the camera's depth only, and the gate that keeps an occluder's
pixels out of it."""

from __future__ import annotations

import numpy as np
import pytest

from rgbd_calib.core.config import DepthConfig
from rgbd_calib.core.geometry import invert_transform
from rgbd_calib.depth.clouds import board_face_pixels
from rgbd_calib.depth.stage import board_views_per_camera, unseen_board_views
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.synth.ground_truth import load_ground_truth


def _half_seen(gt):
    """Each camera 'detected' every other frame set."""
    frames = sorted(gt.T_ref_board)
    return {c: {f: invert_transform(T) @ gt.T_ref_board[f] for f in frames[::2]}
            for c, T in gt.T_ref_cam.items()}


def test_the_board_a_camera_did_not_detect_is_read_from_its_depth(tiny_dataset):
    ds, gt, board, config = (FolderDataset(tiny_dataset), load_ground_truth(tiny_dataset),
                             thesis_board(), DepthConfig(model_unseen_views=True))
    seen = _half_seen(gt)
    unseen = unseen_board_views(gt.T_ref_cam, gt.T_ref_board, seen, board, ds, config)
    n_faces = 0
    for c, views in unseen.items():
        assert not set(views) & set(seen[c])  # only the sets the camera did not use
        intr = ds.rig.cameras[c]
        for frame, T_cam_board in views.items():
            assert np.allclose(T_cam_board, invert_transform(gt.T_ref_cam[c])
                               @ gt.T_ref_board[frame])
            face = board_face_pixels(ds.read_depth(c, frame), intr, T_cam_board, board, config,
                                     detected=False)
            if face is None:
                continue
            n_faces += 1
            # the true depth on the face: the measured depth agrees within the noise
            assert abs(np.median(face.z_measured - face.z_true)) < 2e-3
    assert n_faces >= 2
    # switched off: nothing
    off = DepthConfig(model_unseen_views=False)
    assert unseen_board_views(gt.T_ref_cam, gt.T_ref_board, seen, board, ds, off) == {}


def test_an_occluded_board_gives_no_depth_pixels(tiny_dataset):
    """A board the camera cannot see (here: put 15 % nearer than it was, so the depth image
    shows the real board, or what is behind it, far off that face) yields no face pixels: the
    gate ``board_depth_gate`` of the views the camera did not detect keeps out what is not the
    board. In a view it detected, the gate is about the view's median ratio instead: the whole
    face off by one factor (a misprinted board) stays."""
    ds, gt, board, config = (FolderDataset(tiny_dataset), load_ground_truth(tiny_dataset),
                             thesis_board(), DepthConfig())
    checked = 0
    for c, T_ref_cam in gt.T_ref_cam.items():
        intr = ds.rig.cameras[c]
        for frame, T_ref_board in gt.T_ref_board.items():
            T_cam_board = invert_transform(T_ref_cam) @ T_ref_board
            if board_face_pixels(ds.read_depth(c, frame), intr, T_cam_board, board, config,
                                 detected=False) is None:
                continue
            nearer = T_cam_board.copy()
            nearer[:3, 3] *= 0.85  # along the ray through the board origin: same image region
            assert board_face_pixels(ds.read_depth(c, frame), intr, nearer, board, config,
                                     detected=False) is None
            # a detected view keeps its pixels (a board printed at the wrong scale must still
            # show as every camera's depth off by the same factor)
            seen = board_face_pixels(ds.read_depth(c, frame), intr, nearer, board, config)
            assert seen is not None
            assert abs(np.median(seen.z_measured / seen.z_true) - 1 / 0.85) < 0.01
            checked += 1
    assert checked >= 4


def test_at_capture_poses_replace_the_sets_and_leave_out_the_unknown(tiny_dataset):
    """With a time model, each camera's board poses are those at its own capture
    (``at_capture``); a set missing there (its pose at that capture too uncertain) is left
    out of both the detected and the depth-only views."""
    ds, gt, board, config = (FolderDataset(tiny_dataset), load_ground_truth(tiny_dataset),
                             thesis_board(), DepthConfig(model_unseen_views=True))
    frames = sorted(gt.T_ref_board)
    shift = np.eye(4)
    shift[0, 3] = 0.004
    at_capture = {c: {f: shift @ gt.T_ref_board[f] for f in frames[1:]} for c in gt.T_ref_cam}

    class _Obs:
        def __init__(self, camera, frame):
            self.camera, self.frame = camera, frame

    obs = [_Obs(c, f) for c in gt.T_ref_cam for f in frames[::2]]
    views = board_views_per_camera(obs, gt.T_ref_cam, gt.T_ref_board, at_capture)
    for c, v in views.items():
        assert frames[0] not in v
        for f, T in v.items():
            assert np.allclose(gt.T_ref_cam[c] @ T, shift @ gt.T_ref_board[f])
    unseen = unseen_board_views(gt.T_ref_cam, gt.T_ref_board, views, board, ds, config,
                                at_capture)
    for c, v in unseen.items():
        assert frames[0] not in v and not set(v) & set(views.get(c, {}))


def test_a_set_whose_board_at_the_capture_is_known_to_a_centimetre_counts_for_depth():
    """The depth stage takes the board at each camera's capture (the time model's twist) for
    every set where that pose is known to :data:`MAX_CAPTURE_POSE_SIGMA_MM` (10 mm), with that
    uncertainty (m) for its plane's random effect, and leaves out the sets beyond: at 1 mm,
    before the planes were uncertain, 6 of a moving race's 8 cameras got no depth model."""
    from types import SimpleNamespace

    from rgbd_calib.pipelines.calibrate import MAX_CAPTURE_POSE_SIGMA_MM, _boards_at_capture
    from rgbd_calib.solve.time_model import TimeModel

    assert MAX_CAPTURE_POSE_SIGMA_MM == 10.0
    v = np.array([0.0, 0.0, 0.0, 0.3, 0.0, 0.0])
    sigmas = {"slow": np.full(6, 0.0005), "mid": np.full(6, 0.03), "fast": np.full(6, 0.3)}
    tm = TimeModel({"a": 0.0, "b": 16.0}, {"a": 0.0, "b": 0.1}, {"a": 0.0, "b": 0.0},
                   {"a": 0.0, "b": 0.0}, {k: v for k in sigmas}, sigmas)
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 1.5]
    bundle = SimpleNamespace(time=tm, T_ref_board={k: T for k in sigmas})
    poses, unc = _boards_at_capture(bundle, thesis_board(), {"a": np.eye(4), "b": np.eye(4)})
    assert set(poses["a"]) == set(sigmas) and max(unc["a"].values()) == 0.0  # its own instant
    assert set(poses["b"]) == {"slow", "mid"}  # 0.02 and 1.2 mm kept (1.2: not at 1 mm), 12 out
    assert 1e-3 < unc["b"]["mid"] < 1e-2 and unc["b"]["slow"] < 1e-4
    assert np.linalg.norm(poses["b"]["mid"][:3, 3] - T[:3, 3]) == pytest.approx(0.3 * 0.016)


def test_the_board_at_a_cameras_capture_follows_the_sets_twist():
    """``TimeModel.board_at_capture``: the set's board moved by its twist to the camera's
    capture, the time synth exposes its depth image and its colour image's middle row
    (``row_time_s`` at the middle row: offset + timestamps, not the readout's end or start),
    and there it is where synth's truth puts it; the twist's sigmas times that time are its
    uncertainty; None for a set or camera the solve did not have."""
    from rgbd_calib.core.geometry import pose_after_twist
    from rgbd_calib.solve.time_model import TimeModel
    from rgbd_calib.synth.timing import row_time_s

    twist = np.array([0.0, 0.0, 0.5, 0.3, -0.1, 0.0])  # w (rad/s), v (m/s)
    sigma = np.array([0.01, 0.01, 0.01, 0.002, 0.002, 0.002])
    height, readout_ms = 480, 20.0
    tm = TimeModel({"a": 0.0, "b": 6.0}, {"a": 0.0, "b": 0.1}, {"a": 0.0, "b": readout_ms},
                   {"a": 0.0, "b": 0.5}, {"s": twist}, {"s": sigma},
                   capture_ms={("b", "s"): 4.0})
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 1.5]
    moved, unc = tm.board_at_capture("b", "s", T, 0.3)
    tau = row_time_s((height - 1) / 2, height, 1e-3 * (6.0 + 4.0), 1e-3 * readout_ms)
    assert tau == pytest.approx(0.010)
    assert np.allclose(moved, pose_after_twist(T, twist[3:], twist[:3], tau))
    assert np.linalg.norm(moved[:3, 3] - T[:3, 3]) > 3e-3  # it did move (0.3 m/s x 10 ms)
    assert unc == pytest.approx((np.linalg.norm(sigma[3:]) + 0.3 * np.linalg.norm(sigma[:3]))
                                * 10.0)
    reference, _ = tm.board_at_capture("a", "s", T, 0.3)  # the set's own instant
    assert np.allclose(reference, T)
    assert tm.board_at_capture("c", "s", T, 0.3) is None
    assert tm.board_at_capture("b", "t", T, 0.3) is None


def _first_camera_fit(tiny_dataset):
    """The depth model fit of the tiny dataset's first camera on the true board poses."""
    from rgbd_calib.depth.clouds import board_faces
    from rgbd_calib.depth.depth_model_fit import board_samples, fit_depth_model

    ds, gt, board, config = (FolderDataset(tiny_dataset), load_ground_truth(tiny_dataset),
                             thesis_board(), DepthConfig())
    c = ds.cameras[0]
    views = {f: invert_transform(gt.T_ref_cam[c]) @ T for f, T in gt.T_ref_board.items()}
    intr = ds.rig.cameras[c]
    return fit_depth_model(c, board_samples(intr, board_faces(ds, c, views, board, config),
                                            config), intr, config)


def test_the_depth_beyond_the_board_is_known_worse_the_farther_and_reported(tiny_dataset):
    """``correction_sigma_mm`` grows beyond the board's depths (the stereo law extrapolated),
    also for a camera that kept the identity; the finding ``depth_extrapolated`` names the
    cameras with a quarter of their cloud beyond the board and their depth there known to worse
    than 1 mm, and no other."""
    from rgbd_calib.depth.depth_model_fit import beyond_board
    from rgbd_calib.outputs.report.findings_depth import depth_extrapolated

    fit = _first_camera_fit(tiny_dataset)
    lo, hi = fit.model.depth_range_m
    near, far = fit.correction_sigma_mm(0.5 * (lo + hi)), fit.correction_sigma_mm(2.5 * hi)
    assert 0 < near < far
    b = beyond_board(fit, np.array([0.5 * (lo + hi)] * 10 + [2.5 * hi] * 90))
    gap = fit.model_gap_mm(2.5 * hi)
    counted = abs(gap) > 3 * fit.model_gap_sigma_mm(2.5 * hi)  # the applied model's bias
    assert b.fraction == pytest.approx(0.9) and b.model_gap_mm == gap
    assert b.sigma_mm == pytest.approx(max(far, abs(gap)) if counted else far)

    def report(fraction, sigma_mm):
        return {"depth_models": {"cam0": {"beyond_board": {
            "board_max_m": 1.5, "cloud_p90_m": 3.8, "fraction": fraction,
            "sigma_mm": sigma_mm}}}}

    found = depth_extrapolated(report(0.9, 3.3), [])
    assert [f["code"] for f in found] == ["depth_extrapolated"]
    assert found[0]["cameras"] == ["cam0"] and "+-3.3 mm at 3.8 m" in found[0]["message"]
    assert depth_extrapolated(report(0.1, 3.3), []) == []
    assert depth_extrapolated(report(0.9, 0.6), []) == []
    assert depth_extrapolated({}, []) == []


def test_the_far_depth_sigma_holds_the_applied_models_distance_from_the_every_term_fit(
        tiny_dataset):
    """``beyond_board.sigma_mm`` is the every-term fit's sigma at the cloud's depth or, where
    larger and significant (beyond 3 of its own sigmas were the applied model right), the
    applied model's distance from that fit (``model_gap_mm``): a model that left out a term
    trading with its own over the board's range extrapolates with a bias the every-term sigma
    does not hold (a 5-view camera without its depth sensor's pose: -36 mm at 3.7 m against a
    sigma of 6.7 mm, its cloud 29 mm off), while an insignificant gap is the every-term fit's
    own noise (the demo's race: 12-16 mm, its clouds within 0.9 mm). A camera with every term
    (the applied model is that fit) has no gap."""
    from dataclasses import replace

    from rgbd_calib.depth.depth_model_fit import beyond_board

    fit = _first_camera_fit(tiny_dataset)
    far_z = 2.5 * fit.model.depth_range_m[1]
    z, law_sigma = np.full(100, far_z), fit.correction_sigma_mm(far_z)
    law = replace(fit.law_model, depth_range_m=fit.model.depth_range_m,
                  sigmas=dict(zip(fit.law_names, np.sqrt(np.diag(fit.law_cov)))))
    same = replace(fit, model=law, model_cov=fit.law_cov)
    assert abs(same.model_gap_mm(far_z)) < 1e-9 and same.model_gap_sigma_mm(far_z) < 1e-6
    assert beyond_board(same, z).sigma_mm == pytest.approx(law_sigma)
    # a biased applied model as precise as the every-term fit: its whole gap is bias
    off = replace(same, model=law.with_values({"scale": law.value("scale") * 1.01}))
    gap = off.model_gap_mm(far_z)
    assert abs(gap) == pytest.approx(10.0 * far_z, rel=0.1)  # 1 % of the depth, in mm
    b = beyond_board(off, z)
    assert b.model_gap_mm == gap and b.sigma_mm == max(abs(gap), law_sigma)
    assert b.to_dict()["model_gap_mm"] == gap
    # an exact applied model (no covariance of its own): a gap within 3 sigma is noise
    noise = replace(off, model=law.with_values({"scale": law.value("scale") * 1.0001}),
                    model_cov=np.zeros_like(fit.law_cov))
    assert noise.model_gap_sigma_mm(far_z) == pytest.approx(law_sigma)
    assert 0 < abs(noise.model_gap_mm(far_z)) < 3 * law_sigma
    assert beyond_board(noise, z).sigma_mm == pytest.approx(law_sigma)


def test_the_far_depth_sigma_is_taken_where_the_clouds_far_points_lie_in_the_image(
        tiny_dataset):
    """With the cloud's rays the far sigma and the gap are those of the mean depth over the
    rays of the cloud's points beyond the board, not of the centre's ray: a disparity
    gradient the applied model got wrong moves nothing on the centre's ray, and the cloud's
    far points lying on one side of the image (a ring camera's far wall) move by it."""
    from dataclasses import replace

    from rgbd_calib.depth.depth_model_fit import FAR_RAYS, beyond_board

    fit = _first_camera_fit(tiny_dataset)
    fit = replace(fit, law_cov=1e-4 * fit.law_cov)  # as from 10^4 times the tiny set's samples
    lo, hi = fit.model.depth_range_m
    far_z = 2.5 * hi
    law = replace(fit.law_model, depth_range_m=fit.model.depth_range_m,
                  sigmas=dict(zip(fit.law_names, np.sqrt(np.diag(fit.law_cov)))))
    tilted = replace(fit, model=law.with_values({"dx": law.value("dx") + 0.3}),
                     model_cov=fit.law_cov)
    rng = np.random.default_rng(3)
    n = 2000
    # the far points on the image's right half (x > 0), the near tenth anywhere
    x = np.where(np.arange(n) < n // 10, rng.uniform(-0.5, 0.5, n), rng.uniform(0.1, 0.5, n))
    rays = np.column_stack([x, rng.uniform(-0.35, 0.35, n), np.ones(n)])
    z = np.where(np.arange(n) < n // 10, 0.5 * (lo + hi), far_z)
    centre = beyond_board(tilted, z)
    over_image = beyond_board(tilted, z, rays)
    assert abs(centre.model_gap_mm) < 1e-6  # x = 0: a gradient in x moves nothing there
    far_rays = rays[n // 10:][np.linspace(0, n - n // 10 - 1, FAR_RAYS).astype(int)]
    per_ray = [tilted.model_gap_mm(far_z, r[None]) for r in far_rays]
    assert over_image.model_gap_mm == pytest.approx(np.mean(per_ray), rel=1e-3)
    assert abs(over_image.model_gap_mm) > 3 * tilted.model_gap_sigma_mm(far_z, far_rays)
    assert over_image.sigma_mm == pytest.approx(
        max(abs(over_image.model_gap_mm), fit.correction_sigma_mm(far_z, far_rays)))
    assert fit.correction_sigma_mm(far_z, np.array([[0.0, 0.0, 1.0]])) == pytest.approx(
        fit.correction_sigma_mm(far_z))


def test_a_camera_whose_far_depth_is_known_to_centimetres_is_a_warning_and_on_the_console():
    """Beyond :data:`FAR_WARN_SIGMA_MM` (a centimetre, 1 sigma) ``depth_extrapolated`` is a
    warning naming those cameras and their board views (an untuned ring's cameras of 3 and 4
    views: +-88 / +-124 mm, their clouds 31 / 47 mm off, named only in an info before), and
    the same finding says the others (one finding, not a second info saying it again); the
    console's fused-cloud line names them too, also without pairs."""
    from types import SimpleNamespace

    from rgbd_calib.cli.console import fused_line
    from rgbd_calib.depth.depth_model_fit import BeyondBoard
    from rgbd_calib.outputs.report.findings_depth import depth_extrapolated

    far = {"cam1": BeyondBoard("cam1", 2.28, 3.65, 0.67, 123.8),
           "cam2": BeyondBoard("cam2", 2.5, 3.82, 0.82, 3.6),
           "cam3": BeyondBoard("cam3", 2.3, 3.8, 0.92, 88.5),
           "cam4": BeyondBoard("cam4", 2.3, 3.8, 0.10, 50.0)}  # its cloud mostly on the board
    report = {"depth_models": {c: {"beyond_board": b.to_dict(), "n_views": n}
                               for (c, b), n in zip(far.items(), (4, 11, 3, 9))}}
    found = depth_extrapolated(report, [])
    assert [(f["severity"], f["cameras"]) for f in found] == [("warning", ["cam1", "cam3"])]
    assert "the other cameras' far clouds (cam2 +-3.6 mm) are known better" in found[0]["message"]
    assert "cam1's depth is known to +-124 mm (1 sigma) at 3.6 m" in found[0]["message"]
    assert "from 4 board views" in found[0]["message"]
    line = fused_line(None, far)
    assert line.startswith("fused cloud: ") and "cam2" not in line and "cam4" not in line
    assert line.index("+-124 mm (cam1 at 3.6 m)") < line.index("+-88 mm (cam3 at 3.8 m)")
    pairs = SimpleNamespace(pairs=[], off_cameras=[], ambiguous=[])
    assert fused_line(pairs, {"cam2": far["cam2"]}) is None


def test_a_camera_with_depth_but_no_board_view_is_named(tiny_dataset):
    """A camera that has depth but no view of the board usable for it (here: given none) gets
    no depth model; the depth stage says so (``depth.unmodelled``), the report's finding
    ``depth_unmodelled`` names it, and a camera that got its model is not named."""
    from rgbd_calib.depth.stage import measure_depth
    from rgbd_calib.outputs.report.findings_depth import depth_unmodelled

    ds, gt, board = FolderDataset(tiny_dataset), load_ground_truth(tiny_dataset), thesis_board()
    seen = _half_seen(gt)
    bare = ds.cameras[1]
    seen.pop(bare)
    depth = measure_depth(ds, board, gt.T_ref_cam, seen, gt.T_ref_board, "none",
                          DepthConfig(model_unseen_views=False))
    assert set(depth.unmodelled) == {bare}
    assert set(depth.depth_models) == set(ds.cameras) - {bare}
    status = depth.status_dict()
    assert set(status["unmodelled"]) == {bare}
    found = depth_unmodelled({"depth": status}, [])
    assert [f["code"] for f in found] == ["depth_unmodelled"] and found[0]["cameras"] == [bare]
    assert "uncorrected" in found[0]["message"]
    assert depth_unmodelled({"depth": {"status": "none", "reason": None,
                                       "weak_cameras": {}}}, []) == []


def test_each_depth_view_gets_the_covariance_of_the_pose_its_plane_came_from():
    """:func:`view_pose_covariances`: a view the camera detected, its own PnP covariance
    moved from the board's body frame into the camera frame (the corners fix the board in the
    camera); the board it did not detect, its extrinsics' covariance plus the time model's
    uncertainty at its capture on each axis; a view with neither is left out (exact)."""
    from types import SimpleNamespace

    from rgbd_calib.core.geometry import adjoint, make_transform, rotvec_to_matrix
    from rgbd_calib.depth.stage import view_pose_covariances

    T = make_transform(rotvec_to_matrix([0.1, -0.4, 0.2]), [0.3, -0.1, 1.4])
    pnp = np.diag([1e-6, 2e-6, 3e-6, 4e-8, 5e-8, 6e-8])
    obs = [SimpleNamespace(camera="a", frame="000001", T_cam_board=T, covariance=pnp)]
    ext = np.diag([1e-7] * 3 + [1e-8] * 3)
    cov = view_pose_covariances(obs, {"a": {"000001": T}},
                                {"a": {"000002": T}, "b": {"000002": T, "000003": T}},
                                {"a": ext, "b": None}, {"a": {"000002": 2e-4},
                                                        "b": {"000002": 1e-4}})
    assert np.allclose(cov["a"]["000001"], adjoint(T) @ pnp @ adjoint(T).T)
    assert not np.allclose(cov["a"]["000001"], pnp)  # the frame matters: a lever of 1.4 m
    assert np.allclose(cov["a"]["000002"], ext + np.diag([0] * 3 + [4e-8] * 3))
    assert np.allclose(cov["b"]["000002"], np.diag([0] * 3 + [1e-8] * 3))
    assert "000003" not in cov["b"]  # the reference's extrinsics and a still board: exact
