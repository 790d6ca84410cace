"""Board model: thesis Table 4.2, back-face winding, validation errors."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from conftest import CONFIGS

from rgbd_calib.core.errors import BoardError
from rgbd_calib.model.board import BACK, FRONT, thesis_board, winding_sign
from rgbd_calib.model.board_file import load_board, save_board

TABLE = CONFIGS / "board_thesis_table42.yaml"


def table42_raw() -> dict[int, np.ndarray]:
    """Table 4.2 exactly as printed in the thesis (corner order untouched)."""
    data = yaml.safe_load(TABLE.read_text())
    return {int(k): np.asarray(v, float) for k, v in data["markers"].items()}


def test_grid_form_reproduces_table_4_2():
    board = load_board(CONFIGS / "board_thesis.yaml")
    raw = table42_raw()
    assert sorted(board.ids.tolist()) == list(range(56)) == sorted(raw)
    for i, c in zip(board.ids, board.corners):
        face = board.faces[board.index_of[int(i)]]
        # the table lists every marker in front-face order; ours is detection order,
        # which differs from it exactly by a left-right mirror on the back face
        expected = raw[int(i)] if face == FRONT else raw[int(i)][[1, 0, 3, 2]]
        np.testing.assert_allclose(c, expected, atol=1e-12)
    assert np.sum(board.faces == FRONT) == np.sum(board.faces == BACK) == 28
    # origin at the outer bottom-left corner of marker 21; back face at z = -6.6 mm
    np.testing.assert_allclose(board.object_points([21])[0][3], [0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(board.object_points([55])[0][:, 2], -0.0066)
    # the back sheet's first column sits at the board's largest x
    assert board.object_points([28])[0][:, 0].max() == pytest.approx(0.40)


def test_thesis_board_in_code_matches_config():
    a, b = thesis_board(), load_board(CONFIGS / "board_thesis.yaml")
    np.testing.assert_allclose(a.corners, b.corners)
    assert a.panel == b.panel


def test_table_back_face_is_mirrored_against_aruco_detection():
    """Table 4.2's back markers, read as detection order, wind the wrong way for their face;
    and an image of the printed back sheet, seen from outside, detects corners in the order
    our loader stores (the mirror of the table's)."""
    raw = table42_raw()
    assert all(winding_sign(raw[i], FRONT) > 0 for i in range(28))
    assert all(winding_sign(raw[i], BACK) < 0 for i in range(28, 56))
    with pytest.raises(BoardError, match=r"28, 29"):
        load_board_text(TABLE.read_text().replace("corner_order: front", ""), "t.yaml")

    # Draw marker 28 as printed on the back sheet and view it from outside the back face:
    # ArUco's first corner (top-left of the pattern) must be the board corner at x = 0.40.
    board = thesis_board()
    d = board.aruco_dict
    img = np.full((300, 300), 255, np.uint8)
    img[50:250, 50:250] = cv2.aruco.generateImageMarker(d, 28, 200)
    corners, ids, _ = cv2.aruco.ArucoDetector(d).detectMarkers(img)
    assert ids is not None and int(ids.ravel()[0]) == 28
    tl = corners[0].reshape(4, 2)[0]
    assert tl[0] < 100 and tl[1] < 100  # detected TL is the pattern's top-left as printed
    # seen from the back, the printed top-left lands on the board's largest x
    assert board.object_points([28])[0][0].tolist() == pytest.approx([0.40, 0.22, -0.0066])
    assert raw[28][0].tolist() == pytest.approx([0.36, 0.22, -0.0066])


def load_board_text(text: str, name: str, tmp=None, **kw):
    import tempfile

    folder = Path(tempfile.mkdtemp())
    path = folder / name
    path.write_text(text)
    return load_board(path, **kw)


def test_fix_winding_option_matches_corner_order_front():
    text = TABLE.read_text().replace("corner_order: front", "")
    fixed = load_board_text(text, "t.yaml", fix_winding=True)
    np.testing.assert_allclose(fixed.corners, thesis_board().corners, atol=1e-12)


GRID = """dictionary: DICT_4X4_50
thickness: 0.005
grid: {rows: 2, cols: 3, marker_length: 0.05, separation: 0.01, front_first_id: 0,
       back_first_id: %s}
"""


@pytest.mark.parametrize("text, message", [
    (GRID % 3, r"duplicate marker id\(s\) \[3, 4, 5\]"),
    (GRID % 48, r"id\(s\) \[50, 51, 52, 53\] outside the dictionary"),
    ((GRID % 6).replace("DICT_4X4_50", "DICT_9X9"), "unknown ArUco dictionary"),
    (GRID % 6 + "colour: red\n", "unknown key"),
    ("dictionary: DICT_4X4_50\nthickness: 0.005\n", "exactly one of 'grid'"),
    ("dictionary: DICT_4X4_50\nthickness: 0.005\nmarkers:\n  0: [[0,0.05,0],[0.05,0.05,0],"
     "[0.05,0,0],[0,0.01,0]]\n", r"marker\(s\) \[0\] are not squares"),
    ("dictionary: DICT_4X4_50\nthickness: 0.005\nmarkers:\n  0: [[0,0.05,0],[0.05,0.05,0.01],"
     "[0.05,0,0],[0,0,0]]\n", "not planar"),
    ("dictionary: DICT_4X4_50\nthickness: 0.005\nmarkers:\n  0: [[0,0.05,0],[0.05,0.05,0]]\n",
     "expected 4 corners"),
    ("[1, 2", "not valid YAML"),
    (GRID % 6 + "print_scale_sigma: -0.001\n", "print_scale_sigma: must be positive"),
    (GRID % 6 + "print_scale_sigma: 0.5\n", "give at most 0.05"),
    (GRID % 6 + "print_scale_sigma: half a mm\n", "print_scale_sigma: expected a finite number"),
])
def test_bad_boards_fail_with_one_line(text, message):
    with pytest.raises(BoardError, match=message) as err:
        load_board_text(text, "bad.yaml")
    assert "\n" not in str(err.value) and "bad.yaml" in str(err.value)


def test_explicit_form_round_trip(tmp_path):
    from rgbd_calib.model.board_file import save_board

    board = thesis_board()
    save_board(board, tmp_path / "b.yaml")
    again = load_board(tmp_path / "b.yaml")
    np.testing.assert_allclose(again.corners, board.corners)


@pytest.mark.parametrize("path", [CONFIGS / "board_thesis.yaml",
                                  CONFIGS / "board_charuco_a3.yaml",
                                  CONFIGS / "board_cube.yaml"])
def test_the_printed_sizes_sigma_is_read_and_written_for_every_board_form(path, tmp_path):
    """``print_scale_sigma`` (how well the printed size is known, relative 1 sigma) is one
    top-level key of every board form: unstated it is None (the file's lengths taken as
    exact), stated it round-trips through save_board, and a refined board keeps it."""
    from rgbd_calib.model.board import refined_board, refined_multiface

    assert load_board(path).print_scale_sigma is None
    data = yaml.safe_load(path.read_text())
    data["print_scale_sigma"] = 0.0005
    (tmp_path / path.name).write_text(yaml.safe_dump(data))
    board = load_board(tmp_path / path.name)
    assert board.print_scale_sigma == 0.0005
    save_board(board, tmp_path / "again.yaml")
    assert load_board(tmp_path / "again.yaml").print_scale_sigma == 0.0005
    refined = (refined_multiface(board, {}) if board.sheets else
               refined_board(board, np.eye(4)) if board.charuco is None else board)
    assert refined.print_scale_sigma == 0.0005


# ------------------------------------------------------------------------ multi-face targets
CUBE, CUBE_CHARUCO, L_BOARD = (CONFIGS / "board_cube.yaml", CONFIGS / "board_cube_charuco.yaml",
                               CONFIGS / "board_L.yaml")
CUBE400_CHARUCO = CONFIGS / "board_cube400_charuco.yaml"
PLANE_TOL_M = 1e-12


def test_flat_board_face_poses_come_from_the_thickness():
    """The double-sided board's two faces as face poses: front the identity, back flipped about
    y at z = -thickness; each face's markers on its z = 0 plane, normal (0, 0, +-1)."""
    board = thesis_board()
    assert board.face_labels == (FRONT, BACK) and not board.is_multiface
    for face in (FRONT, BACK):
        T = board.T_board_face(face)
        np.testing.assert_array_equal(T[:3, 2], board.face_normal(face))
        np.testing.assert_array_equal(board.face_normal(face), [0, 0, face])
        local = (board.corners[board.faces == face].reshape(-1, 3) - T[:3, 3]) @ T[:3, :3]
        np.testing.assert_allclose(local[:, 2], 0.0, atol=PLANE_TOL_M)
        # detection order seen from outside: the winding is positive about the face normal
        c = board.corners[board.faces == face][0]
        assert np.cross(c[1] - c[0], c[3] - c[0]) @ board.face_normal(face) < 0


@pytest.mark.parametrize("path", [CUBE, CUBE_CHARUCO, CUBE400_CHARUCO, L_BOARD])
def test_multiface_faces_on_their_planes_and_round_trip(path, tmp_path):
    board = load_board(path)
    assert board.is_multiface and board.face_labels == tuple(range(1, len(board.sheets) + 1))
    assert len(np.unique(board.ids)) == len(board.ids)
    for s in board.sheets:
        T = board.T_board_face(s.label)
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        local = (board.corners[board.faces == s.label].reshape(-1, 3) - T[:3, 3]) @ T[:3, :3]
        np.testing.assert_allclose(local[:, 2], 0.0, atol=PLANE_TOL_M)
        # every marker seen from outside its face winds the detection way round
        for c in board.corners[board.faces == s.label]:
            assert np.cross(c[1] - c[0], c[3] - c[0]) @ board.face_normal(s.label) < 0
    out = tmp_path / "again.yaml"
    save_board(board, out)
    again = load_board(out)
    np.testing.assert_array_equal(again.ids, board.ids)
    np.testing.assert_allclose(again.corners, board.corners, atol=1e-12)
    np.testing.assert_array_equal(again.faces, board.faces)


@pytest.mark.parametrize("path, half_side", [(CUBE, 0.125), (CUBE400_CHARUCO, 0.2)])
def test_cube_faces_point_out_of_the_cube(path, half_side):
    """configs/board_cube.yaml (250 mm, ArUco) and board_cube400_charuco.yaml (400 mm,
    ChArUco): 6 faces of a cube centred at the origin, each face's measurements centred on
    its side, normals along +-x, +-y, +-z, one face per side."""
    board = load_board(path)
    normals = np.array([board.face_normal(f) for f in board.face_labels])
    np.testing.assert_allclose(np.abs(normals).sum(axis=0), [2, 2, 2], atol=1e-12)
    for f, n in zip(board.face_labels, normals):
        centre = board.corners[board.faces == f].reshape(-1, 3).mean(axis=0)
        # 1e-8: OpenCV's CharucoBoard keeps its chessboard corners in float32 (~4 nm here)
        np.testing.assert_allclose(centre, half_side * n, atol=1e-8)
    if path == CUBE:
        assert sorted(board.ids.tolist()) == list(range(54))


def _write(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "target.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["faces"][1]["board"]["grid"].update(front_first_id=5),
     "marker id 5 is printed on faces[0] and faces[1]"),
    (lambda d: d["faces"][1]["pose"].update(translation_m=[0.2, 0.0, 0.1]),
     "faces[0] and faces[1] pass through each other"),
    (lambda d: d["faces"][1]["board"]["grid"].update(back_first_id=60),
     "a face is one sheet"),
    (lambda d: d["faces"][1]["board"].update(dictionary="DICT_5X5_100"),
     "differs from the target's DICT_4X4_100"),
    (lambda d: d["faces"][1]["pose"].update(rotation_deg=[0, 90]),
     "faces[1].pose.rotation_deg: expected 3 numbers"),
    (lambda d: d["faces"][1].update(where=1), "unknown key(s) where"),
    (lambda d: d.update(faces=[]), "faces must be a list"),
])
def test_multiface_errors_name_file_face_and_fix(tmp_path, edit, message):
    data = yaml.safe_load(L_BOARD.read_text())
    edit(data)
    path = _write(tmp_path, data)
    with pytest.raises(BoardError) as err:
        load_board(path)
    assert str(path) in str(err.value) and message in str(err.value)
    assert "\n" not in str(err.value)


