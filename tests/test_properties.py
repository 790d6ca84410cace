"""Property tests: the YAML loaders (rig, board, extrinsics) and geometry helpers that
test_geometry.py does not cover.

Loaders: any valid mapping written and read back is the same object; any garbage (random
YAML values, a valid file with one value replaced, random bytes) is either accepted or
rejected with an RgbdCalibError (a one-line user error), never another exception.
"""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.errors import RgbdCalibError
from rgbd_calib.core.geometry import (
    invert_transform,
    is_rigid,
    look_at,
    make_transform,
    matrix_to_quaternion_xyzw,
    matrix_to_rotvec,
    orthonormalize,
    quaternion_xyzw_to_matrix,
    rotation_angle_deg,
    rotvec_to_matrix,
    skew,
    transform_error,
)
from rgbd_calib.model.board import Board, board_from_grid
from rgbd_calib.model.board_file import load_board, save_board
from rgbd_calib.model.results import CameraExtrinsics, Extrinsics, load_extrinsics, write_extrinsics
from rgbd_calib.model.rig import Rig, load_rig, save_rig
from rgbd_calib.solve.pose import se3_exp

# tmp_path is reused across examples: every example writes its own file first
SETTINGS = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
unit = st.tuples(finite, finite, finite).filter(lambda v: np.linalg.norm(v) > 1e-3).map(
    lambda v: np.asarray(v) / np.linalg.norm(v))
camera_name = st.from_regex(r"[A-Za-z0-9_-]{1,10}", fullmatch=True)


@st.composite
def rotations(draw, max_angle=np.pi):
    return rotvec_to_matrix(draw(unit) * draw(st.floats(0, max_angle)))


@st.composite
def transforms(draw):
    return make_transform(draw(rotations()), draw(vec3))


# ----------------------------------------------------------------------------- garbage
leaf = (st.none() | st.booleans() | st.integers() | st.just(10**400) | st.floats()
        | st.text(max_size=12) | st.just("[[x]") | st.just(".nan"))
garbage = st.recursive(
    leaf,
    lambda inner: st.lists(inner, max_size=5)
    | st.dictionaries(st.text(max_size=8) | st.integers(-5, 5), inner, max_size=5),
    max_leaves=20,
)


def replace_somewhere(data, draw):
    """``data`` (nested dicts/lists) with one value, at a random path, replaced by garbage
    (or one garbage key added to a mapping)."""
    node = data
    while True:
        if isinstance(node, dict) and node:
            key = draw(st.sampled_from(sorted(node, key=str)))
        elif isinstance(node, list) and node:
            key = draw(st.integers(0, len(node) - 1))
        else:
            return data
        child = node[key]
        if not isinstance(child, (dict, list)) or not child or draw(st.booleans()):
            if isinstance(node, dict) and draw(st.integers(0, 4)) == 0:
                node[draw(st.text(min_size=1, max_size=6))] = draw(garbage)
            else:
                node[key] = draw(garbage)
            return data
        node = child


def assert_only_user_errors(load, path: Path) -> None:
    try:
        load(path)
    except RgbdCalibError as exc:
        assert "\n" not in str(exc), str(exc)
        assert str(path) in str(exc), str(exc)  # every message names the file


# ----------------------------------------------------------------------------- rig.yaml
@st.composite
def intrinsics(draw):
    width = draw(st.integers(1, 8192))
    height = draw(st.integers(1, 8192))
    pos = st.floats(1e-3, 1e5, allow_nan=False)
    n_dist = draw(st.sampled_from([4, 5, 8, 12, 14]))
    return CameraIntrinsics(
        width, height, draw(pos), draw(pos),
        draw(st.floats(0, width, exclude_min=True, exclude_max=True)),
        draw(st.floats(0, height, exclude_min=True, exclude_max=True)),
        tuple(draw(st.lists(finite, min_size=n_dist, max_size=n_dist))),
        draw(st.floats(1e-6, 1.0)),
    )


@st.composite
def rigs(draw):
    names = draw(st.lists(camera_name, min_size=1, max_size=5, unique=True))
    cams = {n: draw(intrinsics()) for n in names}
    return Rig(cams, draw(st.sampled_from(names)))


@SETTINGS
@given(rigs())
def test_rig_round_trip(tmp_path, rig):
    save_rig(rig, tmp_path / "rig.yaml")
    assert load_rig(tmp_path / "rig.yaml") == rig


