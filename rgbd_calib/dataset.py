"""The recorded RGB-D set in folder form (docs/formats.md), read lazily.

Only file names are indexed up front; images are decoded one at a time when asked for, so
a set of any size streams through in constant memory. Every read checks what the contract
promises (colour size = intrinsics, depth 16-bit single-channel of the same size) and fails
with one line naming the file.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .errors import DatasetError
from .rig import CAMERA_NAME, Rig, load_rig

COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class FrameSet:
    """One synchronised capture: the files each camera has for frame ``frame``."""

    frame: str
    color: dict[str, Path]
    depth: dict[str, Path]


@dataclass(frozen=True)
class DatasetSummary:
    cameras: list[str]
    n_frames: int
    frames_per_camera: dict[str, int]
    missing: dict[str, list[str]]  # camera -> frames other cameras have but this one lacks
    depth_cameras: list[str]

    def to_dict(self) -> dict:
        return {
            "cameras": self.cameras,
            "n_frames": self.n_frames,
            "frames_per_camera": self.frames_per_camera,
            "missing": {c: len(m) for c, m in self.missing.items()},
            "depth_cameras": self.depth_cameras,
        }


class FolderDataset:
    """Index of ``<dataset>/<camera>/{color,depth}/<frame>.png`` with its ``rig.yaml``."""

    def __init__(self, path: Path, rig: Rig | None = None):
        self.path = Path(path)
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: dataset folder not found; check the path")
        rig_path = self.path / "rig.yaml"
        if rig is None:
            if not rig_path.is_file():
                raise DatasetError(
                    f"{rig_path}: missing; every dataset needs a rig.yaml with "
                    "the cameras' intrinsics (docs/formats.md)"
                )
            rig = load_rig(rig_path)
        self.rig = rig
        folders = sorted(
            p.name for p in self.path.iterdir() if p.is_dir() and (p / "color").is_dir()
        )
        extra = [f for f in folders if f not in rig.cameras]
        if extra:
            raise DatasetError(
                f"{self.path}: camera folder(s) {', '.join(extra)} have no entry "
                f"in {rig_path.name}; add their intrinsics or remove the folders"
            )
        absent = [c for c in rig.cameras if c not in folders]
        if absent:
            raise DatasetError(
                f"{self.path}: camera(s) {', '.join(absent)} of "
                f"{rig_path.name} have no <camera>/color folder; record them or "
                "remove them from the rig"
            )
        self._color: dict[str, dict[str, Path]] = {}
        self._depth: dict[str, dict[str, Path]] = {}
        for cam in rig.cameras:
            if not CAMERA_NAME.match(cam):
                raise DatasetError(f"{self.path / cam}: invalid camera folder name")
            self._color[cam] = {
                p.stem: p
                for p in sorted((self.path / cam / "color").iterdir())
                if p.suffix.lower() in COLOR_SUFFIXES
            }
            depth_dir = self.path / cam / "depth"
            self._depth[cam] = (
                {p.stem: p for p in sorted(depth_dir.iterdir()) if p.suffix.lower() == ".png"}
                if depth_dir.is_dir()
                else {}
            )
        self.frames = sorted(set().union(*(set(c) for c in self._color.values())))
        if not self.frames:
            raise DatasetError(
                f"{self.path}: no colour images found under <camera>/color/; "
                "is this the dataset folder?"
            )

    @property
    def cameras(self) -> list[str]:
        return self.rig.names

    def has_depth(self, camera: str) -> bool:
        return bool(self._depth[camera])

    def summary(self) -> DatasetSummary:
        missing = {c: [f for f in self.frames if f not in self._color[c]] for c in self.cameras}
        return DatasetSummary(
            self.cameras,
            len(self.frames),
            {c: len(self._color[c]) for c in self.cameras},
            missing,
            [c for c in self.cameras if self.has_depth(c)],
        )

    def color_path(self, camera: str, frame: str) -> Path | None:
        return self._color[camera].get(frame)

    def depth_path(self, camera: str, frame: str) -> Path | None:
        return self._depth[camera].get(frame)

    def frame_sets(self) -> Iterator[FrameSet]:
        """Synchronised frame sets in frame order (paths only; nothing is decoded)."""
        for f in self.frames:
            color = {c: self._color[c][f] for c in self.cameras if f in self._color[c]}
            depth = {c: self._depth[c][f] for c in self.cameras if f in self._depth[c]}
            yield FrameSet(f, color, depth)

    def read_color(self, camera: str, frame: str, gray: bool = False) -> np.ndarray:
        path = self._color[camera].get(frame)
        if path is None:
            raise DatasetError(f"{self.path / camera / 'color'}: no frame {frame}")
        return read_color_image(
            path, self.rig.cameras[camera].width, self.rig.cameras[camera].height, gray
        )

    def read_depth(self, camera: str, frame: str) -> np.ndarray | None:
        path = self._depth[camera].get(frame)
        if path is None:
            return None
        intr = self.rig.cameras[camera]
        return read_depth_image(path, intr.width, intr.height)


def read_color_image(path: Path, width: int, height: int, gray: bool = False) -> np.ndarray:
    """Decode an 8-bit colour image and check its size against the intrinsics."""
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"{path}: unreadable or corrupt image; re-export or delete it")
    if img.shape[:2] != (height, width):
        raise DatasetError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]} but rig.yaml says "
            f"{width}x{height}; use the intrinsics of this resolution"
        )
    return img


def read_depth_image(path: Path, width: int, height: int) -> np.ndarray:
    """Decode a 16-bit single-channel depth PNG and check its size."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{path}: unreadable or corrupt depth image; re-export or delete it")
    if img.dtype != np.uint16 or img.ndim != 2:
        kind = f"{img.dtype}, {1 if img.ndim == 2 else img.shape[2]} channel(s)"
        raise DatasetError(
            f"{path}: depth must be a 16-bit single-channel PNG, got {kind}; "
            "export raw depth counts (z16) aligned to colour"
        )
    if img.shape != (height, width):
        raise DatasetError(
            f"{path}: depth is {img.shape[1]}x{img.shape[0]} but the colour "
            f"intrinsics say {width}x{height}; align depth to colour first"
        )
    return img
