"""Board self-calibration in the bundle adjustment (``bundle.board: refine``).

The back sheet's pose relative to the front sheet, ``T_front_back`` (a Pose3 with its tilts
held), moves the back-face markers' board points. Measured (see the numbers next to each
bound) on the analytic scene of test_bundle and on a rendered race rig (8 cameras, 848x480,
20 frames, seed 3) with the back sheet glued off by 1.5 mm, -1.0 mm, 0.3 deg.
"""

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from conftest import assert_transforms_close
from test_bundle import K, perturb, scene

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.config import BundleConfig
from rgbd_calib.core.geometry import (
    invert_transform,
    look_at,
    make_transform,
    rotvec_to_matrix,
    transform_error,
)
from rgbd_calib.model.board import thesis_board
from rgbd_calib.solve.bundle import (
    BundleProblem,
    MarkerMeasurement,
    bundle_adjust,
    intrinsics_vector,
)
from rgbd_calib.solve.bundle_factors import view_factor, view_factor_intrinsics

GLUE = (1.5, -1.0, 0.3)  # back sheet off by dx mm, dy mm, rot deg (as synth --glue)
GLUE_OFFSET_TOL_MM = 0.1  # acceptance of the issue
GLUE_ROTATION_TOL_DEG = 0.02


def _glue_transform(board, dx_mm, dy_mm, rot_deg, dz_mm=0.0):
    """``T_front_back`` of a back sheet rotated about its grid centre and shifted (synth's
    convention, docs/synthetic.md)."""
    back = board.corners[board.faces < 0].reshape(-1, 3)
    c = np.r_[(back[:, :2].min(axis=0) + back[:, :2].max(axis=0)) / 2, 0.0]
    R = rotvec_to_matrix([0, 0, np.radians(rot_deg)])
    return make_transform(R, c - R @ c + np.array([dx_mm, dy_mm, dz_mm]) / 1000.0)


def _with_faces(meas, board):
    return [replace(m, face=int(board.faces[board.index_of[m.marker_id]])) for m in meas]


def _numerical_jacobian(f, values, keys):
    e0 = f.unwhitenedError(values)
    cols = []
    for key, kind, dim in keys:
        for j in range(dim):
            d = np.zeros(dim)
            d[j] = 1e-6
            moved = gtsam.Values(values)
            if kind == "pose":
                moved.update(key, values.atPose3(key).retract(d))
            else:
                moved.update(key, values.atVector(key) + d)
            cols.append((f.unwhitenedError(moved) - e0) / 1e-6)
    return e0, np.array(cols).T


def _factor_values(rng):
    T_cam = make_transform(rotvec_to_matrix([0.1, -0.2, 0.05]), [0.1, 0.2, -0.1])
    T_board = T_cam @ make_transform(rotvec_to_matrix([0.2, 0.1, 0.3]), [0.05, -0.02, 1.3])
    T_fb = make_transform(rotvec_to_matrix([0.0, 0.0, 0.01]), [0.002, -0.001, 0.0005])
    P = rng.uniform(-0.2, 0.2, (4, 4, 3))
    P[:2, :, 2], P[2:, :, 2] = 0.0, -0.006  # two front, two back markers
    back = np.array([False, False, True, True])
    measured = rng.normal([640, 360], 80, (4, 4, 2))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3(T_cam))
    values.insert(1, gtsam.Pose3(T_board))
    values.insert(3, gtsam.Pose3(T_fb))
    return values, P, back, measured


def test_back_sheet_jacobians_match_numerical():
    """The whole factor's error against numerical differences, for every key (right
    perturbations, rotation first), with pinhole K."""
    values, P, back, measured = _factor_values(np.random.default_rng(2))
    f = view_factor(0, 1, K, P, measured, 1.0, "none", 3.0, moving=[(3, back, None)])
    A, b = f.linearize(values).jacobian()
    e0, numerical = _numerical_jacobian(f, values, [(0, "pose", 6), (1, "pose", 6),
                                                    (3, "pose", 6)])
    np.testing.assert_allclose(b, -e0)
    np.testing.assert_allclose(A, numerical, atol=2e-3 * np.abs(A).max())
    assert np.all(A[:16, 12:] == 0)  # front markers do not depend on the back sheet


