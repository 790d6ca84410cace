"""Timestamp matching: colour with the nearest depth of its camera, cameras into frame sets."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from ..core.errors import DatasetError
from .staging import StagedCamera, StagedFrame

DEFAULT_FPS = 30.0  # frame rate assumed when a stream has a single frame


def median_period_ms(times: Iterable[float], fps: float | None) -> float:
    t = np.sort(np.fromiter(times, dtype=float))
    steps = np.diff(t)
    steps = steps[steps > 0]
    if steps.size:
        return float(np.median(steps))
    return 1000.0 / (fps or DEFAULT_FPS)


def pair_depth(cam: StagedCamera) -> dict[int, StagedFrame]:
    """Colour index -> nearest depth frame within one colour frame period."""
    if not cam.depths:
        return {}
    t_depth = np.array([d.t_ms for d in cam.depths])
    order = np.argsort(t_depth)
    t_sorted = t_depth[order]
    tol = median_period_ms((c.t_ms for c in cam.colors), cam.fps)
    out: dict[int, StagedFrame] = {}
    for i, c in enumerate(cam.colors):
        k = int(np.searchsorted(t_sorted, c.t_ms))
        cands = [j for j in (k - 1, k) if 0 <= j < t_sorted.size]
        j = min(cands, key=lambda j: abs(t_sorted[j] - c.t_ms))
        if abs(t_sorted[j] - c.t_ms) <= tol + 1e-6:
            out[i] = cam.depths[order[j]]
    return out


def match_frames(times_ms: dict[str, np.ndarray], tolerance_ms: float) -> list[dict[str, int]]:
    """Group frames of several cameras into synchronised sets.

    The camera with the most frames is the reference; each of its frames takes, from every
    other camera, the nearest frame within ``tolerance_ms`` (one frame per set, the closest
    claim wins). Frames left over are grouped the same way among themselves, so a set may
    lack the reference camera. With several cameras a set needs at least two of them.
    Returns sets as ``{camera: frame index}`` in time order."""
    remaining = {c: np.arange(len(t)) for c, t in times_ms.items()}
    min_size = 2 if len(times_ms) > 1 else 1
    sets: list[dict[str, int]] = []
    while True:
        live = [c for c in times_ms if remaining[c].size]
        if len(live) < min_size:
            break
        ref = max(live, key=lambda c: remaining[c].size)
        ref_idx = remaining[ref]
        ref_t = times_ms[ref][ref_idx]
        groups: list[dict[str, int]] = [{ref: int(i)} for i in ref_idx]
        for cam in live:
            if cam == ref:
                continue
            idx = remaining[cam][np.argsort(times_ms[cam][remaining[cam]])]
            t = times_ms[cam][idx]
            k = np.clip(np.searchsorted(t, ref_t), 1, max(t.size - 1, 1))
            left = np.clip(k - 1, 0, t.size - 1)
            right = np.clip(k, 0, t.size - 1)
            pick = np.where(np.abs(t[left] - ref_t) <= np.abs(t[right] - ref_t), left, right)
            dt = np.abs(t[pick] - ref_t)
            best: dict[int, tuple[float, int]] = {}
            for g, (p, d) in enumerate(zip(pick, dt)):
                if d <= tolerance_ms and (p not in best or d < best[p][0]):
                    best[int(p)] = (float(d), g)
            for p, (_, g) in best.items():
                groups[g][cam] = int(idx[p])
        used = {c: set() for c in live}
        for g in groups:
            if len(g) >= min_size:
                sets.append(g)
                for c, i in g.items():
                    used[c].add(i)
        # the reference's frames are settled either way; other cameras keep what is unused
        remaining[ref] = np.array([], dtype=int)
        for c in live:
            if c != ref:
                remaining[c] = np.array([i for i in remaining[c] if i not in used[c]], dtype=int)
    sets.sort(key=lambda g: min(times_ms[c][i] for c, i in g.items()))
    return sets


def match_cameras(
    cams: list[StagedCamera], tolerance_ms: float | None
) -> tuple[str, float, list[dict[str, int]]]:
    """The cameras' colour frames as synchronised sets (:func:`match_frames`): the reference
    camera (most frames), the tolerance used (default half its frame period) and the sets."""
    times = {c.name: np.array([f.t_ms for f in c.colors]) for c in cams}
    reference = max(cams, key=lambda c: len(c.colors))
    if tolerance_ms is None:
        tolerance_ms = 0.5 * median_period_ms(times[reference.name], reference.fps)
    sets = match_frames(times, tolerance_ms)
    if not sets:
        raise DatasetError(
            f"{', '.join(c.key for c in cams)}: no frames of different cameras lie within "
            f"{tolerance_ms:.1f} ms of each other; check that the recordings overlap in "
            "time (global time enabled) or raise --sync-tolerance-ms"
        )
    return reference.name, tolerance_ms, sets


def one_clock(domains: list[str]) -> bool:
    """Whether frame times in these timestamp domains (one per camera) are on one clock: a
    single camera, or none on its camera's own ``hardware_clock`` (librealsense's
    ``global_time`` and ``system_time`` are the host's clock; ROS header stamps the ROS
    clock)."""
    return len(domains) <= 1 or all(d != "hardware_clock" for d in domains)


def shared_clock(cams: list[StagedCamera]) -> bool:
    """Whether the cameras' frame times are on one clock as far as the sources tell
    (:func:`one_clock`)."""
    return one_clock([c.timestamp_domain for c in cams])


def clock_notes(cams: list[StagedCamera]) -> list[str]:
    """A warning when cameras' timestamps may share no clock (so matching may be wrong, and
    no ``timestamps.csv`` is written)."""
    if not shared_clock(cams):
        return [
            "some recordings use the camera's hardware clock: timestamps of different "
            "cameras share no common clock, so their matching may be wrong and no "
            "timestamps.csv was written; enable global time when recording"
        ]
    return []
