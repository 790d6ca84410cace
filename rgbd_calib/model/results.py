"""Typed calibration data: the board-pose edges the solvers take, the results, and the
``extrinsics.yaml`` contract (docs/formats.md)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..core.errors import ConfigError, UnknownCameraError
from ..core.geometry import is_rigid, matrix_to_quaternion_xyzw, orthonormalize
from ..core.yamlio import check_keys, matrix4, read_yaml_mapping, shown, write_yaml

# translation_m / quaternion_xyzw may differ from T_ref_cam by rounding (hand-written files)
REDUNDANT_TOL_M = 1e-4
REDUNDANT_TOL_RAD = 1e-3


@dataclass(frozen=True)
class PoseEdge:
    """One detection: board view ``view`` seen by ``camera`` as ``T_cam_board`` (4x4, metres).

    ``covariance`` is 6x6 in GTSAM order ``[rot rad, trans m]``, in the body frame of the board
    pose (a right perturbation ``T_cam_board @ Exp(xi)``); ``None`` = the config's default.
    ``model_error_covariance`` is the part of ``covariance`` that is the per-view model-error
    floor (``pose.model_error_px``): the pose graph's camera model-error test whitens without
    it, its outlier test and its solve with it. ``model_error_unit`` is that floor's
    covariance for a 1 px model error, not included in ``covariance``: with
    ``pose.model_error_px: auto`` the pose graph estimates the floor from the views'
    disagreement and adds it (``solve.posegraph._estimate_view_floor``)."""

    camera: str
    view: str
    T_cam_board: np.ndarray
    covariance: np.ndarray | None = None
    model_error_covariance: np.ndarray | None = None
    model_error_unit: np.ndarray | None = None


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


class Solve(Protocol):
    """What a solve (bundle adjustment, pose graph of depth pairs) gives per camera."""

    T_ref_cam: dict[str, np.ndarray]
    sigma_rotation_deg: dict[str, float]
    sigma_translation_mm: dict[str, float]
    covariance: dict[str, np.ndarray]


def cameras_from_solve(solve: Solve) -> dict[str, CameraExtrinsics]:
    """One :class:`CameraExtrinsics` per camera of a solve, with its marginal sigmas."""
    return {
        c: CameraExtrinsics(
            c,
            solve.T_ref_cam[c],
            solve.sigma_rotation_deg[c],
            solve.sigma_translation_mm[c],
            solve.covariance[c],
        )
        for c in solve.T_ref_cam
    }


# report.json ``summary.verdict``, best first: good (no warning), check (usable, look at the
# warnings first), poor (do not use these extrinsics as they are)
VERDICT_GRADES = ("good", "check", "poor")


@dataclass(frozen=True)
class Verdict:
    """What a result is worth: ``grade`` (one of :data:`VERDICT_GRADES`, report.json's
    ``summary.verdict``) and the reason in one line (its worst finding)."""

    grade: str
    reason: str

    def __post_init__(self) -> None:
        if self.grade not in VERDICT_GRADES:
            raise ConfigError(f"verdict grade {self.grade!r}: use one of "
                              f"{', '.join(VERDICT_GRADES)}")

    def to_dict(self) -> dict[str, str]:
        return {"grade": self.grade, "reason": self.reason}

    @property
    def line(self) -> str:
        """``POOR: <reason>``, as the exports' header comments state it."""
        return f"{self.grade.upper()}: {self.reason}"


class CameraMap(dict):
    """``Extrinsics.cameras``: a dict whose unknown name raises :class:`UnknownCameraError`
    naming the cameras it has (a ``KeyError`` too) instead of a bare ``KeyError``."""

    def __missing__(self, name: Any) -> CameraExtrinsics:
        raise UnknownCameraError(
            f"camera {name!r} is not in this calibration; its cameras: "
            f"{', '.join(map(str, self)) or 'none'}")


@dataclass(frozen=True)
class Extrinsics:
    """All calibrated cameras of a rig in the reference camera's frame, and, once judged, the
    verdict on them (``extrinsics.yaml`` ``verdict``; None: not judged, e.g. ``posegraph``)."""

    reference: str
    cameras: dict[str, CameraExtrinsics]
    unconnected: dict[str, str] = field(default_factory=dict)  # camera -> why not calibrated
    verdict: Verdict | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.cameras, CameraMap):
            object.__setattr__(self, "cameras", CameraMap(self.cameras))
        # the reference is the world frame: its pose is the identity exactly, not the
        # optimiser's 1e-28 (the prior holding it is a numerical device)
        ref = self.cameras.get(self.reference)
        if ref is not None and np.allclose(ref.T_ref_cam, np.eye(4), atol=1e-9):
            self.cameras[self.reference] = replace(ref, T_ref_cam=np.eye(4))

    def T_ref_cam(self, name: str) -> np.ndarray:
        """The camera's pose (4x4, metres); an unknown name raises
        :class:`~rgbd_calib.core.errors.UnknownCameraError` listing the cameras."""
        return self.cameras[name].T_ref_cam

    def to_dict(self) -> dict[str, Any]:
        """``extrinsics.yaml``'s content: the verdict first (when judged), where a reader of
        the file sees it before any number."""
        head = {"verdict": self.verdict.to_dict()} if self.verdict is not None else {}
        return {
            **head,
            "reference": self.reference,
            "cameras": {n: c.to_dict() for n, c in self.cameras.items()},
        }


