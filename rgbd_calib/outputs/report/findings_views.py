"""Findings about single board views and markers: pose-graph outliers, the per-view model error,
a bad marker, the rig's reprojection error, dropped views (:mod:`.findings` runs the rules)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...solve.pose import DROP_ADVICE
from .findings_base import Finding, cameras_of, finding
from .findings_cameras import explained_model_errors, fitting_outliers, moved_set_views
from .numbers import median_or_none
from .schema import (
    MARKER_FACTOR,
    MARKER_MIN_PX,
    REPROJECTION_FACTOR,
    RIG_REPROJECTION_MAX_PX,
    RIG_REPROJECTION_POOR_PX,
)


def outlier_views(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    skip = cameras_of(earlier, "inconsistent_camera") | explained_model_errors(report)
    fitting = fitting_outliers(report)
    moved = moved_set_views(report)
    outliers = [o for o in report["pose_graph"]["outliers"]
                if o["camera"] not in skip and (o["camera"], o["view"]) not in fitting
                and (o["camera"], o["view"]) not in moved]
    if not outliers:
        return []
    listed = ", ".join(f"{o['camera']}/{o['view']}" for o in outliers[:8])
    return [
        finding(
            "warning",
            "outlier_views",
            sorted({o["camera"] for o in outliers}),
            f"{len(outliers)} board view(s) were rejected as pose-graph outliers and do not fit "
            f"the final calibration: {listed}{' ...' if len(outliers) > 8 else ''}.",
            "Look at those frames: motion blur, a camera out of sync, or a wrong detection.",
        )
    ]


def fitting_outlier_views(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The pose-graph outlier views the final calibration fits (see
    :func:`fitting_outliers`), of cameras no other finding covers: why their edges say
    ``outlier`` and no warning does."""
    skip = cameras_of(earlier, "inconsistent_camera") | explained_model_errors(report)
    used: dict[str, int] = {}
    left: dict[str, int] = {}
    moved = moved_set_views(report)
    for (cam, frame), in_bundle in sorted(fitting_outliers(report).items()):
        if cam not in skip and (cam, frame) not in moved:
            bucket = used if in_bundle else left
            bucket[cam] = bucket.get(cam, 0) + 1
    if not used and not left:
        return []
    parts = []
    if used:
        parts.append(f"{sum(used.values())} used by the bundle adjustment with the "
                     "self-calibrated board / lens ("
                     + ", ".join(f"{c} {k}" for c, k in used.items()) + ")")
    if left:
        parts.append(f"{sum(left.values())} left out ("
                     + ", ".join(f"{c} {k}" for c, k in left.items()) + "), their PnP "
                     "uncertainty a little smaller than their error")
    return [
        finding(
            "info",
            "fitting_outlier_views",
            sorted(set(used) | set(left)),
            f"{sum(used.values()) + sum(left.values())} board view(s) the pose graph rejected "
            "fit the final calibration like the rest of the rig (within "
            f"{REPROJECTION_FACTOR:.0f}x the typical view's reprojection RMS): "
            + "; ".join(parts) + ".",
            "Nothing to do.",
        )
    ]


def view_model_error(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The per-view model-error floor ``pose.model_error_px: auto`` estimated, when not 0:
    the board views disagreed beyond their corner noise, and by how much."""
    floor = report["pose_graph"].get("view_floor")
    if not floor or not floor["model_error_px"] > 0:
        return []
    ratio = floor["misfit_ratio"]
    typical = f" (the typical view {np.sqrt(ratio):.1f}x its corner-noise sigma)" if ratio else ""
    return [
        finding(
            "info",
            "view_model_error",
            [],
            f"the board views disagree with each other beyond their corner noise{typical}: a "
            f"model error of {floor['model_error_px']:.2f} px shared by each view's corners "
            "was estimated and added to every view's uncertainty in the pose graph "
            "(pose.model_error_px: auto), so such views are weighed, not rejected as outliers.",
            "Usual for real cameras (intrinsics or lens slightly off, a print or detector "
            "bias, a rolling shutter on a moving board); above ~1 px hold the board still for "
            "each view and cover the images with it.",
        )
    ]


def marker(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    med_marker = median_or_none([m["rms_px"] for m in report["markers"]])
    return [
        finding(
            "warning",
            "marker",
            [],
            f"marker {m['id']} ({m['face']} face) reprojects {m['rms_px']:.2f} px RMS, "
            f"{m['rms_px'] / med_marker:.0f}x the median marker.",
            f"Check marker {m['id']} on the board: flat, not peeling, printed at scale "
            "and placed where the board file says.",
        )
        for m in report["markers"]
        if med_marker and m["rms_px"] > max(MARKER_FACTOR * med_marker, MARKER_MIN_PX)
    ]


def reprojection(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    rig_rms = report["summary"]["reprojection_rms_px"]
    if rig_rms is None or rig_rms <= RIG_REPROJECTION_MAX_PX:
        return []
    poor = rig_rms > RIG_REPROJECTION_POOR_PX  # the model does not explain the images
    return [
        finding(
            "error" if poor else "warning",
            "reprojection",
            [],
            f"the rig's reprojection RMS is {rig_rms:.2f} px (expected well below "
            f"{RIG_REPROJECTION_MAX_PX} px)"
            + (": the calibrated poses do not explain the images." if poor else "."),
            "Check the intrinsics in rig.yaml, the board's flatness and its printed scale"
            + ("; a board moving through unsynchronised cameras needs timestamps.csv or "
               "still poses." if poor else "."),
        )
    ]


def dropped_views(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """One finding per drop reason, naming the cameras and counts."""
    by_reason: dict[str, dict[str, int]] = {}
    for d in report["dropped_views"]:
        by_reason.setdefault(d["reason"], {})
        by_reason[d["reason"]][d["camera"]] = by_reason[d["reason"]].get(d["camera"], 0) + 1
    out = []
    for reason, per in sorted(by_reason.items()):
        total = sum(per.values())
        where = ", ".join(f"{c} {n}" for c, n in sorted(per.items(), key=lambda kv: -kv[1]))
        out.append(
            finding(
                "info",
                "dropped_views",
                sorted(per),
                f"{total} view(s) dropped ({reason}): {where}.",
                DROP_ADVICE.get(reason, "").capitalize() + ("." if reason in DROP_ADVICE else ""),
            )
        )
    return out
