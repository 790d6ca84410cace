"""Targets behind the board-file reader's table of types (issue 57): Kalibr's AprilGrid and
checkerboard files read as they are, detected where a projection puts them, and every bad
target file one line naming the file and the fix."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from conftest import SHARED_DATA, shared_data_missing
from typer.testing import CliRunner

from rgbd_calib.cli.commands import app
from rgbd_calib.core.errors import BoardError
from rgbd_calib.detect.checkerboard import order_by_colour
from rgbd_calib.detect.markers import detect_markers
from rgbd_calib.model.aprilgrid import corner_squares
from rgbd_calib.model.board import APRILGRID, CHECKERBOARD
from rgbd_calib.model.board_file import load_board, save_board

runner = CliRunner()

KALIBR_APRILGRID = """target_type: 'aprilgrid' #gridtype
tagCols: 2               #number of apriltags
tagRows: 2               #number of apriltags
tagSize: 0.088           #size of apriltag, edge to edge [m]
tagSpacing: 0.3          #ratio of space between tags to tagSize
"""
KALIBR_CHECKERBOARD = """target_type: 'checkerboard' #gridtype
targetCols: 6               #number of internal chessboard corners
targetRows: 7               #number of internal chessboard corners
rowSpacingMeters: 0.06      #size of one chessboard square [m]
colSpacingMeters: 0.05      #size of one chessboard square [m]
"""
# Kalibr's own tag36h11 codes of ids 0..3 (kalibr_create_target_pdf, from the AprilTags C++
# library), to print a tag exactly as Kalibr does
KALIBR_CODES = (0xD5D628584, 0xD97F18B49, 0xDD280910E, 0xE479E9C98)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _kalibr_page(board, px_per_m: float, margin_px: int) -> np.ndarray:
    """The AprilGrid page as ``kalibr_create_target_pdf`` draws it (a 2-cell border, the code
    bits turned half a turn, black squares at the tag corners), fronto-parallel: board point
    (x, y) at pixel (margin + x * s, H - margin - y * s)."""
    g = board.grid
    size, gap = g["tagSize"], g["tagSpacing"] * g["tagSize"]
    w = int(round((g["tagCols"] * (size + gap)) * px_per_m)) + 2 * margin_px
    h = int(round((g["tagRows"] * (size + gap)) * px_per_m)) + 2 * margin_px
    page = np.full((h, w), 255, np.uint8)

    def fill(x0, x1, y0, y1):  # board-frame rectangle, metres
        page[int(round(h - margin_px - y1 * px_per_m)):int(round(h - margin_px - y0 * px_per_m)),
             int(round(margin_px + x0 * px_per_m)):int(round(margin_px + x1 * px_per_m))] = 0

    bit = size / 10.0
    for k in range(g["tagCols"] * g["tagRows"]):
        r, c = divmod(k, g["tagCols"])
        x, y = c * (size + gap), r * (size + gap)
        fill(x, x + size, y, y + size)
        code = np.array([[0 if KALIBR_CODES[k] & (1 << (6 * i + j)) else 1 for j in range(6)]
                         for i in range(6)])
        code = np.rot90(code, 2)  # Kalibr's rotation=2
        for i in range(6):
            for j in range(6):
                if not code[i, j]:  # a white bit (row 0 at the top)
                    page[int(round(h - margin_px - (y + (8 - i) * bit) * px_per_m)):
                         int(round(h - margin_px - (y + (7 - i) * bit) * px_per_m)),
                         int(round(margin_px + (x + (j + 2) * bit) * px_per_m)):
                         int(round(margin_px + (x + (j + 3) * bit) * px_per_m))] = 255
    for _, x0, x1, y0, y1 in corner_squares(board):
        fill(x0, x1, y0, y1)
    return page


def test_a_kalibr_aprilgrid_file_is_read_as_it_is_and_its_print_detected_in_kalibr_order(
        tmp_path):
    board = load_board(_write(tmp_path, "april_6x6.yaml", KALIBR_APRILGRID))
    assert board.board_type == APRILGRID and board.border_bits == 2
    assert board.dictionary == "DICT_APRILTAG_36h11" and board.ids.tolist() == [0, 1, 2, 3]
    # tag 0 at the origin, tag 1 to its right, tag 2 above it (Kalibr's grid)
    lows = board.corners[:, :, :2].min(axis=1)
    assert np.allclose(lows, [[0, 0], [0.088 * 1.3, 0], [0, 0.088 * 1.3],
                              [0.088 * 1.3, 0.088 * 1.3]])
    assert len(corner_squares(board)) == 9  # shared between neighbours, drawn once
    scale, margin = 2500.0, 60  # px per metre
    page = cv2.GaussianBlur(_kalibr_page(board, scale, margin), (0, 0), 0.8)
    det = detect_markers(page, board)
    assert det.ids.tolist() == [0, 1, 2, 3]
    h = page.shape[0]
    xy = board.object_points(det.ids)[:, :, :2]
    expected = np.stack([margin + xy[..., 0] * scale, h - margin - xy[..., 1] * scale], axis=-1)
    # pixel centres at integer coordinates: a board edge at pixel boundary b lies at b - 0.5
    err = np.abs(det.corners_px - (expected - 0.5))
    assert err[det.refined].max() < 0.3, err


def test_a_kalibr_checkerboard_file_is_read_and_written_back_in_this_projects_form(tmp_path):
    board = load_board(_write(tmp_path, "checker.yaml", KALIBR_CHECKERBOARD))
    assert board.board_type == CHECKERBOARD
    spec = board.pattern
    assert (spec.cols, spec.rows, spec.col_spacing, spec.row_spacing) == (6, 7, 0.05, 0.06)
    assert len(spec.saddles()) == 42 and len(board.ids) == 5 * 6
    save_board(board, tmp_path / "again.yaml")
    again = load_board(tmp_path / "again.yaml")
    assert np.array_equal(again.corners, board.corners) and again.board_type == CHECKERBOARD


def _checker_image(spec, H: np.ndarray, size=(640, 480)) -> np.ndarray:
    """The printed chessboard (top-left square black) warped by ``H`` (board metres ->
    pixels)."""
    s = 400  # px per metre on the flat print
    sx, sy = spec.square_xy
    flat = np.full((int(spec.height * s) + 1, int(spec.width * s) + 1), 255, np.uint8)
    for r, row in enumerate(spec.black_squares()):
        for c, black in enumerate(row):
            if black:
                flat[round(r * sy * s):round((r + 1) * sy * s),
                     round(c * sx * s):round((c + 1) * sx * s)] = 0
    # flat pixel centre (u, v) is board point ((u + 0.5) / s, height - (v + 0.5) / s)
    A = np.array([[1 / s, 0, 0.5 / s], [0, -1 / s, spec.height - 0.5 / s], [0, 0, 1]])
    img = cv2.warpPerspective(flat, H @ A, size, borderValue=200)
    return cv2.GaussianBlur(img, (0, 0), 0.7)


@pytest.mark.parametrize("turn", [0, 90, 180, 270])
def test_a_checkerboard_view_names_its_corners_by_the_squares_colours_however_it_is_turned(
        tmp_path, turn):
    board = load_board(_write(tmp_path, "checker.yaml", KALIBR_CHECKERBOARD))
    spec = board.pattern
    a = np.radians(turn + 8)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) * 700.0
    centre = np.array([spec.width / 2, spec.height / 2])
    H = np.eye(3)
    H[:2, :2] = R @ np.diag([1.0, -1.0])  # board y up -> image y down
    H[:2, 2] = np.array([320.0, 240.0]) - H[:2, :2] @ centre
    det = detect_markers(_checker_image(spec, H), board)
    assert len(det) > 0
    obj = board.object_points(det.ids)[..., :2].reshape(-1, 2)
    expected = obj @ H[:2, :2].T + H[:2, 2]
    assert np.abs(det.corners_px.reshape(-1, 2) - expected).max() < 0.5


def test_the_detectors_corner_order_is_turned_to_the_boards(tmp_path):
    """A grid found mirrored or half a turn off is put back in saddle order."""
    board = load_board(_write(tmp_path, "checker.yaml", KALIBR_CHECKERBOARD))
    spec = board.pattern
    H = np.array([[600.0, 0, 100], [0, -600.0, 420], [0, 0, 1]])
    img = _checker_image(spec, H)
    xy = spec.saddles()[:, :2]
    true = (xy @ H[:2, :2].T + H[:2, 2]).reshape(spec.rows, spec.cols, 2)
    for found in (true, true[::-1, ::-1], true[:, ::-1], true[::-1, :]):
        assert np.allclose(order_by_colour(img, found), true)


@pytest.mark.parametrize("text, says", [
    ("target_type: circlegrid\ntargetCols: 6\ntargetRows: 7\nspacingMeters: 0.02\n",
     "target_type 'circlegrid'"),
    ("target_type: checkerboard\ntargetCols: 2\ntargetRows: 5\nrowSpacingMeters: 0.02\n"
     "colSpacingMeters: 0.02\n", "too small"),
    ("target_type: checkerboard\ntargetCols: 6\ntargetRows: 6\nrowSpacingMeters: 0.02\n"
     "colSpacingMeters: 0.02\n", "half a turn"),
    ("target_type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSize: 88\ntagSpacing: 0.3\n",
     "cannot be metres"),
    ("target_type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 30\n",
     "fraction of tagSize"),
    ("target_type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\n", "tagSpacing"),
    ("type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 0.3\n"
     "back_first_id: 10\n", "reuses the front's tag ids"),
])
def test_a_bad_target_file_is_one_line_naming_the_file(tmp_path, text, says):
    path = _write(tmp_path, "target.yaml", text)
    with pytest.raises(BoardError) as err:
        load_board(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and says in message, message


def test_calibrate_with_an_unknown_kalibr_target_exits_2_and_writes_nothing(tmp_path):
    path = _write(tmp_path, "target.yaml", "target_type: circlegrid\ntargetCols: 6\n")
    dataset = tmp_path / "ds"
    (dataset / "cam0" / "color").mkdir(parents=True)
    (dataset / "rig.yaml").write_text("cameras:\n  cam0: {width: 640, height: 480}\n")
    out = tmp_path / "out"
    result = runner.invoke(app, ["calibrate", str(dataset), "--board", str(path),
                                 "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert "target_type 'circlegrid'" in result.output and not out.exists()


WEBCAMS = SHARED_DATA / "webcam-chessboard-2cam"


def _webcam_dataset(root: Path) -> tuple[Path, Path]:
    """``shared/data/webcam-chessboard-2cam`` as a dataset folder: sets 0-3 the 4 pairs, sets
    4-7 cam0 alone and 8-11 cam1 alone (its intrinsics views); the board as Kalibr's file."""
    ds = root / "ds"
    for cam, k in (("cam0", 0), ("cam1", 1)):
        (ds / cam / "color").mkdir(parents=True)
        for i in range(4):
            shutil.copy(WEBCAMS / "frames_pair" / f"camera{k}_{i}.png",
                        ds / cam / "color" / f"{i:06d}.png")
            shutil.copy(WEBCAMS / "frames" / f"camera{k}_{i}.png",
                        ds / cam / "color" / f"{4 + 4 * k + i:06d}.png")
    (ds / "rig.yaml").write_text("cameras:\n  cam0: {width: 1280, height: 720}\n"
                                 "  cam1: {width: 1280, height: 720}\n")
    target = _write(root, "target.yaml", "target_type: checkerboard\ntargetCols: 7\n"
                    "targetRows: 4\nrowSpacingMeters: 0.0319\ncolSpacingMeters: 0.0319\n")
    return ds, target


