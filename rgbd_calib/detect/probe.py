"""Which target is in the images, when it is not the board given (a wrong or forgotten
``--board``)? OpenCV's predefined marker families are tried on a few images, and the markers
of the family that finds most are checked for a ChArUco layout, so the error can say which
board file to pass instead of blaming the lens or the number of views.

Families nest (``DICT_4X4_50`` is the first 50 markers of ``DICT_4X4_1000``), so each is
probed with its largest member and the smallest dictionary holding the ids found is named.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..model.board import aruco_dictionary
from .markers import to_gray

# (largest dictionary of the family, its members' sizes and name stem, the markers' border
# in cells: 2 for Kalibr's AprilGrid tags)
FAMILIES = (
    ("DICT_4X4_1000", "DICT_4X4_{}", (50, 100, 250, 1000), 1),
    ("DICT_5X5_1000", "DICT_5X5_{}", (50, 100, 250, 1000), 1),
    ("DICT_6X6_1000", "DICT_6X6_{}", (50, 100, 250, 1000), 1),
    ("DICT_7X7_1000", "DICT_7X7_{}", (50, 100, 250, 1000), 1),
    ("DICT_ARUCO_ORIGINAL", "DICT_ARUCO_ORIGINAL", (), 1),
    ("DICT_APRILTAG_36h11", "DICT_APRILTAG_36h11", (), 1),
    ("DICT_APRILTAG_36h11", "DICT_APRILTAG_36h11", (), 2),  # Kalibr's AprilGrid
    ("DICT_APRILTAG_25h9", "DICT_APRILTAG_25h9", (), 1),
    ("DICT_APRILTAG_16h5", "DICT_APRILTAG_16h5", (), 1),
)
DIAGONAL_RATIO = 0.6  # nearest neighbour offset min/max in the marker's frame: diagonal


@dataclass(frozen=True)
class TargetGuess:
    """The marker family that found most markers: the smallest ``dictionary`` holding them,
    how many markers in how many images, their id range, whether they are printed
    ``inverted`` (white on black) and whether they sit as a ChArUco board's do (each marker's
    nearest neighbours diagonal to it, in a chessboard's white squares)."""

    dictionary: str
    markers: int
    images: int
    id_min: int
    id_max: int
    charuco: bool
    inverted: bool
    border_bits: int = 1  # 2: Kalibr's AprilGrid tags

    def describe(self) -> str:
        if self.border_bits == 2:
            return (f"{self.markers} tags of a Kalibr AprilGrid (tag36h11 with a 2-cell border, "
                    f"ids {self.id_min}-{self.id_max}) in {self.images} images")
        kind = "a ChArUco board" if self.charuco else "an ArUco marker board"
        ink = " printed inverted (white on black)" if self.inverted else ""
        return (f"{self.markers} markers of {self.dictionary}{ink} (ids {self.id_min}-"
                f"{self.id_max}) in {self.images} images, laid out as {kind}")

    def family(self) -> str:
        return dictionary_family(self.dictionary)


def dictionary_family(name: str) -> str:
    """The family of an OpenCV dictionary name: ``DICT_4X4_100`` -> ``DICT_4X4`` (its
    members share their first markers); a dictionary of one size is its own family."""
    return name.rsplit("_", 1)[0] if name[5:6].isdigit() else name


def _smallest(stem: str, sizes: tuple[int, ...], id_max: int) -> str:
    for n in sizes:
        if id_max < n:
            return stem.format(n)
    return stem.format(sizes[-1]) if sizes else stem


def _diagonal_share(corners: np.ndarray) -> float:
    """Share of markers whose nearest neighbour is diagonal in the marker's own frame (its
    edges TL->TR and TL->BL as axes, so perspective does not matter locally)."""
    centres = corners.mean(axis=1)
    votes = []
    for k, c in enumerate(corners):
        d = np.linalg.norm(centres - centres[k], axis=1)
        d[k] = np.inf
        j = int(np.argmin(d))
        axes = np.column_stack([c[1] - c[0], c[3] - c[0]])
        if abs(np.linalg.det(axes)) < 1e-6:
            continue
        dx, dy = np.abs(np.linalg.solve(axes, centres[j] - centres[k]))
        votes.append(min(dx, dy) / max(dx, dy, 1e-9) > DIAGONAL_RATIO)
    return float(np.mean(votes)) if votes else 0.0


def _detect(grays: list[np.ndarray], dictionary: str, inverted: bool, border_bits: int = 1):
    params = cv2.aruco.DetectorParameters()
    params.detectInvertedMarker = inverted
    params.markerBorderBits = border_bits
    detector = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), params)
    ids_all, corners_all = [], []
    for g in grays:
        corners, ids, _ = detector.detectMarkers(g)
        if ids is not None and len(ids):
            ids_all.append(np.asarray(ids, int).reshape(-1))
            corners_all.append(np.asarray(corners, float).reshape(-1, 4, 2))
    return ids_all, corners_all


def probe_targets(images: list[np.ndarray], min_markers: int = 4) -> TargetGuess | None:
    """The marker family that finds most markers in ``images`` (BGR or grey; each family
    tried as printed and inverted), at least ``min_markers``; None when none finds that
    many."""
    grays = [to_gray(im) for im in images]
    best: TargetGuess | None = None
    for largest, stem, sizes, bits in FAMILIES:
        either = _detect(grays, largest, True, bits)  # both polarities
        if sum(map(len, either[0])) < min_markers:
            continue
        plain = _detect(grays, largest, False, bits)
        # both polarities also pick up a few inverted codes in texture: a print is inverted
        # only when the plain pass misses most of what both find
        inverted = sum(map(len, plain[0])) < 0.5 * sum(map(len, either[0]))
        ids_all, corners_all = either if inverted else plain
        n = sum(len(i) for i in ids_all)
        if n < min_markers or (best is not None and n <= best.markers):
            continue
        # a large dictionary also "finds" stray codes in texture: an id counts once it is
        # seen in two images (or is the only evidence there is)
        ids = np.concatenate(ids_all)
        seen = np.array([sum(i in set(a.tolist()) for a in ids_all) for i in ids])
        ids = ids[seen >= 2] if np.count_nonzero(seen >= 2) >= min_markers else ids
        per_image = [c for c in corners_all if len(c) >= 3]
        share = float(np.mean([_diagonal_share(c) for c in per_image])) if per_image else 0.0
        best = TargetGuess(_smallest(stem, sizes, int(ids.max())), n, len(ids_all),
                           int(ids.min()), int(ids.max()), share > 0.5, inverted, bits)
    return best
