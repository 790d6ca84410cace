"""A detector's edge offset read from the bundle's corner residuals (pure maths, numpy only).

A detector that sees every marker edge ``d`` px outside where it is (the edge fit on real
prints: +0.05..+0.16 px by camera, its imaging's blur and sharpening; docs/accuracy.md,
"Corners on real photos") moves each corner ``d`` along the outward normals of its two edges,
``d sqrt(2)`` along the corner's outward bisector for a square marker. The bundle predicts the
printed corners, and the poses absorb little of such a pattern (a +0.1 px offset leaves
+0.136 px of the 0.141 along the bisectors in the residuals of a race render), so each
camera's mean outward residual over its markers, over ``sqrt(2)``, reads its offset. Nothing
models the offset yet: this measures it, so the report can name it (``edge_offset``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAD_CUT = 5.0  # markers farther than this many robust sigmas from the median are left out


@dataclass(frozen=True)
class EdgeOffset:
    """One camera's edge offset (px per edge; positive: its markers look larger than the
    board's geometry) with its standard error over ``markers`` markers."""

    offset_px: float
    sigma_px: float
    markers: int

    def to_dict(self) -> dict[str, float | int]:
        return {"offset_px": self.offset_px, "sigma_px": self.sigma_px, "markers": self.markers}


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


def edge_offsets(cameras: list[str], outward_px: np.ndarray) -> dict[str, EdgeOffset]:
    """Per camera (``cameras[i]`` is marker ``i``'s): its edge offset, the robust mean of its
    markers' outward residuals (markers beyond :data:`MAD_CUT` robust sigmas of the median left
    out: an outlier marker is not an offset) over ``sqrt(2)``, with its standard error.
    Cameras with fewer than 2 markers get none."""
    out: dict[str, EdgeOffset] = {}
    names = np.asarray(cameras)
    values = np.asarray(outward_px, dtype=float)
    for cam in dict.fromkeys(cameras):
        r = values[names == cam]
        r = r[np.isfinite(r)]
        if r.size < 2:
            continue
        med = np.median(r)
        spread = 1.4826 * np.median(np.abs(r - med))
        if spread > 0:
            r = r[np.abs(r - med) <= MAD_CUT * spread]
        if r.size < 2:
            continue
        se = float(np.std(r, ddof=1) / np.sqrt(r.size))
        out[str(cam)] = EdgeOffset(float(np.mean(r)) / np.sqrt(2.0), se / np.sqrt(2.0), int(r.size))
    return out
