"""Builds the report dict: the primary numbers of a calibration result
(:func:`report_dict`), then the sections derived from them (:func:`finalize_report`).

    CalibrationResult --report_dict--> primary numbers (schema: docs/report_schema.md)
        --finalize_report--> + co-visibility, coverage, summary, warnings, next steps
"""

from __future__ import annotations

import math
import re
from typing import TYPE_CHECKING, Any

import numpy as np

from ... import __version__
from ...core.geometry import invert_transform, move_rows, transform_points
from ...core.yamlio import to_builtin
from .findings import findings
from .findings_base import actionable
from .numbers import histogram_edges_px, median_or_none, stats
from .schema import (
    COVERAGE_GRID,
    PAIR_SCHEMA,
    REGION_MIN,
    REGIONS,
    REPORT_SCHEMA_VERSION,
    finite_or_null,
    view_in_estimate,
)

if TYPE_CHECKING:
    from ...model.results import Extrinsics
    from ...model.rig import Rig
    from ...pipelines.calibrate import CalibrationResult
    from ...solve.bundle_problem import BundleResult
    from ...solve.posegraph import PoseGraphResult

FACE_NAMES = {1: "front", -1: "back", 0: "both"}


def face_name(face: int, multiface: bool) -> str:
    """A view's or marker's face in report.json: front / back / both on a flat board;
    ``face<k>`` (face k of the board file, 1-based) / ``several`` on a multi-face target."""
    if multiface:
        return "several" if face == 0 else f"face{int(face)}"
    return FACE_NAMES[int(face)]


# ----------------------------------------------------------------------------- primary numbers
def report_dict(
    result: CalibrationResult,
    rig: Rig,
    pairs: list[dict[str, Any]] | None = None,
    depth_scale: dict[str, dict[str, float]] | None = None,
) -> dict[str, Any]:
    """Machine-readable quality metrics (schema documented in docs/report_schema.md).

    ``pairs`` (one dict per registered camera pair: ``cam_a``, ``cam_b`` and any of the pair
    keys of the schema, e.g. ``PairRegistration.to_dict()`` merged with
    ``PairOverlap.to_dict()`` and an ``error_map`` from :func:`rgbd_calib.outputs.report.error_map`)
    and ``depth_scale`` (camera -> ``{"factor", "sigma"}``) come from the depth stage; without
    them those keys are empty / null."""
    rows, boards = _final_marker_residuals(result, rig)
    all_res = [r["rms"] for r in rows if r["rms"] is not None]
    edges_px = histogram_edges_px(np.concatenate(all_res) if all_res else np.zeros(0))
    depth_scale = depth_scale or {}
    report: dict[str, Any] = {
        "schema_version": REPORT_SCHEMA_VERSION,
        "rgbd_calib_version": __version__,
        "reference": result.extrinsics.reference,
        "method": result.config.method,
        "dataset": {
            **result.dataset_summary,
            "path": str(rig.source.parent.resolve()) if rig.source else None,
        },
        "board": {**_board_geometry(result), **board_refined_entry(result)},
        "cameras": {
            name: _camera_entry(result, rig, name, rows, edges_px, depth_scale.get(name) or {})
            for name in rig.names
        },
        "unconnected": result.extrinsics.unconnected,
        "pose_graph": _pose_graph_entry(result.posegraph, result.model_error_factor),
        "views": [_view_entry(r, result.board) for r in rows],
        "board_views": _board_view_entries(rows, boards, rig.names),
        "markers": _marker_entries(rows, result.board),
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
        "motion": [m.to_dict() for m in result.motion],
        "pairs": [pair_entry(p) for p in (pairs or [])],
        "timings_s": result.timings_s,
    }
    if getattr(result, "set_selection", None) is not None:
        report["frame_selection"] = result.set_selection.to_dict()
    if result.bundle is not None:
        report["bundle"] = _bundle_entry(result.bundle)
        if result.self_calibration is not None:
            report["bundle"]["self_calibration"] = result.self_calibration.to_dict()
    if getattr(result, "depth", None) is not None:
        report["depth"] = result.depth.status_dict()
        if result.depth.depth_models:
            far = result.depth.beyond_board
            report["depth_models"] = {c: _depth_model_entry(f, far.get(c))
                                      for c, f in result.depth.depth_models.items()}
        if result.depth.agreement is not None:
            report["fused_agreement"] = result.depth.agreement.to_dict()
    return finalize_report(to_builtin(report))


