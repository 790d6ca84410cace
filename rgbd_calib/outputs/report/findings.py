"""The findings (``report.json`` ``warnings``): one rule per warning code over a report's
numbers, thresholds from :mod:`.schema`.

A rule takes the report and the findings of the rules before it (a camera already found
inconsistent or weak is not flagged again for what follows from that) and returns its own.
:data:`RULES` runs them in a fixed order; :func:`findings` sorts the result by severity
(stable, so the order within a severity is the rules' order).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .numbers import fmt, median_or_none
from .schema import (
    BOARD_SCALE_MIN,
    BOARD_SCALE_SPREAD,
    CORNER_REGIONS,
    COVERAGE_MIN,
    DEPTH_SCALE_TOL,
    DISTANCE_SPREAD_MIN,
    DROP_ADVICE,
    FEW_SHARED_VIEWS,
    FEW_VIEWS,
    FEW_VIEWS_ENOUGH,
    FEW_VIEWS_FACTOR,
    GLUE_MIN_DEG,
    GLUE_MIN_MM,
    GLUE_SIGMAS,
    INCONSISTENT_FRACTION,
    INTRINSICS_SUPPORT_MAX,
    MARKER_FACTOR,
    MARKER_MIN_PX,
    PAIR_FINAL_EXCESS_MM,
    PAIR_FITNESS_MIN,
    PAIR_RMSE_MAX_MM,
    REFINE_MOVE_SIGMAS,
    REPROJECTION_FACTOR,
    REPROJECTION_MIN_PX,
    RIG_REPROJECTION_MAX_PX,
    TILT_SPREAD_MIN_DEG,
    WEAK_SIGMA_FACTOR,
    WEAK_SIGMA_MIN_DEG,
    WEAK_SIGMA_MIN_MM,
)

Finding = dict[str, Any]
Rule = Callable[[dict[str, Any], list[Finding]], list[Finding]]
SEVERITY_ORDER = {"error": 0, "warning": 1, "info": 2}


def finding(severity: str, code: str, cameras: list[str], message: str, advice: str) -> Finding:
    """One ``warnings[]`` entry."""
    return {
        "severity": severity,
        "code": code,
        "cameras": cameras,
        "message": message,
        "advice": advice,
    }


def _cameras_of(found: list[Finding], code: str) -> set[str]:
    return {c for w in found if w["code"] == code for c in w["cameras"]}


def _placement(report: dict[str, Any], earlier: list[Finding]) -> list[tuple[str, Any]]:
    """The calibrated cameras not found inconsistent: those whose board placement counts."""
    inconsistent = _cameras_of(earlier, "inconsistent_camera")
    return [
        (n, c) for n, c in report["cameras"].items() if c["calibrated"] and n not in inconsistent
    ]


# ----------------------------------------------------------------------------- cameras
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
    explained = _explained_model_errors(report)
    fitting = _fitting_outliers(report)
    for name, cam in cams.items():
        views = [v for v in report["views"] if v["camera"] == name]
        rejected = [v for v in views if v["edge_status"] == "outlier"
                    and (v["camera"], v["frame"]) not in fitting]
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
                    else "The refined board / intrinsics explain it: its corners fit like the "
                    "rest of the rig, and its uncertainty is not inflated; but "
                    + ", ".join(beyond) + " moved beyond 3 sigma of the rig.yaml prior."
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
            f"and rig.yaml's model ({counts} beyond the outlier threshold); the refined "
            "board / intrinsics explain it within their priors: the corners fit like the rest "
            "of the rig, and the uncertainty is not inflated.",
            "Nothing to do; rig_refined.yaml (and board_refined.yaml when the board was "
            "refined) hold the refined models.",
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
    reported one over ``widening``) from rig.yaml, as 'fx +4.8 % (16 sigma)': the rig.yaml
    value was wrong beyond its stated tolerance."""
    out = []
    for p, e in (cam.get("intrinsics_refined") or {}).items():
        sigma = (e.get("prior_sigma") or 0.0) / widening
        if sigma and abs(e["change"]) > n_sigma * sigma:
            size = (f"{e['change_pct']:+.2f} %" if e.get("change_pct") is not None
                    else f"{e['change']:+.3g}")
            out.append(f"{p} {size} ({abs(e['change']) / sigma:.0f} sigma)")
    return out