@SETTINGS
@given(st.data())
def test_rig_garbage_is_a_user_error(tmp_path, data):
    rig = data.draw(rigs())
    raw = yaml.safe_load(yaml.safe_dump(rig.to_dict()))
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(replace_somewhere(raw, data.draw)))
    assert_only_user_errors(load_rig, path)
    path.write_text(yaml.safe_dump(data.draw(garbage)))
    assert_only_user_errors(load_rig, path)
    path.write_bytes(data.draw(st.binary(max_size=200)))
    assert_only_user_errors(load_rig, path)


# ----------------------------------------------------------------------------- extrinsics
@st.composite
def extrinsics(draw):
    names = draw(st.lists(camera_name, min_size=1, max_size=5, unique=True))
    sigma = st.floats(0, 10, allow_nan=False)
    cams = {n: CameraExtrinsics(n, np.eye(4) if k == 0 else draw(transforms()), draw(sigma),
                                draw(sigma)) for k, n in enumerate(names)}
    return Extrinsics(names[0], cams)


@SETTINGS
@given(extrinsics())
def test_extrinsics_round_trip(tmp_path, ext):
    write_extrinsics(ext, tmp_path / "extrinsics.yaml")
    back = load_extrinsics(tmp_path / "extrinsics.yaml", check_redundant=True)
    assert back.reference == ext.reference and list(back.cameras) == list(ext.cameras)
    for name, cam in ext.cameras.items():
        np.testing.assert_allclose(back.T_ref_cam(name), cam.T_ref_cam, atol=1e-12)
        assert back.cameras[name].sigma_rotation_deg == cam.sigma_rotation_deg
        assert back.cameras[name].sigma_translation_mm == cam.sigma_translation_mm


@SETTINGS
@given(st.data())
def test_extrinsics_garbage_is_a_user_error(tmp_path, data):
    raw = yaml.safe_load(yaml.safe_dump(_plain(data.draw(extrinsics()).to_dict())))
    path = tmp_path / "extrinsics.yaml"
    path.write_text(yaml.safe_dump(replace_somewhere(raw, data.draw)))
    assert_only_user_errors(load_extrinsics, path)
    assert_only_user_errors(functools.partial(load_extrinsics, check_redundant=True), path)
    path.write_text(yaml.safe_dump(data.draw(garbage)))
    assert_only_user_errors(load_extrinsics, path)


def test_extrinsics_with_hand_rounded_numbers_load(tmp_path):
    """translation_m / quaternion_xyzw rounded by hand (4 decimals) still agree with
    T_ref_cam; a real edit of one of them does not."""
    R = rotvec_to_matrix([0.1, -0.2, 0.3])
    T = make_transform(R, [0.4, 0.01, -0.02])
    cam = {"T_ref_cam": np.round(T, 4).tolist(), "translation_m": [0.4, 0.01, -0.02],
           "quaternion_xyzw": np.round(matrix_to_quaternion_xyzw(R), 4).tolist()}
    path = tmp_path / "e.yaml"
    path.write_text(yaml.safe_dump({"cameras": {"a": {"T_ref_cam": np.eye(4).tolist()},
                                                "b": cam}}))
    loaded = load_extrinsics(path, check_redundant=True)
    assert transform_error(loaded.T_ref_cam("b"), T)[1] < 0.1
    cam["quaternion_xyzw"] = [0, 0, 0, 1]
    path.write_text(yaml.safe_dump({"cameras": {"a": {"T_ref_cam": np.eye(4).tolist()},
                                                "b": cam}}))
    with pytest.raises(RgbdCalibError, match="quaternion_xyzw disagrees"):
        load_extrinsics(path, check_redundant=True)


def _plain(obj):
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return float(obj) if isinstance(obj, np.floating) else obj


# ----------------------------------------------------------------------------- board
@st.composite
def grid_boards(draw):
    rows, cols = draw(st.integers(1, 5)), draw(st.integers(1, 5))
    n = rows * cols
    front = draw(st.integers(0, 250 - n))
    back = draw(st.none() | st.integers(0, 250 - n).filter(lambda b: b + n <= front or
                                                          b >= front + n))
    return board_from_grid(
        "DICT_4X4_250", rows, cols, draw(st.floats(0.005, 0.3)), draw(st.floats(0, 0.05)),
        draw(st.floats(0.001, 0.05)), front, back, name=draw(camera_name))


