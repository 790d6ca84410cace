"""Findings about time: cameras that did not capture at the same instant, a rolling shutter,
and a board that moved while they did (the time model, ``report.bundle.time``;
:mod:`.findings` runs the rules)."""

from __future__ import annotations

from typing import Any

from .findings_base import Finding, finding
from .numbers import fmt

TIME_ADVICE = (
    "For the best accuracy hold the board still for a moment at each pose (or pick those "
    "frames), connect the cameras' sync cable (D435i: inter_cam_sync_mode), and record with "
    "timestamps (rgbd-calib record and convert keep them in timestamps.csv), which fix the "
    "clocks' scale; more frame sets help too."
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
    return (
        f"The board moved at {speed['median']:.2f} m/s (median over the frame sets; max "
        f"{speed['max']:.2f}) and {rate['median']:.0f} deg/s while the cameras exposed; clock "
        f"offsets from {reference} (ms): {offsets or 'none'}; rolling-shutter readouts "
        f"{min(readouts):.1f}-{max(readouts):.1f} ms"
    )


def capture_time(report: dict[str, Any], earlier: list[Finding]) -> list[Finding]:
    """The time model was chosen (``bundle.time``): the cameras' clocks, readouts and the
    board's motion explained views that disagreed under the timeless model. A warning when no
    camera's offset is anchored by timestamps: the clocks' scale is then a gauge of the images
    (docs/conventions.md 'Time'): offsets, readouts and speeds are known only up to a common
    factor (the extrinsics are not affected), and a global shutter loses most of what a moving
    board's views measure. Else an info."""
    time = (report.get("bundle") or {}).get("time")
    if not time:
        return []
    anchored = bool(time["anchored_by_timestamps"])
    scale = ("" if anchored else
             " No timestamps.csv anchors the clocks: offsets, readouts and speeds are known only "
             "up to a common scale factor (the extrinsics are not affected).")
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