def _pose_error(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    E = np.linalg.inv(A) @ B
    angle = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)))
    return 1000 * float(np.linalg.norm(A[:3, 3] - B[:3, 3])), float(angle)


@pytest.mark.skipif(not WEBCAMS.is_dir(), reason=shared_data_missing(WEBCAMS.name))
def test_two_real_webcams_and_a_chessboard_agree_with_opencvs_stereo_calibration(tmp_path):
    """The documented path (a dataset folder, Kalibr's checkerboard file, intrinsics from
    scratch) against cv2.stereoCalibrate on the same corners with cv2.calibrateCamera's
    intrinsics: within 3 of the claimed sigmas (measured 2026-12-07: 1.96 mm / 0.58 deg
    against sigmas 1.59 mm / 0.27 deg), and a verdict that is not GOOD for four pairs."""
    ds, target = _webcam_dataset(tmp_path)
    board = load_board(target)
    spec, quads = board.pattern, board.pattern.quads()
    obj = spec.saddles().astype(np.float32)
    corners = {}
    for cam in ("cam0", "cam1"):
        for path in sorted((ds / cam / "color").glob("*.png")):
            det = detect_markers(cv2.imread(str(path)), board)
            assert len(det), f"no chessboard found in {path.name} of {cam}"
            px = np.zeros((len(obj), 2), np.float32)
            for i, c in zip(det.ids, det.corners_px):
                px[quads[i]] = c
            corners[cam, path.stem] = px
    K = {}
    for cam in ("cam0", "cam1"):
        pts = [v for (c, _), v in corners.items() if c == cam]
        _, M, d, _, _ = cv2.calibrateCamera([obj] * len(pts), pts, (1280, 720), None, None)
        K[cam] = (M, d)
    pairs = [f"{i:06d}" for i in range(4)]
    *_, R, T, _, _ = cv2.stereoCalibrate(
        [obj] * 4, [corners["cam0", f] for f in pairs], [corners["cam1", f] for f in pairs],
        *K["cam0"], *K["cam1"], (1280, 720), flags=cv2.CALIB_FIX_INTRINSIC)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, T.ravel()
    out = tmp_path / "out"
    result = runner.invoke(app, ["calibrate", str(ds), "--board", str(target), "--out",
                                 str(out)])
    assert result.exit_code in (0, 3), result.output
    ex = yaml.safe_load((out / "extrinsics.yaml").read_text())
    cam1 = ex["cameras"]["cam1"]
    mm, deg = _pose_error(np.array(cam1["T_ref_cam"]), np.linalg.inv(M))
    assert mm < 3 * cam1["sigma_translation_mm"] and deg < 3 * cam1["sigma_rotation_deg"], (
        mm, deg, cam1)
    assert ex["verdict"]["grade"] != "good"