def _depth_model_entry(fit: Any, far: Any = None) -> dict[str, Any]:
    """report.json ``depth_models.<camera>``: the chosen terms, their parameters and sigmas, the
    board-plane residuals by distance band before and after the model, the board views they
    were fitted on (``depth.model_fit.model_terms: auto`` frees every term from 15), and (``far``, a
    :class:`~rgbd_calib.depth.depth_model_fit.BeyondBoard`) how much of the camera's cloud lies
    beyond the board's depths and how well its depth is known there, and (``held_out``) how
    well the model predicts board views it was not fitted to, against the raw depth."""
    d = fit.to_dict()
    entry = {"terms": d["model"]["terms"],
             "parameters": {p: d["model"]["parameters"][p] for p in d["model"]["sigmas"]},
             "sigmas": d["model"]["sigmas"], "bands": d["bands"], "n_views": d["n_views"]}
    if "held_out" in d:
        entry["held_out"] = d["held_out"]
    if far is not None:
        entry["beyond_board"] = far.to_dict()
    return entry


def depth_only_report_dict(
    extrinsics: Extrinsics,
    rig: Rig,
    dataset_summary: dict[str, Any],
    refine: dict[str, Any],
    pairs: list[dict[str, Any]],
    depth_status: dict[str, Any],
    depth_scale: dict[str, dict[str, float | None]] | None = None,
    timings_s: dict[str, float] | None = None,
) -> dict[str, Any]:
    """``report.json`` of a depth-only refinement (``rgbd-calib refine``, method ``depth``):
    the same schema as a calibration's, the board sections empty (no view, board pose or
    marker; ``board`` and ``pose_graph`` zero / null), plus ``refine``: where it started
    (``init``), how (``registration``, ``fix_others``), its ``outcome`` and ``message`` (the
    ``verdict`` and ``message`` of refine_report.json), the cameras found moved since ``init``
    (``moved_since_init``, ``--fix-others`` only) and per camera its move from ``init`` and
    where its depth-scale factor came from (``refine["cameras"]``).

    ``pairs`` and ``depth_scale`` (camera -> ``{"factor", "sigma"}``, sigma may be None) as
    for :func:`report_dict`; ``depth_status`` is report.json ``depth``."""
    edges_px = histogram_edges_px(np.zeros(0))
    zeros = [0] * (len(edges_px) - 1)
    depth_scale = depth_scale or {}
    cameras = {}
    for name in rig.names:
        scale = depth_scale.get(name) or {}
        cameras[name] = {
            "calibrated": name in extrinsics.cameras,
            "views_used": 0,
            "views_dropped": 0,
            "dropped_reasons": {},
            "pnp_reprojection_rms_px": None,
            **_pose_entry(extrinsics, name, why_not=f"not in {refine['init']}"),
            "intrinsics": rig.cameras[name].to_dict(),
            "reprojection_px": None,
            "reprojection_all_px": None,
            "reprojection_histogram": {"used": list(zeros), "excluded": list(zeros)},
            "edge_outliers": 0,
            "depth_scale_factor": scale.get("factor"),
            "depth_scale_sigma": scale.get("sigma"),
        }
    report: dict[str, Any] = {
        "schema_version": REPORT_SCHEMA_VERSION,
        "rgbd_calib_version": __version__,
        "reference": extrinsics.reference,
        "method": "depth",
        "dataset": {
            **dataset_summary,
            "path": str(rig.source.parent.resolve()) if rig.source else None,
        },
        "board": {"markers_seen": 0, "extent_m": None, "thickness_m": None},
        "cameras": cameras,
        "unconnected": {c: cameras[c]["why_not"] for c in rig.names
                        if not cameras[c]["calibrated"]},
        "pose_graph": {"edges": 0, "used": 0, "stale": 0, "outliers": [], "model_error": []},
        "views": [],
        "board_views": [],
        "markers": [],
        "reprojection_histogram_edges_px": edges_px.tolist(),
        "dropped_views": [],
        "pairs": [pair_entry(p) for p in pairs],
        "timings_s": dict(timings_s or {}),
        "depth": depth_status,
        "refine": refine,
    }
    return finalize_report(to_builtin(report))


def _edge_status(edge: Any) -> str:
    """How the final estimate treated a view's pose-graph edge (None: the view has none)."""
    if edge is None:
        return "unused"
    if edge.stale:
        return "stale"
    if edge.outlier:
        return "outlier"
    return "used" if edge.used else "unused"


