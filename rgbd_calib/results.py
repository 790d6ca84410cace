"""Typed calibration results and the ``extrinsics.yaml`` contract (docs/formats.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError
from .geometry import is_rigid, matrix_to_quaternion_xyzw, orthonormalize
from .yamlio import check_keys, matrix4, read_yaml_mapping, write_yaml


@dataclass(frozen=True)
class CameraExtrinsics:
    """``T_ref_cam`` (4x4, metres) with its 1-sigma marginal uncertainty."""

    name: str
    T_ref_cam: np.ndarray
    sigma_rotation_deg: float = float("nan")
    sigma_translation_mm: float = float("nan")
    covariance: np.ndarray | None = None  # 6x6, body frame, [rot(rad), trans(m)] (GTSAM order)

    def to_dict(self) -> dict[str, Any]:
        T = np.asarray(self.T_ref_cam, dtype=float)
        return {
            "T_ref_cam": T.tolist(),
            "translation_m": T[:3, 3].tolist(),
            "quaternion_xyzw": matrix_to_quaternion_xyzw(T[:3, :3]).tolist(),
            "sigma_rotation_deg": float(self.sigma_rotation_deg),
            "sigma_translation_mm": float(self.sigma_translation_mm),
        }


@dataclass(frozen=True)
class Extrinsics:
    """All calibrated cameras of a rig in the reference camera's frame."""

    reference: str
    cameras: dict[str, CameraExtrinsics]
    unconnected: dict[str, str] = field(default_factory=dict)  # camera -> why not calibrated

    def T_ref_cam(self, name: str) -> np.ndarray:
        return self.cameras[name].T_ref_cam

    def to_dict(self) -> dict[str, Any]:
        return {
            "reference": self.reference,
            "cameras": {n: c.to_dict() for n, c in self.cameras.items()},
        }


def write_extrinsics(extrinsics: Extrinsics, path: Path) -> None:
    """Write ``extrinsics.yaml`` atomically (temporary file + rename)."""
    write_yaml(path, extrinsics.to_dict())


def load_extrinsics(path: Path) -> Extrinsics:
    """Read an ``extrinsics.yaml`` (ours, or hand-written with at least ``T_ref_cam``)."""
    path = Path(path)
    data = read_yaml_mapping(path, "extrinsics file")
    check_keys(data, {"reference", "cameras"}, str(path), required=("cameras",))
    cams = data["cameras"]
    if not isinstance(cams, dict) or not cams:
        raise ConfigError(f"{path}: 'cameras' must be a non-empty mapping")
    out: dict[str, CameraExtrinsics] = {}
    for name, raw in cams.items():
        where = f"{path}: cameras.{name}"
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: expected a mapping with T_ref_cam")
        check_keys(
            raw,
            {
                "T_ref_cam",
                "translation_m",
                "quaternion_xyzw",
                "sigma_rotation_deg",
                "sigma_translation_mm",
            },
            where,
            required=("T_ref_cam",),
        )
        T = matrix4(raw["T_ref_cam"], f"{where}.T_ref_cam")
        if not is_rigid(T, atol=1e-4):
            raise ConfigError(
                f"{where}.T_ref_cam is not a rigid transform (rotation not "
                "orthonormal or last row not 0 0 0 1)"
            )
        T[:3, :3] = orthonormalize(T[:3, :3])
        out[str(name)] = CameraExtrinsics(
            str(name),
            T,
            float(raw.get("sigma_rotation_deg", float("nan"))),
            float(raw.get("sigma_translation_mm", float("nan"))),
        )
    reference = str(data.get("reference") or next(iter(out)))
    if reference not in out:
        raise ConfigError(f"{path}: reference {reference!r} is not among the cameras")
    return Extrinsics(reference, out)
