"""Findings about the depth stage: camera pairs, unused depth, the board's print scale and the
cameras' depth scale; and those of a depth-only refinement (``rgbd-calib refine``)
(:mod:`.findings` runs the rules)."""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

import numpy as np

from .findings_base import Finding, Rule, finding
from .schema import (
    BOARD_SCALE_MIN,
    BOARD_SCALE_SPREAD,
    DEPTH_SCALE_TOL,
    FAR_FRACTION,
    FAR_SIGMA_MM,
    FAR_WARN_SIGMA_MM,
    PAIR_FINAL_EXCESS_MM,
    PAIR_FITNESS_MIN,
    PAIR_RMSE_MAX_MM,
    REFINE_MOVE_SIGMAS,
)


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
    ``--init``'s) uncertainty and its own
    (:func:`rgbd_calib.depth.stage.consistent_with_board`), or it was accepted and then not
    used (the joint solve failed or moved a camera too far)."""
    return bool({"beyond_extrinsics", "not_used"} & set(pair.get("rejected_by") or ()))


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
    confirms them, it has nothing to correct (a warning there had made a good result's verdict
    CHECK; measured: docs/report_schema.md)."""
    status = (report.get("depth") or {}).get("status")
    if status is not None and status != "fallback":
        return []
    ran = "depth" in report.get("timings_s", {}) or is_depth_only(report)
    if not ran or any(p["accepted"] for p in report["pairs"]):
        return []
    start = "the initial extrinsics (--init)" if is_depth_only(report) else "the board result"
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
    reasons = rejection_reasons(pairs)
    why = (f"all {len(pairs)} camera pairs were rejected ({'; '.join(reasons[:3])}"
           f"{'; ...' if len(reasons) > 3 else ''})" if pairs
           else (report.get("depth") or {}).get("reason")
           or "no camera pair overlapped under the board extrinsics")
    modelled = [] if is_depth_only(report) else beyond_scale(report, pairs)
    because = (f". The pairs register each camera's depth divided by its scale alone, and the "
               f"depth models of {', '.join(modelled)} found errors beyond the scale (a "
               "disparity offset or the depth sensor's pose), which move the surfaces the "
               "pairs register by millimetres beyond the board's depths"
               if modelled else "")
    return [finding(
        "warning",
        "depth_unused",
        [],
        f"Depth refinement added nothing: {why}; the extrinsics are {start}{because}.",
        f"{start[0].upper()}{start[1:]} stands on its own; see the pairs table for each "
        "pair's reason" + ("; for depth that helps, hold the board where the cameras' views "
                           "overlap, near and far (docs/depth.md, 'Weak board data')"
                           if modelled else "") + ".",
    )]


def rejection_reasons(pairs: list[dict[str, Any]]) -> list[str]:
    """The rejected pairs' reasons (the first clause of each), alike ones (of one kind,
    ``pairs[].rejected_by``, and equal but for their numbers) once with their count, the
    commonest first; a group of moves beyond the extrinsics says the moves' range."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for p in pairs:
        if p.get("reason"):
            first = str(p["reason"]).split(";")[0]
            kinds = p.get("rejected_by") or ["?"]
            groups.setdefault((kinds[0], re.sub(r"\d+(\.\d+)?", "#", first)), []).append(p)
    out = []
    for (kind, _), group in sorted(groups.items(), key=lambda kv: (-len(kv[1]), kv[0])):
        first = str(group[0]["reason"]).split(";")[0]
        mm = [float(p["correction_mm"]) for p in group if p.get("correction_mm") is not None]
        if len(group) == 1:
            out.append(first)
        elif kind == "beyond_extrinsics" and mm:
            out.append(f"{len(group)} pairs: ICP moved {min(mm):.1f}-{max(mm):.1f} mm from the "
                       "board's extrinsics, beyond their uncertainty and the pair's: a wrong "
                       "local minimum or a depth error")
        else:
            out.append(f"{len(group)} pairs like: {first}")
    return out


def beyond_scale(report: dict[str, Any], pairs: list[dict[str, Any]]) -> list[str]:
    """The cameras of ``pairs`` whose depth model (report.json ``depth_models``) has a term
    beyond the scale: the depth calibrate's pairs register (divided by the scale alone) is off
    by it."""
    models = report.get("depth_models") or {}
    cams = {c for p in pairs for c in (p["cam_a"], p["cam_b"])}
    return sorted(c for c in cams
                  if any(t != "scale" for t in (models.get(c) or {}).get("terms") or ()))


def common_depth_scale(factors: dict[str, tuple[float, float]]) -> float | None:
    """The depth-scale ratio every camera agrees on, when it says the board's print differs
    from its board file; None otherwise.

    ``factors``: camera -> (factor, sigma) of ``z_measured ~ factor * z_board`` (depth/clouds.py),
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
    """A camera whose depth reads long or short by more than :data:`DEPTH_SCALE_TOL`, and
    significantly so: its depth model's scale (``depth_models``; a camera whose model has
    every term free has the scale whether it is needed or not), or, in a report without one,
    its factor, more than 3 sigmas from 1. One finding names every such camera (it says one
    thing for all of them)."""
    if any(w["code"] == "board_scale" for w in earlier):
        return []  # one board finding instead of every camera's depth blamed
    off = []
    for name, cam in report["cameras"].items():
        f, modelled = _significant_scale(cam, (report.get("depth_models") or {}).get(name))
        if f is not None and abs(f - 1.0) > DEPTH_SCALE_TOL:
            off.append((name, f, modelled))
    if not off:
        return []
    names = [n for n, _, _ in off]
    reads = ", ".join(f"{n} {100 * (f - 1):+.2f}%" for n, f, _ in off)
    divide = ", ".join(f"{n}'s by {f:.4f}" for n, f, _ in off)
    whose = names[0] if len(names) == 1 else "their"
    modelled = [n for n, _, m in off if m]
    advice = (f"Correct {', '.join(modelled)}'s depth with depth_model.yaml "
              "(rgbd_calib.correct_depth_image, or convert --depth-model); fused.ply already "
              f"is. The scale alone: divide {divide}." if modelled else
              f"Divide {divide} (or recalibrate {whose} depth unit).")
    return [finding(
        "info", "depth_scale", names,
        f"The depth reads off the board's true distance: {reads}.", advice)]


