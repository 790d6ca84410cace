"""Writes a calibration's results into its output folder, atomically.

Everything is first written into a staging folder beside the outputs, then each file is renamed
into place, ``extrinsics.yaml`` last: an interrupted or failed run leaves any earlier result
untouched, and never a half-written file.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from . import __version__
from .calibrate import CalibrationResult
from .exports import write_exports
from .results import write_extrinsics
from .rig import Rig
from .yamlio import to_builtin

REPORT_SCHEMA_VERSION = "1.0"


def _percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {}
    v = np.asarray(values)
    return {"rms": float(np.sqrt(np.mean(v**2))), "p50": float(np.median(v)),
            "p90": float(np.percentile(v, 90)), "p99": float(np.percentile(v, 99)),
            "max": float(v.max())}


def report_dict(result: CalibrationResult, rig: Rig) -> dict[str, Any]:
    """Machine-readable quality metrics (schema documented in docs/report_schema.md)."""
    per_cam: dict[str, Any] = {}
    for name in rig.names:
        obs = [o for o in result.observations if o.camera == name]
        rej = [r for r in result.rejected if r.camera == name]
        entry: dict[str, Any] = {
            "calibrated": name in result.extrinsics.cameras,
            "views_used": len(obs),
            "views_dropped": len(rej),
            "dropped_reasons": _count([r.reason for r in rej]),
            "pnp_reprojection_rms_px": _percentiles([o.reprojection_rms_px for o in obs]),
        }
        if name in result.extrinsics.cameras:
            entry.update(result.extrinsics.cameras[name].to_dict())
        else:
            entry["why_not"] = result.extrinsics.unconnected.get(name, "unknown")
        if result.bundle is not None:
            res = [r[3] for r in result.bundle.residuals_px if r[0] == name]
            entry["bundle_marker_rms_px"] = _percentiles(res)
            entry["bundle_outlier_markers"] = sum(1 for r in result.bundle.outliers
                                                  if r[0] == name)
        per_cam[name] = entry
    pg = result.posegraph
    report: dict[str, Any] = {
        "schema_version": REPORT_SCHEMA_VERSION,
        "rgbd_calib_version": __version__,
        "reference": result.extrinsics.reference,
        "method": result.config.method,
        "dataset": result.dataset_summary,
        "cameras": per_cam,
        "unconnected": result.extrinsics.unconnected,
        "pose_graph": {
            "edges": len(pg.residuals),
            "used": len(pg.used_edges),
            "stale": len(pg.stale_edges),
            "outliers": [{"camera": pg.residuals[i].camera, "view": pg.residuals[i].view,
                          "whitened_norm": pg.residuals[i].whitened_norm}
                         for i in pg.outlier_edges],
        },
        "views": [{"camera": o.camera, "frame": o.frame, "markers": o.n_markers,
                   "reprojection_rms_px": o.reprojection_rms_px} for o in result.observations],
        "dropped_views": [{"camera": r.camera, "frame": r.frame, "reason": r.reason}
                          for r in result.rejected],
        "timings_s": result.timings_s,
    }
    if result.bundle is not None:
        report["bundle"] = {
            "pixel_sigma_estimated": result.bundle.pixel_sigma_estimated,
            "iterations": result.bundle.iterations,
            "markers": len(result.bundle.residuals_px),
            "outlier_markers": [{"camera": c, "view": v, "marker": m, "rms_px": r}
                                for c, v, m, r in result.bundle.outliers],
        }
    return to_builtin(report)


def _count(items: list[str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for i in items:
        out[i] = out.get(i, 0) + 1
    return out


def write_outputs(result: CalibrationResult, rig: Rig, out_dir: Path) -> list[Path]:
    """Write extrinsics.yaml, report.json, config_resolved.yaml and exports/ into out_dir."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stage = out_dir / f".staging-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        (stage / "report.json").write_text(json.dumps(report_dict(result, rig), indent=1))
        (stage / "config_resolved.yaml").write_text(
            yaml.safe_dump(to_builtin(result.config.model_dump()), sort_keys=False))
        boards = result.bundle.T_ref_board if result.bundle else result.posegraph.T_ref_board
        write_exports(result.extrinsics, stage, rig=rig, board_poses=boards)
        write_extrinsics(result.extrinsics, stage / "extrinsics.yaml")
        written = []
        for path in sorted(stage.rglob("*"), key=lambda p: p.name == "extrinsics.yaml"):
            if path.is_dir():
                continue
            target = out_dir / path.relative_to(stage)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, target)
            written.append(target)
        return written
    finally:
        shutil.rmtree(stage, ignore_errors=True)
