"""Findings about the cameras: not calibrated, inconsistent with the rig, a model error, weakly
constrained, too few views or shared views (:mod:`.findings` runs the rules)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .findings_base import Finding, Rule, cameras_of, finding
from .numbers import change_text, fmt, median_or_none
from .schema import (
    FEW_SHARED_VIEWS,
    FEW_VIEWS,
    FEW_VIEWS_ENOUGH,
    FEW_VIEWS_FACTOR,
    INCONSISTENT_FRACTION,
    REPROJECTION_FACTOR,
    REPROJECTION_MIN_PX,
    WEAK_SIGMA_FACTOR,
    WEAK_SIGMA_MIN_DEG,
    WEAK_SIGMA_MIN_MM,
)


def not_calibrated(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    out = []
    for name, cam in report["cameras"].items():
        if cam["calibrated"]:
            continue
        partner = cam["coverage"]["best_partner"]
        why = cam["why_not"]
        all_out = bool(cam["edge_outliers"]) and cam["edge_outliers"] == cam["views_used"]
        if why in (None, "unknown"):
            why = (
                f"all {cam['edge_outliers']} of its board views were rejected as outliers"
                if all_out
                else "the final estimate dropped it"
            )
        out.append(
            finding(
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
        )
    return out


def _lens_source(cam: dict[str, Any]) -> str:
    """Where a camera's starting intrinsics came from, for advice."""
    return ("its first estimate from scratch, rig.yaml giving only its size"
            if cam.get("intrinsics_initial") else "rig.yaml")


