"""Issue 14, item 1: no failure of one camera pair ends a run.

Pairs of no, tiny and degenerate (single plane) overlap are built from an analytic scene
(textured rectangles ray-cast in numpy, D435 noise), so these tests need no rendering; the
end-to-end fallback runs ``calibrate`` on the session's small race rig."""

from __future__ import annotations

import numpy as np
import pytest
from analytic_scene import BOX, BOX_SIDE, CAM_A, CAM_B, FLOOR, SIDE, WALL, scene_cloud
from analytic_scene import nudge as _nudge

from rgbd_calib.core.config import REGISTRATION_METHODS, DepthConfig
from rgbd_calib.core.geometry import invert_transform, transform_error
from rgbd_calib.depth import information as DI
from rgbd_calib.depth import registration as D
from rgbd_calib.depth import stage as S
from rgbd_calib.depth.registration import DepthPair, pair_dicts


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(4)
    rects = (FLOOR, WALL, SIDE, BOX, BOX_SIDE)
    return {
        "a": scene_cloud("a", CAM_A, rects, rng),
        "b": scene_cloud("b", CAM_B, rects, rng),
    }


# --------------------------------------------------------------------------- single pairs
def test_a_good_scene_pair_registers(scene):
    """The control: the analytic pair itself is fine (so the failures below are the overlap's)."""
    reg = D.register_pair(scene["a"], scene["b"], _nudge(CAM_A), CAM_B, "colored-icp")
    assert reg.accepted, reg.reason
    err_deg, err_mm = transform_error(reg.T_b_a, invert_transform(CAM_B) @ CAM_A)
    assert err_mm < 3.0 and err_deg < 0.1


@pytest.mark.parametrize("method", REGISTRATION_METHODS)
def test_no_overlap_rejects_the_pair_instead_of_raising(scene, method):
    """b sees only a plane 0.5 m behind what a sees, inside a's view: ICP has points but no
    correspondence within its distance (Open3D raised "No correspondences found")."""
    rng = np.random.default_rng(5)
    far_wall = (WALL[0] + np.array([0.5, 0.0, 0.0]), WALL[1], WALL[2])
    a = scene_cloud("a", CAM_A, (WALL,), rng)
    b = scene_cloud("b", CAM_B, (far_wall,), rng)
    reg = D.register_pair(a, b, CAM_A, CAM_B, method)
    assert not reg.accepted and reg.reason
    assert not np.any(reg.information)


