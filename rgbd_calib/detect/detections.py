"""What a detector found in one image (:class:`MarkerDetections`), shared by every target's
detector (:mod:`rgbd_calib.detect.markers`, :mod:`rgbd_calib.detect.checkerboard`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np


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
