"""Findings about time: cameras that did not capture at the same instant, a rolling shutter,
and a board that moved while they did (the time model, ``report.bundle.time``;
:mod:`.findings` runs the rules)."""

from __future__ import annotations

from typing import Any

from .findings_base import Finding, finding
from .findings_cameras import explained_model_errors
from .numbers import fmt

TIME_ADVICE = (
    "For the best accuracy hold the board still for a moment at each pose (or pick those "
    "frames), connect the cameras' sync cable (D435i: inter_cam_sync_mode), and record with "
    "timestamps (rgbd-calib record and convert keep them in timestamps.csv), which fix the "
    "clocks' scale; keep the recording's consecutive frames (convert every frame of the .bag): "
    "they measure the board's motion; more frame sets help too."
)


def time_sentence(time: dict[str, Any], reference: str) -> str:
    """'The board moved at 0.30 m/s (median; max 0.35) and 29 deg/s while the cameras exposed:
    clock offsets from left0: left1 -15.2 +- 0.3 ms, ...; rolling-shutter readouts 25.1 ms
    (24.7-25.6)' from ``report.bundle.time``."""
    cams = time["cameras"]
    others = [c for c in sorted(cams) if c != reference]
    offsets = ", ".join(f"{c} {cams[c]['offset_ms']:+.1f} +- {fmt(cams[c]['offset_sigma_ms'], 1)}"
                        for c in others)
    readouts = [cams[c]["readout_ms"] for c in sorted(cams)]
    speed, rate = time["board_speed_mps"], time["board_rate_dps"]
    linked = time.get("linked_sets", 0)
    return (
        f"The board moved at {speed['median']:.2f} m/s (median over the frame sets; max "
        f"{speed['max']:.2f}) and {rate['median']:.0f} deg/s while the cameras exposed; clock "
        f"offsets from {reference} (ms): {offsets or 'none'}; rolling-shutter readouts "
        f"{min(readouts):.1f}-{max(readouts):.1f} ms"
        + (f"; {linked} consecutive frame sets tracked the board's motion and acceleration"
           if linked else "")
    )