def test_tiny_overlap_is_rejected_with_a_reason(scene):
    a = scene["a"]
    centre = a.points[a.n_points // 2]
    patch = a.select(np.linalg.norm(a.points - centre, axis=1) < 0.05)
    reg = D.register_pair(patch, scene["b"], _nudge(CAM_A), CAM_B, "colored-icp")
    assert not reg.accepted and "correspondences" in reg.reason
    assert reg.rejected_by[0] == "correspondences"


@pytest.mark.parametrize("method", REGISTRATION_METHODS)
def test_single_untextured_plane_is_rejected_as_degenerate(method):
    rng = np.random.default_rng(6)
    a = scene_cloud("a", CAM_A, (FLOOR,), rng, textured=False)
    b = scene_cloud("b", CAM_B, (FLOOR,), rng, textured=False)
    reg = D.register_pair(a, b, _nudge(CAM_A), CAM_B, method)
    assert not reg.accepted and "poorly conditioned" in reg.reason
    assert "conditioning" in reg.rejected_by and reg.to_dict()["rejected_by"] == list(
        reg.rejected_by)


def test_an_exception_inside_one_pair_rejects_only_that_pair(scene, monkeypatch):
    calls = []

    def flaky(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("[Open3D Error] (...) ColoredICP.cpp:102: No correspondences "
                               "found between source and target pointcloud.")
        return real(*args, **kwargs)

    real = D._colored_icp_call
    monkeypatch.setattr(D, "_colored_icp_call", flaky)
    reg = D.register_pair(scene["a"], scene["b"], _nudge(CAM_A), CAM_B, "colored-icp")
    assert not reg.accepted and "No correspondences found" in reg.reason
    assert reg.rejected_by == ("failed",)
    # anything else a pair raises is caught one level up, in the stage
    monkeypatch.setattr(S, "register_pair", lambda *a, **k: 1 / 0)
    reg = S._register_safely(scene["a"], scene["b"], CAM_A, CAM_B, "colored-icp",
                             DepthConfig())
    assert not reg.accepted and "ZeroDivisionError" in reg.reason


# --------------------------------------------------------------------------- whole run
# static clouds from 2 frames and every camera registered (no board-based selection), in
# this process (monkeypatched): these runs check the flow only
FAST_DEPTH = {"max_frames": 2, "board_weak_sigma_mm": 0.0, "board_weak_sigma_deg": 0.0}


def _open3d_failure(*args, **kwargs):
    raise RuntimeError("\x1b[1;31m[Open3D Error] (...) ColoredICP.cpp:102: No correspondences "
                       "found between source and target pointcloud.\x1b[0;m")


@pytest.fixture(scope="module")
def line_board_only(small_line, tmp_path_factory):
    """The small thesis-line rig calibrated without depth (detections cached for the runs
    below)."""
    from rgbd_calib.core.config import CalibrationConfig
    from rgbd_calib.model.board import thesis_board
    from rgbd_calib.model.dataset import FolderDataset
    from rgbd_calib.pipelines.calibrate import calibrate

    cache = tmp_path_factory.mktemp("fallback")
    run = lambda **kw: calibrate(FolderDataset(small_line.path), thesis_board(),  # noqa: E731
                                 CalibrationConfig(**kw, depth=FAST_DEPTH, workers=1),
                                 cache_dir=cache)
    return run, run(refine="none"), FolderDataset(small_line.path).rig


def _assert_board_result(result, board_only, rig):
    from rgbd_calib.outputs.report.build import report_dict

    assert result.depth is not None and result.depth.fallback
    assert not result.depth.relative_poses and not any(p.accepted for p in result.depth.pairs)
    for name, cam in board_only.extrinsics.cameras.items():
        np.testing.assert_allclose(result.extrinsics.cameras[name].T_ref_cam, cam.T_ref_cam,
                                   atol=1e-9)
    report = report_dict(result, rig, pair_dicts(result.depth.pairs),
                         result.depth.depth_scale_dict())
    codes = [w["code"] for w in report["warnings"]]
    assert "depth_unused" in codes and report["summary"]["verdict"] != "good"


def test_calibrate_falls_back_to_the_board_when_every_pair_fails(line_board_only, monkeypatch):
    run, board_only, rig = line_board_only
    monkeypatch.setattr(S, "register_pair", _open3d_failure)
    result = run()  # default: colored ICP
    assert result.depth.pairs, "the thesis line has overlapping pairs"
    for p in result.depth.pairs:
        assert "No correspondences found" in p.reason and "\x1b" not in p.reason
    _assert_board_result(result, board_only, rig)


def test_calibrate_falls_back_when_the_joint_solve_fails(line_board_only, monkeypatch):
    from rgbd_calib.pipelines import calibrate as C

    run, board_only, rig = line_board_only
    real = C.bundle_sound_first

    def failing(*args, **kwargs):
        if args[0].relative_poses:  # the call with depth pairs
            raise RuntimeError("Indeterminant linear system detected while working near "
                               "variable 7 (Symbol: x7).")
        return real(*args, **kwargs)

    def accepted(cloud_a, cloud_b, T_ref_a, T_ref_b, method, config, *rest):  # plausible
        T_b_a = invert_transform(T_ref_b) @ T_ref_a
        return D.PairRegistration(
            cloud_a.camera, cloud_b.camera, method, T_b_a, T_b_a, np.eye(6) * 1e6,
            DI.INFORMATION_FRAME, 0.9, 1.0, 1.0, 1.0, 0.1, 5000, 0.0, 0.0, True, None, 0.0)

    monkeypatch.setattr(S, "register_pair", accepted)
    monkeypatch.setattr(C, "bundle_sound_first", failing)
    result = run()
    assert any("not used: the joint solve with the depth pairs failed" in p.reason
               for p in result.depth.pairs)
    _assert_board_result(result, board_only, rig)


def test_a_pair_against_the_board_and_an_unused_pair_say_their_kind():
    """The stage's own rejections carry their kind (``rejected_by``) like register_pair's: a
    move beyond the board's uncertainty and the pair's (``beyond_extrinsics``), and a pair
    accepted but left out of the solve (``not_used``); the report's findings read the kind."""
    from dataclasses import replace

    base = D.failed_registration("a", "b", "colored-icp", invert_transform(CAM_B) @ CAM_A,
                                 "placeholder")
    moved = base.T_b_a.copy()
    moved[:3, 3] += [0.02, 0.0, 0.0]  # 20 mm
    tight = np.diag([1e8] * 3 + [1e8] * 3)  # the pair's own sigma: 0.1 mm / 0.006 deg
    reg = replace(base, T_b_a=moved, information=tight, accepted=True, reason=None,
                  rejected_by=(), correction_mm=20.0)
    board = {c: np.diag([1e-8] * 3 + [1e-8] * 3) for c in ("a", "b")}  # 0.1 mm
    out = S.consistent_with_board(reg, board, {"a": CAM_A, "b": CAM_B}, DepthConfig())
    assert not out.accepted and out.rejected_by == ("beyond_extrinsics",)
    assert out.to_dict()["rejected_by"] == ["beyond_extrinsics"]
    # within the board's uncertainty (1 m sigma): kept as it was
    loose = {c: np.eye(6) for c in ("a", "b")}
    assert S.consistent_with_board(reg, loose, {"a": CAM_A, "b": CAM_B}, DepthConfig()) is reg
    depth = S.DepthRefinement("colored-icp", {}, {}, [DepthPair(reg)], [], {})
    (pair,) = depth.with_fallback("the joint solve failed").pairs
    assert not pair.accepted and pair.to_dict()["rejected_by"] == ["not_used"]
