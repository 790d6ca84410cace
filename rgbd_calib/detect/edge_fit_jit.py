"""The edge model's Levenberg-Marquardt fit compiled with numba: one marker at a time.

The numpy reference (:func:`rgbd_calib.detect.edge_fit._fit_edge_models`) evaluates every marker of
an image at once with whole-array operations: ~25 temporaries of the band's size per model
evaluation and the normal equations through a 0/1 scatter matrix, so the fit costs ~10 ms per
1280x720 image, more than OpenCV's marker detection. Here the same maths runs as loops over one
marker's pixels (no temporaries, the normal equations summed in place, the small damped system
solved by Gaussian elimination), and a marker stops as soon as its step is below ``tol`` (the
numpy version runs every marker for ``iterations``, the slowest marker's count).

Pure maths on flat arrays (the layout of ``edge_fit._EdgeSamples``); compiled on first use
and cached on disk (``cache=True``), so worker processes load the machine code instead of
compiling it again. Results equal the reference to ~1e-9 px (summation order, ``erfc`` vs
scipy's ``ndtr``, the linear solver; tests/test_detection.py checks 1e-6 px).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_FAR = 8.5  # |x| beyond which ndtr(x) is 0 or 1 to double precision (as in edge_fit._FAR)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_SQRT1_2 = math.sqrt(0.5)


# cephes' rational approximations of erf (|x| <= 1) and erfc (x >= 1) (scipy.special.ndtr is
# cephes' ndtr), so that Phi and phi can share their exponential: erfc(x) = exp(-x^2) * P/Q
# with exp(-x^2) = exp(-a^2/2) for x = a/sqrt(2), the Gaussian pdf's own exponential. libm's
# erf/erfc cost ~25 ns a call, exp ~9 ns: the model's cost is these calls.
_T = (9.60497373987051638749e0, 9.00260197203842689217e1, 2.23200534594684319226e3,
      7.00332514112805075473e3, 5.55923013010394962768e4)  # fmt: skip
_U = (3.35617141647503099647e1, 5.21357949780152679795e2, 4.59432382970980127987e3,
      2.26290000613890934246e4, 4.92673942608635921086e4)  # fmt: skip
_P = (2.46196981473530512524e-10, 5.64189564831068821977e-1, 7.46321056442269912687e0,
      4.86371970985681366614e1, 1.96520832956077098242e2, 5.26445194995477358631e2,
      9.34528527171957607540e2, 1.02755188689515710272e3, 5.57535335369399327526e2)  # fmt: skip
_Q = (1.32281951154744992508e1, 8.67072140885989742329e1, 3.54937778887819891062e2,
      9.75708501743205489753e2, 1.82390916687909736289e3, 2.24633760818710981792e3,
      1.65666309194161350182e3, 5.57535340817727675546e2)  # fmt: skip
_R = (5.64189583547755073984e-1, 1.27536670759978104416e0, 5.01905042251180477414e0,
      6.16021097993053585195e0, 7.40974269950448939160e0, 2.97886665372100240670e0)  # fmt: skip
_S = (2.26052863220117276590e0, 9.39603524938001434673e0, 1.20489539808096656605e1,
      1.70814450747565897222e1, 9.60896809063285878198e0, 3.36907645100081516050e0)  # fmt: skip


@njit(cache=True, inline="always")
def _polevl(x, c):
    y = c[0]
    for i in range(1, len(c)):
        y = y * x + c[i]
    return y


@njit(cache=True, inline="always")
def _p1evl(x, c):
    y = x + c[0]
    for i in range(1, len(c)):
        y = y * x + c[i]
    return y


@njit(cache=True, inline="always")
def _ndtr_pdf(a: float) -> tuple[float, float]:
    """(Phi(a), phi(a)): the standard normal CDF as cephes' ``ndtr`` and the density, from
    one exponential."""
    e = math.exp(-0.5 * a * a)
    x = a * _SQRT1_2
    z = abs(x)
    if z < 1.0:  # cephes: 0.5 + 0.5 erf(x) below sqrt(1/2), then 0.5 (1 - erf|x|): same
        zz = x * x
        erf = x * _polevl(zz, _T) / _p1evl(zz, _U)
        return 0.5 + 0.5 * erf, e * _INV_SQRT_2PI
    if z < 8.0:
        y = 0.5 * (e * _polevl(z, _P) / _p1evl(z, _Q))
    else:
        y = 0.5 * (e * _polevl(z, _R) / _p1evl(z, _S))
    return (1.0 - y if x > 0.0 else y), e * _INV_SQRT_2PI


@njit(cache=True)
def _model(
    e0, d0, tn, tn2, m_pix, pair_ptr, pair_s, pair_step, local, width, curved,
    basis, d_dist, d_width,
):  # fmt: skip
    """The blurred marker image (0 on the ink, 1 on the quiet zone) and its derivatives by d
    and by w at one marker's pixels (see ``edge_fit._edge_model``); ``local`` ``(4,3)`` rho,
    theta, kappa of its edges, ``e0`` ``(5,)`` the pixel offsets of its four edges."""
    wd = width
    for k in range(4):
        rho, theta, kappa = local[k, 0], local[k, 1], local[k, 2]
        for i in range(e0[k], e0[k + 1]):
            dist = d0[i] - rho + theta * tn[i]
            if curved:
                dist += kappa * tn2[i]
            z = dist / wd
            e = -(dist + m_pix[i]) / wd
            behind = 0.0
            behind_w = 0.0
            for j in range(pair_ptr[i], pair_ptr[i + 1]):
                g = pair_s[j] / width
                if abs(g) < _FAR:
                    cdf, pdf = _ndtr_pdf(g)
                    behind += pair_step[j] * cdf
                    behind_w += -pair_step[j] * pdf * g
                elif g > 0.0:
                    behind += pair_step[j]
            # the data cells' step only where a white cell is behind and within _FAR blur
            # widths (else its terms are 0, or below 1e-16 of the contrast for pdf(e))
            phi_e = pe = 0.0
            if e > -_FAR and (behind != 0.0 or behind_w != 0.0):
                phi_e, pe = _ndtr_pdf(e)
            phi_z, pz = _ndtr_pdf(z)
            basis[i] = phi_z + phi_e * behind
            d_dist[i] = (pz - pe * behind) / wd
            d_width[i] = (-pz * z - pe * e * behind + phi_e * behind_w) / wd


@njit(cache=True)
def _solve_linear(p0, p1, values, basis, wt, width, w0, w_sigma, resid):
    """Closed-form weighted least squares values = D + C * basis over pixels ``p0:p1``:
    returns (cost with the blur prior, C) and fills ``resid`` (see ``edge_fit._edge_solve``)."""
    sw = s1 = s2 = sv = svb = 0.0
    for i in range(p0, p1):
        w, b, v = wt[i], basis[i], values[i]
        sw += w
        s1 += w * b
        s2 += w * b * b
        sv += w * v
        svb += w * v * b
    det = sw * s2 - s1 * s1
    contrast = (sw * svb - s1 * sv) / (det if abs(det) > 1e-12 else 1e-12)
    dark = (sv - contrast * s1) / max(sw, 1e-12)
    cost = 0.0
    for i in range(p0, p1):
        r = values[i] - (dark + contrast * basis[i])
        resid[i] = r
        cost += wt[i] * r * r
    return cost + ((width - w0) / w_sigma) ** 2, contrast


@njit(cache=True)
def _gauss_solve(a, b):
    """Solve ``a x = b`` in place by Gaussian elimination with partial pivoting (``a`` small,
    symmetric positive definite after damping); a zero pivot gives a zero step (the numpy
    reference's ``nan_to_num``)."""
    n = b.shape[0]
    for c in range(n):
        piv = c
        for r in range(c + 1, n):
            if abs(a[r, c]) > abs(a[piv, c]):
                piv = r
        if a[piv, c] == 0.0:
            return np.zeros(n)
        if piv != c:
            for j in range(n):
                a[c, j], a[piv, j] = a[piv, j], a[c, j]
            b[c], b[piv] = b[piv], b[c]
        for r in range(c + 1, n):
            f = a[r, c] / a[c, c]
            if f != 0.0:
                for j in range(c, n):
                    a[r, j] -= f * a[c, j]
                b[r] -= f * b[c]
    x = np.zeros(n)
    for c in range(n - 1, -1, -1):
        acc = b[c]
        for j in range(c + 1, n):
            acc -= a[c, j] * x[j]
        x[c] = acc / a[c, c]
    for c in range(n):
        if not math.isfinite(x[c]):
            x[c] = 0.0
    return x


@njit(cache=True)
def _lm_step(
    e0, tn, tn2, basis, d_dist, d_width, resid, wt, contrast, width, lam, w0, w_sigma, n_loc
):  # fmt: skip
    """One damped Gauss-Newton step of one marker: ``n_loc`` parameters per edge, then D, C
    and the blur width (see ``edge_fit._lm_step``)."""
    n_par = n_loc + 3
    n_big = 4 * n_loc + 3
    jtj = np.zeros((n_big, n_big))
    jtr = np.zeros(n_big)
    col = np.zeros(n_par)
    ej = np.zeros((n_par, n_par))
    er = np.zeros(n_par)
    index = np.zeros(n_par, dtype=np.int64)
    for k in range(4):
        ej[:] = 0.0
        er[:] = 0.0
        for i in range(e0[k], e0[k + 1]):
            g = contrast * d_dist[i]
            col[0] = -g
            col[1] = g * tn[i]
            if n_loc == 3:
                col[2] = g * tn2[i]
            col[n_loc] = 1.0
            col[n_loc + 1] = basis[i]
            col[n_loc + 2] = contrast * d_width[i]
            w, r = wt[i], resid[i]
            for a in range(n_par):
                wa = w * col[a]
                for b in range(a, n_par):
                    ej[a, b] += wa * col[b]
                er[a] += wa * r
        for a in range(n_loc):
            index[a] = k * n_loc + a
        for a in range(3):
            index[n_loc + a] = 4 * n_loc + a
        for a in range(n_par):
            for b in range(a, n_par):
                jtj[index[a], index[b]] += ej[a, b]
                if a != b:
                    jtj[index[b], index[a]] += ej[a, b]
            jtr[index[a]] += er[a]
    jtj[n_big - 1, n_big - 1] += 1.0 / w_sigma**2  # Gaussian prior on the blur width
    jtr[n_big - 1] += (w0 - width) / w_sigma**2
    for a in range(n_big):
        jtj[a, a] += lam * jtj[a, a] + 1e-9
    return _gauss_solve(jtj, jtr)


@njit(cache=True)
def _upper_median(v):
    """Element ``len // 2`` of the sorted ``v`` (0 when empty), as ``edge_fit._edge_medians``;
    by quickselect on ``v`` (reordered in place): O(n), and much quicker to compile than
    ``np.sort``."""
    n = v.size
    if n == 0:
        return 0.0
    k = n // 2
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = v[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while v[i] < pivot:
                i += 1
            while v[j] > pivot:
                j -= 1
            if i <= j:
                v[i], v[j] = v[j], v[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return v[k]
    return v[k]


@njit(cache=True)
def fit_edge_models(
    edge_ptr, d0, tn, tn2, values, m_pix, pair_ptr, pair_s, pair_step, band, w0, w_sigma,
    iterations, curved, tol,
):  # fmt: skip
    """Levenberg-Marquardt of the edge model per marker (see ``edge_fit._fit_edge_models``).

    ``edge_ptr`` ``(4M+1,)``: pixel offsets of the edges (pixels ordered by edge);
    ``pair_ptr`` ``(P+1,)``: offsets of each pixel's (pixel, cell boundary) pairs; ``band``
    ``(M,4)`` (px). A marker stops early once past the last outlier rejection and its step
    moves no edge nor the blur width by more than ``tol`` px (theta and kappa in px at the
    span's ends). Returns ``local`` ``(M,4,3)``, ``width`` ``(M,)``, the pixel weights (0/1),
    the contrast ``(M,)``, the residuals per pixel (grey levels) and the iterations run
    ``(M,)``."""
    m = band.shape[0]
    n_pix = d0.shape[0]
    n_loc = 3 if curved else 2
    local_all = np.zeros((m, 4, 3))
    width_all = np.full(m, w0)
    contrast_all = np.zeros(m)
    weight = np.ones(n_pix)
    resid = np.zeros(n_pix)
    basis, d_dist, d_width = np.zeros(n_pix), np.zeros(n_pix), np.zeros(n_pix)
    t_basis, t_d_dist, t_d_width = np.zeros(n_pix), np.zeros(n_pix), np.zeros(n_pix)
    t_resid = np.zeros(n_pix)
    scratch = np.zeros(n_pix)
    n_iter = np.zeros(m, dtype=np.int64)
    # outlier rejection at iterations 3 and 6 (as the reference): no stop before the last one
    last_reject = 6 if iterations > 6 else (3 if iterations > 3 else 0)
    for mk in range(m):
        e0 = edge_ptr[4 * mk : 4 * mk + 5]
        p0, p1 = e0[0], e0[4]
        local = np.zeros((4, 3))
        width = w0
        lam = 1e-3
        _model(e0, d0, tn, tn2, m_pix, pair_ptr, pair_s, pair_step, local, width,
               curved, basis, d_dist, d_width)  # fmt: skip
        cost, contrast = _solve_linear(p0, p1, values, basis, weight, width, w0, w_sigma, resid)
        trial = np.zeros((4, 3))
        for it in range(iterations):
            if it == 3 or it == 6:  # reject outlier pixels (occlusion, stray texture)
                floor = 0.02 * abs(contrast) + 1.0
                for k in range(4):
                    a, b = e0[k], e0[k + 1]
                    n_in = 0
                    for i in range(a, b):  # |residuals| of the edge's current inliers
                        if weight[i] > 0:
                            scratch[n_in] = abs(resid[i])
                            n_in += 1
                    limit = max(4.0 * 1.4826 * _upper_median(scratch[:n_in]), floor)
                    for i in range(a, b):
                        weight[i] = 1.0 if abs(resid[i]) <= limit else 0.0
                cost, contrast = _solve_linear(
                    p0, p1, values, basis, weight, width, w0, w_sigma, resid
                )
            step = _lm_step(e0, tn, tn2, basis, d_dist, d_width, resid, weight, contrast,
                            width, lam, w0, w_sigma, n_loc)  # fmt: skip
            n_iter[mk] = it + 1
            trial[:] = local
            size = abs(step[-1])
            for k in range(4):
                for j in range(n_loc):
                    trial[k, j] += step[k * n_loc + j]
                    size = max(size, abs(step[k * n_loc + j]))
                trial[k, 0] = min(max(trial[k, 0], -band[mk, k]), band[mk, k])
            trial_w = min(max(width + step[-1], 0.15), 3.0)
            _model(e0, d0, tn, tn2, m_pix, pair_ptr, pair_s, pair_step, trial,
                   trial_w, curved, t_basis, t_d_dist, t_d_width)  # fmt: skip
            t_cost, t_contrast = _solve_linear(
                p0, p1, values, t_basis, weight, trial_w, w0, w_sigma, t_resid
            )
            if t_cost < cost:
                local[:] = trial
                width, cost, contrast = trial_w, t_cost, t_contrast
                lam /= 3.0
                basis[p0:p1] = t_basis[p0:p1]
                d_dist[p0:p1] = t_d_dist[p0:p1]
                d_width[p0:p1] = t_d_width[p0:p1]
                resid[p0:p1] = t_resid[p0:p1]
            else:
                lam *= 4.0
            if it >= last_reject and size < tol:
                break
        local_all[mk] = local
        width_all[mk] = width
        contrast_all[mk] = contrast
    return local_all, width_all, weight, contrast_all, resid, n_iter


@njit(cache=True)
def edge_band_samples(
    axis, c_lo, stride, n_used, half_minor, slope, mid, d, normal, band, tau_lo, tau_hi,
    r_max, height, width, m_at0, m_slope, tau_scale, bound, step_at,
):  # fmt: skip
    """The band pixels of every edge and their (pixel, cell boundary) pairs, as flat arrays
    ordered by edge (see ``edge_fit._band_pixels`` and ``edge_fit._edge_samples``, whose
    arithmetic this repeats operation by operation, so the same pixels are selected).

    Per edge ``(4M,)``: the major image axis (0: x), the first column ``c_lo`` and column
    ``stride`` along it, the columns used, the band's extent along the minor axis and the
    edge's slope (minor per major px), ``mid``/``d``/``normal`` ``(4M,2)``, ``band``,
    ``tau_lo``/``tau_hi`` (px), the module width ``m_at0 + m_slope * tau`` and ``tau_scale``;
    ``bound``/``step_at`` ``(4M,B)`` the cell boundaries along the edge and the change of
    whiteness there. Returns ``edge_of``, pixel ``x``, ``y``, ``d0``, ``tau``, ``m_pix``,
    ``tn``, the per-edge ``n_expected`` (ignoring the image border), and per pair its pixel,
    ``s - c_i`` (px) and step."""
    n_edges = axis.shape[0]
    cap = 0
    for e in range(n_edges):
        cap += n_used[e] * r_max
    edge_of = np.empty(cap, dtype=np.int64)
    xs, ys = np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64)
    d0s, taus = np.empty(cap), np.empty(cap)
    n_expected = np.zeros(n_edges, dtype=np.int64)
    n = 0
    for e in range(n_edges):
        for j in range(n_used[e]):
            col = c_lo[e] + j * stride[e]
            line_minor = mid[e, 1 - axis[e]] + (col - mid[e, axis[e]]) * slope[e]
            row0 = math.floor(line_minor - half_minor[e])
            for r in range(r_max):
                row = row0 + r
                if axis[e] == 0:
                    x, y = col, row
                else:
                    x, y = row, col
                rel_x = x - mid[e, 0]
                rel_y = y - mid[e, 1]
                d0 = rel_x * normal[e, 0] + rel_y * normal[e, 1]
                tau = rel_x * d[e, 0] + rel_y * d[e, 1]
                if abs(d0) <= band[e] and tau >= tau_lo[e] and tau <= tau_hi[e]:
                    n_expected[e] += 1
                    if x >= 0 and y >= 0 and x <= width - 1 and y <= height - 1:
                        edge_of[n] = e
                        xs[n], ys[n] = int(x), int(y)
                        d0s[n], taus[n] = d0, tau
                        n += 1
    edge_of, xs, ys, d0s, taus = edge_of[:n], xs[:n], ys[:n], d0s[:n], taus[:n]
    m_pix = np.empty(n)
    tn = np.empty(n)
    n_b = step_at.shape[1]
    n_pairs = 0
    for i in range(n):
        e = edge_of[i]
        m_pix[i] = max(m_at0[e] + m_slope[e] * taus[i], 0.1)
        tn[i] = taus[i] / tau_scale[e]
        for b in range(n_b):
            if step_at[e, b] != 0:
                n_pairs += 1
    pair_pix = np.empty(n_pairs, dtype=np.int64)
    pair_s, pair_step = np.empty(n_pairs), np.empty(n_pairs)
    k = 0
    for i in range(n):
        e = edge_of[i]
        for b in range(n_b):
            if step_at[e, b] != 0:
                pair_pix[k] = i
                pair_s[k] = taus[i] - bound[e, b]
                pair_step[k] = step_at[e, b]
                k += 1
    return edge_of, xs, ys, d0s, taus, m_pix, tn, n_expected, pair_pix, pair_s, pair_step
