"""Board files: loading, validating and saving the board forms (docs/formats.md).

A board file's ``type`` (:data:`~rgbd_calib.model.board.BoardType`) names its form:
``aruco`` (the default; a double-sided ArUco board in grid form, ``grid:``, or explicit
form, ``markers:``), ``charuco`` (one-faced ChArUco), ``checkerboard`` (a plain chessboard),
``aprilgrid`` (Kalibr's AprilGrid, optionally double-sided) or ``multiface`` (several faces,
each a single-face board at a pose). Kalibr's target files (``target_type: aprilgrid`` or
``checkerboard``) are read as they are (:data:`_FORMS` is the table of types). Every
mistake is one :class:`~rgbd_calib.core.errors.BoardError` line naming the file, the key and
the fix. The boards themselves are built by the
constructors of :mod:`rgbd_calib.model.board`.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import BoardError, ConfigError
from ..core.geometry import make_transform, rotvec_to_matrix
from ..core.yamlio import check_keys, read_yaml_mapping, write_yaml
from .aprilgrid import APRILGRID_DICTIONARY, KALIBR_KEYS, aprilgrid_board
from .board import (
    APRILGRID,
    ARUCO,
    CHARUCO,
    CHARUCO_ID_BASE,
    CHECKERBOARD,
    FRONT,
    MAX_LISTED_IDS,
    MULTIFACE,
    Board,
    CharucoSpec,
    FaceSheet,
    aruco_dictionary,
    board_from_charuco,
    board_from_grid,
    id_list,
    multiface_board,
    validate_markers,
)
from .checkerboard import CheckerSpec, check_orderable


def _number(value: Any, where: str, positive: bool = True, allow_zero: bool = False) -> float:
    try:
        ok = (not isinstance(value, bool) and isinstance(value, (int, float))
              and math.isfinite(float(value)))
    except OverflowError:
        ok = False
    if not ok:
        raise BoardError(f"{where}: expected a finite number, got {str(value)[:40]!r}")
    if positive and (value < 0 or (value == 0 and not allow_zero)):
        raise BoardError(f"{where}: must be positive, got {value!r}")
    return float(value)


def _int(value: Any, where: str, minimum: int = 0) -> int:
    if (isinstance(value, bool) or not isinstance(value, int) or value < minimum
            or value >= 2**31):
        raise BoardError(f"{where}: expected a whole number >= {minimum}, got "
                         f"{str(value)[:40]!r}")
    return int(value)


_TOP_KEYS = {
    "name",
    "dictionary",
    "thickness",
    "grid",
    "markers",
    "corner_order",
    "panel",
    "margin",
    "type",
    "print_scale_sigma",
}
_CHARUCO_KEYS = {
    "name", "type", "dictionary", "squares_x", "squares_y", "square_length", "marker_length",
    "legacy_pattern", "first_id", "inverted", "panel", "margin", "thickness", "print_scale_sigma",
}
_GRID_KEYS = {"rows", "cols", "marker_length", "separation", "front_first_id", "back_first_id"}


def _check_grid_fits(
    rows: int,
    cols: int,
    front_first_id: int,
    back_first_id: int | None,
    dictionary: str,
    dict_size: int,
    where: str,
) -> None:
    """Reject a grid with more markers than its dictionary has ids, or ids beyond it, before
    it is built marker by marker (a 100000 x 100000 grid would exhaust memory)."""
    per_face = rows * cols
    firsts = [front_first_id] + ([] if back_first_id is None else [back_first_id])
    if per_face * len(firsts) > dict_size:
        faces = " on each of 2 faces" if len(firsts) == 2 else ""
        raise BoardError(
            f"{where}: grid: {rows} x {cols} markers{faces} ({per_face * len(firsts)} in all) but "
            f"{dictionary} has only {dict_size} ids; use a larger dictionary or a smaller grid"
        )
    outside = [range(max(first, dict_size), first + per_face) for first in firsts]
    total = sum(len(r) for r in outside)
    if total:
        shown = [i for r in outside for i in r[:MAX_LISTED_IDS]][:MAX_LISTED_IDS]
        raise BoardError(
            f"{where}: marker id(s) {id_list(shown, total)} outside the dictionary "
            f"(ids 0..{dict_size - 1}); use a larger dictionary or fix the ids"
        )


def load_board(path: Path, fix_winding: bool = False) -> Board:
    """Load a board YAML in grid form or explicit form (see configs/board_thesis*.yaml).

    ``fix_winding`` (or ``corner_order: front`` in the file) reorders mirrored markers instead
    of rejecting them."""
    path = Path(path)
    where = str(path)
    raw = _read_raw_mapping(path)
    return _board_from_mapping(raw, path, where, fix_winding)


def _board_from_mapping(raw: dict, path: Path, where: str, fix_winding: bool = False) -> Board:
    """The board of a board file's top-level mapping (any ``type``), with its optional
    ``print_scale_sigma``."""
    board = _board_of_form(raw, path, where, fix_winding)
    _check_metres(board, where)
    sigma = raw.get("print_scale_sigma")
    if sigma is None:
        return board
    sigma = _number(sigma, f"{where}: print_scale_sigma", allow_zero=True)
    if sigma > MAX_PRINT_SCALE_SIGMA:
        raise BoardError(f"{where}: print_scale_sigma {sigma} is the printed size's relative "
                         "1 sigma (0.0005 for a print measured to 0.05 %); give at most "
                         f"{MAX_PRINT_SCALE_SIGMA:g}")
    return replace(board, print_scale_sigma=sigma)


MAX_BOARD_SPAN_M = 5.0  # a hand-held calibration target spans less; more is not metres


def _check_metres(board: Board, where: str) -> None:
    """A board whose markers span more than :data:`MAX_BOARD_SPAN_M` (or a panel thicker than
    half a metre) was written in other units than metres (millimetres, most often): every
    distance of the calibration would be scaled by 1000."""
    pts = np.asarray(board.corners, dtype=float).reshape(-1, 3)
    span = float(np.ptp(pts[:, :2], axis=0).max()) if len(pts) else 0.0
    if span > MAX_BOARD_SPAN_M or board.thickness > 0.5:
        raise BoardError(
            f"{where}: the markers span {span:g} and the panel is {board.thickness:g} thick, "
            "which cannot be metres (a hand-held board spans under "
            f"{MAX_BOARD_SPAN_M:g} m); board files are in metres: if it was written in "
            "millimetres, divide every length by 1000")


def _board_of_form(raw: dict, path: Path, where: str, fix_winding: bool) -> Board:
    """The board of a board file's top-level mapping, by its ``type`` (or a Kalibr target
    file's ``target_type``)."""
    if "target_type" in raw:
        raw = _from_kalibr(raw, where)
    kind = raw.get("type", ARUCO)
    if kind == ARUCO:
        return _load_aruco(raw, path, where, fix_winding)
    if not isinstance(kind, str) or kind not in _FORMS:
        raise BoardError(f"{where}: type must be one of {', '.join(_FORMS)} (default aruco); "
                         f"got {str(kind)[:40]!r}")
    return _FORMS[kind](raw, path, where)