def test_back_sheet_with_refined_intrinsics_jacobians_match_numerical():
    """Both refinements at once: camera, board, intrinsics and back-sheet blocks."""
    values, P, back, measured = _factor_values(np.random.default_rng(3))
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    intr = CameraIntrinsics(1280, 720, 600.0, 605.0, 640.0, 360.0,
                            (-0.05, 0.02, 0.001, -0.0005, 0.01))
    values.insert(2, intrinsics_vector(intr, names) * 1.002)
    f = view_factor_intrinsics(0, 1, 2, intr, names, P, measured, 1.0, "none", 3.0,
                                moving=[(3, back, None)])
    A, b = f.linearize(values).jacobian()
    e0, numerical = _numerical_jacobian(
        f, values, [(0, "pose", 6), (1, "pose", 6), (2, "vector", len(names)), (3, "pose", 6)])
    np.testing.assert_allclose(b, -e0)
    np.testing.assert_allclose(A, numerical, atol=2e-3 * np.abs(A).max())


def _glued_scene(seed, glue=GLUE, n_views=25, sigma_px=0.2):
    """As test_bundle.scene with two cameras on each side of the board (both faces seen in
    one view), the back-face corners projected from the glued-off sheet ``T_front_back``."""
    board = thesis_board()
    rng = np.random.default_rng(seed)
    T_fb = _glue_transform(board, *glue)
    eyes = [[0.0, 0, 1.2], [0.8, 0, 1.2], [0.0, 3.2, 1.2], [0.8, 3.2, 1.2]]
    T_world_cam = {f"c{i}": look_at(np.array(e) + rng.normal(0, .02, 3), [0.4, 1.6, 1.0])
                   for i, e in enumerate(eyes)}
    T_ref_cam = {c: invert_transform(T_world_cam["c0"]) @ T for c, T in T_world_cam.items()}
    boards, meas = {}, []
    for v in range(n_views):
        R = rotvec_to_matrix([np.pi / 2, 0, 0]) @ rotvec_to_matrix(rng.normal(0, 0.3, 3))
        T_world_board = make_transform(R, [rng.uniform(0.2, 0.6), rng.uniform(1.4, 1.8), 1.0])
        view = f"{v:06d}"
        boards[view] = invert_transform(T_world_cam["c0"]) @ T_world_board
        for c, T in T_ref_cam.items():
            T_cam_board = invert_transform(T) @ boards[view]
            for face in (1, -1):
                if face * (T_cam_board[:3, :3] @ [0, 0, 1]) @ T_cam_board[:3, 3] > 0:
                    continue  # that face looks away from the camera
                sel = board.faces == face
                for i, P in zip(board.ids[sel], board.corners[sel]):
                    P_true = P @ T_fb[:3, :3].T + T_fb[:3, 3] if face < 0 else P
                    p = P_true @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
                    uv = (p[:, :2] / p[:, 2:]) * [K[0, 0], K[1, 1]] + K[:2, 2]
                    if np.all((uv > 0) & (uv < [1280, 720])):
                        meas.append(MarkerMeasurement(
                            c, view, int(i), uv + rng.normal(0, sigma_px, uv.shape), P, face))
    return T_ref_cam, boards, meas, T_fb


def _solve(T_ref_cam, boards, meas, mode, seed=0):
    rng = np.random.default_rng(seed)
    init_cam = {c: (T if c == "c0" else perturb(T, rng)) for c, T in T_ref_cam.items()}
    init_board = {v: perturb(T, rng) for v, T in boards.items()}
    return bundle_adjust(BundleProblem(meas, {c: K for c in T_ref_cam}, "c0", init_cam,
                                       init_board, BundleConfig(board=mode)))