def _explained_model_errors(report: dict[str, Any]) -> set[str]:
    """Cameras the pose graph flagged for a model error that the self-calibrated board or
    intrinsics explained (not inflated: ``sigma_factor`` 1): their pose-graph outlier views
    were judged with the model the bundle adjustment replaced, and it used them."""
    return {m["camera"] for m in report["pose_graph"].get("model_error") or []
            if m.get("sigma_factor") is not None and m["sigma_factor"] <= 1.0}


def _fitting_outliers(report: dict[str, Any]) -> dict[tuple[str, str], bool]:
    """The pose-graph outlier views the final calibration fits, ``(camera, frame)`` -> whether
    the bundle adjustment used them: their corners reproject through the final extrinsics and
    board pose within ``REPROJECTION_FACTOR`` x the typical used view's RMS. Two kinds,
    measured: with a self-calibrated board or lens the bundle keeps the views the pose graph
    rejected under the board file's / rig.yaml's model (``calibrate.marker_measurements``) and
    they fit it (a misglued ring: 21 views at 0.03-0.06 px, typical 0.045); and a view whose
    PnP covariance is a little tighter than its error is rejected at 4.6-5.4 whitened sigmas
    although it fits like the rest (clean 8-camera ring, blur 1 px: 4 of ~150 views at
    0.03-0.07 px, typical 0.044). A view wrong in itself (blur, out of sync, a wrong
    detection) does not fit the board pose the other cameras of its frame give."""
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
    inconsistent = _cameras_of(earlier, "inconsistent_camera")
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
                or name in _cameras_of(out, "weak_camera")
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
        skip = _cameras_of(earlier, "inconsistent_camera") | _cameras_of(earlier, "weak_camera")
        found = [
            check(report, name, cam)
            for name, cam in report["cameras"].items()
            if cam["calibrated"] and name not in skip
            for check in checks
        ]
        return [f for f in found if f is not None]

    return rule