def capture_time(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The time model was chosen (``bundle.time``): the cameras' clocks, readouts and the
    board's motion explained views that disagreed under the timeless model. A warning when no
    camera's offset is anchored by timestamps: the clocks' scale is then a gauge of the images
    (docs/conventions.md 'Time'): offsets, readouts and speeds are known only up to a common
    factor (the extrinsics are not affected), and a global shutter loses most of what a moving
    board's views measure, and only the offsets' wide prior keeps the per-set motions from
    taking up other misfit (docs/accuracy.md, the Caliscope webcams). Else an info."""
    time = (report.get("bundle") or {}).get("time")
    if not time:
        return []
    anchored = bool(time["anchored_by_timestamps"])
    scale = ("" if anchored else
             " No timestamps.csv anchors the clocks (frames matched by index): offsets, "
             "readouts and speeds are known only up to a common scale factor and only a wide "
             "prior holds the offsets; the model was kept because it predicts each view from "
             "the other cameras' views better than the timeless model; keep timestamps.csv, "
             "or compare with --time fixed if the board was held still.")
    return [finding(
        "info" if anchored else "warning",
        "capture_time",
        sorted(time["cameras"]),
        "Cameras did not capture the moving board at the same instant; the time model "
        "(each camera's clock offset and readout, each frame set's board motion) explains "
        f"the views' disagreement and the extrinsics account for it. "
        f"{time_sentence(time, report['reference'])}.{scale}",
        TIME_ADVICE,
    )]


def time_unresolved(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The pose graph found cameras whose views disagree beyond their noise and the chosen
    model did not explain them (a lens or back sheet would have), the time model was tried
    and fitted them, but it predicted each view's corners from the other cameras' views worse
    than the timeless model (the ladder's held-out check): its per-set motions and clocks took
    up what the data do not fix (single frames through global shutters, clocks that no
    timestamps anchor), so it was not kept, and the timeless result carries the disagreement.
    An error: the extrinsics are as good as a moving board's single unsynchronised frames
    allow, which is not good enough to fuse clouds."""
    bundle = report.get("bundle") or {}
    ladder = (bundle.get("self_calibration") or {}).get("levels") or []
    rejected = [lv for lv in ladder if lv.get("time") and not lv.get("accepted")
                and lv.get("held_out") and lv["held_out"]["rms_after_px"]
                >= lv["held_out"]["rms_before_px"]]
    unexplained = {m["camera"] for m in report["pose_graph"].get("model_error") or []
                   } - explained_model_errors(report)
    if bundle.get("time") or not rejected or not unexplained:
        return []
    held = rejected[0]["held_out"]
    cams = sorted(unexplained)
    return [finding(
        "error",
        "time_unresolved",
        cams,
        "The cameras' views of the board disagree beyond their noise, as a board moving "
        "through unsynchronised cameras makes them; the time model fitted them, but predicted "
        "held-out views worse than the timeless model (corner RMS "
        f"{held['rms_before_px']:.2f} -> {held['rms_after_px']:.2f} px on {held['views']} "
        "views): these recordings cannot fix the board's motion, so the extrinsics keep the "
        "disagreement.",
        "Record again with timestamps.csv (rgbd-calib record or convert keep them), the "
        "cameras' sync cable, or the board held still at each pose; to accept the timeless "
        "result as it is, calibrate with --time fixed --accept-poor.",
    )]


OFFSET_PRIOR_K = 3.0  # an offset this many prior sigmas out contradicts the frame matching


def time_offsets_implausible(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The time model was kept with a camera's clock offset beyond :data:`OFFSET_PRIOR_K`
    sigmas of its prior (the timestamps' jitter where they anchor it, the wide prior of
    frames matched by index otherwise): the per-set motions and the clocks traded with the
    extrinsics until the clocks left what the recording allows. An error."""
    time = (report.get("bundle") or {}).get("time")
    if not time:
        return []
    out = {c: (d["offset_beyond_timestamps_ms"], d["offset_prior_sigma_ms"])
           for c, d in time["cameras"].items()
           if d.get("offset_prior_sigma_ms") and abs(d["offset_beyond_timestamps_ms"])
           > OFFSET_PRIOR_K * d["offset_prior_sigma_ms"]}
    if not out:
        return []
    matched = time.get("frames_matched_by", "index")
    said = ", ".join(f"{c} {o:+.1f} ms (prior +-{s:.0f})" for c, (o, s) in sorted(out.items()))
    return [finding(
        "error",
        "time_offsets_implausible",
        sorted(out),
        f"The time model put clock offsets beyond {OFFSET_PRIOR_K:.0f} sigmas of what the "
        f"frame matching ({matched}) allows: {said}; the board's motions and the clocks took "
        "up misfit they cannot be, and the extrinsics with them.",
        "Record with timestamps.csv and the sync cable, or hold the board still at each pose; "
        "compare with --time fixed.",
    )]


MOVED_SETS_WARNING = 0.25  # of the frame sets: more moved, and the finding is a warning


def moving_board(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """Frame sets the board moved during (``report.motion``, :mod:`rgbd_calib.solve.stillness`):
    most of their cameras saw it at poses that disagree, so the pose graph left those views out
    and the rest of the recording, held still, kept the timeless model. An info while few sets
    moved; a warning when more than :data:`MOVED_SETS_WARNING` of them did (their views are
    lost to the calibration)."""
    motion = report.get("motion") or []
    moved = [m for m in motion if m["moved"]]
    if not moved:
        return []
    views = sum(len(m["outliers"]) for m in moved)
    speeds = [m["speed_mps"] for m in moved if m["speed_mps"] is not None]
    low, high = (f"{min(speeds):.2f}", f"{max(speeds):.2f}") if speeds else ("", "")
    speed = (f"; the timestamps put the board at {low}{'' if low == high else '-' + high} m/s"
             if speeds else "")
    spread = sorted(m["spread_mm"] for m in moved)
    frames = ", ".join(m["frame"] for m in moved[:8]) + (" ..." if len(moved) > 8 else "")
    return [finding(
        "warning" if len(moved) > MOVED_SETS_WARNING * len(motion) else "info",
        "moving_board",
        sorted({c for m in moved for c in m["outliers"]}),
        f"The board moved during {len(moved)} of {len(motion)} frame sets ({frames}): their "
        f"cameras saw it up to {spread[-1]:.1f} mm apart (median {spread[len(spread) // 2]:.1f} "
        f"mm){speed}. Their {views} disagreeing views were left out (the other sets were held "
        "still, so the timeless model was kept); the cameras themselves are not at fault.",
        "Hold the board still for a moment at each pose (a sync cable lets it move: "
        "D435i inter_cam_sync_mode); record more sets if these cameras lack views.",
    )]
