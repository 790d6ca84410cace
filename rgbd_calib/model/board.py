"""Calibration targets: geometry in the board frame, the board model and its constructors
(the board files are read and written by :mod:`rgbd_calib.model.board_file`).

A target is rigid and carries markers on one or more planar faces. Each face has a label and
a pose ``T_board_face`` (4x4, metres; face frame: markers in its z = 0 plane, z the outward
normal) that every "which face / which normal / which plane" question goes through
(:meth:`Board.T_board_face`, :meth:`Board.face_normal`):

- the double-sided board (ArUco grid, explicit markers, AprilGrid, or one-faced ChArUco or
  checkerboard): labels +1 (front, z = 0, the identity) and -1 (back, ``z = -thickness``, the
  front flipped about y), derived from ``thickness`` as they always were;
- a multi-face target (``type: multiface``: a cube, an L of two boards, ...): labels 1..F, one
  per listed face, each face a single-face ArUco grid or ChArUco sheet (``Board.sheets``) at its
  own pose. Face 1 is the reference face of the board self-calibration.

Board frame (docs/formats.md): origin at the outer bottom-left corner of the front-face marker
grid, x right and y up as seen from the front, z out of the front face. Back-face markers lie
at ``z = -thickness``. A multi-face target's board frame is the one its file's face poses are
given in.

Every marker's corners are stored in **ArUco detection order**: top-left, top-right,
bottom-right, bottom-left *as seen from outside that marker's face*. For a back-face marker
that order is the mirror of the front-face order (the thesis's Table 4.2 lists back markers in
front-face order; :func:`~rgbd_calib.model.board_file.load_board` detects and rejects or
fixes that).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np

from ..core.errors import BoardError
from ..core.geometry import matrix_to_rotvec, transform_points
from .checkerboard import CheckerSpec

#: A board file's ``type:``, one per board form (docs/formats.md): ``aruco`` (the default: a
#: double-sided ArUco board, its markers in grid or explicit form), ``charuco`` (a one-faced
#: ChArUco board), ``multiface`` (a target of several faces, each an ArUco, AprilGrid or
#: ChArUco sheet), ``checkerboard`` (:mod:`.checkerboard`) or ``aprilgrid`` (Kalibr's,
#: :mod:`.aprilgrid`; an ArUco board of tag36h11 with 2-cell borders).
BoardType = Literal["aruco", "charuco", "multiface", "checkerboard", "aprilgrid"]
BOARD_TYPES: tuple[BoardType, ...] = get_args(BoardType)
ARUCO, CHARUCO, MULTIFACE, CHECKERBOARD, APRILGRID = BOARD_TYPES

FRONT, BACK = 1, -1
CHARUCO_ID_BASE = 10000  # a multi-face target's ChArUco face k (0-based): quad q has id
#                          CHARUCO_ID_BASE * (k + 1) + q (ArUco dictionaries hold < 1100 ids)
FACE_CROSS_TOL_M = 0.005  # faces passing this far through each other are rejected (a pose
#                           typo; a hand-built or refined target's faces may overlap ~mm at edges)
PLANE_TOL_M = 1e-4  # corners further than this from their face plane are "non-planar"
SQUARE_TOL = 1e-3  # relative tolerance on equal sides and diagonals


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """Predefined OpenCV dictionary by name, e.g. ``DICT_4X4_100``."""
    code = getattr(cv2.aruco, str(name), None)
    if not str(name).startswith("DICT_") or not isinstance(code, int):
        raise BoardError(
            f"unknown ArUco dictionary {name!r}; use an OpenCV name like DICT_4X4_100")
    return cv2.aruco.getPredefinedDictionary(code)


@dataclass(frozen=True)
class FaceSheet:
    """One face of a multi-face target: a single-face ``board`` (an ArUco grid or ChArUco, its
    markers in its own frame at z = 0) whose frame sits at ``T_board_face`` (4x4, metres) in the
    target's board frame; ``label`` (1..F) is its face label, ``id_offset`` what is added to the
    sheet's measurement ids (ChArUco quads, :data:`CHARUCO_ID_BASE`; 0 for ArUco markers)."""

    label: int
    board: Board
    T_board_face: np.ndarray
    id_offset: int = 0

    def to_board(self, quads: np.ndarray) -> np.ndarray:
        """Quads ``(K,4,3)`` of this face's frame (m) in the target's board frame."""
        return transform_points(self.T_board_face, quads.reshape(-1, 3)).reshape(-1, 4, 3)


