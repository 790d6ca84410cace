"""The rig description (``rig.yaml``, docs/formats.md): cameras by name with their
intrinsics (:class:`~rgbd_calib.core.camera.CameraIntrinsics`). Pure numpy.

A camera may give only ``width`` and ``height``: its intrinsics are then calibrated from
scratch from the calibration set (:mod:`rgbd_calib.solve.intrinsics_init`, then the bundle
adjustment); until then it holds :func:`placeholder_intrinsics` and is listed in
``Rig.unknown_intrinsics``."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..core.camera import (
    DEPTH_NOISE_MODELS,
    DISTORTION_LENGTHS,
    FISHEYE,
    LENS_MODELS,
    OPENCV,
    CameraIntrinsics,
)
from ..core.errors import ConfigError
from ..core.yamlio import check_keys, read_yaml_mapping, write_yaml

CAMERA_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_CAMERA_KEYS = {"width", "height", "fx", "fy", "cx", "cy", "distortion", "depth_scale",
                "depth_noise", "model"}
_PINHOLE_KEYS = ("fx", "fy", "cx", "cy")
_DIST_ADVICE = "give OpenCV's k1 k2 p1 p2 k3, e.g. [0, 0, 0, 0, 0]"
_ADVICE = "copy the colour intrinsics of the recorded resolution (rs-enumerate-devices -c)"


@dataclass(frozen=True)
class Rig:
    """Cameras by name, in file order; ``reference`` is the calibration's world frame.

    ``sigmas`` (camera -> {parameter: marginal sigma}) marks intrinsics that were estimated,
    e.g. refined by a bundle adjustment (``rig_refined.yaml`` with its report.json): the depth
    stage carries their uncertainty into every pair. Empty: the intrinsics are taken as exact."""

    cameras: dict[str, CameraIntrinsics]
    reference: str
    source: Path | None = field(default=None, compare=False)
    # cameras whose rig.yaml gave only width/height: their `cameras` entry is a placeholder
    unknown_intrinsics: frozenset[str] = frozenset()
    sigmas: dict[str, dict[str, float]] = field(default_factory=dict, compare=False)

    @property
    def names(self) -> list[str]:
        return list(self.cameras)

    def with_intrinsics(self, cameras: dict[str, CameraIntrinsics]) -> Rig:
        """This rig with the models of ``cameras`` replaced (they are known from then on)."""
        return Rig({n: cameras.get(n, c) for n, c in self.cameras.items()}, self.reference,
                   self.source, self.unknown_intrinsics - set(cameras), self.sigmas)

    def to_dict(self) -> dict[str, Any]:
        return {
            "reference": self.reference,
            "cameras": {n: _size_only(c) if n in self.unknown_intrinsics else c.to_dict()
                        for n, c in self.cameras.items()},
        }


def placeholder_intrinsics(width: int, height: int, depth_scale: float = 0.001,
                           depth_noise: str = "d435") -> CameraIntrinsics:
    """The model of a camera with unknown intrinsics until they are initialised: a pinhole of
    ~64 deg horizontal field of view centred on the image, no distortion (only the detection
    runs with it, and it uses only the distortion)."""
    return CameraIntrinsics(width, height, 0.8 * width, 0.8 * width, (width - 1) / 2.0,
                            (height - 1) / 2.0, (0.0,) * 5, depth_scale, depth_noise)


def _size_only(c: CameraIntrinsics) -> dict[str, Any]:
    """rig.yaml's entry of a camera with unknown intrinsics: its size (and depth settings)."""
    out: dict[str, Any] = {"width": c.width, "height": c.height}
    if c.depth_scale != 0.001:
        out["depth_scale"] = c.depth_scale
    if c.depth_noise != "d435":
        out["depth_noise"] = c.depth_noise
    return out


