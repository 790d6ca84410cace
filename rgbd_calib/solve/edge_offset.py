"""A detector's edge offset: read from the bundle's corner residuals, then modelled (pure
maths, numpy only).

A detector that sees every marker edge ``d`` px outside where it is (the edge fit on real
prints: +0.05..+0.16 px by camera, its imaging's blur and sharpening; docs/accuracy.md,
"Corners on real photos") moves each corner ``d`` along the outward normals of its two edges,
``d sqrt(2)`` along the corner's outward bisector for a square marker. The bundle predicts the
printed corners, and the poses absorb little of such a pattern (a +0.1 px offset leaves
+0.136 px of the 0.141 along the bisectors in the residuals of a race render), so each
camera's mean outward residual over its markers, over ``sqrt(2)``, reads its offset
(:func:`edge_offsets`).

The model: per camera one offset ``d`` (px per edge), taken out of its edge-fitted corners
before the solve (:func:`without_offset`; a ChArUco square's saddle corners are not edge-fitted
and keep theirs). It is estimated by a fixed-point iteration on the residuals (what the poses
absorb, ~4 %, is read again next round) and kept only for a camera whose reading is
significant (:func:`significant`): a clean camera keeps ``d = 0``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

MAD_CUT = 5.0  # markers farther than this many robust sigmas from the median are left out
# a camera's offset is modelled when its reading is at least this many standard errors and
# this large (px per edge: ~0.2 mm of extrinsics on the race and ring renders, below their
# sigmas; a clean render reads <= 0.003)
APPLY_SIGMAS = 5.0
APPLY_MIN_PX = 0.01
CONVERGED_PX = 0.002  # the iteration stops when no modelled camera's reading moves more
ITERATIONS = 4  # at most this many re-solves (each takes the residual ~25x closer)
MIN_SIZE_MARKERS = 20  # the size dependence is read from at least this many markers


@dataclass(frozen=True)
class EdgeOffset:
    """One camera's edge offset (px per edge; positive: its markers look larger than the
    board's geometry) with its standard error over ``markers`` markers; ``applied_px`` of it
    is modelled (taken out of the corners before the solve), the rest is in the residuals."""

    offset_px: float
    sigma_px: float
    markers: int
    applied_px: float = 0.0
    # what no offset holds: the part that grows with the markers' size in the image, read
    # from the residuals (not modelled): as an ink spread on the board (mm per edge) with its
    # standard error, and how much more the camera's near markers (90th percentile of size)
    # read than its far ones (10th), px per edge
    size_mm: float = 0.0
    size_sigma_mm: float = 0.0
    size_effect_px: float = 0.0

    @property
    def residual_px(self) -> float:
        """What the residuals still read: the offset no model holds."""
        return self.offset_px - self.applied_px

    def to_dict(self) -> dict[str, float | int]:
        return {"offset_px": self.offset_px, "sigma_px": self.sigma_px, "markers": self.markers,
                "applied_px": self.applied_px, "size_mm": self.size_mm,
                "size_sigma_mm": self.size_sigma_mm, "size_effect_px": self.size_effect_px}


def outward_normals(quads: np.ndarray) -> np.ndarray:
    """Unit outward normals ``(n, 4, 2)`` of each quad's edges (edge ``i``: corner ``i`` ->
    ``i+1``), outward meaning away from the quad's centre, whatever the corners' order."""
    q = np.asarray(quads, dtype=float)
    edge = np.roll(q, -1, axis=1) - q
    normal = np.stack([edge[..., 1], -edge[..., 0]], axis=-1)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    mid = (q + np.roll(q, -1, axis=1)) / 2 - q.mean(axis=1, keepdims=True)
    return normal * np.where(np.sum(normal * mid, axis=-1, keepdims=True) < 0, -1.0, 1.0)


def corner_normal_sums(quads: np.ndarray) -> np.ndarray:
    """Per corner ``(n, 4, 2)`` the sum of the outward normals of its two edges (corner ``i``
    lies on the edges ``i-1 -> i`` and ``i -> i+1``): where an edge offset of 1 px moves it."""
    normal = outward_normals(quads)
    return normal + np.roll(normal, 1, axis=1)


def without_offset(quads: np.ndarray, offset_px: float) -> np.ndarray:
    """Marker quads ``(n, 4, 2)`` with an edge offset of ``offset_px`` taken out: every edge
    moved inward by it (each corner along its :func:`corner_normal_sums`)."""
    q = np.asarray(quads, dtype=float)
    return q - offset_px * corner_normal_sums(q) if offset_px else q


def significant(offsets: dict[str, EdgeOffset]) -> dict[str, float]:
    """The cameras whose reading supports the model (at least :data:`APPLY_SIGMAS` standard
    errors and :data:`APPLY_MIN_PX`), each with the offset to take out."""
    return {c: e.offset_px for c, e in offsets.items()
            if abs(e.offset_px) >= max(APPLY_MIN_PX, APPLY_SIGMAS * e.sigma_px)}


def outward_bisectors(quads: np.ndarray) -> np.ndarray:
    """Unit vectors ``(n, 4, 2)`` along each corner's outward bisector
    (:func:`corner_normal_sums` normalised)."""
    s = corner_normal_sums(quads)
    return s / np.maximum(np.linalg.norm(s, axis=-1, keepdims=True), 1e-12)


def marker_outward_px(measured: np.ndarray, residuals: np.ndarray) -> np.ndarray:
    """Per marker ``(n,)``: the mean over its 4 corners of how far the measured corner lies
    outside the predicted one along the corner's outward bisector (px). ``measured`` (n, 4, 2)
    the detected corners, ``residuals`` (n, 4, 2) ``predicted - measured``."""
    m = np.asarray(measured, dtype=float)
    return np.mean(np.sum(-np.asarray(residuals, dtype=float) * outward_bisectors(m), axis=-1),
                   axis=1)


def marker_gain(measured: np.ndarray, object_points: np.ndarray) -> np.ndarray:
    """Per marker ``(n,)``: how far (px) its corners move outward along their bisectors per
    metre of a spread on the board (each edge out by it): ``sqrt(2)`` times its mean corner
    distance from its centre in the image over that on the board (its local scale)."""
    q = np.asarray(measured, dtype=float)
    P = np.asarray(object_points, dtype=float)
    h = np.linalg.norm(q - q.mean(axis=1, keepdims=True), axis=-1).mean(axis=1)
    rho = np.linalg.norm(P - P.mean(axis=1, keepdims=True), axis=-1).mean(axis=1)
    return np.sqrt(2.0) * h / np.maximum(rho, 1e-12)


def edge_offsets(cameras: list[str], outward_px: np.ndarray,
                 applied: dict[str, float] | None = None,
                 gain: np.ndarray | None = None) -> dict[str, EdgeOffset]:
    """Per camera (``cameras[i]`` is marker ``i``'s): its edge offset, the robust mean of its
    markers' outward residuals (markers beyond :data:`MAD_CUT` robust sigmas of the median left
    out: an outlier marker is not an offset) over ``sqrt(2)``, with its standard error, plus
    what ``applied`` (camera -> px) had already taken out of its corners. With each marker's
    ``gain`` (:func:`marker_gain`) and at least :data:`MIN_SIZE_MARKERS` markers, also what
    grows with the markers' size: the slope of the residuals on the gain (``size_mm``), read,
    not modelled. Cameras with fewer than 2 markers get none."""
    applied = applied or {}
    out: dict[str, EdgeOffset] = {}
    names = np.asarray(cameras)
    values = np.asarray(outward_px, dtype=float)
    gains = np.full(values.shape, np.nan) if gain is None else np.asarray(gain, dtype=float)
    for cam in dict.fromkeys(cameras):
        r, g = values[names == cam], gains[names == cam]
        keep = np.isfinite(r)
        r, g = r[keep], g[keep]
        if r.size < 2:
            continue
        med = np.median(r)
        spread = 1.4826 * np.median(np.abs(r - med))
        if spread > 0:
            keep = np.abs(r - med) <= MAD_CUT * spread
            r, g = r[keep], g[keep]
        if r.size < 2:
            continue
        se = float(np.std(r, ddof=1) / np.sqrt(r.size))
        done = float(applied.get(str(cam), 0.0))
        out[str(cam)] = EdgeOffset(done + float(np.mean(r)) / np.sqrt(2.0), se / np.sqrt(2.0),
                                   int(r.size), done, *_size_slope(r, g))
    return out


def _size_slope(r: np.ndarray, g: np.ndarray) -> tuple[float, float, float]:
    """The slope of outward residuals ``r`` on gains ``g`` (mm of spread), its standard error
    and the difference it makes per edge between the 90th and the 10th percentile of the
    gains (px); zeros with too few markers or no spread in size."""
    ok = np.isfinite(g)
    r, g = r[ok], g[ok]
    if r.size < MIN_SIZE_MARKERS or np.ptp(g) <= 0:
        return 0.0, 0.0, 0.0
    A = np.column_stack([np.ones_like(g), g])
    x = np.linalg.lstsq(A, r, rcond=None)[0]
    s2 = float(np.sum((r - A @ x) ** 2)) / (r.size - 2)
    se = float(np.sqrt(np.linalg.inv(A.T @ A)[1, 1] * s2))
    lo, hi = np.percentile(g, [10, 90])
    return 1000 * float(x[1]), 1000 * se, float(x[1]) * (hi - lo) / np.sqrt(2.0)


def measurements_without_offset(measurements: Sequence[Any],
                                offset: dict[str, float]) -> list[Any]:
    """The bundle's marker measurements (``camera``, ``corners_px`` (4, 2), ``edge_fitted``)
    with each camera's ``offset`` taken out of its edge-fitted corners
    (:func:`without_offset`)."""
    return [replace(m, corners_px=without_offset(m.corners_px[None], offset[m.camera])[0])
            if m.edge_fitted and offset.get(m.camera) else m for m in measurements]


def read_offsets(measurements: Sequence[Any], corner_res: np.ndarray,
                 applied: dict[str, float]) -> dict[str, EdgeOffset]:
    """Per camera the edge offset (and what grows with the markers' size: ``object_points``
    give each marker's :func:`marker_gain`) its edge-fitted markers' residuals ``corner_res``
    (n, 4, 2, ``predicted - measured``, one per measurement) read on top of what was
    ``applied`` (:func:`edge_offsets`)."""
    fitted = [i for i, m in enumerate(measurements) if m.edge_fitted]
    if not fitted:
        return {}
    measured = np.array([measurements[i].corners_px for i in fitted], dtype=float)
    board = np.array([measurements[i].object_points for i in fitted], dtype=float)
    return edge_offsets([measurements[i].camera for i in fitted],
                        marker_outward_px(measured, np.asarray(corner_res)[fitted]), applied,
                        marker_gain(measured, board))