_KALIBR_TYPES = {
    APRILGRID: KALIBR_KEYS,
    CHECKERBOARD: ("targetCols", "targetRows", "rowSpacingMeters", "colSpacingMeters"),
}


def _from_kalibr(raw: dict, where: str) -> dict:
    """A Kalibr target file's mapping as the board file of its type: ``target_type:
    aprilgrid`` keeps its keys, ``checkerboard``'s become ``cols``, ``rows`` (inner corners),
    ``col_spacing`` and ``row_spacing``. A one-line error for another ``target_type``."""
    kind = raw["target_type"]
    if kind not in _KALIBR_TYPES:
        raise BoardError(
            f"{where}: target_type {str(kind)[:40]!r}: the Kalibr targets read are "
            f"{' and '.join(_KALIBR_TYPES)}; describe another target in a board file of this "
            "project's form (docs/formats.md)")
    try:
        check_keys(raw, {"target_type", *_KALIBR_TYPES[kind]}, where,
                   required=_KALIBR_TYPES[kind])
    except ConfigError as exc:
        raise BoardError(str(exc)) from None
    if kind == APRILGRID:
        return {"type": APRILGRID, **{k: raw[k] for k in KALIBR_KEYS}}
    return {"type": CHECKERBOARD, "cols": raw["targetCols"], "rows": raw["targetRows"],
            "col_spacing": raw["colSpacingMeters"], "row_spacing": raw["rowSpacingMeters"]}


