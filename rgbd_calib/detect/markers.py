"""ArUco marker detection with an unbiased subpixel corner refinement; ChArUco saddle corners.

OpenCV's corner refinements sit inside the true marker corner (measured: docs/accuracy.md),
which shrinks every marker and biases board poses. The ``"edges"`` refinement removes that
bias: corners as intersections of lines fitted to each marker's four *outer* edges with a
model of the blurred image across the edge (:mod:`rgbd_calib.detect.edge_fit`).

ChArUco boards (``board.charuco``, :func:`detect_charuco`): the chessboard saddle corners are
the measurements, the markers only identify them. They are returned in the same
:class:`MarkerDetections` as ArUco markers, so the cache, the per-view PnP, the pose graph,
the bundle adjustment and the report take them unchanged: each "marker" is a quad of 4 saddle
corners (ids and board points from :meth:`rgbd_calib.model.board.CharucoSpec.quads`, the unit
squares of the corner grid), the quads :func:`rgbd_calib.model.board.cover_quads` picks in each view
so that every found corner lying in a whole quad is used, about once. The price: a corner in no
whole quad (its three neighbours of a square not all found) is not used, and a few corners are
used twice (slightly optimistic covariances). A measurement of any number of points would need
the bundle's and PnP's per-marker (4-point) structures generalised.

``detect_markers`` is a pure function of ``(image, board, config)`` so callers can run it in a
process pool; it never touches ``board.aruco_dict`` (a cached ``cv2`` object that cannot be
pickled).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.config import DetectionConfig
from ..model.board import (
    APRILGRID,
    CHARUCO,
    CHECKERBOARD,
    Board,
    aruco_dictionary,
    cover_quads,
)
from ..model.dataset import read_color_image
from .checkerboard import detect_checkerboard
from .detections import MarkerDetections, to_gray
from .edge_fit import refine_corners_edges

_CV_REFINE = {
    "edges": cv2.aruco.CORNER_REFINE_NONE,  # edge fit from the contour corners (fails less)
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
}


@lru_cache(maxsize=4096)
def marker_pattern(dictionary: str, marker_id: int, border_bits: int = 1) -> np.ndarray:
    """A marker's cells ``(bits+2b, bits+2b)``, True where white, row 0 at its top edge, the
    ``b`` = ``border_bits`` black border included (what the edge model needs to know behind
    the border)."""
    d = aruco_dictionary(dictionary)
    n = int(d.markerSize) + 2 * border_bits
    img = cv2.aruco.generateImageMarker(d, int(marker_id), n, borderBits=border_bits)
    out = img > 127
    out.setflags(write=False)
    return out


def _marker_parameters(config: DetectionConfig, image_size: tuple[int, int],
                       border_bits: int = 1) -> cv2.aruco.DetectorParameters:
    """OpenCV's marker-finding parameters from ``config`` (ArUco and ChArUco boards alike;
    ``border_bits`` the markers' printed border, :attr:`Board.border_bits`)."""
    params = cv2.aruco.DetectorParameters()
    params.markerBorderBits = int(border_bits)
    params.minMarkerPerimeterRate = config.min_marker_perimeter_px / max(image_size)
    params.errorCorrectionRate = config.error_correction_rate
    params.adaptiveThreshWinSizeMin = config.aruco.adaptive_thresh_win_size_min
    params.adaptiveThreshWinSizeMax = config.aruco.adaptive_thresh_win_size_max
    params.adaptiveThreshWinSizeStep = config.aruco.adaptive_thresh_win_size_step
    return params


