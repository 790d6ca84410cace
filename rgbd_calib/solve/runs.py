"""Consecutive frames of a continuous recording: their corner errors are not independent.

A recording kept whole (a ``.bag`` converted frame by frame, ``record``, ``synth --burst``)
holds runs of frame sets a frame period apart in which the board hardly moves. Each camera
then sees each marker almost as before: the detector's systematic error of that marker at
that pose (blur, aliasing, the corner refinement's bias on a slanted marker) repeats, and only
the sensor noise is new. The bundle adjustment weighs every corner as independent, so three
near-identical frames claim three times the information of one, and the marginal sigmas come
out too small (race, bursts of 3, 0.3 m/s: RMS error / sigma 2.9).

:func:`recording_runs` finds the runs from the frame sets' times; :func:`run_inflation`
measures, per camera, the correlation ``rho`` of the corner residuals of the same marker in
two views of one run, and gives the variance factor of that camera's estimates: a run of
``n`` views with equicorrelated errors is worth ``n / (1 + (n - 1) rho)`` independent ones
(the design effect of cluster sampling; Kish 1965), so the factor is
``sum n / sum(n / (1 + (n - 1) rho))``. Independent frames (``rho`` ~ 0) keep factor 1: a
recording of separate poses, or a continuous one whose noise dominates, is not touched. Pure
numpy; the bundle adjustment (:mod:`rgbd_calib.solve.bundle`) supplies the residuals.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Collection, Mapping
from dataclasses import dataclass

import numpy as np

MIN_PAIRS = 20  # common marker pairs a camera needs before its correlation is trusted
# time_link_ms auto: consecutive frame sets are linked when at most LINK_PERIODS frame periods
# apart, never below LINK_MIN_MS (the fixed window before auto existed, so a 30 fps recording
# links exactly as it did, a dropped frame's gap included); the frame period is the median gap
# between consecutive sets among gaps up to MAX_FRAME_PERIOD_MS (a 5 fps camera's: slower
# recordings are separate poses, not a trajectory)
LINK_PERIODS = 1.5
LINK_MIN_MS = 100.0
MAX_FRAME_PERIOD_MS = 200.0


@dataclass(frozen=True)
class RunCorrelation:
    """One camera's corner-error correlation between views of a run (``rho``, clipped to
    [0, 1]), from ``pairs`` common markers, and the variance factor it gives (>= 1)."""

    rho: float
    pairs: int
    factor: float


def frame_period_ms(set_ms: Mapping[str, float]) -> float | None:
    """The recording's frame period (ms): the median gap between frame sets consecutive in
    ``set_ms`` (each set's time, ms) among the gaps up to :data:`MAX_FRAME_PERIOD_MS`; None
    without two such gaps (separate poses, or no timestamps)."""
    times = np.sort(np.fromiter(set_ms.values(), float, len(set_ms)))
    gaps = np.diff(times)
    gaps = gaps[(gaps > 0.0) & (gaps <= MAX_FRAME_PERIOD_MS)]
    return float(np.median(gaps)) if len(gaps) >= 2 else None


def link_window_ms(setting: float | str, set_ms: Mapping[str, float]) -> float:
    """``bundle.time_model.time_link_ms`` as a number: a number as given; ``"auto"``
    :data:`LINK_PERIODS` frame periods of the recording (:func:`frame_period_ms`), at least
    :data:`LINK_MIN_MS`; :data:`LINK_MIN_MS` when the sets show no frame period (nothing to
    link then, or the stretches of a 30 fps recording)."""
    if setting != "auto":
        return float(setting)
    period = frame_period_ms(set_ms)
    return LINK_MIN_MS if period is None else max(LINK_MIN_MS, LINK_PERIODS * period)


def recording_runs(set_ms: Mapping[str, float], views: Collection[str],
                   max_ms: float) -> tuple[tuple[str, ...], ...]:
    """The runs of ``views`` (two or more) whose consecutive frame sets are no more than
    ``max_ms`` apart by ``set_ms`` (each set's time, ms): the stretches of a continuous
    recording. Views without a time, and ``max_ms`` 0, give none."""
    timed = sorted((set_ms[v], v) for v in views if v in set_ms)
    runs: list[list[str]] = []
    last = None
    for t, v in timed:
        if last is not None and max_ms > 0 and 0.0 < t - last <= max_ms:
            runs[-1].append(v)
        else:
            runs.append([v])
        last = t
    return tuple(tuple(r) for r in runs if len(r) > 1)


def run_inflation(runs: tuple[tuple[str, ...], ...],
                  residuals: Mapping[tuple[str, str, int], np.ndarray],
                  ) -> dict[str, RunCorrelation]:
    """Per camera seen in two views of a run: :class:`RunCorrelation` from ``residuals``
    ``(camera, view, marker) -> (4, 2)`` corner residuals (px). ``rho`` pools
    ``sum r_i . r_j / sqrt(sum |r_i|^2 sum |r_j|^2)`` over every two views of a run and their
    common markers; the views of no run count as runs of one. A camera with fewer than
    :data:`MIN_PAIRS` common markers gets factor 1."""
    markers: dict[tuple[str, str], dict[int, np.ndarray]] = defaultdict(dict)
    for (camera, view, marker), r in residuals.items():
        markers[(camera, view)][marker] = np.asarray(r, float).ravel()
    cameras = sorted({c for c, _ in markers})
    out = {}
    for c in cameras:
        sxy = sxx = syy = 0.0
        pairs = 0
        sizes = []
        for run in runs:
            seen = [markers[(c, v)] for v in run if (c, v) in markers]
            if len(seen) < 2:
                sizes += [1] * len(seen)
                continue
            sizes.append(len(seen))
            for i in range(len(seen)):
                for j in range(i + 1, len(seen)):
                    for m in seen[i].keys() & seen[j].keys():
                        a, b = seen[i][m], seen[j][m]
                        sxy += float(a @ b)
                        sxx += float(a @ a)
                        syy += float(b @ b)
                        pairs += 1
        in_runs = {v for run in runs for v in run}
        sizes += [1] * sum(1 for cam, v in markers if cam == c and v not in in_runs)
        if pairs == 0:
            continue
        rho = float(np.clip(sxy / np.sqrt(sxx * syy), 0.0, 1.0)) if sxx * syy > 0 else 0.0
        n = np.array(sizes, float)
        factor = (float(n.sum() / np.sum(n / (1.0 + (n - 1.0) * rho)))
                  if pairs >= MIN_PAIRS else 1.0)
        out[c] = RunCorrelation(rho, pairs, factor)
    return out


@dataclass(frozen=True)
class SetSelection:
    """The frame sets a long continuous recording was thinned to (:func:`select_sets`):
    ``kept`` in time order, out of ``total`` sets with board views, as runs of up to
    ``run_length`` consecutive sets."""

    kept: tuple[str, ...]
    total: int
    run_length: int

    def to_dict(self) -> dict:
        return {"kept": len(self.kept), "total": self.total, "run_length": self.run_length}


def select_sets(set_ms: Mapping[str, float], seen: Mapping[str, Mapping[str, int]],
                max_sets: int, run_length: int, max_ms: float,
                min_camera_views: int | None = None) -> SetSelection | None:
    """Thin a continuous recording to about ``max_sets`` frame sets, or None when it has no
    more (or no runs: separate poses are all kept). ``seen``: per set, the markers each
    camera saw of the board.

    A recording kept whole holds a frame set every frame period: 1800 sets in a minute, each
    near its neighbours. What the calibration needs of them is the board at many poses, and at
    each pose a few consecutive sets (the motion prior measures the board's twist from them:
    :func:`recording_runs`). So the sets in time order are cut into ``max_sets //
    run_length`` equal stretches, and each keeps its best window of ``run_length``
    consecutive sets of one run (a shorter run: all of it), scored by the cameras that see
    the board in it, then their markers (sets two cameras see link them). A camera left with
    fewer than ``min_camera_views`` views (default a fifth of ``max_sets``; all it had, when
    fewer) gets its best windows back, so thinning never drops a camera a sparse view links
    to the rig."""
    cands = [v for v, cams in seen.items() if cams]
    if max_sets <= 0 or len(cands) <= max_sets:
        return None
    runs = recording_runs(set_ms, cands, max_ms)
    if not runs:
        return None
    order = sorted(cands, key=lambda v: (set_ms.get(v, np.inf), v))
    index = {v: i for i, v in enumerate(order)}
    most = max(sum(c.values()) for c in seen.values() if c)
    score = {v: len(seen[v]) + sum(seen[v].values()) / (1.0 + most) for v in cands}
    in_runs = {v for r in runs for v in r}
    windows = []  # (start index in time order, score, sets)
    for seg in list(runs) + [(v,) for v in order if v not in in_runs]:
        k = min(run_length, len(seg))
        windows += [(index[seg[i]], sum(score[v] for v in seg[i:i + k]), seg[i:i + k])
                     for i in range(len(seg) - k + 1)]
    stretches = max(1, max_sets // max(1, run_length))
    bounds = np.linspace(0, len(order), stretches + 1)
    best: dict[int, list] = defaultdict(list)
    for w in windows:
        best[int(np.searchsorted(bounds, w[0], side="right")) - 1].append(w)
    kept: set[str] = set()
    for stretch in sorted(best):
        for _, _, sets in sorted(best[stretch], key=lambda w: (-w[1], w[0])):
            if not kept.intersection(sets):
                kept.update(sets)
                break
    floor = max_sets // 5 if min_camera_views is None else min_camera_views
    for camera in sorted({c for cams in seen.values() for c in cams}):
        want = min(sum(camera in seen[v] for v in cands), floor)
        have = sum(camera in seen[v] for v in kept)
        ranked = sorted((w for w in windows if any(camera in seen[v] for v in w[2])),
                        key=lambda w: (-sum(seen[v].get(camera, 0) for v in w[2]), w[0]))
        for _, _, sets in ranked:
            if have >= want:
                break
            have += sum(camera in seen[v] for v in sets if v not in kept)
            kept.update(sets)
    return SetSelection(tuple(sorted(kept, key=index.__getitem__)), len(cands),
                        run_length)
