"""How far measured points lie from the true surfaces of a synthetic scene (pure numpy).

For a cloud seen by one camera (world frame, metres) and the scene's rectangles
(:class:`~rgbd_calib.synth.scene.Rect`), :func:`surface_distances` gives each point's nearest
rectangle, by the Euclidean distance to the *bounded* rectangle (so a point near a small box is
not matched to the far wall whose plane runs past it), and its signed distance along that
rectangle's normal, positive when the point lies beyond the surface as seen from the camera
(the depth measured too long), negative in front of it. Points farther than ``max_distance_m``
from every rectangle (the board or a moving thing left in, a flying pixel) are unmatched.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene import Rect

MAX_DISTANCE_M = 0.05  # a point farther from every surface is not a measurement of one
CHUNK_POINTS = 16384  # points per block: (chunk, rects) float64 arrays of a few MB


@dataclass(frozen=True)
class SurfaceDistances:
    """Per point (N,): ``signed_m`` the signed distance along the matched rectangle's normal
    (m; positive beyond the surface as the camera sees it, NaN when unmatched), ``gap_m`` the
    Euclidean distance to that bounded rectangle (m; inf when unmatched) and ``rect_index``
    its index in the scene's list (-1 when unmatched)."""

    signed_m: np.ndarray
    gap_m: np.ndarray
    rect_index: np.ndarray

    @property
    def matched(self) -> np.ndarray:
        return self.rect_index >= 0


def surface_distances(
    rects: list[Rect],
    points_world: np.ndarray,
    eye_world: np.ndarray,
    max_distance_m: float = MAX_DISTANCE_M,
    chunk: int = CHUNK_POINTS,
) -> SurfaceDistances:
    """Each of ``points_world`` ``(N,3)`` (world frame, metres) against its nearest rectangle
    of ``rects``, seen from the camera centre ``eye_world`` (3,) (world frame, metres); see
    :class:`SurfaceDistances`. Blocks of ``chunk`` points bound the memory to
    ``chunk x len(rects)`` per array."""
    points = np.asarray(points_world, dtype=float).reshape(-1, 3)
    eye = np.asarray(eye_world, dtype=float).reshape(3)
    n = points.shape[0]
    signed = np.full(n, np.nan)
    gap = np.full(n, np.inf)
    index = np.full(n, -1, dtype=np.int64)
    if n == 0 or not rects:
        return SurfaceDistances(signed, gap, index)
    origin = np.array([r.origin for r in rects], dtype=float)  # (R,3)
    u = np.array([r.u_axis for r in rects], dtype=float)
    v = np.array([r.v_axis for r in rects], dtype=float)
    normal = np.array([r.normal for r in rects], dtype=float)
    size_u = np.array([r.size_u for r in rects], dtype=float)
    size_v = np.array([r.size_v for r in rects], dtype=float)
    # the camera's side of each rectangle's plane: beyond the surface is the other side
    towards_camera = np.sign(np.einsum("rk,rk->r", eye[None] - origin, normal))
    o_u = np.einsum("rk,rk->r", origin, u)
    o_v = np.einsum("rk,rk->r", origin, v)
    o_n = np.einsum("rk,rk->r", origin, normal)
    step = max(int(chunk), 1)
    for start in range(0, n, step):
        p = points[start:start + step]
        # in-plane coordinates and height of every point over every rectangle's plane
        a = p @ u.T - o_u
        b = p @ v.T - o_v
        h = p @ normal.T - o_n
        out_a = a - np.clip(a, 0.0, size_u)
        out_b = b - np.clip(b, 0.0, size_v)
        d2 = out_a * out_a + out_b * out_b + h * h  # squared distance to the bounded rectangle
        k = np.argmin(d2, axis=1)
        rows = np.arange(p.shape[0])
        best = np.sqrt(d2[rows, k])
        ok = best <= max_distance_m
        sl = slice(start, start + p.shape[0])
        gap[sl] = np.where(ok, best, np.inf)
        index[sl] = np.where(ok, k, -1)
        signed[sl] = np.where(ok, -towards_camera[k] * h[rows, k], np.nan)
    return SurfaceDistances(signed, gap, index)
