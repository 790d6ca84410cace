"""The checkerboard target: a plain chessboard, measured by its inner (saddle) corners.

Geometry (board frame, docs/formats.md): ``cols`` x ``rows`` inner corners, ``cols + 1`` x
``rows + 1`` squares of ``col_spacing`` x ``row_spacing`` metres; origin at the outer
bottom-left corner of the chessboard, x right and y up as seen from the printed face, z out of
it. The top-left square is black. Saddle id ``r * cols + c`` is the inner corner in row ``r``
(from the top) and column ``c`` (from the left).

A view must show the whole board (``cv2.findChessboardCornersSB`` finds all corners or none).
Which corner is which is read from the squares' colours: the detector's order is turned so
that the inner square at the top-left is black. A board whose ``cols + rows`` is even looks
the same turned half a turn, so no image can say which corner is which: :func:`check_orderable`
refuses it.

Like a ChArUco board, the pipeline measures it in quads of 4 saddle corners
(:meth:`CheckerSpec.quads`, picked per view by :func:`rgbd_calib.model.board.cover_quads`).
Kalibr's ``target_type: checkerboard`` files (``targetCols``, ``targetRows``: inner corners;
``rowSpacingMeters``, ``colSpacingMeters``) are read as they are by
:mod:`rgbd_calib.model.board_file`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.errors import BoardError

CHECKERBOARD = "checkerboard"
MIN_INNER_CORNERS = 3  # per side: fewer cannot hold a quad per row and column and a pose


@dataclass(frozen=True)
class CheckerSpec:
    """A chessboard of ``cols`` x ``rows`` inner corners, squares ``col_spacing`` (along x)
    by ``row_spacing`` (along y) metres."""

    cols: int
    rows: int
    col_spacing: float
    row_spacing: float

    kind = CHECKERBOARD
    inverted = False  # printed black on white; the renderer's and printer's question

    @property
    def squares_x(self) -> int:
        return self.cols + 1

    @property
    def squares_y(self) -> int:
        return self.rows + 1

    @property
    def square_xy(self) -> tuple[float, float]:
        """A square's width (x) and height (y), metres."""
        return self.col_spacing, self.row_spacing

    @property
    def height(self) -> float:
        return self.squares_y * self.row_spacing

    @property
    def width(self) -> float:
        return self.squares_x * self.col_spacing

    def saddles(self, dictionary: str | None = None) -> np.ndarray:
        """The inner corners ``(C,3)`` in the board frame (m), in saddle-id order."""
        r, c = np.divmod(np.arange(self.rows * self.cols), self.cols)
        return np.column_stack([(c + 1) * self.col_spacing,
                                self.height - (r + 1) * self.row_spacing,
                                np.zeros(len(r))])

    def quads(self) -> np.ndarray:
        """Saddle ids ``(Q,4)`` of every unit square of the inner-corner grid, row-major from
        the top-left, TL, TR, BR, BL as seen from the front."""
        n = self.cols
        return np.array([[r * n + c, r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c]
                         for r in range(self.rows - 1) for c in range(self.cols - 1)], dtype=int)

    def black_squares(self, dictionary: str | None = None) -> np.ndarray:
        """``(squares_y, squares_x)`` bool, True where a square is black (row 0 at the top)."""
        r, c = np.mgrid[0:self.squares_y, 0:self.squares_x]
        return (r + c) % 2 == 0

    def printed_markers(self, dictionary: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A checkerboard prints no markers: empty ids and corners."""
        return np.zeros(0, dtype=int), np.zeros((0, 4, 3))

    def to_dict(self) -> dict[str, Any]:
        return {"cols": self.cols, "rows": self.rows, "col_spacing": self.col_spacing,
                "row_spacing": self.row_spacing}


def check_orderable(cols: int, rows: int, where: str) -> None:
    """Refuse a grid too small for a pose, or one that looks the same turned half a turn
    (``cols + rows`` even, a square grid included): no image of it can say which corner is
    which, so views of one frame set could disagree by 180 degrees."""
    if min(cols, rows) < MIN_INNER_CORNERS:
        raise BoardError(f"{where}: a checkerboard of {cols} x {rows} inner corners is too "
                         f"small; give at least {MIN_INNER_CORNERS} x {MIN_INNER_CORNERS} "
                         "(inner corners, not squares)")
    if (cols + rows) % 2 == 0:
        raise BoardError(
            f"{where}: a checkerboard of {cols} x {rows} inner corners looks the same turned "
            "half a turn, so no view can tell its corners apart; use one with an even number "
            "of inner corners one way and an odd number the other (e.g. 9 x 6), or a ChArUco "
            "board")
