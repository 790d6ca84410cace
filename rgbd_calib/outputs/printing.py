"""Printable sheets of a board: vector PDFs and PNGs at true physical scale.

Every sheet is one face of the board as it must be printed and glued, seen from outside that
face, at 1 mm on the board = 1 mm on paper. Positions on a sheet are *page millimetres*:
origin at the page's top-left corner, u to the right, v down.

Board frame (docs/formats.md) to page, with the panel ``(xmin, xmax, ymin, ymax)`` centred on
the page at offset ``(off_u, off_v)`` mm:

- front sheet (seen from +z):  ``u = off_u + (x - xmin)``, ``v = off_v + (ymax - y)``
- back sheet (seen from -z, where board x points left): ``u = off_u + (xmax - x)``,
  ``v = off_v + (ymax - y)``

The markers themselves are ordinary, un-mirrored printed markers: corner 0 of every marker
(``Board.corners[k, 0]``, detection order) lands on the top-left of its printed pattern.
Alignment crosshairs at the panel's corners and edge midpoints sit at the same board points on
both sheets, so the sheets line up when held together against the light.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from reportlab.pdfbase.pdfmetrics import stringWidth
from reportlab.pdfgen.canvas import Canvas

from ..core.errors import BoardError, ConfigError
from ..model.aprilgrid import corner_squares
from ..model.board import BACK, FRONT, Board, printed_markers
from ..model.board_print import front_span_m

MM_PER_INCH = 25.4
PT_PER_MM = 72.0 / MM_PER_INCH
ISO_A_MM = {"A4": (210.0, 297.0), "A3": (297.0, 420.0), "A2": (420.0, 594.0),
            "A1": (594.0, 841.0), "A0": (841.0, 1189.0)}  # (short, long) side, smallest first
FIT_TOL_MM = 1e-6  # float slack when comparing the panel with a page
PRINTER_MARGIN_MM = 5.0  # typical unprintable border; text stays inside it
MARK_ARM_MM = 5.0  # crosshair half-length (shortened to respect the quiet zone)
MARK_ARM_MIN_MM = 1.0  # a crosshair that would be shorter than this is left out
MARK_LINE_MM = 0.2  # crosshair and scale-bar outline width
SCALE_BAR_MM = 100.0
SCALE_BAR_HEIGHT_MM = 2.5
FONT_PT, FONT_MIN_PT = 9.0, 5.0
GAP_MM = 1.0
MAX_RASTER_PX = 1_000_000_000
FACE_NAMES = {FRONT: "front", BACK: "back"}


@dataclass(frozen=True)
class PrintedSheet:
    """One printed face: marker ids and their corners on the page.

    ``corners_page_mm`` is ``(N,4,2)``, page millimetres (origin top-left, u right, v down),
    corners in ArUco detection order, rows matching ``ids``."""

    face: int
    ids: np.ndarray
    corners_page_mm: np.ndarray
    pdf: Path
    png: Path

    def to_dict(self) -> dict[str, Any]:
        return {"face": FACE_NAMES.get(self.face, f"face{self.face}"), "pdf": str(self.pdf),
                "png": str(self.png),
                "corners_page_mm": {int(i): c.tolist()
                                    for i, c in zip(self.ids, self.corners_page_mm, strict=True)}}


@dataclass(frozen=True)
class PrintResult:
    """What :func:`write_printable_board` wrote.

    ``page_size_mm`` is ``(width, height)`` of every page; ``png_size_px`` is ``(width,
    height)`` of the PNGs (the page rounded to whole pixels at ``dpi``); ``notes`` lists
    anything left out (alignment marks or the text block that found no room)."""

    files: tuple[Path, ...]
    page_name: str
    page_size_mm: tuple[float, float]
    dpi: int
    png_size_px: tuple[int, int]
    sheets: tuple[PrintedSheet, ...]
    notes: tuple[str, ...] = ()

    def sheet(self, face: int) -> PrintedSheet:
        for s in self.sheets:
            if s.face == face:
                return s
        raise KeyError(f"no printed sheet for face {face}")

    def to_dict(self) -> dict[str, Any]:
        return {"files": [str(f) for f in self.files], "page": self.page_name,
                "page_size_mm": list(self.page_size_mm), "dpi": self.dpi,
                "png_size_px": list(self.png_size_px),
                "sheets": [s.to_dict() for s in self.sheets], "notes": list(self.notes)}


# ----------------------------------------------------------------------------- page layout


def _where(board: Board) -> str:
    return str(board.source) if board.source is not None else f"board {board.name!r}"


def panel_size_mm(board: Board) -> tuple[float, float]:
    """Panel width and height in millimetres."""
    xmin, xmax, ymin, ymax = board.panel
    return (xmax - xmin) * 1000.0, (ymax - ymin) * 1000.0


def choose_page(board: Board, page: str | None = None) -> tuple[str, float, float]:
    """``(name, width_mm, height_mm)`` of the page for ``board``.

    ``page`` is an ISO A size ``"A0"``..``"A4"``, optionally suffixed ``-portrait`` or
    ``-landscape``; ``None`` picks the smallest A size (portrait before landscape) that holds
    the panel. Raises BoardError when the panel does not fit."""
    pw, ph = panel_size_mm(board)

    def fits(w: float, h: float) -> bool:
        return pw <= w + FIT_TOL_MM and ph <= h + FIT_TOL_MM

    if page is None:
        for size, (short, long) in ISO_A_MM.items():
            for orient, (w, h) in (("portrait", (short, long)), ("landscape", (long, short))):
                if fits(w, h):
                    return f"{size}-{orient}", w, h
        raise BoardError(f"{_where(board)}: panel {pw:.1f} x {ph:.1f} mm is larger than A0; "
                         "shrink the panel or print it in tiles yourself")
    size, _, orient = page.strip().upper().partition("-")
    if size not in ISO_A_MM or orient not in ("", "PORTRAIT", "LANDSCAPE"):
        raise ConfigError(f"unknown page {page!r}; use A0..A4, optionally with -portrait or "
                          "-landscape (e.g. A3-landscape)")
    short, long = ISO_A_MM[size]
    options = {"portrait": (short, long), "landscape": (long, short)}
    if orient:
        options = {orient.lower(): options[orient.lower()]}
    for o, (w, h) in options.items():
        if fits(w, h):
            return f"{size}-{o}", w, h
    raise BoardError(f"{_where(board)}: panel {pw:.1f} x {ph:.1f} mm does not fit page {page} "
                     f"({', '.join(f'{w:g} x {h:g} mm' for w, h in options.values())}); "
                     "choose a larger page or omit page to pick one automatically")


def board_to_page_mm(board: Board, face: int, xy_m: np.ndarray,
                     page_size_mm: tuple[float, float]) -> np.ndarray:
    """Map board-frame points ``(...,2)`` (x, y in metres) onto ``face``'s printed sheet.

    Returns page millimetres ``(...,2)``: origin at the page's top-left, u right, v down, with
    the panel centred on a ``(width, height)`` mm page. The back sheet is seen from -z, so
    board x runs right-to-left on it."""
    xmin, xmax, ymin, ymax = board.panel
    pw, ph = panel_size_mm(board)
    off_u = (page_size_mm[0] - pw) / 2.0
    off_v = (page_size_mm[1] - ph) / 2.0
    xy = np.asarray(xy_m, dtype=float)
    u = (xy[..., 0] - xmin) if face == FRONT else (xmax - xy[..., 0])
    v = ymax - xy[..., 1]
    return np.stack([off_u + 1000.0 * u, off_v + 1000.0 * v], axis=-1)


def _module_mm(board: Board) -> float:
    """One marker module (cell) in mm: the minimum quiet zone around every marker."""
    if board.pattern is not None and board.charuco is None:  # a checkerboard: a square
        return min(board.pattern.square_xy) * 1000.0
    length = board.marker_length if board.charuco is None else board.charuco.marker_length
    return length * 1000.0 / (board.bits + 2 * board.border_bits)


def _black_squares_mm(board: Board, face: int = FRONT
                        ) -> list[tuple[float, float, float, float]]:
    """The black squares printed on ``face`` besides the markers, as board-frame boxes
    ``(xmin, xmax, ymin, ymax)`` mm: a ChArUco board's or checkerboard's chessboard (front),
    an AprilGrid's corner squares."""
    out = [tuple(1000.0 * r[1:]) for r in corner_squares(board) if r[0] == face]
    spec = board.pattern
    if spec is None or face != FRONT:
        return out
    sx, sy = (1000.0 * v for v in spec.square_xy)
    top = spec.height * 1000.0
    black = spec.black_squares(board.dictionary)
    return out + [(c * sx, (c + 1) * sx, top - (r + 1) * sy, top - r * sy)
                  for r, c in zip(*np.nonzero(black))]