def test_fixed_board_path_ignores_the_faces():
    """bundle.board fixed: the faces the measurements now carry change nothing, bit for bit
    (also checked once against the code before this change: identical)."""
    T_ref_cam, boards, meas = scene(np.random.default_rng(5), n_views=8)
    a = _solve(T_ref_cam, boards, meas, "fixed")
    b = _solve(T_ref_cam, boards, _with_faces(meas, thesis_board()), "fixed")
    assert b.board is None
    for c in a.T_ref_cam:
        assert np.array_equal(a.T_ref_cam[c], b.T_ref_cam[c])
        assert np.array_equal(a.covariance[c], b.covariance[c])
    assert a.final_error == b.final_error


def test_refine_recovers_the_glue_error():
    """Analytic scene (2 + 2 cameras 1280x720 facing each other across the board, 25 views,
    0.2 px noise), back sheet off by 1.5 / -1.0 mm and 0.3 deg. Measured (seed 0): fixed
    worst camera 3.65 mm / 0.161 deg; refine 0.83 mm / 0.030 deg (c1, on the front side, is
    0.59 mm off with the fixed board too: this scene's noise floor); T_front_back within
    0.034 mm / 0.012 deg of the truth: offset (1.495, -1.032) mm, 0.288 deg, sigmas
    0.038 / 0.044 mm, 0.0076 deg."""
    T_ref_cam, boards, meas, T_fb = _glued_scene(0)
    fixed = _solve(T_ref_cam, boards, meas, "fixed")
    refined = _solve(T_ref_cam, boards, meas, "refine")
    worst = {}
    for name, res in (("fixed", fixed), ("refine", refined)):
        errs = [transform_error(res.T_ref_cam[c], T_ref_cam[c]) for c in T_ref_cam]
        worst[name] = (max(e[1] for e in errs), max(e[0] for e in errs))
    assert worst["refine"][0] < 1.2 and worst["refine"][1] < 0.05, worst
    assert worst["fixed"][0] > 3 * worst["refine"][0], worst
    model = refined.board
    assert not model.held
    assert_transforms_close(model.T_front_back, T_fb, GLUE_OFFSET_TOL_MM, GLUE_ROTATION_TOL_DEG)
    np.testing.assert_allclose(model.offset_mm[:2], GLUE[:2], atol=GLUE_OFFSET_TOL_MM)
    assert abs(model.rotation_deg - GLUE[2]) < GLUE_ROTATION_TOL_DEG
    s = model.sigmas
    assert abs(model.offset_mm[0] - GLUE[0]) < 4 * s["offset_x_mm"] + 1e-3
    assert abs(model.offset_mm[1] - GLUE[1]) < 4 * s["offset_y_mm"] + 1e-3
    assert abs(model.rotation_deg - GLUE[2]) < 4 * s["rotation_deg"] + 1e-4


def test_back_sheet_held_when_never_seen_with_the_front():
    """Only back-face markers in a view that no camera sees from the front: the back sheet's
    pose is unobservable (it trades against those board poses); it is held and said so."""
    T_ref_cam, boards, meas, _ = _glued_scene(7, glue=(0, 0, 0), n_views=8)
    front_views = {m.view for m in meas if m.face > 0}
    only_front = [m for m in meas if m.face > 0]
    res = _solve(T_ref_cam, boards, only_front, "refine")
    assert "never seen" in res.board.held
    assert np.array_equal(res.board.T_front_back, np.eye(4))
    # both faces, but never in the same view
    split = [m for m in meas if (m.face > 0) == (int(m.view) % 2 == 0)]
    assert front_views  # the scene sees both faces
    res = _solve(T_ref_cam, boards, split, "refine")
    assert "unobservable" in res.board.held


