"""The printed board's measured size: the scale and sigma two readings give, and the board file
rescaled to them in every single-face form (grid, explicit, ChArUco), read back exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import CONFIGS

from rgbd_calib.core.errors import BoardError, ConfigError
from rgbd_calib.model.board import refined_board
from rgbd_calib.model.board_file import load_board, save_board
from rgbd_calib.model.board_print import front_span_m, measured_print_scale, rescaled_board
from rgbd_calib.synth.imperfections import BoardPrint


def test_the_front_span_is_what_the_board_file_puts_there():
    thesis = load_board(CONFIGS / "board_thesis.yaml")
    assert front_span_m(thesis) == pytest.approx((0.400, 0.220))
    assert front_span_m(load_board(CONFIGS / "board_cube.yaml")) is None


def test_two_readings_give_one_scale_and_its_sigma():
    thesis = load_board(CONFIGS / "board_thesis.yaml")
    exact = measured_print_scale(thesis, (400.0, 220.0), 0.3)
    assert exact.scale == pytest.approx(1.0) and not exact.stretched
    assert exact.sigma == pytest.approx(0.3 / math.hypot(400.0, 220.0))
    large = measured_print_scale(thesis, (400.8, 220.44), 0.3)  # 0.2 % large both ways
    assert large.scale == pytest.approx(1.002) and large.sigma == pytest.approx(exact.sigma)
    # 2.3 sigmas apart: the sigma widens by that ratio, not yet a stretched print
    apart = measured_print_scale(thesis, (401.6, 220.1), 0.3)
    z = (401.6 / 400 - 220.1 / 220) / (0.3 * math.hypot(1 / 400, 1 / 220))
    assert not apart.stretched and apart.sigma == pytest.approx(z * exact.sigma)
    assert apart.across == pytest.approx(1.004) and apart.down == pytest.approx(220.1 / 220)
    # 0.6 % more across than down: stretched, held to half the gap
    stretched = measured_print_scale(thesis, (402.6, 220.1), 0.3)
    assert stretched.stretched and stretched.sigma >= (402.6 / 400 - 220.1 / 220) / 2


@pytest.mark.parametrize("reading, sigma, error", [
    ((40.0, 22.0), 0.3, BoardError),  # millimetres read as centimetres: over 5 % off
    ((400.0, -220.0), 0.3, ConfigError),
    ((400.0, float("nan")), 0.3, ConfigError),
    ((400.0, 220.0), 0.0, ConfigError),
    ((400.0, 220.0), 30.0, ConfigError),  # a sigma no board file can state
])
def test_bad_readings_are_one_line_errors(reading, sigma, error):
    thesis = load_board(CONFIGS / "board_thesis.yaml")
    with pytest.raises(error) as info:
        measured_print_scale(thesis, reading, sigma)
    assert "\n" not in str(info.value)


def test_a_multiface_target_is_measured_face_by_face():
    cube = load_board(CONFIGS / "board_cube.yaml")
    with pytest.raises(BoardError, match="each face"):
        measured_print_scale(cube, (100.0, 100.0), 0.3)
    with pytest.raises(BoardError, match="each face"):
        rescaled_board(cube, 1.001, 0.001)


@pytest.mark.parametrize("form", ["grid", "explicit", "charuco"])
def test_the_rescaled_file_reads_back_as_the_print(form, tmp_path):
    """The rescaled board is the board a renderer prints at that scale (synth's --print-scale:
    every corner scaled in the faces' planes, the thickness kept), and its file in the same form
    reads back to the same corners, panel and sigma."""
    if form == "charuco":
        board = load_board(CONFIGS / "board_charuco_a3.yaml")
    else:
        board = load_board(CONFIGS / "board_thesis.yaml")
        if form == "explicit":  # a board_refined.yaml: every corner listed
            board = refined_board(board, np.eye(4))
    scale = 1.0023
    rescaled = rescaled_board(board, scale, 0.0004)
    printed = BoardPrint(board.thickness, print_scale=scale).corners(board)
    np.testing.assert_allclose(rescaled.corners, printed, atol=1e-12)
    assert rescaled.thickness == board.thickness
    assert front_span_m(rescaled) == pytest.approx(tuple(scale * v for v in front_span_m(board)))
    path = tmp_path / "board.yaml"
    save_board(rescaled, path)
    again = load_board(path)
    assert ("grid" in path.read_text()) == (form == "grid")
    # OpenCV builds a ChArUco board's corners in float32: 0.1 um
    np.testing.assert_allclose(again.corners, rescaled.corners, atol=1e-7)
    np.testing.assert_allclose(again.panel, np.array(board.panel) * scale, atol=1e-12)
    assert again.print_scale_sigma == 0.0004
    assert list(again.ids) == list(board.ids)
