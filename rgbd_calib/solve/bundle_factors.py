"""The bundle adjustment's view factors: projection, Jacobians and the per-marker robust kernel.

One GTSAM ``CustomFactor`` per camera view holds all its markers (:func:`view_factor`); with
refined intrinsics the board points are projected through the full camera model onto the raw
pixels (:func:`view_factor_intrinsics`), with board self-calibration the markers of a face move
with that face's pose (:func:`_view_factor_faces`). Poses are perturbed on the right,
``T <- T Exp([w, v])`` (GTSAM's Pose3, rotation first). Used by :mod:`rgbd_calib.solve.bundle`.
"""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from ..core.camera import (
    DISTORTION_LENGTHS,
    DISTORTION_NAMES,
    FISHEYE,
    FISHEYE_NAMES,
    PINHOLE_NAMES,
    CameraIntrinsics,
    pinhole_pose_jacobian,
    project_pinhole,
)
from ..core.geometry import adjoint, invert_transform, make_transform, move_rows
from .corner_noise import CornerNoise


def project_board(T_ref_cam: np.ndarray, T_ref_board: np.ndarray, K: np.ndarray,
                  P_b: np.ndarray, jacobians: bool = True):
    """Pinhole projection of board points ``P_b`` (N,3) through T_ref_cam and T_ref_board.

    p_cam = T_ref_cam^-1 T_ref_board p_board = R_cb P_b + t_cb, projected by the camera model
    (:mod:`rgbd_calib.core.camera`; the pixels are already undistorted). Returns the pixels (N,2)
    and, with ``jacobians``, d(u,v)/dxi (N,2,6) for the camera and for the board, for right
    perturbations T <- T Exp([w, v]) (GTSAM's Pose3 convention, rotation first): J_cam is
    :func:`~rgbd_calib.core.camera.pinhole_pose_jacobian` (dp_cam/dxi_cam = [[p_cam]x, -I]) and,
    as Exp(-xi) T_cb = T_cb Exp(-Ad(T_cb^-1) xi), the board Jacobian is
    J_board = -J_cam Ad(T_cb) (equal to d(u,v)/dp_cam R_cb [-[P_b]x, I])."""
    R_rc, t_rc = T_ref_cam[:3, :3], T_ref_cam[:3, 3]
    R_cb = R_rc.T @ T_ref_board[:3, :3]
    t_cb = R_rc.T @ (T_ref_board[:3, 3] - t_rc)
    p = P_b @ R_cb.T + t_cb  # (N,3) camera frame
    fx, fy = K[0, 0], K[1, 1]
    uv = project_pinhole(p, fx, fy, K[0, 2], K[1, 2])
    if not jacobians:
        return uv, None, None
    J_cam = pinhole_pose_jacobian(p, fx, fy)
    J_board = J_cam @ -adjoint(make_transform(R_cb, t_cb))
    return uv, J_cam, J_board


def as_noise(sigma: float | CornerNoise) -> CornerNoise:
    """A view factor's corner noise: a :class:`~rgbd_calib.solve.corner_noise.CornerNoise`, or
    a sigma (px) every corner has independently."""
    return sigma if isinstance(sigma, CornerNoise) else CornerNoise(float(sigma))