def test_clean_board_refine_no_worse_than_fixed():
    """A correctly glued board: refining finds no glue and is no worse than the fixed board
    beyond noise. Measured on the analytic scene, seeds 1-4, worst camera error fixed ->
    refine: 0.459 -> 0.429 mm, 0.0141 -> 0.0179 deg; 0.510 -> 0.524, 0.0168 -> 0.0170;
    0.484 -> 0.467, 0.0163 -> 0.0180; 0.716 -> 0.731, 0.0244 -> 0.0251 (ratios <= 1.03 in mm,
    <= 1.27 in deg); back sheet within 2.6 sigma of nothing. Rendered race rig (seed 3):
    fixed 0.140 mm / 0.0028 deg, refine 0.131 mm / 0.0032 deg, back sheet (0.004, 0.005) mm,
    -0.002 deg (sigmas 0.021 / 0.005 mm, 0.0016 deg)."""
    T_ref_cam, boards, meas, T_fb = _glued_scene(1, glue=(0.0, 0.0, 0.0))
    worst = {}
    for mode in ("fixed", "refine"):
        res = _solve(T_ref_cam, boards, meas, mode)
        errs = [transform_error(res.T_ref_cam[c], T_ref_cam[c]) for c in T_ref_cam]
        worst[mode] = (max(e[1] for e in errs), max(e[0] for e in errs))
    refined = res
    assert worst["refine"][0] < 1.25 * worst["fixed"][0], worst
    assert worst["refine"][1] < 1.5 * worst["fixed"][1], worst
    s = refined.board.sigmas
    assert np.all(np.abs(refined.board.offset_mm[:2]) < 4 * np.array(
        [s["offset_x_mm"], s["offset_y_mm"]]))
    assert abs(refined.board.rotation_deg) < 4 * s["rotation_deg"]


def test_refined_board_file_round_trip(tmp_path):
    """board_refined.yaml is the explicit form (the grid form cannot shift a back sheet):
    load_board reads back the moved back corners and the new thickness."""
    from rgbd_calib.model.board import refined_board
    from rgbd_calib.model.board_file import load_board, save_board

    board = thesis_board()
    T_fb = _glue_transform(board, 1.5, -1.0, 0.3, dz_mm=-0.4)  # 0.4 mm thicker
    out = refined_board(board, T_fb)
    save_board(out, tmp_path / "board_refined.yaml")
    back = load_board(tmp_path / "board_refined.yaml")
    assert back.grid is None
    np.testing.assert_array_equal(back.ids, board.ids)
    np.testing.assert_array_equal(back.faces, board.faces)
    assert back.thickness == pytest.approx(board.thickness + 0.0004, abs=1e-12)
    front = board.faces > 0
    np.testing.assert_allclose(back.corners[front], board.corners[front], atol=1e-15)
    moved = board.corners[~front].reshape(-1, 3) @ T_fb[:3, :3].T + T_fb[:3, 3]
    np.testing.assert_allclose(back.corners[~front].reshape(-1, 3), moved, atol=1e-12)
    assert back.marker_length == pytest.approx(board.marker_length, rel=1e-12)


# ------------------------------------------------------------------ the pipeline, rendered
@pytest.fixture(scope="module")
def glued_race(tmp_path_factory):
    """Race rig (8 cameras 848x480, 20 frames, seed 3), back sheet glued off by GLUE; the
    board file nominal. Calibrated with the board fixed and refined (no depth stage)."""
    from rgbd_calib.core.config import load_config
    from rgbd_calib.model.dataset import FolderDataset
    from rgbd_calib.pipelines.calibrate import calibrate
    from rgbd_calib.synth.render import SynthParams, synthesize

    out = tmp_path_factory.mktemp("synth") / "glued"
    synth = synthesize(out, "race", 20, 3, thesis_board(), SynthParams(glue=GLUE), workers=2)
    runs = {}
    for mode in ("fixed", "refine", "auto"):
        cfg = load_config(None, workers=2, refine="none", **{
            "bundle.board": mode, "bundle.intrinsics": "auto" if mode == "auto" else "fixed"})
        runs[mode] = calibrate(FolderDataset(synth.path), thesis_board(), cfg)
    return synth, runs


RACE_MAX_MM, RACE_MAX_DEG = 1.0, 0.1  # acceptance of the issue for the race layout