def _marker_boxes_mm(board: Board) -> np.ndarray:
    """Axis-aligned board-frame boxes ``(M,4)`` ``(xmin, xmax, ymin, ymax)`` in mm of all
    markers of both faces (both sheets share the alignment marks, so both must avoid them);
    a ChArUco board's whole chessboard."""
    if board.pattern is not None:
        spec = board.pattern
        return np.array([[0.0, spec.squares_x * spec.square_xy[0] * 1000.0, 0.0,
                          spec.height * 1000.0]])
    xy = board.corners[:, :, :2] * 1000.0
    return np.stack([xy[..., 0].min(1), xy[..., 0].max(1), xy[..., 1].min(1),
                     xy[..., 1].max(1)], axis=1)


def _markers_outside_panel(board: Board) -> list[int]:
    xmin, xmax, ymin, ymax = board.panel
    xy = board.corners[:, :, :2]
    tol = FIT_TOL_MM / 1000.0
    out = ((xy[..., 0] < xmin - tol) | (xy[..., 0] > xmax + tol) | (xy[..., 1] < ymin - tol)
           | (xy[..., 1] > ymax + tol)).any(axis=1)
    return board.ids[out].tolist()


def _alignment_marks(board: Board) -> tuple[list[tuple[float, float, float]], list[str]]:
    """Crosshairs ``(x_mm, y_mm, arm_mm)`` in the board frame at the panel's corners and edge
    midpoints, each shortened so that it keeps one module clear of every marker."""
    xmin, xmax, ymin, ymax = (v * 1000.0 for v in board.panel)
    xmid, ymid = (xmin + xmax) / 2.0, (ymin + ymax) / 2.0
    points = [(xmin, ymin), (xmax, ymin), (xmin, ymax), (xmax, ymax),
              (xmid, ymin), (xmid, ymax), (xmin, ymid), (xmax, ymid)]
    boxes = _marker_boxes_mm(board)
    clear = _module_mm(board) + MARK_LINE_MM / 2.0
    marks, notes = [], []
    for x, y in points:
        for arm in np.arange(MARK_ARM_MM, MARK_ARM_MIN_MM - 1e-9, -0.1):
            gx = np.maximum(0.0, np.maximum(boxes[:, 0] - (x + arm), (x - arm) - boxes[:, 1]))
            gy = np.maximum(0.0, np.maximum(boxes[:, 2] - (y + arm), (y - arm) - boxes[:, 3]))
            if np.all(np.hypot(gx, gy) >= clear):
                marks.append((x, y, float(arm)))
                break
        else:
            notes.append(f"alignment mark at board ({x:.1f}, {y:.1f}) mm left out: no room "
                         "outside the markers' quiet zone")
    return marks, notes