def _robust_weight_loss(kind: str, k: float, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weight w(d) and loss rho(d) of GTSAM's M-estimators at whitened norms ``d`` (vector).

    Huber: w = 1 for d <= k else k/d; rho = d^2/2 for d <= k else k (d - k/2).
    Cauchy: w = k^2 / (k^2 + d^2); rho = k^2/2 log(1 + d^2/k^2). 'none': w = 1, rho = d^2/2."""
    if kind == "huber":
        small = d <= k
        w = np.where(small, 1.0, k / np.where(small, 1.0, d))
        rho = np.where(small, d * d / 2, k * (d - k / 2))
    elif kind == "cauchy":
        k2 = k * k
        w = k2 / (k2 + d * d)
        rho = 0.5 * k2 * np.log(1.0 + d * d / k2)
    else:
        w, rho = np.ones_like(d), d * d / 2
    return w, rho


def robust_rows(r: np.ndarray, blocks, H: list[np.ndarray] | None, robust: str,
                 robust_k: float) -> np.ndarray:
    """The per-marker robust kernel of a view factor (see :func:`view_factor`).

    ``r`` (n,8) whitened residuals of n markers; ``blocks()`` the whitened Jacobians
    (8n, d_k) of the factor's keys, called only when ``H`` is given (a linearisation); they
    are written into ``H`` scaled by sqrt(w(d_m)) row by row. Returns the factor's error."""
    if robust not in ("huber", "cauchy"):
        if H is not None:
            for k, J in enumerate(blocks()):
                H[k] = J
        return r.reshape(-1)
    d = np.sqrt(np.einsum("ij,ij->i", r, r))
    w, rho = _robust_weight_loss(robust, robust_k, d)
    if H is None:
        scale = np.sqrt(2.0 * rho) / np.where(d > 0, d, 1.0)
        return (r * np.where(d > 0, scale, 1.0)[:, None]).reshape(-1)
    sw = np.repeat(np.sqrt(w), 8)[:, None]
    for k, J in enumerate(blocks()):
        H[k] = J * sw
    return r.reshape(-1) * sw[:, 0]


def face_transform(X: np.ndarray, A: np.ndarray | None) -> np.ndarray:
    """The board-frame move ``C = A X A^-1`` of a face whose correction ``X`` is expressed in
    the frame ``A`` (a multi-face target's nominal face pose); ``X`` itself when ``A`` is None
    (the back sheet's ``T_front_back``, a board-frame transform)."""
    return X if A is None else A @ X @ invert_transform(A)


def _back_sheet_jacobian(J_board: np.ndarray, back: np.ndarray,
                         T_front_back: np.ndarray) -> np.ndarray:
    """d(u,v)/dxi (N,2,6) of the back-sheet pose from the board pose's ``J_board``: with
    ``T_front_back <- T_front_back Exp(xi)``, ``T_ref_board T_front_back Exp(xi) =
    T_ref_board Exp(Ad(T_front_back) xi) T_front_back``, so J = J_board Ad(T_front_back) on
    the back-face rows and 0 on the front-face ones."""
    J = np.zeros_like(J_board)
    J[back] = J_board[back] @ adjoint(T_front_back)
    return J


def _face_jacobian(J_board: np.ndarray, rows: np.ndarray, X: np.ndarray,
                   A: np.ndarray | None) -> np.ndarray:
    """d(u,v)/dxi (N,2,6) of a face's correction ``X`` (``X <- X Exp(xi)``, expressed in frame
    ``A``): ``T_ref_board A X Exp(xi) A^-1 = T_ref_board Exp(Ad(A X) xi) C``, so J = J_board
    Ad(A X) on the face's rows (:func:`_back_sheet_jacobian` when ``A`` is None)."""
    return _back_sheet_jacobian(J_board, rows, X if A is None else A @ X)


def view_factor(key_cam: int, key_board: int, K: np.ndarray, object_points: np.ndarray,
                corners_px: np.ndarray, sigma: float | CornerNoise, robust: str,
                robust_k: float,
                moving: list | None = None):
    """All markers of one camera view in one factor, each marker with its own robust kernel.

    It reproduces, marker by marker, what a per-marker ``Robust(kernel, Isotropic(8, sigma))``
    noise model does in GTSAM, so the optimiser sees the same cost and the same linear
    systems. For marker m, r_m = (uv_m - uv_m_meas) / sigma (8-vector, whitened), d_m = |r_m|:

    - cost: sum_m rho(d_m), GTSAM's ``Robust::loss``; the callback, called with ``H = None``
      for an error evaluation, returns r_m * sqrt(2 rho(d_m)) / d_m so that the factor's
      ``0.5 |e|^2`` under a unit noise model equals that sum;
    - linearisation (iteratively re-weighted least squares, GTSAM's ``Robust::WhitenSystem``):
      rows r_m and J_m / sigma scaled by sqrt(w(d_m)), with w the kernel weight at the
      current point; w = 1 and rho = d^2/2 without a kernel (the plain Gaussian graph).

    ``object_points`` (n,4,3), ``corners_px`` (n,4,2) undistorted pinhole pixels. The factor's
    ``unwhitenedError`` is therefore the loss-scaled whitened residual, not pixels.

    With ``moving`` (board self-calibration) the markers of each listed face are moved by that
    face's pose, a Pose3 variable (:func:`_view_factor_faces`)."""
    if moving:
        return _view_factor_faces(key_cam, key_board, moving, K, None, (),
                                  object_points, corners_px, sigma, robust, robust_k)
    n = len(object_points)
    measured = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    P_b = np.asarray(object_points, dtype=float).reshape(-1, 3)
    noise = as_noise(sigma)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None):
        uv, J_cam, J_board = project_board(values.atPose3(key_cam).matrix(),
                                      values.atPose3(key_board).matrix(), K, P_b, H is not None)
        r = noise.whiten((uv - measured).reshape(n, 8))
        return robust_rows(r, lambda: (noise.whiten_rows(J_cam.reshape(-1, 6)),
                                       noise.whiten_rows(J_board.reshape(-1, 6))),
                           H, robust, robust_k)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * n), [key_cam, key_board], error)


