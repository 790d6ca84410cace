"""An earlier calibration's output folder read back for the depth-only commands: the
depth models or depth-scale factors, the board views and the ``cameras`` of its
``report.json``, and the intrinsics its ``rig_refined.yaml`` refined (docs/formats.md);
:func:`load_calibration` reads them all at once."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.depth_model import DepthModel
from ..core.errors import ConfigError, DatasetError
from .board import Board, thesis_board
from .board_file import DATASET_BOARD_FILE, load_board
from .depth_model_file import DEPTH_MODEL_FILE, load_depth_models
from .results import Extrinsics, load_extrinsics
from .rig import Rig, load_rig


def load_depth_corrections(calib_dir: str | Path) -> dict[str, float | DepthModel]:
    """camera -> how the calibration in ``calib_dir`` corrects its depth: the
    :class:`DepthModel` of its ``depth_model.yaml`` (the identity where the evidence chose no
    term), else the depth-scale factor of its ``report.json`` (a calibration from before
    depth models); cameras with neither are left out (their depth scale is unknown)."""
    calib_dir = Path(calib_dir)
    out: dict[str, float | DepthModel] = dict(load_depth_scales(calib_dir / "report.json"))
    if (calib_dir / DEPTH_MODEL_FILE).is_file():
        out.update(load_depth_models(calib_dir / DEPTH_MODEL_FILE))
    return out


@dataclass(frozen=True)
class EarlierCalibration:
    """A calibration read back: its ``extrinsics.yaml`` (``path``), and from the files beside
    it each camera's depth correction (:func:`load_depth_corrections`) and the board views
    (frame -> ``T_ref_board`` and frame -> cameras that saw it); empty when it has none."""

    path: Path
    extrinsics: Extrinsics
    depth_scales: dict[str, float | DepthModel]  # depth model, else report.json's factor
    T_ref_board: dict[str, np.ndarray]
    board_cameras: dict[str, list[str]]
    edge_offsets: dict[str, float] = field(default_factory=dict)  # camera -> modelled px


def load_calibration(calib: str | os.PathLike) -> EarlierCalibration:
    """A calibrate (or refine) output folder, or an ``extrinsics.yaml``, read back."""
    path = Path(calib)
    path = path / "extrinsics.yaml" if path.is_dir() else path
    if not path.is_file():
        raise ConfigError(f"{calib}: no extrinsics.yaml; give a calibrate output folder or an "
                          "extrinsics.yaml")
    report = path.parent / "report.json"
    return EarlierCalibration(path, load_extrinsics(path, check_redundant=True),
                              load_depth_corrections(path.parent), *load_board_views(report),
                              load_edge_offsets(report))


def load_edge_offsets(report_json: Path) -> dict[str, float]:
    """camera -> the detector edge offset (px per edge) a calibration modelled, from its
    ``report.json`` (``bundle.edge_offset.<camera>.applied_px``, schema 1.21; cameras without
    one are left out); empty when the file does not exist or has none."""
    if not Path(report_json).is_file():
        return {}
    try:
        offsets = (json.loads(Path(report_json).read_text()).get("bundle") or {}).get(
            "edge_offset") or {}
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{report_json}: not a readable report.json ({exc}); remove it or "
                           "repair it") from exc
    return {str(c): float(e["applied_px"]) for c, e in offsets.items()
            if isinstance(e, dict) and e.get("applied_px")}


def load_depth_scales(report_json: Path) -> dict[str, float]:
    """camera -> depth-scale factor from a calibrate ``report.json``
    (``cameras.<camera>.depth_scale_factor``; cameras without one are left out); empty when
    the file does not exist."""
    return {c: float(v["depth_scale_factor"]) for c, v in report_cameras(report_json).items()
            if isinstance(v, dict) and v.get("depth_scale_factor") is not None}


def report_cameras(report_json: Path) -> dict[str, Any]:
    """``cameras`` of a calibrate ``report.json``; empty when the file does not exist."""
    if not report_json.is_file():
        return {}
    try:
        return json.loads(report_json.read_text()).get("cameras", {})
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{report_json}: not a readable report.json ({exc}); remove it or "
                           "repair it") from exc


def with_refined_intrinsics(rig: Rig, calib_dir: Path) -> tuple[Rig, list[str]]:
    """``rig`` with the intrinsics the calibration in ``calib_dir`` refined (its
    ``rig_refined.yaml``), marked with their marginal sigmas from its report.json
    (``cameras.<camera>.intrinsics_refined.<parameter>.sigma``; without them the refined
    values are taken as exact), and the cameras that changed. A calibration without
    rig_refined.yaml leaves ``rig`` as it is: depth back-projected with intrinsics other than
    those the extrinsics were solved with is off by millimetres (measured: docs/depth.md)."""
    path = Path(calib_dir) / "rig_refined.yaml"
    if not path.is_file():
        return rig, []
    cams = report_cameras(Path(calib_dir) / "report.json")
    changed: dict[str, CameraIntrinsics] = {}
    sigmas = dict(rig.sigmas)
    for c, intr in load_rig(path).cameras.items():
        if c not in rig.cameras or intr == rig.cameras[c]:
            continue
        now = rig.cameras[c]
        if (intr.width, intr.height) != (now.width, now.height):
            raise DatasetError(
                f"{path}: camera {c} is {intr.width}x{intr.height}, the dataset's "
                f"{now.width}x{now.height}; give the calibration of this "
                "resolution, or remove rig_refined.yaml to use rig.yaml's intrinsics")
        changed[c] = intr
        entry = cams.get(c, {}).get("intrinsics_refined") or {}
        sigmas[c] = {k: float(v["sigma"]) for k, v in entry.items()
                     if isinstance(v, dict) and v.get("sigma") is not None}
    return replace(rig.with_intrinsics(changed), sigmas=sigmas), list(changed)


def load_board_views(report_json: Path) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """frame -> ``T_ref_board`` (4x4) and frame -> cameras that saw it, from a calibrate
    ``report.json`` (``board_views``); empty when the file does not exist."""
    if not report_json.is_file():
        return {}, {}
    try:
        views = json.loads(report_json.read_text()).get("board_views", [])
        poses = {str(v["frame"]): np.asarray(v["T_ref_board"], dtype=float) for v in views}
        cams = {str(v["frame"]): [str(c) for c in v["cameras"]] for v in views}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{report_json}: board_views unreadable ({exc}); remove or repair "
                           "the report.json next to --init") from exc
    return poses, cams


BOARD_REFINED_FILE = "board_refined.yaml"  # calibrate's measured board (docs/formats.md)


def calibration_board(calib_dir: str | Path, dataset_dir: str | Path | None = None,
                      ) -> tuple[Board, str]:
    """The board a check of the calibration in ``calib_dir`` looks for, and where it came
    from: the board the calibration measured (its ``board_refined.yaml``), else the board file
    of the dataset checked (``dataset_dir``'s ``board.yaml``), else that of the dataset the
    calibration was made from (its ``report.json``'s ``dataset``), else the thesis board."""
    calib_dir = Path(calib_dir)
    candidates = [calib_dir / BOARD_REFINED_FILE]
    if dataset_dir is not None:
        candidates.append(Path(dataset_dir) / DATASET_BOARD_FILE)
    try:
        source = json.loads((calib_dir / "report.json").read_text())["dataset"]["path"]
        if isinstance(source, str):
            candidates.append(Path(source) / DATASET_BOARD_FILE)
    except (OSError, ValueError, KeyError, TypeError):
        pass
    for path in candidates:
        if path.is_file():
            return load_board(path), str(path)
    return thesis_board(), "the thesis board (no board file with the calibration or dataset)"