def inconsistent_camera(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    cams = report["cameras"]
    rig_p50 = median_or_none(
        [(c["reprojection_all_px"] or {}).get("p50") for c in cams.values() if c["calibrated"]]
    )
    out = []
    explained = explained_model_errors(report)
    fitting = fitting_outliers(report)
    moved = moved_set_views(report)
    for name, cam in cams.items():
        views = [v for v in report["views"] if v["camera"] == name]
        rejected = [v for v in views if v["edge_status"] == "outlier"
                    and (v["camera"], v["frame"]) not in fitting
                    and (v["camera"], v["frame"]) not in moved]
        parts = (_inconsistencies(cam, views, rejected, rig_p50, name in explained)
                 if views else [])
        if parts:
            out.append(
                finding(
                    "error",
                    "inconsistent_camera",
                    [name],
                    f"{name}: " + "; ".join(parts) + ".",
                    f"Check {name}'s intrinsics (fx, fy, cx, cy and distortion for the "
                    f"recorded resolution; from {_lens_source(cam)}), then its frame "
                    "synchronisation; re-run calibrate.",
                )
            )
    return out


def camera_model_error(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Cameras whose views all disagree with the rig the same way: kept, with an inflated
    sigma (``pose_graph.model_error``), instead of dropped as outliers. A warning, unless the
    self-calibrated board / intrinsics explain it (not inflated) with every refined intrinsic
    within 3 sigma of its rig.yaml prior: the listed model was as good as it claimed, and the
    finding is an info, one for all such cameras (with every lens off, the whole rig)."""
    out, fine = [], []
    chosen = ((report.get("bundle") or {}).get("self_calibration") or {}).get("chosen")
    model = f"the self-calibrated model ({chosen})" if chosen else "the refined board / intrinsics"
    for m in report["pose_graph"].get("model_error") or []:
        name = m["camera"]
        explained = m.get("sigma_factor") is not None and m["sigma_factor"] <= 1.0
        beyond = _beyond_prior(report["cameras"].get(name, {}), _prior_widening(report))
        if explained and not beyond:
            fine.append(m)
            continue
        out.append(
            finding(
                "warning",
                "camera_model_error",
                [name],
                f"{name}: its board views disagree with the rest of the rig as a whole "
                f"({m['outliers_before']} of {m['edges']} beyond the outlier threshold; "
                f"median {fmt(m['translation_mm'], 1)} mm / {fmt(m['rotation_deg'], 2)} deg "
                "per view): a model error, not outlier views. "
                + (
                    f"The camera is kept, its uncertainty scaled x{m['sigma_factor']:.1f} to "
                    "match."
                    if not explained
                    else f"{model[0].upper()}{model[1:]} explains it: its corners fit like the "
                    "rest of the rig, and its uncertainty is not inflated; but "
                    + ", ".join(beyond) + " moved beyond 3 sigma of its prior."
                ),
                f"Use rig_refined.yaml's entry for {name} in rig.yaml: the listed "
                f"intrinsics (from {_lens_source(report['cameras'].get(name, {}))}) are off "
                "beyond their prior."
                if explained else
                f"Likely causes: {name}'s intrinsics (fx, fy, cx, cy) or lens distortion, "
                f"from {_lens_source(report['cameras'].get(name, {}))}; the board (back sheet "
                "glued off, thickness, print scale) when it sees one face; its frame "
                "synchronisation. Fix the model and re-run calibrate.",
            )
        )
    if fine:  # one info for every camera the refined model explains (often the whole rig)
        fine.sort(key=lambda m: m["camera"])
        names = [m["camera"] for m in fine]
        counts = ", ".join((f"{m['camera']} " if len(fine) > 1 else "")
                           + f"{m['outliers_before']} of {m['edges']}" for m in fine)
        whose = f"{names[0]}: its" if len(fine) == 1 else f"{', '.join(names)}: their"
        out.insert(0, finding(
            "info",
            "camera_model_error",
            names,
            f"{whose} board views disagreed with the rest of the rig under the board file's "
            f"and rig.yaml's model ({counts} beyond the outlier threshold); {model} explains "
            "it within its priors: the corners fit like the rest of the rig, and the "
            "uncertainty is not inflated.",
            "Nothing to do; rig_refined.yaml (and board_refined.yaml when the board was "
            "refined) hold the refined models." if chosen not in (None, "time") else
            "Nothing to do here (the capture_time finding says how the capture limits the "
            "accuracy).",
        ))
    return out


def _prior_widening(report: dict[str, Any]) -> float:
    """How much wider than configured the reported intrinsics priors are: the self-calibration
    loosens them (:data:`~rgbd_calib.solve.selfcal.LOOSEN`) when the data put a parameter several
    prior sigmas from rig.yaml, and says so in the chosen level's reason."""
    from ...solve.selfcal import LOOSEN

    sc = (report.get("bundle") or {}).get("self_calibration") or {}
    chosen = [lv for lv in sc.get("levels") or [] if lv.get("level") == sc.get("chosen")]
    return LOOSEN if any("priors loosened" in (lv.get("reason") or "") for lv in chosen) else 1.0


def _beyond_prior(cam: dict[str, Any], widening: float = 1.0,
                  n_sigma: float = 3.0) -> list[str]:
    """Refined intrinsics that moved more than ``n_sigma`` configured prior sigmas (the
    reported one over ``widening``) from their prior (rig.yaml's, or the first estimate of a
    camera calibrated from scratch), as 'fx +4.8 % (16 sigma)' or, for a prior about zero,
    'p1 +0.0093 (5 sigma)': the prior was wrong beyond its stated tolerance."""
    out = []
    for p, e in (cam.get("intrinsics_refined") or {}).items():
        sigma = (e.get("prior_sigma") or 0.0) / widening
        if sigma and abs(e["change"]) > n_sigma * sigma:
            size = change_text(e.get("prior"), e["change"],
                               "px" if p in ("fx", "fy", "cx", "cy") else "")
            out.append(f"{p} {size} ({abs(e['change']) / sigma:.0f} sigma)")
    return out


def explained_model_errors(report: dict[str, Any]) -> set[str]:
    """Cameras the pose graph flagged for a model error that the self-calibrated board or
    intrinsics explained (not inflated: ``sigma_factor`` 1): their pose-graph outlier views
    were judged with the model the bundle adjustment replaced, and it used them."""
    return {m["camera"] for m in report["pose_graph"].get("model_error") or []
            if m.get("sigma_factor") is not None and m["sigma_factor"] <= 1.0}


def moved_set_views(report: dict[str, Any]) -> set[tuple[str, str]]:
    """The rejected views ``(camera, frame)`` of frame sets the board moved during
    (``report.motion``, :mod:`rgbd_calib.solve.stillness`): the cameras saw it at different
    poses because it moved, not because they are off."""
    return {(c, m["frame"]) for m in report.get("motion") or [] if m["moved"]
            for c in m["outliers"]}


def fitting_outliers(report: dict[str, Any]) -> dict[tuple[str, str], bool]:
    """The pose-graph outlier views the final calibration fits, ``(camera, frame)`` -> whether
    the bundle adjustment used them: their corners reproject through the final extrinsics and
    board pose within ``REPROJECTION_FACTOR`` x the typical used view's RMS. Two kinds
    (measured: docs/report_schema.md): with a self-calibrated board or lens the bundle keeps
    the views the pose graph rejected under the board file's / rig.yaml's model
    (``solve.ladder.marker_measurements``) and they fit it; and a view whose PnP covariance is a
    little tighter than its error is rejected although it fits like the rest. A view wrong in
    itself (blur, out of sync, a wrong detection) does not fit the board pose the other cameras
    of its frame give."""
    typical = median_or_none([v["final_reprojection_rms_px"] for v in report["views"]
                              if v["edge_status"] == "used"])
    if typical is None:
        return {}
    return {
        (v["camera"], v["frame"]):
            v["excluded_markers"] is not None and 2 * v["excluded_markers"] <= v["markers"]
        for v in report["views"]
        if v["edge_status"] == "outlier" and v["final_reprojection_rms_px"] is not None
        and v["final_reprojection_rms_px"] <= REPROJECTION_FACTOR * typical
    }


def _inconsistencies(
    cam: dict[str, Any], views: list[dict[str, Any]], rejected: list[dict[str, Any]],
    rig_p50: float | None, explained: bool = False,
) -> list[str]:
    """Why a camera disagrees with the rig (empty: it does not): many ``rejected`` views
    (pose-graph outliers the final calibration does not fit; none when a self-calibrated
    model ``explained`` the camera), a median reprojection error far above the rig's, many
    views whose corners fit no pose."""
    n_out = 0 if explained else len(rejected)
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
    parts = []
    if bad_views:
        med = median_or_none([v["edge_translation_mm"] for v in rejected])
        parts.append(
            f"{n_out} of its {len(views)} board views disagree with the rest "
            f"of the rig (median {fmt(med, 1)} mm)"
        )
    if bad_px:
        parts.append(
            f"its board corners reproject {fmt(p50)} px off (median) through "
            f"the calibrated poses, {p50 / rig_p50:.0f}x the rig's "
            f"{fmt(rig_p50)} px"
        )
    if bad_pnp:
        parts.append(f"{dropped_rms} views were dropped because their corners fit no pose")
    return parts


def weak_camera(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Cameras whose 1-sigma translation, else rotation, is far above the rig median."""
    cams, summ = report["cameras"], report["summary"]
    inconsistent = cameras_of(earlier, "inconsistent_camera")
    out: list[Finding] = []
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
                or name in inconsistent
                or not (s > WEAK_SIGMA_FACTOR * med and s > floor)
                or name in cameras_of(out, "weak_camera")
            ):
                continue
            cov = cam["coverage"]
            partner = f" ({cov['best_partner']})" if cov["best_partner"] else ""
            out.append(
                finding(
                    "warning",
                    "weak_camera",
                    [name],
                    f"{name} is weakly constrained: 1-sigma {fmt(s, 3)} {unit}, "
                    f"{s / med:.1f}x the rig median {fmt(med, 3)} {unit} "
                    f"({cam['views_used']} board views used, at most {cov['max_shared_views']} "
                    f"shared with one camera{partner}).",
                    f"Record more board views for {name}, held where it and "
                    f"{cov['best_partner'] or 'a calibrated neighbour'} see the board together.",
                )
            )
    return out


def few_views(report: dict[str, Any], name: str, cam: dict[str, Any]) -> Finding | None:
    cams = report["cameras"]
    views_median = median_or_none([c["views_used"] for c in cams.values() if c["calibrated"]]) or 0
    if cam["views_used"] >= max(FEW_VIEWS, min(FEW_VIEWS_FACTOR * views_median, FEW_VIEWS_ENOUGH)):
        return None
    return finding(
        "warning",
        "few_views",
        [name],
        f"{name} has only {cam['views_used']} usable board views (rig median {views_median:.0f}).",
        f"Show the board to {name} in more positions.",
    )


def weak_link(report: dict[str, Any], name: str, cam: dict[str, Any]) -> Finding | None:
    cov = cam["coverage"]
    if name == report["reference"] or cov["max_shared_views"] >= FEW_SHARED_VIEWS:
        return None
    return finding(
        "warning",
        "weak_link",
        [name] + ([cov["best_partner"]] if cov["best_partner"] else []),
        f"{name} shares at most {cov['max_shared_views']} board views with any other camera.",
        f"Hold the board where {name} and "
        f"{cov['best_partner'] or 'a neighbouring camera'} both see it.",
    )


CameraCheck = Callable[[dict[str, Any], str, dict[str, Any]], Finding | None]


def each_sound_camera(*checks: CameraCheck) -> Rule:
    """A rule applying ``checks`` in turn to each calibrated camera not already found
    inconsistent or weak (a camera's findings stay together, in camera order)."""

    def rule(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
        skip = cameras_of(earlier, "inconsistent_camera") | cameras_of(earlier, "weak_camera")
        found = [
            check(report, name, cam)
            for name, cam in report["cameras"].items()
            if cam["calibrated"] and name not in skip
            for check in checks
        ]
        return [f for f in found if f is not None]

    return rule