def _significant_scale(cam: dict[str, Any], model: dict[str, Any] | None
                       ) -> tuple[float | None, bool]:
    """(the camera's significant depth-scale factor or None, whether a depth model says so)."""
    if model is not None:
        if "scale" not in model.get("terms", []):
            return None, True
        f, sigma = float(model["parameters"]["scale"]), (model.get("sigmas") or {}).get("scale")
        return (None if sigma and abs(f - 1.0) <= 3.0 * sigma else f), True
    f, sigma = cam.get("depth_scale_factor"), cam.get("depth_scale_sigma")
    if f is None or (sigma and abs(f - 1.0) <= 3.0 * sigma):
        return None, False
    return float(f), False


def is_far(fraction: float, sigma_mm: float, above_mm: float = FAR_SIGMA_MM) -> bool:
    """Whether a camera's cloud lies largely (``fraction`` of it, at least
    :data:`FAR_FRACTION`) beyond the depths its model was fitted on, where its depth is known
    to worse than ``above_mm`` (``sigma_mm``, 1 sigma): the rule of ``depth_extrapolated``
    (``above_mm`` :data:`FAR_WARN_SIGMA_MM`: its warning, and the console's fused-cloud
    line)."""
    return fraction >= FAR_FRACTION and sigma_mm > above_mm


def far_cameras(report: dict[str, Any], above_mm: float = FAR_SIGMA_MM
                ) -> list[tuple[str, dict[str, Any], int | None]]:
    """``(camera, beyond_board, board views)`` of the cameras :func:`is_far` by their
    ``depth_models.<camera>.beyond_board``."""
    return [(c, m["beyond_board"], m.get("n_views"))
            for c, m in (report.get("depth_models") or {}).items()
            if m.get("beyond_board") and is_far(m["beyond_board"]["fraction"],
                                                m["beyond_board"]["sigma_mm"], above_mm)]


