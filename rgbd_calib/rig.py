"""Camera intrinsics and the rig description (``rig.yaml``, docs/formats.md). Pure numpy."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError
from .yamlio import check_keys, read_yaml_mapping, write_yaml

CAMERA_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_CAMERA_KEYS = {"width", "height", "fx", "fy", "cx", "cy", "distortion", "depth_scale"}
_DIST_ADVICE = "give OpenCV's k1 k2 p1 p2 k3, e.g. [0, 0, 0, 0, 0]"
_ADVICE = "copy the colour intrinsics of the recorded resolution (rs-enumerate-devices -c)"


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole + OpenCV distortion model of one colour sensor (depth is aligned to it)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    depth_scale: float = 0.001  # metres per depth count

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=float)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project ``(N,3)`` camera-frame points (metres) to ``(N,2)`` pixels (no distortion
        unless the model has some: then OpenCV's k1 k2 p1 p2 k3 model)."""
        p = np.asarray(points_cam, dtype=float)
        x = p[:, 0] / p[:, 2]
        y = p[:, 1] / p[:, 2]
        if self.has_distortion:
            x, y = _distort(x, y, self.dist)
        return np.column_stack([self.fx * x + self.cx, self.fy * y + self.cy])

    def to_dict(self) -> dict[str, Any]:
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "distortion": list(self.distortion),
            "depth_scale": self.depth_scale,
        }


def _distort(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    k1, k2, p1, p2 = d[:4]
    k3 = d[4] if d.size > 4 else 0.0
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


@dataclass(frozen=True)
class Rig:
    """Cameras by name, in file order; ``reference`` is the calibration's world frame."""

    cameras: dict[str, CameraIntrinsics]
    reference: str
    source: Path | None = field(default=None, compare=False)

    @property
    def names(self) -> list[str]:
        return list(self.cameras)

    def to_dict(self) -> dict[str, Any]:
        return {
            "reference": self.reference,
            "cameras": {n: c.to_dict() for n, c in self.cameras.items()},
        }


def _show(value: Any) -> str:
    """``repr`` for an error message, shortened (a YAML integer may have 400 digits)."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _positive(value: Any, where: str, integer: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{where}: expected a number, got {_show(value)}; write a plain number")
    try:
        finite = math.isfinite(value)
    except OverflowError:  # an int too large for a float
        finite = False
    if not finite or value <= 0:
        raise ConfigError(
            f"{where}: must be a positive finite number, got {_show(value)}; {_ADVICE}"
        )
    if integer and int(value) != value:
        raise ConfigError(f"{where}: must be a whole number, got {value!r}; fix it")
    return float(value)


def parse_camera(raw: Any, where: str) -> CameraIntrinsics:
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: expected a mapping of intrinsics; {_ADVICE}")
    check_keys(raw, _CAMERA_KEYS, where, required=("width", "height", "fx", "fy", "cx", "cy"))
    width = int(_positive(raw["width"], f"{where}.width", integer=True))
    height = int(_positive(raw["height"], f"{where}.height", integer=True))
    fx = _positive(raw["fx"], f"{where}.fx")
    fy = _positive(raw["fy"], f"{where}.fy")
    cx = _positive(raw["cx"], f"{where}.cx")
    cy = _positive(raw["cy"], f"{where}.cy")
    if not (0 < cx < width and 0 < cy < height):
        raise ConfigError(
            f"{where}: principal point ({cx}, {cy}) lies outside the {width}x{height} image; "
            "check that the intrinsics belong to this resolution"
        )
    dist_raw = raw.get("distortion", [0.0] * 5)
    if dist_raw is None:
        dist_raw = [0.0] * 5
    if not isinstance(dist_raw, (list, tuple)):
        raise ConfigError(f"{where}.distortion: expected a list of numbers; {_DIST_ADVICE}")
    try:
        dist = tuple(float(v) for v in dist_raw)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ConfigError(
            f"{where}.distortion: expected a list of numbers; {_DIST_ADVICE}"
        ) from exc
    if len(dist) not in (4, 5, 8, 12, 14) or not all(math.isfinite(v) for v in dist):
        raise ConfigError(
            f"{where}.distortion: expected 4, 5, 8, 12 or 14 finite OpenCV coefficients "
            f"(k1 k2 p1 p2 k3 ...), got {len(dist)}; {_DIST_ADVICE}"
        )
    depth_scale = _positive(raw.get("depth_scale", 0.001), f"{where}.depth_scale")
    return CameraIntrinsics(width, height, fx, fy, cx, cy, dist, depth_scale)


def load_rig(path: Path) -> Rig:
    """Load and validate a ``rig.yaml``; every problem is one ConfigError line naming the file."""
    path = Path(path)
    data = read_yaml_mapping(path, "rig file")
    check_keys(data, {"reference", "cameras"}, str(path), required=("cameras",))
    cams_raw = data["cameras"]
    if not isinstance(cams_raw, dict) or not cams_raw:
        raise ConfigError(
            f"{path}: 'cameras' must be a non-empty mapping of camera name to intrinsics; "
            "use the layout of docs/formats.md"
        )
    cameras: dict[str, CameraIntrinsics] = {}
    for name, raw in cams_raw.items():
        name = str(name)
        if not CAMERA_NAME.match(name):
            raise ConfigError(
                f"{path}: camera name {name!r} may only use letters, digits, '_' and '-'; "
                "rename the camera and its folder"
            )
        cameras[name] = parse_camera(raw, f"{path}: cameras.{name}")
    reference = str(data.get("reference") or next(iter(cameras)))
    if reference not in cameras:
        raise ConfigError(
            f"{path}: reference camera {reference!r} is not among the cameras "
            f"({', '.join(cameras)}); set reference to one of them"
        )
    return Rig(cameras=cameras, reference=reference, source=path)


def save_rig(rig: Rig, path: Path) -> None:
    write_yaml(path, rig.to_dict())