def _detector(
    dictionary: cv2.aruco.Dictionary, config: DetectionConfig, image_size: tuple[int, int],
    border_bits: int = 1, from_junctions: bool = False,
) -> cv2.aruco.ArucoDetector:
    """OpenCV's detector. ``from_junctions``: the markers' corners touch black squares (an
    AprilGrid), so the contour's corners are pulled outwards (1.5 px median on a ring
    render) and the edge fit starts from OpenCV's SUBPIX corners at the junctions instead
    (measured there: 8 % of corners left unrefined instead of 30 %, the refined ones 0.024 px
    RMS from the truth instead of 0.065)."""
    params = _marker_parameters(config, image_size, border_bits)
    method = config.refinement
    params.cornerRefinementMethod = _CV_REFINE["subpix" if from_junctions and method == "edges"
                                               else method]
    params.cornerRefinementWinSize = config.aruco.subpix_win_size_px
    params.relativeCornerRefinmentWinSize = config.aruco.subpix_relative_win_size  # (sic)
    params.cornerRefinementMaxIterations = config.aruco.subpix_max_iterations
    params.cornerRefinementMinAccuracy = config.aruco.subpix_min_accuracy_px
    return cv2.aruco.ArucoDetector(dictionary, params)


def _gray_float(image: np.ndarray) -> np.ndarray:
    """Grey image for the edge fit: float for a BGR image (no 8-bit rounding of the BGR ->
    grey conversion), else the uint8 grey image itself (the fit converts only the pixels it
    reads, not the whole image)."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        return image.astype(np.float32) @ np.array([0.114, 0.587, 0.299], dtype=np.float32)
    return to_gray(image)


def _refine_with_board(
    detector: cv2.aruco.ArucoDetector,
    dictionary: cv2.aruco.Dictionary,
    gray: np.ndarray,
    board: Board,
    corners,
    ids,
    rejected,
):
    """OpenCV's refineDetectedMarkers against the layout of the face seen most (one face: a
    two-faced layout would predict back markers where front ones are)."""
    faces = board.faces[[board.index_of[int(i)] for i in ids if int(i) in board.index_of]]
    if faces.size == 0:
        return corners, ids
    sel = board.faces == board.most_seen_face(faces)
    cv_board = cv2.aruco.Board(
        board.corners[sel].astype(np.float32), dictionary, board.ids[sel].astype(np.int32)
    )  # float32: api-notes
    corners, ids, _, _ = detector.refineDetectedMarkers(gray, cv_board, corners, ids, rejected)
    return corners, ids


def detect_markers(
    image: np.ndarray,
    board: Board,
    config: DetectionConfig | None = None,
    intrinsics: CameraIntrinsics | None = None,
) -> MarkerDetections:
    """Detect the board's markers in a BGR or grey image (a pure function: safe to map over
    images in a process pool).

    Steps: OpenCV's detector; ids not on the board go to ``foreign_ids``; an id seen twice
    cannot be both on the rigid board, so every copy is dropped and the id recorded in
    ``duplicate_ids``; markers the detector rejected but the board layout predicts are
    recovered (``refine_with_board``, fed only the unique on-board markers: a duplicated id
    would spoil its board fit), and the duplicate rule is applied again to its output; then
    the corner refinement. With ``intrinsics`` that have lens distortion, the edge fit bends
    with the distortion (a quadratic term per edge), fits its lines in undistorted pixels and
    maps the corners back to distorted pixels.
    """
    config = config or DetectionConfig()
    if board.sheets:
        return detect_multiface(image, board, config, intrinsics)
    if board.pattern is not None:
        return _PATTERN_DETECTORS[board.pattern.kind](image, board, config)
    gray = to_gray(image)
    size = (int(gray.shape[1]), int(gray.shape[0]))
    dictionary = aruco_dictionary(board.dictionary)
    detector = _detector(dictionary, config, size, board.border_bits,
                         from_junctions=board.board_type == APRILGRID)
    corners, ids, rejected = detector.detectMarkers(gray)
    foreign = duplicate = np.zeros(0, dtype=int)
    if ids is not None and len(ids):
        flat = np.asarray(ids, dtype=int).reshape(-1)
        on_board = np.array([int(i) in board.index_of for i in flat], dtype=bool)
        foreign = np.unique(flat[~on_board])
        uniq, counts = np.unique(flat[on_board], return_counts=True)
        duplicate = uniq[counts > 1]
        keep = on_board & ~np.isin(flat, duplicate)
        if not keep.all():  # else OpenCV's own output, untouched
            corners = tuple(c for c, k in zip(corners, keep) if k)
            ids = ids[keep]
    if ids is not None and len(ids) and config.refine_with_board:
        corners, ids = _refine_with_board(detector, dictionary, gray, board, corners, ids, rejected)
    if ids is None or len(ids) == 0:
        empty = np.zeros(0, dtype=int)
        return MarkerDetections(
            empty,
            np.zeros((0, 4, 2)),
            np.zeros((0, 4), bool),
            foreign,
            duplicate,
            size,
            config.refinement,
        )
    ids = np.asarray(ids, dtype=int).reshape(-1)
    corners_px = np.asarray(corners, dtype=float).reshape(-1, 4, 2)
    # the refinement only adds board markers, but may add one twice or one dropped above
    on_board = np.array([int(i) in board.index_of for i in ids], dtype=bool)
    foreign = np.union1d(foreign, ids[~on_board])
    ids, corners_px = ids[on_board], corners_px[on_board]
    uniq, counts = np.unique(ids, return_counts=True)
    duplicate = np.union1d(duplicate, uniq[counts > 1])
    keep = ~np.isin(ids, duplicate)
    ids, corners_px = ids[keep], corners_px[keep]
    order = np.argsort(ids, kind="stable")
    ids, corners_px = ids[order], corners_px[order]
    refined = np.zeros(corners_px.shape[:2], dtype=bool)
    if config.refinement == "edges" and len(ids):
        white = np.stack([marker_pattern(board.dictionary, int(i), board.border_bits)
                          for i in ids])
        corners_px, refined = refine_corners_edges(
            _gray_float(image), corners_px, white, config, intrinsics
        )
        if not refined.all():
            corners_px = _subpix_fallback(gray, corners_px, ~refined, board, config)
    return MarkerDetections(ids, corners_px, refined, foreign, duplicate, size, config.refinement)


def _subpix_fallback(
    gray: np.ndarray,
    corners_px: np.ndarray,
    mask: np.ndarray,
    board: Board,
    config: DetectionConfig,
) -> np.ndarray:
    """OpenCV's SUBPIX refinement (cornerSubPix, the window sized as the detector sizes it)
    of the corners in ``mask`` ``(N,4)``: the fallback for corners the edge fit rejected."""
    out = corners_px.copy()
    cells = int(aruco_dictionary(board.dictionary).markerSize) + 2 * board.border_bits
    side = np.linalg.norm(np.roll(corners_px, -1, axis=1) - corners_px, axis=-1).mean(axis=1)
    aruco = config.aruco
    win = np.clip(np.ceil(aruco.subpix_relative_win_size * side / cells), 1,
                  aruco.subpix_win_size_px).astype(int)
    criteria = (
        cv2.TERM_CRITERIA_MAX_ITER | cv2.TERM_CRITERIA_EPS,
        config.aruco.subpix_max_iterations,
        config.aruco.subpix_min_accuracy_px,
    )
    for w in np.unique(win[mask.any(axis=1)]):
        sel = mask & (win == w)[:, None]
        pts = corners_px[sel].astype(np.float32).reshape(-1, 1, 2)
        cv2.cornerSubPix(gray, pts, (int(w), int(w)), (-1, -1), criteria)
        out[sel] = pts.reshape(-1, 2)
    return out


def detect_multiface(
    image: np.ndarray,
    board: Board,
    config: DetectionConfig | None = None,
    intrinsics: CameraIntrinsics | None = None,
) -> MarkerDetections:
    """The measurements of a multi-face target (``board.sheets``): its ArUco faces' markers in
    one pass of :func:`detect_markers` over them all (one dictionary, ids unique over the
    target), each ChArUco face's saddle-corner quads by :func:`detect_charuco` with its ids
    shifted by the face's ``id_offset``. ``foreign_ids`` are the markers printed nowhere on
    the target."""
    config = config or DetectionConfig()
    parts = []
    aruco = board.aruco_faces
    if aruco is not None:
        parts.append(detect_markers(image, aruco, config, intrinsics))
    for s in board.sheets:
        if s.board.pattern is not None:
            det = _PATTERN_DETECTORS[s.board.pattern.kind](image, s.board, config)
            parts.append(MarkerDetections(det.ids + s.id_offset, det.corners_px, det.refined,
                                          det.foreign_ids, det.duplicate_ids, det.image_size,
                                          det.refinement))
    printed = set(board.printed_ids.tolist())
    foreign = np.unique(np.concatenate([p.foreign_ids for p in parts] + [np.zeros(0, int)]))
    foreign = np.array([i for i in foreign.tolist() if i not in printed], dtype=int)
    ids = np.concatenate([p.ids for p in parts]).astype(int)
    order = np.argsort(ids, kind="stable")
    refinement = parts[0].refinement  # the ArUco faces' when there are any (pose.py drops
    #                                   unrefined edge-fit corners by it; quads are all refined)
    return MarkerDetections(
        ids[order], np.concatenate([p.corners_px for p in parts])[order],
        np.concatenate([p.refined for p in parts])[order], foreign,
        np.unique(np.concatenate([p.duplicate_ids for p in parts])).astype(int),
        parts[0].image_size, refinement)


# --------------------------------------------------------------------------- ChArUco
CHARUCO_WIN_FRACTION = 0.8  # cornerSubPix half-window / the white margin around a marker


def detect_charuco(
    image: np.ndarray, board: Board, config: DetectionConfig | None = None,
    corners: str | None = None,
) -> MarkerDetections:
    """The saddle corners of a ChArUco board (``board.charuco``) in a BGR or grey image, as
    the board's saddle-corner quads (see :class:`rgbd_calib.model.board.CharucoSpec`): whole quads
    (all 4 corners found) chosen by :func:`rgbd_calib.model.board.cover_quads`, ``corners_px``
    ``(N,4,2)`` in their order.

    Steps: an inverted print is inverted back (so OpenCV sees black markers); OpenCV's
    ``CharucoDetector.detectBoard`` finds the markers (identification only) and interpolates
    the saddle corners from them; each corner is then refined (``corners``, default
    ``config.charuco_corners``): ``"painted"`` fills every detected marker with the white of
    its margin (:func:`_paint_markers`), so a ``cv2.cornerSubPix`` window of
    :data:`PAINTED_WIN_FRACTION` of a square sees only the four chessboard squares;
    ``"subpix"`` runs cornerSubPix on the raw image with a window inside the white margin
    (:data:`CHARUCO_WIN_FRACTION`; a larger one reaches the markers and is pulled off);
    ``"opencv"`` keeps the detector's corners (their bias and scatter on renders, measured:
    docs/accuracy.md)."""
    config = config or DetectionConfig()
    spec = board.charuco
    size = (int(np.asarray(image).shape[1]), int(np.asarray(image).shape[0]))
    ids, px, foreign = _saddles(image, board, config, corners)
    empty = MarkerDetections(np.zeros(0, dtype=int), np.zeros((0, 4, 2)),
                             np.zeros((0, 4), bool), foreign, np.zeros(0, dtype=int), size,
                             "charuco")
    if len(ids) == 0:
        return empty
    quads = spec.quads()
    q_ids = cover_quads(quads, ids)
    if len(q_ids) == 0:
        return empty
    found = dict(zip(ids.tolist(), px))
    q_px = np.array([[found[int(k)] for k in quads[i]] for i in q_ids])
    return MarkerDetections(q_ids, q_px, np.ones((len(q_ids), 4), bool), foreign,
                            np.zeros(0, dtype=int), size, "charuco")


def detect_saddles(
    image: np.ndarray, board: Board, config: DetectionConfig | None = None,
    corners: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The refined saddle corners of a ChArUco board one by one (not in quads, as
    :func:`detect_charuco` reports them): OpenCV's ChArUco corner ids ``(K,)`` and pixels
    ``(K,2)``, refined by ``corners`` (default ``config.charuco_corners``)."""
    ids, px, _ = _saddles(image, board, config or DetectionConfig(), corners)
    return ids, px


