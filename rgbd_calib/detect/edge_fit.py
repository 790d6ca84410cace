"""The edge-fit corner model: marker corners as intersections of lines fitted to the
markers' outer edges (``DetectionConfig.refinement: edges``, :func:`refine_corners_edges`).

It fits a straight line to each of a marker's four *outer* edges (black border against the
white quiet zone) and intersects adjacent lines. Each line comes from a model of the blurred
image across the edge, fitted to the raw pixels of a band about one module wide along the
middle of the edge (see :func:`_fit_edge_lines`): the step from quiet zone to border, the
marker's own data cells behind the one-module border (known from its id), and a Gaussian blur
whose width is fitted. Corner regions, where blur rounds the square, are not used.

:func:`_fit_edge_models` is the numpy reference of the fit; :mod:`rgbd_calib.detect.edge_fit_jit`
is its numba twin, which the detector runs (tests/test_detection.py pins them equal).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from scipy.special import ndtr

from ..core.camera import CameraIntrinsics
from ..core.config import DetectionConfig

_UNIT_SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])  # TL TR BR BL, y down


def _homographies(corners: np.ndarray) -> np.ndarray:
    """``(M,3,3)`` homographies mapping the unit square (marker coordinates, TL at the origin,
    y down) onto each marker's image corners ``(M,4,2)``."""
    m = corners.shape[0]
    a = np.zeros((m, 8, 8))
    x, y = _UNIT_SQUARE[:, 0], _UNIT_SQUARE[:, 1]
    u, v = corners[..., 0], corners[..., 1]
    a[:, 0::2, 0], a[:, 0::2, 1], a[:, 0::2, 2] = x, y, 1.0
    a[:, 0::2, 6], a[:, 0::2, 7] = -u * x, -u * y
    a[:, 1::2, 3], a[:, 1::2, 4], a[:, 1::2, 5] = x, y, 1.0
    a[:, 1::2, 6], a[:, 1::2, 7] = -v * x, -v * y
    b = np.stack([u, v], axis=-1).reshape(m, 8)
    h = np.linalg.solve(a + 1e-12 * np.eye(8), b[..., None])[..., 0]
    return np.concatenate([h, np.ones((m, 1))], axis=1).reshape(m, 3, 3)


