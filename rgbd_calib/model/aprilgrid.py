"""Kalibr's AprilGrid target: a grid of AprilTags (tag36h11) with black squares at their
corners, as ``kalibr_create_target_pdf`` prints it.

Geometry (Kalibr's, which is also this project's board frame): ``tagCols`` x ``tagRows`` tags
of side ``tagSize`` m (the outer edge of the tag's black border), ``tagSpacing`` the gap
between tags as a fraction of ``tagSize``; origin at the outer bottom-left corner of tag 0, x
along a row, y up the columns, z out of the printed face. Tag ``k`` sits in row
``k // tagCols`` (from the bottom) and column ``k % tagCols``. Kalibr prints each tag with a
2-cell black border, turned half a turn from OpenCV's canonical tag image: OpenCV's
``DICT_APRILTAG_36h11`` decodes it with ``markerBorderBits = 2`` and reports its corners from
the printed bottom-right (detection order, as every board here stores them).

A double-sided grid (this project's extension: ``back_first_id`` in an ``type: aprilgrid``
board file) carries a second grid on the back, printed the same way and glued behind the
front, its tags numbered from ``back_first_id``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .board import APRILGRID, BACK, FRONT, Board

APRILGRID_DICTIONARY = "DICT_APRILTAG_36h11"
APRILGRID_BORDER_BITS = 2  # Kalibr's tags have a black border two code cells wide
KALIBR_KEYS = ("tagCols", "tagRows", "tagSize", "tagSpacing")


def _tag_origins(cols: int, rows: int, size: float, spacing: float) -> np.ndarray:
    """Bottom-left corner ``(cols*rows, 2)`` of every tag, id order (m)."""
    r, c = np.divmod(np.arange(cols * rows), cols)
    pitch = (1.0 + spacing) * size
    return np.column_stack([c * pitch, r * pitch])


def grid_width(cols: int, size: float, spacing: float) -> float:
    """Width of the tags' area (m): from tag 0's left edge to the last column's right edge."""
    return cols * size + (cols - 1) * spacing * size


def aprilgrid_board(
    cols: int, rows: int, size: float, spacing: float, thickness: float = 0.003,
    back_first_id: int | None = None, panel: tuple[float, float, float, float] | None = None,
    name: str = "aprilgrid", source: Path | None = None,
) -> Board:
    """The AprilGrid :class:`Board`: ``cols`` x ``rows`` tags of ``size`` m, gaps of
    ``spacing * size``; with ``back_first_id``, a second grid on the back (``z = -thickness``)
    whose tags are numbered from it. The panel (default) holds the corner squares and half a
    tag of white around them."""
    o = _tag_origins(cols, rows, size, spacing)
    s = size
    # OpenCV's detection order of a Kalibr tag: printed BR, BL, TL, TR (seen from its face)
    local = np.stack([o + [s, 0.0], o, o + [0.0, s], o + [s, s]], axis=1)
    ids = [np.arange(cols * rows)]
    corners = [np.concatenate([local, np.zeros(local.shape[:2] + (1,))], axis=2)]
    faces = [np.full(cols * rows, FRONT)]
    if back_first_id is not None:  # printed the same way and glued on the back: x mirrored
        back = np.concatenate([grid_width(cols, s, spacing) - local[..., :1], local[..., 1:],
                               np.full(local.shape[:2] + (1,), -thickness)], axis=2)
        ids.append(back_first_id + np.arange(cols * rows))
        corners.append(back)
        faces.append(np.full(cols * rows, BACK))
    if panel is None:
        m = spacing * s + s / 2
        panel = (-m, grid_width(cols, s, spacing) + m, -m, grid_width(rows, s, spacing) + m)
    grid = {"tagCols": cols, "tagRows": rows, "tagSize": size, "tagSpacing": spacing}
    if back_first_id is not None:
        grid["back_first_id"] = back_first_id
    return Board(APRILGRID_DICTIONARY, np.concatenate(ids), np.concatenate(corners),
                 np.concatenate(faces), float(thickness), tuple(map(float, panel)), name, grid,
                 source, border_bits=APRILGRID_BORDER_BITS)


def corner_squares(board: Board) -> np.ndarray:
    """The black squares Kalibr prints at every tag corner (side ``tagSpacing * tagSize``,
    touching the tag at its corner, outside it): ``(K,5)`` rows ``face, xmin, xmax, ymin,
    ymax`` in the board frame (m); empty for another board."""
    if board.board_type != APRILGRID:
        return np.zeros((0, 5))
    g = board.grid
    cols, rows, s, sp = g["tagCols"], g["tagRows"], g["tagSize"], g["tagSpacing"]
    q = sp * s
    out = []
    for x, y in _tag_origins(cols, rows, s, sp):
        for dx, dy in ((-q, -q), (s, -q), (s, s), (-q, s)):
            out.append((FRONT, x + dx, x + dx + q, y + dy, y + dy + q))
    squares = np.unique(np.round(np.array(out), 12), axis=0)
    if "back_first_id" in g:
        w = grid_width(cols, s, sp)
        back = squares.copy()
        back[:, 0] = BACK
        back[:, 1], back[:, 2] = w - squares[:, 2], w - squares[:, 1]
        squares = np.concatenate([squares, back])
    return squares
