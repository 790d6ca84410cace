"""What ``report.json`` is: its schema version and key tree (docs/report_schema.md), the
checker, the thresholds of the findings, and the one way a report's numbers become JSON
(non-finite numbers to null, canonical text).

Numpy-free on purpose: the schema is the contract every other report module writes to.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

from ...core.errors import RgbdCalibError

REPORT_SCHEMA_VERSION = "1.29"


class ReportError(RgbdCalibError):
    """A calibration folder cannot be reported on (missing or inconsistent saved results)."""


def view_in_estimate(view: dict[str, Any]) -> bool:
    """Whether the final estimate used some marker of a ``views[]`` entry (without marker
    counts: whether the pose graph used its edge). With refined intrinsics the bundle
    adjustment also solves views the pose graph left out, so the two can differ."""
    if view["excluded_markers"] is None:
        return view["edge_status"] == "used"
    return view["excluded_markers"] < view["markers"]


# ----------------------------------------------------------------------------- thresholds
WEAK_SIGMA_FACTOR = 3.0  # a camera's sigma this many times the rig median is weak ...
WEAK_SIGMA_MIN_MM = 0.25  # ... and above these absolute floors (tiny sigmas are all fine)
WEAK_SIGMA_MIN_DEG = 0.01
FEW_VIEWS = 3  # fewer used views than this (or than FEW_VIEWS_FACTOR x the median): weak
FEW_VIEWS_FACTOR = 0.35
# ... but this many used views are never "few": on a long recording (race16 x 1000 sets, rig
# median 370) a camera with 123 views was flagged; how precise it is, is weak_camera's test
FEW_VIEWS_ENOUGH = 30
FEW_SHARED_VIEWS = 3  # a camera sharing fewer views with every other camera is weakly tied
INCONSISTENT_FRACTION = 0.3  # share of a camera's views that are pose-graph outliers
REPROJECTION_FACTOR = 3.0  # a camera's median reprojection error this many times the rig's ...
REPROJECTION_MIN_PX = 0.5  # ... and above this is suspect (intrinsics, blur, sync)
RIG_REPROJECTION_MAX_PX = 0.5  # the whole rig's RMS above this: check intrinsics / board
RIG_REPROJECTION_POOR_PX = 2.0  # ... above this the poses do not explain the images: POOR
MARKER_FACTOR = 3.0  # a marker id whose RMS is this many times the median marker's ...
MARKER_MIN_PX = 0.3  # ... and above this: check that marker on the board
COVERAGE_MIN = 0.35  # fraction of the image the board's views covered
DISTANCE_SPREAD_MIN = 1.3  # max/min board distance over a camera's views
TILT_SPREAD_MIN_DEG = 20.0  # range of board tilts seen by a camera
# edge_offset: a camera whose markers read at least this much larger or smaller per edge (px),
# by at least EDGE_OFFSET_SIGMAS standard errors; ~18 mm of extrinsics per px on the race and
# ring renders (docs/accuracy.md, "A detector's edge offset"), so 0.02 px is ~0.4 mm
EDGE_OFFSET_MIN_PX = 0.02
EDGE_OFFSET_SIGMAS = 5.0
# edge_size: a camera whose markers' edge bias grows with their size beyond the modelled offset
# (bundle.edge_offset.<camera>.size_mm) by at least EDGE_OFFSET_SIGMAS standard errors, its
# near markers reading at least this much more than its far ones (px per edge)
EDGE_SIZE_MIN_PX = 0.02
PAIR_RMSE_MAX_MM = 15.0  # point-to-plane RMSE after ICP above this: depth itself is off
# the joint extrinsics fit a pair worse than its own ICP did by more than this: the pair and
# the rest of the calibration disagree (depth noise alone gives ~5 mm at 2 m on a D435)
PAIR_FINAL_EXCESS_MM = 2.0
PAIR_FITNESS_MIN = 0.3
GLUE_SIGMAS = 3.0  # a back-sheet offset or rotation beyond this many sigma is real ...
GLUE_MIN_MM = 0.2  # ... and worth a corrected board file above this offset ...
GLUE_MIN_DEG = 0.05  # ... or this rotation
BOARD_SCALE_MIN = 0.01  # every camera's depth scale off by this much the same way: the print
BOARD_SIZE_EXAMPLE = 0.001  # the print error the board_size finding puts into millimetres
BOARD_SCALE_SPREAD = 0.003  # camera-to-camera depth-scale spread allowed on top of the sigmas
DEPTH_SCALE_TOL = 0.003  # |factor - 1| above this: the camera's depth needs its scale
REFINE_MOVE_SIGMAS = 3.0  # refine: a camera moved by more than this many initial sigmas
# depth_extrapolated: a camera with at least this fraction of its cloud beyond the board's
# depths, where its depth is known to worse than FAR_SIGMA_MM (1 sigma; the bound)
FAR_FRACTION = 0.25
FAR_SIGMA_MM = 1.0
# ... and a warning where it is known to worse than this (1 sigma): a centimetre, where one
# camera's surfaces stand visibly apart from another's (an untuned ring's cameras of 3 and 4
# board views: +-88 and +-124 mm, their clouds 31 and 47 mm off; docs/depth.md)
FAR_WARN_SIGMA_MM = 10.0
INTRINSICS_SUPPORT_MAX = 0.5  # a refined parameter's sigma above this x its prior's: the
# data added little to the rig.yaml value (few views, corners not reaching the image border)
COVERAGE_GRID = (48, 27)  # sample points across, down, for the image coverage of a camera
REGION_MIN = 0.1  # a 3x3 image region less covered than this counts as never reached
REGIONS = (
    ("top-left", "top", "top-right"),
    ("left", "centre", "right"),
    ("bottom-left", "bottom", "bottom-right"),
)
CORNER_REGIONS = ("top-left", "top-right", "bottom-left", "bottom-right")


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
SURFACE_DISTANCES = Block("surface_distances", {"n": INT, "median_mm": N, "median_se_mm": N,
                                                "p90_mm": N})

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
    "intrinsics_initial?": {"views": INT, "corners": INT, "rms_px": N, "image_fraction": N,
                            "fx": N, "fy": N, "cx": N, "cy": N, "distortion": ListOf(N)},
    "intrinsics_refined?": MapOf(
        "<param>",
        {"prior": N, "prior_sigma": Nullable(N), "refined": N, "sigma": Nullable(N),
         "change": N, "change_pct": Nullable(N)},
    ),
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
    "agrees": Nullable(B),
    "rejected_by": Nullable(ListOf(S)),
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
    "board": {
        "markers_seen": INT,
        "extent_m": Nullable(ListOf(N)),
        "thickness_m": Nullable(N),
        "marker_length_m?": N,
        "square_length_m?": N,
        "print_scale_sigma?": Nullable(N),
        "refined?": {
            "held": Nullable(S),
            "offset_mm": Nullable(ListOf(N)),
            "rotation_deg": Nullable(N),
            "thickness_mm": Nullable(N),
            "thickness_change_mm": Nullable(N),
            "sigmas": Nullable(
                {"offset_mm": ListOf(N), "rotation_deg": N, "thickness_mm": N}
            ),
            "T_front_back": MAT4,
        },
        "refined_faces?": ListOf({
            "face": INT,
            "held": Nullable(S),
            "offset_mm": Nullable(ListOf(N)),
            "rotation_deg": Nullable(ListOf(N)),
            "sigmas": Nullable({"offset_mm": ListOf(N), "rotation_deg": ListOf(N)}),
            "T_board_face": MAT4,
        }),
    },
    "cameras": MapOf("<camera>", CAMERA_SCHEMA),
    "unconnected": MapOf("<camera>", S),
    "pose_graph": {
        "edges": INT,
        "used": INT,
        "stale": INT,
        "outliers": ListOf({"camera": S, "view": S, "whitened_norm": N}),
        "model_error": ListOf(
            {
                "camera": S,
                "edges": INT,
                "outliers_before": INT,
                "translation_mm": Nullable(N),
                "rotation_deg": Nullable(N),
                "variance_factor": N,
                "sigma_factor": N,
            }
        ),
        "view_floor?": Nullable({"model_error_px": N, "misfit_ratio": Nullable(N),
                                 "edges": INT}),
    },
    "views_file?": {"path": S, "format": S, "count": INT, "sha256": S},
    "views?": ListOf(
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
    "depth_models?": MapOf("<camera>", {
        "terms": ListOf(S),
        "parameters": MapOf("<parameter>", N),
        "sigmas": MapOf("<parameter>", N),
        "bands": ListOf({"z_min_m": N, "z_max_m": N, "n": INT, "median_before_mm": N,
                         "median_after_mm": N, "p90_before_mm": N, "p90_after_mm": N,
                         "noise_mm": N}),
        "beyond_board?": {"board_max_m": N, "cloud_p90_m": N, "fraction": N, "sigma_mm": N,
                           "model_gap_mm?": N},
        "n_views?": INT,
        "held_out?": {"model": N, "identity": N, "views": INT, "rejected": B},
    }),
    "fused_agreement?": {
        "pairs": ListOf({"cam_a": S, "cam_b": S, "after": SURFACE_DISTANCES,
                         "before": Nullable(SURFACE_DISTANCES), "noise_p90_mm": N, "off": B}),
        "worst_bias_mm": Nullable(N),
        "worst_bias_before_mm": Nullable(N),
        "camera_bias_mm": MapOf("<camera>", N),
        "off_cameras": ListOf(S),
        "ambiguous": ListOf(ListOf(S)),
    },
    "motion?": ListOf({"frame": S, "cameras": ListOf(S), "outliers": ListOf(S),
                       "spread_mm": N, "speed_mps": Nullable(N), "moved": B}),
    "frame_selection?": {"kept": INT, "total": INT, "run_length": INT},
    "pairs": ListOf(PAIR_SCHEMA),
    "timings_s": MapOf("<stage>", N),
    "depth?": {"status": S, "reason": Nullable(S), "weak_cameras": MapOf("<camera>", S),
               "unmodelled?": MapOf("<camera>", S), "pair_variance_factor?": N,
               "pair_bias_sigma_mm?": N, "pair_bias_sigma_deg?": N,
               "sensor_pose_sigma_deg?": N, "sensor_pose_sigma_mm?": N,
               "overlap_models?": {
                   "iterations": INT,
                   "held_out?": {"update": N, "board": N, "pairs": INT, "rejected": B},
                   "cameras": MapOf("<camera>", {"shift_chi2": Nullable(N), "dof": INT}),
                   "pairs": ListOf({"cam_a": S, "cam_b": S, "median_mm": N, "se_mm": N,
                                    "n": INT, "median_after_mm": N, "se_after_mm": N})}},
    "refine?": {
        "init": S,
        "registration": S,
        "fix_others": B,
        "outcome": S,
        "message": S,
        "moved_since_init": ListOf(S),
        "unconfirmed?": MapOf("<camera>", S),
        "pair_variance_factor?": Nullable(N),
        "cameras": MapOf("<camera>", {"moved_mm": N, "moved_deg": N,
                                      "initial_sigma_mm": Nullable(N),
                                      "depth_scale_source": S}),
    },
    "bundle?": {
        "pixel_sigma_estimated": N,
        "iterations": INT,
        "markers": INT,
        "outlier_markers": ListOf({"camera": S, "view": S, "marker": INT, "rms_px": N}),
        "time?": {
            "anchored_by_timestamps": ListOf(S),
            "frames_matched_by?": S,
            "cameras": MapOf("<camera>", {"offset_ms": N, "offset_beyond_timestamps_ms": N,
                                          "offset_sigma_ms": N, "readout_ms": N,
                                          "readout_sigma_ms": N,
                                          "offset_prior_sigma_ms?": Nullable(N)}),
            "board_speed_mps": {"median": N, "max": N},
            "board_rate_dps": {"median": N, "max": N},
            "linked_sets?": INT,
            "motion_prior?": {"q_mps": N, "q_dps": N},
        },
        "corner_noise?": {"shape_sigma_px": N, "centre_sigma_px": N, "centre_ratio": N,
                          "scale_sigma_ppm": N},
        "run_correlation?": MapOf("<camera>", {"rho": N, "pairs": INT, "factor": N}),
        "edge_offset?": MapOf("<camera>", {"offset_px": N, "sigma_px": N, "markers": INT,
                                           "applied_px?": N, "size_mm?": N,
                                           "size_sigma_mm?": N, "size_effect_px?": N}),
        "self_calibration?": {
            "chosen": S,
            "board": B,
            "time?": B,
            "intrinsics_params": ListOf(S),
            "redetected": B,
            "levels": ListOf({
                "level": S, "board": B, "time?": B, "intrinsics_params": ListOf(S),
                "cameras": INT,
                "markers": INT, "rms_px": Nullable(N), "added_parameters": INT,
                "bic_gain": Nullable(N), "accepted": B, "reason": S,
                "held_out?": Nullable({"rms_before_px": N, "rms_after_px": N,
                                       "markers": INT, "views": INT}),
            }),
        },
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
    "method": {"bundle", "posegraph", "depth"},
    "outcome": {"refined", "unchanged", "check"},
    "depth_scale_source": {"board", "given", "unknown", "none"},
    "face": {"front", "back", "both", "several"},  # and face<k> (a multi-face target)
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
    if isinstance(report, dict) and ("views" in report) == ("views_file" in report):
        errors.append("<root>: needs exactly one of views (inline) and views_file (large rig)")
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
                if leaf and isinstance(value[name], str) and value[name] not in ENUMS[leaf] \
                        and not (leaf == "face" and re.fullmatch(r"face\d+", value[name])):
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


# ----------------------------------------------------------------------------- JSON
def finite_or_null(obj: Any) -> Any:
    """``obj`` with every non-finite float (NaN, inf) replaced by None, through dicts and
    lists: JSON has no NaN. The one sanitiser of every report this package (and the
    thesis pose-graph path) writes."""
    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [finite_or_null(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dump_report(report: dict[str, Any]) -> str:
    """The canonical text of ``report.json`` (what :func:`rebuild_report` reproduces)."""
    return json.dumps(report, indent=1, allow_nan=False) + "\n"