def _final_marker_residuals(
    result: CalibrationResult, rig: Rig
) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
    """Per observation: the RMS reprojection error (px) of each marker through the final
    ``T_cam_board = inv(T_ref_cam) @ T_ref_board`` (the calibration's own prediction, lens
    distortion included), and whether the final estimate used it: the bundle adjustment's
    markers when there is one (with refined intrinsics it also solves views the pose graph
    left out, see ``solve.ladder.unsolved_views``), else the pose graph's used views."""
    boards = result.bundle.T_ref_board if result.bundle else result.posegraph.T_ref_board
    cams = result.extrinsics.cameras
    edge_of = {(r.camera, r.view): r for r in result.posegraph.residuals}
    in_bundle = ({(c, v, m) for c, v, m, _ in result.bundle.residuals_px}
                 if result.bundle else None)
    model = result.bundle.board if result.bundle else None
    T_front_back = model.T_front_back if model is not None and not model.held else None
    board = result.board
    face_moves = {}  # a multi-face target's faces where the bundle found them (board frame)
    for f in (result.bundle.faces if result.bundle else ()):
        if not f.held:
            face_moves[f.label] = f.T_board_face @ invert_transform(f.T_nominal)
    rows: list[dict[str, Any]] = []
    for o in result.observations:
        edge = edge_of.get((o.camera, o.frame))
        status = _edge_status(edge)
        row: dict[str, Any] = {
            "obs": o,
            "edge": edge,
            "status": status,
            "rms": None,
            "used_markers": np.zeros(0, bool),
        }
        if o.camera in cams and o.frame in boards:
            T_cam_board = invert_transform(cams[o.camera].T_ref_cam) @ boards[o.frame]
            P_b = o.object_points.reshape(-1, 3)
            moves = []  # (rows, board-frame move): the faces where the bundle found them
            if T_front_back is not None:
                moves.append((P_b[:, 2] < -model.thickness_m / 2, T_front_back))
            if face_moves and board is not None:
                rows4 = np.repeat(board.faces_of(o.ids), 4)
                moves += [(rows4 == label, C) for label, C in face_moves.items()]
            P_b = move_rows(P_b, moves)
            clock = result.bundle.time if result.bundle else None
            if clock is not None:  # each corner where the board was at its row's time
                uv = clock.project(o.camera, o.frame, cams[o.camera].T_ref_cam, boards[o.frame],
                                   _final_model(result, rig, o.camera), P_b,
                                   o.corners_px.reshape(-1, 2)[:, 1]).reshape(-1, 4, 2)
            else:
                pts = transform_points(T_cam_board, P_b)
                uv = _final_model(result, rig, o.camera).project(pts).reshape(-1, 4, 2)
            row["rms"] = np.sqrt(np.mean(np.sum((uv - o.corners_px) ** 2, axis=-1), axis=-1))
            row["used_markers"] = np.array(
                [status == "used" if in_bundle is None else (o.camera, o.frame, int(m)) in in_bundle
                 for m in o.ids],
                dtype=bool,
            )
        rows.append(row)
    return rows, boards


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


def _camera_entry(
    result: CalibrationResult,
    rig: Rig,
    name: str,
    rows: list[dict[str, Any]],
    edges_px: np.ndarray,
    scale: dict[str, float],
) -> dict[str, Any]:
    """``cameras.<name>``: views, extrinsics (or why not), reprojection statistics and
    histograms over ``edges_px``, depth scale ``{"factor", "sigma"}`` (may be empty)."""
    obs = [o for o in result.observations if o.camera == name]
    rej = [r for r in result.rejected if r.camera == name]
    mine = [r for r in rows if r["obs"].camera == name and r["rms"] is not None]
    used = np.concatenate([r["rms"][r["used_markers"]] for r in mine]) if mine else []
    every = np.concatenate([r["rms"] for r in mine]) if mine else []
    entry: dict[str, Any] = {
        "calibrated": name in result.extrinsics.cameras,
        "views_used": len(obs),
        "views_dropped": len(rej),
        "dropped_reasons": _count([r.reason for r in rej]),
        "pnp_reprojection_rms_px": _percentiles([o.reprojection_rms_px for o in obs]),
        **_pose_entry(result.extrinsics, name),
    }
    if result.bundle is not None:
        res = [r[3] for r in result.bundle.residuals_px if r[0] == name]
        entry["bundle_marker_rms_px"] = _percentiles(res)
        entry["bundle_outlier_markers"] = sum(1 for r in result.bundle.outliers if r[0] == name)
        if name in result.bundle.intrinsics:
            entry["intrinsics_refined"] = intrinsics_change(
                rig.cameras[name], result.bundle.intrinsics[name],
                result.bundle.intrinsics_sigma.get(name, {}),
                result.bundle.intrinsics_prior_sigma.get(name, {}))
    initial = getattr(result, "initial_intrinsics", {})
    if name in initial:
        entry["intrinsics_initial"] = initial[name].to_dict()
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
    return entry