def test_pipeline_glued_board(glued_race):
    """Measured: fixed keeps 4 of 8 cameras (the pose graph flags every view of the four
    back-facing ones, right0-3, as outliers: the nominal board's PnP poses are off by the
    glue); refine keeps all 8, worst 0.106 mm / 0.0030 deg (race acceptance: 1.0 mm /
    0.1 deg), back sheet (1.494, -1.000) mm, 0.2996 deg, T_front_back within 0.011 mm /
    0.0004 deg of the truth. (With the per-view model-error floor, ``pose.model_error_px``
    0.1-0.5 px, fixed keeps all 8, the back-facing ones 1.1-3.9 mm off at 7-18 claimed
    sigmas: the floor is off by default.)"""
    from rgbd_calib.synth.render import load_ground_truth

    synth, runs = glued_race
    gt = load_ground_truth(synth.path)
    fixed, refined = runs["fixed"], runs["refine"]
    assert fixed.bundle.board is None
    # measured: right0-3 dropped. A known gap of "model error is not an outlier": on this
    # seed the camera-level model-error rule does not catch the back-facing side (on seed 5
    # it keeps all 8); board refinement is what keeps them here.
    assert len(fixed.extrinsics.cameras) == 4
    assert not refined.extrinsics.unconnected
    assert len(refined.extrinsics.cameras) == 8
    for c, e in refined.extrinsics.cameras.items():
        assert_transforms_close(e.T_ref_cam, gt.T_ref_cam[c], RACE_MAX_MM, RACE_MAX_DEG)
        assert_transforms_close(e.T_ref_cam, gt.T_ref_cam[c], 0.3, 0.01)  # measured <= 0.11
    # the refined board explains the flagged cameras' error: sigmas not inflated, honest
    ratios = [transform_error(e.T_ref_cam, gt.T_ref_cam[c])[1] / e.sigma_translation_mm
              for c, e in refined.extrinsics.cameras.items() if c != gt.reference]
    assert 0.2 < float(np.sqrt(np.mean(np.square(ratios)))) < 3.0, ratios
    model = refined.bundle.board
    assert not model.held
    assert_transforms_close(model.T_front_back, gt.T_front_back, GLUE_OFFSET_TOL_MM,
                            GLUE_ROTATION_TOL_DEG)
    np.testing.assert_allclose(model.offset_mm[:2], GLUE[:2], atol=GLUE_OFFSET_TOL_MM)
    assert abs(model.rotation_deg - GLUE[2]) < GLUE_ROTATION_TOL_DEG


def test_pipeline_glued_board_auto(glued_race):
    """The default (``auto`` board and intrinsics) on the glued set: the back sheet is freed
    because it keeps the 4 cameras the nominal board loses; all 8 within the race bounds and
    the glue recovered as with ``refine``."""
    from rgbd_calib.synth.render import load_ground_truth

    synth, runs = glued_race
    gt = load_ground_truth(synth.path)
    auto = runs["auto"]
    ladder = auto.self_calibration
    assert ladder is not None and ladder.chosen.board
    assert [f.level.name for f in ladder.fits][:2] == ["nominal", "board"]
    assert ladder.fits[1].accepted and ladder.fits[1].cameras == 8
    assert len(auto.extrinsics.cameras) == 8 and not auto.extrinsics.unconnected
    for c, e in auto.extrinsics.cameras.items():
        assert_transforms_close(e.T_ref_cam, gt.T_ref_cam[c], RACE_MAX_MM, RACE_MAX_DEG)
    assert_transforms_close(auto.bundle.board.T_front_back, gt.T_front_back,
                            GLUE_OFFSET_TOL_MM, GLUE_ROTATION_TOL_DEG)