@dataclass(frozen=True)
class _TextBlock:
    """Where the info text and scale bar go, page mm (shared by both sheets)."""

    u: float
    v: float  # top of the block
    font_mm: float

    @property
    def baselines(self) -> tuple[float, float]:
        return self.v + self.font_mm, self.v + 2.3 * self.font_mm

    @property
    def bar_top(self) -> float:
        return self.v + 2.3 * self.font_mm + GAP_MM + 0.3 * self.font_mm


def _block_height(font_mm: float) -> float:
    return 2.6 * font_mm + GAP_MM + SCALE_BAR_HEIGHT_MM


def _info_lines(board: Board, face: int) -> tuple[str, str]:
    side = "FRONT" if face == FRONT else "BACK"
    where = "front" if face == FRONT else "back"
    if board.pattern is not None and board.charuco is None:
        c = board.pattern
        return (f"{board.name}  |  checkerboard {c.cols} x {c.rows} inner corners, squares "
                f"{c.col_spacing * 1000:.1f} x {c.row_spacing * 1000:.1f} mm",
                "print at 100% / actual size, check: this bar = 100 mm")
    if board.charuco is not None:
        c = board.charuco
        first = (f"{board.name}  |  ChArUco {c.squares_x} x {c.squares_y} squares of "
                 f"{c.square_length * 1000:.1f} mm  |  {board.dictionary}, ids "
                 f"{c.first_id}-{c.first_id + c.n_markers - 1}  |  marker "
                 f"{c.marker_length * 1000:.1f} mm" + ("  |  inverted" if c.inverted else ""))
        return first, "print at 100% / actual size, check: this bar = 100 mm"
    ids = board.face_ids(face)
    first = (f"{board.name}  |  {side} face: glue on the {where}, this side out, top edge up  |  "
             f"{board.dictionary}, ids {int(ids.min())}-{int(ids.max())}  |  marker "
             f"{board.marker_length * 1000:.1f} mm  |  thickness {board.thickness * 1000:.1f} mm")
    return first, "print at 100% / actual size, check: this bar = 100 mm"