def _load_checkerboard(data: dict, path: Path, where: str) -> Board:
    """A ``type: checkerboard`` board file: ``cols`` x ``rows`` inner corners, squares of
    ``col_spacing`` x ``row_spacing`` m (``square_length`` for both); refused when no view
    could order its corners (:func:`~rgbd_calib.model.checkerboard.check_orderable`)."""
    try:
        check_keys(data, {"name", "type", "cols", "rows", "col_spacing", "row_spacing",
                          "square_length", "panel", "margin", "thickness",
                          "print_scale_sigma"}, where, required=("cols", "rows"))
    except ConfigError as exc:
        raise BoardError(str(exc)) from None
    cols = _int(data["cols"], f"{where}: cols", 1)
    rows = _int(data["rows"], f"{where}: rows", 1)
    check_orderable(cols, rows, where)
    if "square_length" in data:
        if "col_spacing" in data or "row_spacing" in data:
            raise BoardError(f"{where}: give square_length or col_spacing and row_spacing, "
                             "not both")
        sx = sy = _number(data["square_length"], f"{where}: square_length")
    elif "col_spacing" in data and "row_spacing" in data:
        sx = _number(data["col_spacing"], f"{where}: col_spacing")
        sy = _number(data["row_spacing"], f"{where}: row_spacing")
    else:
        raise BoardError(f"{where}: give square_length (m) or col_spacing and row_spacing")
    if cols * rows > 10000:
        raise BoardError(f"{where}: cols x rows is more than 10000 corners; check them")
    margin = data.get("margin")
    margin = None if margin is None else _number(margin, f"{where}: margin", allow_zero=True)
    return board_from_charuco("none", CheckerSpec(cols, rows, sx, sy),
                              _panel(data.get("panel"), where), margin,
                              str(data.get("name", path.stem)), path,
                              _number(data.get("thickness", 0.003), f"{where}: thickness"))


def _load_aprilgrid(data: dict, path: Path, where: str) -> Board:
    """A ``type: aprilgrid`` board file: Kalibr's keys (``tagCols``, ``tagRows``, ``tagSize``
    m, ``tagSpacing`` a fraction of ``tagSize``), and optionally ``back_first_id`` (a second
    grid on the back), ``thickness``, ``panel``, ``name``."""
    try:
        check_keys(data, {"name", "type", *KALIBR_KEYS, "back_first_id", "thickness", "panel",
                          "print_scale_sigma", "dictionary"}, where, required=KALIBR_KEYS)
    except ConfigError as exc:
        raise BoardError(str(exc)) from None
    if data.get("dictionary", APRILGRID_DICTIONARY) != APRILGRID_DICTIONARY:
        raise BoardError(f"{where}: an AprilGrid is printed with {APRILGRID_DICTIONARY} "
                         "tags; leave dictionary out or use type: aruco for other markers")
    cols = _int(data["tagCols"], f"{where}: tagCols", 1)
    rows = _int(data["tagRows"], f"{where}: tagRows", 1)
    if min(cols, rows) < 2:
        raise BoardError(f"{where}: an AprilGrid of {cols} x {rows} tags is too small; give "
                         "at least 2 x 2 tags")
    size = _number(data["tagSize"], f"{where}: tagSize")
    spacing = _number(data["tagSpacing"], f"{where}: tagSpacing")
    if spacing > 1.0:
        raise BoardError(f"{where}: tagSpacing {spacing} is the gap as a fraction of tagSize "
                         "(Kalibr's 0.3 for a gap of 30 % of a tag); give at most 1")
    back = data.get("back_first_id")
    back = None if back is None else _int(back, f"{where}: back_first_id")
    n_dict = aruco_dictionary(APRILGRID_DICTIONARY).bytesList.shape[0]
    _check_grid_fits(rows, cols, 0, back, APRILGRID_DICTIONARY, n_dict, where)
    if back is not None and back < cols * rows:
        raise BoardError(f"{where}: back_first_id {back} reuses the front's tag ids "
                         f"0..{cols * rows - 1}; give at least {cols * rows}")
    thickness = _number(data.get("thickness", 0.003), f"{where}: thickness",
                        allow_zero=back is None)
    return aprilgrid_board(cols, rows, size, spacing, thickness, back,
                           _panel(data.get("panel"), where), str(data.get("name", path.stem)),
                           path)


