"""The calibration report: ``report.json`` (versioned schema, docs/report_schema.md) and one
self-contained, offline ``report.html``.

It answers three questions: can I trust these extrinsics, which camera is weak, what do I do
next. Data flows one way::

    CalibrationResult --outputs.report_dict--> report.json (primary numbers)
        --finalize_report--> + summary, co-visibility, coverage, warnings (derived, pure)
        --write_report_html--> report.html (+ fused.ply, or a preview cloud from the dataset)

Everything the HTML shows comes from ``report.json``, ``fused.ply`` and the dataset folder
recorded in it, so :func:`rebuild_report` reproduces both files byte for byte (there is no
timestamp). Figures are matplotlib PNGs embedded as base64; the 3D view is a small inline
canvas viewer (no WebGL, no network, no external script).

This is the only module of the package that imports matplotlib.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .errors import RgbdCalibError

REPORT_SCHEMA_VERSION = "1.1"
Progress = Callable[[str, int, int], Callable[[int], None]]


class ReportError(RgbdCalibError):
    """A calibration folder cannot be reported on (missing or inconsistent saved results)."""


# ----------------------------------------------------------------------------- thresholds
WEAK_SIGMA_FACTOR = 3.0  # a camera's sigma this many times the rig median is weak ...
WEAK_SIGMA_MIN_MM = 0.25  # ... and above these absolute floors (tiny sigmas are all fine)
WEAK_SIGMA_MIN_DEG = 0.01
FEW_VIEWS = 3  # fewer used views than this (or than FEW_VIEWS_FACTOR x the median): weak
FEW_VIEWS_FACTOR = 0.35
FEW_SHARED_VIEWS = 3  # a camera sharing fewer views with every other camera is weakly tied
INCONSISTENT_FRACTION = 0.3  # share of a camera's views that are pose-graph outliers
REPROJECTION_FACTOR = 3.0  # a camera's median reprojection error this many times the rig's ...
REPROJECTION_MIN_PX = 0.5  # ... and above this is suspect (intrinsics, blur, sync)
RIG_REPROJECTION_MAX_PX = 0.5  # the whole rig's RMS above this: check intrinsics / board
MARKER_FACTOR = 3.0  # a marker id whose RMS is this many times the median marker's ...
MARKER_MIN_PX = 0.3  # ... and above this: check that marker on the board
COVERAGE_MIN = 0.35  # fraction of the image the board's views covered
DISTANCE_SPREAD_MIN = 1.3  # max/min board distance over a camera's views
TILT_SPREAD_MIN_DEG = 20.0  # range of board tilts seen by a camera
PAIR_RMSE_MAX_MM = 15.0  # point-to-plane RMSE after ICP above this: depth itself is off
# the joint extrinsics fit a pair worse than its own ICP did by more than this: the pair and
# the rest of the calibration disagree (depth noise alone gives ~5 mm at 2 m on a D435)
PAIR_FINAL_EXCESS_MM = 2.0
PAIR_FITNESS_MIN = 0.3
DEPTH_SCALE_TOL = 0.003  # |factor - 1| above this: the camera's depth needs its scale
COVERAGE_GRID = (48, 27)  # sample points across, down, for the image coverage of a camera
REGION_MIN = 0.1  # a 3x3 image region less covered than this counts as never reached
REGIONS = (
    ("top-left", "top", "top-right"),
    ("left", "centre", "right"),
    ("bottom-left", "bottom", "bottom-right"),
)

DROP_ADVICE = {
    "too_few_markers": "board too far, too oblique or half out of the image: bring it closer "
    "and turn it towards the camera",
    "reprojection_rms": "corners do not fit a pose: motion blur, wrong intrinsics or a bent "
    "board; hold the board still and check rig.yaml",
    "ambiguous": "planar flip ambiguity (small board seen face-on from far): tilt the board "
    "20-40 deg or bring it closer",
    "both_faces": "markers of both faces in one image: a wrong detection or a reflection",
    "face_away": "the pose shows the seen face turned away (a mirror solution): tilt the board "
    "more towards the camera",
    "outlier_markers": "a stray detection carrying a board id: check the background for "
    "printed markers",
    "pnp_failed": "PnP found no pose: check the board definition (--board)",
    "degenerate": "the markers seen constrain no pose (too few, in a line)",
}


# ----------------------------------------------------------------------------- schema
class Nullable:
    def __init__(self, node: Any):
        self.node = node


class ListOf:
    def __init__(self, node: Any):
        self.node = node


class MapOf:
    def __init__(self, key: str, node: Any):
        self.key, self.node = key, node


class Block:
    """A named object type used in several places, documented once."""

    def __init__(self, name: str, node: dict[str, Any]):
        self.name, self.node = name, node


S, INT, N, B = "string", "integer", "number", "boolean"
MAT4 = "matrix4"
_PCT = Nullable(Block("percentiles", {"rms": N, "p50": N, "p90": N, "p99": N, "max": N}))
_STATS = Nullable(Block("stats", {"n": INT, "rms": N, "p50": N, "p90": N, "p99": N, "max": N}))
_RANGE = Nullable(Block("range", {"min": N, "max": N}))
_WORST = Nullable(Block("worst", {"camera": S, "value": N}))

CAMERA_SCHEMA: dict[str, Any] = {
    "calibrated": B,
    "views_used": INT,
    "views_dropped": INT,
    "dropped_reasons": MapOf("<reason>", INT),
    "pnp_reprojection_rms_px": _PCT,
    "T_ref_cam": Nullable(MAT4),
    "translation_m": Nullable(ListOf(N)),
    "quaternion_xyzw": Nullable(ListOf(N)),
    "sigma_rotation_deg": Nullable(N),
    "sigma_translation_mm": Nullable(N),
    "why_not": Nullable(S),
    "bundle_marker_rms_px?": _PCT,
    "bundle_outlier_markers?": INT,
    "intrinsics": {
        "width": INT,
        "height": INT,
        "fx": N,
        "fy": N,
        "cx": N,
        "cy": N,
        "distortion": ListOf(N),
        "depth_scale": N,
    },
    "reprojection_px": _STATS,
    "reprojection_all_px": _STATS,
    "reprojection_histogram": {"used": ListOf(INT), "excluded": ListOf(INT)},
    "edge_outliers": INT,
    "depth_scale_factor": Nullable(N),
    "depth_scale_sigma": Nullable(N),
    "coverage": {
        "image_fraction": N,
        "missing_regions": ListOf(S),
        "distance_m": _RANGE,
        "tilt_deg": _RANGE,
        "faces": {"front": INT, "back": INT, "both": INT},
        "max_shared_views": INT,
        "best_partner": Nullable(S),
    },
}

PAIR_SCHEMA: dict[str, Any] = {
    "cam_a": S,
    "cam_b": S,
    "overlap_fraction": Nullable(N),
    "n_points": Nullable(INT),
    "fitness": Nullable(N),
    "rmse_before_mm": Nullable(N),
    "rmse_after_mm": Nullable(N),
    "rmse_final_mm": Nullable(N),
    "correction_deg": Nullable(N),
    "correction_mm": Nullable(N),
    "accepted": Nullable(B),
    "reason": Nullable(S),
    "error_map": Nullable(
        {"width": INT, "height": INT, "cols": INT, "rows": INT, "values_mm": ListOf(Nullable(N))}
    ),
}

REPORT_SCHEMA: dict[str, Any] = {
    "schema_version": S,
    "rgbd_calib_version": S,
    "reference": S,
    "method": S,
    "dataset": {
        "cameras": ListOf(S),
        "n_frames": INT,
        "frames_per_camera": MapOf("<camera>", INT),
        "missing": MapOf("<camera>", INT),
        "depth_cameras": ListOf(S),
        "path": Nullable(S),
    },
    "board": {"markers_seen": INT, "extent_m": Nullable(ListOf(N)), "thickness_m": Nullable(N)},
    "cameras": MapOf("<camera>", CAMERA_SCHEMA),
    "unconnected": MapOf("<camera>", S),
    "pose_graph": {
        "edges": INT,
        "used": INT,
        "stale": INT,
        "outliers": ListOf({"camera": S, "view": S, "whitened_norm": N}),
    },
    "views": ListOf(
        {
            "camera": S,
            "frame": S,
            "markers": INT,
            "reprojection_rms_px": N,
            "face": S,
            "distance_m": N,
            "tilt_deg": N,
            "image_bbox_px": ListOf(N),
            "pnp_sigma_rotation_deg": N,
            "pnp_sigma_translation_mm": N,
            "edge_status": S,
            "edge_translation_mm": Nullable(N),
            "edge_rotation_deg": Nullable(N),
            "edge_whitened_norm": Nullable(N),
            "final_reprojection_rms_px": Nullable(N),
            "final_reprojection_max_px": Nullable(N),
            "excluded_markers": Nullable(INT),
        }
    ),
    "board_views": ListOf(
        {
            "frame": S,
            "T_ref_board": MAT4,
            "cameras": ListOf(S),
            "final_reprojection_rms_px": Nullable(N),
        }
    ),
    "markers": ListOf({"id": INT, "face": S, "observations": INT, "rms_px": N, "max_px": N}),
    "reprojection_histogram_edges_px": ListOf(N),
    "dropped_views": ListOf({"camera": S, "frame": S, "reason": S, "markers": INT, "detail": S}),
    "pairs": ListOf(PAIR_SCHEMA),
    "timings_s": MapOf("<stage>", N),
    "bundle?": {
        "pixel_sigma_estimated": N,
        "iterations": INT,
        "markers": INT,
        "outlier_markers": ListOf({"camera": S, "view": S, "marker": INT, "rms_px": N}),
    },
    "summary": {
        "verdict": S,
        "n_cameras": INT,
        "n_calibrated": INT,
        "n_frames": INT,
        "n_board_views": INT,
        "n_views_used": INT,
        "n_views_dropped": INT,
        "n_markers_used": INT,
        "n_markers_excluded": INT,
        "n_outlier_edges": INT,
        "reprojection_rms_px": Nullable(N),
        "median_camera_reprojection_rms_px": Nullable(N),
        "median_sigma_rotation_deg": Nullable(N),
        "median_sigma_translation_mm": Nullable(N),
        "worst_sigma_rotation_deg": _WORST,
        "worst_sigma_translation_mm": _WORST,
        "median_edge_translation_mm": Nullable(N),
        "median_edge_rotation_deg": Nullable(N),
    },
    "covisibility": {"cameras": ListOf(S), "views": ListOf(ListOf(INT))},
    "warnings": ListOf({"severity": S, "code": S, "cameras": ListOf(S), "message": S, "advice": S}),
    "next_steps": ListOf(S),
}
ENUMS = {
    "method": {"bundle", "posegraph"},
    "face": {"front", "back", "both"},
    "edge_status": {"used", "outlier", "stale", "unused"},
    "verdict": {"good", "check", "poor"},
    "severity": {"error", "warning", "info"},
}


def _type_name(node: Any) -> str:
    if isinstance(node, Nullable):
        return _type_name(node.node) + " | null"
    if isinstance(node, ListOf):
        return f"list[{_type_name(node.node)}]"
    if isinstance(node, MapOf):
        return f"map[{node.key} -> {_type_name(node.node)}]"
    if isinstance(node, Block):
        return node.name
    if isinstance(node, dict):
        return "object"
    return str(node)


def schema_blocks() -> dict[str, dict[str, str]]:
    """The named blocks (``stats``, ``percentiles``, ...) with their keys and types."""
    blocks = {}
    for b in (_PCT, _STATS, _RANGE, _WORST):
        blocks[b.node.name] = {k: _type_name(v) for k, v in b.node.node.items()}
    return blocks


def schema_paths(node: Any = None, prefix: str = "") -> dict[str, str]:
    """Every key path of the schema (``cameras.<camera>.views_used``, ``views[].camera``) with
    its type, as documented in docs/report_schema.md; named blocks are not expanded."""
    node = REPORT_SCHEMA if node is None else node
    out: dict[str, str] = {}
    inner = node.node if isinstance(node, Nullable) else node
    if isinstance(inner, ListOf) and isinstance(
        inner.node.node if isinstance(inner.node, Nullable) else inner.node, dict
    ):
        out.update(schema_paths(inner.node, prefix + "[]"))
    elif isinstance(inner, MapOf) and isinstance(inner.node, dict):
        out.update(schema_paths(inner.node, f"{prefix}.{inner.key}"))
    elif isinstance(inner, dict):
        for key, child in inner.items():
            name = key.rstrip("?")
            path = f"{prefix}.{name}" if prefix else name
            out[path] = _type_name(child) + (" (optional)" if key.endswith("?") else "")
            out.update(schema_paths(child, path))
    return out


def validate_report(report: Any) -> list[str]:
    """Errors of ``report`` against :data:`REPORT_SCHEMA` (empty when it conforms): types,
    required and unknown keys, enumerations, finite numbers."""
    errors: list[str] = []
    _check(report, REPORT_SCHEMA, "", errors)
    return errors


def _check(value: Any, node: Any, path: str, errors: list[str]) -> None:
    where = path or "<root>"
    if isinstance(node, Nullable):
        if value is not None:
            _check(value, node.node, path, errors)
        return
    if isinstance(node, ListOf):
        if not isinstance(value, list):
            errors.append(f"{where}: expected a list, got {type(value).__name__}")
            return
        for i, item in enumerate(value):
            _check(item, node.node, f"{path}[{i}]", errors)
        return
    if isinstance(node, MapOf):
        if not isinstance(value, dict):
            errors.append(f"{where}: expected an object, got {type(value).__name__}")
            return
        for key, item in value.items():
            _check(item, node.node, f"{path}.{key}", errors)
        return
    if isinstance(node, Block):
        node = node.node
    if isinstance(node, dict):
        if not isinstance(value, dict):
            errors.append(f"{where}: expected an object, got {type(value).__name__}")
            return
        known = {k.rstrip("?") for k in node}
        for key, child in node.items():
            name = key.rstrip("?")
            sub = f"{path}.{name}" if path else name
            if name in value:
                _check(value[name], child, sub, errors)
                leaf = name if name in ENUMS else None
                if leaf and isinstance(value[name], str) and value[name] not in ENUMS[leaf]:
                    errors.append(f"{sub}: {value[name]!r} not one of {sorted(ENUMS[leaf])}")
            elif not key.endswith("?"):
                errors.append(f"{sub}: missing")
        errors.extend(
            f"{path}.{k}: not in schema {REPORT_SCHEMA_VERSION}" for k in value if k not in known
        )
        return
    ok = {
        S: isinstance(value, str),
        B: isinstance(value, bool),
        INT: isinstance(value, int) and not isinstance(value, bool),
        N: isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value),
        MAT4: isinstance(value, list)
        and len(value) == 4
        and all(
            isinstance(r, list)
            and len(r) == 4
            and all(isinstance(x, (int, float)) and math.isfinite(x) for x in r)
            for r in value
        ),
    }[node]
    if not ok:
        errors.append(f"{where}: expected {node}, got {value!r:.60}")


# ----------------------------------------------------------------------------- numbers
def stats(values: Sequence[float] | np.ndarray) -> dict[str, float] | None:
    """``{n, rms, p50, p90, p99, max}`` of non-negative values (px), None when empty."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.size == 0:
        return None
    return {
        "n": int(v.size),
        "rms": float(np.sqrt(np.mean(v**2))),
        "p50": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "p99": float(np.percentile(v, 99)),
        "max": float(v.max()),
    }


