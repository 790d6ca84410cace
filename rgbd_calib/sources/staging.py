"""What a reader hands to the writer: each camera's frames, decoded once and staged on disk.

A reader (:mod:`.realsense`, :mod:`.ros`) fills one :class:`StagedCamera` per camera with its
calibration and the timestamps and staged PNG paths of its colour and depth frames; the
conversion then pairs, matches and moves those files into the folder form.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.camera import CameraIntrinsics
from ..model.dataset import write_png
from ..model.rig import CAMERA_NAME


@dataclass
class StagedFrame:
    t_ms: float
    path: Path


@dataclass
class StagedCamera:
    """One camera's staged frames and calibration while its sources are read."""

    key: str  # where it came from (file or namespace), for messages
    name: str
    intrinsics: CameraIntrinsics | None = None
    intrinsics_source: str = ""
    depth_source: str = "none (colour-only camera)"
    colors: list[StagedFrame] = field(default_factory=list)
    depths: list[StagedFrame] = field(default_factory=list)
    depth_raw: bool = False  # depths are raw depth-camera images that still need aligning
    depth_intrinsics: CameraIntrinsics | None = None
    T_color_depth: np.ndarray | None = None
    depth_scale: float = 0.001
    fps: float | None = None
    timestamp_domain: str = ""


class Stager:
    """Writes decoded images once into ``<tmp>/.staging`` and hands out their paths."""

    def __init__(self, root: Path):
        self.root = root / ".staging"
        self.root.mkdir(parents=True)
        self._n = 0

    def put(self, image: np.ndarray) -> Path:
        self._n += 1
        path = self.root / f"{self._n:08d}.png"
        write_png(path, image)
        return path


def sanitize_name(name: str) -> str:
    clean = "".join(ch if CAMERA_NAME.match(ch) else "_" for ch in name).strip("_")
    return clean or "camera"