def _load_aruco(raw: dict, path: Path, where: str, fix_winding: bool) -> Board:
    """A ``type: aruco`` (default) board file, in grid or explicit form."""
    data = _check_board_mapping(raw, where)
    # the keys both forms share
    dictionary = str(data["dictionary"])
    try:
        d = aruco_dictionary(dictionary)
    except BoardError as exc:
        raise BoardError(f"{where}: {exc}") from None
    n_dict = d.bytesList.shape[0]
    thickness = _number(data["thickness"], f"{where}: thickness", allow_zero=True)
    name = str(data.get("name", path.stem))
    panel = _panel(data.get("panel"), where)
    # the form-specific part
    if "grid" in data:
        return _board_from_grid_form(data, dictionary, n_dict, thickness, panel, name, path, where)
    return _board_from_explicit_form(
        data, dictionary, n_dict, thickness, panel, name, path, where, fix_winding
    )


def _read_raw_mapping(path: Path) -> dict:
    """The board file's top-level mapping, unchecked (a BoardError when it is not one)."""
    try:
        return read_yaml_mapping(path, "board file")
    except BoardError:
        raise
    except ConfigError as exc:
        raise BoardError(str(exc)) from None


def _bool(value: Any, where: str) -> bool:
    if not isinstance(value, bool):
        raise BoardError(f"{where}: expected true or false, got {str(value)[:40]!r}")
    return value


def _load_charuco(data: dict, path: Path, where: str) -> Board:
    """A ``type: charuco`` board file (docs/formats.md): every key checked, one line per
    mistake naming the file, the key and the fix."""
    try:
        check_keys(data, _CHARUCO_KEYS, where, required=(
            "dictionary", "squares_x", "squares_y", "square_length", "marker_length"))
    except ConfigError as exc:
        raise BoardError(str(exc)) from None
    dictionary = str(data["dictionary"])
    try:
        d = aruco_dictionary(dictionary)
    except BoardError as exc:
        raise BoardError(f"{where}: dictionary: {exc}") from None
    spec = CharucoSpec(
        _int(data["squares_x"], f"{where}: squares_x", 3),
        _int(data["squares_y"], f"{where}: squares_y", 3),
        _number(data["square_length"], f"{where}: square_length"),
        _number(data["marker_length"], f"{where}: marker_length"),
        _bool(data.get("legacy_pattern", False), f"{where}: legacy_pattern"),
        _int(data.get("first_id", 0), f"{where}: first_id"),
        _bool(data.get("inverted", False), f"{where}: inverted"),
    )
    if spec.marker_length >= spec.square_length:
        raise BoardError(
            f"{where}: marker_length ({spec.marker_length}) must be smaller than square_length "
            f"({spec.square_length}); both in metres, the marker sits inside a white square")
    n_dict = d.bytesList.shape[0]
    if spec.first_id + spec.n_markers > n_dict:
        raise BoardError(
            f"{where}: first_id {spec.first_id} + {spec.n_markers} markers exceeds {dictionary} "
            f"({n_dict} ids); use a larger dictionary or a smaller first_id")
    if spec.squares_x * spec.squares_y > 10000:
        raise BoardError(f"{where}: squares_x x squares_y is more than 10000 squares; "
                         "check squares_x and squares_y")
    margin = data.get("margin")
    margin = None if margin is None else _number(margin, f"{where}: margin", allow_zero=True)
    thickness = _number(data.get("thickness", 0.003), f"{where}: thickness")
    return board_from_charuco(dictionary, spec, _panel(data.get("panel"), where), margin,
                              str(data.get("name", path.stem)), path, thickness)


def _check_board_mapping(data: dict, where: str) -> dict:
    """An ArUco board file's top-level mapping: known keys only, the required ones present,
    and exactly one of the grid and explicit forms (every failure a BoardError)."""
    try:
        check_keys(data, _TOP_KEYS, where, required=("dictionary", "thickness"))
    except ConfigError as exc:
        raise BoardError(str(exc)) from None
    if ("grid" in data) == ("markers" in data):
        raise BoardError(
            f"{where}: give exactly one of 'grid' (grid form) or 'markers' (explicit form)"
        )
    return data