def _map(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply ``(M,3,3)`` homographies to marker coordinates ``(M,...,2)``."""
    shape = pts.shape
    p = pts.reshape(shape[0], -1, 2)
    q = np.einsum("mij,mnj->mni", H[:, :, :2], p) + H[:, None, :, 2]
    return (q[..., :2] / q[..., 2:]).reshape(shape)


def _edge_layout(cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each edge k (corner k -> k+1) in marker coordinates: start point, direction, inward
    normal, and the (row, col) of the data cells behind its border, in edge order."""
    start = _UNIT_SQUARE
    along = np.roll(_UNIT_SQUARE, -1, axis=0) - _UNIT_SQUARE
    inward = np.stack([-along[:, 1], along[:, 0]], axis=-1)  # y-down: rotate along by +90 deg
    f = (np.arange(1, cells - 1) + 0.5) / cells  # centres of the data cells along the edge
    centre = start[:, None] + f[None, :, None] * along[:, None] + 1.5 / cells * inward[:, None]
    rc = np.floor(centre * cells).astype(int)  # (4, bits, 2) as (x, y) cell indices
    return start, along, inward, np.stack([rc[..., 1], rc[..., 0]], axis=-1)


def _fit_edge_lines(
    gray: np.ndarray,
    corners: np.ndarray,
    white: np.ndarray,
    config: DetectionConfig,
    intrinsics: CameraIntrinsics | None,
    blur_prior: tuple[float, float],
    compiled: bool = True,
):
    """Fit a line to each outer edge of each marker with a model of its blurred image.

    Edge ``k`` runs from corner ``k`` to corner ``k+1``. The pixels whose centres lie within a
    band about one module wide around the current edge (and away from the corners) are fitted
    by Levenberg-Marquardt with the image of the marker's border as the marker defines it: the
    outer step (quiet zone to black border) plus, behind the one-module border, the white data
    cells of this marker (``white`` ``(M,cells,cells)``, from its id), all blurred by a
    Gaussian of width ``w``. ``d`` is the signed distance of a pixel centre to the edge line
    (outwards positive), ``s`` its coordinate along the edge, ``m(s)`` the module width there:

        I = D + C * [Phi(d/w) + Phi(-(d + m)/w) * sum_j white_j (Phi((s-a_j)/w) - Phi((s-b_j)/w))]

    A pixel's value is the area average of the blurred image, a function of ``d`` alone for a
    straight step, so raw pixels need no interpolation (bilinear interpolation makes an edge
    profile depend on its sub-pixel phase; measured: docs/accuracy.md). The data cells
    matter: once blurred, a one-module border backed by a white cell never reaches the ink
    level, which pulls a plain step fit outwards (measured: docs/accuracy.md).

    Returns unit normals ``(M,4,2)`` (out of the marker), offsets ``rho`` ``(M,4)`` with
    ``normal . x = rho`` on the line (undistorted pixels when ``intrinsics`` has distortion),
    a validity mask ``(M,4)`` and the fitted blur width per marker ``(M,)``. ``compiled``:
    the model fitted by :mod:`rgbd_calib.detect.edge_fit_jit` (numba), else by the numpy reference
    :func:`_fit_edge_models` (same corners to ~1e-9 px, ~10x slower).
    """
    # each edge's frame in the image, then the marker's layout seen through the current corners
    frame = _edge_frames(corners)
    layout = _edge_cell_layout(corners, white, frame)
    # the band fitted across each edge and the span sampled along it
    band, tau_lo, tau_hi = _edge_band(config, layout.m_at0, frame.length)
    # the band's pixels as flat per-pixel arrays, ordered by edge
    curved = intrinsics is not None and intrinsics.has_distortion
    samples, n_expected, tau_scale = _edge_samples(
        gray, frame, layout, band, tau_lo, tau_hi, config.edges.edge_max_samples, curved, compiled
    )
    # the edge model fitted per marker
    fit = _fit_edge_models_compiled if compiled else _fit_edge_models
    local, width, weight, contrast, resid = fit(samples, band, blur_prior,
                                                config.edges.edge_iterations)
    # which edges are usable: every test passed
    tests = _edge_tests(samples, local, width, weight, contrast, resid, band, n_expected, config)
    ok = np.logical_and.reduce(list(tests.values()))
    # the fitted edges as straight lines
    nrm, rho = _edge_lines(local, frame, tau_scale, intrinsics if curved else None)
    return nrm, rho, ok, width


@dataclass(frozen=True, eq=False)
class _EdgeFrame:
    """Each marker edge ``k`` (corner ``k`` -> ``k+1``) in image pixels (as detected, i.e.
    distorted): ``length`` ``(M,4)`` px, unit direction ``d`` and unit outward ``normal``
    ``(M,4,2)`` (``(d, normal)`` right-handed), midpoint ``mid`` ``(M,4,2)`` px."""

    length: np.ndarray
    d: np.ndarray
    normal: np.ndarray
    mid: np.ndarray


def _edge_frames(corners: np.ndarray) -> _EdgeFrame:
    """The frame of each edge of markers with image corners ``corners`` ``(M,4,2)`` (px)."""
    vec = np.roll(corners, -1, axis=1) - corners
    length = np.linalg.norm(vec, axis=-1)  # (M,4)
    d = vec / length[..., None]
    normal = np.stack([d[..., 1], -d[..., 0]], axis=-1)
    outward = np.sign(
        np.einsum("mkj,mkj->mk", corners + 0.5 * vec - corners.mean(1)[:, None], normal)
    )
    normal = normal * np.where(outward == 0, 1.0, outward)[..., None]
    d = np.stack([-normal[..., 1], normal[..., 0]], axis=-1)  # (d, normal) right-handed
    mid = corners + 0.5 * vec
    return _EdgeFrame(length, d, normal, mid)


@dataclass(frozen=True, eq=False)
class _CellLayout:
    """The marker's cells seen along each edge through the current corners, in px of the
    edge's frame: ``bound`` ``(M,4,cells-1)`` along-edge positions (from the midpoint) of the
    cell boundaries, the module width across the edge ``m_at0 + m_slope * s`` (``(M,4)``, px
    and px/px), and ``step_at`` ``(M,4,cells-1)`` the change of the data cells' whiteness at
    each boundary (see :func:`_edge_cell_layout`)."""

    bound: np.ndarray
    m_at0: np.ndarray
    m_slope: np.ndarray
    step_at: np.ndarray


def _edge_cell_layout(corners: np.ndarray, white: np.ndarray, frame: _EdgeFrame) -> _CellLayout:
    """Module width across each edge (linear along it) and the data cells' extents along it,
    from the homography of the unit square onto ``corners`` ``(M,4,2)`` (px)."""
    m = corners.shape[0]
    cells = white.shape[-1]
    d, normal, mid = frame.d, frame.normal, frame.mid
    H = _homographies(corners)
    start, along, inward, rc = _edge_layout(cells)
    fr = np.arange(1, cells) / cells  # cell boundaries along the edge (the corner modules too)
    on_inner = start[:, None] + fr[None, :, None] * along[:, None] + inward[:, None] / cells
    inner_px = _map(H, np.broadcast_to(on_inner, (m, *on_inner.shape)))  # (M,4,cells-1,2)
    rel = inner_px - mid[:, :, None, :]
    bound = np.einsum("mkcj,mkj->mkc", rel, d)  # along-edge positions of the cell boundaries
    depth = -np.einsum("mkcj,mkj->mkc", rel, normal)  # module width there
    m_slope = (depth[..., -1] - depth[..., 0]) / np.where(
        np.abs(bound[..., -1] - bound[..., 0]) > 1e-9, bound[..., -1] - bound[..., 0], 1.0
    )
    m_at0 = depth[..., 0] - m_slope * bound[..., 0]  # module width at the edge's midpoint
    # The white data cells behind the border, sum_j white_j (Phi((s-a_j)/w) - Phi((s-b_j)/w))
    # with [a_j, b_j] cell j's extent, telescope over the shared cell boundaries c_i:
    # sum_i step_i Phi((s-c_i)/w), step_i = q_i - q_(i-1) with q_j = +-white_j (the sign of
    # c_(j+1) - c_j: a cell's extent is (min, max) of its two boundaries) and q = 0 outside.
    cell_white = white[:, rc[..., 0], rc[..., 1]].astype(float)  # (M,4,bits)
    q = cell_white * np.where(bound[..., 1:] >= bound[..., :-1], 1.0, -1.0)
    pad = np.zeros((m, 4, 1))
    step_at = np.concatenate([q, pad], axis=-1) - np.concatenate([pad, q], axis=-1)  # (M,4,B)
    return _CellLayout(bound, m_at0, m_slope, step_at)


def _edge_band(config: DetectionConfig, m_at0: np.ndarray, length: np.ndarray):
    """Per edge ``(M,4)``: the band half-width across it (px) and the sampled span along it,
    ``tau_lo .. tau_hi`` (px from the midpoint), kept away from the corners."""
    edges = config.edges
    module = np.clip(m_at0, 0.1, None)
    band = np.clip(edges.edge_band_modules * module, *edges.edge_band_px)
    margin = np.minimum(edges.edge_corner_margin_px / length, 0.4)
    tau_lo = (np.maximum(edges.edge_span[0], margin) - 0.5) * length  # span about the midpoint
    tau_hi = (np.minimum(edges.edge_span[1], 1.0 - margin) - 0.5) * length
    return band, tau_lo, tau_hi


@dataclass(frozen=True, eq=False)
class _BandColumns:
    """How each edge's band is walked, per edge ``(M,4)``: its major image axis (0: x,
    1: y), the first pixel column ``c_lo`` along it, the column ``stride`` and the number of
    columns used, the band's extent along the minor axis ``half_minor`` (px) and the edge's
    ``slope`` (minor px per major px); ``r_max`` pixel rows per column cover every band."""

    axis: np.ndarray
    c_lo: np.ndarray
    stride: np.ndarray
    n_used: np.ndarray
    half_minor: np.ndarray
    slope: np.ndarray
    r_max: int


def _band_columns(
    frame: _EdgeFrame, band: np.ndarray, tau_lo: np.ndarray, tau_hi: np.ndarray, max_samples: int
) -> _BandColumns:
    """The columns of each edge's band (at most ``max_samples`` per edge)."""
    d, mid = frame.d, frame.mid
    axis = (np.abs(d[..., 1]) > np.abs(d[..., 0])).astype(int)  # 0: x-major, 1: y-major
    other = 1 - axis
    d_major = np.take_along_axis(d, axis[..., None], -1)[..., 0]
    d_minor = np.take_along_axis(d, other[..., None], -1)[..., 0]
    ends = np.stack([mid + tau_lo[..., None] * d, mid + tau_hi[..., None] * d], axis=-2)
    major_ends = np.take_along_axis(ends, np.repeat(axis[..., None, None], 2, -2), -1)[..., 0]
    c_lo = np.ceil(major_ends.min(-1))
    n_cols = np.maximum(np.floor(major_ends.max(-1)) - c_lo + 1, 0).astype(int)
    stride = np.maximum(np.ceil(n_cols / max_samples), 1).astype(int)
    n_used = np.ceil(n_cols / stride).astype(int)
    half_minor = band / np.maximum(np.abs(d_major), 1e-6)  # band extent along the minor axis
    r_max = int(np.ceil(2 * half_minor.max())) + 2
    slope = d_minor / np.where(d_major == 0, 1e-6, d_major)
    return _BandColumns(axis, c_lo, stride, n_used, half_minor, slope, r_max)


def _band_pixels(
    image_shape: tuple[int, int],
    frame: _EdgeFrame,
    band: np.ndarray,
    tau_lo: np.ndarray,
    tau_hi: np.ndarray,
    max_samples: int,
):
    """Candidate pixels of each edge's band, column by column along the edge's dominant image
    axis (at most ``max_samples`` columns): integer pixel centres ``x``, ``y`` ``(M,4,S,R)``,
    their distance ``d0`` across the edge (px, outwards positive) and ``tau`` along it (px
    from the midpoint), the mask ``use`` of those in the band and the image, and
    ``n_expected`` ``(M,4)`` the band's pixel count ignoring the image border."""
    d, normal, mid = frame.d, frame.normal, frame.mid
    m = d.shape[0]
    cols = _band_columns(frame, band, tau_lo, tau_hi, max_samples)
    axis, c_lo, stride, n_used = cols.axis, cols.c_lo, cols.stride, cols.n_used
    half_minor, r_max = cols.half_minor, cols.r_max
    s_max = max(int(n_used.max()), 1)
    j = np.arange(s_max)
    col = c_lo[..., None] + j * stride[..., None]  # (M,4,S)
    mid_major = np.take_along_axis(mid, axis[..., None], -1)[..., 0]
    mid_minor = np.take_along_axis(mid, 1 - axis[..., None], -1)[..., 0]
    line_minor = mid_minor[..., None] + (col - mid_major[..., None]) * cols.slope[..., None]
    row = np.floor(line_minor - half_minor[..., None])[..., None] + np.arange(r_max)
    col = np.broadcast_to(col[..., None], row.shape)  # (M,4,S,R)
    x = np.where(axis[..., None, None] == 0, col, row)
    y = np.where(axis[..., None, None] == 0, row, col)
    rel_x = x - mid[..., 0, None, None]
    rel_y = y - mid[..., 1, None, None]
    d0 = rel_x * normal[..., 0, None, None] + rel_y * normal[..., 1, None, None]
    tau = rel_x * d[..., 0, None, None] + rel_y * d[..., 1, None, None]
    h_img, w_img = image_shape
    inside = (x >= 0) & (y >= 0) & (x <= w_img - 1) & (y <= h_img - 1)
    use = (
        (j < n_used[..., None])[..., None]
        & (np.abs(d0) <= band[..., None, None])
        & (tau >= tau_lo[..., None, None])
        & (tau <= tau_hi[..., None, None])
    )
    n_expected = use.reshape(m, 4, -1).sum(-1)
    use &= inside
    return x, y, d0, tau, use, n_expected


@dataclass(frozen=True, eq=False)
class _EdgeSamples:
    """The band pixels of all edges as flat arrays, ordered by edge (``m*4 + k``), hence by
    marker, and the (pixel, cell boundary) pairs where the data cells change colour, ordered by
    pixel. Per pixel: ``d0`` (px across the edge, outwards positive, from the current edge),
    ``tn`` (along-edge position normalised to [-1, 1]) and ``tn2 = tn**2``, grey ``values``,
    the module width ``m_pix`` (px). Per pair: its pixel ``pair_pix``, ``pair_s`` = s - c_i
    (px) and ``pair_step`` = step_i. ``curved``: lens distortion (the edges get a curvature
    term). Per-edge/per-marker values spread to the pixels by ``np.repeat`` with the counts;
    sums per edge or marker are sums of contiguous segments (``edge_sum``, ``per_marker``)."""

    m: int
    curved: bool
    edge_of: np.ndarray
    d0: np.ndarray
    tn: np.ndarray
    tn2: np.ndarray
    values: np.ndarray
    m_pix: np.ndarray
    pair_pix: np.ndarray
    pair_s: np.ndarray
    pair_step: np.ndarray
    edge_count: np.ndarray
    marker_count: np.ndarray
    pair_count: np.ndarray
    edge_sum: Any
    per_marker: Any

    def at_pixels(self, per_marker_value: np.ndarray) -> np.ndarray:
        return np.repeat(per_marker_value, self.marker_count)

    def per_edge(self, v: np.ndarray) -> np.ndarray:
        return self.edge_sum(v).reshape(self.m, 4)


def _edge_samples(
    gray: np.ndarray,
    frame: _EdgeFrame,
    layout: _CellLayout,
    band: np.ndarray,
    tau_lo: np.ndarray,
    tau_hi: np.ndarray,
    max_samples: int,
    curved: bool,
    compiled: bool = True,
):
    """The band's pixels of every edge (:func:`_band_pixels`) kept as :class:`_EdgeSamples`;
    also ``n_expected`` ``(M,4)`` and the along-edge scale ``tau_scale`` ``(M,4)`` (px) of
    ``tn``. ``compiled``: the pixels and pairs from
    :func:`rgbd_calib.detect.edge_fit_jit.edge_band_samples` (the same arithmetic as the numpy
    code below, without its padded ``(M,4,S,R)`` grids)."""
    m = frame.d.shape[0]
    n_edges = 4 * m
    tau_scale = np.maximum(0.5 * (tau_hi - tau_lo), 1.0)
    step_at = layout.step_at
    n_b = step_at.shape[-1]
    if compiled:
        from .edge_fit_jit import edge_band_samples

        cols = _band_columns(frame, band, tau_lo, tau_hi, max_samples)
        flat = [
            np.ascontiguousarray(a.reshape(n_edges, *a.shape[2:]), dtype=np.float64)
            for a in (
                cols.c_lo, cols.half_minor, cols.slope, frame.mid, frame.d, frame.normal,
                band, tau_lo, tau_hi, layout.m_at0, layout.m_slope, tau_scale, layout.bound,
                step_at,
            )
        ]  # fmt: skip
        ints = [np.ascontiguousarray(a.reshape(-1), dtype=np.int64) for a in
                (cols.axis, cols.stride, cols.n_used)]  # fmt: skip
        (edge_of, px_x, px_y, d0, tau, m_pix, tn, n_exp, pair_pix, pair_s, pair_step) = (
            edge_band_samples(
                ints[0], flat[0], ints[1], ints[2], *flat[1:9], cols.r_max,
                gray.shape[0], gray.shape[1], *flat[9:],
            )
        )  # fmt: skip
        n_expected = n_exp.reshape(m, 4)
        marker_of = edge_of // 4
    else:
        x, y, d0, tau, use, n_expected = _band_pixels(
            gray.shape, frame, band, tau_lo, tau_hi, max_samples
        )
        # keep only the band's pixels, as flat arrays with their edge (m*4 + k) and marker
        sel = np.nonzero(use.reshape(m * 4, -1))
        edge_of = sel[0]
        marker_of = edge_of // 4
        d0, tau = d0.reshape(m * 4, -1)[sel], tau.reshape(m * 4, -1)[sel]
        px_x = x.reshape(m * 4, -1)[sel].astype(np.intp)
        px_y = y.reshape(m * 4, -1)[sel].astype(np.intp)
        m_at0, m_slope = layout.m_at0, layout.m_slope
        m_pix = np.clip(m_at0.reshape(-1)[edge_of] + m_slope.reshape(-1)[edge_of] * tau, 0.1, None)
        tn = tau / tau_scale.reshape(-1)[edge_of]  # normalised along-edge coordinate in [-1, 1]
        # (pixel, boundary) pairs where the data cells change colour (step_i != 0): s - c_i
        # and step_i, ordered by pixel
        pair = np.flatnonzero(step_at.reshape(n_edges, n_b)[edge_of] != 0)
        pair_pix = pair // n_b
        at_boundary = edge_of[pair_pix] * n_b + pair % n_b
        pair_s = tau[pair_pix] - layout.bound.reshape(-1)[at_boundary]
        pair_step = step_at.reshape(-1)[at_boundary]
    values = gray[px_y, px_x].astype(np.float64)
    # the pixels are ordered by edge (hence by marker), and the pairs by pixel: per-edge or
    # per-marker values spread to the pixels by np.repeat, sums per edge or marker are sums of
    # contiguous segments (np.add.reduceat); both much faster than fancy indexing/np.bincount
    edge_count = np.bincount(edge_of, minlength=n_edges)
    samples = _EdgeSamples(
        m=m,
        curved=curved,
        edge_of=edge_of,
        d0=d0,
        tn=tn,
        tn2=tn**2,
        values=values,
        m_pix=m_pix,
        pair_pix=pair_pix,
        pair_s=pair_s,
        pair_step=pair_step,
        edge_count=edge_count,
        marker_count=edge_count.reshape(m, 4).sum(axis=1),
        pair_count=np.bincount(marker_of[pair_pix], minlength=m),
        edge_sum=_segment_summer(edge_of, n_edges),
        per_marker=_segment_summer(marker_of, m),
    )
    return samples, n_expected, tau_scale


def _edge_model(s: _EdgeSamples, local: np.ndarray, width: np.ndarray):
    """The basis (the blurred marker image, 0 on the ink and 1 on the quiet zone) at each
    pixel and its derivatives by d and by w (per px); independent of the pixel weights.
    ``local`` ``(M,4,3)``: rho (px), theta, kappa (px per unit of ``tn``) per edge; ``width``
    ``(M,)`` the blur width (px).

    Only the cell boundaries within _FAR blur widths of a pixel need the Gaussian CDF:
    further ones contribute exactly step_i (in front of the pixel) or 0 (behind it) in
    double precision, and nothing to the derivative."""
    n_pix = s.d0.shape[0]
    rho, theta, kappa = (np.repeat(v, s.edge_count) for v in local.reshape(4 * s.m, 3).T)
    dist = s.d0 - rho + theta * s.tn
    if s.curved:  # kappa stays 0 otherwise
        dist += kappa * s.tn2
    wd = s.at_pixels(width)
    z = dist / wd
    e = -(dist + s.m_pix) / wd
    g = s.pair_s / np.repeat(width, s.pair_count)
    near = np.flatnonzero(np.abs(g) < _FAR)
    gn, step_n = g[near], s.pair_step[near]
    phi = np.where(g > 0.0, s.pair_step, 0.0)
    phi[near] = step_n * ndtr(gn)
    behind = np.bincount(s.pair_pix, phi, minlength=n_pix)  # white data cells behind, at s
    behind_w = np.bincount(  # w * d behind / d w
        s.pair_pix[near], -step_n * _pdf(gn) * gn, minlength=n_pix
    )
    phi_e = np.zeros_like(e)  # 0 where the data cells are > _FAR blur widths behind
    live = np.flatnonzero(e > -_FAR)
    phi_e[live] = ndtr(e[live])
    basis = ndtr(z) + phi_e * behind
    pz, pe = _pdf(z), _pdf(e)
    d_dist = (pz - pe * behind) / wd  # d basis / d dist
    d_width = (-pz * z - pe * e * behind + phi_e * behind_w) / wd
    return basis, d_dist, d_width


def _edge_solve(
    s: _EdgeSamples,
    basis: np.ndarray,
    width: np.ndarray,
    wt: np.ndarray,
    blur_prior: tuple[float, float],
):
    """Closed-form weighted least squares of values = D + C * basis, per marker: the
    cost (with the blur prior on ``width``, px), the contrast C (grey levels) and the
    residuals (grey levels, per pixel)."""
    w0, w_sigma = blur_prior
    per_marker, values = s.per_marker, s.values
    sw, s1, s2 = per_marker(wt), per_marker(wt * basis), per_marker(wt * basis**2)
    sv, svb = per_marker(wt * values), per_marker(wt * values * basis)
    det = sw * s2 - s1 * s1
    contrast = (sw * svb - s1 * sv) / np.where(np.abs(det) > 1e-12, det, 1e-12)
    dark = (sv - contrast * s1) / np.maximum(sw, 1e-12)
    resid = values - (s.at_pixels(dark) + s.at_pixels(contrast) * basis)
    cost = per_marker(wt * resid**2) + ((width - w0) / w_sigma) ** 2
    return cost, contrast, resid


def _lm_step(
    s: _EdgeSamples,
    model: tuple[np.ndarray, np.ndarray, np.ndarray],
    contrast: np.ndarray,
    resid: np.ndarray,
    weight: np.ndarray,
    width: np.ndarray,
    lam: np.ndarray,
    blur_prior: tuple[float, float],
) -> np.ndarray:
    """One damped Gauss-Newton step ``(M, 4*n_loc+3)`` per marker: the ``n_loc`` edge
    parameters of each edge (rho, theta[, kappa]), then D, C and the blur width (px)."""
    basis, d_dist, d_width = model
    w0, w_sigma = blur_prior
    m, tn, tn2 = s.m, s.tn, s.tn2
    n_loc = 3 if s.curved else 2
    n_big = 4 * n_loc + 3
    upper, scatter = _normal_equation_layout(n_loc)
    c_pix = s.at_pixels(contrast)
    g = c_pix * d_dist
    # the Jacobian's columns for the pixel's own edge, then per-edge sums of the products
    # of the columns (upper triangle) and of the columns with the residuals, placed into
    # each marker's system by a constant 0/1 matrix (row by row: no (n_par^2, P) temporary)
    cols = [-g, g * tn, g * tn2][:n_loc] + [np.ones_like(g), basis, c_pix * d_width]
    wcols = [weight * c for c in cols]
    sums = np.stack(
        [s.edge_sum(wcols[a] * cols[b]) for a, b in zip(*upper)]
        + [s.edge_sum(wc * resid) for wc in wcols]
    )
    normal_eq = sums.reshape(-1, m, 4).transpose(1, 2, 0).reshape(m, -1) @ scatter
    jtj = normal_eq[:, : n_big * n_big].reshape(m, n_big, n_big)
    jtr = normal_eq[:, n_big * n_big :]
    jtj[:, -1, -1] += 1.0 / w_sigma**2  # Gaussian prior on the blur width
    jtr[:, -1] += (w0 - width) / w_sigma**2
    diag = np.einsum("mii->mi", jtj)
    damped = jtj + (lam[:, None] * diag + 1e-9)[..., None] * np.eye(n_big)
    return np.nan_to_num(np.linalg.solve(damped, jtr[..., None])[..., 0])


def _fit_edge_models(
    s: _EdgeSamples, band: np.ndarray, blur_prior: tuple[float, float], iterations: int
):
    """Levenberg-Marquardt per marker: offset rho_k (px), angle theta_k (curvature kappa_k
    with lens distortion) per edge, d = d0 - rho + theta*tn + kappa*tn^2, and a blur width w
    (px) shared by the four edges (an axis-aligned edge samples the step at a single sub-pixel
    phase and cannot tell its position from the blur on its own). D and C enter linearly and
    are solved in closed form at every evaluation (variable projection): no initial guess
    needed. Returns ``local`` ``(M,4,3)``, ``width`` ``(M,)``, the pixel weights (0/1), the
    contrast ``(M,)`` and the residuals per pixel (grey levels)."""
    m, n_loc = s.m, 3 if s.curved else 2
    w0 = blur_prior[0]
    local = np.zeros((m, 4, 3))  # rho, theta, kappa per edge
    width = np.full(m, w0)
    lam = np.full(m, 1e-3)
    weight = np.ones_like(s.values)
    # the model at the current parameters is kept: after a rejected step it is unchanged, after
    # an accepted one it is the trial's (one model evaluation per iteration)
    basis, d_dist, d_width = _edge_model(s, local, width)
    cost, contrast, resid = _edge_solve(s, basis, width, weight, blur_prior)
    for it in range(iterations):
        if it in (3, 6):  # reject outlier pixels (occlusion, stray texture) from then on
            limit = np.maximum(
                4.0 * 1.4826 * _edge_medians(np.abs(resid), weight > 0, s.edge_of, 4 * m),
                0.02 * np.abs(contrast).repeat(4) + 1.0,
            )
            weight = (np.abs(resid) <= np.repeat(limit, s.edge_count)).astype(float)
            cost, contrast, resid = _edge_solve(s, basis, width, weight, blur_prior)
        step = _lm_step(
            s, (basis, d_dist, d_width), contrast, resid, weight, width, lam, blur_prior
        )
        # the trial parameters, kept per marker where they lower the cost
        trial = local.copy()
        trial[..., :n_loc] += step[:, : 4 * n_loc].reshape(m, 4, n_loc)
        trial[..., 0] = np.clip(trial[..., 0], -band, band)
        trial_w = np.clip(width + step[:, -1], 0.15, 3.0)
        t_basis, t_d_dist, t_d_width = _edge_model(s, trial, trial_w)
        t_cost, t_contrast, t_resid = _edge_solve(s, t_basis, trial_w, weight, blur_prior)
        better = t_cost < cost
        local = np.where(better[:, None, None], trial, local)
        width = np.where(better, trial_w, width)
        lam = np.where(better, lam / 3.0, lam * 4.0)
        cost = np.where(better, t_cost, cost)
        contrast = np.where(better, t_contrast, contrast)
        on = s.at_pixels(better)
        basis = np.where(on, t_basis, basis)
        d_dist = np.where(on, t_d_dist, d_dist)
        d_width = np.where(on, t_d_width, d_width)
        resid = np.where(on, t_resid, resid)
    return local, width, weight, contrast, resid


#: the compiled fit stops a marker once its step is below this (px): results stay within
#: ~1e-9 px of running every marker for ``edge_iterations`` like the numpy reference
EDGE_STEP_TOL_PX = 1e-9


def _fit_edge_models_compiled(
    s: _EdgeSamples, band: np.ndarray, blur_prior: tuple[float, float], iterations: int
):
    """:func:`_fit_edge_models` by :func:`rgbd_calib.detect.edge_fit_jit.fit_edge_models`, one
    marker at a time with its own iteration count (stops when its step is below
    :data:`EDGE_STEP_TOL_PX`, at most ``iterations``). numba is imported here, on the first
    edge fit, so that importing the detection stage stays cheap."""
    from .edge_fit_jit import fit_edge_models

    n_pix = s.d0.shape[0]
    edge_ptr = np.concatenate([[0], np.cumsum(s.edge_count)]).astype(np.int64)
    pairs_per_pixel = np.bincount(s.pair_pix, minlength=n_pix)
    pair_ptr = np.concatenate([[0], np.cumsum(pairs_per_pixel)]).astype(np.int64)
    f64 = [np.ascontiguousarray(a, dtype=np.float64) for a in (s.d0, s.tn, s.tn2, s.values)]
    local, width, weight, contrast, resid, _ = fit_edge_models(
        edge_ptr,
        *f64,
        np.ascontiguousarray(s.m_pix, dtype=np.float64),
        pair_ptr,
        np.ascontiguousarray(s.pair_s, dtype=np.float64),
        np.ascontiguousarray(s.pair_step, dtype=np.float64),
        np.ascontiguousarray(band, dtype=np.float64),
        float(blur_prior[0]),
        float(blur_prior[1]),
        int(iterations),
        bool(s.curved),
        EDGE_STEP_TOL_PX,
    )
    return local, width, weight, contrast, resid


def _edge_tests(
    s: _EdgeSamples,
    local: np.ndarray,
    width: np.ndarray,
    weight: np.ndarray,
    contrast: np.ndarray,
    resid: np.ndarray,
    band: np.ndarray,
    n_expected: np.ndarray,
    config: DetectionConfig,
) -> dict[str, np.ndarray]:
    """The tests an edge's fit must pass, by name, ``(M,4)`` True where passed: enough
    contrast (grey levels) and inlier pixels, its offset inside the band (px), a blur width
    (px) off the fit's floor and cap, and a small RMS residual relative to the contrast (the
    bound of :func:`edge_residual_bound`)."""
    rho = local[..., 0]
    n_in = s.per_edge(weight)
    rms = np.sqrt(s.per_edge(weight * resid**2) / np.maximum(n_in, 1))
    c = contrast[:, None]
    w = np.broadcast_to(width[:, None], rho.shape)
    tests = {
        "contrast": np.broadcast_to(c >= config.edges.min_edge_contrast, rho.shape),
        "inliers": (n_in >= 6) & (n_in >= config.edges.min_edge_inliers * n_expected),
        "offset": np.abs(rho) < band,
        "blur_floor": w > 0.15,
        "blur_cap": w < 3.0,
    }
    relative = rms / np.maximum(c, 1e-9)
    fits = np.logical_and.reduce(list(tests.values()))
    tests["residual"] = relative <= edge_residual_bound(relative[fits], config)
    return tests


def edge_residual_bound(relative: np.ndarray, config: DetectionConfig) -> float:
    """The largest RMS residual / contrast an edge of this image may have: the fixed
    ``max_edge_residual``, or, where the image's edges all fit the model worse (a camera's
    sharpening and compression; measured: docs/accuracy.md), ``edge_residual_factor`` times
    the median of its edges
    ``relative`` (those passing the other tests), at most ``max_edge_residual_cap``. An
    occluded or wrong edge still stands out against the image's own median."""
    if relative.size == 0 or config.edges.edge_residual_factor is None:
        return config.edges.max_edge_residual
    adaptive = config.edges.edge_residual_factor * float(np.median(relative))
    return float(np.clip(adaptive, config.edges.max_edge_residual,
                         max(config.edges.max_edge_residual_cap, config.edges.max_edge_residual)))


def _edge_lines(
    local: np.ndarray,
    frame: _EdgeFrame,
    tau_scale: np.ndarray,
    intrinsics: CameraIntrinsics | None,
):
    """The fitted edges as points on them, then straight lines ``normal . x = rho``: unit
    normals ``(M,4,2)`` (out of the marker) and ``rho`` ``(M,4)`` (px), in undistorted pixels
    when ``intrinsics`` is given (only with lens distortion), else image pixels."""
    rho, theta, kappa = np.moveaxis(local, -1, 0)
    normal = frame.normal
    tau_scale = tau_scale[..., None]
    tq = np.array([-1.0, 0.0, 1.0])
    off = rho[..., None] - theta[..., None] * tq - kappa[..., None] * tq**2  # d0 on the edge
    pts = (
        frame.mid[..., None, :]
        + (tq[None, None, :, None] * tau_scale[..., None]) * frame.d[..., None, :]
        + off[..., None] * normal[..., None, :]
    )  # (M,4,3,2)
    if intrinsics is not None:
        pts = intrinsics.undistort_pixels(pts)
    centre = pts.mean(axis=-2)
    direction = pts[..., 2, :] - pts[..., 0, :]
    direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-12)
    nrm = np.stack([direction[..., 1], -direction[..., 0]], axis=-1)
    nrm *= np.where(np.einsum("mkj,mkj->mk", nrm, normal) < 0, -1.0, 1.0)[..., None]
    return nrm, np.einsum("mkj,mkj->mk", centre, nrm)


