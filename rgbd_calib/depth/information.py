"""What a registration's correspondences say about its pose.

Nearest-neighbour matches with the depth-noise sigma of each residual, the Gauss-Newton
information of the point-to-plane and photometric terms, its conditioning (Gelfand et al.
2003), and the noise-model information of a registration: whitened residuals grouped by surface
patch, their cluster-robust covariance (:func:`noise_model_information`). Every information
is 6x6 in GTSAM order ``[rotation (rad), translation (m)]`` for a right perturbation of
``T_b_a`` (:data:`INFORMATION_FRAME`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..core.camera import FISHEYE, CameraIntrinsics
from ..core.geometry import invert_transform, matrix_to_rotvec, skew, transform_points
from .clouds import DisparityMoment, VoxelLevel, voxel_keys

INFORMATION_FRAME = (
    "right perturbation of T_b_a: T_b_a_true = T_b_a @ Exp(xi), xi = [omega (rad), v (m)] in "
    "camera a's frame (GTSAM Pose3 local coordinates; BetweenFactorPose3(key_ref_b, key_ref_a, "
    "T_b_a) uses exactly this tangent space)"
)


# --------------------------------------------------------------------------- correspondences
@dataclass(frozen=True)
class Matches:
    """Nearest-neighbour correspondences of source (a) points in the target (b) cloud."""

    src: np.ndarray  # source points in a, (M,3)
    tgt: np.ndarray  # target points in b
    normals_b: np.ndarray  # target normals in b
    residual: np.ndarray  # point-to-plane residual (m)
    sigma: np.ndarray  # its noise-model sigma (m)
    distance: np.ndarray  # point-to-point distance (m)
    src_index: np.ndarray  # indices into the source level
    tgt_index: np.ndarray  # indices into the target level


def nearest_matches(src: VoxelLevel, tgt: VoxelLevel, tree: cKDTree, T_b_a: np.ndarray,
                    max_distance: float) -> Matches:
    p_b = transform_points(T_b_a, src.points)
    d, j = tree.query(p_b, distance_upper_bound=max_distance, workers=-1)
    ok = np.isfinite(d)
    i, j = np.nonzero(ok)[0], j[ok]
    n_b = tgt.normals[j]
    r = np.einsum("ij,ij->i", n_b, p_b[i] - tgt.points[j])
    # depth noise moves a point along its viewing ray: its normal component scales by
    # |n . p| / z (p/z is the ray with z = 1)
    m_a = n_b @ T_b_a[:3, :3]  # target normal in a's frame
    sa = src.sigma_z[i] * np.abs(np.einsum("ij,ij->i", m_a, src.points[i])) / src.points[i, 2]
    q = tgt.points[j]
    sb = tgt.sigma_z[j] * np.abs(np.einsum("ij,ij->i", n_b, q)) / q[:, 2]
    return Matches(src.points[i], q, n_b, r, np.sqrt(sa**2 + sb**2 + 1e-12), d[ok], i, j)


def rmse_mm(matches: Matches) -> float:
    if matches.residual.size == 0:
        return float("nan")
    return float(1000.0 * np.sqrt(np.mean(matches.residual**2)))


def normalised_rms(matches: Matches) -> float:
    """RMS of the point-to-plane residuals over their noise-model sigma (1 when the residuals
    are the depth noise alone)."""
    if matches.residual.size == 0:
        return float("nan")
    return float(np.sqrt(np.mean((matches.residual / matches.sigma) ** 2)))


def tangent_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """``xi`` (6, [rot rad, trans m]) with ``T_true ~ T_est Exp(xi)``: the right-perturbation
    error of ``T_est`` in the frame of :data:`INFORMATION_FRAME`."""
    D = invert_transform(np.asarray(T_est, dtype=float)) @ np.asarray(T_true, dtype=float)
    return np.concatenate([matrix_to_rotvec(D[:3, :3]), D[:3, 3]])


def with_bias_floor(information: np.ndarray, sigma_deg: float, sigma_mm: float) -> np.ndarray:
    """``information`` (6x6, ``[rot rad, trans m]``) of a pair whose covariance gains a bias
    ``B`` (``sigma_deg`` per rotation axis, ``sigma_mm`` per translation axis): ``(W^-1 +
    B)^-1`` (:func:`with_covariance`, which holds for a singular ``W`` too: a pair whose
    information leaves the directions of an unknown depth scale out). However many points a
    pair has, its information then stays below ``B^-1``. ``information`` as it is when
    either sigma is 0."""
    var = np.array([np.radians(sigma_deg) ** 2] * 3 + [(sigma_mm * 1e-3) ** 2] * 3)
    if not np.all(var > 0):
        return information
    return with_covariance(information, np.diag(var))


def with_covariance(information: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """``information`` (6x6) of an estimate whose covariance gains ``covariance`` (6x6,
    symmetric positive semi-definite, e.g. an error the estimate carries from its inputs):
    ``(W^-1 + L L^T)^-1 = W - W L (I + L^T W L)^-1 L^T W`` with ``covariance = L L^T``, which
    holds for a singular ``W`` or ``covariance`` too."""
    w, V = np.linalg.eigh(0.5 * (covariance + covariance.T))
    keep = w > 1e-15 * max(float(w.max(initial=0.0)), 1e-300)
    if not np.any(keep):
        return information
    L = V[:, keep] * np.sqrt(w[keep])
    W = np.asarray(information, dtype=float)
    WL = W @ L
    out = W - WL @ np.linalg.solve(np.eye(L.shape[1]) + L.T @ WL, WL.T)
    return 0.5 * (out + out.T)


# --------------------------------------------------------------------------- Gauss-Newton
def _intensity(colors: np.ndarray) -> np.ndarray:
    return np.asarray(colors, dtype=float).mean(axis=1)  # as Open3D's colored ICP: (r+g+b)/3


def color_gradients(points: np.ndarray, normals: np.ndarray, colors: np.ndarray,
                    k: int = 16, at: np.ndarray | None = None) -> np.ndarray:
    """Gradient (N,3) of the intensity on each point's tangent plane, fitted by least squares
    to its ``k`` nearest neighbours projected onto the plane (Park et al. 2017: the
    continuous colour function ``C_p(u) = C(p) + d_p^T (u - p)`` with ``d_p . n_p = 0``).
    ``at`` (indices) limits the fit to those points; the others get zeros."""
    n_pts = points.shape[0]
    out = np.zeros_like(points, dtype=float)
    if n_pts < 4:
        return out
    idx = np.arange(n_pts) if at is None else np.unique(at)
    k = min(k, n_pts)
    _, nb = cKDTree(points).query(points[idx], k=k, workers=-1)
    intensity = _intensity(colors)
    n = normals[idx]
    # orthonormal tangent basis per point
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    d = points[nb] - points[idx, None]  # (M,k,3)
    a = np.stack([np.einsum("nkj,nj->nk", d, t1), np.einsum("nkj,nj->nk", d, t2)], axis=-1)
    b = intensity[nb] - intensity[idx, None]
    ata = np.einsum("nki,nkj->nij", a, a) + 1e-9 * np.eye(2)
    atb = np.einsum("nki,nk->ni", a, b)
    g2 = np.linalg.solve(ata, atb[..., None])[..., 0]
    out[idx] = g2[:, :1] * t1 + g2[:, 1:] * t2
    return out


def point_to_plane_information(matches: Matches, T_b_a: np.ndarray) -> np.ndarray:
    """Gauss-Newton information (6x6, [rot, trans]) of the point-to-plane residuals
    ``r = n_b . (T_b_a Exp(xi) p_a - q_b)`` for a right perturbation ``xi`` of ``T_b_a``.

    With ``m = R_b_a^T n_b`` (the normal in a's frame) the Jacobian row is
    ``[p_a x m, m]``. Weights are 1/sigma^2 of the D435 model; the whole matrix is divided by
    the residuals' variance factor chi^2/dof when that exceeds 1 (residuals larger than the
    noise model: sampling and registration error)."""
    if matches.residual.size < 6:
        return np.zeros((6, 6))
    m = matches.normals_b @ T_b_a[:3, :3]
    J = np.hstack([np.cross(matches.src, m), m])
    w = 1.0 / matches.sigma**2
    H = (J * w[:, None]).T @ J
    dof = max(matches.residual.size - 6, 1)
    chi2_dof = float(np.sum(w * matches.residual**2) / dof)
    return H / max(chi2_dof, 1.0)


def photometric_information(matches: Matches, src: VoxelLevel, tgt: VoxelLevel,
                            gradients_b: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    """Gauss-Newton information (6x6, [rot, trans], right perturbation of ``T_b_a``) of the
    colour residuals of colored ICP (Park et al. 2017):
    ``r = C(q) + d_q . (T_b_a Exp(xi) p - q) - C(p)`` with the target's tangent-plane
    gradient ``d_q``. With ``g = R_b_a^T d_q`` the Jacobian row is ``[p x g, g]``; the
    residual variance is taken from the residuals themselves (colours have no noise model)."""
    if matches.residual.size < 7:
        return np.zeros((6, 6))
    d_q = gradients_b[matches.tgt_index]
    p_b = transform_points(T_b_a, matches.src)
    r = (_intensity(tgt.colors[matches.tgt_index]) + np.einsum("ij,ij->i", d_q, p_b - matches.tgt)
         - _intensity(src.colors[matches.src_index]))
    variance = max(float(np.sum(r**2) / (r.size - 6)), 1e-12)
    g = d_q @ T_b_a[:3, :3]
    J = np.hstack([np.cross(matches.src, g), g])
    return J.T @ J / variance


def conditioning(information: np.ndarray, points_a: np.ndarray) -> float:
    """Smallest over largest eigenvalue of ``information`` (right perturbation of ``T_b_a``,
    [rot, trans]) re-expressed about the centroid ``c`` of the overlap ``points_a`` (a's frame)
    with rotations scaled by their RMS radius ``L``, so both blocks are in metres (Gelfand,
    Ikemoto, Rusinkiewicz, Levoy: "Geometrically Stable Sampling for the ICP Algorithm", 3DIM
    2003). Near 0: a direction the overlap does not constrain (a single plane, ...).

    With ``xi = M xi'``, ``xi' = [L omega, v + omega x c]``: ``M = [[I/L, 0], [[c]x / L, I]]``
    and the normalised information is ``M^T I M``."""
    if points_a.shape[0] < 6 or not np.any(information):
        return 0.0
    c = points_a.mean(axis=0)
    L = float(np.sqrt(np.mean(np.sum((points_a - c) ** 2, axis=1)))) or 1.0
    M = np.eye(6)
    M[:3, :3] /= L
    M[3:, :3] = skew(c) / L
    ev = np.linalg.eigvalsh(M.T @ information @ M)
    return float(max(ev[0], 0.0) / ev[-1]) if ev[-1] > 0 else 0.0


# --------------------------------------------------------------------------- noise model
@dataclass(frozen=True)
class _WhitenedRows:
    """Residuals of a registration divided by their sigma, with their Jacobian rows (right
    perturbation of ``T_b_a``, [rot, trans]) and the surface patch each one comes from."""

    J: np.ndarray  # (M,6)
    r: np.ndarray  # (M,)
    patch: np.ndarray  # (M,) patch index in [0, n_patches)
    n_patches: int
    n_geometric: int  # the first n_geometric rows are point-to-plane, the rest photometric
    # d(whitened residual)/d(parameter) (M,P) and the parameters' variances (P,): the
    # intrinsics the two clouds were back-projected with, and the disparity offsets their
    # depths keep, are uncertain (None: exact)
    D: np.ndarray | None = None
    lens_variance: np.ndarray | None = None
    # D's first n_disparity columns are the clouds' disparity offsets (unit variance): kept out
    # of the information (the gates judge a pair by its own noise), given by disparity_covariance
    n_disparity: int = 0


def back_projection_jacobian(points: np.ndarray, intr: CameraIntrinsics,
                             names: list[str]) -> np.ndarray:
    """d p / d theta ``(N,3,P)`` of points ``p = z * ray(u, v)`` back-projected from fixed
    pixels at fixed depth, for the intrinsics ``names`` (fx fy cx cy k1 k2 p1 p2 k3; a
    fisheye's k1..k4 exactly, through :meth:`CameraIntrinsics.ray_coefficient_jacobian`), to
    first order in the distortion: a pixel's normalised coordinates are
    ``x = (u - cx) / fx - delta_x(x, y)`` with the Brown-Conrady offset ``delta``, so e.g.
    ``dX/dfx = -X / fx``, ``dX/dcx = -Z / fx`` and ``d(X, Y)/dk1 = -r^2 (X, Y)``."""
    p = np.asarray(points, dtype=float)
    X, Y, Z = p[:, 0], p[:, 1], p[:, 2]
    x, y = X / Z, Y / Z
    r2 = x * x + y * y
    zero = np.zeros_like(X)
    cols = {
        "fx": (-X / intr.fx, zero), "fy": (zero, -Y / intr.fy),
        "cx": (-Z / intr.fx, zero), "cy": (zero, -Z / intr.fy),
        "k1": (-X * r2, -Y * r2), "k2": (-X * r2**2, -Y * r2**2),
        "k3": (-X * r2**3, -Y * r2**3),
        "p1": (-Z * 2 * x * y, -Z * (r2 + 2 * y * y)),
        "p2": (-Z * (r2 + 2 * x * x), -Z * 2 * x * y),
    }
    if intr.lens == FISHEYE:  # its k1..k4: the exact ray derivative of the camera model
        J = intr.ray_coefficient_jacobian(np.column_stack([x, y]))
        cols |= {n: (Z * J[:, 0, k], Z * J[:, 1, k])
                 for k, n in enumerate(intr.coefficient_names)}
    out = np.zeros((p.shape[0], 3, len(names)))
    for k, name in enumerate(names):
        out[:, 0, k], out[:, 1, k] = cols[name]
    return out


Lens = tuple[CameraIntrinsics, dict[str, float]]


def _lens_columns(v_b: np.ndarray, T_b_a: np.ndarray, src: np.ndarray, tgt: np.ndarray,
                  lenses: tuple[Lens, Lens]) -> np.ndarray:
    """d r / d theta of residuals ``r = v_b . (T_b_a p_a - q_b) + ...`` (``v_b``: the target
    normal, or the colour gradient) for the uncertain intrinsics of a, then of b."""
    (intr_a, var_a), (intr_b, var_b) = lenses
    cols = []
    if var_a:
        v_a = v_b @ T_b_a[:3, :3]
        cols.append(np.einsum("ij,ijk->ik", v_a, back_projection_jacobian(src, intr_a,
                                                                           list(var_a))))
    if var_b:
        cols.append(-np.einsum("ij,ijk->ik", v_b, back_projection_jacobian(tgt, intr_b,
                                                                            list(var_b))))
    return np.hstack(cols) if cols else np.zeros((src.shape[0], 0))


def _disparity_columns(v: np.ndarray, points: np.ndarray, moment: DisparityMoment,
                       ) -> np.ndarray:
    """d r / d u (M,6) of residuals ``r = v . p + ...`` (``p``: a cloud's points in its own
    frame) for the disparity offset of ``moment`` in unit-variance coordinates ``u`` (the
    coefficients ``L u``, ``L L^T`` their second moment): each point moves along its ray by
    its relative depth error ``z delta(x, y) / (f B)``."""
    z = points[:, 2]
    x, y = points[:, 0] / z, points[:, 1] / z
    basis = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    along = np.einsum("ij,ij->i", v, points) * z / moment.focal_baseline_px_m
    w, V = np.linalg.eigh(0.5 * (moment.second_moment + moment.second_moment.T))
    return (along[:, None] * basis) @ (V * np.sqrt(np.clip(w, 0.0, None)))


def whitened_rows(matches: Matches, T_b_a: np.ndarray, patch_m: float,
                  colour: tuple[VoxelLevel, VoxelLevel, np.ndarray] | None = None,
                  free_scale: tuple[bool, bool] = (False, False),
                  lenses: tuple[Lens, Lens] | None = None,
                  disparity: tuple[DisparityMoment | None, DisparityMoment | None] = (None, None),
                  ) -> _WhitenedRows:
    """Point-to-plane residuals over their noise-model sigma (:func:`nearest_matches`), and, with
    ``colour = (src, tgt, gradients_b)``, the photometric residuals of colored ICP over their
    RMS (colour has no noise model: its variance comes from the residuals). Rows are grouped
    by the ``patch_m`` voxel of their source point.

    ``free_scale`` adds a column per camera (a, b) whose depth scale is unknown: the
    derivative of the residual for ``p_a -> (1 + d_a) p_a`` (``m . p_a``) or
    ``q_b -> (1 + d_b) q_b`` (``-n_b . q_b``).

    ``lenses`` ``((intrinsics_a, variance_a), (intrinsics_b, variance_b))``: each camera's
    intrinsics and the variances of those that were estimated (name -> variance; empty:
    exact); their derivatives (:func:`back_projection_jacobian`) become ``D`` for
    :func:`noise_model_information`. So do, with ``disparity``, the disparity offsets each
    cloud's depths keep (:func:`_disparity_columns`, unit variance each)."""
    lenses = lenses if lenses is not None and (lenses[0][1] or lenses[1][1]) else None
    m = matches.normals_b @ T_b_a[:3, :3]
    cols = [np.cross(matches.src, m), m]
    if free_scale[0]:
        cols.append(np.einsum("ij,ij->i", m, matches.src)[:, None])
    if free_scale[1]:
        cols.append(-np.einsum("ij,ij->i", matches.normals_b, matches.tgt)[:, None])
    J = np.hstack(cols) / matches.sigma[:, None]
    r = matches.residual / matches.sigma

    def nuisance(v_b: np.ndarray) -> np.ndarray:  # D's columns for residuals along v_b
        out = [_disparity_columns(v, p, d) for v, p, d in (
            (v_b @ T_b_a[:3, :3], matches.src, disparity[0]),
            (-v_b, matches.tgt, disparity[1])) if d is not None]
        if lenses is not None:
            out.append(_lens_columns(v_b, T_b_a, matches.src, matches.tgt, lenses))
        return np.hstack(out)

    n_disparity = 6 * sum(d is not None for d in disparity)
    has_d = lenses is not None or n_disparity > 0
    D = nuisance(matches.normals_b) / matches.sigma[:, None] if has_d else None
    n_geo = r.size
    if colour is not None and r.size >= 7:
        src, tgt, gradients_b = colour
        d_q = gradients_b[matches.tgt_index]
        p_b = transform_points(T_b_a, matches.src)
        rc = (_intensity(tgt.colors[matches.tgt_index])
              + np.einsum("ij,ij->i", d_q, p_b - matches.tgt)
              - _intensity(src.colors[matches.src_index]))
        sigma_c = max(float(np.sqrt(np.mean(rc**2))), 1e-6)
        g = d_q @ T_b_a[:3, :3]
        cols = [np.cross(matches.src, g), g]
        if free_scale[0]:
            cols.append(np.einsum("ij,ij->i", g, matches.src)[:, None])
        if free_scale[1]:
            cols.append(-np.einsum("ij,ij->i", d_q, matches.tgt)[:, None])
        J = np.vstack([J, np.hstack(cols) / sigma_c])
        r = np.concatenate([r, rc / sigma_c])
        if D is not None:
            D = np.vstack([D, nuisance(d_q) / sigma_c])
    variance = (np.array([1.0] * n_disparity + ([*lenses[0][1].values(),
                                                 *lenses[1][1].values()] if lenses else []),
                         dtype=float) if has_d else None)
    if n_geo == 0:
        return _WhitenedRows(np.zeros((0, J.shape[1])), np.zeros(0), np.zeros(0, int), 0, 0)
    _, patch = np.unique(voxel_keys(matches.src, patch_m), return_inverse=True)
    patch = patch.ravel()
    n_patches = int(patch.max()) + 1
    # a photometric row belongs to the patch of its point-to-plane row
    return _WhitenedRows(J, r, np.tile(patch, r.size // n_geo), n_patches, n_geo, D, variance,
                         n_disparity)


def noise_model_information(rows: _WhitenedRows) -> np.ndarray:
    """Information (6x6) of a registration from the depth noise model and its residuals.

    With whitened rows ``J_i``, ``r_i`` (:func:`whitened_rows`) the Gauss-Newton information
    ``H = sum J_i^T J_i`` is the inverse covariance of the estimate only if the residuals are
    independent with unit variance. They are neither: the normals, the voxel means and the
    differences between two cameras' samplings of a surface make residuals of one surface
    patch err together. The estimate's covariance is therefore the cluster-robust sandwich
    (Liang & Zeger 1986; White 1980)::

        Cov = H^-1 M H^-1,   M = G/(G-1) sum_k g_k g_k^T,   g_k = sum_{i in patch k} J_i^T r_i

    over the G patches. If the noise model held exactly and residuals were independent,
    E[M] = H and Cov = H^-1; residuals larger than the model grow M by their variance factor,
    and residuals correlated within a patch by its effective size; residuals smaller than the
    model (nearest-neighbour matching picks the closest noisy point, so the whitened
    point-to-plane residuals' mean square ``s^2`` is below 1; measured: docs/depth.md) do not
    make the estimate better than the noise allows: M is divided by ``min(s^2, 1)``. The
    per-row meat ``sum (r_i J_i)^T (r_i J_i)`` over G is added to M so that a direction no
    patch's score happened to span keeps a finite variance.

    Intrinsics that were estimated (``rows.D`` past its disparity columns,
    ``rows.lens_variance``) move every point of a cloud together, so their error does not
    average out over points: the estimate moves by ``S dtheta`` with ``S = -H^-1 J^T D`` (the
    Gauss-Newton step for residuals changed by ``D dtheta``), which adds ``S diag(var) S^T`` to
    ``Cov``. The result is the inverse of ``Cov``'s pose block. The disparity offsets the
    clouds keep do the same, but are left out here (:func:`disparity_covariance`)."""
    k = rows.J.shape[1]
    if rows.n_geometric < k or rows.n_patches < 2:
        return np.zeros((6, 6))
    H = rows.J.T @ rows.J
    scores = np.zeros((rows.n_patches, k))
    np.add.at(scores, rows.patch, rows.J * rows.r[:, None])
    G = rows.n_patches
    row_scores = rows.J * rows.r[:, None]
    M = G / (G - 1) * scores.T @ scores + row_scores.T @ row_scores / G
    # nearest-neighbour correspondences make residuals look smaller than the noise they carry
    # (each point takes the closest of the other cloud's noisy points): a whitened residual's
    # variance is at least the noise model's, 1
    s2 = float(np.mean(rows.r[: rows.n_geometric] ** 2))
    M = M / min(max(s2, 1e-6), 1.0)
    try:
        H_inv = np.linalg.inv(H)
        cov = H_inv @ M @ H_inv
        k0 = rows.n_disparity  # the lens's columns of D follow the disparity offsets'
        if rows.D is not None and rows.lens_variance is not None and rows.D.shape[1] > k0:
            S = H_inv @ (rows.J.T @ rows.D[:, k0:])
            cov = cov + (S * rows.lens_variance[k0:]) @ S.T
        # columns beyond the pose (free depth scales) are marginalised: pose block of Cov
        info = np.linalg.inv(cov[:6, :6])
    except np.linalg.LinAlgError:
        return np.zeros((6, 6))
    return 0.5 * (info + info.T)


def disparity_covariance(rows: _WhitenedRows) -> np.ndarray | None:
    """The covariance (6x6, pose block) the clouds' disparity offsets add to a registration
    (``rows.D``'s first ``rows.n_disparity`` columns, unit variance each): every point of a
    cloud moves with its offset, so the estimate moves by ``S u`` with ``S = -H^-1 J^T D``,
    which nothing averages out. None without them (or a singular ``H``)."""
    if rows.D is None or not rows.n_disparity or rows.n_geometric < rows.J.shape[1]:
        return None
    try:
        S = np.linalg.solve(rows.J.T @ rows.J, rows.J.T @ rows.D[:, :rows.n_disparity])
    except np.linalg.LinAlgError:
        return None
    C = S[:6] @ S[:6].T
    return 0.5 * (C + C.T)