def depth_extrapolated(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Cameras whose cloud lies largely beyond the depths their model was fitted on, where
    their depth is known to worse than :data:`FAR_SIGMA_MM` (:func:`far_cameras`): the far
    part of ``fused.ply`` is an extrapolation of the board. A warning for those known to
    worse than :data:`FAR_WARN_SIGMA_MM` (their far cloud can be centimetres off the true
    surfaces, and the overlaps cannot tell when two cameras err alike), which names the others
    too (one finding says it once); an info when all are known better."""
    uncertain = far_cameras(report, FAR_WARN_SIGMA_MM)
    rest = [f for f in far_cameras(report) if f not in uncertain]
    out = []
    if uncertain:  # one finding: the others beyond the board are said in it, not again
        others = ("; the other cameras' far clouds ("
                  + ", ".join(f"{c} +-{b['sigma_mm']:.1f} mm" for c, b, _ in rest)
                  + ") are known better") if rest else ""
        return [finding(
            "warning", "depth_extrapolated", [c for c, _, _ in uncertain],
            "fused.ply beyond the board's depths can be centimetres off the true surfaces: "
            + "; ".join(f"{c}'s depth is known to +-{b['sigma_mm']:.0f} mm (1 sigma) at "
                        f"{b['cloud_p90_m']:.1f} m, {100 * b['fraction']:.0f} % of its cloud "
                        f"beyond the board's {b['board_max_m']:.2f} m"
                        + (f", from {n} board views" if n else "")
                        for c, b, n in uncertain)
            + others + ". The overlaps cannot see an error that overlapping cameras share.",
            "Record again with the board held in front of these cameras in more poses (their "
            "depth model frees every term from 15 views) and at the distances of their scene, "
            "or leave their far points out of the fused cloud; docs/depth.md, 'Few board "
            "views'.")]
    if rest:
        out.append(finding(
            "info", "depth_extrapolated", [c for c, _, _ in rest],
            "fused.ply lies beyond the board's depths, where each camera's depth model is an "
            "extrapolation (points beyond the board's farthest depth; the depth's 1 sigma at "
            "the cloud's 90th percentile, over the image where its far points lie): "
            + "; ".join(
                f"{c} {100 * b['fraction']:.0f} % beyond {b['board_max_m']:.2f} m, "
                f"+-{b['sigma_mm']:.1f} mm at {b['cloud_p90_m']:.1f} m" for c, b, _ in rest)
            + ".",
            "The depth model is fitted where the board was and extrapolated beyond: hold the "
            "board at those distances too (the cameras that detect it place it; "
            "depth.model_fit.model_unseen_views reads it where this camera cannot detect it), "
            "or count the far cloud that uncertain; docs/depth.md."))
    return out


def depth_unmodelled(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Cameras with depth that got no depth model from the board (``depth.unmodelled``): their
    part of ``fused.ply`` is their raw depth, which a D435 reads millimetres off."""
    unmodelled = (report.get("depth") or {}).get("unmodelled") or {}
    if not unmodelled:
        return []
    return [finding(
        "warning", "depth_unmodelled", sorted(unmodelled),
        "No depth model for " + "; ".join(f"{c} ({why})" for c, why in sorted(
            unmodelled.items())) + ": their depth in fused.ply is uncorrected.",
        "Hold the board still where these cameras see it, at the distances their scene is; "
        "docs/depth.md.")]


def fused_disagrees(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The fused cloud: a camera (or a pair, when it cannot tell which camera) whose corrected
    depth lies off its overlapping cameras' surfaces beyond the noise (``fused_agreement``)."""
    agree = report.get("fused_agreement")
    if not agree:
        return []
    off = [p for p in agree["pairs"] if p["off"]]

    def pairs_text(ps: list[dict[str, Any]]) -> str:
        return ", ".join(f"{p['cam_a']}-{p['cam_b']} {p['after']['median_mm']:+.1f} mm "
                         f"(+-{p['after']['median_se_mm']:.1f})" for p in ps)

    advice = ("The depth model is fitted on the board: hold the board where this camera sees "
              "the scene it shares with the others (near and far, centre and edges), and check "
              "its depth for interference (a facing D435's projector); docs/depth.md.")
    bias = agree.get("camera_bias_mm") or {}
    out = [finding("warning", "fused_disagrees", [c],
                   f"fused.ply: {c}'s depth reads {bias.get(c, 0.0):+.1f} mm against the other "
                   "cameras' where they overlap, beyond the noise, after its depth model"
                   + (f" (off pairs: {pairs_text(ps)})"
                      if (ps := [p for p in off if c in (p['cam_a'], p['cam_b'])]) else "")
                   + ".", advice)
               for c in agree["off_cameras"]]
    for a, b in agree["ambiguous"]:
        ps = [p for p in off if {p["cam_a"], p["cam_b"]} == {a, b}]
        out.append(finding("warning", "fused_disagrees", [a, b],
                           f"fused.ply: {a} and {b} disagree where they overlap beyond the "
                           f"noise ({pairs_text(ps)}); the data cannot tell which one's depth "
                           "is off.", advice))
    return out


# ----------------------------------------------------------------------------- depth-only
def is_depth_only(report: dict[str, Any]) -> bool:
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
    """``refine --fix-others``: a camera found moved whose new pose the evidence does not
    confirm: no pair fits after its re-registration and no board view (its pose is the
    check's estimate), or its depth pairs and the board put it apart beyond their sigmas
    (``refine.unconfirmed``; reports before it: no accepted pair of the camera)."""
    ref = report["refine"]
    if "unconfirmed" in ref:
        why = ref["unconfirmed"]
    else:
        why = {c: "no camera pair fits after re-registering: its pose is the check's rough "
               "estimate" for c in ref["moved_since_init"]
               if not any(p["accepted"] and c in (p["cam_a"], p["cam_b"])
                          for p in report["pairs"])}
    if not why:
        return []
    lost = sorted(why)
    return [finding(
        "warning",
        "refit_failed",
        lost,
        f"{', '.join(lost)} moved since the calibration, and the evidence does not confirm "
        "where the fix put it: " + "; ".join(f"{c}: {why[c]}" for c in lost) + ".",
        f"Calibrate {', '.join(lost)} again with the board (or record frames where it overlaps "
        "more of its neighbours' views, with the board held where they all see it).",
    )]