def _pose_entry(extrinsics: Extrinsics, name: str, why_not: str = "unknown") -> dict[str, Any]:
    """The extrinsics keys of ``cameras.<name>`` (``T_ref_cam`` ... ``why_not``): the camera's
    pose and sigmas, or nulls and why it has none (``extrinsics.unconnected``, else
    ``why_not``)."""
    entry: dict[str, Any] = {
        "T_ref_cam": None,
        "translation_m": None,
        "quaternion_xyzw": None,
        "sigma_rotation_deg": None,
        "sigma_translation_mm": None,
        "why_not": None,
    }
    if name in extrinsics.cameras:
        entry.update(extrinsics.cameras[name].to_dict())
    else:
        entry["why_not"] = extrinsics.unconnected.get(name, why_not)
    return entry


def _final_model(result: CalibrationResult, rig: Rig, camera: str) -> Any:
    """The camera model of the final estimate: the refined intrinsics when the bundle
    adjustment refined them, else the rig.yaml ones."""
    if result.bundle is not None and camera in result.bundle.intrinsics:
        return result.bundle.intrinsics[camera]
    return rig.cameras[camera]


def intrinsics_change(prior: Any, refined: Any, sigma: dict[str, float],
                      prior_sigma: dict[str, float]) -> dict[str, Any]:
    """``cameras.<name>.intrinsics_refined``: per refined parameter its rig.yaml ``prior``,
    the prior's sigma ``prior_sigma``, the ``refined`` value, its marginal ``sigma``,
    ``change`` (refined - prior, px for fx fy cx cy) and ``change_pct`` (percent of the
    prior; null when the prior is 0)."""
    before, after = prior.parameters, refined.parameters
    out = {}
    for name in sigma:
        p, r = float(before.get(name, 0.0)), float(after[name])
        out[name] = {"prior": p, "prior_sigma": prior_sigma.get(name), "refined": r,
                     "sigma": sigma[name], "change": r - p,
                     "change_pct": 100.0 * (r - p) / abs(p) if p != 0 else None}
    return out


def _excluded(rows: list[dict[str, Any]]) -> np.ndarray:
    parts = [r["rms"][~r["used_markers"]] for r in rows]
    return np.concatenate(parts) if parts else np.zeros(0)