def _back_face_pose(thickness: float) -> np.ndarray:
    """``T_board_face`` of the legacy back face: the front flipped about y, at z = -thickness
    (x = -x_board, seen from the back "right" is -x, as :func:`grid_corners` prints it)."""
    T = np.diag([-1.0, 1.0, -1.0, 1.0])
    T[2, 3] = -thickness
    return T


@dataclass(frozen=True, eq=False)
class Board:
    """A rigid target carrying markers on one or more planar faces.

    ``corners`` is ``(M,4,3)`` in metres in the board frame, detection order per marker;
    ``faces`` is ``(M,)`` the face label of each marker: +1 (front, z = 0) or -1 (back,
    z = -thickness) on a double-sided board, 1..F on a multi-face target (``sheets``).
    ``panel`` is the physical outline ``(xmin, xmax, ymin, ymax)`` in metres (a multi-face
    target: the xy box of its faces' panels).
    """

    dictionary: str
    ids: np.ndarray
    corners: np.ndarray
    faces: np.ndarray
    thickness: float
    panel: tuple[float, float, float, float]
    name: str = "board"
    grid: dict[str, Any] | None = None
    source: Path | None = field(default=None, compare=False)
    # a target measured by chessboard saddle corners (ChArUco, checkerboard): ids/corners
    # are saddle-corner quads (:meth:`CharucoSpec.quads`); None for a marker board
    pattern: CharucoSpec | CheckerSpec | None = None
    sheets: tuple[FaceSheet, ...] = ()  # a multi-face target: its faces (empty otherwise)
    body: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    # how well the printed size is known against this file (relative 1 sigma, as measured);
    # None: not stated (the file's lengths are taken as exact). Every translation of a
    # calibration scales with it (docs/formats.md, 'print_scale_sigma')
    print_scale_sigma: float | None = None
    border_bits: int = 1  # black cells around each marker's code (Kalibr's AprilGrid: 2)

    @property
    def charuco(self) -> CharucoSpec | None:
        """The ChArUco spec of a ChArUco board, else None."""
        return self.pattern if isinstance(self.pattern, CharucoSpec) else None

    @cached_property
    def index_of(self) -> dict[int, int]:
        return {int(i): k for k, i in enumerate(self.ids)}

    @property
    def is_multiface(self) -> bool:
        return bool(self.sheets)

    @property
    def board_type(self) -> BoardType:
        """The form of this board's file (its ``type:``)."""
        if self.sheets:
            return MULTIFACE
        if self.pattern is not None:
            return self.pattern.kind
        return APRILGRID if self.grid is not None and "tagCols" in self.grid else ARUCO

    @cached_property
    def face_labels(self) -> tuple[int, ...]:
        """The labels of the faces that carry markers, the reference face first."""
        if self.sheets:
            return tuple(s.label for s in self.sheets)
        return tuple(f for f in (FRONT, BACK) if np.any(self.faces == f))

    def most_seen_face(self, faces: np.ndarray) -> int:
        """The face label most frequent in ``faces`` (one label per seen marker); the
        reference face wins a tie."""
        labels = self.face_labels
        return labels[int(np.argmax([np.sum(faces == f) for f in labels]))]

    @property
    def reference_face(self) -> int:
        """The face whose pose defines the board frame (held in the self-calibration)."""
        return self.sheets[0].label if self.sheets else FRONT

    def T_board_face(self, face: int) -> np.ndarray:
        """Pose (4x4, metres) of face ``face``'s frame (markers at its z = 0, z the outward
        normal) in the board frame."""
        if self.sheets:
            return self.sheet(face).T_board_face.copy()
        if face == FRONT:
            return np.eye(4)
        if face == BACK:
            return _back_face_pose(self.thickness)
        raise KeyError(f"board {self.name} has no face {face}")

    def sheet(self, face: int) -> FaceSheet:
        """A multi-face target's face ``face``."""
        for s in self.sheets:
            if s.label == face:
                return s
        raise KeyError(f"board {self.name} has no face {face}")

    @cached_property
    def aruco_faces(self) -> Board | None:
        """A multi-face target's ArUco faces as one plain board (what one ArUco detector pass
        looks for; labels kept); None without ArUco faces."""
        sel = [s for s in self.sheets if s.board.pattern is None]
        if not sel:
            return None
        ids = np.concatenate([s.board.ids for s in sel])
        corners = np.concatenate([s.to_board(s.board.corners) for s in sel])
        faces = np.concatenate([np.full(len(s.board.ids), s.label) for s in sel])
        return Board(self.dictionary, ids, corners, faces, self.thickness, self.panel,
                     f"{self.name}_aruco", border_bits=sel[0].board.border_bits)

    @cached_property
    def printed_ids(self) -> np.ndarray:
        """Every ArUco marker id printed on the board."""
        return printed_markers(self)[0]

    def saddle_quads(self, ids) -> np.ndarray:
        """Per measurement id ``(N,)`` whether its 4 points are a ChArUco square's saddle
        corners (True) rather than an ArUco marker's edge-fitted corners (False)."""
        ids = np.asarray(ids)
        if self.sheets:
            return ids >= CHARUCO_ID_BASE
        return np.full(ids.shape, self.pattern is not None)

    def faces_of(self, ids) -> np.ndarray:
        """Face labels ``(N,)`` of the given marker ids."""
        return np.array([self.faces[self.index_of[int(i)]] for i in ids], dtype=int)

    @cached_property
    def aruco_dict(self) -> cv2.aruco.Dictionary:
        return aruco_dictionary(self.dictionary)

    @property
    def marker_length(self) -> float:
        """Mean side length of the markers (metres)."""
        return float(np.linalg.norm(np.diff(self.corners[:, [0, 1]], axis=1), axis=-1).mean())

    @property
    def printed_lengths(self) -> tuple[float, float | None]:
        """``(marker side, chessboard square side or None)`` in metres as the file gives them:
        the lengths a wrong print scale multiplies (a ChArUco board's corner quads are its
        squares, so :attr:`marker_length` is the square there)."""
        if self.charuco is not None:
            return self.charuco.marker_length, self.charuco.square_length
        if self.pattern is not None:  # a checkerboard: its squares only
            return self.marker_length, self.marker_length
        return self.marker_length, None

    @property
    def bits(self) -> int:
        return int(self.aruco_dict.markerSize)

    def object_points(self, ids: np.ndarray) -> np.ndarray:
        """Board-frame corners ``(N,4,3)`` of the given marker ids (metres)."""
        return self.corners[[self.index_of[int(i)] for i in ids]]

    def face_ids(self, face: int) -> np.ndarray:
        return self.ids[self.faces == face]

    def marker_cells(self, marker_id: int) -> np.ndarray:
        """Marker pattern as a ``(bits+2b, bits+2b)`` uint8 image (0 black, 255 white), row 0
        at the marker's top edge, including the ``b`` = :attr:`border_bits` black border."""
        n = self.bits + 2 * self.border_bits
        return cv2.aruco.generateImageMarker(self.aruco_dict, int(marker_id), n,
                                             borderBits=self.border_bits)

    def face_normal(self, face: int) -> np.ndarray:
        """Outward unit normal of a face in the board frame."""
        if not self.sheets:
            return np.array([0.0, 0.0, float(face)])  # the two faces of a flat board
        return self.T_board_face(face)[:3, 2].copy()

    def to_dict(self) -> dict[str, Any]:
        out = self._form_dict()
        if self.print_scale_sigma is not None:
            out["print_scale_sigma"] = self.print_scale_sigma
        return out

    def _form_dict(self) -> dict[str, Any]:
        if self.sheets:
            out: dict[str, Any] = {"name": self.name, "type": MULTIFACE,
                                   "dictionary": self.dictionary, "thickness": self.thickness}
            if self.body is not None:
                out["body"] = {"box": [list(self.body[0]), list(self.body[1])]}
            out["faces"] = [{"board": _sheet_dict(s.board), "pose": pose_dict(s.T_board_face)}
                            for s in self.sheets]
            return out
        if self.pattern is not None:
            return {"name": self.name, "type": self.pattern.kind,
                    **({} if self.charuco is None else {"dictionary": self.dictionary}),
                    **self.pattern.to_dict(), "thickness": self.thickness,
                    "panel": list(self.panel)}
        if self.board_type == APRILGRID:
            return {"name": self.name, "type": APRILGRID, **self.grid,
                    "thickness": self.thickness, "panel": list(self.panel)}
        out: dict[str, Any] = {
            "name": self.name,
            "dictionary": self.dictionary,
            "thickness": self.thickness,
        }
        if self.grid is not None:
            out["grid"] = dict(self.grid)
        else:
            out["corner_order"] = "detection"
            out["markers"] = {int(i): c.tolist() for i, c in zip(self.ids, self.corners)}
        out["panel"] = list(self.panel)
        return out