EXTRINSICS_HEADER = """rgbd-calib extrinsics (docs/formats.md, "Calibration output").
T_ref_cam maps a camera's points into the reference camera's frame: p_ref = T_ref_cam @ p_cam.
Camera frame: the OpenCV optical frame of the colour sensor (x right, y down, z forward).
Units: metres; quaternion_xyzw is the rotation of T_ref_cam; sigmas are 1-sigma marginals."""


VERDICT_HEADER = """verdict: good (ready to use), check (usable; read report.html's warnings
first) or poor (do not use these extrinsics as they are), with the worst finding as its reason."""


def write_extrinsics(extrinsics: Extrinsics, path: Path) -> None:
    """Write ``extrinsics.yaml`` atomically (temporary file + rename), after a comment stating
    the convention (and what the verdict means, when the extrinsics carry one)."""
    header = EXTRINSICS_HEADER + ("\n" + VERDICT_HEADER if extrinsics.verdict else "")
    write_yaml(path, extrinsics.to_dict(), header=header)


def load_extrinsics(path: Path, check_redundant: bool = False) -> Extrinsics:
    """Read an ``extrinsics.yaml`` (ours, or hand-written with at least ``T_ref_cam``).

    ``T_ref_cam`` is what is read; with ``check_redundant`` (files a user hands to the CLI) a
    ``translation_m`` / ``quaternion_xyzw`` that disagrees with it is an error, not ignored."""
    path = Path(path)
    data = read_yaml_mapping(path, "extrinsics file")
    check_keys(data, {"verdict", "reference", "cameras"}, str(path), required=("cameras",))
    cams = data["cameras"]
    if not isinstance(cams, dict) or not cams:
        raise ConfigError(
            f"{path}: 'cameras' must be a non-empty mapping; use the layout of docs/formats.md"
        )
    out: dict[str, CameraExtrinsics] = {}
    for name, raw in cams.items():
        where = f"{path}: cameras.{shown(name)}"
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: expected a mapping with T_ref_cam; add T_ref_cam")
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
                "orthonormal or last row not 0 0 0 1); fix the matrix"
            )
        T[:3, :3] = orthonormalize(T[:3, :3])
        if check_redundant:
            _check_redundant(raw, T, where)
        out[str(name)] = CameraExtrinsics(
            str(name),
            T,
            _optional_float(raw.get("sigma_rotation_deg"), f"{where}.sigma_rotation_deg"),
            _optional_float(raw.get("sigma_translation_mm"), f"{where}.sigma_translation_mm"),
        )
    reference = str(data.get("reference") or next(iter(out)))
    if reference not in out:
        raise ConfigError(
            f"{path}: reference {reference!r} is not among the cameras; add it (identity)"
        )
    return Extrinsics(reference, out, verdict=_verdict(data.get("verdict"), path))


def _verdict(raw: Any, path: Path) -> Verdict | None:
    """``verdict: {grade, reason}`` of an extrinsics.yaml (absent or null: not judged)."""
    if raw is None:
        return None
    if (not isinstance(raw, dict) or set(map(str, raw)) != {"grade", "reason"}
            or raw["grade"] not in VERDICT_GRADES or not isinstance(raw["reason"], str)):
        raise ConfigError(f"{path}: verdict must be {{grade: {' | '.join(VERDICT_GRADES)}, "
                          "reason: <text>}; fix it or remove the verdict")
    return Verdict(raw["grade"], raw["reason"])


def _optional_float(value: Any, where: str) -> float:
    """A number, or NaN when absent (``null``)."""
    if value is None:
        return float("nan")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{where}: expected a number, got {str(value)[:40]!r}; fix or remove it")
    try:
        return float(value)
    except OverflowError:
        raise ConfigError(f"{where}: number out of range; fix or remove it") from None


def _check_redundant(raw: dict[str, Any], T: np.ndarray, where: str) -> None:
    """``translation_m`` / ``quaternion_xyzw`` repeat ``T_ref_cam``; a hand edit of one but not
    the other must not pass silently (``T_ref_cam`` is what is read)."""
    if raw.get("translation_m") is not None:
        t = _vector(raw["translation_m"], 3, f"{where}.translation_m")
        if np.abs(t - T[:3, 3]).max() > REDUNDANT_TOL_M:
            raise ConfigError(
                f"{where}.translation_m {t.tolist()} disagrees with T_ref_cam's translation "
                f"{T[:3, 3].tolist()}; edit both or remove translation_m"
            )
    if raw.get("quaternion_xyzw") is not None:
        q = _vector(raw["quaternion_xyzw"], 4, f"{where}.quaternion_xyzw")
        if not np.linalg.norm(q) > 0:
            raise ConfigError(
                f"{where}.quaternion_xyzw: a zero quaternion is no rotation; fix or remove it"
            )
        cos_half = abs(float(q @ matrix_to_quaternion_xyzw(T[:3, :3]))) / np.linalg.norm(q)
        if 2.0 * np.arccos(min(cos_half, 1.0)) > REDUNDANT_TOL_RAD:
            raise ConfigError(
                f"{where}.quaternion_xyzw disagrees with T_ref_cam's rotation; "
                "edit both or remove quaternion_xyzw"
            )


def _vector(value: Any, n: int, where: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        v = np.zeros(0)
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise ConfigError(f"{where}: expected {n} finite numbers; fix or remove it")
    return v