def _nice_ceil(x: float) -> float:
    """Smallest of 1, 2, 2.5, 5 x 10^k that is >= x."""
    k = math.floor(math.log10(x))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * 10**k >= x * (1 - 1e-12):
            return float(m * 10**k)
    return float(10 ** (k + 1))


def histogram_edges_px(values: np.ndarray, bins: int = 40) -> np.ndarray:
    """Shared bin edges (px) of the per-camera reprojection histograms: 0 to a round number
    near 3x the 90th percentile; larger values land in the last bin."""
    v = np.asarray(values, dtype=float)
    top = _nice_ceil(max(3.0 * float(np.percentile(v, 90)), 0.2) if v.size else 1.0)
    return np.linspace(0.0, top, bins + 1)


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
    return out


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


def _sanitize(obj: Any) -> Any:
    """Non-finite floats become null (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: _sanitize(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_sanitize(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dump_report(report: dict[str, Any]) -> str:
    """The canonical text of ``report.json`` (what :func:`rebuild_report` reproduces)."""
    return json.dumps(report, indent=1, allow_nan=False) + "\n"


# ----------------------------------------------------------------------------- derived figures
def _median(values: list[float]) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.median(vals)) if vals else None


def _worst(values: dict[str, float | None]) -> dict[str, Any] | None:
    vals = {k: v for k, v in values.items() if v is not None}
    if not vals:
        return None
    cam = max(vals, key=lambda k: (vals[k], k))
    return {"camera": cam, "value": vals[cam]}


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


def finalize_report(report: dict[str, Any]) -> dict[str, Any]:
    """Add (or recompute) the derived sections of a report from its primary numbers:
    ``summary``, ``covisibility``, ``cameras.*.coverage``, ``warnings`` and ``next_steps``.

    Pure and idempotent: ``finalize_report(json.loads(dump_report(r))) == r`` for a finalized
    ``r``, which is what makes a rebuilt ``report.json`` byte-identical."""
    report = _sanitize(report)
    cams: dict[str, dict[str, Any]] = report["cameras"]
    names = list(cams)
    used_views = [v for v in report["views"] if v["edge_status"] == "used"]

    # co-visibility: board views both cameras contributed to the estimate
    index = {c: i for i, c in enumerate(names)}
    covis = np.zeros((len(names), len(names)), dtype=int)
    by_frame: dict[str, list[str]] = {}
    for v in used_views:
        by_frame.setdefault(v["frame"], []).append(v["camera"])
    for members in by_frame.values():
        for a in members:
            for b in members:
                covis[index[a], index[b]] += 1
    report["covisibility"] = {"cameras": names, "views": covis.tolist()}

    for name, cam in cams.items():
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
        cam["coverage"] = {
            "image_fraction": fraction,
            "missing_regions": missing,
            "distance_m": _range([v["distance_m"] for v in mine]),
            "tilt_deg": _range([v["tilt_deg"] for v in mine]),
            "faces": faces,
            "max_shared_views": shared[best] if best else 0,
            "best_partner": best,
        }

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
    report["summary"] = {
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
        "median_camera_reprojection_rms_px": _median(
            [(cams[c]["reprojection_px"] or {}).get("rms") for c in calibrated]
        ),
        "median_sigma_rotation_deg": _median([cams[c]["sigma_rotation_deg"] for c in free]),
        "median_sigma_translation_mm": _median([cams[c]["sigma_translation_mm"] for c in free]),
        "worst_sigma_rotation_deg": _worst({c: cams[c]["sigma_rotation_deg"] for c in free}),
        "worst_sigma_translation_mm": _worst({c: cams[c]["sigma_translation_mm"] for c in free}),
        "median_edge_translation_mm": _median([v["edge_translation_mm"] for v in edges]),
        "median_edge_rotation_deg": _median([v["edge_rotation_deg"] for v in edges]),
    }
    found = _warnings(report)
    report["warnings"] = found
    severities = {w["severity"] for w in found}
    report["summary"]["verdict"] = (
        "poor" if "error" in severities else "check" if "warning" in severities else "good"
    )
    report["next_steps"] = list(dict.fromkeys(w["advice"] for w in found if w["advice"]))
    return report


def _fmt(x: float | None, digits: int = 2) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def _warnings(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Rules over the report's numbers; thresholds are the module constants above."""
    cams = report["cameras"]
    summ = report["summary"]
    out: list[dict[str, Any]] = []

    def add(severity: str, code: str, cameras: list[str], message: str, advice: str) -> None:
        out.append(
            {
                "severity": severity,
                "code": code,
                "cameras": cameras,
                "message": message,
                "advice": advice,
            }
        )

    for name, cam in cams.items():
        if not cam["calibrated"]:
            partner = cam["coverage"]["best_partner"]
            why = cam["why_not"]
            all_out = bool(cam["edge_outliers"]) and cam["edge_outliers"] == cam["views_used"]
            if why in (None, "unknown"):
                why = (
                    f"all {cam['edge_outliers']} of its board views were rejected as outliers"
                    if all_out
                    else "the final estimate dropped it"
                )
            add(
                "error",
                "not_calibrated",
                [name],
                f"{name} was not calibrated: {why}.",
                f"Fix {name}'s intrinsics or synchronisation (see the inconsistent_camera "
                "finding) and re-run calibrate."
                if all_out
                else f"Record views where {name} and a calibrated neighbour"
                f"{f' (e.g. {partner})' if partner else ''} see the board at the same time.",
            )

    views_median = _median([c["views_used"] for c in cams.values() if c["calibrated"]]) or 0
    flagged_inconsistent: set[str] = set()
    rig_p50 = _median(
        [(c["reprojection_all_px"] or {}).get("p50") for c in cams.values() if c["calibrated"]]
    )
    for name, cam in cams.items():
        views = [v for v in report["views"] if v["camera"] == name]
        if not views:
            continue
        n_out = cam["edge_outliers"]
        p50 = (cam["reprojection_all_px"] or {}).get("p50")
        bad_views = n_out >= 2 and n_out >= INCONSISTENT_FRACTION * max(len(views), 1)
        bad_px = (
            p50 is not None
            and rig_p50 is not None
            and p50 > REPROJECTION_MIN_PX
            and p50 > REPROJECTION_FACTOR * rig_p50
        )
        dropped_rms = cam["dropped_reasons"].get("reprojection_rms", 0)
        bad_pnp = dropped_rms >= 2 and dropped_rms >= INCONSISTENT_FRACTION * (
            cam["views_used"] + cam["views_dropped"]
        )
        if bad_views or bad_px or bad_pnp:
            flagged_inconsistent.add(name)
            med = _median(
                [v["edge_translation_mm"] for v in views if v["edge_status"] == "outlier"]
            )
            parts = []
            if bad_views:
                parts.append(
                    f"{n_out} of its {len(views)} board views disagree with the rest "
                    f"of the rig (median {_fmt(med, 1)} mm)"
                )
            if bad_px:
                parts.append(
                    f"its board corners reproject {_fmt(p50)} px off (median) through "
                    f"the calibrated poses, {p50 / rig_p50:.0f}x the rig's "
                    f"{_fmt(rig_p50)} px"
                )
            if bad_pnp:
                parts.append(f"{dropped_rms} views were dropped because their corners fit no pose")
            add(
                "error",
                "inconsistent_camera",
                [name],
                f"{name}: " + "; ".join(parts) + ".",
                f"Check {name}'s intrinsics in rig.yaml (fx, fy, cx, cy and distortion for the "
                f"recorded resolution), then its frame synchronisation; re-run calibrate.",
            )

    for key, unit, floor in (
        ("sigma_translation_mm", "mm", WEAK_SIGMA_MIN_MM),
        ("sigma_rotation_deg", "deg", WEAK_SIGMA_MIN_DEG),
    ):
        med = summ["median_sigma_" + key.split("_", 1)[1]]
        for name, cam in cams.items():
            s = cam[key]
            if (
                s is None
                or med is None
                or name == report["reference"]
                or name in flagged_inconsistent
                or not (s > WEAK_SIGMA_FACTOR * med and s > floor)
            ):
                continue
            if any(w["code"] == "weak_camera" and name in w["cameras"] for w in out):
                continue
            cov = cam["coverage"]
            partner = f" ({cov['best_partner']})" if cov["best_partner"] else ""
            add(
                "warning",
                "weak_camera",
                [name],
                f"{name} is weakly constrained: 1-sigma {_fmt(s, 3)} {unit}, "
                f"{s / med:.1f}x the rig median {_fmt(med, 3)} {unit} "
                f"({cam['views_used']} board views used, at most {cov['max_shared_views']} "
                f"shared with one camera{partner}).",
                f"Record more board views for {name}, held where it and "
                f"{cov['best_partner'] or 'a calibrated neighbour'} see the board together.",
            )

    weak = {c for w in out if w["code"] == "weak_camera" for c in w["cameras"]}
    for name, cam in cams.items():
        if not cam["calibrated"] or name in flagged_inconsistent | weak:
            continue
        cov = cam["coverage"]
        if cam["views_used"] < max(FEW_VIEWS, FEW_VIEWS_FACTOR * views_median):
            add(
                "warning",
                "few_views",
                [name],
                f"{name} has only {cam['views_used']} usable board views "
                f"(rig median {views_median:.0f}).",
                f"Show the board to {name} in more positions.",
            )
        if name != report["reference"] and cov["max_shared_views"] < FEW_SHARED_VIEWS:
            add(
                "warning",
                "weak_link",
                [name] + ([cov["best_partner"]] if cov["best_partner"] else []),
                f"{name} shares at most {cov['max_shared_views']} board views with any other "
                "camera.",
                f"Hold the board where {name} and "
                f"{cov['best_partner'] or 'a neighbouring camera'} both see it.",
            )

    placement = [
        (n, c) for n, c in cams.items() if c["calibrated"] and n not in flagged_inconsistent
    ]
    low = [
        (n, c["coverage"])
        for n, c in placement
        if c["coverage"]["image_fraction"] < COVERAGE_MIN and c["coverage"]["missing_regions"]
    ]
    if low:
        regions: dict[str, int] = {}
        for _, cov in low:
            for r in cov["missing_regions"]:
                regions[r] = regions.get(r, 0) + 1
        common = sorted(regions, key=lambda r: -regions[r])[:3]
        add(
            "info",
            "board_coverage",
            [n for n, _ in low],
            f"The board reached less than {COVERAGE_MIN:.0%} of the image of {len(low)} "
            "camera(s): "
            + ", ".join(f"{n} {cov['image_fraction']:.0%}" for n, cov in low)
            + ". Corners near the image border constrain the pose best.",
            "Next recording: also hold the board in the image regions it never reached "
            f"(most often: {', '.join(common)}; per camera in 'Where to put the board next').",
        )
    narrow = [
        (n, c["coverage"]["distance_m"])
        for n, c in placement
        if c["coverage"]["distance_m"]
        and c["views_used"] >= 3
        and c["coverage"]["distance_m"]["max"]
        < DISTANCE_SPREAD_MIN * c["coverage"]["distance_m"]["min"]
    ]
    if narrow:
        add(
            "info",
            "board_distance",
            [n for n, _ in narrow],
            "The board was at one distance only for "
            + ", ".join(f"{n} ({d['min']:.2f}-{d['max']:.2f} m)" for n, d in narrow)
            + ".",
            "Also show the board nearer to and further from "
            + ", ".join(n for n, _ in narrow)
            + ".",
        )
    flat = [
        (n, c["coverage"]["tilt_deg"])
        for n, c in placement
        if c["coverage"]["tilt_deg"]
        and c["views_used"] >= 3
        and c["coverage"]["tilt_deg"]["max"] - c["coverage"]["tilt_deg"]["min"]
        < TILT_SPREAD_MIN_DEG
    ]
    if flat:
        add(
            "info",
            "board_tilt",
            [n for n, _ in flat],
            "The board's tilt barely varied for "
            + ", ".join(f"{n} ({t['min']:.0f}-{t['max']:.0f} deg)" for n, t in flat)
            + ".",
            "Tilt the board 20-50 deg in different directions in front of "
            + ", ".join(n for n, _ in flat)
            + ".",
        )

    outliers = [
        o for o in report["pose_graph"]["outliers"] if o["camera"] not in flagged_inconsistent
    ]
    if outliers:
        listed = ", ".join(f"{o['camera']}/{o['view']}" for o in outliers[:8])
        add(
            "warning",
            "outlier_views",
            sorted({o["camera"] for o in outliers}),
            f"{len(outliers)} board view(s) were rejected as pose-graph outliers: {listed}"
            f"{' ...' if len(outliers) > 8 else ''}.",
            "Look at those frames: motion blur, a camera out of sync, or a wrong detection.",
        )

    marker_rms = [m["rms_px"] for m in report["markers"]]
    med_marker = _median(marker_rms)
    for m in report["markers"]:
        if med_marker and m["rms_px"] > max(MARKER_FACTOR * med_marker, MARKER_MIN_PX):
            add(
                "warning",
                "marker",
                [],
                f"marker {m['id']} ({m['face']} face) reprojects {m['rms_px']:.2f} px RMS, "
                f"{m['rms_px'] / med_marker:.0f}x the median marker.",
                f"Check marker {m['id']} on the board: flat, not peeling, printed at scale "
                "and placed where the board file says.",
            )

    rig_rms = summ["reprojection_rms_px"]
    if rig_rms is not None and rig_rms > RIG_REPROJECTION_MAX_PX:
        add(
            "warning",
            "reprojection",
            [],
            f"the rig's reprojection RMS is {rig_rms:.2f} px (expected well below "
            f"{RIG_REPROJECTION_MAX_PX} px).",
            "Check the intrinsics in rig.yaml, the board's flatness and its printed scale.",
        )

    by_reason: dict[str, dict[str, int]] = {}
    for d in report["dropped_views"]:
        by_reason.setdefault(d["reason"], {})
        by_reason[d["reason"]][d["camera"]] = by_reason[d["reason"]].get(d["camera"], 0) + 1
    for reason, per in sorted(by_reason.items()):
        total = sum(per.values())
        where = ", ".join(f"{c} {n}" for c, n in sorted(per.items(), key=lambda kv: -kv[1]))
        add(
            "info",
            "dropped_views",
            sorted(per),
            f"{total} view(s) dropped ({reason}): {where}.",
            DROP_ADVICE.get(reason, "").capitalize() + ("." if reason in DROP_ADVICE else ""),
        )

    for p in report["pairs"]:
        pair = [p["cam_a"], p["cam_b"]]
        final, after = p.get("rmse_final_mm"), p["rmse_after_mm"]
        if p["accepted"] and final is not None and after is not None and (
                final > after + PAIR_FINAL_EXCESS_MM):
            add(
                "warning",
                "pair_disagrees",
                pair,
                f"{p['cam_a']}-{p['cam_b']}: the final extrinsics fit their common surfaces "
                f"{final:.1f} mm RMS, ICP alone {after:.1f} mm.",
                f"The depth of {p['cam_a']}/{p['cam_b']} and the board disagree: check their "
                "depth scale and that the scene did not move.",
            )
        if p["rmse_after_mm"] is not None and p["rmse_after_mm"] > PAIR_RMSE_MAX_MM:
            add(
                "warning",
                "pair_rmse",
                pair,
                f"{p['cam_a']}-{p['cam_b']}: surfaces disagree by {p['rmse_after_mm']:.1f} mm "
                "RMS after ICP.",
                f"Check the depth of {p['cam_a']} and {p['cam_b']} (scale, temperature drift).",
            )
        if p["fitness"] is not None and p["fitness"] < PAIR_FITNESS_MIN:
            add(
                "info",
                "pair_fitness",
                pair,
                f"{p['cam_a']}-{p['cam_b']}: only {p['fitness']:.0%} of points overlap.",
                "",
            )
    for name, cam in cams.items():
        f = cam["depth_scale_factor"]
        if f is not None and abs(f - 1.0) > DEPTH_SCALE_TOL:
            add(
                "info",
                "depth_scale",
                [name],
                f"{name}'s depth reads {100 * (f - 1):+.2f}% off the board's true distance.",
                f"Divide {name}'s depth by {f:.4f} (or recalibrate its depth unit).",
            )
    order = {"error": 0, "warning": 1, "info": 2}
    out.sort(key=lambda w: order[w["severity"]])
    return out


