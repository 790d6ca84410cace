"""The findings (``report.json`` ``warnings``): one rule per warning code over a report's
numbers, thresholds from :mod:`.schema`.

A rule takes the report and the findings of the rules before it (a camera already found
inconsistent or weak is not flagged again for what follows from that) and returns its own.
:data:`RULES` runs them in a fixed order; :func:`findings` sorts the result by severity
(stable, so the order within a severity is the rules' order).

The rules live by subject: :mod:`.findings_cameras`, :mod:`.findings_board` (where the board
was held, the refined lens and back sheet), :mod:`.findings_views` (views and markers),
:mod:`.findings_depth` (the depth stage, a depth-only refinement), :mod:`.findings_time`
(cameras that did not capture at one instant); :mod:`.findings_base` holds
what they share. This module orders them and re-exports every rule.
"""

from __future__ import annotations

from typing import Any

from ...model.results import Verdict
from .findings_base import (
    SEVERITY_ORDER,
    Finding,
    Rule,
    cameras_of,
    finding,
)
from .findings_board import (
    board_coverage,
    board_distance,
    board_glue,
    board_size,
    board_tilt,
    edge_offset,
    glue_sentence,
    intrinsics_unsupported,
    lens_coverage,
    scratch_coverage,
)
from .findings_cameras import (
    CameraCheck,
    camera_model_error,
    each_sound_camera,
    explained_model_errors,
    few_views,
    fitting_outliers,
    inconsistent_camera,
    not_calibrated,
    weak_camera,
    weak_link,
)
from .findings_depth import (
    board_scale,
    board_scale_sentence,
    common_depth_scale,
    confirming_pairs,
    depth_extrapolated,
    depth_scale,
    depth_scale_unknown,
    depth_unmodelled,
    depth_unused,
    each_pair,
    fused_disagrees,
    is_depth_only,
    pair_disagrees,
    pair_fitness,
    pair_rmse,
    refine_moved,
    refit_failed,
)
from .findings_time import (
    capture_time,
    moving_board,
    time_offsets_implausible,
    time_sentence,
    time_unresolved,
)
from .findings_views import (
    dropped_views,
    fitting_outlier_views,
    marker,
    outlier_views,
    reprojection,
    view_model_error,
)

__all__ = [
    "CameraCheck",
    "DEPTH_ONLY_RULES",
    "Finding",
    "RULES",
    "Rule",
    "SEVERITY_ORDER",
    "board_coverage",
    "board_distance",
    "board_glue",
    "board_size",
    "board_scale",
    "board_scale_sentence",
    "board_tilt",
    "camera_model_error",
    "cameras_of",
    "capture_time",
    "common_depth_scale",
    "confirming_pairs",
    "depth_extrapolated",
    "depth_scale",
    "depth_scale_unknown",
    "depth_unmodelled",
    "depth_unused",
    "dropped_views",
    "each_pair",
    "each_sound_camera",
    "edge_offset",
    "explained_model_errors",
    "few_views",
    "finding",
    "findings",
    "fitting_outlier_views",
    "fitting_outliers",
    "fused_disagrees",
    "glue_sentence",
    "inconsistent_camera",
    "intrinsics_unsupported",
    "is_depth_only",
    "lens_coverage",
    "marker",
    "moving_board",
    "not_calibrated",
    "outlier_views",
    "pair_disagrees",
    "pair_fitness",
    "pair_rmse",
    "refine_moved",
    "refit_failed",
    "reprojection",
    "scratch_coverage",
    "time_offsets_implausible",
    "time_sentence",
    "time_unresolved",
    "view_model_error",
    "weak_camera",
    "weak_link",
]


RULES: tuple[Rule, ...] = (
    not_calibrated,
    time_unresolved,
    time_offsets_implausible,
    inconsistent_camera,
    camera_model_error,
    capture_time,
    moving_board,
    weak_camera,
    each_sound_camera(few_views, weak_link),
    board_glue,
    board_size,
    edge_offset,
    board_coverage,
    board_distance,
    board_tilt,
    intrinsics_unsupported,
    scratch_coverage,
    lens_coverage,
    outlier_views,
    fitting_outlier_views,
    view_model_error,
    marker,
    reprojection,
    dropped_views,
    each_pair(pair_disagrees, pair_rmse, pair_fitness),
    depth_unused,
    depth_unmodelled,
    fused_disagrees,
    depth_extrapolated,
    board_scale,
    depth_scale,
)


# a depth-only refinement has no board views: only these rules apply to it
DEPTH_ONLY_RULES: tuple[Rule, ...] = (
    not_calibrated,
    time_unresolved,
    each_pair(pair_disagrees, pair_rmse, pair_fitness),
    depth_unused,
    refine_moved,
    depth_scale_unknown,
    refit_failed,
    board_scale,
    depth_scale,
)


def findings(report: dict[str, Any]) -> list[Finding]:
    """Every rule of :data:`RULES` (:data:`DEPTH_ONLY_RULES` for a depth-only refinement) over
    a report with its ``summary`` and coverage, errors first, then warnings, then infos."""
    found: list[Finding] = []
    for rule in DEPTH_ONLY_RULES if is_depth_only(report) else RULES:
        found += rule(report, found)
    return sorted(found, key=lambda w: SEVERITY_ORDER[w["severity"]])


REASON_MAX_CHARS = 300  # a verdict's reason stays one readable line


def report_verdict(report: dict[str, Any]) -> Verdict:
    """The verdict of a finalized report (``summary.verdict``) with its reason in one line:
    the worst finding (an error for ``poor``, a warning for ``check``) and how many more of
    that severity report.json lists."""
    grade = report["summary"]["verdict"]
    severity = {"poor": "error", "check": "warning"}.get(grade)
    worst = [w for w in report.get("warnings", []) if w["severity"] == severity]
    if not worst:
        return Verdict(grade, "no error or warning in report.json")
    first = worst[0]
    cams = f" [{', '.join(first['cameras'])}]" if first.get("cameras") else ""
    reason = " ".join(f"{first['code']}{cams}: {first['message']}".split())
    if len(reason) > REASON_MAX_CHARS:
        reason = reason[: REASON_MAX_CHARS - 3].rstrip() + "..."
    if len(worst) > 1:
        reason += f" (and {len(worst) - 1} more {severity}(s) in report.json)"
    return Verdict(grade, reason)