def intrinsics_given(raw: Any) -> bool:
    """Whether a rig.yaml camera entry gives its pinhole (fx fy cx cy); False: width/height
    only, the intrinsics are calibrated from scratch."""
    return not isinstance(raw, dict) or any(k in raw for k in _PINHOLE_KEYS + ("distortion",))


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
    """One camera entry of rig.yaml. An entry with only width/height (no fx fy cx cy, no
    distortion) gives :func:`placeholder_intrinsics` (check :func:`intrinsics_given`)."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: expected a mapping of intrinsics; {_ADVICE}")
    given = intrinsics_given(raw)
    check_keys(raw, _CAMERA_KEYS, where,
               required=("width", "height") + (_PINHOLE_KEYS if given else ()))
    width = int(_positive(raw["width"], f"{where}.width", integer=True))
    height = int(_positive(raw["height"], f"{where}.height", integer=True))
    if not given:
        if raw.get("model", OPENCV) == FISHEYE:
            raise ConfigError(f"{where}: a fisheye camera (model: fisheye) needs its fx fy cx "
                              "cy (and distortion, zeros to self-calibrate it); calibrating a "
                              "fisheye from scratch is not supported")
        return placeholder_intrinsics(width, height, *_depth_settings(raw, where))
    fx = _positive(raw["fx"], f"{where}.fx")
    fy = _positive(raw["fy"], f"{where}.fy")
    cx = _positive(raw["cx"], f"{where}.cx")
    cy = _positive(raw["cy"], f"{where}.cy")
    if not (0 < cx < width and 0 < cy < height):
        raise ConfigError(
            f"{where}: principal point ({cx}, {cy}) lies outside the {width}x{height} image; "
            "check that the intrinsics belong to this resolution"
        )
    lens = raw.get("model", OPENCV)
    if lens not in LENS_MODELS:
        raise ConfigError(f"{where}.model: {_show(lens)} is not a lens model; give "
                          f"{' or '.join(LENS_MODELS)} (equidistant, cv2.fisheye's k1..k4)")
    zeros = [0.0] * (4 if lens == FISHEYE else 5)
    dist_raw = raw.get("distortion", zeros)
    if dist_raw is None:
        dist_raw = zeros
    if not isinstance(dist_raw, (list, tuple)):
        raise ConfigError(f"{where}.distortion: expected a list of numbers; {_DIST_ADVICE}")
    try:
        dist = tuple(float(v) for v in dist_raw)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ConfigError(
            f"{where}.distortion: expected a list of numbers; {_DIST_ADVICE}"
        ) from exc
    if lens == FISHEYE and (len(dist) != 4 or not all(math.isfinite(v) for v in dist)):
        raise ConfigError(
            f"{where}.distortion: a fisheye lens (model: fisheye) has 4 finite coefficients "
            f"k1 k2 k3 k4 (cv2.fisheye, Kalibr's pinhole-equi), got {len(dist)}; give four, "
            "or model: opencv for k1 k2 p1 p2 k3")
    if len(dist) not in DISTORTION_LENGTHS or not all(math.isfinite(v) for v in dist):
        raise ConfigError(
            f"{where}.distortion: expected 4, 5, 8, 12 or 14 finite OpenCV coefficients "
            f"(k1 k2 p1 p2 k3 ...), got {len(dist)}; {_DIST_ADVICE}"
        )
    return CameraIntrinsics(width, height, fx, fy, cx, cy, dist, *_depth_settings(raw, where),
                            lens=lens)


def _depth_settings(raw: dict[str, Any], where: str) -> tuple[float, str]:
    depth_scale = _positive(raw.get("depth_scale", 0.001), f"{where}.depth_scale")
    noise = raw.get("depth_noise", "d435")
    if noise not in DEPTH_NOISE_MODELS:
        raise ConfigError(
            f"{where}.depth_noise: {_show(noise)} is not a depth noise model; use one of "
            f"{', '.join(DEPTH_NOISE_MODELS)} (d435: active stereo, the default; kinect-v1: "
            "structured light)"
        )
    return depth_scale, noise


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
    unknown: set[str] = set()
    for name, raw in cams_raw.items():
        name = str(name)
        if not CAMERA_NAME.match(name):
            raise ConfigError(
                f"{path}: camera name {name!r} may only use letters, digits, '_' and '-'; "
                "rename the camera and its folder"
            )
        cameras[name] = parse_camera(raw, f"{path}: cameras.{name}")
        if not intrinsics_given(raw):
            unknown.add(name)
    reference = str(data.get("reference") or next(iter(cameras)))
    if reference not in cameras:
        raise ConfigError(
            f"{path}: reference camera {reference!r} is not among the cameras "
            f"({', '.join(cameras)}); set reference to one of them"
        )
    return Rig(cameras=cameras, reference=reference, source=path,
               unknown_intrinsics=frozenset(unknown))


def save_rig(rig: Rig, path: Path) -> None:
    write_yaml(path, rig.to_dict())
