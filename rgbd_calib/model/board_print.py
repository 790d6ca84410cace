"""The printed board's size: what its front sheet should measure, and a board file rescaled to
what it does measure.

A print a fraction of a percent off its file scales every translation of a calibration, and
neither the images nor the depth can tell (docs/accuracy.md, "The board's printed size"). The
user measures the span of the front sheet's outermost marker corners (a ChArUco board: its
inner chessboard corners) across and down with a rule or calipers; :func:`measured_print_scale`
turns the two readings into one scale with its relative 1 sigma, and :func:`rescaled_board`
gives the board with every printed length multiplied by it and that sigma as its
``print_scale_sigma`` (docs/formats.md). The thickness is not printed and is kept. A printer
that stretches one direction more than the other (the paper's feed) cannot be held by one
scale: the mean is taken and the sigma widened to cover half the difference, so the
calibration's sigmas say it rather than a silent bias. Pure numpy; used by the ``board``
command.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..core.errors import BoardError, ConfigError
from .board import APRILGRID, FRONT, Board
from .board_file import MAX_PRINT_SCALE_SIGMA

PLAUSIBLE_SCALE = 0.05  # a measured span more than 5 % off the file's: the wrong corners measured
STRETCH_SIGMAS = 3.0  # the two directions' ratios this many sigmas apart: a stretched print


def front_span_m(board: Board) -> tuple[float, float] | None:
    """The span ``(across, down)`` in metres of the front face's outermost marker corners (a
    ChArUco board's are its inner chessboard corners), as the board file puts them; None for a
    multi-face target (each face is its own sheet) or a board without front markers."""
    if board.sheets:
        return None
    front = board.corners[board.faces == FRONT].reshape(-1, 3)
    if not len(front):
        return None
    w, h = front[:, :2].max(axis=0) - front[:, :2].min(axis=0)
    return float(w), float(h)


@dataclass(frozen=True)
class PrintScale:
    """The printed size against the board file from a measured front sheet: ``scale`` the
    printed / file ratio (the mean of the two directions weighed by their spans), ``sigma``
    its relative 1 sigma (the measurement's, widened by the two directions' disagreement in
    sigmas where it exceeds 1, and to half their difference beyond 3: ``stretched``);
    ``across`` and ``down`` each direction's own ratio."""

    scale: float
    sigma: float
    across: float
    down: float
    stretched: bool


def measured_print_scale(board: Board, measured_mm: tuple[float, float],
                         sigma_mm: float) -> PrintScale:
    """The :class:`PrintScale` of ``board`` whose front sheet measures ``measured_mm``
    (across, down; mm) to ``sigma_mm`` (1 sigma of one reading, mm). One-line errors: a
    BoardError for a multi-face target or a reading more than 5 % off the file (the wrong
    corners measured), a ConfigError for a reading or sigma that is not a positive length or
    a sigma beyond what a board file can state."""
    span = front_span_m(board)
    if span is None:
        raise BoardError(f"{_where(board)}: a multi-face target has no front sheet to measure; "
                         "rescale each face's board mapping by its own sheet's measurement")
    if not (sigma_mm > 0 and math.isfinite(sigma_mm)):
        raise ConfigError(f"--measured-sigma {sigma_mm}: expected a positive length in mm (0.2 "
                         "for a steel rule read to a fifth of a millimetre)")
    expected = np.array(span) * 1000.0
    got = np.array(measured_mm, dtype=float)
    if not (np.all(np.isfinite(got)) and np.all(got > 0)):
        raise ConfigError(f"--measured {got[0]:g} {got[1]:g}: expected two positive lengths in mm")
    ratios = got / expected
    if np.any(np.abs(ratios - 1.0) > PLAUSIBLE_SCALE):
        raise BoardError(
            f"{_where(board)}: the front sheet measured {got[0]:g} x {got[1]:g} mm against "
            f"{expected[0]:.1f} x {expected[1]:.1f} mm in the file, more than "
            f"{PLAUSIBLE_SCALE:.0%} off; measure the outermost marker corners (a ChArUco "
            "board: its inner chessboard corners) across and down, in mm")
    weights = (expected / sigma_mm) ** 2  # each ratio's sigma is sigma_mm / expected
    scale = float(np.sum(weights * ratios) / np.sum(weights))
    spread = abs(float(ratios[0] - ratios[1]))
    z = spread / (sigma_mm * math.hypot(*(1.0 / expected)))  # the directions' gap in sigmas
    # two readings that disagree beyond their sigma widen it by their Birge ratio (z: the
    # chi of one degree of freedom); a print stretched beyond 3 sigma is held to half its gap
    sigma = float(max(1.0, z) / math.sqrt(np.sum(weights)))
    stretched = z > STRETCH_SIGMAS
    if stretched:
        sigma = max(sigma, spread / 2.0)
    if sigma > MAX_PRINT_SCALE_SIGMA:
        raise ConfigError(f"--measured-sigma {sigma_mm} mm: a relative sigma of {sigma:.3f} "
                          "over this board's span; measure to better than "
                          f"{MAX_PRINT_SCALE_SIGMA:.0%}")
    return PrintScale(scale, sigma, float(ratios[0]), float(ratios[1]), stretched)


def rescaled_board(board: Board, scale: float, sigma: float) -> Board:
    """``board`` with every printed length multiplied by ``scale`` (its markers' corners in the
    faces' planes about the board frame's origin, the panel, the grid's or the ChArUco
    board's lengths) and ``print_scale_sigma = sigma``; the thickness kept. A multi-face
    target raises BoardError (its faces are printed and measured one by one)."""
    if board.sheets:
        raise BoardError(f"{_where(board)}: rescale each face's board mapping of a multi-face "
                         "target by its own sheet's measurement")
    corners = board.corners.copy()
    corners[..., :2] *= scale
    grid = board.grid
    if board.board_type == APRILGRID:  # its tagSpacing is relative to tagSize
        grid = {**grid, "tagSize": grid["tagSize"] * scale}
    elif grid is not None:
        grid = {**grid, "marker_length": grid["marker_length"] * scale,
                "separation": grid["separation"] * scale}
    pattern = board.pattern
    if board.charuco is not None:
        pattern = replace(pattern, square_length=pattern.square_length * scale,
                          marker_length=pattern.marker_length * scale)
    elif pattern is not None:  # a checkerboard
        pattern = replace(pattern, col_spacing=pattern.col_spacing * scale,
                          row_spacing=pattern.row_spacing * scale)
    panel = tuple(float(v) * scale for v in board.panel)
    return replace(board, corners=corners, panel=panel, grid=grid, pattern=pattern,
                   print_scale_sigma=float(sigma))


def _where(board: Board) -> str:
    return str(board.source) if board.source is not None else f"board {board.name!r}"