def _segment_summer(group: np.ndarray, n: int):
    """``f(v)`` = ``np.bincount(group, v, minlength=n)`` for a sorted ``group``."""
    counts = np.bincount(group, minlength=n)
    nonempty = counts > 0
    starts = (np.cumsum(counts) - counts)[nonempty]

    def total(v: np.ndarray) -> np.ndarray:
        out = np.zeros(n)
        if starts.size:
            out[nonempty] = np.add.reduceat(v, starts)
        return out

    return total


def _edge_medians(v: np.ndarray, use: np.ndarray, edge_of: np.ndarray, n_edges: int):
    """Per edge, the upper median of ``v[use]`` (element ``count // 2`` of the edge's sorted
    values; 0 without any) for pixels sorted by ``edge_of``."""
    v, edge = v[use], edge_of[use]
    counts = np.bincount(edge, minlength=n_edges)
    out = np.zeros(n_edges)
    if v.size == 0:
        return out
    starts = np.cumsum(counts) - counts
    table = np.full((n_edges, int(counts.max())), np.inf)
    table[edge, np.arange(v.size) - starts[edge]] = v
    table.sort(axis=1)
    has = counts > 0
    out[has] = table[has, counts[has] // 2]
    return out


@lru_cache(maxsize=4)
def _normal_equation_layout(n_loc: int) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """Where the per-edge sums go in a marker's normal equations.

    A marker's parameters are ``n_loc`` per edge (edge ``k``: ``k*n_loc ...``) then the three
    shared ones (D, C, w); a pixel's Jacobian row is non-zero only in its edge's ``n_loc`` and
    the shared columns (``n_par = n_loc + 3``). Returns the upper-triangle index pairs of the
    ``n_par`` columns and a 0/1 matrix mapping the per-edge sums, ordered (edge, products of
    column pairs then column x residual), to ``J^T J`` (flat) followed by ``J^T r``."""
    n_par, n_big = n_loc + 3, 4 * n_loc + 3
    upper = np.triu_indices(n_par)
    n_pairs = upper[0].size
    scatter = np.zeros((4, n_pairs + n_par, n_big * n_big + n_big))
    for k in range(4):
        index = [k * n_loc + i for i in range(n_loc)] + [4 * n_loc + i for i in range(3)]
        for p, (a, b) in enumerate(zip(*upper)):
            scatter[k, p, index[a] * n_big + index[b]] = 1.0
            scatter[k, p, index[b] * n_big + index[a]] = 1.0
        for a in range(n_par):
            scatter[k, n_pairs + a, n_big * n_big + index[a]] = 1.0
    scatter = scatter.reshape(4 * (n_pairs + n_par), -1)
    scatter.setflags(write=False)
    upper[0].setflags(write=False)
    upper[1].setflags(write=False)
    return upper, scatter


_FAR = 8.5  # |x| beyond which ndtr(x) is 0 or 1 to double precision (ndtr(-8.5) ~ 1e-17)


def _pdf(x: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * x * x) * (1.0 / np.sqrt(2.0 * np.pi))


def refine_corners_edges(
    gray: np.ndarray,
    corners_px: np.ndarray,
    white: np.ndarray,
    config: DetectionConfig | None = None,
    intrinsics: CameraIntrinsics | None = None,
    compiled: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Corners as intersections of lines fitted to the markers' outer edges.

    ``gray`` is a grey image (any real dtype; float keeps the BGR -> grey conversion
    unrounded), ``corners_px`` ``(N,4,2)`` the initial corners (ArUco
    order), ``white`` ``(N,cells,cells)`` each marker's cells (True = white, border included;
    see :func:`rgbd_calib.detect.markers.marker_pattern`). Returns the corners and a
    ``(N,4)`` mask of the corners the edge fit set; the others keep their input position
    (marker too small, edge off the image or occluded, poor fit, grazing intersection, or a
    jump beyond ``max_corner_shift_px``).
    ``compiled=False`` runs the numpy reference of the edge model's fit (tests compare them).
    """
    config = config or DetectionConfig()
    gray = np.asarray(gray)  # any real dtype: the edge fit converts the pixels it reads
    if gray.dtype.kind not in "uif":
        gray = gray.astype(np.float64)
    initial = np.asarray(corners_px, dtype=float)
    white = np.asarray(white, dtype=bool)
    n = initial.shape[0]
    out = initial.copy()
    refined = np.zeros((n, 4), dtype=bool)
    if n == 0:
        return out, refined
    side = np.linalg.norm(np.roll(initial, -1, axis=1) - initial, axis=-1)
    sel = np.nonzero(side.min(axis=1) >= config.edges.min_edge_length_px)[0]
    if sel.size == 0:
        return out, refined
    current = initial[sel].copy()
    ok_corner = np.zeros((sel.size, 4), dtype=bool)
    blur_prior = config.edges.blur_prior_px
    for _ in range(config.edges.edge_passes):
        nrm, rho, ok_line, width = _fit_edge_lines(
            gray, current, white[sel], config, intrinsics, blur_prior, compiled
        )
        good = ok_line.all(axis=1)
        if np.any(good):  # later passes: the image's typical blur, a tighter prior
            blur_prior = (float(np.median(width[good])), 0.5 * blur_prior[1])
        # corner k lies on edge k-1 (from corner k-1) and edge k (to corner k+1)
        n_prev, r_prev, ok_prev = (
            np.roll(nrm, 1, axis=1),
            np.roll(rho, 1, axis=1),
            np.roll(ok_line, 1, axis=1),
        )
        det = n_prev[..., 0] * nrm[..., 1] - n_prev[..., 1] * nrm[..., 0]
        well_posed = np.abs(det) > np.sin(np.radians(15.0))
        safe = np.where(well_posed, det, 1.0)
        x = (r_prev * nrm[..., 1] - rho * n_prev[..., 1]) / safe
        y = (n_prev[..., 0] * rho - nrm[..., 0] * r_prev) / safe
        corner = np.stack([x, y], axis=-1)
        if intrinsics is not None and intrinsics.has_distortion:
            corner = intrinsics.distort_pixels(corner)
        shift = np.linalg.norm(corner - initial[sel], axis=-1)
        ok_corner = (
            ok_line
            & ok_prev
            & well_posed
            & np.isfinite(shift)
            & (shift <= config.max_corner_shift_px)
        )
        current = np.where(ok_corner[..., None], corner, initial[sel])
    out[sel] = current
    refined[sel] = ok_corner
    return out, refined