def _place_text(board: Board, page_size_mm: tuple[float, float],
                marks: list[tuple[float, float, float]]) -> _TextBlock | None:
    """First free horizontal band (panel bottom margin, panel top margin, page below the panel,
    page above it) that holds the info block clear of the markers' quiet zone, the alignment
    marks and the printer's unprintable border."""
    W, H = page_size_mm
    pw, ph = panel_size_mm(board)
    off_u, off_v = (W - pw) / 2.0, (H - ph) / 2.0
    boxes = _marker_boxes_mm(board)
    qz = _module_mm(board)
    ymax_mm = board.panel[3] * 1000.0
    grid_top = off_v + ymax_mm - boxes[:, 3].max() - qz  # page v of the quiet zone's top
    grid_bottom = off_v + ymax_mm - boxes[:, 2].min() + qz
    arm_top = max([a for _, y, a in marks if abs(y - ymax_mm) < 1e-6], default=0.0)
    arm_bottom = max([a for _, y, a in marks if abs(y - board.panel[2] * 1000) < 1e-6],
                     default=0.0)
    lo_u, hi_u = PRINTER_MARGIN_MM, W - PRINTER_MARGIN_MM
    lo_v, hi_v = PRINTER_MARGIN_MM, H - PRINTER_MARGIN_MM
    arm_side = max([a for x, _, a in marks if abs(x - board.panel[0] * 1000) < 1e-6
                    or abs(x - board.panel[1] * 1000) < 1e-6], default=0.0)
    side = arm_side + GAP_MM  # clear of the crosshairs on the left and right panel edges
    panel_u = (max(lo_u, off_u + side), min(hi_u, off_u + pw - side))
    bands = [  # (u0, u1, v0, v1)
        (*panel_u, grid_bottom + GAP_MM, min(hi_v, off_v + ph - arm_bottom - GAP_MM)),
        (*panel_u, max(lo_v, off_v + arm_top + GAP_MM), grid_top - GAP_MM),
        (lo_u, hi_u, off_v + ph + arm_bottom + GAP_MM, hi_v),
        (lo_u, hi_u, lo_v, off_v - arm_top - GAP_MM),
    ]
    lines = [_info_lines(board, f) for f in (FRONT, BACK) if np.any(board.faces == f)]
    for u0, u1, v0, v1 in bands:
        for pt in np.arange(FONT_PT, FONT_MIN_PT - 1e-9, -0.5):
            font_mm = pt / PT_PER_MM
            width = max(max(stringWidth(t, "Helvetica", pt) for t in ls) / PT_PER_MM
                        for ls in lines)
            width = max(width, SCALE_BAR_MM + 2 * GAP_MM + 4 * font_mm)
            height = _block_height(font_mm)
            if u1 - u0 >= width and v1 - v0 >= height:
                return _TextBlock(u0, v0 + (v1 - v0 - height) / 2.0, font_mm)
    return None