@dataclass(frozen=True)
class CharucoSpec:
    """A ChArUco board as OpenCV defines it (``cv2.aruco.CharucoBoard``): ``squares_x`` x
    ``squares_y`` chessboard squares of ``square_length`` m, an ArUco marker of
    ``marker_length`` m centred in every white square, ids from ``first_id`` row-major from
    the top-left. ``inverted``: printed white-on-black (the image is inverted before detection).

    Its measurements are the chessboard *saddle* corners (OpenCV's ChArUco corners, id
    ``r * (squares_x - 1) + c`` row-major from the top-left). The pipeline's unit of
    measurement is a quad of 4 points (a "marker"): the board's quads are all its unit squares
    of neighbouring corners (:meth:`quads`, one chessboard square each, overlapping), and each
    view measures with the set of them that :func:`cover_quads` picks from the corners it
    found (on a whole board the stride-2 tiling; a few corners are in two quads)."""

    squares_x: int
    squares_y: int
    square_length: float
    marker_length: float
    legacy_pattern: bool = False
    first_id: int = 0
    inverted: bool = False

    kind = CHARUCO

    @property
    def square_xy(self) -> tuple[float, float]:
        """A square's width (x) and height (y), metres."""
        return self.square_length, self.square_length

    def saddles(self, dictionary: str) -> np.ndarray:
        """The saddle corners ``(C,3)`` in the board frame (m), in saddle-id order."""
        return charuco_saddles(self, dictionary)

    def black_squares(self, dictionary: str) -> np.ndarray:
        """``(squares_y, squares_x)`` bool, True where a square is black (row 0 at the top)."""
        return charuco_black_squares(self, dictionary)

    def printed_markers(self, dictionary: str) -> tuple[np.ndarray, np.ndarray]:
        """The ArUco markers printed: ids ``(K,)`` and corners ``(K,4,3)`` (board frame, m)."""
        return charuco_markers(self, dictionary)

    @property
    def n_markers(self) -> int:
        return (self.squares_x * self.squares_y) // 2

    @property
    def height(self) -> float:
        return self.squares_y * self.square_length

    def cv_board(self, dictionary: cv2.aruco.Dictionary) -> cv2.aruco.CharucoBoard:
        """OpenCV's board (built on demand: cv2 objects cannot be pickled to workers)."""
        ids = np.arange(self.first_id, self.first_id + self.n_markers, dtype=np.int32)
        b = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_length,
                                   self.marker_length, dictionary, ids)
        b.setLegacyPattern(bool(self.legacy_pattern))
        return b

    def to_board_frame(self, xy_cv: np.ndarray) -> np.ndarray:
        """OpenCV's board points (x right, y down from the top-left, m) -> the board frame
        (origin bottom-left, y up, z out of the printed face)."""
        p = np.asarray(xy_cv, dtype=float).reshape(-1, 3).copy()
        p[:, 1] = self.height - p[:, 1]
        p[:, 2] = 0.0
        return p

    def quads(self) -> np.ndarray:
        """Saddle-corner ids ``(Q,4)`` of every unit square of the corner grid (row-major
        from the top-left; quad ``r * (nx - 1) + c`` has corner ``(r, c)`` at its TL), TL,
        TR, BR, BL as seen from the front."""
        nx, ny = self.squares_x - 1, self.squares_y - 1
        return np.array([[r * nx + c, r * nx + c + 1, (r + 1) * nx + c + 1, (r + 1) * nx + c]
                         for r in range(ny - 1) for c in range(nx - 1)], dtype=int)

    def to_dict(self) -> dict[str, Any]:
        return {
            "squares_x": self.squares_x,
            "squares_y": self.squares_y,
            "square_length": self.square_length,
            "marker_length": self.marker_length,
            "legacy_pattern": self.legacy_pattern,
            "first_id": self.first_id,
            "inverted": self.inverted,
        }