def test_images_of_a_kalibr_aprilgrid_calibrated_with_another_board_say_what_they_show(tmp_path):
    """A tag family that does not match the images: one line naming the AprilGrid the images
    show and the file to give, exit 2, no result written."""
    grid = load_board(_write(tmp_path, "april.yaml", KALIBR_APRILGRID))
    page = cv2.GaussianBlur(_kalibr_page(grid, 2500.0, 60), (0, 0), 0.8)
    h, w = page.shape
    dataset = tmp_path / "ds"
    for cam in ("c0", "c1"):
        (dataset / cam / "color").mkdir(parents=True)
        for f in range(3):
            cv2.imwrite(str(dataset / cam / "color" / f"{f:06d}.png"), page)
    (dataset / "rig.yaml").write_text(f"cameras:\n  c0: {{width: {w}, height: {h}}}\n"
                                      f"  c1: {{width: {w}, height: {h}}}\n")
    out = tmp_path / "out"
    result = runner.invoke(app, ["calibrate", str(dataset), "--board",
                                 str(Path(__file__).parents[1] / "configs/board_thesis.yaml"),
                                 "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert "Kalibr AprilGrid" in result.output and "target_type: aprilgrid" in result.output
    # nothing written: the folder the run created is gone with the detection cache it started
    assert not out.exists()