def _saddles(
    image: np.ndarray, board: Board, config: DetectionConfig, corners: str | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Saddle-corner ids ``(K,)``, refined pixels ``(K,2)`` and the foreign marker ids seen
    (the steps of :func:`detect_charuco`)."""
    spec = board.charuco
    method = corners or config.charuco_corners
    gray = to_gray(image)
    if spec.inverted:
        gray = 255 - gray
    size = (int(gray.shape[1]), int(gray.shape[0]))
    dictionary = aruco_dictionary(board.dictionary)
    cv_board = spec.cv_board(dictionary)
    detector = cv2.aruco.CharucoDetector(cv_board, cv2.aruco.CharucoParameters(),
                                         _marker_parameters(config, size))
    ch_corners, ch_ids, marker_corners, marker_ids = detector.detectBoard(gray)
    foreign = np.zeros(0, dtype=int)
    if marker_ids is not None:
        m = np.asarray(marker_ids, dtype=int).reshape(-1)
        foreign = np.unique(m[(m < spec.first_id) | (m >= spec.first_id + spec.n_markers)])
    if ch_ids is None or len(ch_ids) == 0:
        return np.zeros(0, dtype=int), np.zeros((0, 2)), foreign
    ids = np.asarray(ch_ids, dtype=int).reshape(-1)
    px = np.asarray(ch_corners, dtype=np.float64).reshape(-1, 2)
    if method == "subpix":
        px = _saddle_subpix(gray, px, ids, spec, config)
    elif method == "painted":
        painted = _paint_markers(gray, marker_corners, spec)
        px = _saddle_subpix(painted, px, ids, spec, config, fraction=PAINTED_WIN_FRACTION,
                            of_square=True)
    return ids, px, foreign


_PATTERN_DETECTORS = {CHARUCO: detect_charuco, CHECKERBOARD: detect_checkerboard}

PAINTED_WIN_FRACTION = 0.4  # half-window / square, markers painted out
PAINT_GROW_PX = 1.5  # a painted marker extends this far beyond its detected outline


def _paint_markers(gray: np.ndarray, marker_corners, spec) -> np.ndarray:
    """A float32 copy of ``gray`` with each detected marker (outline grown by
    :data:`PAINT_GROW_PX`) filled with the white of its square (the median of the white
    margin ring between the grown marker and the square shrunk by as much; a fixed
    percentile of the square instead left an outward scale bias, measured: docs/accuracy.md):
    around a saddle corner only the chessboard remains."""
    out = gray.astype(np.float32)
    if marker_corners is None:
        return out
    grow_sq = spec.square_length / spec.marker_length
    for c in marker_corners:
        c = np.asarray(c, dtype=np.float64).reshape(4, 2)
        centre = c.mean(axis=0)
        side = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1).mean()
        grown = centre + (c - centre) * (1.0 + 2.0 * PAINT_GROW_PX / max(side, 1.0))
        square = centre + (c - centre) * (grow_sq - 2.0 * PAINT_GROW_PX / max(side, 1.0))
        mask = np.zeros(gray.shape, np.uint8)
        cv2.fillConvexPoly(mask, np.round(square * 16).astype(np.int32), 1, cv2.LINE_8, 4)
        cv2.fillConvexPoly(mask, np.round(grown * 16).astype(np.int32), 2, cv2.LINE_8, 4)
        ring = gray[mask == 1]  # the white margin between the marker and the black squares
        white = float(np.median(ring)) if ring.size else float(np.percentile(gray[mask > 0], 90))
        out[mask == 2] = white
    return out


def _square_px(px: np.ndarray, ids: np.ndarray, spec) -> np.ndarray:
    """Size of a chessboard square at each detected corner ``(M,2)`` in pixels, its narrowest
    extent: with both grid neighbours along x and y detected, the height of the parallelogram
    they span (an oblique view shears the squares: a window sized by the side alone reached
    the next corners and pulled the refinement several pixels off); else the distance to the
    nearest other corner over their grid distance."""
    if len(px) < 2:
        return np.full(len(px), 8.0)
    d = np.linalg.norm(px[:, None] - px[None], axis=-1)
    d[np.arange(len(px)), np.arange(len(px))] = np.inf
    nx = spec.squares_x - 1
    grid = np.stack([ids % nx, ids // nx], axis=1)
    steps = np.abs(grid[:, None] - grid[None]).max(axis=-1).astype(float)
    steps[steps == 0] = 1.0  # (only the corner itself, whose distance is inf)
    out = np.min(d / steps, axis=1)
    where = {(int(c), int(r)): k for k, (c, r) in enumerate(grid)}
    for k, (c, r) in enumerate(grid):
        ex = [px[where[(c + s, r)]] - px[k] for s in (1, -1) if (c + s, r) in where]
        ey = [px[where[(c, r + s)]] - px[k] for s in (1, -1) if (c, r + s) in where]
        if ex and ey:
            a, b = ex[0], ey[0]
            cross = abs(a[0] * b[1] - a[1] * b[0])
            out[k] = min(out[k], cross / max(np.linalg.norm(a), np.linalg.norm(b)))
    return out


def _saddle_subpix(
    gray: np.ndarray, px: np.ndarray, ids: np.ndarray, spec, config: DetectionConfig,
    fraction: float | None = None, of_square: bool = False,
) -> np.ndarray:
    """``cv2.cornerSubPix`` of saddle corners ``(M,2)``, half-window ``fraction`` (default
    :data:`CHARUCO_WIN_FRACTION`) of the white margin around the markers, or of the square
    with ``of_square``, in the image near each corner (:func:`_square_px`), 2 to 25 px."""
    out = px.copy()
    square_px = _square_px(px, ids, spec)
    margin_px = square_px * (1.0 - spec.marker_length / spec.square_length) / 2
    size_px = square_px if of_square else margin_px
    fraction = CHARUCO_WIN_FRACTION if fraction is None else fraction
    win = np.clip(np.floor(fraction * size_px), 2, 25).astype(int)
    criteria = (cv2.TERM_CRITERIA_MAX_ITER | cv2.TERM_CRITERIA_EPS,
                config.aruco.subpix_max_iterations, 0.001)
    for w in np.unique(win):
        sel = win == w
        pts = px[sel].astype(np.float32).reshape(-1, 1, 2)
        cv2.cornerSubPix(gray, pts, (int(w), int(w)), (-1, -1), criteria)
        out[sel] = pts.reshape(-1, 2)
    return out


def limit_threads(threads: int) -> None:
    """OpenCV's own thread pool size (1 inside worker processes, -1 = OpenCV's default)."""
    cv2.setNumThreads(threads)


# --------------------------------------------------------------------------- process-pool worker
# detect.run.detect_dataset runs these two in its pool. They live here, not in run.py, so a
# worker process imports the detection stage only (cv2), never solve/ (gtsam) or depth/ (open3d).
_WORKER: dict[str, Any] = {}


def init_detector(board: Board, config: DetectionConfig, threads: int = 1) -> None:
    """Pool initializer: keep ``board`` and ``config`` for :func:`detect_job`."""
    limit_threads(threads)  # one process per core already
    _WORKER["board"], _WORKER["config"] = board, config


def detect_job(job: tuple) -> tuple[str, str, dict]:
    """``(camera, frame, colour image path, width, height[, intrinsics])`` -> ``(camera, frame,
    MarkerDetections.to_dict())``, with the board and config of :func:`init_detector`. The
    optional ``intrinsics`` (a camera with lens distortion) bend the edge fit along the
    curved marker edges."""
    camera, frame, path, width, height = job[:5]
    intrinsics = job[5] if len(job) > 5 else None
    gray = read_color_image(Path(path), width, height, gray=True)
    det = detect_markers(gray, _WORKER["board"], _WORKER["config"], intrinsics=intrinsics)
    return camera, frame, det.to_dict()
