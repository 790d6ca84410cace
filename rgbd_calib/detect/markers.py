"""ArUco marker detection with an unbiased subpixel corner refinement; ChArUco saddle corners.

OpenCV's corner refinements sit inside the true marker corner (measured on the synthetic
renders: ~0.5 px with ``CORNER_REFINE_NONE``/``CONTOUR``, 0.2-0.45 px with ``SUBPIX``), which
shrinks every marker and biases board poses. The ``"edges"`` refinement removes that bias: it
fits a straight line to each of a marker's four *outer* edges (black border against the white
quiet zone) and intersects adjacent lines. Each line comes from a model of the blurred image
across the edge, fitted to the raw pixels of a band about one module wide along the middle of
the edge (see :func:`_fit_edge_lines`): the step from quiet zone to border, the marker's own
data cells behind the one-module border (known from its id), and a Gaussian blur whose width
is fitted. Corner regions, where blur rounds the square, are not used.

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

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.special import ndtr

from ..core.camera import CameraIntrinsics
from ..core.config import DetectionConfig
from ..model.board import Board, aruco_dictionary, cover_quads
from ..model.dataset import read_color_image

_CV_REFINE = {
    "edges": cv2.aruco.CORNER_REFINE_NONE,  # edge fit from the contour corners (fails less)
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
}


@dataclass(frozen=True, eq=False)
class MarkerDetections:
    """Board markers found in one image.

    ``ids`` ``(N,)``; ``corners_px`` ``(N,4,2)`` in ArUco order TL, TR, BR, BL (as seen from
    outside the marker's face), pixel centres at integer coordinates. ``refined`` ``(N,4)`` is
    True where the edge fit set a corner (False: OpenCV's SUBPIX corner). ``foreign_ids``
    are dictionary ids not on the board; ``duplicate_ids`` were seen more than once and dropped.
    """

    ids: np.ndarray
    corners_px: np.ndarray
    refined: np.ndarray
    foreign_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    duplicate_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    image_size: tuple[int, int] = (0, 0)  # (width, height)
    refinement: str = "edges"

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def subset(self, keep: np.ndarray) -> MarkerDetections:
        """The detections selected by a boolean mask or index array (same metadata)."""
        return MarkerDetections(
            self.ids[keep],
            self.corners_px[keep],
            self.refined[keep],
            self.foreign_ids,
            self.duplicate_ids,
            self.image_size,
            self.refinement,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "ids": self.ids.astype(int).tolist(),
            "corners_px": self.corners_px.tolist(),
            "refined": self.refined.astype(bool).tolist(),
            "foreign_ids": self.foreign_ids.astype(int).tolist(),
            "duplicate_ids": self.duplicate_ids.astype(int).tolist(),
            "image_size": list(self.image_size),
            "refinement": self.refinement,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MarkerDetections:
        ids = np.asarray(data["ids"], dtype=int).reshape(-1)
        n = ids.shape[0]
        corners = np.asarray(data["corners_px"], dtype=float).reshape(n, 4, 2)
        refined = np.asarray(data.get("refined", np.zeros((n, 4))), dtype=bool).reshape(n, 4)
        return cls(
            ids,
            corners,
            refined,
            np.asarray(data.get("foreign_ids", []), dtype=int).reshape(-1),
            np.asarray(data.get("duplicate_ids", []), dtype=int).reshape(-1),
            tuple(int(v) for v in data.get("image_size", (0, 0))),
            str(data.get("refinement", "edges")),
        )


@lru_cache(maxsize=4096)
def marker_pattern(dictionary: str, marker_id: int) -> np.ndarray:
    """A marker's cells ``(bits+2, bits+2)``, True where white, row 0 at its top edge, the
    one-cell black border included (what the edge model needs to know behind the border)."""
    d = aruco_dictionary(dictionary)
    n = int(d.markerSize) + 2
    img = cv2.aruco.generateImageMarker(d, int(marker_id), n, borderBits=1)
    out = img > 127
    out.setflags(write=False)
    return out


def _marker_parameters(config: DetectionConfig,
                       image_size: tuple[int, int]) -> cv2.aruco.DetectorParameters:
    """OpenCV's marker-finding parameters from ``config`` (ArUco and ChArUco boards alike)."""
    params = cv2.aruco.DetectorParameters()
    params.minMarkerPerimeterRate = config.min_marker_perimeter_px / max(image_size)
    params.errorCorrectionRate = config.error_correction_rate
    params.adaptiveThreshWinSizeMin = config.adaptive_thresh_win_size_min
    params.adaptiveThreshWinSizeMax = config.adaptive_thresh_win_size_max
    params.adaptiveThreshWinSizeStep = config.adaptive_thresh_win_size_step
    return params


def _detector(
    dictionary: cv2.aruco.Dictionary, config: DetectionConfig, image_size: tuple[int, int]
) -> cv2.aruco.ArucoDetector:
    params = _marker_parameters(config, image_size)
    params.cornerRefinementMethod = _CV_REFINE[config.refinement]
    params.cornerRefinementWinSize = config.subpix_win_size_px
    params.relativeCornerRefinmentWinSize = config.subpix_relative_win_size  # (sic)
    params.cornerRefinementMaxIterations = config.subpix_max_iterations
    params.cornerRefinementMinAccuracy = config.subpix_min_accuracy_px
    return cv2.aruco.ArucoDetector(dictionary, params)


def to_gray(image: np.ndarray) -> np.ndarray:
    """uint8 grey image of a BGR or grey input (what the ArUco detector runs on)."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2:
        raise ValueError(f"expected a grey (H,W) or BGR (H,W,3) image, got shape {image.shape}")
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    return image


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
    if board.charuco is not None:
        return detect_charuco(image, board, config)
    gray = to_gray(image)
    size = (int(gray.shape[1]), int(gray.shape[0]))
    dictionary = aruco_dictionary(board.dictionary)
    detector = _detector(dictionary, config, size)
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
        white = np.stack([marker_pattern(board.dictionary, int(i)) for i in ids])
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
    cells = int(aruco_dictionary(board.dictionary).markerSize) + 2
    side = np.linalg.norm(np.roll(corners_px, -1, axis=1) - corners_px, axis=-1).mean(axis=1)
    win = np.clip(
        np.ceil(config.subpix_relative_win_size * side / cells), 1, config.subpix_win_size_px
    ).astype(int)
    criteria = (
        cv2.TERM_CRITERIA_MAX_ITER | cv2.TERM_CRITERIA_EPS,
        config.subpix_max_iterations,
        config.subpix_min_accuracy_px,
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
        if s.board.charuco is not None:
            det = detect_charuco(image, s.board, config)
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
    ``"opencv"`` keeps the detector's corners. docs/accuracy.md has their bias and scatter on
    renders (painted: bias < 0.003 px, scatter 0.03 px)."""
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


PAINTED_WIN_FRACTION = 0.4  # half-window / square, markers painted out
PAINT_GROW_PX = 1.5  # a painted marker extends this far beyond its detected outline


def _paint_markers(gray: np.ndarray, marker_corners, spec) -> np.ndarray:
    """A float32 copy of ``gray`` with each detected marker (outline grown by
    :data:`PAINT_GROW_PX`) filled with the white of its square (the median of the white
    margin ring between the grown marker and the square shrunk by as much; a fixed
    percentile of the square instead left a 100-200 ppm outward scale bias on renders):
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
                config.subpix_max_iterations, 0.001)
    for w in np.unique(win):
        sel = win == w
        pts = px[sel].astype(np.float32).reshape(-1, 1, 2)
        cv2.cornerSubPix(gray, pts, (int(w), int(w)), (-1, -1), criteria)
        out[sel] = pts.reshape(-1, 2)
    return out


# --------------------------------------------------------------------------- edge refinement
_UNIT_SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])  # TL TR BR BL, y down


def _homographies(corners: np.ndarray) -> np.ndarray:
    """``(M,3,3)`` homographies mapping the unit square (marker coordinates, TL at the origin,
    y down) onto each marker's image corners ``(M,4,2)``."""
    m = corners.shape[0]
    a = np.zeros((m, 8, 8))
    x, y = _UNIT_SQUARE[:, 0], _UNIT_SQUARE[:, 1]
    u, v = corners[..., 0], corners[..., 1]
    a[:, 0::2, 0], a[:, 0::2, 1], a[:, 0::2, 2] = x, y, 1.0
    a[:, 0::2, 6], a[:, 0::2, 7] = -u * x, -u * y
    a[:, 1::2, 3], a[:, 1::2, 4], a[:, 1::2, 5] = x, y, 1.0
    a[:, 1::2, 6], a[:, 1::2, 7] = -v * x, -v * y
    b = np.stack([u, v], axis=-1).reshape(m, 8)
    h = np.linalg.solve(a + 1e-12 * np.eye(8), b[..., None])[..., 0]
    return np.concatenate([h, np.ones((m, 1))], axis=1).reshape(m, 3, 3)


def _map(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply ``(M,3,3)`` homographies to marker coordinates ``(M,...,2)``."""
    shape = pts.shape
    p = pts.reshape(shape[0], -1, 2)
    q = np.einsum("mij,mnj->mni", H[:, :, :2], p) + H[:, None, :, 2]
    return (q[..., :2] / q[..., 2:]).reshape(shape)


def _edge_layout(cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each edge k (corner k -> k+1) in marker coordinates: start point, direction, inward
    normal, and the (row, col) of the data cells behind its border, in edge order."""
    start = _UNIT_SQUARE
    along = np.roll(_UNIT_SQUARE, -1, axis=0) - _UNIT_SQUARE
    inward = np.stack([-along[:, 1], along[:, 0]], axis=-1)  # y-down: rotate along by +90 deg
    f = (np.arange(1, cells - 1) + 0.5) / cells  # centres of the data cells along the edge
    centre = start[:, None] + f[None, :, None] * along[:, None] + 1.5 / cells * inward[:, None]
    rc = np.floor(centre * cells).astype(int)  # (4, bits, 2) as (x, y) cell indices
    return start, along, inward, np.stack([rc[..., 1], rc[..., 0]], axis=-1)


def _fit_edge_lines(
    gray: np.ndarray,
    corners: np.ndarray,
    white: np.ndarray,
    config: DetectionConfig,
    intrinsics: CameraIntrinsics | None,
    blur_prior: tuple[float, float],
    compiled: bool = True,
):
    """Fit a line to each outer edge of each marker with a model of its blurred image.

    Edge ``k`` runs from corner ``k`` to corner ``k+1``. The pixels whose centres lie within a
    band about one module wide around the current edge (and away from the corners) are fitted
    by Levenberg-Marquardt with the image of the marker's border as the marker defines it: the
    outer step (quiet zone to black border) plus, behind the one-module border, the white data
    cells of this marker (``white`` ``(M,cells,cells)``, from its id), all blurred by a
    Gaussian of width ``w``. ``d`` is the signed distance of a pixel centre to the edge line
    (outwards positive), ``s`` its coordinate along the edge, ``m(s)`` the module width there:

        I = D + C * [Phi(d/w) + Phi(-(d + m)/w) * sum_j white_j (Phi((s-a_j)/w) - Phi((s-b_j)/w))]

    A pixel's value is the area average of the blurred image, a function of ``d`` alone for a
    straight step, so raw pixels need no interpolation (bilinear interpolation makes an edge
    profile depend on its sub-pixel phase: ~0.1 px errors on axis-aligned edges). The data
    cells matter: once blurred, a one-module border backed by a white cell never reaches the
    ink level, which pulls a plain step fit outwards (~0.05 px at 0.6 px blur on 12 px
    markers, ~0.15 px at 1 px blur).

    Returns unit normals ``(M,4,2)`` (out of the marker), offsets ``rho`` ``(M,4)`` with
    ``normal . x = rho`` on the line (undistorted pixels when ``intrinsics`` has distortion),
    a validity mask ``(M,4)`` and the fitted blur width per marker ``(M,)``. ``compiled``:
    the model fitted by :mod:`rgbd_calib.detect.edge_fit_jit` (numba), else by the numpy reference
    :func:`_fit_edge_models` (same corners to ~1e-9 px, ~10x slower).
    """
    # each edge's frame in the image, then the marker's layout seen through the current corners
    frame = _edge_frames(corners)
    layout = _edge_cell_layout(corners, white, frame)
    # the band fitted across each edge and the span sampled along it
    band, tau_lo, tau_hi = _edge_band(config, layout.m_at0, frame.length)
    # the band's pixels as flat per-pixel arrays, ordered by edge
    curved = intrinsics is not None and intrinsics.has_distortion
    samples, n_expected, tau_scale = _edge_samples(
        gray, frame, layout, band, tau_lo, tau_hi, config.edge_max_samples, curved, compiled
    )
    # the edge model fitted per marker
    fit = _fit_edge_models_compiled if compiled else _fit_edge_models
    local, width, weight, contrast, resid = fit(samples, band, blur_prior, config.edge_iterations)
    # which edges are usable: every test passed
    tests = _edge_tests(samples, local, width, weight, contrast, resid, band, n_expected, config)
    ok = np.logical_and.reduce(list(tests.values()))
    # the fitted edges as straight lines
    nrm, rho = _edge_lines(local, frame, tau_scale, intrinsics if curved else None)
    return nrm, rho, ok, width


@dataclass(frozen=True, eq=False)
class _EdgeFrame:
    """Each marker edge ``k`` (corner ``k`` -> ``k+1``) in image pixels (as detected, i.e.
    distorted): ``length`` ``(M,4)`` px, unit direction ``d`` and unit outward ``normal``
    ``(M,4,2)`` (``(d, normal)`` right-handed), midpoint ``mid`` ``(M,4,2)`` px."""

    length: np.ndarray
    d: np.ndarray
    normal: np.ndarray
    mid: np.ndarray


def _edge_frames(corners: np.ndarray) -> _EdgeFrame:
    """The frame of each edge of markers with image corners ``corners`` ``(M,4,2)`` (px)."""
    vec = np.roll(corners, -1, axis=1) - corners
    length = np.linalg.norm(vec, axis=-1)  # (M,4)
    d = vec / length[..., None]
    normal = np.stack([d[..., 1], -d[..., 0]], axis=-1)
    outward = np.sign(
        np.einsum("mkj,mkj->mk", corners + 0.5 * vec - corners.mean(1)[:, None], normal)
    )
    normal = normal * np.where(outward == 0, 1.0, outward)[..., None]
    d = np.stack([-normal[..., 1], normal[..., 0]], axis=-1)  # (d, normal) right-handed
    mid = corners + 0.5 * vec
    return _EdgeFrame(length, d, normal, mid)


@dataclass(frozen=True, eq=False)
class _CellLayout:
    """The marker's cells seen along each edge through the current corners, in px of the
    edge's frame: ``bound`` ``(M,4,cells-1)`` along-edge positions (from the midpoint) of the
    cell boundaries, the module width across the edge ``m_at0 + m_slope * s`` (``(M,4)``, px
    and px/px), and ``step_at`` ``(M,4,cells-1)`` the change of the data cells' whiteness at
    each boundary (see :func:`_edge_cell_layout`)."""

    bound: np.ndarray
    m_at0: np.ndarray
    m_slope: np.ndarray
    step_at: np.ndarray


def _edge_cell_layout(corners: np.ndarray, white: np.ndarray, frame: _EdgeFrame) -> _CellLayout:
    """Module width across each edge (linear along it) and the data cells' extents along it,
    from the homography of the unit square onto ``corners`` ``(M,4,2)`` (px)."""
    m = corners.shape[0]
    cells = white.shape[-1]
    d, normal, mid = frame.d, frame.normal, frame.mid
    H = _homographies(corners)
    start, along, inward, rc = _edge_layout(cells)
    fr = np.arange(1, cells) / cells  # cell boundaries along the edge (the corner modules too)
    on_inner = start[:, None] + fr[None, :, None] * along[:, None] + inward[:, None] / cells
    inner_px = _map(H, np.broadcast_to(on_inner, (m, *on_inner.shape)))  # (M,4,cells-1,2)
    rel = inner_px - mid[:, :, None, :]
    bound = np.einsum("mkcj,mkj->mkc", rel, d)  # along-edge positions of the cell boundaries
    depth = -np.einsum("mkcj,mkj->mkc", rel, normal)  # module width there
    m_slope = (depth[..., -1] - depth[..., 0]) / np.where(
        np.abs(bound[..., -1] - bound[..., 0]) > 1e-9, bound[..., -1] - bound[..., 0], 1.0
    )
    m_at0 = depth[..., 0] - m_slope * bound[..., 0]  # module width at the edge's midpoint
    # The white data cells behind the border, sum_j white_j (Phi((s-a_j)/w) - Phi((s-b_j)/w))
    # with [a_j, b_j] cell j's extent, telescope over the shared cell boundaries c_i:
    # sum_i step_i Phi((s-c_i)/w), step_i = q_i - q_(i-1) with q_j = +-white_j (the sign of
    # c_(j+1) - c_j: a cell's extent is (min, max) of its two boundaries) and q = 0 outside.
    cell_white = white[:, rc[..., 0], rc[..., 1]].astype(float)  # (M,4,bits)
    q = cell_white * np.where(bound[..., 1:] >= bound[..., :-1], 1.0, -1.0)
    pad = np.zeros((m, 4, 1))
    step_at = np.concatenate([q, pad], axis=-1) - np.concatenate([pad, q], axis=-1)  # (M,4,B)
    return _CellLayout(bound, m_at0, m_slope, step_at)


def _edge_band(config: DetectionConfig, m_at0: np.ndarray, length: np.ndarray):
    """Per edge ``(M,4)``: the band half-width across it (px) and the sampled span along it,
    ``tau_lo .. tau_hi`` (px from the midpoint), kept away from the corners."""
    module = np.clip(m_at0, 0.1, None)
    band = np.clip(config.edge_band_modules * module, *config.edge_band_px)
    margin = np.minimum(config.edge_corner_margin_px / length, 0.4)
    tau_lo = (np.maximum(config.edge_span[0], margin) - 0.5) * length  # span about the midpoint
    tau_hi = (np.minimum(config.edge_span[1], 1.0 - margin) - 0.5) * length
    return band, tau_lo, tau_hi


@dataclass(frozen=True, eq=False)
class _BandColumns:
    """How each edge's band is walked, per edge ``(M,4)``: its major image axis (0: x,
    1: y), the first pixel column ``c_lo`` along it, the column ``stride`` and the number of
    columns used, the band's extent along the minor axis ``half_minor`` (px) and the edge's
    ``slope`` (minor px per major px); ``r_max`` pixel rows per column cover every band."""

    axis: np.ndarray
    c_lo: np.ndarray
    stride: np.ndarray
    n_used: np.ndarray
    half_minor: np.ndarray
    slope: np.ndarray
    r_max: int


def _band_columns(
    frame: _EdgeFrame, band: np.ndarray, tau_lo: np.ndarray, tau_hi: np.ndarray, max_samples: int
) -> _BandColumns:
    """The columns of each edge's band (at most ``max_samples`` per edge)."""
    d, mid = frame.d, frame.mid
    axis = (np.abs(d[..., 1]) > np.abs(d[..., 0])).astype(int)  # 0: x-major, 1: y-major
    other = 1 - axis
    d_major = np.take_along_axis(d, axis[..., None], -1)[..., 0]
    d_minor = np.take_along_axis(d, other[..., None], -1)[..., 0]
    ends = np.stack([mid + tau_lo[..., None] * d, mid + tau_hi[..., None] * d], axis=-2)
    major_ends = np.take_along_axis(ends, np.repeat(axis[..., None, None], 2, -2), -1)[..., 0]
    c_lo = np.ceil(major_ends.min(-1))
    n_cols = np.maximum(np.floor(major_ends.max(-1)) - c_lo + 1, 0).astype(int)
    stride = np.maximum(np.ceil(n_cols / max_samples), 1).astype(int)
    n_used = np.ceil(n_cols / stride).astype(int)
    half_minor = band / np.maximum(np.abs(d_major), 1e-6)  # band extent along the minor axis
    r_max = int(np.ceil(2 * half_minor.max())) + 2
    slope = d_minor / np.where(d_major == 0, 1e-6, d_major)
    return _BandColumns(axis, c_lo, stride, n_used, half_minor, slope, r_max)


def _band_pixels(
    image_shape: tuple[int, int],
    frame: _EdgeFrame,
    band: np.ndarray,
    tau_lo: np.ndarray,
    tau_hi: np.ndarray,
    max_samples: int,
):
    """Candidate pixels of each edge's band, column by column along the edge's dominant image
    axis (at most ``max_samples`` columns): integer pixel centres ``x``, ``y`` ``(M,4,S,R)``,
    their distance ``d0`` across the edge (px, outwards positive) and ``tau`` along it (px
    from the midpoint), the mask ``use`` of those in the band and the image, and
    ``n_expected`` ``(M,4)`` the band's pixel count ignoring the image border."""
    d, normal, mid = frame.d, frame.normal, frame.mid
    m = d.shape[0]
    cols = _band_columns(frame, band, tau_lo, tau_hi, max_samples)
    axis, c_lo, stride, n_used = cols.axis, cols.c_lo, cols.stride, cols.n_used
    half_minor, r_max = cols.half_minor, cols.r_max
    s_max = max(int(n_used.max()), 1)
    j = np.arange(s_max)
    col = c_lo[..., None] + j * stride[..., None]  # (M,4,S)
    mid_major = np.take_along_axis(mid, axis[..., None], -1)[..., 0]
    mid_minor = np.take_along_axis(mid, 1 - axis[..., None], -1)[..., 0]
    line_minor = mid_minor[..., None] + (col - mid_major[..., None]) * cols.slope[..., None]
    row = np.floor(line_minor - half_minor[..., None])[..., None] + np.arange(r_max)
    col = np.broadcast_to(col[..., None], row.shape)  # (M,4,S,R)
    x = np.where(axis[..., None, None] == 0, col, row)
    y = np.where(axis[..., None, None] == 0, row, col)
    rel_x = x - mid[..., 0, None, None]
    rel_y = y - mid[..., 1, None, None]
    d0 = rel_x * normal[..., 0, None, None] + rel_y * normal[..., 1, None, None]
    tau = rel_x * d[..., 0, None, None] + rel_y * d[..., 1, None, None]
    h_img, w_img = image_shape
    inside = (x >= 0) & (y >= 0) & (x <= w_img - 1) & (y <= h_img - 1)
    use = (
        (j < n_used[..., None])[..., None]
        & (np.abs(d0) <= band[..., None, None])
        & (tau >= tau_lo[..., None, None])
        & (tau <= tau_hi[..., None, None])
    )
    n_expected = use.reshape(m, 4, -1).sum(-1)
    use &= inside
    return x, y, d0, tau, use, n_expected


@dataclass(frozen=True, eq=False)
class _EdgeSamples:
    """The band pixels of all edges as flat arrays, ordered by edge (``m*4 + k``), hence by
    marker, and the (pixel, cell boundary) pairs where the data cells change colour, ordered by
    pixel. Per pixel: ``d0`` (px across the edge, outwards positive, from the current edge),
    ``tn`` (along-edge position normalised to [-1, 1]) and ``tn2 = tn**2``, grey ``values``,
    the module width ``m_pix`` (px). Per pair: its pixel ``pair_pix``, ``pair_s`` = s - c_i
    (px) and ``pair_step`` = step_i. ``curved``: lens distortion (the edges get a curvature
    term). Per-edge/per-marker values spread to the pixels by ``np.repeat`` with the counts;
    sums per edge or marker are sums of contiguous segments (``edge_sum``, ``per_marker``)."""

    m: int
    curved: bool
    edge_of: np.ndarray
    d0: np.ndarray
    tn: np.ndarray
    tn2: np.ndarray
    values: np.ndarray
    m_pix: np.ndarray
    pair_pix: np.ndarray
    pair_s: np.ndarray
    pair_step: np.ndarray
    edge_count: np.ndarray
    marker_count: np.ndarray
    pair_count: np.ndarray
    edge_sum: Any
    per_marker: Any

    def at_pixels(self, per_marker_value: np.ndarray) -> np.ndarray:
        return np.repeat(per_marker_value, self.marker_count)

    def per_edge(self, v: np.ndarray) -> np.ndarray:
        return self.edge_sum(v).reshape(self.m, 4)


def _edge_samples(
    gray: np.ndarray,
    frame: _EdgeFrame,
    layout: _CellLayout,
    band: np.ndarray,
    tau_lo: np.ndarray,
    tau_hi: np.ndarray,
    max_samples: int,
    curved: bool,
    compiled: bool = True,
):
    """The band's pixels of every edge (:func:`_band_pixels`) kept as :class:`_EdgeSamples`;
    also ``n_expected`` ``(M,4)`` and the along-edge scale ``tau_scale`` ``(M,4)`` (px) of
    ``tn``. ``compiled``: the pixels and pairs from
    :func:`rgbd_calib.detect.edge_fit_jit.edge_band_samples` (the same arithmetic as the numpy
    code below, without its padded ``(M,4,S,R)`` grids)."""
    m = frame.d.shape[0]
    n_edges = 4 * m
    tau_scale = np.maximum(0.5 * (tau_hi - tau_lo), 1.0)
    step_at = layout.step_at
    n_b = step_at.shape[-1]
    if compiled:
        from .edge_fit_jit import edge_band_samples

        cols = _band_columns(frame, band, tau_lo, tau_hi, max_samples)
        flat = [
            np.ascontiguousarray(a.reshape(n_edges, *a.shape[2:]), dtype=np.float64)
            for a in (
                cols.c_lo, cols.half_minor, cols.slope, frame.mid, frame.d, frame.normal,
                band, tau_lo, tau_hi, layout.m_at0, layout.m_slope, tau_scale, layout.bound,
                step_at,
            )
        ]  # fmt: skip
        ints = [np.ascontiguousarray(a.reshape(-1), dtype=np.int64) for a in
                (cols.axis, cols.stride, cols.n_used)]  # fmt: skip
        (edge_of, px_x, px_y, d0, tau, m_pix, tn, n_exp, pair_pix, pair_s, pair_step) = (
            edge_band_samples(
                ints[0], flat[0], ints[1], ints[2], *flat[1:9], cols.r_max,
                gray.shape[0], gray.shape[1], *flat[9:],
            )
        )  # fmt: skip
        n_expected = n_exp.reshape(m, 4)
        marker_of = edge_of // 4
    else:
        x, y, d0, tau, use, n_expected = _band_pixels(
            gray.shape, frame, band, tau_lo, tau_hi, max_samples
        )
        # keep only the band's pixels, as flat arrays with their edge (m*4 + k) and marker
        sel = np.nonzero(use.reshape(m * 4, -1))
        edge_of = sel[0]
        marker_of = edge_of // 4
        d0, tau = d0.reshape(m * 4, -1)[sel], tau.reshape(m * 4, -1)[sel]
        px_x = x.reshape(m * 4, -1)[sel].astype(np.intp)
        px_y = y.reshape(m * 4, -1)[sel].astype(np.intp)
        m_at0, m_slope = layout.m_at0, layout.m_slope
        m_pix = np.clip(m_at0.reshape(-1)[edge_of] + m_slope.reshape(-1)[edge_of] * tau, 0.1, None)
        tn = tau / tau_scale.reshape(-1)[edge_of]  # normalised along-edge coordinate in [-1, 1]
        # (pixel, boundary) pairs where the data cells change colour (step_i != 0): s - c_i
        # and step_i, ordered by pixel
        pair = np.flatnonzero(step_at.reshape(n_edges, n_b)[edge_of] != 0)
        pair_pix = pair // n_b
        at_boundary = edge_of[pair_pix] * n_b + pair % n_b
        pair_s = tau[pair_pix] - layout.bound.reshape(-1)[at_boundary]
        pair_step = step_at.reshape(-1)[at_boundary]
    values = gray[px_y, px_x].astype(np.float64)
    # the pixels are ordered by edge (hence by marker), and the pairs by pixel: per-edge or
    # per-marker values spread to the pixels by np.repeat, sums per edge or marker are sums of
    # contiguous segments (np.add.reduceat); both much faster than fancy indexing/np.bincount
    edge_count = np.bincount(edge_of, minlength=n_edges)
    samples = _EdgeSamples(
        m=m,
        curved=curved,
        edge_of=edge_of,
        d0=d0,
        tn=tn,
        tn2=tn**2,
        values=values,
        m_pix=m_pix,
        pair_pix=pair_pix,
        pair_s=pair_s,
        pair_step=pair_step,
        edge_count=edge_count,
        marker_count=edge_count.reshape(m, 4).sum(axis=1),
        pair_count=np.bincount(marker_of[pair_pix], minlength=m),
        edge_sum=_segment_summer(edge_of, n_edges),
        per_marker=_segment_summer(marker_of, m),
    )
    return samples, n_expected, tau_scale


def _edge_model(s: _EdgeSamples, local: np.ndarray, width: np.ndarray):
    """The basis (the blurred marker image, 0 on the ink and 1 on the quiet zone) at each
    pixel and its derivatives by d and by w (per px); independent of the pixel weights.
    ``local`` ``(M,4,3)``: rho (px), theta, kappa (px per unit of ``tn``) per edge; ``width``
    ``(M,)`` the blur width (px).

    Only the cell boundaries within _FAR blur widths of a pixel need the Gaussian CDF:
    further ones contribute exactly step_i (in front of the pixel) or 0 (behind it) in
    double precision, and nothing to the derivative."""
    n_pix = s.d0.shape[0]
    rho, theta, kappa = (np.repeat(v, s.edge_count) for v in local.reshape(4 * s.m, 3).T)
    dist = s.d0 - rho + theta * s.tn
    if s.curved:  # kappa stays 0 otherwise
        dist += kappa * s.tn2
    wd = s.at_pixels(width)
    z = dist / wd
    e = -(dist + s.m_pix) / wd
    g = s.pair_s / np.repeat(width, s.pair_count)
    near = np.flatnonzero(np.abs(g) < _FAR)
    gn, step_n = g[near], s.pair_step[near]
    phi = np.where(g > 0.0, s.pair_step, 0.0)
    phi[near] = step_n * ndtr(gn)
    behind = np.bincount(s.pair_pix, phi, minlength=n_pix)  # white data cells behind, at s
    behind_w = np.bincount(  # w * d behind / d w
        s.pair_pix[near], -step_n * _pdf(gn) * gn, minlength=n_pix
    )
    phi_e = np.zeros_like(e)  # 0 where the data cells are > _FAR blur widths behind
    live = np.flatnonzero(e > -_FAR)
    phi_e[live] = ndtr(e[live])
    basis = ndtr(z) + phi_e * behind
    pz, pe = _pdf(z), _pdf(e)
    d_dist = (pz - pe * behind) / wd  # d basis / d dist
    d_width = (-pz * z - pe * e * behind + phi_e * behind_w) / wd
    return basis, d_dist, d_width


def _edge_solve(
    s: _EdgeSamples,
    basis: np.ndarray,
    width: np.ndarray,
    wt: np.ndarray,
    blur_prior: tuple[float, float],
):
    """Closed-form weighted least squares of values = D + C * basis, per marker: the
    cost (with the blur prior on ``width``, px), the contrast C (grey levels) and the
    residuals (grey levels, per pixel)."""
    w0, w_sigma = blur_prior
    per_marker, values = s.per_marker, s.values
    sw, s1, s2 = per_marker(wt), per_marker(wt * basis), per_marker(wt * basis**2)
    sv, svb = per_marker(wt * values), per_marker(wt * values * basis)
    det = sw * s2 - s1 * s1
    contrast = (sw * svb - s1 * sv) / np.where(np.abs(det) > 1e-12, det, 1e-12)
    dark = (sv - contrast * s1) / np.maximum(sw, 1e-12)
    resid = values - (s.at_pixels(dark) + s.at_pixels(contrast) * basis)
    cost = per_marker(wt * resid**2) + ((width - w0) / w_sigma) ** 2
    return cost, contrast, resid


def _lm_step(
    s: _EdgeSamples,
    model: tuple[np.ndarray, np.ndarray, np.ndarray],
    contrast: np.ndarray,
    resid: np.ndarray,
    weight: np.ndarray,
    width: np.ndarray,
    lam: np.ndarray,
    blur_prior: tuple[float, float],
) -> np.ndarray:
    """One damped Gauss-Newton step ``(M, 4*n_loc+3)`` per marker: the ``n_loc`` edge
    parameters of each edge (rho, theta[, kappa]), then D, C and the blur width (px)."""
    basis, d_dist, d_width = model
    w0, w_sigma = blur_prior
    m, tn, tn2 = s.m, s.tn, s.tn2
    n_loc = 3 if s.curved else 2
    n_big = 4 * n_loc + 3
    upper, scatter = _normal_equation_layout(n_loc)
    c_pix = s.at_pixels(contrast)
    g = c_pix * d_dist
    # the Jacobian's columns for the pixel's own edge, then per-edge sums of the products
    # of the columns (upper triangle) and of the columns with the residuals, placed into
    # each marker's system by a constant 0/1 matrix (row by row: no (n_par^2, P) temporary)
    cols = [-g, g * tn, g * tn2][:n_loc] + [np.ones_like(g), basis, c_pix * d_width]
    wcols = [weight * c for c in cols]
    sums = np.stack(
        [s.edge_sum(wcols[a] * cols[b]) for a, b in zip(*upper)]
        + [s.edge_sum(wc * resid) for wc in wcols]
    )
    normal_eq = sums.reshape(-1, m, 4).transpose(1, 2, 0).reshape(m, -1) @ scatter
    jtj = normal_eq[:, : n_big * n_big].reshape(m, n_big, n_big)
    jtr = normal_eq[:, n_big * n_big :]
    jtj[:, -1, -1] += 1.0 / w_sigma**2  # Gaussian prior on the blur width
    jtr[:, -1] += (w0 - width) / w_sigma**2
    diag = np.einsum("mii->mi", jtj)
    damped = jtj + (lam[:, None] * diag + 1e-9)[..., None] * np.eye(n_big)
    return np.nan_to_num(np.linalg.solve(damped, jtr[..., None])[..., 0])


def _fit_edge_models(
    s: _EdgeSamples, band: np.ndarray, blur_prior: tuple[float, float], iterations: int
):
    """Levenberg-Marquardt per marker: offset rho_k (px), angle theta_k (curvature kappa_k
    with lens distortion) per edge, d = d0 - rho + theta*tn + kappa*tn^2, and a blur width w
    (px) shared by the four edges (an axis-aligned edge samples the step at a single sub-pixel
    phase and cannot tell its position from the blur on its own). D and C enter linearly and
    are solved in closed form at every evaluation (variable projection): no initial guess
    needed. Returns ``local`` ``(M,4,3)``, ``width`` ``(M,)``, the pixel weights (0/1), the
    contrast ``(M,)`` and the residuals per pixel (grey levels)."""
    m, n_loc = s.m, 3 if s.curved else 2
    w0 = blur_prior[0]
    local = np.zeros((m, 4, 3))  # rho, theta, kappa per edge
    width = np.full(m, w0)
    lam = np.full(m, 1e-3)
    weight = np.ones_like(s.values)
    # the model at the current parameters is kept: after a rejected step it is unchanged, after
    # an accepted one it is the trial's (one model evaluation per iteration)
    basis, d_dist, d_width = _edge_model(s, local, width)
    cost, contrast, resid = _edge_solve(s, basis, width, weight, blur_prior)
    for it in range(iterations):
        if it in (3, 6):  # reject outlier pixels (occlusion, stray texture) from then on
            limit = np.maximum(
                4.0 * 1.4826 * _edge_medians(np.abs(resid), weight > 0, s.edge_of, 4 * m),
                0.02 * np.abs(contrast).repeat(4) + 1.0,
            )
            weight = (np.abs(resid) <= np.repeat(limit, s.edge_count)).astype(float)
            cost, contrast, resid = _edge_solve(s, basis, width, weight, blur_prior)
        step = _lm_step(
            s, (basis, d_dist, d_width), contrast, resid, weight, width, lam, blur_prior
        )
        # the trial parameters, kept per marker where they lower the cost
        trial = local.copy()
        trial[..., :n_loc] += step[:, : 4 * n_loc].reshape(m, 4, n_loc)
        trial[..., 0] = np.clip(trial[..., 0], -band, band)
        trial_w = np.clip(width + step[:, -1], 0.15, 3.0)
        t_basis, t_d_dist, t_d_width = _edge_model(s, trial, trial_w)
        t_cost, t_contrast, t_resid = _edge_solve(s, t_basis, trial_w, weight, blur_prior)
        better = t_cost < cost
        local = np.where(better[:, None, None], trial, local)
        width = np.where(better, trial_w, width)
        lam = np.where(better, lam / 3.0, lam * 4.0)
        cost = np.where(better, t_cost, cost)
        contrast = np.where(better, t_contrast, contrast)
        on = s.at_pixels(better)
        basis = np.where(on, t_basis, basis)
        d_dist = np.where(on, t_d_dist, d_dist)
        d_width = np.where(on, t_d_width, d_width)
        resid = np.where(on, t_resid, resid)
    return local, width, weight, contrast, resid


#: the compiled fit stops a marker once its step is below this (px): results stay within
#: ~1e-9 px of running every marker for ``edge_iterations`` like the numpy reference
EDGE_STEP_TOL_PX = 1e-9


def _fit_edge_models_compiled(
    s: _EdgeSamples, band: np.ndarray, blur_prior: tuple[float, float], iterations: int
):
    """:func:`_fit_edge_models` by :func:`rgbd_calib.detect.edge_fit_jit.fit_edge_models`, one
    marker at a time with its own iteration count (stops when its step is below
    :data:`EDGE_STEP_TOL_PX`, at most ``iterations``). numba is imported here, on the first
    edge fit, so that importing the detection stage stays cheap."""
    from .edge_fit_jit import fit_edge_models

    n_pix = s.d0.shape[0]
    edge_ptr = np.concatenate([[0], np.cumsum(s.edge_count)]).astype(np.int64)
    pairs_per_pixel = np.bincount(s.pair_pix, minlength=n_pix)
    pair_ptr = np.concatenate([[0], np.cumsum(pairs_per_pixel)]).astype(np.int64)
    f64 = [np.ascontiguousarray(a, dtype=np.float64) for a in (s.d0, s.tn, s.tn2, s.values)]
    local, width, weight, contrast, resid, _ = fit_edge_models(
        edge_ptr,
        *f64,
        np.ascontiguousarray(s.m_pix, dtype=np.float64),
        pair_ptr,
        np.ascontiguousarray(s.pair_s, dtype=np.float64),
        np.ascontiguousarray(s.pair_step, dtype=np.float64),
        np.ascontiguousarray(band, dtype=np.float64),
        float(blur_prior[0]),
        float(blur_prior[1]),
        int(iterations),
        bool(s.curved),
        EDGE_STEP_TOL_PX,
    )
    return local, width, weight, contrast, resid


def _edge_tests(
    s: _EdgeSamples,
    local: np.ndarray,
    width: np.ndarray,
    weight: np.ndarray,
    contrast: np.ndarray,
    resid: np.ndarray,
    band: np.ndarray,
    n_expected: np.ndarray,
    config: DetectionConfig,
) -> dict[str, np.ndarray]:
    """The tests an edge's fit must pass, by name, ``(M,4)`` True where passed: enough
    contrast (grey levels) and inlier pixels, its offset inside the band (px), a blur width
    (px) off the fit's floor and cap, and a small RMS residual relative to the contrast (the
    bound of :func:`edge_residual_bound`)."""
    rho = local[..., 0]
    n_in = s.per_edge(weight)
    rms = np.sqrt(s.per_edge(weight * resid**2) / np.maximum(n_in, 1))
    c = contrast[:, None]
    w = np.broadcast_to(width[:, None], rho.shape)
    tests = {
        "contrast": np.broadcast_to(c >= config.min_edge_contrast, rho.shape),
        "inliers": (n_in >= 6) & (n_in >= config.min_edge_inliers * n_expected),
        "offset": np.abs(rho) < band,
        "blur_floor": w > 0.15,
        "blur_cap": w < 3.0,
    }
    relative = rms / np.maximum(c, 1e-9)
    fits = np.logical_and.reduce(list(tests.values()))
    tests["residual"] = relative <= edge_residual_bound(relative[fits], config)
    return tests


def edge_residual_bound(relative: np.ndarray, config: DetectionConfig) -> float:
    """The largest RMS residual / contrast an edge of this image may have: the fixed
    ``max_edge_residual``, or, where the image's edges all fit the model worse (a camera's
    sharpening and compression: median 0.10 measured on Caliscope's webcam video, 0.01-0.02
    on the synthetic renders), ``edge_residual_factor`` times the median of its edges
    ``relative`` (those passing the other tests), at most ``max_edge_residual_cap``. An
    occluded or wrong edge still stands out against the image's own median."""
    if relative.size == 0 or config.edge_residual_factor is None:
        return config.max_edge_residual
    adaptive = config.edge_residual_factor * float(np.median(relative))
    return float(np.clip(adaptive, config.max_edge_residual,
                         max(config.max_edge_residual_cap, config.max_edge_residual)))


def _edge_lines(
    local: np.ndarray,
    frame: _EdgeFrame,
    tau_scale: np.ndarray,
    intrinsics: CameraIntrinsics | None,
):
    """The fitted edges as points on them, then straight lines ``normal . x = rho``: unit
    normals ``(M,4,2)`` (out of the marker) and ``rho`` ``(M,4)`` (px), in undistorted pixels
    when ``intrinsics`` is given (only with lens distortion), else image pixels."""
    rho, theta, kappa = np.moveaxis(local, -1, 0)
    normal = frame.normal
    tau_scale = tau_scale[..., None]
    tq = np.array([-1.0, 0.0, 1.0])
    off = rho[..., None] - theta[..., None] * tq - kappa[..., None] * tq**2  # d0 on the edge
    pts = (
        frame.mid[..., None, :]
        + (tq[None, None, :, None] * tau_scale[..., None]) * frame.d[..., None, :]
        + off[..., None] * normal[..., None, :]
    )  # (M,4,3,2)
    if intrinsics is not None:
        pts = intrinsics.undistort_pixels(pts)
    centre = pts.mean(axis=-2)
    direction = pts[..., 2, :] - pts[..., 0, :]
    direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-12)
    nrm = np.stack([direction[..., 1], -direction[..., 0]], axis=-1)
    nrm *= np.where(np.einsum("mkj,mkj->mk", nrm, normal) < 0, -1.0, 1.0)[..., None]
    return nrm, np.einsum("mkj,mkj->mk", centre, nrm)


def _segment_summer(group: np.ndarray, n: int):
    """``f(v)`` = ``np.bincount(group, v, minlength=n)`` for a sorted ``group``."""
    counts = np.bincount(group, minlength=n)
    nonempty = counts > 0
    starts = (np.cumsum(counts) - counts)[nonempty]

    def total(v: np.ndarray) -> np.ndarray:
        out = np.zeros(n)
        if starts.size:
            out[nonempty] = np.add.reduceat(v, starts)
        return out

    return total


def _edge_medians(v: np.ndarray, use: np.ndarray, edge_of: np.ndarray, n_edges: int):
    """Per edge, the upper median of ``v[use]`` (element ``count // 2`` of the edge's sorted
    values; 0 without any) for pixels sorted by ``edge_of``."""
    v, edge = v[use], edge_of[use]
    counts = np.bincount(edge, minlength=n_edges)
    out = np.zeros(n_edges)
    if v.size == 0:
        return out
    starts = np.cumsum(counts) - counts
    table = np.full((n_edges, int(counts.max())), np.inf)
    table[edge, np.arange(v.size) - starts[edge]] = v
    table.sort(axis=1)
    has = counts > 0
    out[has] = table[has, counts[has] // 2]
    return out


@lru_cache(maxsize=4)
def _normal_equation_layout(n_loc: int) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """Where the per-edge sums go in a marker's normal equations.

    A marker's parameters are ``n_loc`` per edge (edge ``k``: ``k*n_loc ...``) then the three
    shared ones (D, C, w); a pixel's Jacobian row is non-zero only in its edge's ``n_loc`` and
    the shared columns (``n_par = n_loc + 3``). Returns the upper-triangle index pairs of the
    ``n_par`` columns and a 0/1 matrix mapping the per-edge sums, ordered (edge, products of
    column pairs then column x residual), to ``J^T J`` (flat) followed by ``J^T r``."""
    n_par, n_big = n_loc + 3, 4 * n_loc + 3
    upper = np.triu_indices(n_par)
    n_pairs = upper[0].size
    scatter = np.zeros((4, n_pairs + n_par, n_big * n_big + n_big))
    for k in range(4):
        index = [k * n_loc + i for i in range(n_loc)] + [4 * n_loc + i for i in range(3)]
        for p, (a, b) in enumerate(zip(*upper)):
            scatter[k, p, index[a] * n_big + index[b]] = 1.0
            scatter[k, p, index[b] * n_big + index[a]] = 1.0
        for a in range(n_par):
            scatter[k, n_pairs + a, n_big * n_big + index[a]] = 1.0
    scatter = scatter.reshape(4 * (n_pairs + n_par), -1)
    scatter.setflags(write=False)
    upper[0].setflags(write=False)
    upper[1].setflags(write=False)
    return upper, scatter


_FAR = 8.5  # |x| beyond which ndtr(x) is 0 or 1 to double precision (ndtr(-8.5) ~ 1e-17)


def _pdf(x: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * x * x) * (1.0 / np.sqrt(2.0 * np.pi))


def refine_corners_edges(
    gray: np.ndarray,
    corners_px: np.ndarray,
    white: np.ndarray,
    config: DetectionConfig | None = None,
    intrinsics: CameraIntrinsics | None = None,
    compiled: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Corners as intersections of lines fitted to the markers' outer edges.

    ``gray`` is a grey image (any real dtype; float keeps the BGR -> grey conversion
    unrounded), ``corners_px`` ``(N,4,2)`` the initial corners (ArUco
    order), ``white`` ``(N,cells,cells)`` each marker's cells (True = white, border included;
    see :func:`marker_pattern`). Returns the corners and a ``(N,4)`` mask of the corners the
    edge fit set; the others keep their input position (marker too small, edge off the image
    or occluded, poor fit, grazing intersection, or a jump beyond ``max_corner_shift_px``).
    ``compiled=False`` runs the numpy reference of the edge model's fit (tests compare them).
    """
    config = config or DetectionConfig()
    gray = np.asarray(gray)  # any real dtype: the edge fit converts the pixels it reads
    if gray.dtype.kind not in "uif":
        gray = gray.astype(np.float64)
    initial = np.asarray(corners_px, dtype=float)
    white = np.asarray(white, dtype=bool)
    n = initial.shape[0]
    out = initial.copy()
    refined = np.zeros((n, 4), dtype=bool)
    if n == 0:
        return out, refined
    side = np.linalg.norm(np.roll(initial, -1, axis=1) - initial, axis=-1)
    sel = np.nonzero(side.min(axis=1) >= config.min_edge_length_px)[0]
    if sel.size == 0:
        return out, refined
    current = initial[sel].copy()
    ok_corner = np.zeros((sel.size, 4), dtype=bool)
    blur_prior = config.blur_prior_px
    for _ in range(config.edge_passes):
        nrm, rho, ok_line, width = _fit_edge_lines(
            gray, current, white[sel], config, intrinsics, blur_prior, compiled
        )
        good = ok_line.all(axis=1)
        if np.any(good):  # later passes: the image's typical blur, a tighter prior
            blur_prior = (float(np.median(width[good])), 0.5 * blur_prior[1])
        # corner k lies on edge k-1 (from corner k-1) and edge k (to corner k+1)
        n_prev, r_prev, ok_prev = (
            np.roll(nrm, 1, axis=1),
            np.roll(rho, 1, axis=1),
            np.roll(ok_line, 1, axis=1),
        )
        det = n_prev[..., 0] * nrm[..., 1] - n_prev[..., 1] * nrm[..., 0]
        well_posed = np.abs(det) > np.sin(np.radians(15.0))
        safe = np.where(well_posed, det, 1.0)
        x = (r_prev * nrm[..., 1] - rho * n_prev[..., 1]) / safe
        y = (n_prev[..., 0] * rho - nrm[..., 0] * r_prev) / safe
        corner = np.stack([x, y], axis=-1)
        if intrinsics is not None and intrinsics.has_distortion:
            corner = intrinsics.distort_pixels(corner)
        shift = np.linalg.norm(corner - initial[sel], axis=-1)
        ok_corner = (
            ok_line
            & ok_prev
            & well_posed
            & np.isfinite(shift)
            & (shift <= config.max_corner_shift_px)
        )
        current = np.where(ok_corner[..., None], corner, initial[sel])
    out[sel] = current
    refined[sel] = ok_corner
    return out, refined


def limit_threads(threads: int) -> None:
    """OpenCV's own thread pool size (1 inside worker processes, -1 = OpenCV's default)."""
    cv2.setNumThreads(threads)


# --------------------------------------------------------------------------- process-pool worker
# calibrate.detect_dataset runs these two in its pool. They live here, not in calibrate.py, so a
# worker process imports the detection stage only (cv2), never graph (gtsam) or depth (open3d).
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