def test_pipeline_writes_board_refined_and_report(glued_race, tmp_path):
    """board_refined.yaml puts every corner within 0.05 mm of the printed board (measured
    0.008 mm; the nominal file is 2.08 mm off); report.json's board.refined and the
    board_glue finding name the offset."""
    import json

    from rgbd_calib.model.board_file import load_board
    from rgbd_calib.model.rig import load_rig
    from rgbd_calib.outputs.report import validate_report
    from rgbd_calib.outputs.writer import write_outputs
    from rgbd_calib.synth.render import load_ground_truth

    synth, runs = glued_race
    rig = load_rig(synth.path / "rig.yaml")
    written = write_outputs(runs["refine"], rig, tmp_path)
    assert tmp_path / "board_refined.yaml" in written
    board = load_board(tmp_path / "board_refined.yaml")
    nominal = thesis_board()
    truth = load_ground_truth(synth.path).board_print(nominal).corners(nominal)
    assert np.abs(board.corners - truth).max() < 5e-5
    report = json.loads((tmp_path / "report.json").read_text())
    validate_report(report)
    refined = report["board"]["refined"]
    assert refined["held"] is None
    np.testing.assert_allclose(refined["offset_mm"], GLUE[:2], atol=GLUE_OFFSET_TOL_MM)
    glue = [w for w in report["warnings"] if w["code"] == "board_glue"]
    assert len(glue) == 1 and "right" in glue[0]["message"] and "down" in glue[0]["message"]
    assert "board_refined.yaml" in glue[0]["advice"]
    # the views the pose graph rejected under the nominal board fit the refined one: no
    # camera is inconsistent (the glue's warning is the verdict's reason). Measured: 32
    # pose-graph outliers, 30 used by the bundle and fitting (0.04-0.12 px, typical view
    # 0.043); left1/000000 and right2/000018 (tilted 64-67 deg) fit at 0.28-0.30 px and stay
    # listed
    codes = {w["code"] for w in report["warnings"]}
    assert not codes & {"inconsistent_camera", "not_calibrated"}, codes
    back = next(w for w in report["warnings"] if w["code"] == "fitting_outlier_views")
    assert int(back["message"].split()[0]) >= 20, back
    assert report["summary"]["verdict"] == "check"
    # the fixed run writes no board file and no board.refined
    write_outputs(runs["fixed"], rig, tmp_path / "fixed")
    assert not (tmp_path / "fixed" / "board_refined.yaml").exists()
    assert "refined" not in json.loads((tmp_path / "fixed" / "report.json").read_text())["board"]


# ------------------------------------------------------------------ board scale from depth
def _scale_report(factors, marker_length_m=0.05):
    return {"board": {"marker_length_m": marker_length_m},
            "cameras": {c: {"depth_scale_factor": f, "depth_scale_sigma": s}
                        for c, (f, s) in factors.items()}}


def test_common_depth_scale_names_the_print():
    """A 40 mm print of a 50 mm board file: every camera's depth reads 0.8 of the distance
    the calibration puts the board at; the printed length is the file's times that ratio.
    One board_scale finding replaces the per-camera depth_scale ones."""
    from rgbd_calib.outputs.report.findings import board_scale, common_depth_scale, depth_scale

    print_40 = {"a": (0.800, 0.002), "b": (0.803, 0.003), "c": (0.797, 0.002)}
    assert common_depth_scale(print_40) == pytest.approx(0.8, abs=0.002)
    report = _scale_report(print_40)
    found = board_scale(report, [])
    assert len(found) == 1 and found[0]["code"] == "board_scale"
    assert "40.0 mm" in found[0]["message"] and "50.0 mm" in found[0]["message"]
    assert "20.0% smaller" in found[0]["message"]
    assert depth_scale(report, found) == []
    (blamed,) = depth_scale(report, [])  # without it: every camera blamed, in one finding
    assert blamed["cameras"] == ["a", "b", "c"]
    # one camera disagrees: its depth, not the board
    assert common_depth_scale({**print_40, "d": (1.0, 0.002)}) is None
    # all alike but within 1 %: depth units, not a wrong print
    assert common_depth_scale({"a": (1.006, 0.001), "b": (1.007, 0.001)}) is None
    assert common_depth_scale({"a": (0.8, 0.002)}) is None  # one camera proves nothing