def _rects_for_sheet(board: Board, face: int, page_size_mm: tuple[float, float],
                     marks: list[tuple[float, float, float]],
                     text: _TextBlock | None) -> list[tuple[float, float, float, float]]:
    """Black axis-aligned rectangles ``(u0, v0, u1, v1)`` page mm: marks and the scale bar."""
    rects = []
    w = MARK_LINE_MM / 2.0
    for x, y, arm in marks:
        u, v = board_to_page_mm(board, face, np.array([x, y]) / 1000.0, page_size_mm)
        rects += [(u - arm, v - w, u + arm, v + w), (u - w, v - arm, u + w, v + arm)]
    if text is not None:
        u0, v0, v1 = text.u, text.bar_top, text.bar_top + SCALE_BAR_HEIGHT_MM
        for k in range(0, int(SCALE_BAR_MM // 10), 2):  # alternating 10 mm segments
            rects.append((u0 + 10.0 * k, v0, u0 + 10.0 * (k + 1), v1))
        u1 = u0 + SCALE_BAR_MM
        rects += [(u0, v0, u1, v0 + MARK_LINE_MM), (u0, v1 - MARK_LINE_MM, u1, v1),
                  (u1 - MARK_LINE_MM, v0, u1, v1)]
    return rects


def _marker_quads(board: Board, marker_id: int, corners_page: np.ndarray) -> list[np.ndarray]:
    """Black runs of one marker as page-mm quads ``(4,2)``: each row's consecutive black cells
    (border included) merged, mapped through the marker's own corners (TL, TR, BR, BL)."""
    cells = board.marker_cells(int(marker_id)) == 0
    n = cells.shape[0]
    tl, tr, _, bl = corners_page
    ex, ey = (tr - tl) / n, (bl - tl) / n
    quads = []
    for r in range(n):
        c = 0
        while c < n:
            if not cells[r, c]:
                c += 1
                continue
            c1 = c
            while c1 + 1 < n and cells[r, c1 + 1]:
                c1 += 1
            p = tl + r * ey
            quads.append(np.array([p + c * ex, p + (c1 + 1) * ex, p + (c1 + 1) * ex + ey,
                                   p + c * ex + ey]))
            c = c1 + 1
    return quads


def _chessboard_page_mm(board: Board, page_size_mm: tuple[float, float]):
    """A ChArUco board's chessboard area on the front sheet ``(u0, v0, u1, v1)`` page mm."""
    spec = board.pattern
    corners = np.array([[0.0, spec.height], [spec.squares_x * spec.square_xy[0], 0.0]])
    (u0, v0), (u1, v1) = board_to_page_mm(board, FRONT, corners, page_size_mm)
    return u0, v0, u1, v1


def _black_squares_page_mm(board: Board, page_size_mm: tuple[float, float],
                             face: int = FRONT):
    """The black squares of :func:`_black_squares_mm` as page rectangles ``(u0, v0, u1,
    v1)`` mm (top-left and bottom-right on the page)."""
    out = []
    for x0, x1, y0, y1 in _black_squares_mm(board, face):
        corners = np.array([[x0, y1], [x1, y0]]) / 1000.0
        (u0, v0), (u1, v1) = board_to_page_mm(board, face, corners, page_size_mm)
        out.append((min(u0, u1), v0, max(u0, u1), v1))
    return out


# ----------------------------------------------------------------------------- PDF


def _draw_pdf_page(canvas: Canvas, board: Board, face: int, page_size_mm: tuple[float, float],
                   corners_page: np.ndarray, marks: list[tuple[float, float, float]],
                   text: _TextBlock | None) -> None:
    H = page_size_mm[1]

    def pt(u: float, v: float) -> tuple[float, float]:
        return u * PT_PER_MM, (H - v) * PT_PER_MM

    ink = 0.0
    inverted = board.charuco is not None and board.charuco.inverted
    if inverted:  # white on black: a black chessboard area, the usual shapes in white
        canvas.setFillGray(0.0)
        u0, v0, u1, v1 = _chessboard_page_mm(board, page_size_mm)
        x0, y1 = pt(u0, v0)
        x1, y0 = pt(u1, v1)
        canvas.rect(x0, y0, x1 - x0, y1 - y0, stroke=0, fill=1)
        ink = 1.0
    canvas.setFillGray(ink)
    canvas.setStrokeGray(0.0)
    for u0, v0, u1, v1 in _black_squares_page_mm(board, page_size_mm, face):
        x0, y1 = pt(u0, v0)  # the chessboard squares, an AprilGrid's corner squares
        x1, y0 = pt(u1, v1)
        canvas.rect(x0, y0, x1 - x0, y1 - y0, stroke=0, fill=1)
    ids, _, faces = printed_markers(board)
    for k in np.flatnonzero(faces == face):
        path = canvas.beginPath()
        for quad in _marker_quads(board, int(ids[k]), corners_page[k]):
            path.moveTo(*pt(*quad[0]))
            for q in quad[1:]:
                path.lineTo(*pt(*q))
            path.close()
        canvas.drawPath(path, stroke=0, fill=1)
    canvas.setFillGray(0.0)
    for u0, v0, u1, v1 in _rects_for_sheet(board, face, page_size_mm, marks, text):
        x0, y1 = pt(u0, v0)
        x1, y0 = pt(u1, v1)
        canvas.rect(x0, y0, x1 - x0, y1 - y0, stroke=0, fill=1)
    if text is not None:
        font_pt = text.font_mm * PT_PER_MM
        canvas.setFont("Helvetica", font_pt)
        for line, base in zip(_info_lines(board, face), text.baselines, strict=True):
            canvas.drawString(*pt(text.u, base), line)
        canvas.drawString(*pt(text.u + SCALE_BAR_MM + 2 * GAP_MM,
                              text.bar_top + SCALE_BAR_HEIGHT_MM), "100 mm")
    canvas.showPage()


def _new_canvas(path: Path, board: Board, page_size_mm: tuple[float, float]) -> Canvas:
    c = Canvas(str(path), pagesize=(page_size_mm[0] * PT_PER_MM, page_size_mm[1] * PT_PER_MM),
               invariant=True)
    c.setTitle(f"{board.name} {'ChArUco' if board.charuco else 'ArUco'} board, {board.dictionary}")
    c.setCreator("rgbd_calib.outputs.printing")
    c.setViewerPreference("PrintScaling", "None")  # ask viewers to print at actual size
    return c


# ----------------------------------------------------------------------------- PNG


def _coverage_1d(a: float, b: float, n: int, px_per_mm: float) -> tuple[int, np.ndarray]:
    """Fraction of pixels ``i0..`` covered by the interval ``[a, b]`` mm (pixel i spans
    ``[i, i+1)`` in pixel units). Returns ``(i0, coverage)``."""
    pa, pb = a * px_per_mm, b * px_per_mm
    i0 = max(0, int(np.floor(pa)))
    i1 = min(n, int(np.ceil(pb)))
    if i1 <= i0:
        return i0, np.zeros(0)
    i = np.arange(i0, i1, dtype=float)
    return i0, np.clip(np.minimum(pb, i + 1) - np.maximum(pa, i), 0.0, 1.0)


def _paint(img: np.ndarray, r0: int, c0: int, dark: np.ndarray) -> None:
    """Darken ``img`` (uint8, 255 white) by a coverage patch (0..1) at ``(r0, c0)``."""
    if dark.size == 0:
        return
    sub = img[r0:r0 + dark.shape[0], c0:c0 + dark.shape[1]]
    np.minimum(sub, np.rint(255.0 * (1.0 - np.clip(dark, 0.0, 1.0))).astype(np.uint8), out=sub)


def _raster_rect(img: np.ndarray, px_per_mm: float, u0: float, v0: float, u1: float,
                 v1: float) -> None:
    c0, cx = _coverage_1d(u0, u1, img.shape[1], px_per_mm)
    r0, cy = _coverage_1d(v0, v1, img.shape[0], px_per_mm)
    _paint(img, r0, c0, np.outer(cy, cx))


def _raster_marker(img: np.ndarray, px_per_mm: float, cells_black: np.ndarray,
                   corners_page: np.ndarray) -> None:
    """Exact area coverage of a marker whose edges are page-axis-aligned (any 90 degree turn or
    flip); other orientations are supersampled 8 x 8 per pixel."""
    n = cells_black.shape[0]
    tl, tr, _, bl = corners_page
    ex, ey = (tr - tl) / n, (bl - tl) / n  # one cell along the marker's columns and rows (mm)
    A = np.column_stack([ex, ey])  # page offset = A @ (col, row)
    A_inv = np.linalg.inv(A)
    lo, hi = corners_page.min(axis=0), corners_page.max(axis=0)
    # each marker axis runs along one page axis: one zero entry per column of A
    axis_aligned = bool(np.all(np.abs(A).min(axis=0) <= 1e-9 * np.abs(A).max()))
    if axis_aligned:
        # the marker's cells in page orientation: page cell (i down, j right) -> marker cell
        step = np.abs(A).max()
        j, i = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5)
        cr = (np.stack([lo[0] + j * step, lo[1] + i * step], -1) - tl) @ A_inv.T
        cc, rr = np.floor(cr[..., 0]).astype(int), np.floor(cr[..., 1]).astype(int)
        page_cells = cells_black[rr, cc].astype(float)
        cols = [_coverage_1d(lo[0] + j * step, lo[0] + (j + 1) * step, img.shape[1], px_per_mm)
                for j in range(n)]
        rows = [_coverage_1d(lo[1] + i * step, lo[1] + (i + 1) * step, img.shape[0], px_per_mm)
                for i in range(n)]
        c0, r0 = cols[0][0], rows[0][0]
        width = max(s + len(c) for s, c in cols) - c0
        height = max(s + len(c) for s, c in rows) - r0
        Cx, Cy = np.zeros((width, n)), np.zeros((height, n))
        for k, (s, c) in enumerate(cols):
            Cx[s - c0:s - c0 + len(c), k] = c
        for k, (s, c) in enumerate(rows):
            Cy[s - r0:s - r0 + len(c), k] = c
        _paint(img, r0, c0, Cy @ page_cells @ Cx.T)
        return
    ss = 8
    c0, r0 = max(0, int(np.floor(lo[0] * px_per_mm))), max(0, int(np.floor(lo[1] * px_per_mm)))
    c1 = min(img.shape[1], int(np.ceil(hi[0] * px_per_mm)))
    r1 = min(img.shape[0], int(np.ceil(hi[1] * px_per_mm)))
    offs = (np.arange(ss) + 0.5) / ss
    su = (np.arange(c0, c1)[:, None] + offs).ravel() / px_per_mm
    sv = (np.arange(r0, r1)[:, None] + offs).ravel() / px_per_mm
    U, V = np.meshgrid(su, sv)
    cr = (np.stack([U, V], -1) - tl) @ A_inv.T
    inside = np.all((cr >= 0) & (cr < n), axis=-1)
    cc = np.clip(np.floor(cr[..., 0]).astype(int), 0, n - 1)
    rr = np.clip(np.floor(cr[..., 1]).astype(int), 0, n - 1)
    black = (inside & cells_black[rr, cc]).astype(float)
    dark = black.reshape(r1 - r0, ss, c1 - c0, ss).mean(axis=(1, 3))
    _paint(img, r0, c0, dark)


def _render_png(path: Path, board: Board, face: int, page_size_mm: tuple[float, float],
                dpi: int, corners_page: np.ndarray, marks: list[tuple[float, float, float]],
                text: _TextBlock | None) -> tuple[int, int]:
    px_per_mm = dpi / MM_PER_INCH
    w, h = (int(round(s * px_per_mm)) for s in page_size_mm)
    img = np.full((h, w), 255, dtype=np.uint8)
    for rect in _black_squares_page_mm(board, page_size_mm, face):
        _raster_rect(img, px_per_mm, *rect)
    ids, _, faces = printed_markers(board)
    for k in np.flatnonzero(faces == face):
        cells = board.marker_cells(int(ids[k])) == 0
        _raster_marker(img, px_per_mm, cells, corners_page[k])
    if board.charuco is not None and board.charuco.inverted:  # white on black
        u0, v0, u1, v1 = _chessboard_page_mm(board, page_size_mm)
        c0, c1 = (int(round(u * px_per_mm)) for u in (u0, u1))
        r0, r1 = (int(round(v * px_per_mm)) for v in (v0, v1))
        img[r0:r1, c0:c1] = 255 - img[r0:r1, c0:c1]
    for rect in _rects_for_sheet(board, face, page_size_mm, marks, text):
        _raster_rect(img, px_per_mm, *rect)
    pil = Image.fromarray(img)  # 2-D uint8: 8-bit grey
    if text is not None:
        draw = ImageDraw.Draw(pil)
        font = ImageFont.load_default(size=max(6.0, text.font_mm * px_per_mm))
        for line, base in zip(_info_lines(board, face), text.baselines, strict=True):
            draw.text((text.u * px_per_mm, base * px_per_mm), line, fill=0, font=font,
                      anchor="ls")
        draw.text(((text.u + SCALE_BAR_MM + 2 * GAP_MM) * px_per_mm,
                   (text.bar_top + SCALE_BAR_HEIGHT_MM) * px_per_mm), "100 mm", fill=0,
                  font=font, anchor="ls")
    pil.save(path, dpi=(dpi, dpi))  # pHYs chunk (pixels per metre, so 300 dpi reads 299.9994)
    return w, h


# ----------------------------------------------------------------------------- entry point


def measuring_line(board: Board) -> str | None:
    """What to measure on the printed front sheet, and what it should read: the span of the
    outermost marker corners (a ChArUco board: of its inner chessboard corners) across and
    down, from the board file. A print off by a fraction of a percent scales every
    translation of a calibration (docs/formats.md, ``print_scale_sigma``). None for a
    multi-face target (each face is measured on its own sheet)."""
    span = front_span_m(board)
    if span is None:
        return None
    w, h = 1000 * np.array(span)
    what = ("inner chessboard corners" if board.pattern is not None
            else "outermost marker corners")
    return (f"measure the printed front sheet: its {what} should span {w:.1f} mm across and "
            f"{h:.1f} mm down; where they do not, run this again with --measured ACROSS_MM "
            "DOWN_MM: it writes the board file rescaled to the print, with the measurement's "
            "sigma as its print_scale_sigma (docs/formats.md)")


def write_printable_board(board: Board, out_dir: Path, dpi: int = 300,
                          page: str | None = None) -> PrintResult:
    """Write the board's printable sheets into ``out_dir`` at true scale.

    Files: ``board_front.pdf``, ``board_back.pdf`` (vector, one page each), ``board.pdf``
    (all faces, one page each) and ``board_front.png``, ``board_back.png`` (``dpi`` in the
    PNG metadata); a single-sided board gets only the front files. ``page`` as in
    :func:`choose_page`. Raises BoardError when the panel does not fit the page and
    ConfigError for a bad ``page`` or ``dpi``."""
    if isinstance(dpi, bool) or not isinstance(dpi, int) or dpi < 1:
        raise ConfigError(f"dpi must be a positive whole number, got {dpi!r}")
    if board.sheets:
        return _write_multiface(board, Path(out_dir), dpi, page)
    page_name, W, H = choose_page(board, page)
    page_size = (W, H)
    if (W * dpi / MM_PER_INCH) * (H * dpi / MM_PER_INCH) > MAX_RASTER_PX:
        raise ConfigError(f"{page_name} at {dpi} dpi is over {MAX_RASTER_PX:.0e} pixels; "
                          "use a lower dpi")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if board.pattern is not None:
        x0, x1, y0, y1 = _marker_boxes_mm(board)[0] / 1000.0
        px0, px1, py0, py1 = board.panel
        tol = FIT_TOL_MM / 1000.0
        if x0 < px0 - tol or x1 > px1 + tol or y0 < py0 - tol or y1 > py1 + tol:
            raise BoardError(f"{_where(board)}: the chessboard [0, {x1:g}, 0, {y1:g}] does not "
                             f"fit the panel {list(board.panel)}; enlarge the panel")
    outside = [] if board.pattern is not None else _markers_outside_panel(board)
    if outside:
        raise BoardError(f"{_where(board)}: marker(s) {outside} lie outside the panel "
                         f"{list(board.panel)}; enlarge the panel to cover every marker")
    marks, notes = _alignment_marks(board)
    text = _place_text(board, page_size, marks)
    if text is None:
        notes.append("no room for the info text and 100 mm scale bar outside the markers' "
                      "quiet zone; check the print scale on the markers themselves")

    printed_ids, printed_corners, printed_faces = printed_markers(board)
    faces = [f for f in (FRONT, BACK) if np.any(printed_faces == f)
             or (f == FRONT and board.pattern is not None)]
    combined = _new_canvas(out_dir / "board.pdf", board, page_size)
    sheets, files = [], []
    for face in faces:
        name = FACE_NAMES[face]
        corners_page = board_to_page_mm(board, face, printed_corners[:, :, :2], page_size)
        pdf, png = out_dir / f"board_{name}.pdf", out_dir / f"board_{name}.png"
        single = _new_canvas(pdf, board, page_size)
        for canvas in (single, combined):
            _draw_pdf_page(canvas, board, face, page_size, corners_page, marks, text)
        single.save()
        png_size = _render_png(png, board, face, page_size, dpi, corners_page, marks, text)
        on_face = printed_faces == face
        sheets.append(PrintedSheet(face, printed_ids[on_face].copy(), corners_page[on_face],
                                   pdf, png))
        files += [pdf, png]
    combined.save()
    files.append(out_dir / "board.pdf")
    return PrintResult(tuple(files), page_name, page_size, dpi, png_size, tuple(sheets),
                       tuple(notes))


def _write_multiface(board: Board, out_dir: Path, dpi: int, page: str | None) -> PrintResult:
    """A multi-face target: one sheet per face, each printed as its own single-face board
    into ``out_dir/face<k>/`` (``board_front.pdf``/``.png`` there; the sheet's corners on the
    page in its own frame, the face label in ``sheets``)."""
    sheets, files, notes = [], [], []
    first = None
    for s in board.sheets:
        named = replace(s.board, name=f"{board.name} face {s.label}", source=board.source)
        res = write_printable_board(named, out_dir / f"face{s.label}", dpi, page)
        first = first or res
        files += list(res.files)
        notes += [f"face {s.label}: {n}" for n in res.notes]
        sheets += [replace(sh, face=s.label) for sh in res.sheets]
    return PrintResult(tuple(files), first.page_name, first.page_size_mm, dpi,
                       first.png_size_px, tuple(sheets), tuple(notes))