def _same_board(a: Board, b: Board) -> None:
    assert a.dictionary == b.dictionary and a.name == b.name and a.thickness == b.thickness
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_allclose(a.corners, b.corners, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.panel, b.panel, rtol=0, atol=1e-12)


@SETTINGS
@given(grid_boards(), st.booleans())
def test_board_round_trip(tmp_path, board, explicit):
    if explicit:  # the explicit form: every marker's corners, in detection order
        board = Board(board.dictionary, board.ids, board.corners, board.faces, board.thickness,
                      board.panel, board.name)
    save_board(board, tmp_path / "board.yaml")
    _same_board(load_board(tmp_path / "board.yaml"), board)


@settings(max_examples=200, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_board_garbage_is_a_user_error(tmp_path, data):
    board = data.draw(grid_boards())
    if data.draw(st.booleans()):
        board = Board(board.dictionary, board.ids, board.corners, board.faces, board.thickness,
                      board.panel, board.name)
    raw = yaml.safe_load(yaml.safe_dump(_plain(board.to_dict())))
    path = tmp_path / "board.yaml"
    path.write_text(yaml.safe_dump(replace_somewhere(raw, data.draw)))
    assert_only_user_errors(load_board, path)
    path.write_text(yaml.safe_dump(data.draw(garbage)))
    assert_only_user_errors(load_board, path)


GRID = ("dictionary: DICT_4X4_100\nthickness: {t}\ngrid: {{rows: 2, cols: 2, marker_length: "
        "0.04, separation: 0.01, front_first_id: 0}}\n{extra}")
EXPLICIT = ("dictionary: DICT_4X4_100\nthickness: 0.0066\nmarkers:\n  {id}: [[0, 0.04, 0], "
            "[0.04, 0.04, 0], [0.04, 0, {z}], [0, 0, 0]]\n{extra}")


@pytest.mark.parametrize("text", [
    pytest.param(GRID.format(t="9" * 400, extra=""), id="thickness-400-digits"),
    pytest.param(EXPLICIT.format(id="9" * 30, z=0, extra=""), id="marker-id-30-digits"),
    pytest.param(EXPLICIT.format(id=1, z="9" * 400, extra=""), id="corner-400-digits"),
    pytest.param(EXPLICIT.format(id=1, z=0, extra="margin: abc\n"), id="explicit-margin-text"),
    pytest.param(EXPLICIT.format(id=1.5, z=0, extra=""), id="marker-id-1.5-truncated-to-1"),
])
def test_board_crashers(tmp_path, text):
    path = tmp_path / "board.yaml"
    path.write_text(text)
    with pytest.raises(RgbdCalibError):
        load_board(path)


@pytest.mark.parametrize("size", [1000, 100000])
def test_grid_larger_than_its_dictionary_fails_fast(tmp_path, monkeypatch, size):
    """Checked against the dictionary before the grid is built (100000 x 100000 would exhaust
    memory): building it is never reached (a structural check, not a timed one)."""
    import rgbd_calib.model.board_file as board_module

    def never(*args, **kwargs):
        raise AssertionError("the grid was built before its size was checked")

    monkeypatch.setattr(board_module, "board_from_grid", never)
    path = tmp_path / "board.yaml"
    path.write_text(
        GRID.replace("rows: 2, cols: 2", f"rows: {size}, cols: {size}").format(t=0.005, extra="")
    )
    with pytest.raises(RgbdCalibError) as err:
        load_board(path)
    assert len(str(err.value)) < 300, f"{len(str(err.value))} characters"
    assert "DICT_4X4_100 has only 100 ids" in str(err.value)


def test_many_ids_outside_the_dictionary_are_listed_briefly(tmp_path):
    """A grid that fits the dictionary's size but not its ids: at most 10 ids, then the count."""
    path = tmp_path / "board.yaml"
    path.write_text(
        GRID.replace("rows: 2, cols: 2", "rows: 5, cols: 10")
        .replace("front_first_id: 0", "front_first_id: 80")
        .format(t=0.005, extra="")
    )
    with pytest.raises(
        RgbdCalibError,
        match=r"\[100, 101, 102, 103, 104, 105, 106, 107, 108, 109, \.\.\.\] \(30 in all\) "
        "outside the dictionary",
    ):
        load_board(path)


# ----------------------------------------------------------------------------- geometry
@given(st.lists(finite, min_size=9, max_size=9))
def test_orthonormalize_returns_a_rotation(values):
    M = np.asarray(values).reshape(3, 3)
    assume(abs(np.linalg.det(M)) > 1e-3)
    R = orthonormalize(M)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(orthonormalize(R), R, atol=1e-9)  # idempotent


@given(transforms(), st.floats(1.01, 3), st.integers(0, 2))
def test_is_rigid_rejects_scale_and_bad_last_row(T, scale, axis):
    assert is_rigid(T)
    S = T.copy()
    S[:3, axis] *= scale
    assert not is_rigid(S)
    S = T.copy()
    S[3, axis] = 0.5
    assert not is_rigid(S)
    S = T.copy()
    S[:3, :3] = -S[:3, :3]  # a reflection is orthonormal but not a rotation
    assert not is_rigid(S)


@given(transforms(), transforms())
def test_transform_error_is_symmetric_and_zero_on_equal(T_a, T_b):
    deg_ab, mm_ab = transform_error(T_a, T_b)
    deg_ba, mm_ba = transform_error(T_b, T_a)
    assert deg_ab == pytest.approx(deg_ba, abs=1e-6) and mm_ab == pytest.approx(mm_ba)
    assert transform_error(T_a, T_a) == pytest.approx((0.0, 0.0), abs=1e-5)


@given(unit)
def test_half_turns_round_trip(axis):
    """Exactly pi (R = 2 n n^T - I): the quaternion's w = 0 branches of Shepperd's method."""
    R = 2.0 * np.outer(axis, axis) - np.eye(3)
    q = matrix_to_quaternion_xyzw(R)
    assert abs(q[3]) < 1e-7
    np.testing.assert_allclose(quaternion_xyzw_to_matrix(q), R, atol=1e-9)
    assert rotation_angle_deg(R) == pytest.approx(180.0, abs=1e-5)  # arccos near -1
    np.testing.assert_allclose(rotvec_to_matrix(matrix_to_rotvec(R)), R, atol=1e-7)


@given(rotations())
def test_rotation_angle_matches_rotvec_norm(R):
    assert rotation_angle_deg(R) == pytest.approx(
        np.degrees(np.linalg.norm(matrix_to_rotvec(R))), abs=1e-5)


@given(vec3, vec3)
def test_skew_is_the_cross_product(v, w):
    np.testing.assert_allclose(skew(v) @ w, np.cross(v, w), atol=1e-12)


@given(vec3, vec3, st.sampled_from([(0, 0, 1), (0, 1, 0), (1, 0, 0)]))
def test_look_at_is_rigid_and_looks_at_the_target(eye, target, up):
    assume(np.linalg.norm(target - eye) > 1e-3)
    T_world_cam = look_at(eye, target, up)  # includes looking straight along up
    assert is_rigid(T_world_cam, atol=1e-9)
    direction = (target - eye) / np.linalg.norm(target - eye)
    np.testing.assert_allclose(T_world_cam[:3, 2], direction, atol=1e-9)
    np.testing.assert_allclose(invert_transform(T_world_cam)[:3, :3] @ direction, [0, 0, 1],
                               atol=1e-9)


@settings(deadline=None)
@given(st.tuples(finite, finite, finite), vec3)
def test_se3_exp_matches_gtsam(omega, v):
    gtsam = pytest.importorskip("gtsam")
    xi = np.concatenate([omega, v])
    np.testing.assert_allclose(se3_exp(xi), gtsam.Pose3.Expmap(xi).matrix(), atol=1e-8)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-0.3, 0.3), min_size=5, max_size=5),
       st.lists(st.floats(-0.5, 0.5), min_size=6, max_size=6))
def test_projection_matches_opencv(dist, xy):
    """CameraIntrinsics.project (OpenCV's k1 k2 p1 p2 k3 model) against cv2.projectPoints."""
    intr = CameraIntrinsics(1280, 720, 633.5, 631.0, 640.2, 358.4, tuple(dist))
    pts = np.column_stack([np.reshape(xy, (3, 2)), [1.0, 1.5, 2.0]])
    ours = intr.project(pts)
    theirs, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), intr.K, intr.dist)
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), atol=1e-6)