def lens_names(base: CameraIntrinsics, names: tuple[str, ...]) -> tuple[str, ...]:
    """The parameters ``names`` (the configuration's, in OpenCV's model) as ``base``'s lens
    model names them: the same for an OpenCV lens and for fisheye names (k1..k4); for a
    fisheye asked for OpenCV's coefficients (p1, p2, k5, ...: the configuration's default
    k1 k2 p1 p2 k3), its pinhole names and its four k1..k4."""
    if base.lens != FISHEYE:
        return tuple(names)
    pinhole = tuple(n for n in names if n in PINHOLE_NAMES)
    lens = tuple(n for n in names if n not in pinhole)
    return pinhole + (lens if set(lens) <= set(FISHEYE_NAMES) else FISHEYE_NAMES)


def with_parameters(base: CameraIntrinsics, names: tuple[str, ...],
                    x: np.ndarray) -> CameraIntrinsics:
    """``base`` with the parameters ``names`` set to ``x`` (distortion names index the lens
    model's coefficient list; OpenCV's is padded with zeros to hold the last name)."""
    names = lens_names(base, names)
    values = dict(zip(names, np.asarray(x, dtype=float).tolist()))
    dist = list(padded_distortion(base, names))
    coefficients = FISHEYE_NAMES if base.lens == FISHEYE else DISTORTION_NAMES
    for i, name in enumerate(coefficients[:len(dist)]):
        dist[i] = values.get(name, dist[i])
    return replace(base, fx=values.get("fx", base.fx), fy=values.get("fy", base.fy),
                   cx=values.get("cx", base.cx), cy=values.get("cy", base.cy),
                   distortion=tuple(dist))


def padded_distortion(base: CameraIntrinsics, names: tuple[str, ...]) -> tuple[float, ...]:
    """``base.distortion`` padded with zeros to OpenCV's next valid length (4, 5, 8, 12, 14)
    that holds every distortion coefficient of ``names`` (a fisheye's four as they are)."""
    if base.lens == FISHEYE:
        return tuple(base.distortion)
    need = max([DISTORTION_NAMES.index(n) + 1 for n in names if n in DISTORTION_NAMES]
               + [len(base.distortion)])
    length = next(n for n in DISTORTION_LENGTHS if n >= need)
    return tuple(base.distortion) + (0.0,) * (length - len(base.distortion))


def refined_model(base: CameraIntrinsics,
                  names: tuple[str, ...]) -> tuple[CameraIntrinsics, np.ndarray]:
    """``base`` with its distortion padded to hold every coefficient of ``names``
    (:func:`padded_distortion`), and the columns of ``names`` in its
    :meth:`~rgbd_calib.core.camera.CameraIntrinsics.intrinsics_jacobian`: what a view factor
    that refines those parameters projects through."""
    names = lens_names(base, names)
    padded = replace(base, distortion=padded_distortion(base, names))
    return padded, np.array([padded.parameter_names.index(nm) for nm in names])


def project_board_full(T_ref_cam: np.ndarray, T_ref_board: np.ndarray, intr: CameraIntrinsics,
                       columns: np.ndarray | None, P_b: np.ndarray, jacobians: bool = True):
    """As :func:`project_board`, through the full camera model ``intr`` (distortion included):
    pixels (N,2) and, with ``jacobians``, d(u,v)/dxi (N,2,6) of the camera and of the board
    and d(u,v)/d(intrinsics) (N,2,len(columns)), ``columns`` indexing
    :meth:`~rgbd_calib.core.camera.CameraIntrinsics.intrinsics_jacobian`. The pose Jacobians are
    d(u,v)/dp_cam (``project_jacobian``) times dp_cam/dxi_cam = ``[[p_cam]x, -I]``, the board's
    as in :func:`project_board`."""
    R_rc, t_rc = T_ref_cam[:3, :3], T_ref_cam[:3, 3]
    R_cb = R_rc.T @ T_ref_board[:3, :3]
    t_cb = R_rc.T @ (T_ref_board[:3, 3] - t_rc)
    p = P_b @ R_cb.T + t_cb
    if not jacobians:
        return intr.project(p), None, None, None
    uv, J_point = intr.project_jacobian(p)
    dp_dxi = np.zeros((len(p), 3, 6))
    dp_dxi[:, 0, 1], dp_dxi[:, 0, 2] = -p[:, 2], p[:, 1]  # [p]x: Exp(-w) p = p + p x w
    dp_dxi[:, 1, 0], dp_dxi[:, 1, 2] = p[:, 2], -p[:, 0]
    dp_dxi[:, 2, 0], dp_dxi[:, 2, 1] = -p[:, 1], p[:, 0]
    dp_dxi[:, :, 3:] = -np.eye(3)
    J_cam = J_point @ dp_dxi
    J_board = J_cam @ -adjoint(make_transform(R_cb, t_cb))
    J_intr = intr.intrinsics_jacobian(p)[:, :, columns]
    return uv, J_cam, J_board, J_intr


