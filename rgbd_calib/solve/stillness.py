"""Stillness: did the board move while a frame set was captured? (pure numpy)

Cameras that do not capture at one instant see a moving board at different poses. The time
model (:mod:`.time_model`) explains that when the whole recording moves; when most sets were
held still and a few were not, the timeless model is kept and the pose graph rejects those
few sets' views as outliers (their weight goes to 0: they are down-weighted, not kept). This
module tells such sets from a camera that disagrees with the rig: per set, where each
camera's PnP pose puts the board in the reference frame (through the calibrated extrinsics),
how far those poses spread, how fast the board went when the views' capture times are known
(``timestamps.csv``), and whether the set moved: at least :data:`MOVED_MIN_OUTLIERS` of its
views, and at least half of them, rejected. A camera with a wrong lens or a bad clock
disagrees in most of its own sets; a moving board makes most cameras of one set disagree.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

MOVED_MIN_OUTLIERS = 2  # rejected views a set needs (and at least half of its views) to have moved
MIN_TIME_SPAN_MS = 2.0  # capture times spread less than this do not give a speed


@dataclass(frozen=True)
class SetMotion:
    """One frame set: the cameras whose PnP solved the board there, those whose view the pose
    graph rejected, the RMS distance (mm) of the views' board centres from their mean, the
    board's speed (m/s; least squares of centre against capture time; None without
    timestamps or with the views captured within :data:`MIN_TIME_SPAN_MS`) and whether the
    set moved (see the module docstring)."""

    frame: str
    cameras: tuple[str, ...]
    outliers: tuple[str, ...]
    spread_mm: float
    speed_mps: float | None
    moved: bool

    def to_dict(self) -> dict[str, Any]:
        return {"frame": self.frame, "cameras": list(self.cameras),
                "outliers": list(self.outliers), "spread_mm": self.spread_mm,
                "speed_mps": self.speed_mps, "moved": self.moved}


def _speed_mps(centres: np.ndarray, times_ms: np.ndarray) -> float | None:
    """|v| of the least-squares line ``centre = c0 + v t`` (m, ms -> m/s)."""
    if len(times_ms) < 2 or np.ptp(times_ms) < MIN_TIME_SPAN_MS:
        return None
    t = times_ms - times_ms.mean()
    v = (t[:, None] * (centres - centres.mean(axis=0))).sum(axis=0) / float(t @ t)
    return float(np.linalg.norm(v) * 1e3)


def set_motion(frame: str, centres: dict[str, np.ndarray], outliers: Iterable[str],
               capture_ms: dict[str, float] | None = None) -> SetMotion:
    """:class:`SetMotion` of one set from each camera's board centre in the reference frame
    (m) and, when known, each view's capture time after the reference camera's (ms)."""
    cams = tuple(sorted(centres))
    out = tuple(sorted(set(outliers) & set(cams)))
    P = np.array([centres[c] for c in cams], dtype=float).reshape(-1, 3)
    spread = float(np.sqrt(np.mean(np.sum((P - P.mean(axis=0)) ** 2, axis=1))) * 1e3) \
        if len(P) else 0.0
    speed = None
    if capture_ms is not None and all(c in capture_ms for c in cams):
        speed = _speed_mps(P, np.array([capture_ms[c] for c in cams], dtype=float))
    moved = len(out) >= MOVED_MIN_OUTLIERS and 2 * len(out) >= len(cams)
    return SetMotion(frame, cams, out, spread, speed, moved)


def board_motion(view_poses: Iterable[tuple[str, str, np.ndarray]],
                 T_ref_cam: dict[str, np.ndarray], outliers: set[tuple[str, str]],
                 centre_board: np.ndarray,
                 capture_ms: dict[tuple[str, str], float] | None = None) -> list[SetMotion]:
    """Every frame set's :class:`SetMotion`: ``view_poses`` ``(camera, frame, T_cam_board)``
    (PnP, 4x4, m), the calibrated ``T_ref_cam``, the pose-graph ``outliers`` ``(camera,
    frame)``, the board point whose path is followed (board frame, m; its centre) and each
    view's capture time after the reference's (ms; :func:`.time_model.capture_offsets`)."""
    centres: dict[str, dict[str, np.ndarray]] = defaultdict(dict)
    c_h = np.append(np.asarray(centre_board, dtype=float), 1.0)
    for cam, frame, T_cam_board in view_poses:
        if cam in T_ref_cam:
            centres[frame][cam] = (T_ref_cam[cam] @ (T_cam_board @ c_h))[:3]
    out = []
    for frame in sorted(centres):
        times = None if capture_ms is None else {
            c: capture_ms[(c, frame)] for c in centres[frame] if (c, frame) in capture_ms}
        out.append(set_motion(frame, centres[frame],
                              [c for c, f in outliers if f == frame], times))
    return out
