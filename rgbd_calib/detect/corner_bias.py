"""Marker-corner bias against a ChArUco board's saddle corners (pure maths, numpy only).

On a real print there is no ground truth, but a ChArUco board carries its own reference: the
chessboard saddle corners, which neither ink spread nor an edge-position error of the
detector moves (a saddle is where two edges cross; spreading ink shifts both edges of a
black square but not the crossing). A homography fitted to the saddle corners near a marker
maps the marker's printed (design) corners into the image; a detected marker corner minus
that prediction is the corner's error, split into

- ``normal``: the mean outward offset of the two marker edges through the corner, ``(e . n_a
  + e . n_b) / 2`` with ``n_a``, ``n_b`` their outward unit normals; positive = the marker
  looks larger (ink spread, or a detector that sits outside the edge);
- ``tangent``: ``(e . n_b - e . n_a) / 2`` (``a`` the edge arriving at the corner, ``b`` the
  one leaving it, in ArUco corner order): positive = the corner moved along the corner
  order (a rotation of the marker).

Lens distortion bends the saddle grid; the caller may fit the homography in undistorted
pixels (``undistort``/``distort`` callables, e.g. :class:`rgbd_calib.core.camera.CameraIntrinsics`'
``undistort_pixels``/``distort_pixels``) and compare in image pixels.
:func:`saddle_self_consistency` gives the reference's own floor: each saddle corner predicted
from its neighbours by the same local fit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

PixelMap = Callable[[np.ndarray], np.ndarray]


def fit_homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``(3,3)`` homography mapping ``src`` ``(N,2)`` onto ``dst`` ``(N,2)`` (N >= 4), least
    squares by the normalised DLT (Hartley & Zisserman, *Multiple View Geometry*, 2nd ed.,
    alg. 4.2: each point set translated to its centroid and scaled to mean distance sqrt 2)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)

    def normaliser(p: np.ndarray) -> np.ndarray:
        c = p.mean(axis=0)
        s = np.sqrt(2.0) / max(np.linalg.norm(p - c, axis=1).mean(), 1e-12)
        return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])

    Ts, Td = normaliser(src), normaliser(dst)
    a = apply_homography(Ts, src)
    b = apply_homography(Td, dst)
    n = a.shape[0]
    A = np.zeros((2 * n, 9))
    A[0::2, 0:2], A[0::2, 2] = a, 1.0
    A[0::2, 6:8] = -b[:, :1] * a
    A[0::2, 8] = -b[:, 0]
    A[1::2, 3:5], A[1::2, 5] = a, 1.0
    A[1::2, 6:8] = -b[:, 1:] * a
    A[1::2, 8] = -b[:, 1]
    Hn = np.linalg.svd(A)[2][-1].reshape(3, 3)  # the right singular vector of least sigma
    H = np.linalg.inv(Td) @ Hn @ Ts
    return H / H[2, 2]


def apply_homography(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``pts`` ``(...,2)`` mapped by ``H`` ``(3,3)``."""
    pts = np.asarray(pts, float)
    q = pts @ H[:2, :2].T + H[:2, 2]
    w = pts @ H[2, :2] + H[2, 2]
    return q / w[..., None]


def _identity(p: np.ndarray) -> np.ndarray:
    return np.asarray(p, float)


def _near(board_xy: np.ndarray, centre_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """Mask of the points within ``radius_m`` (Chebyshev, board metres) of ``centre_xy``."""
    return np.abs(board_xy - centre_xy).max(axis=1) <= radius_m + 1e-9


def predict_local(
    saddle_xy: np.ndarray,
    saddle_px: np.ndarray,
    targets_xy: np.ndarray,
    radius_m: float,
    min_points: int = 6,
    undistort: PixelMap = _identity,
    distort: PixelMap = _identity,
) -> np.ndarray | None:
    """Image pixels ``(...,2)`` of board points ``targets_xy`` ``(...,2)`` (m) by the
    homography fitted to the saddle corners (``saddle_xy`` ``(K,2)`` board m, ``saddle_px``
    ``(K,2)`` image px) within ``radius_m`` of the targets' centroid, in the pixels
    ``undistort`` gives (mapped back by ``distort``); None with fewer than ``min_points``."""
    centre = np.asarray(targets_xy, float).reshape(-1, 2).mean(axis=0)
    near = _near(saddle_xy, centre, radius_m)
    if near.sum() < max(min_points, 4):
        return None
    H = fit_homography(saddle_xy[near], undistort(saddle_px[near]))
    return distort(apply_homography(H, targets_xy))


def saddle_self_consistency(
    saddle_xy: np.ndarray,
    saddle_px: np.ndarray,
    radius_m: float,
    min_points: int = 6,
    undistort: PixelMap = _identity,
    distort: PixelMap = _identity,
) -> np.ndarray:
    """Leave-one-out residuals ``(J,2)`` (px, measured - predicted) of the saddle corners:
    each predicted by :func:`predict_local` from the *other* corners within ``radius_m`` of
    it (the reference's floor: its own noise, the print's flatness and the homography's
    misfit to the lens); corners with too few neighbours are left out."""
    out = []
    for j in range(len(saddle_xy)):
        others = np.arange(len(saddle_xy)) != j
        p = predict_local(saddle_xy[others], saddle_px[others], saddle_xy[j:j + 1], radius_m,
                          min_points, undistort, distort)
        if p is not None:
            out.append(saddle_px[j] - p[0])
    return np.array(out).reshape(-1, 2)


def corner_components(measured_px: np.ndarray, predicted_px: np.ndarray):
    """The error of marker corners ``(N,4,2)`` against their predictions ``(N,4,2)`` (ArUco
    corner order), ``(normal, tangent)`` ``(N,4)`` px each, along the outward normals of the
    predicted marker's edges (see the module docstring)."""
    e = np.asarray(measured_px, float) - predicted_px
    edge = np.roll(predicted_px, -1, axis=1) - predicted_px  # edge k: corner k -> k+1
    edge /= np.linalg.norm(edge, axis=-1, keepdims=True)
    n = np.stack([edge[..., 1], -edge[..., 0]], axis=-1)
    centre = predicted_px.mean(axis=1, keepdims=True)
    mid = predicted_px + 0.5 * (np.roll(predicted_px, -1, axis=1) - predicted_px)
    n *= np.where(np.einsum("nkj,nkj->nk", mid - centre, n) < 0, -1.0, 1.0)[..., None]
    n_leave, n_arrive = n, np.roll(n, 1, axis=1)  # corner k: edge k leaves, edge k-1 arrives
    along_leave = np.einsum("nkj,nkj->nk", e, n_leave)
    along_arrive = np.einsum("nkj,nkj->nk", e, n_arrive)
    return 0.5 * (along_arrive + along_leave), 0.5 * (along_leave - along_arrive)


@dataclass(frozen=True)
class BiasSummary:
    """Bias (mean) and scatter (standard deviation) of corner errors, px."""

    corners: int
    normal_bias_px: float
    normal_scatter_px: float
    tangent_bias_px: float
    tangent_scatter_px: float
    rms_px: float  # of the 2-D error

    @classmethod
    def of(cls, normal: np.ndarray, tangent: np.ndarray, error_2d: np.ndarray) -> BiasSummary:
        normal, tangent = np.ravel(normal), np.ravel(tangent)
        if normal.size == 0:
            return cls(0, *(float("nan"),) * 5)
        e = np.asarray(error_2d, float).reshape(-1, 2)
        return cls(int(normal.size), float(normal.mean()), float(normal.std()),
                   float(tangent.mean()), float(tangent.std()),
                   float(np.sqrt((e**2).sum(axis=1).mean())))