def cover_quads(quads: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Which of ``quads`` ``(Q,4)`` (:meth:`CharucoSpec.quads`) one view measures with, given
    the saddle-corner ids it ``found``: indices, ascending, of whole quads (all 4 corners
    found) that use every found corner lying in any whole quad. First disjoint quads in raster
    order (on a whole board: the stride-2 tiling), then, while a found corner in a whole quad is
    unused, the whole quad with the most unused corners (the first of them), which overlaps
    quads already taken: their shared corners are used twice or more (slightly optimistic
    covariances; each quad taken adds a corner, so there are never more quads than corners).
    A corner in no whole quad (e.g. a lone row of corners at the image edge) is not used: the
    measurement unit is 4 points."""
    have = np.zeros(int(quads.max()) + 1 if len(quads) else 0, dtype=bool)
    f = np.asarray(found, dtype=int).reshape(-1)
    have[f[(f >= 0) & (f < have.size)]] = True
    whole = np.nonzero(have[quads].all(axis=1))[0] if len(quads) else np.zeros(0, int)
    used = np.zeros_like(have)
    chosen = []
    for i in whole:
        if not used[quads[i]].any():
            chosen.append(int(i))
            used[quads[i]] = True
    while whole.size:
        new = (~used[quads[whole]]).sum(axis=1)
        best = int(np.argmax(new))  # the first of the most
        if new[best] == 0:
            break
        chosen.append(int(whole[best]))
        used[quads[whole[best]]] = True
    return np.array(sorted(chosen), dtype=int)


def charuco_markers(spec: CharucoSpec, dictionary: str) -> tuple[np.ndarray, np.ndarray]:
    """The printed ArUco markers: ids ``(K,)`` and corners ``(K,4,3)`` in the board frame (m),
    TL, TR, BR, BL as seen from the front (what the renderer draws, not measurements)."""
    b = spec.cv_board(aruco_dictionary(dictionary))
    corners = np.array([spec.to_board_frame(c) for c in b.getObjPoints()])
    return np.asarray(b.getIds(), dtype=int).reshape(-1), corners


def printed_markers(board: Board) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ArUco markers printed on ``board``: ids ``(K,)``, corners ``(K,4,3)`` (board frame,
    m, TL TR BR BL) and faces ``(K,)``; a ChArUco board's are its markers (one face), not the
    saddle-corner quads it measures with."""
    if board.sheets:
        parts = [(s, *printed_markers(s.board)) for s in board.sheets]
        ids = np.concatenate([p[1] for p in parts])
        corners = np.concatenate([s.to_board(c) for s, _, c, _ in parts])
        faces = np.concatenate([np.full(len(i), s.label) for s, i, _, _ in parts])
        return ids, corners, faces
    if board.pattern is None:
        return board.ids, board.corners, board.faces
    ids, corners = board.pattern.printed_markers(board.dictionary)
    return ids, corners, np.full(len(ids), FRONT)


def marker_board(board: Board) -> Board:
    """An ArUco :class:`Board` of the markers ``board`` prints (a ChArUco board's own markers
    instead of its saddle-corner quads; an ArUco board itself): to measure the marker corners
    of a ChArUco board against its saddle corners (``tools/real_corner_bias.py``). Detect on
    the inverted image when ``board.charuco.inverted``."""
    if board.charuco is None:
        return board
    ids, corners, faces = printed_markers(board)
    return Board(board.dictionary, ids, corners, faces, board.thickness, board.panel,
                 f"{board.name}_markers", None, board.source)


def charuco_saddles(spec: CharucoSpec, dictionary: str) -> np.ndarray:
    """The saddle corners ``(C,3)`` in the board frame (m), in OpenCV's ChArUco corner order."""
    b = spec.cv_board(aruco_dictionary(dictionary))
    return spec.to_board_frame(b.getChessboardCorners())


def charuco_black_squares(spec: CharucoSpec, dictionary: str) -> np.ndarray:
    """``(squares_y, squares_x)`` bool, True where a square is printed black (row 0 at the
    top): every square without a marker (before ``inverted``)."""
    ids, corners = charuco_markers(spec, dictionary)
    black = np.ones((spec.squares_y, spec.squares_x), dtype=bool)
    centre = corners.mean(axis=1)
    cols = np.floor(centre[:, 0] / spec.square_length).astype(int)
    rows = np.floor((spec.height - centre[:, 1]) / spec.square_length).astype(int)
    black[rows, cols] = False
    return black


def board_from_charuco(
    dictionary: str,
    spec: CharucoSpec | CheckerSpec,
    panel: tuple[float, float, float, float] | None = None,
    margin: float | None = None,
    name: str = "charuco",
    source: Path | None = None,
    thickness: float = 0.003,
) -> Board:
    """A one-faced ChArUco (or, ``spec`` a :class:`CheckerSpec`, checkerboard) :class:`Board`:
    its "markers" are the saddle-corner quads of ``spec.quads()`` (ids 0..Q-1), the panel the
    chessboard plus ``margin`` (default half a square) unless given. ``thickness`` (m) is the
    panel's (the renderer and the depth stage use it; no marker is on the back)."""
    saddles = spec.saddles(dictionary)
    quads = spec.quads()
    sx, sy = spec.square_xy
    if panel is None:
        m = min(sx, sy) / 2 if margin is None else margin
        panel = (-m, spec.squares_x * sx + m, -m, spec.height + m)
    return Board(dictionary, np.arange(len(quads)), saddles[quads], np.ones(len(quads), int),
                 thickness, tuple(map(float, panel)), name, None, source, spec)


def grid_corners(
    rows: int, cols: int, length: float, sep: float, first_id: int, face: int, thickness: float
) -> tuple[np.ndarray, np.ndarray]:
    """Markers of one printed sheet: ids row-major from the sheet's top-left as printed.

    The front sheet is seen from +z, so its column 0 sits at x = 0. The back sheet is printed
    the same way and glued on the back, so seen from the back (from -z) its column 0 sits at
    the board's largest x, and "right" on the sheet is -x in the board frame.
    """
    pitch = length + sep
    width = cols * length + (cols - 1) * sep
    height = rows * length + (rows - 1) * sep
    ids, corners = [], []
    for r in range(rows):
        for c in range(cols):
            top = height - r * pitch
            if face == FRONT:
                left, right = c * pitch, c * pitch + length
                z = 0.0
            else:
                left, right = width - c * pitch, width - c * pitch - length
                z = -thickness
            tl = (left, top, z)
            tr = (right, top, z)
            br = (right, top - length, z)
            bl = (left, top - length, z)
            ids.append(first_id + r * cols + c)
            corners.append((tl, tr, br, bl))
    return np.asarray(ids, dtype=int), np.asarray(corners, dtype=float)


def winding_sign(corners: np.ndarray, face: int) -> float:
    """+1 when a marker's corners are in detection order seen from outside ``face``.

    Seen from outside a face the camera looks along the inward normal; image x (TL->TR) cross
    image y (TL->BL) is the viewing direction, so it must oppose the outward normal."""
    c = np.asarray(corners, dtype=float)
    n = np.cross(c[1] - c[0], c[3] - c[0])
    return float(-np.sign(n[2] * face))


MAX_LISTED_IDS = 10  # a one-line error lists at most this many ids


def id_list(ids, total: int | None = None) -> str:
    """``[1, 2, 3]``, or the first :data:`MAX_LISTED_IDS` and ``(N in all)`` for a long list
    (``total`` when the ids given are only the first ones)."""
    ids = [int(i) for i in ids]
    total = len(ids) if total is None else total
    if total <= MAX_LISTED_IDS:
        return str(ids)
    return f"[{', '.join(map(str, ids[:MAX_LISTED_IDS]))}, ...] ({total} in all)"


def validate_markers(
    ids: np.ndarray,
    corners: np.ndarray,
    thickness: float,
    dict_size: int,
    where: str,
    fix_winding: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Check ids and marker geometry; return ``(corners, faces)`` (corners fixed if asked).

    Raises BoardError naming the offending markers: duplicate ids, ids outside the dictionary,
    markers off both face planes, non-planar or non-square markers, mirrored winding."""
    uniq, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        raise BoardError(
            f"{where}: duplicate marker id(s) {id_list(uniq[counts > 1])}; give each marker its "
            "own id (grid: front_first_id and back_first_id must not overlap)"
        )
    bad = ids[(ids < 0) | (ids >= dict_size)]
    if bad.size:
        raise BoardError(
            f"{where}: marker id(s) {id_list(bad)} outside the dictionary "
            f"(ids 0..{dict_size - 1}); use a larger dictionary or fix the ids"
        )
    z = corners[:, :, 2]
    faces = np.where(
        np.all(np.abs(z) <= PLANE_TOL_M, axis=1),
        FRONT,
        np.where(np.all(np.abs(z + thickness) <= PLANE_TOL_M, axis=1), BACK, 0),
    )
    off = ids[faces == 0]
    if off.size:
        raise BoardError(
            f"{where}: marker(s) {id_list(off)} are not planar on the front face (z = 0) or the "
            f"back face (z = -{thickness}); check their z coordinates and the thickness"
        )
    sides = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=-1)
    diag = np.linalg.norm(corners[:, [0, 1]] - corners[:, [2, 3]], axis=-1)
    side_ref = sides.mean(axis=1, keepdims=True)
    not_square = (np.abs(sides - side_ref) > SQUARE_TOL * side_ref).any(axis=1) | (
        np.abs(diag[:, 0] - diag[:, 1]) > SQUARE_TOL * side_ref[:, 0]
    )
    if np.any(not_square):
        raise BoardError(
            f"{where}: marker(s) {id_list(ids[not_square])} are not squares; "
            "list the 4 corners of each marker in order around the square"
        )
    signs = np.array([winding_sign(c, f) for c, f in zip(corners, faces)])
    mirrored = signs < 0
    if np.any(mirrored):
        if not fix_winding:
            raise BoardError(
                f"{where}: marker(s) {id_list(ids[mirrored])} are listed mirrored for their face "
                "(e.g. back-face corners in front-face order, as in the thesis Table 4.2); "
                "list corners TL,TR,BR,BL as seen from outside the face, or set "
                "corner_order: front / pass --fix-winding"
            )
        corners = corners.copy()
        corners[mirrored] = corners[mirrored][:, [1, 0, 3, 2]]
    return corners, faces


def board_from_grid(
    dictionary: str,
    rows: int,
    cols: int,
    marker_length: float,
    separation: float,
    thickness: float,
    front_first_id: int,
    back_first_id: int | None,
    margin: float | None = None,
    panel: tuple[float, float, float, float] | None = None,
    name: str = "board",
    where: str = "board",
) -> Board:
    """Build a (double-sided unless ``back_first_id`` is None) grid board."""
    ids, corners = grid_corners(
        rows, cols, marker_length, separation, front_first_id, FRONT, thickness
    )
    if back_first_id is not None:
        ids_b, corners_b = grid_corners(
            rows, cols, marker_length, separation, back_first_id, BACK, thickness
        )
        ids = np.concatenate([ids, ids_b])
        corners = np.concatenate([corners, corners_b])
    d = aruco_dictionary(dictionary)
    corners, faces = validate_markers(ids, corners, thickness, d.bytesList.shape[0], where)
    if panel is None:
        m = separation if margin is None else margin
        w = cols * marker_length + (cols - 1) * separation
        h = rows * marker_length + (rows - 1) * separation
        panel = (-m, w + m, -m, h + m)
    grid = {
        "rows": rows,
        "cols": cols,
        "marker_length": marker_length,
        "separation": separation,
        "front_first_id": front_first_id,
        "back_first_id": back_first_id,
    }
    return Board(dictionary, ids, corners, faces, thickness, tuple(map(float, panel)), name, grid)


def refined_board(board: Board, T_front_back: np.ndarray) -> Board:
    """``board`` with its back sheet where ``T_front_back`` (4x4, metres, board frame) puts it:
    each back-face corner ``p`` becomes ``T_front_back p`` (the bundle adjustment's board
    self-calibration). The grid form cannot express a shifted or rotated back sheet, so the
    result is in the explicit form (every corner listed; :func:`.board_file.save_board` writes
    it, and :func:`.board_file.load_board` reads it back). The thickness becomes the mean depth
    of the moved back corners, which are put exactly on that plane (the tilts of the sheet are
    held at zero)."""
    T = np.asarray(T_front_back, dtype=float)
    corners = board.corners.copy()
    back = board.faces == BACK
    moved = corners[back].reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    thickness = board.thickness
    if len(moved):
        thickness = float(-moved[:, 2].mean())
        moved[:, 2] = -thickness
        corners[back] = moved.reshape(-1, 4, 3)
    return Board(board.dictionary, board.ids.copy(), corners, board.faces.copy(), thickness,
                 board.panel, board.name, None, print_scale_sigma=board.print_scale_sigma)


def thesis_board() -> Board:
    """The seed thesis's board (configs/board_thesis.yaml), built in code for defaults."""
    return board_from_grid("DICT_4X4_100", 4, 7, 0.04, 0.02, 0.0066, 0, 28,
                           panel=(-0.01, 0.41, -0.0385, 0.2585), name="thesis")


# ------------------------------------------------------------------------ multi-face targets
def pose_dict(T_board_face: np.ndarray) -> dict[str, list[float]]:
    """A face pose as the board file writes it: ``rotation_deg`` (rotation vector, axis times
    angle in degrees) and ``translation_m``."""
    T = np.asarray(T_board_face, dtype=float)
    return {"rotation_deg": [float(v) for v in np.degrees(matrix_to_rotvec(T[:3, :3]))],
            "translation_m": [float(v) for v in T[:3, 3]]}


def _sheet_dict(sheet: Board) -> dict[str, Any]:
    """A face's single-face board as its ``board:`` mapping (no name, thickness or type
    repeated where the target gives them)."""
    out = sheet.to_dict()
    out.pop("name", None)
    out.pop("thickness", None)
    if sheet.charuco is None and out.get("grid") is not None:
        out["grid"] = {k: v for k, v in out["grid"].items() if v is not None}
    return out


def sheet_panel_corners(sheet: FaceSheet) -> np.ndarray:
    """The four panel corners ``(4,3)`` of a face in the board frame (m)."""
    x0, x1, y0, y1 = sheet.board.panel
    local = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    return transform_points(sheet.T_board_face, local)


def _crossing(a: FaceSheet, b: FaceSheet, tol: float = FACE_CROSS_TOL_M) -> bool:
    """True when face ``b``'s panel passes through face ``a``'s panel: ``b`` has corners more
    than ``tol`` on both sides of ``a``'s plane and the line where it crosses that plane runs
    more than ``tol`` inside ``a``'s panel (faces meeting at an edge, as on a cube, do not)."""
    local = transform_points(np.linalg.inv(a.T_board_face), sheet_panel_corners(b))
    z = local[:, 2]
    if not (z.max() > tol and z.min() < -tol):
        return False
    pts = []
    for i in range(4):
        p, q = local[i], local[(i + 1) % 4]
        if (p[2] > 0) != (q[2] > 0):
            pts.append(p + (q - p) * (p[2] / (p[2] - q[2])))
    if len(pts) < 2:
        return False
    p, q = pts[0][:2], pts[1][:2]
    x0, x1, y0, y1 = a.board.panel
    lo, hi = np.array([x0 + tol, y0 + tol]), np.array([x1 - tol, y1 - tol])
    # clip the segment p + s (q - p), s in [0, 1], to the shrunk panel (Liang-Barsky)
    d, s0, s1 = q - p, 0.0, 1.0
    for k in range(2):
        if abs(d[k]) < 1e-15:
            if p[k] < lo[k] or p[k] > hi[k]:
                return False
            continue
        ta, tb = (lo[k] - p[k]) / d[k], (hi[k] - p[k]) / d[k]
        s0, s1 = max(s0, min(ta, tb)), min(s1, max(ta, tb))
    return s1 - s0 > 0 and (s1 - s0) * float(np.linalg.norm(d)) > tol


def multiface_board(dictionary: str, sheets: list[FaceSheet], thickness: float = 0.003,
                    name: str = "multiface", body=None, source: Path | None = None,
                    where: str = "board") -> Board:
    """A multi-face target from its faces (:class:`FaceSheet`, labels 1..F): the measurement
    ids (ArUco markers as they are, ChArUco quads shifted by the face's ``id_offset``) and
    corners in the board frame. Raises BoardError for printed marker ids used on two faces
    and for faces crossing each other."""
    sheets = list(sheets)
    printed = [(s, printed_markers(s.board)[0]) for s in sheets]
    seen: dict[int, int] = {}
    for s, ids in printed:
        for i in ids.tolist():
            if i in seen:
                raise BoardError(
                    f"{where}: marker id {i} is printed on faces[{seen[i] - 1}] and "
                    f"faces[{s.label - 1}]; ids must be unique over the target: give the faces "
                    "first ids (front_first_id / first_id) that do not overlap")
            seen[i] = s.label
    for i, a in enumerate(sheets):
        for b in sheets[i + 1:]:
            if _crossing(a, b) or _crossing(b, a):
                raise BoardError(
                    f"{where}: faces[{a.label - 1}] and faces[{b.label - 1}] pass through each "
                    "other; check their pose (rotation_deg, translation_m) and panels: faces may "
                    "meet at an edge but not cross")
    ids = np.concatenate([s.board.ids + s.id_offset for s in sheets]).astype(int)
    corners = np.concatenate([s.to_board(s.board.corners) for s in sheets])
    faces = np.concatenate([np.full(len(s.board.ids), s.label) for s in sheets]).astype(int)
    xy = np.concatenate([sheet_panel_corners(s) for s in sheets])
    panel = (float(xy[:, 0].min()), float(xy[:, 0].max()),
             float(xy[:, 1].min()), float(xy[:, 1].max()))
    return Board(dictionary, ids, corners, faces, float(thickness), panel, name, None, source,
                 None, tuple(sheets), body)


def refined_multiface(board: Board, T_board_face: dict[int, np.ndarray]) -> Board:
    """``board`` (multi-face) with its faces at the given poses (the bundle adjustment's
    self-calibration; faces not given keep theirs): what ``board_refined.yaml`` holds."""
    sheets = [replace(s, T_board_face=np.asarray(T_board_face.get(s.label, s.T_board_face),
                                                 dtype=float)) for s in board.sheets]
    return replace(multiface_board(board.dictionary, sheets, board.thickness, board.name,
                                   board.body, None, board.name),
                   print_scale_sigma=board.print_scale_sigma)
