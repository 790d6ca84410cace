"""Board model: thesis Table 4.2, back-face winding, validation errors."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from conftest import CONFIGS

from rgbd_calib.board import BACK, FRONT, load_board, thesis_board, winding_sign
from rgbd_calib.errors import BoardError

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
])
def test_bad_boards_fail_with_one_line(text, message):
    with pytest.raises(BoardError, match=message) as err:
        load_board_text(text, "bad.yaml")
    assert "\n" not in str(err.value) and "bad.yaml" in str(err.value)


def test_explicit_form_round_trip(tmp_path):
    from rgbd_calib.board import save_board

    board = thesis_board()
    save_board(board, tmp_path / "b.yaml")
    again = load_board(tmp_path / "b.yaml")
    np.testing.assert_allclose(again.corners, board.corners)