def view_factor_intrinsics(key_cam: int, key_board: int, key_intr: int,
                           base: CameraIntrinsics, names: tuple[str, ...],
                           object_points: np.ndarray, corners_px: np.ndarray,
                           sigma: float | CornerNoise,
                           robust: str, robust_k: float, moving: list | None = None):
    """:func:`view_factor` with the camera's intrinsics as a third variable: a vector of the
    parameters ``names`` (the rest of ``base`` held), the board points projected through the
    full model (distortion included) onto the RAW detected pixels ``corners_px`` (n,4,2).
    Same per-marker robust kernel; Jacobians w.r.t. camera pose, board pose, intrinsics
    (and the face poses with ``moving``, :func:`_view_factor_faces`)."""
    if moving:
        return _view_factor_faces(key_cam, key_board, moving, None, (key_intr, base),
                                  names, object_points, corners_px, sigma, robust, robust_k)
    n = len(object_points)
    measured = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    P_b = np.asarray(object_points, dtype=float).reshape(-1, 3)
    noise = as_noise(sigma)
    padded, columns = refined_model(base, names)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None):
        intr = with_parameters(padded, names, values.atVector(key_intr))
        uv, J_cam, J_board, J_intr = project_board_full(
            values.atPose3(key_cam).matrix(), values.atPose3(key_board).matrix(), intr,
            columns, P_b, H is not None)
        r = noise.whiten((uv - measured).reshape(n, 8))
        return robust_rows(r, lambda: (noise.whiten_rows(J_cam.reshape(-1, 6)),
                                       noise.whiten_rows(J_board.reshape(-1, 6)),
                                       noise.whiten_rows(J_intr.reshape(-1, len(columns)))),
                           H, robust, robust_k)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * n),
                              [key_cam, key_board, key_intr], error)


def _view_factor_faces(key_cam: int, key_board: int, moving: list,
                       K: np.ndarray | None, intr: tuple, names: tuple[str, ...],
                       object_points: np.ndarray, corners_px: np.ndarray,
                       sigma: float | CornerNoise,
                       robust: str, robust_k: float):
    """The view factor with face poses as variables (board self-calibration): ``moving`` lists
    ``(key, flags, A)`` per face seen, ``flags`` (n,) marking its markers, ``A`` the frame its
    correction ``X`` (Pose3 ``key``) is expressed in (None: the board frame, the back sheet's
    ``T_front_back``); a flagged marker's corners are ``A X A^-1 @ object_point``
    (:func:`rgbd_calib.core.geometry.move_rows`). Pinhole ``K`` (fixed intrinsics), or
    ``intr = (key_intr, base)`` for refined ones (as :func:`view_factor_intrinsics`). Keys:
    camera, board, [intrinsics,] the faces; same per-marker robust kernel."""
    n = len(object_points)
    measured = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    P_file = np.asarray(object_points, dtype=float).reshape(-1, 3)
    faces = [(key, np.repeat(np.asarray(flags, dtype=bool), 4), A) for key, flags, A in moving]
    noise = as_noise(sigma)
    keys = [key_cam, key_board]
    if intr:
        key_intr, base = intr
        padded, columns = refined_model(base, names)
        keys.append(key_intr)
    keys += [key for key, _, _ in faces]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None):
        X = [values.atPose3(key).matrix() for key, _, _ in faces]
        P_b = move_rows(P_file, [(rows, face_transform(x, A))
                                   for (_, rows, A), x in zip(faces, X)])
        T_cam, T_board = values.atPose3(key_cam).matrix(), values.atPose3(key_board).matrix()
        if intr:
            model = with_parameters(padded, names, values.atVector(key_intr))
            uv, J_cam, J_board, J_intr = project_board_full(T_cam, T_board, model, columns, P_b,
                                                       H is not None)
        else:
            uv, J_cam, J_board = project_board(T_cam, T_board, K, P_b, H is not None)
        r = noise.whiten((uv - measured).reshape(n, 8))

        def blocks():
            out = [noise.whiten_rows(J_cam.reshape(-1, 6)),
                   noise.whiten_rows(J_board.reshape(-1, 6))]
            if intr:
                out.append(noise.whiten_rows(J_intr.reshape(-1, len(columns))))
            out += [noise.whiten_rows(_face_jacobian(J_board, rows, x, A).reshape(-1, 6))
                    for (_, rows, A), x in zip(faces, X)]
            return out

        return robust_rows(r, blocks, H, robust, robust_k)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * n), keys, error)