def test_concave_l_is_valid_and_faces_may_meet_at_an_edge(tmp_path):
    """Two sheets facing each other across a 90 deg corner (a concave L) meet at an edge
    without crossing; a face given as the path of a single-face board file."""
    data = yaml.safe_load(L_BOARD.read_text())
    data["faces"][1]["pose"] = {"rotation_deg": [0, -90, 0], "translation_m": [0.41, 0, 0.42]}
    (tmp_path / "charuco.yaml").write_text((CONFIGS / "board_charuco_a3.yaml").read_text()
                                           + "first_id: 56\n")
    data["faces"].append({"board": "charuco.yaml", "pose": {"rotation_deg": [90, 0, 0],
                                                           "translation_m": [0, -0.05, 0]}})
    data["faces"][2]["pose"]["translation_m"] = [0, -0.3, 0]
    board = load_board(_write(tmp_path, data))
    np.testing.assert_allclose(board.face_normal(2), [-1, 0, 0], atol=1e-12)
    assert board.sheets[2].board.charuco is not None and board.sheets[2].id_offset == 30000
    assert board.ids.max() < 30000 + 100 and len(board.face_labels) == 3


def test_a_render_printed_at_its_files_size_says_its_board_is_exact(tiny_dataset):
    """synth writes the board file as its user has it; printed at the file's size (no
    --print-scale) that file is exact, and it says so (print_scale_sigma 0: no board_size
    finding, no scale term in the sigmas)."""
    assert load_board(tiny_dataset / "board.yaml").print_scale_sigma == 0.0