# ----------------------------------------------------------------------------- board placement
def board_coverage(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    low = [
        (n, c["coverage"])
        for n, c in _placement(report, earlier)
        if c["coverage"]["image_fraction"] < COVERAGE_MIN and c["coverage"]["missing_regions"]
    ]
    if not low:
        return []
    regions: dict[str, int] = {}
    for _, cov in low:
        for r in cov["missing_regions"]:
            regions[r] = regions.get(r, 0) + 1
    common = sorted(regions, key=lambda r: -regions[r])[:3]
    return [
        finding(
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
    ]


def intrinsics_unsupported(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Refined intrinsics the data could not determine: the marginal sigma stays close to the
    prior's, so the 'refined' value is mostly the rig.yaml one (and its error)."""
    weak = {}
    for name, cam in report["cameras"].items():
        params = [
            p for p, e in (cam.get("intrinsics_refined") or {}).items()
            if e["sigma"] is not None and e["prior_sigma"]
            and e["sigma"] > INTRINSICS_SUPPORT_MAX * e["prior_sigma"]
        ]
        if params:
            weak[name] = params
    if not weak:
        return []
    return [
        finding(
            "warning",
            "intrinsics_unsupported",
            list(weak),
            "The board views hardly constrain some refined intrinsics (marginal sigma above "
            f"{INTRINSICS_SUPPORT_MAX:.0%} of the prior's): "
            + "; ".join(f"{n}: {' '.join(p)}" for n, p in weak.items())
            + ". Their refined values are mostly the starting ones (rig.yaml's, or the first "
            "estimate of a camera calibrated from scratch).",
            "Record more views with the board at several distances and tilts, reaching the "
            "image corners (distortion), or refine fewer parameters "
            "(bundle.intrinsics_params, e.g. fx fy cx cy).",
        )
    ]


def lens_coverage(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Refined lens distortion from views that covered little of the image, or never reached
    one of its corners: the polynomial is fitted where the board went and extrapolated
    elsewhere, most at the corners (measured, docs/accuracy.md, issue 13, ring seed 11,
    board volume 2.5: the cameras with a corner region never reached 0.6-6.2 px off the true
    lens over the image; with close-ups reaching every corner under 0.06 px)."""
    thin = {}
    for name, cam in report["cameras"].items():
        if cam.get("intrinsics_initial"):
            continue  # scratch_coverage says it for a camera calibrated from scratch
        refined = cam.get("intrinsics_refined") or {}
        cov = cam.get("coverage") or {}
        if not any(p not in ("fx", "fy", "cx", "cy") for p in refined) \
                or cov.get("image_fraction") is None:
            continue
        corners = [r for r in cov.get("missing_regions") or [] if r in CORNER_REGIONS]
        if cov["image_fraction"] < COVERAGE_MIN or corners:
            thin[name] = f"{cov['image_fraction']:.0%}" + (
                f", never the {' / '.join(corners)} corner" if corners else "")
    if not thin:
        return []
    return [
        finding(
            "warning",
            "lens_coverage",
            list(thin),
            "The lens distortion was refined from views covering little of the image or "
            "not reaching its corners (" + "; ".join(f"{n} {t}" for n, t in thin.items())
            + f"; {COVERAGE_MIN:.0%} and every corner wanted): the refined model "
            "(rig_refined.yaml) holds where the board went and is an extrapolation towards "
            "the image corners.",
            "Before using rig_refined.yaml's distortion for the whole image, record views with "
            "the board close to each camera, reaching its image corners, and calibrate again.",
        )
    ]


def scratch_coverage(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """A camera calibrated from scratch (rig.yaml gave only its size) whose board views
    reached little of the image: its focal length, centre and distortion rest on that part."""
    thin = {
        name: cam["intrinsics_initial"]
        for name, cam in report["cameras"].items()
        if cam.get("intrinsics_initial")
        and cam["intrinsics_initial"]["image_fraction"] < COVERAGE_MIN
    }
    if not thin:
        return []
    return [
        finding(
            "warning",
            "scratch_coverage",
            list(thin),
            "Intrinsics calibrated from scratch from views whose corners reached little of the "
            "image ("
            + ", ".join(f"{n} {i['image_fraction']:.0%} in {i['views']} views"
                        for n, i in thin.items())
            + f", under {COVERAGE_MIN:.0%}): the lens model (rig_refined.yaml) is fitted there "
            "and extrapolated elsewhere, and the focal length trades against the distances.",
            "Record more views with these cameras, the board reaching every image region and "
            "tilted, or give their intrinsics in rig.yaml.",
        )
    ]


def board_glue(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The back sheet off its board-file place (``bundle.board: refine``): significant against
    its sigma and large enough to matter; or held because it was unobservable."""
    refined = report["board"].get("refined")
    if not refined:
        return []
    if refined["held"]:
        return [finding("info", "board_glue", [], f"Board not refined: {refined['held']}.",
                        "To refine the back sheet, record views in which cameras on both "
                        "sides see the board at the same time.")]
    (dx, dy), rot = refined["offset_mm"], refined["rotation_deg"]
    (sx, sy), srot = refined["sigmas"]["offset_mm"], refined["sigmas"]["rotation_deg"]
    shifted = (abs(dx) > GLUE_SIGMAS * sx or abs(dy) > GLUE_SIGMAS * sy) and (
        np.hypot(dx, dy) > GLUE_MIN_MM)
    turned = abs(rot) > GLUE_SIGMAS * srot and abs(rot) > GLUE_MIN_DEG
    if not (shifted or turned):
        return []
    return [finding(
        "warning",
        "board_glue",
        [],
        f"{glue_sentence(refined)} (sigma {fmt(sx, 2)} / {fmt(sy, 2)} mm, {fmt(srot, 3)} deg).",
        "Use board_refined.yaml (--board) for the next calibrations with this board, or "
        "re-glue the back sheet.",
    )]


def glue_sentence(refined: dict[str, Any]) -> str:
    """'Back sheet is 1.50 mm right, 1.00 mm down, 0.30 deg counter-clockwise of where the
    board file puts it (seen from the front); thickness 6.60 mm (+0.00)' from
    ``report.board.refined``."""
    (dx, dy), rot = refined["offset_mm"], refined["rotation_deg"]
    return (
        f"Back sheet is {abs(dx):.2f} mm {'right' if dx >= 0 else 'left'}, "
        f"{abs(dy):.2f} mm {'up' if dy >= 0 else 'down'}, {abs(rot):.2f} deg "
        f"{'counter-clockwise' if rot >= 0 else 'clockwise'} of where the board file puts it "
        f"(seen from the front); thickness {refined['thickness_mm']:.2f} mm "
        f"({refined['thickness_change_mm']:+.2f})"
    )


def board_distance(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    narrow = [
        (n, c["coverage"]["distance_m"])
        for n, c in _placement(report, earlier)
        if c["coverage"]["distance_m"]
        and c["views_used"] >= 3
        and c["coverage"]["distance_m"]["max"]
        < DISTANCE_SPREAD_MIN * c["coverage"]["distance_m"]["min"]
    ]
    if not narrow:
        return []
    return [
        finding(
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
    ]


def board_tilt(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    flat = [
        (n, c["coverage"]["tilt_deg"])
        for n, c in _placement(report, earlier)
        if c["coverage"]["tilt_deg"]
        and c["views_used"] >= 3
        and c["coverage"]["tilt_deg"]["max"] - c["coverage"]["tilt_deg"]["min"]
        < TILT_SPREAD_MIN_DEG
    ]
    if not flat:
        return []
    return [
        finding(
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
    ]


# ----------------------------------------------------------------------------- views, markers
def outlier_views(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    skip = _cameras_of(earlier, "inconsistent_camera") | _explained_model_errors(report)
    fitting = _fitting_outliers(report)
    outliers = [o for o in report["pose_graph"]["outliers"]
                if o["camera"] not in skip and (o["camera"], o["view"]) not in fitting]
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
    :func:`_fitting_outliers`), of cameras no other finding covers: why their edges say
    ``outlier`` and no warning does."""
    skip = _cameras_of(earlier, "inconsistent_camera") | _explained_model_errors(report)
    used: dict[str, int] = {}
    left: dict[str, int] = {}
    for (cam, _), in_bundle in sorted(_fitting_outliers(report).items()):
        if cam not in skip:
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
    return [
        finding(
            "warning",
            "reprojection",
            [],
            f"the rig's reprojection RMS is {rig_rms:.2f} px (expected well below "
            f"{RIG_REPROJECTION_MAX_PX} px).",
            "Check the intrinsics in rig.yaml, the board's flatness and its printed scale.",
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


# ----------------------------------------------------------------------------- depth
def pair_disagrees(p: dict[str, Any]) -> Finding | None:
    final, after = p.get("rmse_final_mm"), p["rmse_after_mm"]
    if not (
        p["accepted"]
        and final is not None
        and after is not None
        and (final > after + PAIR_FINAL_EXCESS_MM)
    ):
        return None
    return finding(
        "warning",
        "pair_disagrees",
        [p["cam_a"], p["cam_b"]],
        f"{p['cam_a']}-{p['cam_b']}: the final extrinsics fit their common surfaces "
        f"{final:.1f} mm RMS, ICP alone {after:.1f} mm.",
        f"The depth of {p['cam_a']}/{p['cam_b']} and the board disagree: check their "
        "depth scale and that the scene did not move.",
    )


def pair_rmse(p: dict[str, Any]) -> Finding | None:
    if p["rmse_after_mm"] is None or p["rmse_after_mm"] <= PAIR_RMSE_MAX_MM:
        return None
    return finding(
        "warning",
        "pair_rmse",
        [p["cam_a"], p["cam_b"]],
        f"{p['cam_a']}-{p['cam_b']}: surfaces disagree by {p['rmse_after_mm']:.1f} mm "
        "RMS after ICP.",
        f"Check the depth of {p['cam_a']} and {p['cam_b']} (scale, temperature drift).",
    )


def pair_fitness(p: dict[str, Any]) -> Finding | None:
    if p["fitness"] is None or p["fitness"] >= PAIR_FITNESS_MIN:
        return None
    return finding(
        "info",
        "pair_fitness",
        [p["cam_a"], p["cam_b"]],
        f"{p['cam_a']}-{p['cam_b']}: only {p['fitness']:.0%} of points overlap.",
        "",
    )


def each_pair(*checks: Callable[[dict[str, Any]], Finding | None]) -> Rule:
    """A rule applying ``checks`` in turn to each camera pair (a pair's findings together)."""

    def rule(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
        found = [check(p) for p in report["pairs"] for check in checks]
        return [f for f in found if f is not None]

    return rule


def _disagrees(pair: dict[str, Any]) -> bool:
    """A pair rejected for contradicting the extrinsics: ICP moved it beyond the board's (or
    ``--init``'s) uncertainty and its own (:func:`rgbd_calib.pipelines.refine.consistent_with_board`),
    or it was accepted and then not used (the joint solve failed or moved a camera too far)."""
    reason = str(pair.get("reason") or "")
    return reason.startswith("not used:") or "beyond their uncertainty" in reason


def confirming_pairs(pairs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The pairs that confirm the extrinsics they started from (``agrees``: ICP moved them by
    less than their own uncertainty), or none when any pair contradicts those extrinsics."""
    if any(_disagrees(p) for p in pairs):
        return []
    return [p for p in pairs if p.get("agrees")]


def depth_unused(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The depth stage ran but no pair went into the solve: the result is the board's alone
    (not when the stage skipped registration because the board constrains every camera), or
    in a depth-only refinement the initial extrinsics. A warning when no pair registered
    cleanly; an info (``depth_agrees``) when some did and ICP moved each of them by less than
    its own uncertainty (``pairs[].agrees``) and none contradicted the extrinsics: the depth
    confirms them, it has nothing to correct. Measured on race seed 301 (glued board, lens
    listed; the board result 0.35 mm from the truth): 19 of 24 pairs agreed, the other 5 had a
    fitness < 0.3, and the warning had made the verdict CHECK."""
    status = (report.get("depth") or {}).get("status")
    if status is not None and status != "fallback":
        return []
    ran = "depth" in report.get("timings_s", {}) or _depth_only(report)
    if not ran or any(p["accepted"] for p in report["pairs"]):
        return []
    start = "the initial extrinsics (--init)" if _depth_only(report) else "the board result"
    pairs = report["pairs"]
    agree = confirming_pairs(pairs)
    if agree:
        mm = sorted(p["correction_mm"] or 0.0 for p in agree)
        deg = sorted(p["correction_deg"] or 0.0 for p in agree)
        return [finding(
            "info",
            "depth_agrees",
            sorted({c for p in agree for c in (p["cam_a"], p["cam_b"])}),
            f"Depth agrees with {start}: {len(agree)} of {len(pairs)} camera pairs registered "
            f"cleanly and ICP moved each by less than its own uncertainty ({mm[0]:.2f}-"
            f"{mm[-1]:.2f} mm, {deg[0]:.3f}-{deg[-1]:.3f} deg); no correction was needed, the "
            f"extrinsics are {start}.",
            "",
        )]
    reasons = sorted({str(p["reason"]).split(";")[0] for p in pairs if p["reason"]})
    why = (f"all {len(pairs)} camera pairs were rejected ({'; '.join(reasons[:3])}"
           f"{'; ...' if len(reasons) > 3 else ''})" if pairs
           else (report.get("depth") or {}).get("reason")
           or "no camera pair overlapped under the board extrinsics")
    return [finding(
        "warning",
        "depth_unused",
        [],
        f"Depth refinement added nothing: {why}; the extrinsics are {start}.",
        f"{start[0].upper()}{start[1:]} stands on its own; see the pairs table for each "
        "pair's reason.",
    )]


def common_depth_scale(factors: dict[str, tuple[float, float]]) -> float | None:
    """The depth-scale ratio every camera agrees on, when it says the board's print differs
    from its board file; None otherwise.

    ``factors``: camera -> (factor, sigma) of ``z_measured ~ factor * z_board`` (depth.py),
    where ``z_board`` is the distance the calibration puts the board at. A board file whose
    markers are ``1/S`` times the printed ones makes every PnP distance (and every extrinsic
    translation) ``1/S`` times too long, so every camera's depth reads factor ``S``: the
    printed marker length is the file's times the common factor. Needs two or more cameras,
    each within 3 x sqrt(sigma^2 + BOARD_SCALE_SPREAD^2) of the weighted mean (real cameras'
    depth scales differ by a few 0.1 %), and the mean off 1 by more than BOARD_SCALE_MIN."""
    usable = [(f, s) for f, s in factors.values() if f is not None and s is not None]
    if len(usable) < 2:
        return None
    f = np.array([u[0] for u in usable])
    var = np.array([u[1] for u in usable]) ** 2 + BOARD_SCALE_SPREAD**2
    mean = float(np.sum(f / var) / np.sum(1.0 / var))
    if np.any(np.abs(f - mean) > 3.0 * np.sqrt(var)) or abs(mean - 1.0) <= BOARD_SCALE_MIN:
        return None
    return mean


def board_scale_sentence(ratio: float, marker_length_m: float | None,
                         square_length_m: float | None = None) -> str:
    """One line: the board's print is ``ratio`` times its file, and the lengths the data
    supports: the marker length of an ArUco grid, or a ChArUco board's square and marker
    lengths (``square_length_m`` given; a print scales both)."""
    size = "smaller" if ratio < 1 else "larger"
    what = "square and marker lengths are" if square_length_m else "marker length is"
    text = (f"Every camera's depth says the board is {100 * abs(1 - ratio):.1f}% {size} than "
            f"its board file: the printed {what} wrong in the board file")
    if square_length_m:
        text += (f" (the data supports square_length {1000 * square_length_m * ratio:.1f} mm"
                 + (f" and marker_length {1000 * marker_length_m * ratio:.1f} mm"
                    if marker_length_m else "")
                 + f", the file says {1000 * square_length_m:.1f}"
                 + (f" and {1000 * marker_length_m:.1f}" if marker_length_m else "") + " mm)")
    elif marker_length_m:
        text += (f" (the data supports {1000 * marker_length_m * ratio:.1f} mm, the file says "
                 f"{1000 * marker_length_m:.1f} mm)")
    return text


def board_scale(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Every camera's depth off by the same few percent: the board's print, not the depth."""
    ratio = common_depth_scale({
        n: (c["depth_scale_factor"], c["depth_scale_sigma"])
        for n, c in report["cameras"].items()})
    if ratio is None:
        return []
    return [finding(
        "error",
        "board_scale",
        [],
        board_scale_sentence(ratio, report["board"].get("marker_length_m"),
                             report["board"].get("square_length_m")) + ".",
        ("Measure a printed chessboard square and set square_length and marker_length "
         if report["board"].get("square_length_m") else
         "Measure a printed marker's black square and set marker_length (grid form) or the "
         "corners (explicit form) ")
        + "of the board file, then calibrate again: every translation "
        f"of this calibration is {abs(1 / ratio - 1):.1%} off.",
    )]


def depth_scale(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    if any(w["code"] == "board_scale" for w in earlier):
        return []  # one board finding instead of every camera's depth blamed
    return [
        finding(
            "info",
            "depth_scale",
            [name],
            f"{name}'s depth reads {100 * (f - 1):+.2f}% off the board's true distance.",
            f"Divide {name}'s depth by {f:.4f} (or recalibrate its depth unit).",
        )
        for name, cam in report["cameras"].items()
        if (f := cam["depth_scale_factor"]) is not None and abs(f - 1.0) > DEPTH_SCALE_TOL
    ]


# ----------------------------------------------------------------------------- depth-only
def _depth_only(report: dict[str, Any]) -> bool:
    """A report of ``rgbd-calib refine`` (no board result; schema 1.3 ``refine``)."""
    return report.get("refine") is not None


def refine_moved(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Depth-only refinement: cameras the depth pairs moved by more than 3 of their initial
    sigmas (not the ones ``--fix-others`` found moved: those were meant to move)."""
    ref = report["refine"]
    far = [(c, m) for c, m in ref["cameras"].items()
           if c not in ref["moved_since_init"] and m["initial_sigma_mm"]
           and m["moved_mm"] > REFINE_MOVE_SIGMAS * m["initial_sigma_mm"]]
    if not far:
        return []
    return [finding(
        "warning",
        "refine_moved",
        [c for c, _ in far],
        "The depth pairs moved " + ", ".join(
            f"{c} by {m['moved_mm']:.2f} mm ({m['moved_mm'] / m['initial_sigma_mm']:.0f} "
            "initial sigmas)" for c, m in far)
        + ": the depth and the initial calibration disagree.",
        "Check those cameras' depth (scale, multipath on shiny surfaces) and whether they "
        "moved since the calibration (rgbd-calib check); the initial extrinsics are in --init.",
    )]


def depth_scale_unknown(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Depth-only refinement: cameras whose depth-scale factor was neither in the report.json
    next to --init nor measured from a board in view."""
    unknown = [c for c, m in report["refine"]["cameras"].items()
               if m["depth_scale_source"] == "unknown"]
    if not unknown:
        return []
    return [finding(
        "warning",
        "depth_scale_unknown",
        unknown,
        f"Depth scale unknown for {', '.join(unknown)}: their pairs were not allowed to move "
        "them along the directions a depth-scale error explains.",
        "Keep the calibration's report.json next to the --init extrinsics.yaml (it holds "
        "each camera's depth-scale factor), or record with the board in view.",
    )]


def refit_failed(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """``refine --fix-others``: a camera found moved that no pair fits after its
    re-registration (its pose is the check's estimate)."""
    ref = report["refine"]
    lost = [c for c in ref["moved_since_init"]
            if not any(p["accepted"] and c in (p["cam_a"], p["cam_b"]) for p in report["pairs"])]
    if not lost:
        return []
    return [finding(
        "warning",
        "refit_failed",
        lost,
        f"{', '.join(lost)} moved since the calibration, and no camera pair fits after "
        "re-registering: its pose is the check's rough estimate.",
        f"Calibrate {', '.join(lost)} again with the board (or record frames where it overlaps "
        "more of its neighbours' views).",
    )]


RULES: tuple[Rule, ...] = (
    not_calibrated,
    inconsistent_camera,
    camera_model_error,
    weak_camera,
    each_sound_camera(few_views, weak_link),
    board_glue,
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
    board_scale,
    depth_scale,
)


# a depth-only refinement has no board views: only these rules apply to it
DEPTH_ONLY_RULES: tuple[Rule, ...] = (
    not_calibrated,
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
    for rule in DEPTH_ONLY_RULES if _depth_only(report) else RULES:
        found += rule(report, found)
    return sorted(found, key=lambda w: SEVERITY_ORDER[w["severity"]])
