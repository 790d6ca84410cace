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


@dataclass(frozen=True)
class RunCorrelation:
    """One camera's corner-error correlation between views of a run (``rho``, clipped to
    [0, 1]), from ``pairs`` common markers, and the variance factor it gives (>= 1)."""

    rho: float
    pairs: int
    factor: float


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
