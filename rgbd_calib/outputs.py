"""Writes a calibration's results into its output folder, atomically.

Everything is first written into a staging folder beside the outputs, then each file is renamed
into place, ``extrinsics.yaml`` last: an interrupted or failed run leaves any earlier result
untouched, and never a half-written file.

``report.json`` (schema: docs/report_schema.md) holds every number the human report shows, so
``rgbd-calib report DIR`` (:func:`rgbd_calib.report.rebuild_report`) rebuilds ``report.html``
from the saved folder alone.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .calibrate import CalibrationResult
from .config import write_config
from .depth import write_fused_ply
from .exports import write_exports
from .geometry import invert_transform
from .report import (
    REPORT_SCHEMA_VERSION,
    dump_report,
    finalize_report,
    histogram_edges_px,
    pair_entry,
    stats,
    write_report_html,
)
from .results import write_extrinsics
from .rig import Rig
from .yamlio import to_builtin

Progress = Callable[[str, int, int], Callable[[int], None]]
FACE_NAMES = {1: "front", -1: "back", 0: "both"}


def _percentiles(values: list[float]) -> dict[str, float] | None:
    """Existing 1.0 statistics block ``{rms, p50, p90, p99, max}`` (px), None when empty."""
    if not values:
        return None
    v = np.asarray(values)
    return {
        "rms": float(np.sqrt(np.mean(v**2))),
        "p50": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "p99": float(np.percentile(v, 99)),
        "max": float(v.max()),
    }


def _final_marker_residuals(
    result: CalibrationResult, rig: Rig
) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
    """Per observation: the RMS reprojection error (px) of each marker through the final
    ``T_cam_board = inv(T_ref_cam) @ T_ref_board`` (the calibration's own prediction, lens
    distortion included), and whether the final estimate used it."""
    boards = result.bundle.T_ref_board if result.bundle else result.posegraph.T_ref_board
    cams = result.extrinsics.cameras
    edge_of = {(r.camera, r.view): r for r in result.posegraph.residuals}
    bundle_out = {(c, v, m) for c, v, m, _ in result.bundle.outliers} if result.bundle else set()
    rows: list[dict[str, Any]] = []
    for o in result.observations:
        edge = edge_of.get((o.camera, o.frame))
        status = (
            "unused"
            if edge is None
            else (
                "stale"
                if edge.stale
                else "outlier"
                if edge.outlier
                else "used"
                if edge.used
                else "unused"
            )
        )
        row: dict[str, Any] = {
            "obs": o,
            "edge": edge,
            "status": status,
            "rms": None,
            "used_markers": np.zeros(0, bool),
        }
        if o.camera in cams and o.frame in boards:
            T_cam_board = invert_transform(cams[o.camera].T_ref_cam) @ boards[o.frame]
            pts = o.object_points.reshape(-1, 3) @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
            uv = rig.cameras[o.camera].project(pts).reshape(-1, 4, 2)
            row["rms"] = np.sqrt(np.mean(np.sum((uv - o.corners_px) ** 2, axis=-1), axis=-1))
            row["used_markers"] = np.array(
                [status == "used" and (o.camera, o.frame, int(m)) not in bundle_out for m in o.ids],
                dtype=bool,
            )
        rows.append(row)
    return rows, boards


def _view_entry(row: dict[str, Any]) -> dict[str, Any]:
    o, edge, rms = row["obs"], row["edge"], row["rms"]
    centre_cam = (
        o.T_cam_board[:3, :3] @ o.object_points.reshape(-1, 3).mean(0) + o.T_cam_board[:3, 3]
    )
    normal_cam = o.T_cam_board[:3, :3] @ np.array([0.0, 0.0, float(o.face or 1)])
    ray = centre_cam / np.linalg.norm(centre_cam)
    tilt = float(np.degrees(np.arccos(np.clip(abs(float(normal_cam @ ray)), 0.0, 1.0))))
    px = o.corners_px.reshape(-1, 2)
    return {
        "camera": o.camera,
        "frame": o.frame,
        "markers": int(o.n_markers),
        "reprojection_rms_px": float(o.reprojection_rms_px),
        "face": FACE_NAMES[int(o.face)],
        "distance_m": float(np.linalg.norm(centre_cam)),
        "tilt_deg": tilt,
        "image_bbox_px": [
            float(px[:, 0].min()),
            float(px[:, 1].min()),
            float(px[:, 0].max()),
            float(px[:, 1].max()),
        ],
        "pnp_sigma_rotation_deg": o.sigma_rotation_deg,
        "pnp_sigma_translation_mm": o.sigma_translation_mm,
        "edge_status": row["status"],
        "edge_translation_mm": None if edge is None else edge.translation_mm,
        "edge_rotation_deg": None if edge is None else edge.rotation_deg,
        "edge_whitened_norm": None if edge is None else edge.whitened_norm,
        "final_reprojection_rms_px": None if rms is None else float(np.sqrt(np.mean(rms**2))),
        "final_reprojection_max_px": None if rms is None else float(rms.max()),
        "excluded_markers": int(np.sum(~row["used_markers"])) if rms is not None else None,
    }


def _board_geometry(result: CalibrationResult) -> dict[str, Any]:
    """Extent of the markers the calibration saw, in the board frame (metres)."""
    if not result.observations:
        return {"markers_seen": 0, "extent_m": None, "thickness_m": None}
    pts = np.concatenate([o.object_points.reshape(-1, 3) for o in result.observations])
    ids = {int(i) for o in result.observations for i in o.ids}
    return {
        "markers_seen": len(ids),
        "extent_m": [
            float(pts[:, 0].min()),
            float(pts[:, 0].max()),
            float(pts[:, 1].min()),
            float(pts[:, 1].max()),
        ],
        "thickness_m": float(max(-pts[:, 2].min(), 0.0)),
    }


def report_dict(
    result: CalibrationResult,
    rig: Rig,
    pairs: list[dict[str, Any]] | None = None,
    depth_scale: dict[str, dict[str, float]] | None = None,
) -> dict[str, Any]:
    """Machine-readable quality metrics (schema documented in docs/report_schema.md).

    ``pairs`` (one dict per registered camera pair: ``cam_a``, ``cam_b`` and any of the pair
    keys of the schema, e.g. ``PairRegistration.to_dict()`` merged with
    ``PairOverlap.to_dict()`` and an ``error_map`` from :func:`rgbd_calib.report.error_map`)
    and ``depth_scale`` (camera -> ``{"factor", "sigma"}``) come from the depth stage; without
    them those keys are empty / null."""
    rows, boards = _final_marker_residuals(result, rig)
    all_res = [r["rms"] for r in rows if r["rms"] is not None]
    edges_px = histogram_edges_px(np.concatenate(all_res) if all_res else np.zeros(0))
    depth_scale = depth_scale or {}
    per_cam: dict[str, Any] = {}
    for name in rig.names:
        obs = [o for o in result.observations if o.camera == name]
        rej = [r for r in result.rejected if r.camera == name]
        mine = [r for r in rows if r["obs"].camera == name and r["rms"] is not None]
        used = np.concatenate([r["rms"][r["used_markers"]] for r in mine]) if mine else []
        every = np.concatenate([r["rms"] for r in mine]) if mine else []
        calibrated = name in result.extrinsics.cameras
        entry: dict[str, Any] = {
            "calibrated": calibrated,
            "views_used": len(obs),
            "views_dropped": len(rej),
            "dropped_reasons": _count([r.reason for r in rej]),
            "pnp_reprojection_rms_px": _percentiles([o.reprojection_rms_px for o in obs]),
            "T_ref_cam": None,
            "translation_m": None,
            "quaternion_xyzw": None,
            "sigma_rotation_deg": None,
            "sigma_translation_mm": None,
            "why_not": None,
        }
        if calibrated:
            entry.update(result.extrinsics.cameras[name].to_dict())
        else:
            entry["why_not"] = result.extrinsics.unconnected.get(name, "unknown")
        if result.bundle is not None:
            res = [r[3] for r in result.bundle.residuals_px if r[0] == name]
            entry["bundle_marker_rms_px"] = _percentiles(res)
            entry["bundle_outlier_markers"] = sum(1 for r in result.bundle.outliers if r[0] == name)
        scale = depth_scale.get(name) or {}
        entry.update(
            {
                "intrinsics": rig.cameras[name].to_dict(),
                "reprojection_px": stats(used),
                "reprojection_all_px": stats(every),
                "reprojection_histogram": {
                    "used": np.histogram(np.clip(used, 0, edges_px[-1]), edges_px)[0].tolist(),
                    "excluded": np.histogram(np.clip(_excluded(mine), 0, edges_px[-1]), edges_px)[
                        0
                    ].tolist(),
                },
                "edge_outliers": sum(
                    1 for r in rows if r["obs"].camera == name and r["status"] == "outlier"
                ),
                "depth_scale_factor": scale.get("factor"),
                "depth_scale_sigma": scale.get("sigma"),
            }
        )
        per_cam[name] = entry

    marker_rows: dict[int, list[float]] = {}
    marker_face: dict[int, str] = {}
    for r in rows:
        if r["rms"] is None:
            continue
        o = r["obs"]
        for mid, value, ok, z in zip(
            o.ids, r["rms"], r["used_markers"], o.object_points[:, :, 2].mean(1)
        ):
            if ok:
                marker_rows.setdefault(int(mid), []).append(float(value))
                marker_face[int(mid)] = "back" if z < -1e-6 else "front"
    pg = result.posegraph
    seen_by: dict[str, list[str]] = {}
    view_px: dict[str, list[np.ndarray]] = {}
    for r in rows:
        if r["status"] == "used":
            seen_by.setdefault(r["obs"].frame, []).append(r["obs"].camera)
            if r["rms"] is not None and r["used_markers"].any():
                view_px.setdefault(r["obs"].frame, []).append(r["rms"][r["used_markers"]])
    report: dict[str, Any] = {
        "schema_version": REPORT_SCHEMA_VERSION,
        "rgbd_calib_version": __version__,
        "reference": result.extrinsics.reference,
        "method": result.config.method,
        "dataset": {
            **result.dataset_summary,
            "path": str(rig.source.parent.resolve()) if rig.source else None,
        },
        "board": _board_geometry(result),
        "cameras": per_cam,
        "unconnected": result.extrinsics.unconnected,
        "pose_graph": {
            "edges": len(pg.residuals),
            "used": len(pg.used_edges),
            "stale": len(pg.stale_edges),
            "outliers": [
                {
                    "camera": pg.residuals[i].camera,
                    "view": pg.residuals[i].view,
                    "whitened_norm": pg.residuals[i].whitened_norm,
                }
                for i in pg.outlier_edges
            ],
        },
        "views": [_view_entry(r) for r in rows],
        "board_views": [
            {
                "frame": f,
                "T_ref_board": np.asarray(T, float).tolist(),
                "cameras": sorted(seen_by.get(f, []), key=rig.names.index),
                "final_reprojection_rms_px": (
                    float(np.sqrt(np.mean(np.concatenate(view_px[f]) ** 2)))
                    if f in view_px
                    else None
                ),
            }
            for f, T in sorted(boards.items())
        ],
        "markers": [
            {
                "id": m,
                "face": marker_face[m],
                "observations": len(v),
                "rms_px": float(np.sqrt(np.mean(np.square(v)))),
                "max_px": float(max(v)),
            }
            for m, v in sorted(marker_rows.items())
        ],
        "reprojection_histogram_edges_px": edges_px.tolist(),
        "dropped_views": [
            {
                "camera": r.camera,
                "frame": r.frame,
                "reason": r.reason,
                "markers": int(r.n_markers),
                "detail": r.detail,
            }
            for r in result.rejected
        ],
        "pairs": [pair_entry(p) for p in (pairs or [])],
        "timings_s": result.timings_s,
    }
    if result.bundle is not None:
        report["bundle"] = {
            "pixel_sigma_estimated": result.bundle.pixel_sigma_estimated,
            "iterations": result.bundle.iterations,
            "markers": len(result.bundle.residuals_px),
            "outlier_markers": [
                {"camera": c, "view": v, "marker": m, "rms_px": r}
                for c, v, m, r in result.bundle.outliers
            ],
        }
    return finalize_report(to_builtin(report))


def _excluded(rows: list[dict[str, Any]]) -> np.ndarray:
    parts = [r["rms"][~r["used_markers"]] for r in rows]
    return np.concatenate(parts) if parts else np.zeros(0)


def _count(items: list[str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for i in items:
        out[i] = out.get(i, 0) + 1
    return out


def write_outputs(
    result: CalibrationResult,
    rig: Rig,
    out_dir: Path,
    fused_ply: Path | None = None,
    pairs: list[dict[str, Any]] | None = None,
    depth_scale: dict[str, dict[str, float]] | None = None,
    progress: Progress | None = None,
) -> list[Path]:
    """Write extrinsics.yaml, report.json, report.html, config_resolved.yaml and exports/
    into out_dir (and fused.ply, copied from ``fused_ply`` when the depth stage made one).

    Without ``fused_ply`` an older ``out_dir/fused.ply`` is removed (it would belong to another
    run) and the report previews the cloud from the dataset's depth frames."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stage = out_dir / f".staging-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        if result.depth is not None:
            pairs = pairs if pairs is not None else result.depth.pairs
            depth_scale = depth_scale if depth_scale is not None else (
                result.depth.depth_scale_dict())
            if fused_ply is None and result.depth.clouds:
                T_ref_cam = {c: e.T_ref_cam for c, e in result.extrinsics.cameras.items()}
                pts, cols, idx, names = result.depth.fused(
                    T_ref_cam, result.config.depth.fused_voxel_m)
                write_fused_ply(stage / "fused.ply", pts, cols, idx, names)
        report = report_dict(result, rig, pairs, depth_scale)
        (stage / "report.json").write_text(dump_report(report))
        if fused_ply is not None:
            shutil.copyfile(fused_ply, stage / "fused.ply")
        write_report_html(report, stage, progress=progress)
        write_config(result.config, stage / "config_resolved.yaml")
        boards = result.bundle.T_ref_board if result.bundle else result.posegraph.T_ref_board
        write_exports(result.extrinsics, stage, rig=rig, board_poses=boards)
        write_extrinsics(result.extrinsics, stage / "extrinsics.yaml")
        if not (stage / "fused.ply").exists():
            (out_dir / "fused.ply").unlink(missing_ok=True)
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
