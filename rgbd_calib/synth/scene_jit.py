"""The renderer's ray-rectangle intersection compiled with numba (:func:`.scene.cast`).

The numpy version visits, per rectangle, the rays of its image bounding box with whole-array
operations: a full-image static scene at 848x480 is ~14 rectangles x 0.4 M rays, a dozen
temporaries each, ~0.17 s a cast and five casts per camera. Here the same arithmetic runs as
one loop per rectangle over its rays, in the same order of operations (no fused multiply-add,
no reassociation), so the hits equal the numpy version's bit for bit (tests/test_synth.py).
Compiled on first use and cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always", error_model="numpy")
def _hit(i, rays, best, index, best_a, best_b, k, o, u, v, n, on, size_u, size_v):
    """Ray ``i`` against one rectangle: keep the hit if it is nearer than ``best[i]``."""
    t = on / (rays[i, 0] * n[0] + rays[i, 1] * n[1] + rays[i, 2] * n[2])
    if not (t > 1e-6 and t < best[i]):
        return
    p0 = rays[i, 0] * t - o[0]
    p1 = rays[i, 1] * t - o[1]
    p2 = rays[i, 2] * t - o[2]
    a = p0 * u[0] + p1 * u[1] + p2 * u[2]
    b = p0 * v[0] + p1 * v[1] + p2 * v[2]
    if a >= 0.0 and a <= size_u and b >= 0.0 and b <= size_v:
        best[i] = t
        index[i] = k
        best_a[i] = a
        best_b[i] = b


@njit(cache=True, error_model="numpy")
def cast_grid_rect(rays, best, index, best_a, best_b, k, o, u, v, n, on, size_u, size_v,
                   r0, r1, c0, c1, cols):
    """One rectangle against the rays of rows ``r0:r1``, columns ``c0:c1`` of a row-major
    pixel grid of ``cols`` columns (its image bounding box)."""
    for row in range(r0, r1):
        for col in range(c0, c1):
            _hit(row * cols + col, rays, best, index, best_a, best_b, k, o, u, v, n, on,
                 size_u, size_v)


@njit(cache=True, error_model="numpy")
def cast_rect(rays, cand, best, index, best_a, best_b, k, o, u, v, n, on, size_u, size_v):
    """One rectangle against the rays ``cand`` (indices)."""
    for j in range(cand.shape[0]):
        _hit(cand[j], rays, best, index, best_a, best_b, k, o, u, v, n, on, size_u, size_v)


def warm_up() -> None:
    """Compile (or load from the disk cache) both kernels."""
    rays = np.zeros((1, 3))
    rays[0, 2] = 1.0
    z = np.zeros(3)
    cast_grid_rect(rays, np.full(1, np.inf), np.full(1, -1, np.int32), np.zeros(1), np.zeros(1),
                   0, z, z, z, z, 0.0, 1.0, 1.0, 0, 1, 0, 1, 1)
    cast_rect(rays, np.zeros(1, np.int64), np.full(1, np.inf), np.full(1, -1, np.int32),
              np.zeros(1), np.zeros(1), 0, z, z, z, z, 0.0, 1.0, 1.0)
