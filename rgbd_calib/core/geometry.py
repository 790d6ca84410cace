"""Rigid-body helpers on 4x4 homogeneous matrices (pure numpy).

Convention (docs/formats.md): ``T_a_b`` maps points from frame ``b`` into frame ``a``,
``p_a = T_a_b @ p_b``; composition cancels inner names, ``T_a_c = T_a_b @ T_b_c``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def make_transform(R: ArrayLike, t: ArrayLike) -> Array:
    """``T_a_b`` (4x4) from rotation ``R_a_b`` (3x3) and translation ``t_a_b`` (3,) in metres."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_transform(T_a_b: ArrayLike) -> Array:
    """Return ``T_b_a`` for a rigid ``T_a_b`` (4x4), using R^T instead of a general inverse."""
    T_a_b = np.asarray(T_a_b, dtype=float)
    R = T_a_b[:3, :3]
    T_b_a = np.eye(4)
    T_b_a[:3, :3] = R.T
    T_b_a[:3, 3] = -R.T @ T_a_b[:3, 3]
    return T_b_a


def transform_points(T_a_b: ArrayLike, points_b: ArrayLike) -> Array:
    """Map points ``(N,3)`` in frame b to frame a."""
    T_a_b = np.asarray(T_a_b, dtype=float)
    points_b = np.asarray(points_b, dtype=float)
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def move_rows(points: ArrayLike, moves) -> Array:
    """A copy of ``points`` ``(N,3)`` with each ``(rows, T)`` of ``moves`` mapping its rows
    (a boolean mask or indices) by the transform ``T`` (4x4); e.g. a target's faces moved to
    where a self-calibration puts them."""
    P = np.array(points, dtype=float)
    for rows, T in moves:
        P[rows] = transform_points(T, P[rows])
    return P


def skew(v: ArrayLike) -> Array:
    x, y, z = np.asarray(v, dtype=float).reshape(3).tolist()
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def adjoint(T_a_b: ArrayLike) -> Array:
    """Adjoint ``(6,6)`` of a rigid ``T_a_b`` (4x4) in GTSAM's ``Pose3::AdjointMap``
    convention, twists ordered ``[omega (rad), v (m)]``: ``[[R, 0], [[t]x R, R]]``, so that
    ``T Exp(xi) = Exp(adjoint(T) xi) T`` (a right perturbation in b's frame as a left one in
    a's frame)."""
    T_a_b = np.asarray(T_a_b, dtype=float)
    R, t = T_a_b[:3, :3], T_a_b[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = skew(t) @ R
    return A


def rotvec_to_matrix(rotvec: ArrayLike) -> Array:
    """Rodrigues' formula: rotation vector (axis * angle, radians) -> 3x3 rotation."""
    w = np.asarray(rotvec, dtype=float).reshape(3)
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3) + skew(w)
    K = skew(w / theta)
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def pose_after_twist(T_a_b: ArrayLike, v_mps: ArrayLike, w_radps: ArrayLike,
                     tau_s: float, a_mps2: ArrayLike | None = None,
                     alpha_radps2: ArrayLike | None = None) -> Array:
    """``T_a_b`` (4x4, metres) ``tau_s`` seconds later under the constant twist ``v_mps``,
    ``w_radps`` (both in frame ``a``; rotation about ``b``'s origin):
    ``[Exp_SO3(w tau) R | p + v tau]`` (docs/conventions.md, "Time"). With the constant
    accelerations ``a_mps2`` and ``alpha_radps2`` (frame ``a``; ``alpha`` parallel to ``w``, so
    the turn keeps its axis and the exponent is exact):
    ``[Exp_SO3(w tau + alpha tau^2 / 2) R | p + v tau + a tau^2 / 2]``. With a zero ``tau_s``
    or motion, ``T_a_b`` itself."""
    v, w = np.asarray(v_mps, float), np.asarray(w_radps, float)
    a = np.zeros(3) if a_mps2 is None else np.asarray(a_mps2, float)
    alpha = np.zeros(3) if alpha_radps2 is None else np.asarray(alpha_radps2, float)
    if tau_s == 0 or not (np.any(v) or np.any(w) or np.any(a) or np.any(alpha)):
        return T_a_b
    T_a_b = np.asarray(T_a_b, dtype=float)
    half = 0.5 * tau_s * tau_s
    R = rotvec_to_matrix(w * tau_s + alpha * half) @ T_a_b[:3, :3]
    return make_transform(R, T_a_b[:3, 3] + v * tau_s + a * half)


def matrix_to_rotvec(R: ArrayLike) -> Array:
    """Inverse of :func:`rotvec_to_matrix`, stable near 0 and pi (via the quaternion)."""
    q = matrix_to_quaternion_xyzw(R)
    v, w = q[:3], q[3]
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return 2.0 * v
    angle = 2.0 * np.arctan2(s, w)
    return v / s * angle


def quaternion_xyzw_to_matrix(q: ArrayLike) -> Array:
    """Unit quaternion ``[x, y, z, w]`` -> 3x3 rotation (normalises its input)."""
    x, y, z, w = np.asarray(q, dtype=float).reshape(4) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion_xyzw(R: ArrayLike) -> Array:
    """3x3 rotation -> unit quaternion ``[x, y, z, w]`` with ``w >= 0`` (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def rotation_angle_deg(R: ArrayLike) -> float:
    """Angle (degrees) of a rotation matrix, robust to round-off."""
    c = (np.trace(np.asarray(R, dtype=float)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def transform_error(T_est: ArrayLike, T_true: ArrayLike) -> tuple[float, float]:
    """Rotation error (deg) and translation error (mm) between two ``T_a_b`` of the same frames."""
    T_est = np.asarray(T_est, dtype=float)
    T_true = np.asarray(T_true, dtype=float)
    dR = T_est[:3, :3] @ T_true[:3, :3].T
    return rotation_angle_deg(dR), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) * 1000.0)


def covariance_sigmas(covariance: ArrayLike) -> tuple[float, float]:
    """1-sigma rotation (deg) and translation (mm) of a 6x6 pose covariance in GTSAM order
    ``[rot (rad), trans (m)]``: the roots of the traces of its rotation and translation blocks
    (all three axes together, as ``sigma_rotation_deg`` / ``sigma_translation_mm`` of the
    results); NaN in, NaN out."""
    C = np.asarray(covariance, dtype=float)
    return (float(np.degrees(np.sqrt(max(np.trace(C[:3, :3]), 0.0)))),
            float(1000.0 * np.sqrt(max(np.trace(C[3:, 3:]), 0.0))))


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> Array:
    """``T_world_cam`` for an OpenCV optical camera (x right, y down, z forward) at ``eye``
    looking at ``target``; ``up`` is the world direction that appears upwards in the image."""
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.column_stack([x, y, z]), eye)


def orthonormalize(R: ArrayLike) -> Array:
    """Nearest rotation matrix (SVD projection onto SO(3))."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def is_rigid(T: ArrayLike, atol: float = 1e-6) -> bool:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.allclose(R @ R.T, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1.0) < atol
        and np.allclose(T[3], [0, 0, 0, 1], atol=atol)
    )