# ----------------------------------------------------------------------------- point cloud
MAX_VIEW_POINTS = 40000  # points in the 3D view and the static cloud figures
PREVIEW_FRAMES = 5  # depth frames per camera in the preview cloud's temporal median


class Cloud:
    """Points (N,3) in the reference frame (m), camera index (N,) into ``names``, colours
    (N,3) uint8 or None, and where they came from (one sentence for the report)."""

    def __init__(
        self,
        points: np.ndarray,
        camera: np.ndarray,
        names: list[str],
        rgb: np.ndarray | None,
        source: str,
    ):
        self.points, self.camera, self.names, self.rgb, self.source = (
            points,
            camera,
            names,
            rgb,
            source,
        )


def read_ply_cloud(
    path: Path,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, list[str]]:
    """Points (N,3) float, RGB (N,3) uint8 or None, camera index (N,) or None and the camera
    names (``comment camera <k> <name>``) of a binary little-endian PLY such as ``fused.ply``
    (``x y z`` float, ``red green blue`` uchar, ``camera`` index). Numpy only."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ReportError(f"{path}: not a PLY file; delete it or re-run calibrate")
    body = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", "replace").splitlines()
    if not any(h.strip() == "format binary_little_endian 1.0" for h in header):
        raise ReportError(f"{path}: only binary little-endian PLY is supported")
    types = {
        "float": "<f4",
        "float32": "<f4",
        "double": "<f8",
        "float64": "<f8",
        "uchar": "u1",
        "uint8": "u1",
        "char": "i1",
        "int8": "i1",
        "ushort": "<u2",
        "uint16": "<u2",
        "short": "<i2",
        "int16": "<i2",
        "int": "<i4",
        "int32": "<i4",
        "uint": "<u4",
        "uint32": "<u4",
    }
    fields, n, names, in_vertex = [], 0, {}, False
    for line in header:
        parts = line.split()
        if parts[:2] == ["comment", "camera"] and len(parts) >= 4:
            names[int(parts[2])] = " ".join(parts[3:])
        elif parts[:1] == ["element"]:
            in_vertex = parts[1] == "vertex"
            n = int(parts[2]) if in_vertex else n
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list" or parts[1] not in types:
                raise ReportError(f"{path}: unsupported PLY property {line.strip()!r}")
            fields.append((parts[2], types[parts[1]]))
    data = np.frombuffer(raw, dtype=np.dtype(fields), count=n, offset=body)
    points = np.column_stack([data["x"], data["y"], data["z"]]).astype(float)
    keys = {f for f, _ in fields}
    rgb = (
        np.column_stack([data["red"], data["green"], data["blue"]]).astype(np.uint8)
        if {"red", "green", "blue"} <= keys
        else None
    )
    cam = data["camera"].astype(int) if "camera" in keys else None
    return points, rgb, cam, [names[k] for k in sorted(names)]


def _subsample(n: int, keep: int) -> np.ndarray:
    """Deterministic even subsample of ``range(n)`` to at most ``keep`` indices."""
    if n <= keep:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, keep).astype(int))


def load_cloud(report: dict[str, Any], folder: Path) -> tuple[Cloud | None, str]:
    """The cloud the report shows: ``folder/fused.ply`` when present (the depth stage's fused
    cloud), else a preview from the dataset's depth frames; ``(None, why)`` without depth."""
    cams = [c for c, v in report["cameras"].items() if v["calibrated"]]
    ply = Path(folder) / "fused.ply"
    if ply.is_file():
        points, rgb, cam, names = read_ply_cloud(ply)
        names = names or cams
        if cam is None:
            cam = np.zeros(len(points), dtype=int)
        order = {c: i for i, c in enumerate(report["cameras"])}
        remap = np.array([order.get(nm, -1) for nm in names] or [-1])
        cam = remap[np.clip(cam, 0, len(remap) - 1)]
        idx = _subsample(len(points), MAX_VIEW_POINTS)
        ok = cam[idx] >= 0
        idx = idx[ok]
        return Cloud(
            points[idx],
            cam[idx],
            list(report["cameras"]),
            None if rgb is None else rgb[idx],
            f"fused.ply: {len(points):,} points from the depth stage (showing {len(idx):,})",
        ), ""
    path = report["dataset"].get("path")
    depth_cams = [c for c in cams if c in report["dataset"].get("depth_cameras", [])]
    if not path or not Path(path).is_dir():
        return None, (
            f"no fused.ply in {folder} and the dataset folder {path} is not "
            "available: no point cloud to show"
        )
    if not depth_cams:
        return None, "no camera of the dataset has depth frames: no point cloud to show"
    return _preview_cloud(report, Path(path), depth_cams), ""


