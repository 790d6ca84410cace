"""A static textured 3D scene made of rectangles, ray-cast exactly (pure numpy).

Used by the synthetic renderer (:mod:`.images`). Rays are given in a camera frame with
z = 1 (a pinhole's ``d = [(u - cx) / fx, (v - cy) / fy, 1]``, or a distorted lens's rays from
:meth:`CameraIntrinsics.rays`), so the ray parameter ``t`` of a hit *is* the camera z-depth.
Textures are procedural value noise, so neighbouring and facing cameras see the same surface
detail (what colored ICP needs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.geometry import transform_points


@dataclass(frozen=True)
class Rect:
    """A textured rectangle ``origin + a * u_axis + b * v_axis``, ``0 <= a <= size_u``,
    ``0 <= b <= size_v`` (metres, world frame). ``albedo`` is BGR in [0, 1]."""

    origin: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray
    size_u: float
    size_v: float
    albedo: tuple[float, float, float]
    texture_seed: int
    texture_cell_m: float = 0.05

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.u_axis, self.v_axis)
        return n / np.linalg.norm(n)


def rect(origin, u_vec, v_vec, albedo, seed, cell=0.05) -> Rect:
    """Rectangle from a corner and two edge vectors (metres)."""
    u_vec = np.asarray(u_vec, float)
    v_vec = np.asarray(v_vec, float)
    lu, lv = np.linalg.norm(u_vec), np.linalg.norm(v_vec)
    return Rect(
        np.asarray(origin, float),
        u_vec / lu,
        v_vec / lv,
        float(lu),
        float(lv),
        tuple(albedo),
        int(seed),
        float(cell),
    )


def box(lo, hi, albedo, seed, cell=0.05) -> list[Rect]:
    """The six faces of an axis-aligned box, normals pointing outwards."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    return [
        rect((x0, y0, z0), (0, dy, 0), (dx, 0, 0), albedo, seed, cell),  # bottom (-z)
        rect((x0, y0, z1), (dx, 0, 0), (0, dy, 0), albedo, seed + 1, cell),  # top (+z)
        rect((x0, y0, z0), (dx, 0, 0), (0, 0, dz), albedo, seed + 2, cell),  # -y
        rect((x0, y1, z0), (0, 0, dz), (dx, 0, 0), albedo, seed + 3, cell),  # +y
        rect((x0, y0, z0), (0, 0, dz), (0, dy, 0), albedo, seed + 4, cell),  # -x
        rect((x1, y0, z0), (0, dy, 0), (0, 0, dz), albedo, seed + 5, cell),  # +x
    ]


def _hash01(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) per integer lattice point."""
    h = (ix.astype(np.int64) * 73856093) ^ (iy.astype(np.int64) * 19349663) ^ (seed * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFF).astype(np.float64) / 65536.0


def value_noise(a: np.ndarray, b: np.ndarray, cell: float, seed: int) -> np.ndarray:
    """Bilinear value noise on a lattice of ``cell`` metres, in [0, 1)."""
    fa, fb = a / cell, b / cell
    ia, ib = np.floor(fa), np.floor(fb)
    ta, tb = fa - ia, fb - ib
    ta, tb = ta * ta * (3 - 2 * ta), tb * tb * (3 - 2 * tb)  # smoothstep
    v00 = _hash01(ia, ib, seed)
    v10 = _hash01(ia + 1, ib, seed)
    v01 = _hash01(ia, ib + 1, seed)
    v11 = _hash01(ia + 1, ib + 1, seed)
    return (v00 * (1 - ta) + v10 * ta) * (1 - tb) + (v01 * (1 - ta) + v11 * ta) * tb


def surface_texture(r: Rect, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Three octaves of value noise (coarse blotches, mid detail, fine grain) -> (N,) in [0,1]."""
    c = r.texture_cell_m
    n = (
        0.5 * value_noise(a, b, 4 * c, r.texture_seed)
        + 0.35 * value_noise(a, b, c, r.texture_seed + 7)
        + 0.15 * value_noise(a, b, c / 4, r.texture_seed + 13)
    )
    return n


@dataclass
class Hits:
    """Nearest hit per ray: ``depth`` (camera z, inf for none), ``index`` (rect, -1 none),
    surface coordinates ``a``, ``b`` (metres)."""

    depth: np.ndarray
    index: np.ndarray
    a: np.ndarray
    b: np.ndarray