def _count(items: list[str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for i in items:
        out[i] = out.get(i, 0) + 1
    return out


def _view_entry(row: dict[str, Any], board=None) -> dict[str, Any]:
    o, edge, rms = row["obs"], row["edge"], row["rms"]
    multiface = board is not None and board.is_multiface
    centre_cam = (
        o.T_cam_board[:3, :3] @ o.object_points.reshape(-1, 3).mean(0) + o.T_cam_board[:3, 3]
    )
    normal_b = (board.face_normal(int(o.face or board.reference_face)) if multiface
                else np.array([0.0, 0.0, float(o.face or 1)]))
    normal_cam = o.T_cam_board[:3, :3] @ normal_b
    ray = centre_cam / np.linalg.norm(centre_cam)
    tilt = float(np.degrees(np.arccos(np.clip(abs(float(normal_cam @ ray)), 0.0, 1.0))))
    px = o.corners_px.reshape(-1, 2)
    return {
        "camera": o.camera,
        "frame": o.frame,
        "markers": int(o.n_markers),
        "reprojection_rms_px": float(o.reprojection_rms_px),
        "face": face_name(int(o.face), multiface),
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
    corners = np.concatenate([o.object_points for o in result.observations])
    side_m = float(np.linalg.norm(np.diff(corners[:, [0, 1]], axis=1), axis=-1).mean())
    charuco = result.board is not None and result.board.pattern is not None
    lengths = ({"marker_length_m": side_m} if not charuco else  # quads: chessboard squares
               {"marker_length_m": result.board.printed_lengths[0], "square_length_m": side_m})
    return {
        "markers_seen": len(ids),
        **lengths,
        "extent_m": [
            float(pts[:, 0].min()),
            float(pts[:, 0].max()),
            float(pts[:, 1].min()),
            float(pts[:, 1].max()),
        ],
        "thickness_m": float(max(-pts[:, 2].min(), 0.0)),
        **({"print_scale_sigma": result.board.print_scale_sigma}
           if result.board is not None else {}),
    }


def board_refined_entry(result: CalibrationResult) -> dict[str, Any]:
    """``board.refined`` when the bundle adjustment refined the board (``bundle.board:
    refine``): the back sheet's offset (mm, board x right / y up seen from the front) and
    rotation (deg, counter-clockwise seen from the front) at the centre of the back-marker
    grid, the thickness and its change (mm), their marginal sigmas, and why it was held."""
    model = result.bundle.board if result.bundle is not None else None
    faces = result.bundle.faces if result.bundle is not None else ()
    if faces:
        return {"refined_faces": [f.to_dict() for f in faces]}
    if model is None:
        return {}
    held = bool(model.held)
    offset = model.offset_mm
    sig = model.sigmas
    return {"refined": {
        "held": model.held or None,
        "offset_mm": None if held else [float(offset[0]), float(offset[1])],
        "rotation_deg": None if held else model.rotation_deg,
        "thickness_mm": None if held else model.thickness_mm,
        "thickness_change_mm": None if held else model.thickness_mm - model.thickness_m * 1000,
        "sigmas": None if held else {
            "offset_mm": [sig["offset_x_mm"], sig["offset_y_mm"]],
            "rotation_deg": sig["rotation_deg"],
            "thickness_mm": sig["thickness_mm"],
        },
        "T_front_back": model.T_front_back,
    }}


def _pose_graph_entry(pg: PoseGraphResult, factors: dict[str, float]) -> dict[str, Any]:
    """The edges, their outliers, and the cameras kept with a model error: the factor their
    final covariance was scaled by (``factors``, else the pose graph's own)."""
    return {
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
        "model_error": [
            {
                "camera": c,
                "edges": m.edges,
                "outliers_before": m.outliers_before,
                "translation_mm": m.translation_mm,
                "rotation_deg": m.rotation_deg,
                "variance_factor": float(factors.get(c, m.variance_factor)),
                "sigma_factor": float(np.sqrt(factors.get(c, m.variance_factor))),
            }
            for c, m in pg.model_error.items()
        ],
        "view_floor": _view_floor_entry(pg.stats.get("view_floor")),
    }


def _view_floor_entry(floor: dict[str, Any] | None) -> dict[str, Any] | None:
    """``pose_graph.view_floor``: the per-view model-error floor ``pose.model_error_px: auto``
    estimated (None when the config fixed it)."""
    if floor is None:
        return None
    ratio = floor["misfit_ratio"]
    return {"model_error_px": float(floor["model_error_px"]),
            "misfit_ratio": float(ratio) if np.isfinite(ratio) else None,
            "edges": int(floor["edges"])}


def _board_view_entries(
    rows: list[dict[str, Any]], boards: dict[str, np.ndarray], names: list[str]
) -> list[dict[str, Any]]:
    """``board_views[]``: every solved board pose, the cameras whose edge the estimate used
    and the RMS over those views' used markers."""
    seen_by: dict[str, list[str]] = {}
    view_px: dict[str, list[np.ndarray]] = {}
    for r in rows:
        if r["used_markers"].any():
            seen_by.setdefault(r["obs"].frame, []).append(r["obs"].camera)
            view_px.setdefault(r["obs"].frame, []).append(r["rms"][r["used_markers"]])
    return [
        {
            "frame": f,
            "T_ref_board": np.asarray(T, float).tolist(),
            "cameras": sorted(seen_by.get(f, []), key=names.index),
            "final_reprojection_rms_px": (
                float(np.sqrt(np.mean(np.concatenate(view_px[f]) ** 2))) if f in view_px else None
            ),
        }
        for f, T in sorted(boards.items())
    ]


def _marker_entries(rows: list[dict[str, Any]], board=None) -> list[dict[str, Any]]:
    """``markers[]``: per marker id, the RMS and max of its used final reprojection errors."""
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
                marker_face[int(mid)] = (
                    face_name(int(board.faces[board.index_of[int(mid)]]), True)
                    if board is not None and board.is_multiface
                    else "back" if z < -1e-6 else "front")
    return [
        {
            "id": m,
            "face": marker_face[m],
            "observations": len(v),
            "rms_px": float(np.sqrt(np.mean(np.square(v)))),
            "max_px": float(max(v)),
        }
        for m, v in sorted(marker_rows.items())
    ]


def _bundle_entry(bundle: BundleResult) -> dict[str, Any]:
    entry = {
        "pixel_sigma_estimated": bundle.pixel_sigma_estimated,
        "iterations": bundle.iterations,
        "markers": len(bundle.residuals_px),
        "outlier_markers": [
            {"camera": c, "view": v, "marker": m, "rms_px": r} for c, v, m, r in bundle.outliers
        ],
    }
    if bundle.time is not None:
        entry["time"] = bundle.time.to_dict()
    if bundle.edge_offset:  # what the corner residuals read of each detector's edge offset
        entry["edge_offset"] = {c: e.to_dict() for c, e in sorted(bundle.edge_offset.items())}
    if bundle.corner_noise is not None:  # the corners' centre and shape noise, read
        n = bundle.corner_noise
        entry["corner_noise"] = {"shape_sigma_px": n.sigma_px,
                                 "centre_sigma_px": n.centre_sigma_px / 2,
                                 "centre_ratio": n.centre_ratio,
                                 "scale_sigma_ppm": bundle.scale_sigma_ppm}
    if bundle.run_correlation:  # consecutive frames: their sigmas' variance factors
        entry["run_correlation"] = {c: {"rho": r.rho, "pairs": r.pairs, "factor": r.factor}
                                    for c, r in sorted(bundle.run_correlation.items())}
    return entry


def pair_entry(pair: dict[str, Any]) -> dict[str, Any]:
    """One ``pairs[]`` entry from a depth-stage dict (``PairRegistration.to_dict()`` merged
    with ``PairOverlap.to_dict()`` and an ``error_map``): the schema's keys, null when absent."""
    out: dict[str, Any] = {}
    for key in PAIR_SCHEMA:
        value = pair.get(key)
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        if isinstance(value, (np.generic,)):
            value = value.item()
        out[key] = value
    out["cam_a"], out["cam_b"] = str(pair["cam_a"]), str(pair["cam_b"])
    if "agrees" not in pair:
        out["agrees"] = agrees_from_reason(pair)
    if "rejected_by" not in pair:
        out["rejected_by"] = kinds_from_reason(pair)
    else:
        out["rejected_by"] = [str(k) for k in pair["rejected_by"] or ()]
    return out


# A reason clause's first words -> its kind (rgbd_calib.depth.registration.REJECTION_KINDS),
# for pairs written before schema 1.18 named the kind; anything else is a failed registration.
_CLAUSE_KINDS = (
    (r"\d+ correspondences <", "correspondences"),
    (r"fitness ", "fitness"),
    (r"point-to-plane RMSE", "rmse"),
    (r"residuals ", "residuals"),
    (r"poorly conditioned", "conditioning"),
    (r"\d+ surface patches", "patches"),
    (r"moved .* from the initial guess", "correction"),
    (r"moved .* from the check's estimate", "fix_reach"),
    (r"no significant improvement", "not_significant"),
    (r"information matrix not finite", "information"),
    (r"ICP moved .* beyond their uncertainty", "beyond_extrinsics"),
)


def kinds_from_reason(pair: dict[str, Any]) -> list[str]:
    """``pairs[].rejected_by`` of a pair written before schema 1.18, from its ``reason``'s
    clauses (an accepted pair: none)."""
    reason = str(pair.get("reason") or "")
    if not reason:
        return []
    if reason.startswith("not used:"):
        return ["not_used"]
    kinds = [next((k for pattern, k in _CLAUSE_KINDS if re.match(pattern, clause.strip())),
                  "failed") for clause in reason.split(";")]
    return list(dict.fromkeys(kinds))


def agrees_from_reason(pair: dict[str, Any]) -> bool:
    """``pairs[].agrees`` of a pair written before schema 1.9, from its ``reason``: the
    significance test (:func:`rgbd_calib.depth.registration.register_pair`) is its only reason."""
    return pair.get("accepted") is False and kinds_from_reason(pair) == ["not_significant"]


def error_map(
    pixels_uv: np.ndarray, distance_m: np.ndarray, width: int, height: int, cell_px: int = 16
) -> dict[str, Any]:
    """Coarse overlap error map of camera a for ``pairs[].error_map``: the median signed
    point-to-plane distance (mm) per ``cell_px`` image cell, from a's point pixels ``(N,2)``
    ``(u, v)`` and their distances (m, NaN = no partner; e.g. ``depth.overlap_error``)."""
    cols, rows = math.ceil(width / cell_px), math.ceil(height / cell_px)
    uv = np.asarray(pixels_uv, dtype=int).reshape(-1, 2)
    d = np.asarray(distance_m, dtype=float).reshape(-1)
    ok = np.isfinite(d)
    cell = (uv[ok, 1] // cell_px) * cols + uv[ok, 0] // cell_px
    values: list[float | None] = [None] * (cols * rows)
    for c in np.unique(cell):
        values[int(c)] = float(np.median(d[ok][cell == c]) * 1000.0)
    return {
        "width": int(width),
        "height": int(height),
        "cols": cols,
        "rows": rows,
        "values_mm": values,
    }


# ----------------------------------------------------------------------------- derived sections
def finalize_report(report: dict[str, Any]) -> dict[str, Any]:
    """Add (or recompute) the derived sections of a report from its primary numbers:
    ``summary``, ``covisibility``, ``cameras.*.coverage``, ``warnings`` and ``next_steps``.

    Pure and idempotent: ``finalize_report(json.loads(dump_report(r))) == r`` for a finalized
    ``r``, which is what makes a rebuilt ``report.json`` byte-identical."""
    report = finite_or_null(report)
    cams: dict[str, dict[str, Any]] = report["cameras"]
    names = list(cams)
    used_views = [v for v in report["views"] if v["edge_status"] == "used"]
    covis = _covisibility(names, used_views)
    report["covisibility"] = {"cameras": names, "views": covis.tolist()}
    estimated = [v for v in report["views"] if view_in_estimate(v)]
    for name, cam in cams.items():
        cam["coverage"] = _camera_coverage(name, cams, estimated, covis)
    report["summary"] = _summary(report)
    found = findings(report)
    report["warnings"] = found
    severities = {w["severity"] for w in found}
    report["summary"]["verdict"] = (
        "poor" if "error" in severities else "check" if "warning" in severities else "good"
    )
    # a finding with nothing to do (an info that explains the result) is not a step
    report["next_steps"] = list(dict.fromkeys(w["advice"] for w in found if actionable(w)))
    return report


def _covisibility(names: list[str], used_views: list[dict[str, Any]]) -> np.ndarray:
    """Board views both cameras contributed to the estimate, (n, n) in ``names`` order (the
    diagonal: each camera's used views)."""
    index = {c: i for i, c in enumerate(names)}
    covis = np.zeros((len(names), len(names)), dtype=int)
    by_frame: dict[str, list[str]] = {}
    for v in used_views:
        by_frame.setdefault(v["frame"], []).append(v["camera"])
    for members in by_frame.values():
        for a in members:
            for b in members:
                covis[index[a], index[b]] += 1
    return covis


def _camera_coverage(
    name: str,
    cams: dict[str, dict[str, Any]],
    used_views: list[dict[str, Any]],
    covis: np.ndarray,
) -> dict[str, Any]:
    """``cameras.<name>.coverage``: where, how far and how tilted the board was in the
    camera's views the final estimate used (:func:`view_in_estimate`), and the calibrated
    camera it shares most pose-graph views with (``covis``)."""
    names = list(cams)
    index = {c: i for i, c in enumerate(names)}
    cam = cams[name]
    mine = [v for v in used_views if v["camera"] == name]
    fraction, missing = _coverage(mine, cam["intrinsics"]) if mine else (0.0, [])
    shared = {
        other: int(covis[index[name], index[other]])
        for other in names
        if other != name and cams[other]["calibrated"]
    }
    best = max(shared, key=lambda k: (shared[k], -index[k])) if shared else None
    best = best if best and shared[best] > 0 else None
    faces = {f: sum(1 for v in mine if v["face"] == f) for f in ("front", "back", "both")}
    if any(v["face"].startswith("face") or v["face"] == "several" for v in mine):
        # a multi-face target: views of one face count as front, of several as both
        faces = {"front": sum(1 for v in mine if v["face"].startswith("face")), "back": 0,
                 "both": sum(1 for v in mine if v["face"] == "several")}
    return {
        "image_fraction": fraction,
        "missing_regions": missing,
        "distance_m": _range([v["distance_m"] for v in mine]),
        "tilt_deg": _range([v["tilt_deg"] for v in mine]),
        "faces": faces,
        "max_shared_views": shared[best] if best else 0,
        "best_partner": best,
    }


def _coverage(views: list[dict[str, Any]], intr: dict[str, Any]) -> tuple[float, list[str]]:
    """Fraction of the image inside some used view's marker bounding box (on a grid of
    sample points), and the 3x3 image regions less than REGION_MIN of which was covered."""
    gx, gy = COVERAGE_GRID
    w, h = intr["width"], intr["height"]
    boxes = np.array([v["image_bbox_px"] for v in views], dtype=float).reshape(-1, 4)
    u = (np.arange(gx) + 0.5) * w / gx
    v = (np.arange(gy) + 0.5) * h / gy
    uu, vv = np.meshgrid(u, v)
    inside = np.zeros(uu.shape, dtype=bool)
    for u0, v0, u1, v1 in boxes:
        inside |= (u0 <= uu) & (uu <= u1) & (v0 <= vv) & (vv <= v1)
    missing = [
        REGIONS[j][i]
        for j in range(3)
        for i in range(3)
        if inside[j * gy // 3 : (j + 1) * gy // 3, i * gx // 3 : (i + 1) * gx // 3].mean()
        < REGION_MIN
    ]
    return float(inside.mean()), missing


def _range(values: list[float]) -> dict[str, float] | None:
    return {"min": float(min(values)), "max": float(max(values))} if values else None


def _worst(values: dict[str, float | None]) -> dict[str, Any] | None:
    vals = {k: v for k, v in values.items() if v is not None}
    if not vals:
        return None
    cam = max(vals, key=lambda k: (vals[k], k))
    return {"camera": cam, "value": vals[cam]}


def _summary(report: dict[str, Any]) -> dict[str, Any]:
    """``summary`` with verdict ``good``: :func:`finalize_report` sets the verdict from the
    findings, which read this summary."""
    cams = report["cameras"]
    names = list(cams)
    calibrated = [c for c in names if cams[c]["calibrated"]]
    free = [c for c in calibrated if c != report["reference"]]
    n_used = sum((cams[c]["reprojection_px"] or {}).get("n", 0) for c in names)
    sq = sum(
        (cams[c]["reprojection_px"] or {}).get("n", 0)
        * (cams[c]["reprojection_px"] or {}).get("rms", 0.0) ** 2
        for c in names
    )
    n_all = sum((cams[c]["reprojection_all_px"] or {}).get("n", 0) for c in names)
    edges = [
        v
        for v in report["views"]
        if v["edge_status"] == "used" and v["edge_translation_mm"] is not None
    ]
    return {
        "verdict": "good",
        "n_cameras": len(names),
        "n_calibrated": len(calibrated),
        "n_frames": int(report["dataset"].get("n_frames", 0)),
        "n_board_views": len(report["board_views"]),
        "n_views_used": len(report["views"]),
        "n_views_dropped": len(report["dropped_views"]),
        "n_markers_used": int(n_used),
        "n_markers_excluded": int(n_all - n_used),
        "n_outlier_edges": len(report["pose_graph"]["outliers"]),
        "reprojection_rms_px": float(math.sqrt(sq / n_used)) if n_used else None,
        "median_camera_reprojection_rms_px": median_or_none(
            [(cams[c]["reprojection_px"] or {}).get("rms") for c in calibrated]
        ),
        "median_sigma_rotation_deg": median_or_none([cams[c]["sigma_rotation_deg"] for c in free]),
        "median_sigma_translation_mm": median_or_none(
            [cams[c]["sigma_translation_mm"] for c in free]
        ),
        "worst_sigma_rotation_deg": _worst({c: cams[c]["sigma_rotation_deg"] for c in free}),
        "worst_sigma_translation_mm": _worst({c: cams[c]["sigma_translation_mm"] for c in free}),
        "median_edge_translation_mm": median_or_none([v["edge_translation_mm"] for v in edges]),
        "median_edge_rotation_deg": median_or_none([v["edge_rotation_deg"] for v in edges]),
    }
