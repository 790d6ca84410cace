"""``depth_model.yaml``: each camera's depth model as ``calibrate`` chose it, written next to
``extrinsics.yaml`` and read back by :func:`load_depth_models` (docs/formats.md). Apply one to a
depth image with :func:`rgbd_calib.core.depth_model.correct_depth_image`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..core.depth_model import DepthModel
from ..core.errors import DatasetError, RgbdCalibError
from ..core.yamlio import read_yaml_mapping, write_yaml

DEPTH_MODEL_FILE = "depth_model.yaml"
FORMAT_VERSION = 1
HEADER = (
    "rgbd-calib depth models: per camera, measured depth (aligned to colour) -> true depth.\n"
    "1/z = scale/z_m - delta(x, y)/focal_baseline_px_m, delta = d0 + dx x + dy y + dxx x^2 +\n"
    "dxy x y + dyy y^2 (px; x, y the pixel's undistorted ray), then p = R p + t (rx ry rz deg,\n"
    "tx ty tz mm). Apply with rgbd_calib.correct_depth_image (docs/formats.md).\n"
)


def depth_models_dict(models: dict[str, DepthModel],
                      evidence: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """The file's content: ``cameras.<camera>`` the model (:meth:`DepthModel.to_dict`) plus,
    when given, its evidence (the term tests and the board-plane residuals)."""
    return {"format_version": FORMAT_VERSION,
            "cameras": {c: {**m.to_dict(), **((evidence or {}).get(c) or {})}
                        for c, m in sorted(models.items())}}


def save_depth_models(models: dict[str, DepthModel], path: Path,
                      evidence: dict[str, dict[str, Any]] | None = None) -> None:
    write_yaml(Path(path), depth_models_dict(models, evidence), header=HEADER)


def load_depth_models(path: str | Path) -> dict[str, DepthModel]:
    """camera -> :class:`DepthModel` from a ``depth_model.yaml`` (a calibrate output folder's,
    or the folder itself)."""
    path = Path(path)
    if path.is_dir():
        path = path / DEPTH_MODEL_FILE
    data = read_yaml_mapping(path, "depth model file")
    cams = data.get("cameras")
    if not isinstance(cams, dict):
        raise DatasetError(f"{path}: no 'cameras' mapping; write it as rgbd-calib calibrate "
                           "does (docs/formats.md, depth_model.yaml)")
    out = {}
    for c, entry in cams.items():
        if not isinstance(entry, dict):
            raise DatasetError(f"{path}: cameras.{c} is not a mapping")
        try:
            out[str(c)] = DepthModel.from_dict(entry, where=f"{path}: cameras.{c}")
        except RgbdCalibError as exc:
            raise DatasetError(str(exc)) from exc
    return out