def _panel(panel: Any, where: str) -> tuple[float, float, float, float] | None:
    """The optional ``panel`` key: ``[xmin, xmax, ymin, ymax]`` in metres, min < max."""
    if panel is None:
        return None
    if not (isinstance(panel, list) and len(panel) == 4):
        raise BoardError(f"{where}: panel must be [xmin, xmax, ymin, ymax] in metres")
    panel = tuple(_number(v, f"{where}: panel", positive=False) for v in panel)
    if panel[0] >= panel[1] or panel[2] >= panel[3]:
        raise BoardError(f"{where}: panel must be [xmin, xmax, ymin, ymax] with min < max")
    return panel


def _board_from_grid_form(
    data: dict,
    dictionary: str,
    n_dict: int,
    thickness: float,
    panel: tuple[float, float, float, float] | None,
    name: str,
    path: Path,
    where: str,
) -> Board:
    """The board of a grid-form file (the ``grid`` mapping and the optional ``margin``, m);
    ``n_dict`` is the dictionary's marker count."""
    g = data["grid"]
    if not isinstance(g, dict):
        raise BoardError(f"{where}: grid must be a mapping")
    try:
        check_keys(
            g,
            _GRID_KEYS,
            f"{where}: grid",
            required=("rows", "cols", "marker_length", "separation", "front_first_id"),
        )
    except ConfigError as exc:
        raise BoardError(str(exc)) from None
    back = g.get("back_first_id")
    margin = data.get("margin")
    rows = _int(g["rows"], f"{where}: grid.rows", 1)
    cols = _int(g["cols"], f"{where}: grid.cols", 1)
    front_id = _int(g["front_first_id"], f"{where}: grid.front_first_id")
    back_id = None if back is None else _int(back, f"{where}: grid.back_first_id")
    _check_grid_fits(rows, cols, front_id, back_id, dictionary, n_dict, where)
    board = board_from_grid(
        dictionary,
        rows,
        cols,
        _number(g["marker_length"], f"{where}: grid.marker_length"),
        _number(g["separation"], f"{where}: grid.separation", allow_zero=True),
        thickness,
        front_id,
        back_id,
        None if margin is None else _number(margin, f"{where}: margin", allow_zero=True),
        panel,
        name,
        where,
    )
    return Board(
        board.dictionary,
        board.ids,
        board.corners,
        board.faces,
        board.thickness,
        board.panel,
        board.name,
        board.grid,
        path,
    )  # (an ArUco board: charuco stays None)


def _board_from_explicit_form(
    data: dict,
    dictionary: str,
    n_dict: int,
    thickness: float,
    panel: tuple[float, float, float, float] | None,
    name: str,
    path: Path,
    where: str,
    fix_winding: bool,
) -> Board:
    """The board of an explicit-form file (``markers``: id -> 4 corners in metres, the
    optional ``corner_order`` and ``margin``); faces and winding checked by
    :func:`validate_markers`, the panel defaulting to the corners' extent plus the margin."""
    order = data.get("corner_order", "detection")
    if order not in ("detection", "front"):
        raise BoardError(f"{where}: corner_order must be 'detection' or 'front', got {order!r}")
    ids_a, corners_a = _explicit_markers(data["markers"], where)
    corners_a, faces = validate_markers(
        ids_a,
        corners_a,
        thickness,
        n_dict,
        where,
        fix_winding=fix_winding or order == "front",
    )
    if panel is None:
        m = _number(data.get("margin", 0.0) or 0.0, f"{where}: margin", allow_zero=True)
        lo = corners_a.reshape(-1, 3).min(axis=0)
        hi = corners_a.reshape(-1, 3).max(axis=0)
        panel = (lo[0] - m, hi[0] + m, lo[1] - m, hi[1] + m)
    return Board(
        dictionary, ids_a, corners_a, faces, thickness, tuple(map(float, panel)), name, None, path
    )