def test_board_and_intrinsics_refined_together():
    """Both refinements in one bundle (exact rig intrinsics, no distortion): the glue is still
    recovered (measured: within 0.020 mm / 0.012 deg; the cameras move by up to 2.6 mm, the
    focal-length / distance trade-off test_intrinsics measures on clean intrinsics)."""
    T_ref_cam, boards, meas, T_fb = _glued_scene(0)
    intr = CameraIntrinsics(1280, 720, K[0, 0], K[1, 1], K[0, 2], K[1, 2], (0.0,) * 5)
    rng = np.random.default_rng(0)
    init_cam = {c: (T if c == "c0" else perturb(T, rng)) for c, T in T_ref_cam.items()}
    init_board = {v: perturb(T, rng) for v, T in boards.items()}
    res = bundle_adjust(BundleProblem(meas, {c: K for c in T_ref_cam}, "c0", init_cam,
                                      init_board,
                                      BundleConfig(board="refine", intrinsics="refine",
                                                   intrinsics_params=["fx", "fy", "cx", "cy"]),
                                      intrinsics={c: intr for c in T_ref_cam}))
    assert set(res.intrinsics) == set(T_ref_cam)
    assert_transforms_close(res.board.T_front_back, T_fb, GLUE_OFFSET_TOL_MM,
                            GLUE_ROTATION_TOL_DEG)


def test_pipeline_names_a_wrong_marker_length(tmp_path_factory, tmp_path):
    """synth --print-scale 0.8: the 40 mm markers of the thesis board file printed at 32 mm.
    Measured (race 848x480, 8 frames, seed 3; left2 and left3 have no usable view at that
    size): the six cameras' depth factors 0.79996-0.80006; one board_scale error naming
    32.0 mm, no per-camera depth_scale finding (20 frames: seven cameras, 0.79993-0.80002)."""
    import json

    from rgbd_calib.core.config import load_config
    from rgbd_calib.model.dataset import FolderDataset
    from rgbd_calib.model.rig import load_rig
    from rgbd_calib.outputs.writer import write_outputs
    from rgbd_calib.pipelines.calibrate import calibrate
    from rgbd_calib.synth.render import SynthParams, synthesize

    out = tmp_path_factory.mktemp("synth") / "print80"
    synth = synthesize(out, "race", 8, 3, thesis_board(), SynthParams(print_scale=0.8),
                       workers=2)
    result = calibrate(FolderDataset(synth.path), thesis_board(), load_config(None, workers=2))
    write_outputs(result, load_rig(synth.path / "rig.yaml"), tmp_path)
    report = json.loads((tmp_path / "report.json").read_text())
    codes = [w["code"] for w in report["warnings"]]
    assert codes.count("board_scale") == 1 and "depth_scale" not in codes
    message = next(w["message"] for w in report["warnings"] if w["code"] == "board_scale")
    assert "32.0 mm" in message and "40.0 mm" in message, message
    # the dataset's board file is the nominal one, as its user has it: no print_scale_sigma
    from rgbd_calib.model.board_file import load_board

    assert load_board(synth.path / "board.yaml").print_scale_sigma is None


def test_board_scale_names_a_charuco_boards_square_and_marker():
    """A ChArUco print scales the squares and the markers together: the line names both
    (before, it called the chessboard square the "marker length")."""
    from rgbd_calib.outputs.report.findings import board_scale, board_scale_sentence

    line = board_scale_sentence(0.8, 0.03, 0.04)
    assert "square_length 32.0 mm and marker_length 24.0 mm" in line, line
    assert "the file says 40.0 and 30.0 mm" in line, line
    report = _scale_report({"a": (0.800, 0.002), "b": (0.801, 0.002)})
    report["board"] = {"marker_length_m": 0.03, "square_length_m": 0.04}
    found = board_scale(report, [])
    assert "square_length 32.0 mm" in found[0]["message"]
    assert "chessboard square" in found[0]["advice"]