def _preview_cloud(report: dict[str, Any], dataset: Path, cams: list[str]) -> Cloud | None:
    """Each camera's static scene: the temporal median of a few depth frames (the moving
    board mostly drops out), back-projected on a pixel grid (pinhole, the rig.yaml depth
    scale; no depth-scale correction) and moved into the reference frame."""
    from .dataset import read_color_image, read_depth_image

    order = list(report["cameras"])
    per_cam = MAX_VIEW_POINTS // max(len(cams), 1)
    pts, idx, cols = [], [], []
    for name in cams:
        cam = report["cameras"][name]
        intr = cam["intrinsics"]
        w, h = intr["width"], intr["height"]
        frames = sorted(p.stem for p in (dataset / name / "depth").glob("*.png"))
        if not frames:
            continue
        frames = [frames[i] for i in _subsample(len(frames), PREVIEW_FRAMES)]
        step = max(1, int(math.ceil(math.sqrt(w * h / (per_cam * 1.5)))))
        vs, us = np.mgrid[step // 2 : h : step, step // 2 : w : step]
        stack, rgb = [], []
        for f in frames:
            d = read_depth_image(dataset / name / "depth" / f"{f}.png", w, h)[vs, us]
            stack.append(np.where(d > 0, d * intr["depth_scale"], np.nan))
            color = next((p for p in (dataset / name / "color").glob(f"{f}.*")), None)
            if color is not None:
                rgb.append(read_color_image(color, w, h)[vs, us, ::-1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            z = np.nanmedian(np.stack(stack), axis=0)
        ok = np.isfinite(z)
        x = (us[ok] - intr["cx"]) / intr["fx"] * z[ok]
        y = (vs[ok] - intr["cy"]) / intr["fy"] * z[ok]
        p_cam = np.column_stack([x, y, z[ok]])
        T = np.asarray(cam["T_ref_cam"], dtype=float)
        keep = _subsample(len(p_cam), per_cam)
        pts.append((p_cam @ T[:3, :3].T + T[:3, 3])[keep])
        idx.append(np.full(len(keep), order.index(name)))
        cols.append(
            np.median(np.stack(rgb), axis=0)[ok][keep].astype(np.uint8)
            if rgb
            else np.full((len(keep), 3), 160, np.uint8)
        )
    if not pts:
        return None
    return Cloud(
        np.concatenate(pts),
        np.concatenate(idx),
        order,
        np.concatenate(cols),
        f"preview (no fused.ply yet): median of {PREVIEW_FRAMES} depth frames per "
        f"camera from {dataset}, {sum(len(p) for p in pts):,} points, rig.yaml depth "
        "scale, no depth-scale correction",
    )


# ----------------------------------------------------------------------------- display frame
def display_frame(report: dict[str, Any]) -> np.ndarray:
    """Rows ``(e1, e2, up)``: the axes of the top and side views, in the reference frame.

    ``up`` is minus the mean of the cameras' image-down (y) axes (cameras are mounted roughly
    upright); ``e1`` is the horizontal direction along which the cameras spread most."""
    Ts = [
        np.asarray(c["T_ref_cam"], float)
        for c in report["cameras"].values()
        if c["T_ref_cam"] is not None
    ]
    ys = np.array([T[:3, 1] for T in Ts])
    up = -ys.mean(0)
    if np.linalg.norm(up) < 0.3:
        centres = np.array([T[:3, 3] for T in Ts])
        _, _, vt = np.linalg.svd(centres - centres.mean(0))
        up = vt[2]
    up /= np.linalg.norm(up)
    pts = np.array(
        [T[:3, 3] for T in Ts]
        + [np.asarray(b["T_ref_board"], float)[:3, 3] for b in report["board_views"]]
    )
    flat = pts - np.outer(pts @ up, up)
    flat -= flat.mean(0)
    _, _, vt = np.linalg.svd(flat)
    e1 = vt[0] - (vt[0] @ up) * up
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(up, [0.0, 0.0, 1.0]) if abs(up[2]) < 0.9 else np.cross(up, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    if e1[0] < 0 or (abs(e1[0]) < 1e-9 and e1[1] < 0):
        e1 = -e1
    e2 = np.cross(up, e1)
    return np.array([e1, e2, up])


def _frustum(cam: dict[str, Any], depth_m: float) -> np.ndarray:
    """Centre and the 4 image-corner rays at ``depth_m`` of a camera, reference frame (5,3)."""
    intr = cam["intrinsics"]
    T = np.asarray(cam["T_ref_cam"], float)
    uv = [(0, 0), (intr["width"], 0), (intr["width"], intr["height"]), (0, intr["height"])]
    rays = (
        np.array(
            [[(u - intr["cx"]) / intr["fx"], (v - intr["cy"]) / intr["fy"], 1.0] for u, v in uv]
        )
        * depth_m
    )
    return np.vstack([T[:3, 3], rays @ T[:3, :3].T + T[:3, 3]])


def _board_outline(report: dict[str, Any], T_ref_board: np.ndarray) -> np.ndarray:
    ext = report["board"]["extent_m"] or [0.0, 0.3, 0.0, 0.3]
    x0, x1, y0, y1 = ext
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    return corners @ T_ref_board[:3, :3].T + T_ref_board[:3, 3]


def _rig_size(report: dict[str, Any]) -> float:
    centres = np.array(
        [
            np.asarray(c["T_ref_cam"], float)[:3, 3]
            for c in report["cameras"].values()
            if c["T_ref_cam"] is not None
        ]
    )
    span = float(np.ptp(centres, axis=0).max()) if len(centres) > 1 else 1.0
    return max(span, 0.3)


# ----------------------------------------------------------------------------- figures
REF_COLOR = (0.84, 0.15, 0.16)  # the reference camera is red, as in the thesis's Fig. 4.11


def _palette(report: dict[str, Any]) -> list[tuple[float, float, float]]:
    """One colour per camera (rig order), the same in every figure and in the 3D view: the
    reference red, the others from a qualitative map without red."""
    import matplotlib

    others = len(report["cameras"]) - 1
    if others <= 18:
        name, reds = ("tab10", {3}) if others <= 9 else ("tab20", {6, 7})
        cmap = matplotlib.colormaps[name]
        pool = [tuple(cmap(i)[:3]) for i in range(cmap.N) if i not in reds]
    else:
        hsv = matplotlib.colormaps["hsv"]
        pool = [tuple(hsv(0.08 + 0.84 * i / others)[:3]) for i in range(others)]
    it = iter(pool)
    return [REF_COLOR if c == report["reference"] else next(it) for c in report["cameras"]]


def _png(fig) -> str:
    """A matplotlib figure as a base64 PNG (no metadata: identical bytes on a rebuild)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=96, metadata={"Software": None})
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _figure(w: float, h: float, **kw):
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 9, "axes.titlesize": 10, "svg.hashsalt": "rgbd-calib"})
    return plt.subplots(figsize=(w, h), layout="constrained", **kw)


def _draw_rig(
    ax,
    report: dict[str, Any],
    frame: np.ndarray,
    axes: tuple[int, int],
    colors: list,
    boards: bool = True,
) -> None:
    """Cameras as frusta (reference in red, bold) and board poses projected on ``axes``."""
    from matplotlib.collections import LineCollection, PolyCollection

    size = _rig_size(report)
    a, b = axes
    if boards and report["board_views"]:
        Ts = [np.asarray(bv["T_ref_board"], float) for bv in report["board_views"]]
        outlines = np.array([_board_outline(report, T) @ frame.T for T in Ts])[:, :, [a, b]]
        ax.add_collection(
            PolyCollection(outlines, facecolor=(0.55, 0.55, 0.55, 0.12), edgecolor="0.45", lw=0.5)
        )
        step = max(1, len(Ts) // 40)  # every k-th board pose as a 3D axis (thesis Fig. 4.11)
        for axis, col in zip(range(3), ("tab:red", "tab:green", "tab:blue")):
            segs = [
                np.array([T[:3, 3], T[:3, 3] + T[:3, axis] * 0.08 * size / 1.5]) @ frame.T
                for T in Ts[::step]
            ]
            ax.add_collection(LineCollection([s[:, [a, b]] for s in segs], colors=col, lw=0.8))
    for i, (name, cam) in enumerate(report["cameras"].items()):
        if cam["T_ref_cam"] is None:
            continue
        f = _frustum(cam, 0.12 * size) @ frame.T
        ref = name == report["reference"]
        col = colors[i]
        for j in range(1, 5):
            ax.plot([f[0, a], f[j, a]], [f[0, b], f[j, b]], color=col, lw=1.6 if ref else 1.0)
        ring = f[[1, 2, 3, 4, 1]]
        ax.plot(ring[:, a], ring[:, b], color=col, lw=1.6 if ref else 1.0)
        ax.annotate(
            name + (" (ref)" if ref else ""),
            (f[0, a], f[0, b]),
            fontsize=8,
            xytext=(3, 3),
            textcoords="offset points",
            color=col,
            fontweight="bold" if ref else "normal",
        )
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3, alpha=0.5)


def fig_rig(report: dict[str, Any], frame: np.ndarray) -> str:
    fig, (top, side) = _figure(11, 4.6, ncols=2)
    colors = _palette(report)
    _draw_rig(top, report, frame, (0, 1), colors)
    _draw_rig(side, report, frame, (0, 2), colors)
    top.set(title="top view (looking down)", xlabel="e1 (m)", ylabel="e2 (m)")
    side.set(title="side view", xlabel="e1 (m)", ylabel="up (m)")
    return _png(fig)


def fig_cloud(report: dict[str, Any], cloud: Cloud, frame: np.ndarray) -> str:
    fig, (top, side) = _figure(11, 4.6, ncols=2)
    colors = np.array(_palette(report))
    p = cloud.points @ frame.T
    order = np.argsort(p[:, 2])  # top view: higher points drawn last
    for ax, (a, b), idx in ((top, (0, 1), order), (side, (0, 2), np.argsort(-p[:, 1]))):
        ax.scatter(
            p[idx, a], p[idx, b], s=0.6, c=colors[cloud.camera[idx]], linewidths=0, rasterized=True
        )
        _draw_rig(ax, report, frame, (a, b), list(map(tuple, colors)), boards=False)
    top.set(title="fused cloud, top view (colour = camera)", xlabel="e1 (m)", ylabel="e2 (m)")
    side.set(title="fused cloud, side view", xlabel="e1 (m)", ylabel="up (m)")
    return _png(fig)


def fig_histograms(report: dict[str, Any]) -> str:
    names = list(report["cameras"])
    edges = np.asarray(report["reprojection_histogram_edges_px"])
    cols = min(4, len(names))
    rows = math.ceil(len(names) / cols)
    fig, axes = _figure(2.8 * cols, 2.0 * rows, nrows=rows, ncols=cols, squeeze=False, sharex=True)
    colors = _palette(report)
    rig_p50 = _median([(c["reprojection_px"] or {}).get("p50") for c in report["cameras"].values()])
    flagged = {c for w in report["warnings"] if w["severity"] != "info" for c in w["cameras"]}
    for k, ax in enumerate(axes.ravel()):
        if k >= len(names):
            ax.axis("off")
            continue
        name = names[k]
        cam = report["cameras"][name]
        h = cam["reprojection_histogram"]
        ax.bar(edges[:-1], h["used"], width=np.diff(edges), align="edge", color=colors[k])
        ax.bar(
            edges[:-1],
            h["excluded"],
            width=np.diff(edges),
            align="edge",
            bottom=h["used"],
            color="0.6",
            label="excluded",
        )
        st = cam["reprojection_px"]
        if st:
            ax.axvline(min(st["p50"], edges[-1]), color="k", lw=1)
            ax.axvline(min(st["p90"], edges[-1]), color="k", lw=1, ls=":")
        if rig_p50:
            ax.axvline(rig_p50, color="0.35", lw=0.9, ls="--")
        over = h["used"][-1] + h["excluded"][-1]
        if over:
            ax.annotate(
                f"last bin: {over} >= {edges[-2]:.2g} px",
                (1, 1),
                xycoords="axes fraction",
                ha="right",
                va="top",
                fontsize=7,
            )
        title = f"{name}: p50 {_fmt(st['p50'] if st else None)} px"
        ax.set_title(title, color="red" if name in flagged else "black", fontsize=9)
        ax.set_xlim(0, edges[-1])
    for ax in axes[-1]:
        ax.set_xlabel("marker reprojection RMS (px)")
    for ax in axes[:, 0]:
        ax.set_ylabel("markers")
    return _png(fig)


def fig_edges(report: dict[str, Any]) -> str:
    """Residual of every pose-graph edge (camera, board view), like the thesis's Fig. 5.2."""
    names = list(report["cameras"])
    colors = _palette(report)
    views = report["views"]
    fig, axes = _figure(11, 6.2, nrows=3, sharex=True)
    x = np.arange(len(views))
    panels = (
        ("edge_translation_mm", "translation residual (mm)"),
        ("edge_rotation_deg", "rotation residual (deg)"),
        ("final_reprojection_rms_px", "final reprojection RMS (px)"),
    )
    for ax, (key, label) in zip(axes, panels):
        for k, name in enumerate(names):
            sel = [
                i
                for i, v in enumerate(views)
                if v["camera"] == name and v[key] is not None and v["edge_status"] == "used"
            ]
            ax.scatter(
                x[sel],
                [max(views[i][key], 1e-4) for i in sel],
                s=9,
                color=colors[k],
                label=name if key == panels[0][0] else None,
            )
        bad = [
            i
            for i, v in enumerate(views)
            if v["edge_status"] in ("outlier", "stale") and v[key] is not None
        ]
        if bad:
            ax.scatter(
                x[bad],
                [max(views[i][key], 1e-4) for i in bad],
                s=30,
                marker="x",
                color="red",
                label="outlier / stale" if key == panels[0][0] else None,
            )
        ax.set_yscale("log")
        ax.set_ylabel(label)
        ax.grid(True, which="major", lw=0.3, alpha=0.6)
    axes[0].legend(
        ncol=min(len(names) + 1, 9),
        fontsize=7,
        loc="lower left",
        bbox_to_anchor=(0, 1.02),
        frameon=False,
    )
    axes[-1].set_xlabel("edge id (board views in frame order, cameras within a frame)")
    return _png(fig)


def fig_covisibility(report: dict[str, Any]) -> str:
    cov = report["covisibility"]
    names, m = cov["cameras"], np.asarray(cov["views"])
    n = len(names)
    fig, ax = _figure(1.2 + 0.55 * n, 1.0 + 0.5 * n)
    off = m.astype(float).copy()
    np.fill_diagonal(off, np.nan)
    im = ax.imshow(
        np.where(np.eye(n, dtype=bool), np.nan, m),
        cmap="viridis",
        vmin=0,
        vmax=max(np.nanmax(off) if n > 1 else 1, 1),
    )
    for i in range(n):
        for j in range(n):
            ax.text(
                j,
                i,
                str(m[i, j]),
                ha="center",
                va="center",
                fontsize=8,
                color="black"
                if i == j
                else ("white" if m[i, j] < 0.6 * np.nanmax(off if n > 1 else m) else "black"),
                fontweight="bold" if i == j else "normal",
            )
    ax.set_xticks(range(n), names, rotation=45, ha="right")
    ax.set_yticks(range(n), names)
    ax.set_title("board views shared (diagonal: views used)")
    fig.colorbar(im, ax=ax, shrink=0.8, label="shared views")
    return _png(fig)


def fig_coverage(report: dict[str, Any]) -> str:
    """Where in each image the board was: how many used views' marker bounding boxes cover
    each cell (views left out are not counted)."""
    names = list(report["cameras"])
    cols = min(4, len(names))
    rows = math.ceil(len(names) / cols)
    fig, axes = _figure(2.8 * cols, 1.9 * rows, nrows=rows, ncols=cols, squeeze=False)
    gx, gy = COVERAGE_GRID
    for k, ax in enumerate(axes.ravel()):
        if k >= len(names):
            ax.axis("off")
            continue
        name = names[k]
        cam = report["cameras"][name]
        w, h = cam["intrinsics"]["width"], cam["intrinsics"]["height"]
        uu, vv = np.meshgrid((np.arange(gx) + 0.5) * w / gx, (np.arange(gy) + 0.5) * h / gy)
        count = np.zeros(uu.shape)
        left_out = 0
        for v in report["views"]:
            if v["camera"] != name:
                continue
            if v["edge_status"] != "used":
                left_out += 1
                continue
            u0, v0, u1, v1 = v["image_bbox_px"]
            count += (u0 <= uu) & (uu <= u1) & (v0 <= vv) & (vv <= v1)
        ax.imshow(
            np.where(count > 0, count, np.nan),
            cmap="viridis",
            vmin=0,
            vmax=max(count.max(), 1),
            extent=(0, w, h, 0),
            interpolation="nearest",
        )
        ax.set_facecolor("#f3f3f3")
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_xticks([])
        ax.set_yticks([])
        cov = cam["coverage"]
        extra = f", {left_out} left out" if left_out else ""
        ax.set_title(f"{name}: {cov['image_fraction']:.0%} covered{extra}", fontsize=9)
    return _png(fig)


def fig_distance(report: dict[str, Any]) -> str:
    """Board distance and tilt of every view per camera (front o, back s, left out x)."""
    names = list(report["cameras"])
    colors = _palette(report)
    fig, (ad, at) = _figure(11, 3.0, ncols=2)
    for k, name in enumerate(names):
        mine = [v for v in report["views"] if v["camera"] == name]
        x = k + 0.05 * ((np.arange(len(mine)) % 7) - 3)  # spread one camera's dots a little
        for marker, color, pick in (
            ("o", colors[k], lambda v: v["edge_status"] == "used" and v["face"] != "back"),
            ("s", colors[k], lambda v: v["edge_status"] == "used" and v["face"] == "back"),
            ("x", "red", lambda v: v["edge_status"] != "used"),
        ):
            sel = [i for i, v in enumerate(mine) if pick(v)]
            if not sel:
                continue
            for ax, key in ((ad, "distance_m"), (at, "tilt_deg")):
                ax.scatter(x[sel], [mine[i][key] for i in sel], s=16, marker=marker, color=color)
    for ax, label in ((ad, "board distance (m)"), (at, "board tilt to the ray (deg)")):
        ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
        ax.set_ylabel(label)
        ax.grid(True, lw=0.3, alpha=0.6)
    ad.set_title("distance per view (o front face, s back face, x left out)")
    at.set_title("tilt per view")
    return _png(fig)


def fig_markers(report: dict[str, Any]) -> str:
    ms = report["markers"]
    fig, ax = _figure(11, 2.4)
    if ms:
        x = np.arange(len(ms))
        ax.bar(
            x,
            [m["rms_px"] for m in ms],
            color=["tab:blue" if m["face"] == "front" else "tab:orange" for m in ms],
        )
        ax.set_xticks(x, [str(m["id"]) for m in ms], fontsize=7)
        med = _median([m["rms_px"] for m in ms])
        ax.axhline(med, color="k", lw=0.8, ls="--")
    ax.set(
        xlabel="marker id (blue front face, orange back face)",
        ylabel="reprojection RMS (px)",
        title="final reprojection error per marker",
    )
    return _png(fig)


def fig_error_maps(report: dict[str, Any]) -> str:
    pairs = [p for p in report["pairs"] if p["error_map"]]
    cols = min(3, len(pairs))
    rows = math.ceil(len(pairs) / cols)
    fig, axes = _figure(3.6 * cols, 2.4 * rows, nrows=rows, ncols=cols, squeeze=False)
    vals = np.array([v for p in pairs for v in p["error_map"]["values_mm"] if v is not None])
    lim = float(np.percentile(np.abs(vals), 95)) if vals.size else 1.0
    im = None
    for k, ax in enumerate(axes.ravel()):
        if k >= len(pairs):
            ax.axis("off")
            continue
        em = pairs[k]["error_map"]
        grid = np.array([np.nan if v is None else v for v in em["values_mm"]], float)
        im = ax.imshow(
            grid.reshape(em["rows"], em["cols"]),
            cmap="coolwarm",
            vmin=-lim,
            vmax=lim,
            extent=(0, em["width"], em["height"], 0),
        )
        ax.set_title(f"{pairs[k]['cam_a']} vs {pairs[k]['cam_b']}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.8, label="point-to-plane distance (mm)")
    return _png(fig)


# ----------------------------------------------------------------------------- html
_CSS = """
body{font:14px/1.45 system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;color:#1d2330;
background:#f4f5f7}
main{max-width:1180px;margin:0 auto;padding:18px 24px 60px}
h1{font-size:24px;margin:8px 0 2px}h2{font-size:18px;margin:30px 0 8px;border-bottom:2px solid
#d9dce3;padding-bottom:4px}.sub{color:#5b6475;font-size:13px}
section{background:#fff;border-radius:8px;padding:6px 18px 14px;margin:14px 0;
box-shadow:0 1px 2px rgba(0,0,0,.08)}
table{border-collapse:collapse;font-size:12.5px;margin:6px 0}th,td{padding:3px 7px;
border-bottom:1px solid #e3e5ea;text-align:right;white-space:nowrap}th{white-space:normal;
vertical-align:bottom}.scroll{overflow-x:auto}
.l{text-align:left;white-space:normal}th{background:#f0f2f5;
font-weight:600}td:first-child,th:first-child{text-align:left}
.verdict{display:inline-block;padding:3px 12px;border-radius:14px;font-weight:700;
color:#fff;margin-left:8px;font-size:15px;vertical-align:middle}
.good{background:#2e8b57}.check{background:#d08a00}.poor{background:#c0392b}
.w{border-left:5px solid;padding:6px 10px;margin:6px 0;border-radius:4px;background:#fafbfc}
.w.error{border-color:#c0392b}.w.warning{border-color:#d08a00}.w.info{border-color:#5b7db1}
.w b.sev{text-transform:uppercase;font-size:11px;margin-right:6px}
.w .adv{color:#3b4252;margin-top:2px}.bad{color:#c0392b;font-weight:600}
img.fig{max-width:100%;height:auto;display:block;margin:6px 0}
.cap{color:#5b6475;font-size:12.5px;margin:2px 0 8px}
#viewer{width:100%;height:560px;background:#11151c;border-radius:6px;cursor:grab;display:block}
.legend span{display:inline-block;margin:2px 10px 2px 0;font-size:12.5px}
.legend i{display:inline-block;width:11px;height:11px;border-radius:2px;margin-right:4px;
vertical-align:-1px}button{font:inherit;font-size:12.5px;padding:3px 10px;margin:4px 6px 4px 0;
border:1px solid #b8bfcc;background:#fff;border-radius:4px;cursor:pointer}
details{margin:6px 0}code{font-size:12.5px}ol li{margin:3px 0}
"""

_JS_GUARD = """
(function(){var b=document.documentElement;function add(m){b.dataset.jsErrors=
(b.dataset.jsErrors||'')+m+'\\n';}window.addEventListener('error',function(e){add(e.message||
'resource error');},true);window.addEventListener('unhandledrejection',function(e){add(
String(e.reason));});})();
"""

_JS_VIEWER = r"""
(function(){
var D=JSON.parse(document.getElementById('viewer-data').textContent);
var cv=document.getElementById('viewer'),ctx=cv.getContext('2d');
function dec(s,T){var b=atob(s),u=new Uint8Array(b.length);for(var i=0;i<b.length;i++)
u[i]=b.charCodeAt(i);return new T(u.buffer);}
var n=D.cloud?D.cloud.n:0,P=new Float32Array(3*n),C=n?dec(D.cloud.cam,Uint8Array):null,
RGB=(n&&D.cloud.rgb)?dec(D.cloud.rgb,Uint8Array):null;
if(n){var q=dec(D.cloud.xyz,Int16Array);for(var i=0;i<3*n;i++)P[i]=q[i]*D.cloud.scale+
D.cloud.offset[i%3];}
var st={yaw:-0.6,pitch:0.5,dist:D.dist,rgb:false,boards:true};
function home(){st.yaw=-0.6;st.pitch=0.5;st.dist=D.dist;}
function project(W,H){var cy=Math.cos(st.yaw),sy=Math.sin(st.yaw),cp=Math.cos(st.pitch),
sp=Math.sin(st.pitch),f=0.9*Math.min(W,H),t=D.target;return function(x,y,z){x-=t[0];y-=t[1];
z-=t[2];var x1=cy*x-sy*y,y1=sy*x+cy*y,y2=cp*y1-sp*z,z2=sp*y1+cp*z,d=st.dist+y2;
if(d<0.05)return null;return [W/2+f*x1/d,H/2-f*z2/d,d];};}
function draw(){var r=window.devicePixelRatio||1,W=Math.max(cv.clientWidth,300)*r,
H=Math.max(cv.clientHeight,200)*r;cv.width=W;cv.height=H;var pr=project(W,H);
var img=ctx.createImageData(W,H),px=img.data,zb=new Float32Array(W*H).fill(1e9),s=Math.max(
2,Math.round(2*r)),drawn=0;for(var k=3;k<px.length;k+=4){px[k-3]=17;px[k-2]=21;px[k-1]=28;
px[k]=255;}for(var i=0;i<n;i++){var p=pr(P[3*i],P[3*i+1],P[3*i+2]);if(!p)continue;var u=p[0]|0,
v=p[1]|0;if(u<0||v<0||u>=W-s||v>=H-s)continue;var c=st.rgb&&RGB?[RGB[3*i],RGB[3*i+1],
RGB[3*i+2]]:D.colors[C[i]];drawn++;for(var a=0;a<s;a++)for(var b=0;b<s;b++){var o=(v+b)*W+u+a;
if(p[2]<zb[o]){zb[o]=p[2];px[4*o]=c[0];px[4*o+1]=c[1];px[4*o+2]=c[2];}}}
ctx.putImageData(img,0,0);function line(a,b,col,w){var p=pr(a[0],a[1],a[2]),
q=pr(b[0],b[1],b[2]);if(!p||!q)return;ctx.strokeStyle=col;ctx.lineWidth=w*r;ctx.beginPath();
ctx.moveTo(p[0],p[1]);ctx.lineTo(q[0],q[1]);ctx.stroke();}
if(st.boards)D.boards.forEach(function(b){for(var j=0;j<4;j++)line(b[j],b[(j+1)%4],
'rgba(200,200,200,0.55)',1);});
D.cameras.forEach(function(c){var col='rgb('+c.color.join(',')+')',f=c.frustum,w=c.ref?2.5:1.5;
for(var j=1;j<5;j++){line(f[0],f[j],col,w);line(f[j],f[j%4+1],col,w);}var p=pr(f[0][0],f[0][1],
f[0][2]);if(p){ctx.fillStyle=col;ctx.font=(12*r)+'px sans-serif';ctx.fillText(c.name+(c.ref?
' (ref)':''),p[0]+4*r,p[1]-4*r);}});
cv.dataset.pointsDrawn=drawn;cv.dataset.frames=(+cv.dataset.frames||0)+1;}
var drag=null;cv.addEventListener('mousedown',function(e){drag=[e.clientX,e.clientY];});
window.addEventListener('mouseup',function(){drag=null;});
window.addEventListener('mousemove',function(e){if(!drag)return;st.yaw+=(e.clientX-drag[0])*
0.008;st.pitch=Math.max(-1.57,Math.min(1.57,st.pitch+(e.clientY-drag[1])*0.008));
drag=[e.clientX,e.clientY];draw();});
cv.addEventListener('wheel',function(e){e.preventDefault();st.dist*=Math.exp(e.deltaY*0.001);
draw();},{passive:false});
function btn(id,fn){document.getElementById(id).addEventListener('click',function(){fn();draw();
});}
btn('v-top',function(){st.pitch=1.5707;st.yaw=0;});btn('v-side',function(){st.pitch=0;
st.yaw=0;});btn('v-home',home);btn('v-color',function(){st.rgb=!st.rgb;});
btn('v-boards',function(){st.boards=!st.boards;});
window.addEventListener('resize',draw);draw();cv.dataset.ready='yes';
})();
"""

_JS_READY = """
(function(){function check(){var imgs=Array.prototype.slice.call(document.images),
done=imgs.every(function(i){return i.complete;}),cv=document.getElementById('viewer');
if(!done||!cv||cv.dataset.ready!=='yes'){return setTimeout(check,50);}
var broken=imgs.filter(function(i){return !(i.naturalWidth>0);}).length,b=document.body;
b.dataset.images=imgs.length;b.dataset.brokenImages=broken;
b.dataset.reportReady=broken===0?'yes':'broken';}
if(document.readyState==='complete')check();else window.addEventListener('load',check);})();
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _num(x: float | None, digits: int = 3, unit: str = "") -> str:
    if x is None:
        return '<span class="sub">n/a</span>'
    text = f"{x:.{digits}f}"
    return (text.lstrip("-") if float(text) == 0 else text) + unit


def _img(b64: str, alt: str) -> str:
    return f'<img class="fig" alt="{_e(alt)}" src="data:image/png;base64,{b64}">'


def _table(headers: Sequence[str], rows: Sequence[Sequence[str]], left: Sequence[int] = ()) -> str:
    """An HTML table; columns in ``left`` are left-aligned text."""

    def cell(tag: str, k: int, c: str) -> str:
        return f"<{tag} class='l'>{c}</{tag}>" if k in left else f"<{tag}>{c}</{tag}>"

    head = "".join(cell("th", k, h) for k, h in enumerate(headers))
    body = "".join(
        "<tr>" + "".join(cell("td", k, c) for k, c in enumerate(r)) + "</tr>" for r in rows
    )
    return (
        f"<div class='scroll'><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody>"
        "</table></div>"
    )


def _viewer_data(report: dict[str, Any], cloud: Cloud | None, frame: np.ndarray) -> str:
    """JSON for the inline 3D viewer, in display coordinates (e1, e2, up); the cloud as
    base64 int16 steps of `scale` metres (>= 1 mm) around its centre, camera index and RGB
    as base64 bytes."""
    colors = [[int(round(255 * c)) for c in col] for col in _palette(report)]
    size = _rig_size(report)
    cams = []
    for i, (name, cam) in enumerate(report["cameras"].items()):
        if cam["T_ref_cam"] is None:
            continue
        ref = name == report["reference"]
        cams.append(
            {
                "name": name,
                "ref": ref,
                "color": colors[i],
                "frustum": np.round(_frustum(cam, 0.12 * size) @ frame.T, 4).tolist(),
            }
        )
    boards = [
        np.round(_board_outline(report, np.asarray(b["T_ref_board"], float)) @ frame.T, 4).tolist()
        for b in report["board_views"]
    ]
    # look at the middle of cameras and board poses, from far enough to see all of them
    centres = np.array([c["frustum"][0] for c in cams])
    origins = (
        np.array(
            [np.asarray(b["T_ref_board"], float)[:3, 3] for b in report["board_views"]]
        ).reshape(-1, 3)
        @ frame.T
    )
    target = (centres.mean(0) + origins.mean(0)) / 2 if len(origins) else centres.mean(0)
    radius = float(np.linalg.norm(np.vstack([centres, origins]) - target, axis=1).max())
    data: dict[str, Any] = {
        "cameras": cams,
        "boards": boards,
        "colors": colors,
        "target": np.round(target, 4).tolist(),
        "dist": round(3.0 * max(radius, 0.2 * size) + 0.5, 3),
        "cloud": None,
    }
    if cloud is not None and len(cloud.points):
        p = cloud.points @ frame.T
        offset = np.round((p.max(0) + p.min(0)) / 2, 3)
        scale = max(float(np.abs(p - offset).max()) / 32000.0, 0.001)
        q = np.clip(np.round((p - offset) / scale), -32767, 32767).astype("<i2")
        data["cloud"] = {
            "n": int(len(p)),
            "scale": scale,
            "offset": offset.tolist(),
            "xyz": base64.b64encode(q.tobytes()).decode("ascii"),
            "cam": base64.b64encode(cloud.camera.astype(np.uint8).tobytes()).decode("ascii"),
            "rgb": None
            if cloud.rgb is None
            else base64.b64encode(np.ascontiguousarray(cloud.rgb, np.uint8).tobytes()).decode(),
        }
    return json.dumps(data, separators=(",", ":")).replace("</", "<\\/")


def render_html(
    report: dict[str, Any],
    cloud: Cloud | None,
    no_cloud_reason: str = "",
    tick: Callable[[int], None] | None = None,
) -> str:
    """The report page: one self-contained HTML string (figures as base64 PNG, inline JS)."""
    tick = tick or (lambda n=1: None)
    summ, cams, names = report["summary"], report["cameras"], list(report["cameras"])
    frame = display_frame(report)
    figs = {}
    for key, fn in (
        ("rig", lambda: fig_rig(report, frame)),
        ("hist", lambda: fig_histograms(report)),
        ("edges", lambda: fig_edges(report)),
        ("covis", lambda: fig_covisibility(report)),
        ("coverage", lambda: fig_coverage(report)),
        ("distance", lambda: fig_distance(report)),
        ("markers", lambda: fig_markers(report)),
        ("cloud", lambda: fig_cloud(report, cloud, frame) if cloud else None),
        (
            "errmap",
            lambda: (
                fig_error_maps(report) if any(p["error_map"] for p in report["pairs"]) else None
            ),
        ),
    ):
        figs[key] = fn()
        tick(1)
    colors = _palette(report)
    flagged = {
        c: w["severity"]
        for w in reversed(report["warnings"])
        if w["severity"] != "info"
        for c in w["cameras"]
    }
    ds = report["dataset"]
    out: list[str] = []
    add = out.append
    add(
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width,initial-scale=1'>"
        f"<title>rgbd-calib report: {_e(ds.get('path') or '')}</title>"
        f"<style>{_CSS}</style><script>{_JS_GUARD}</script></head><body><main>"
    )
    add(
        f"<h1>Calibration report <span class='verdict {summ['verdict']}'>"
        f"{_e(summ['verdict'].upper())}</span></h1>"
    )
    add(
        f"<div class='sub'>dataset <code>{_e(ds.get('path'))}</code> &middot; method "
        f"<b>{_e(report['method'])}</b> &middot; reference camera <b>{_e(report['reference'])}"
        f"</b> (world frame = its colour optical frame: x right, y down, z forward) &middot; "
        f"rgbd-calib {_e(report['rgbd_calib_version'])}, report schema "
        f"{_e(report['schema_version'])}</div>"
    )

    add("<section><h2>Verdict and what to do next</h2>")
    verdict_text = {
        "good": "No camera or view needs attention: these extrinsics can be used.",
        "check": "Usable, but some cameras or views need a look (warnings below).",
        "poor": "Do not use these extrinsics as they are: fix the errors below and re-run.",
    }[summ["verdict"]]
    add(f"<p><b>{verdict_text}</b></p>")
    if report["warnings"]:
        for w in report["warnings"]:
            add(
                f"<div class='w {w['severity']}'><b class='sev'>{w['severity']}</b>"
                f"<code>{_e(w['code'])}</code> {_e(w['message'])}"
                + (f"<div class='adv'>&rarr; {_e(w['advice'])}</div>" if w["advice"] else "")
                + "</div>"
            )
    else:
        add("<p>No warnings.</p>")
    if report["next_steps"]:
        add(
            "<h3>Next steps, in order</h3><ol>"
            + "".join(f"<li>{_e(s)}</li>" for s in report["next_steps"])
            + "</ol>"
        )
    add("</section>")

    worst_r, worst_t = summ["worst_sigma_rotation_deg"], summ["worst_sigma_translation_mm"]
    rows = [
        ("cameras calibrated", f"{summ['n_calibrated']} / {summ['n_cameras']}", ""),
        ("frame sets", summ["n_frames"], ""),
        ("board poses (views of the board)", summ["n_board_views"], ""),
        ("camera views used / dropped", f"{summ['n_views_used']} / {summ['n_views_dropped']}", ""),
        ("markers used / excluded", f"{summ['n_markers_used']} / {summ['n_markers_excluded']}", ""),
        ("pose-graph outlier views", summ["n_outlier_edges"], ""),
        ("reprojection RMS, whole rig", _num(summ["reprojection_rms_px"], 3), "px"),
        (
            "median camera reprojection RMS",
            _num(summ["median_camera_reprojection_rms_px"], 3),
            "px",
        ),
        (
            "median 1-sigma rotation / translation",
            f"{_num(summ['median_sigma_rotation_deg'], 4)} / "
            f"{_num(summ['median_sigma_translation_mm'], 3)}",
            "deg / mm",
        ),
        (
            "worst 1-sigma rotation",
            (f"{worst_r['value']:.4f} ({_e(worst_r['camera'])})" if worst_r else "n/a"),
            "deg",
        ),
        (
            "worst 1-sigma translation",
            (f"{worst_t['value']:.3f} ({_e(worst_t['camera'])})" if worst_t else "n/a"),
            "mm",
        ),
        (
            "median edge residual translation / rotation",
            f"{_num(summ['median_edge_translation_mm'], 3)} / "
            f"{_num(summ['median_edge_rotation_deg'], 4)}",
            "mm / deg",
        ),
    ]
    if "bundle" in report:
        rows.append(
            (
                "bundle: corner noise estimated",
                _num(report["bundle"]["pixel_sigma_estimated"], 3),
                "px",
            )
        )
    add(
        "<section><h2>Summary</h2>"
        + _table(["quantity", "value", "unit"], [(a, str(b), c) for a, b, c in rows])
    )
    cam_rows = []
    for i, name in enumerate(names):
        c = cams[name]
        rep, t = c["reprojection_all_px"] or {}, c["translation_m"] or [None] * 3
        cov = c["coverage"]
        d = cov["distance_m"]
        sw = (
            "<i style='display:inline-block;width:10px;height:10px;margin-right:5px;"
            f"background:rgb{tuple(int(255 * v) for v in colors[i])}'></i>"
        )
        label = f"<span class='bad'>{_e(name)}</span>" if name in flagged else _e(name)
        cam_rows.append(
            [
                sw + label + (" (ref)" if name == report["reference"] else ""),
                "yes" if c["calibrated"] else "<span class='bad'>no</span>",
                f"{c['views_used']} / {c['views_dropped']}",
                str(c["edge_outliers"]),
                _num(rep.get("p50"), 3),
                _num(rep.get("p90"), 3),
                _num(c["sigma_rotation_deg"], 4),
                _num(c["sigma_translation_mm"], 3),
                " ".join(_num(v, 3) for v in t),
                f"{d['min']:.2f}-{d['max']:.2f}" if d else "n/a",
                f"{cov['faces']['front']}/{cov['faces']['back']}",
                f"{cov['image_fraction']:.0%}",
                _num(c["depth_scale_factor"], 4),
            ]
        )
    add(
        "<h3>Cameras</h3>"
        + _table(
            [
                "camera",
                "calibrated",
                "views used / dropped",
                "outlier views",
                "reproj. p50 (px)",
                "reproj. p90 (px)",
                "&sigma; rot (deg)",
                "&sigma; trans (mm)",
                "x y z (m)",
                "board dist. (m)",
                "faces front/back",
                "image covered",
                "depth scale factor",
            ],
            cam_rows,
        )
    )
    add(
        "<p class='cap'>Reprojection: RMS over each marker's 4 corners of the board corners "
        "projected through the final camera and board poses, over all of the camera's views "
        "(also the excluded ones). &sigma;: 1-sigma marginal uncertainty of T_ref_cam "
        "(largest single axis). Depth scale factor: measured / true depth (depth stage; n/a "
        "until it runs).</p></section>"
    )

    add("<section><h2>Rig layout</h2>" + _img(figs["rig"], "top and side views of the rig"))
    add(
        "<p class='cap'>Camera frusta (reference camera in red) and every board pose (grey "
        "outlines; RGB axes = board x, y, z for a subset, as in the thesis's Figure 4.11). "
        "Axes: <i>up</i> = minus the cameras' mean image-down direction, <i>e1</i> = the "
        "horizontal direction along which the cameras spread most, e2 = up &times; e1.</p>"
        "</section>"
    )

    add(
        "<section><h2>3D view</h2><div><button id='v-home'>reset</button><button id='v-top'>"
        "top</button><button id='v-side'>side</button><button id='v-color'>colour: camera / "
        "RGB</button><button id='v-boards'>board poses on/off</button> <span class='sub'>"
        "drag to orbit, scroll to zoom</span></div><canvas id='viewer'></canvas>"
        "<div class='legend'>"
        + "".join(
            f"<span><i style='background:rgb{tuple(int(255 * v) for v in colors[i])}'></i>"
            f"{_e(n)}</span>"
            for i, n in enumerate(names)
        )
        + "</div>"
    )
    add(
        f"<p class='cap'>{_e(cloud.source) if cloud else 'No point cloud: ' + _e(no_cloud_reason)}"
        "</p></section>"
    )

    add("<section><h2>Fused cloud</h2>")
    if figs["cloud"]:
        add(_img(figs["cloud"], "fused point cloud, top and side views"))
        add(
            "<p class='cap'>Coloured by camera: where two colours meet, the cameras agree if the "
            "surfaces coincide (a doubled wall or floor means an extrinsic or depth-scale "
            "error). " + _e(cloud.source if cloud else "") + "</p>"
        )
    else:
        add(f"<p><b>No depth</b>: {_e(no_cloud_reason)}.</p>")
    add("</section>")

    add(
        "<section><h2>Reprojection error per camera</h2>"
        + _img(figs["hist"], "per-camera reprojection error histograms")
    )
    add(
        "<p class='cap'>Per-marker RMS reprojection error (px) through the calibrated poses. "
        "Black: the camera's median (solid) and 90th percentile (dotted) over used markers; "
        "grey dashed: the rig's median camera; grey bars: markers the estimate excluded (outlier "
        "views or markers). A camera whose histogram sits right of the others has wrong "
        "intrinsics, blur or sync problems.</p></section>"
    )

    add("<section><h2>Residual by edge</h2>" + _img(figs["edges"], "residual by edge"))
    add(
        "<p class='cap'>Each pose-graph edge is one camera seeing one board pose (as in the "
        "thesis's Figure 5.2). Top: translation and rotation between the measured board pose "
        "(PnP) and the calibrated prediction; bottom: that view's final reprojection RMS. "
        "Red crosses: outlier or stale edges left out of the estimate.</p></section>"
    )

    add("<section><h2>Co-visibility</h2>" + _img(figs["covis"], "co-visibility matrix"))
    add(
        "<p class='cap'>Number of board poses two cameras both contributed to the estimate; a "
        "camera tied to the rest by few shared views is weakly constrained.</p></section>"
    )

    add(
        "<section><h2>Board coverage</h2>"
        + _img(figs["coverage"], "board coverage per camera")
        + _img(figs["distance"], "board distance and tilt per camera")
    )
    add(
        "<p class='cap'>Where the board was in each image (number of used views whose marker "
        "bounding box covers each spot; grey = never), and its distance and tilt. Good sets "
        "cover the whole image, several distances and tilts of 20-50 degrees.</p>"
    )
    next_rows = []
    for name in names:
        cov = cams[name]["coverage"]
        d, t = cov["distance_m"], cov["tilt_deg"]
        next_rows.append(
            [
                _e(name),
                f"{cov['image_fraction']:.0%}",
                _e(", ".join(cov["missing_regions"]) or "none"),
                f"{d['min']:.2f}-{d['max']:.2f}" if d else "n/a",
                f"{t['min']:.0f}-{t['max']:.0f}" if t else "n/a",
                f"{cov['faces']['front']} / {cov['faces']['back']}",
                f"{cov['max_shared_views']} ({_e(cov['best_partner'] or '-')})",
            ]
        )
    add(
        "<h3>Where to put the board next</h3>"
        + _table(
            [
                "camera",
                "image covered",
                "image regions never reached",
                "distance (m)",
                "tilt (deg)",
                "views front / back face",
                "most views shared with",
            ],
            next_rows,
            left=(2,),
        )
        + "</section>"
    )

    add("<section><h2>Markers</h2>" + _img(figs["markers"], "reprojection error per marker"))
    add(
        "<p class='cap'>A single marker far above the dashed median is misplaced, bent or "
        "peeling.</p></section>"
    )

    add("<section><h2>Camera pairs (depth)</h2>")
    if report["pairs"]:
        add(
            _table(
                [
                    "pair",
                    "overlap",
                    "ICP fitness",
                    "RMSE before (mm)",
                    "RMSE after (mm)",
                    "correction (deg / mm)",
                    "accepted",
                ],
                [
                    [
                        f"{_e(p['cam_a'])} &ndash; {_e(p['cam_b'])}",
                        _num(p["overlap_fraction"], 2),
                        _num(p["fitness"], 2),
                        _num(p["rmse_before_mm"], 2),
                        _num(p["rmse_after_mm"], 2),
                        f"{_num(p['correction_deg'], 3)} / {_num(p['correction_mm'], 2)}",
                        _e(p["accepted"] if p["accepted"] is not None else "n/a"),
                    ]
                    for p in report["pairs"]
                ],
            )
        )
        if figs["errmap"]:
            add(
                _img(figs["errmap"], "overlap error maps")
                + "<p class='cap'>Overlap error maps: point-to-plane distance (mm) of camera a's "
                "points to camera b's surface, over a's image; a ramp across the map is a "
                "rotation error, a uniform offset a depth-scale or translation error.</p>"
            )
    else:
        add(
            "<p>No camera pairs: the depth stage (pairwise ICP and overlap error maps) did not "
            "run for this result.</p>"
        )
    add("</section>")

    add("<section><h2>Dropped views</h2>")
    reasons = sorted({d["reason"] for d in report["dropped_views"]})
    if reasons:
        counts = [
            [_e(n)]
            + [
                str(
                    sum(1 for d in report["dropped_views"] if d["camera"] == n and d["reason"] == r)
                )
                for r in reasons
            ]
            for n in names
        ]
        add(_table(["camera"] + [_e(r) for r in reasons], counts))
        add(
            "<ul>"
            + "".join(
                f"<li><code>{_e(r)}</code>: {_e(DROP_ADVICE.get(r, ''))}</li>" for r in reasons
            )
            + "</ul>"
        )
        add(
            "<details><summary>every dropped view</summary>"
            + _table(
                ["camera", "frame", "reason", "markers", "detail"],
                [
                    [
                        _e(d["camera"]),
                        _e(d["frame"]),
                        _e(d["reason"]),
                        str(d["markers"]),
                        _e(d["detail"]),
                    ]
                    for d in report["dropped_views"]
                ],
                left=(2, 4),
            )
            + "</details>"
        )
    else:
        add("<p>No view was dropped.</p>")
    if report["pose_graph"]["outliers"]:
        add(
            "<h3>Outlier views (pose graph)</h3>"
            + _table(
                ["camera", "frame", "whitened residual"],
                [
                    [_e(o["camera"]), _e(o["view"]), f"{o['whitened_norm']:.1f}"]
                    for o in report["pose_graph"]["outliers"]
                ],
            )
        )
    add("</section>")
    add(
        "<p class='sub'>Rebuild this page from the saved folder with <code>rgbd-calib report "
        "DIR</code>; every number above is in <code>report.json</code> (schema "
        f"{_e(report['schema_version'])}, docs/report_schema.md).</p></main>"
    )
    add(
        f"<script type='application/json' id='viewer-data'>"
        f"{_viewer_data(report, cloud, frame)}</script>"
    )
    add(f"<script>{_JS_VIEWER}</script><script>{_JS_READY}</script></body></html>")
    return "\n".join(out)


def write_report_html(
    report: dict[str, Any], folder: Path, progress: Progress | None = None
) -> Path:
    """Write ``folder/report.html`` for a finalized report (cloud: ``folder/fused.ply``, else
    a preview from the dataset recorded in the report)."""
    from .yamlio import atomic_write_text

    folder = Path(folder)
    tick = progress("building report.html", 10, 0) if progress else None
    cloud, why = load_cloud(report, folder)
    if tick:
        tick(1)
    text = render_html(report, cloud, why, tick)
    path = folder / "report.html"
    atomic_write_text(path, text)
    return path


def rebuild_report(out_dir: Path, progress: Progress | None = None) -> Path:
    """Rebuild ``report.json`` and ``report.html`` of a calibration folder from its saved
    results alone (``report.json``, ``extrinsics.yaml``, ``fused.ply`` and the dataset folder
    recorded in the report). The derived sections are recomputed, so a report of this schema
    comes back byte-identical. Returns the path of ``report.html``."""
    from .results import load_extrinsics
    from .yamlio import atomic_write_text

    out_dir = Path(out_dir)
    path = out_dir / "report.json"
    if not path.is_file():
        raise ReportError(
            f"{path}: missing; is {out_dir} the --out folder of rgbd-calib calibrate?"
        )
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise ReportError(f"{path}: not valid JSON ({exc}); re-run calibrate") from None
    if not isinstance(report, dict) or "cameras" not in report:
        raise ReportError(f"{path}: not an rgbd-calib report; re-run calibrate")
    version = str(report.get("schema_version", "?"))
    if version.split(".")[0] != REPORT_SCHEMA_VERSION.split(".")[0]:
        raise ReportError(
            f"{path}: report schema {version} cannot be read by this rgbd-calib "
            f"(schema {REPORT_SCHEMA_VERSION}); re-run calibrate"
        )
    try:
        report["schema_version"] = REPORT_SCHEMA_VERSION
        for pair in report.get("pairs") or []:  # 1.1 added it; an older report has no value
            if isinstance(pair, dict):
                pair.setdefault("rmse_final_mm", None)
        report = finalize_report(report)
    except (KeyError, TypeError, ValueError) as exc:
        raise ReportError(
            f"{path}: incomplete report ({exc!r}; written by an older "
            "rgbd-calib?); re-run calibrate"
        ) from None
    errors = validate_report(report)
    if errors:
        raise ReportError(
            f"{path}: does not match report schema {REPORT_SCHEMA_VERSION}: "
            f"{'; '.join(errors[:3])}; re-run calibrate"
        )
    ext_path = out_dir / "extrinsics.yaml"
    if ext_path.is_file():
        ext = load_extrinsics(ext_path)
        for name, cam in ext.cameras.items():
            saved = report["cameras"].get(name, {}).get("T_ref_cam")
            if saved is None or not np.allclose(saved, cam.T_ref_cam, atol=1e-6):
                raise ReportError(
                    f"{ext_path}: camera {name} differs from {path}; the two "
                    "files come from different runs; re-run calibrate"
                )
    atomic_write_text(path, dump_report(report))
    return write_report_html(report, out_dir, progress)