def _dot3(vectors: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Row-wise dot product with a 3-vector, without BLAS (no thread oversubscription when
    rendering in several processes)."""
    return vectors[:, 0] * w[0] + vectors[:, 1] * w[1] + vectors[:, 2] * w[2]


def cast(
    rects: list[Rect],
    T_cam_world: np.ndarray,
    rays: np.ndarray,
    two_sided: bool = True,
    grid: tuple[int, int] | None = None,
    compiled: bool = True,
) -> Hits:
    """Nearest intersection of camera-frame rays ``(N,3)`` (z = 1) with the rectangles.

    ``grid=(rows, cols)`` says the rays are a row-major pixel grid (x varies along columns
    only, y along rows only): each rectangle then only visits the rays of its image bounding
    box, found by bisection instead of a test over every ray. The per-ray arithmetic runs in
    :mod:`rgbd_calib.synth.scene_jit` (numba), bit-identical to the numpy reference
    (``compiled=False``)."""
    if compiled:
        from .scene_jit import cast_grid_rect, cast_rect
    rays = np.ascontiguousarray(rays, dtype=float)
    n_rays = rays.shape[0]
    best = np.full(n_rays, np.inf)
    index = np.full(n_rays, -1, dtype=np.int32)
    best_a = np.zeros(n_rays)
    best_b = np.zeros(n_rays)
    R = T_cam_world[:3, :3]
    all_rays = np.arange(n_rays)
    if grid is not None:
        rows, cols = grid
        xs = rays[:cols, 0]
        ys = rays[::cols, 1]
    for k, r in enumerate(rects):
        o = transform_points(T_cam_world, r.origin[None])[0]
        u, v = R @ r.u_axis, R @ r.v_axis
        n = np.cross(u, v)
        on = o @ n
        if not two_sided and on >= 0:  # camera behind the face
            continue
        corners = o + np.array(
            [[0, 0], [r.size_u, 0], [0, r.size_v], [r.size_u, r.size_v]]
        ) @ np.stack([u, v])
        if np.all(corners[:, 2] <= 0):
            continue
        cand = all_rays
        if np.all(corners[:, 2] > 1e-6):  # cull rays outside the rectangle's image bbox
            xy = corners[:, :2] / corners[:, 2:]
            lo, hi = xy.min(axis=0) - 1e-9, xy.max(axis=0) + 1e-9
            if grid is not None:
                c0, c1 = np.searchsorted(xs, lo[0]), np.searchsorted(xs, hi[0], "right")
                r0, r1 = np.searchsorted(ys, lo[1]), np.searchsorted(ys, hi[1], "right")
                if c0 >= c1 or r0 >= r1:
                    continue
                if compiled:
                    cast_grid_rect(rays, best, index, best_a, best_b, k, o, u, v, n, on,
                                   float(r.size_u), float(r.size_v), r0, r1, c0, c1, cols)
                    continue
                cand = (np.arange(r0, r1)[:, None] * cols + np.arange(c0, c1)[None]).ravel()
            else:
                cand = np.nonzero(
                    (rays[:, 0] >= lo[0])
                    & (rays[:, 0] <= hi[0])
                    & (rays[:, 1] >= lo[1])
                    & (rays[:, 1] <= hi[1])
                )[0]
            if cand.size == 0:
                continue
        if compiled:
            cast_rect(rays, cand, best, index, best_a, best_b, k, o, u, v, n, on,
                      float(r.size_u), float(r.size_v))
            continue
        rc = rays[cand]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = on / _dot3(rc, n)
        ok = (t > 1e-6) & (t < best[cand])
        if not np.any(ok):
            continue
        idx = cand[ok]
        t_idx = t[ok]
        p = rc[ok] * t_idx[:, None] - o
        a = _dot3(p, u)
        b = _dot3(p, v)
        inside = (a >= 0) & (a <= r.size_u) & (b >= 0) & (b <= r.size_v)
        idx = idx[inside]
        best[idx] = t_idx[inside]
        index[idx] = k
        best_a[idx] = a[inside]
        best_b[idx] = b[inside]
    return Hits(best, index, best_a, best_b)


def shade_scene(
    rects: list[Rect],
    hits: Hits,
    light_dir_cam: np.ndarray,
    T_cam_world: np.ndarray,
    ambient: float = 0.55,
) -> np.ndarray:
    """BGR colour in [0,1] of scene hits: albedo x texture x (ambient + diffuse)."""
    out = np.zeros((hits.depth.size, 3))
    R = T_cam_world[:3, :3]
    for k, r in enumerate(rects):
        sel = hits.index == k
        if not np.any(sel):
            continue
        tex = surface_texture(r, hits.a[sel], hits.b[sel])
        lam = abs(float((R @ r.normal) @ light_dir_cam))
        shade = (ambient + (1 - ambient) * lam) * (0.35 + 0.65 * tex)
        out[sel] = shade[:, None] * np.asarray(r.albedo)[None]
    return out


def pixel_rays(K: np.ndarray, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """Camera-frame rays with z = 1 through pixel coordinates (OpenCV: pixel centres at
    integers)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.column_stack([(us - cx) / fx, (vs - cy) / fy, np.ones_like(us, dtype=float)])