def _explicit_markers(markers: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    """The ``markers`` mapping as ids ``(N,)`` and corners ``(N,4,3)`` (m, file order):
    whole-number ids in [0, 2^31), four finite 3-D corners each."""
    if not isinstance(markers, dict) or not markers:
        raise BoardError(
            f"{where}: markers must map marker id -> 4 corners [[x,y,z], ...]; use the form of "
            "configs/board_thesis_table42.yaml"
        )
    ids, corners = [], []
    for key, value in markers.items():
        try:
            if isinstance(key, bool) or (isinstance(key, float) and not key.is_integer()):
                raise ValueError("not a whole number")
            mid = int(key)
            if not 0 <= mid < 2**31:
                raise ValueError("id out of range")
            c = np.asarray(value, dtype=float)
        except (TypeError, ValueError, OverflowError):
            raise BoardError(
                f"{where}: marker {key!r}: expected an integer id and 4 corners of 3 numbers"
            ) from None
        if c.shape != (4, 3) or not np.all(np.isfinite(c)):
            raise BoardError(
                f"{where}: marker {key}: expected 4 corners of 3 finite numbers, "
                f"got shape {c.shape}"
            )
        ids.append(mid)
        corners.append(c)
    return np.asarray(ids, dtype=int), np.asarray(corners, dtype=float)


MAX_PRINT_SCALE_SIGMA = 0.05  # a board file's print_scale_sigma: a print known to 5 % at worst
DATASET_BOARD_FILE = "board.yaml"  # a dataset folder's own board (docs/formats.md)


def save_board(board: Board, path: Path) -> None:
    write_yaml(path, board.to_dict())


def dataset_board_file(dataset_dir: str | Path) -> Path | None:
    """The dataset folder's own board file (``board.yaml``, written by ``synth`` and
    ``convert --board``), or None."""
    path = Path(dataset_dir) / DATASET_BOARD_FILE
    return path if path.is_file() else None


# ------------------------------------------------------------------------ multi-face targets
_MULTIFACE_KEYS = {"name", "type", "dictionary", "thickness", "faces", "body",
                   "print_scale_sigma"}
_FACE_KEYS = {"board", "pose"}
_POSE_KEYS = {"rotation_deg", "translation_m"}


def _vector3(value: Any, where: str) -> np.ndarray:
    if not (isinstance(value, list) and len(value) == 3):
        raise BoardError(f"{where}: expected 3 numbers [x, y, z]")
    return np.array([_number(v, where, positive=False) for v in value])


def _face_pose(value: Any, where: str) -> np.ndarray:
    """A face's ``pose`` mapping: ``rotation_deg`` (rotation vector, degrees; default none)
    and ``translation_m`` (default zeros): ``T_board_face``."""
    if value is None:
        return np.eye(4)
    if not isinstance(value, dict):
        raise BoardError(f"{where}: expected a mapping with rotation_deg: [rx, ry, rz] (rotation "
                         "vector, degrees) and translation_m: [x, y, z]")
    try:
        check_keys(value, _POSE_KEYS, where)
    except ConfigError as exc:
        raise BoardError(str(exc)) from None
    rot = _vector3(value.get("rotation_deg", [0, 0, 0]), f"{where}.rotation_deg")
    t = _vector3(value.get("translation_m", [0, 0, 0]), f"{where}.translation_m")
    return make_transform(rotvec_to_matrix(np.radians(rot)), t)


def _load_multiface(data: dict, path: Path, where: str) -> Board:
    """A ``type: multiface`` board file (docs/formats.md): each face a single-face ArUco grid
    (or explicit markers) or ChArUco board at a pose; the target's ``dictionary`` and
    ``thickness`` are the faces' defaults. Every mistake one line naming the file, the face
    and the fix: a face with markers on its back, another dictionary, marker ids used twice
    over the target, faces crossing each other."""
    try:
        check_keys(data, _MULTIFACE_KEYS, where, required=("faces",))
    except ConfigError as exc:
        raise BoardError(str(exc)) from None
    faces = data["faces"]
    if not isinstance(faces, list) or not faces:
        raise BoardError(f"{where}: faces must be a list of {{board: ..., pose: ...}}, one per "
                         "face; see configs/board_cube.yaml")
    dictionary = data.get("dictionary")
    thickness = _number(data.get("thickness", 0.003), f"{where}: thickness")
    sheets = []
    for k, face in enumerate(faces):
        fwhere = f"{where}: faces[{k}]"
        if not isinstance(face, dict):
            raise BoardError(f"{fwhere}: expected a mapping {{board: ..., pose: ...}}")
        try:
            check_keys(face, _FACE_KEYS, fwhere, required=("board",))
        except ConfigError as exc:
            raise BoardError(str(exc)) from None
        sheet = _face_board(face["board"], path, fwhere, dictionary, thickness)
        if dictionary is None:
            dictionary = sheet.dictionary
        if sheet.dictionary != dictionary:
            raise BoardError(f"{fwhere}: dictionary {sheet.dictionary} differs from the "
                             f"target's {dictionary}; one dictionary for every face")
        T = _face_pose(face.get("pose"), f"{fwhere}.pose")
        offset = CHARUCO_ID_BASE * (k + 1) if sheet.charuco is not None else 0
        bits = {s.board.border_bits for s in sheets if s.board.pattern is None}
        if sheet.pattern is None and bits and sheet.border_bits not in bits:
            raise BoardError(f"{fwhere}: its markers' border ({sheet.border_bits} cells) "
                             "differs from the other faces'; one marker print for every face")
        sheets.append(FaceSheet(k + 1, sheet, T, offset))
    return multiface_board(str(dictionary), sheets, thickness, str(data.get("name", path.stem)),
                           _body(data.get("body"), where), path, where)


_FORMS = {
    ARUCO: None,  # read by _load_aruco (its explicit form takes fix_winding)
    CHARUCO: _load_charuco,
    CHECKERBOARD: _load_checkerboard,
    APRILGRID: _load_aprilgrid,
    MULTIFACE: _load_multiface,
}


def _face_board(value: Any, path: Path, where: str, dictionary: str | None,
                thickness: float) -> Board:
    """A face's ``board``: a mapping in a single-face board file's form, or the path of such a
    file (relative to the target's file); the target's dictionary and thickness fill in."""
    if isinstance(value, str):
        sub = (path.parent / value) if not Path(value).is_absolute() else Path(value)
        return _face_board(_read_raw_mapping(sub), sub, f"{where} ({sub})", dictionary,
                           thickness)
    if not isinstance(value, dict):
        raise BoardError(f"{where}.board: expected a board mapping (grid or ChArUco form) or "
                         "the path of a single-face board file")
    raw = dict(value)
    if raw.get("type") == MULTIFACE:
        raise BoardError(f"{where}.board: a face cannot itself be a multiface target")
    if dictionary is not None:
        raw.setdefault("dictionary", dictionary)
    if raw.get("type", ARUCO) == ARUCO:
        raw.setdefault("thickness", thickness)
        if isinstance(raw.get("grid"), dict) and raw["grid"].get("back_first_id") is not None:
            raise BoardError(f"{where}.board: grid.back_first_id: a face is one sheet; give "
                             "the back sheet as a face of its own with its pose")
    sheet = _board_from_mapping(raw, path, f"{where}.board")
    if sheet.board_type == CHECKERBOARD:
        raise BoardError(f"{where}.board: a checkerboard face cannot say which face a view "
                         "sees; give the target's faces as ArUco, AprilGrid or ChArUco sheets")
    if np.any(sheet.faces != FRONT):
        raise BoardError(f"{where}.board: markers off the sheet's z = 0 plane; a face is one "
                         "sheet: list its markers at z = 0 and give the face a pose")
    return sheet


def _body(value: Any, where: str):
    """The optional ``body: {box: [[x0, y0, z0], [x1, y1, z1]]}`` (m, board frame): the solid
    the faces are mounted on (rendered and masked like the faces)."""
    if value is None:
        return None
    if not (isinstance(value, dict) and set(value) == {"box"} and isinstance(value["box"], list)
            and len(value["box"]) == 2):
        raise BoardError(f"{where}: body must be {{box: [[x0, y0, z0], [x1, y1, z1]]}} "
                         "(metres, board frame)")
    lo = _vector3(value["box"][0], f"{where}: body.box[0]")
    hi = _vector3(value["box"][1], f"{where}: body.box[1]")
    if np.any(lo >= hi):
        raise BoardError(f"{where}: body.box must be [[x0, y0, z0], [x1, y1, z1]] with "
                         "x0 < x1, y0 < y1, z0 < z1")
    return tuple(map(float, lo)), tuple(map(float, hi))
