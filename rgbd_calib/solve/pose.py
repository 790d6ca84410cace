"""Per-view board pose by PnP, with its covariance and quality gates.

One image's marker detections become ``T_cam_board`` (4x4, metres; maps board-frame points into
the camera's optical frame) with a 6x6 covariance in GTSAM's order and frame: rotation (rad)
then translation (m), in the board (body) frame, i.e. for the right perturbation
``T_cam_board @ Exp(xi)``, ``xi = [omega, v]`` (``gtsam.Pose3.retract``). That is what
``noiseModel.Gaussian.Covariance`` of a ``BetweenFactorPose3``/``PriorFactorPose3`` expects.

Pipeline per view: physically impossible detections out (markers of both faces at once: the
minority face is dropped), planar PnP (IPPE: both solutions of the planar ambiguity and their
errors), Levenberg-Marquardt refinement, per-marker outlier rejection (a stray marker carrying
a board id is far off the pose of the others), gates, then the covariance
``sigma^2 (J^T J)^-1`` with ``J`` the Jacobian of the reprojection residuals, plus a per-view
model-error floor (:func:`model_error_covariance`, ``PoseConfig.model_error_px``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..core.camera import FISHEYE, CameraIntrinsics
from ..core.config import CalibrationConfig, PoseConfig
from ..core.geometry import make_transform, rotation_angle_deg, rotvec_to_matrix, skew
from ..detect.markers import MarkerDetections
from ..model.board import Board
from ..model.results import PoseEdge
from ..model.rig import Rig


@dataclass(frozen=True, eq=False)
class BoardObservation:
    """The board's pose seen by one camera in one frame.

    ``T_cam_board`` maps board-frame points (metres) into the camera's optical frame.
    ``covariance`` is 6x6 ``[rot rad, trans m]`` in the board (body) frame (GTSAM's Pose3
    tangent). ``face`` is +1 (front), -1 (back) or 0 (both, only with ``allow_both_faces``); on
    a multi-face target the label of the one face seen, or 0 for several.
    ``ids``/``corners_px`` ``(N,4,2)``/``object_points`` ``(N,4,3)`` are the markers used;
    ``dropped`` lists markers left out and why (``outlier``, ``minority_face``, ``unrefined``).
    ``model_error_covariance`` is the per-view model-error floor included in ``covariance``
    (:func:`model_error_covariance`; None when ``PoseConfig.model_error_px`` is 0 or
    ``auto``); ``model_error_unit`` is that floor for a 1 px model error, not included (with
    ``auto`` the pose graph estimates the floor from the views and adds it).
    """

    camera: str
    frame: str
    T_cam_board: np.ndarray
    covariance: np.ndarray
    reprojection_rms_px: float
    n_markers: int
    face: int
    ids: np.ndarray
    corners_px: np.ndarray
    object_points: np.ndarray
    ambiguity_ratio: float
    sigma_px: float
    dropped: dict[str, list[int]] = field(default_factory=dict)
    model_error_covariance: np.ndarray | None = None
    model_error_unit: np.ndarray | None = None

    @property
    def sigma_rotation_deg(self) -> float:
        """Largest 1-sigma rotation about a single axis (degrees)."""
        return float(np.degrees(np.sqrt(np.linalg.eigvalsh(self.covariance[:3, :3]).max())))

    @property
    def sigma_translation_mm(self) -> float:
        """Largest 1-sigma translation along a single axis (mm)."""
        return float(1000.0 * np.sqrt(np.linalg.eigvalsh(self.covariance[3:, 3:]).max()))

    def to_dict(self) -> dict[str, Any]:
        return {
            "camera": self.camera,
            "frame": self.frame,
            "T_cam_board": np.asarray(self.T_cam_board, dtype=float).tolist(),
            "covariance": np.asarray(self.covariance, dtype=float).tolist(),
            "reprojection_rms_px": float(self.reprojection_rms_px),
            "n_markers": int(self.n_markers),
            "face": int(self.face),
            "ids": self.ids.astype(int).tolist(),
            "corners_px": self.corners_px.tolist(),
            "object_points": self.object_points.tolist(),
            "ambiguity_ratio": float(self.ambiguity_ratio),
            "sigma_px": float(self.sigma_px),
            "dropped": {k: [int(i) for i in v] for k, v in self.dropped.items()},
        }


# what a user does about each reason a view gave no pose (RejectedView.reason): for the
# console, the report and the error when no view is left
DROP_ADVICE = {
    "too_few_markers": "board too far, too oblique or half out of the image: bring it closer "
    "and turn it towards the camera",
    "reprojection_rms": "corners do not fit a pose: motion blur, wrong intrinsics or a bent "
    "board; hold the board still and check rig.yaml",
    "ambiguous": "planar flip ambiguity (small board seen face-on from far): tilt the board "
    "20-40 deg or bring it closer",
    "both_faces": "markers of both faces in one image: a wrong detection or a reflection",
    "face_away": "the pose shows the seen face turned away (a mirror solution): tilt the board "
    "more towards the camera",
    "outlier_markers": "a stray detection carrying a board id: check the background for "
    "printed markers",
    "pnp_failed": "PnP found no pose: check the board definition (--board)",
    "degenerate": "the markers seen constrain no pose (too few, in a line)",
}


@dataclass(frozen=True)
class RejectedView:
    """A view that gave no usable pose, and why (one short machine-readable reason)."""

    camera: str
    frame: str
    reason: str
    n_markers: int
    detail: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "camera": self.camera,
            "frame": self.frame,
            "reason": self.reason,
            "n_markers": int(self.n_markers),
            "detail": self.detail,
        }


# --------------------------------------------------------------------------- maths helpers
def se3_exp(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential of ``xi = [omega, v]`` (GTSAM's Pose3.Expmap order) as a 4x4."""
    xi = np.asarray(xi, dtype=float)
    omega, v = xi[:3], xi[3:]
    theta = float(np.linalg.norm(omega))
    W = skew(omega)
    if theta < 1e-3:  # Taylor series: the closed form cancels catastrophically here
        t2 = theta * theta
        a, b = 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    else:
        a = (1 - np.cos(theta)) / theta**2
        b = (theta - np.sin(theta)) / theta**3
    V = np.eye(3) + a * W + b * (W @ W)
    return make_transform(rotvec_to_matrix(omega), V @ v)


def _to_rvec_tvec(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rvec, _ = cv2.Rodrigues(np.asarray(T[:3, :3], dtype=float))
    return rvec.reshape(3), np.asarray(T[:3, 3], dtype=float).copy()


def _from_rvec_tvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))
    return make_transform(R, np.asarray(tvec, dtype=float).reshape(3))


def project_points(
    T_cam_board: np.ndarray, object_points: np.ndarray, intrinsics: CameraIntrinsics
) -> np.ndarray:
    """Pixels of board-frame points ``(...,3)`` (metres) seen through ``T_cam_board``
    (OpenCV camera model, intrinsics' distortion) as ``(...,2)``."""
    pts = np.asarray(object_points, dtype=float)
    if intrinsics.lens == FISHEYE:  # cv2.projectPoints is OpenCV's lens only
        T = np.asarray(T_cam_board, dtype=float)
        return intrinsics.project(pts @ T[:3, :3].T + T[:3, 3])
    rvec, tvec = _to_rvec_tvec(np.asarray(T_cam_board, dtype=float))
    uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, tvec, intrinsics.K, intrinsics.dist)
    return uv.reshape(*pts.shape[:-1], 2)  # projectPoints gives (M,1,2)


def reprojection_residuals(
    T_cam_board: np.ndarray,
    object_points: np.ndarray,
    corners_px: np.ndarray,
    intrinsics: CameraIntrinsics,
) -> np.ndarray:
    """Projected minus observed pixels, shape of ``corners_px`` (``(...,2)``).

    ``T_cam_board`` 4x4 maps the board-frame ``object_points`` ``(...,3)`` (metres) into the
    camera frame; ``corners_px`` are the matching detected pixels."""
    return project_points(T_cam_board, object_points, intrinsics) - np.asarray(corners_px, float)


def pose_jacobian(
    T_cam_board: np.ndarray,
    object_points: np.ndarray,
    intrinsics: CameraIntrinsics,
) -> np.ndarray:
    """``(2M,6)`` Jacobian of the projected pixels of ``M`` board points with respect to the
    right perturbation ``T_cam_board @ Exp(xi)``, ``xi = [omega (rad), v (m)]`` (the
    distortion model included), in closed form.

    ``T Exp(xi) P = R (P + omega x P + v) + t`` to first order, so ``dX/dxi = [-R [P]x, R]``
    for the camera-frame point ``X``; ``d pixel / dX`` is the derivative by the translation
    that ``cv2.projectPoints`` returns with the pixels (``X = R P + t``). One call for all
    points, instead of 12 projections by central differences (1.3 ms -> ~0.1 ms a view;
    the two agree to ~1e-9 relative, :func:`pose_jacobian_numeric`)."""
    pts = np.asarray(object_points, dtype=float).reshape(-1, 3)
    R = np.asarray(T_cam_board, dtype=float)[:3, :3]
    if intrinsics.lens == FISHEYE:
        _, d_pix_d_x = intrinsics.project_jacobian(pts @ R.T + np.asarray(T_cam_board)[:3, 3])
    else:
        rvec, tvec = _to_rvec_tvec(np.asarray(T_cam_board, dtype=float))
        _, d = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, tvec, intrinsics.K,
                                 intrinsics.dist)
        d_pix_d_x = d[:, 3:6].reshape(-1, 2, 3)  # columns: rvec, tvec, f, c, distortion
    P_x = np.cross(pts[:, None, :], np.eye(3)).transpose(0, 2, 1)  # [P]x: column k is P x e_k
    d_x_d_omega = -np.einsum("ij,njk->nik", R, P_x)
    J = np.empty((len(pts), 2, 6))
    J[:, :, :3] = d_pix_d_x @ d_x_d_omega
    J[:, :, 3:] = d_pix_d_x @ R
    return J.reshape(-1, 6)


def pose_jacobian_numeric(
    T_cam_board: np.ndarray,
    object_points: np.ndarray,
    intrinsics: CameraIntrinsics,
    step: float = 1e-6,
) -> np.ndarray:
    """:func:`pose_jacobian` by central differences of the projection (the reference the
    closed form is tested against)."""
    pts = np.asarray(object_points, dtype=float).reshape(-1, 3)
    J = np.zeros((2 * len(pts), 6))
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = step
        plus = project_points(T_cam_board @ se3_exp(xi), pts, intrinsics)
        minus = project_points(T_cam_board @ se3_exp(-xi), pts, intrinsics)
        J[:, i] = ((plus - minus) / (2 * step)).reshape(-1)
    return J


# --------------------------------------------------------------------------- PnP
def _solve(
    object_points: np.ndarray, image_points: np.ndarray, intrinsics: CameraIntrinsics, planar: bool
) -> tuple[np.ndarray, float, float] | None:
    """PnP on ``(P,3)``/``(P,2)`` points: ``(T_cam_board, ambiguity_ratio, angle_deg)`` or
    None; the ratio is IPPE's best/second reprojection error, the angle between the two
    solutions' rotations (0 without a second solution)."""
    obj = object_points.astype(np.float64).reshape(-1, 1, 3)
    img, K, dist = _cv_camera(image_points, intrinsics)
    flags = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_SQPNP
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, dist, flags=flags)
    except cv2.error:
        return None
    if not n:
        return None
    errs = np.asarray(errs, dtype=float).reshape(-1)
    order = np.argsort(errs)
    best = int(order[0])
    ratio, angle = 0.0, 0.0
    if n > 1:
        second = int(order[1])
        ratio = float(errs[best] / errs[second]) if errs[second] > 0 else 1.0
        R1, _ = cv2.Rodrigues(rvecs[best])
        R2, _ = cv2.Rodrigues(rvecs[second])
        angle = rotation_angle_deg(R1.T @ R2)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvecs[best].copy(),
                                      tvecs[best].copy())
    return _from_rvec_tvec(rvec, tvec), ratio, angle


def _cv_camera(image_points: np.ndarray, intrinsics: CameraIntrinsics):
    """``(pixels (P,1,2), K, distortion)`` for OpenCV's PnP: the pixels and the lens as they
    are for OpenCV's model; for another lens (fisheye) the pixels undistorted to the same
    ``K`` and no distortion (the bundle adjustment then fits the raw pixels through the
    lens)."""
    img = np.asarray(image_points, dtype=np.float64).reshape(-1, 2)
    if intrinsics.lens == FISHEYE:
        return intrinsics.undistort_pixels(img).reshape(-1, 1, 2), intrinsics.K, None
    return img.reshape(-1, 1, 2), intrinsics.K, intrinsics.dist


def _pose_covariance(
    J: np.ndarray, resid: np.ndarray, config: PoseConfig
) -> tuple[np.ndarray, float]:
    """6x6 covariance of the least-squares pose and the corner sigma it implies (px).

    With a fixed ``pixel_sigma_px``: ``sigma^2 (J^T J)^-1``. Otherwise the corner noise is
    estimated from the residuals ``(N,4,2)`` in two parts per marker: the marker's shift (the
    mean of its 4 corner residuals, 2 of its 8 degrees of freedom) and the rest (its size,
    rotation and shape). They differ: the edge fit's errors are mostly in a marker's size and
    shape (opposite edges move together with the fitted blur), which hardly move the board
    pose, while its shift, which the pose follows, holds ~5 % of the residual energy instead
    of the 25 % of independent noise; a single sigma from all residuals overstates the pose
    uncertainty ~2x. The covariance is the least-squares sandwich
    ``(J^T J)^-1 J^T S J (J^T J)^-1`` with ``S`` block-diagonal per marker,
    ``S = s_shift^2 P + s_rest^2 (I - P)``, ``P`` the projector on the marker's shift. The pose
    absorbs its 6 degrees of freedom from the shifts (``2N - 6`` remain), so with few markers
    ``s_shift^2`` is shrunk towards the all-residual ``RSS / (8N - 6)`` (conservative) with
    ``sigma_prior_dof`` pseudo degrees of freedom.
    """
    n = resid.shape[0]
    JtJ_inv = np.linalg.inv(J.T @ J)
    if config.pixel_sigma_px is not None:
        sigma = float(config.pixel_sigma_px)
        return sigma**2 * JtJ_inv, sigma
    floor = config.min_pixel_sigma_px**2
    shift = resid.mean(axis=1)  # (N,2)
    rest = resid - shift[:, None, :]
    var_all = float((resid**2).sum()) / max(8 * n - 6, 1)
    dof_shift = max(2 * n - 6, 0)
    nu = config.sigma_prior_dof  # shrink the shift variance towards the all-residual one
    var_shift = (4.0 * float((shift**2).sum()) + nu * var_all) / (dof_shift + nu)
    var_rest = float((rest**2).sum()) / (6 * n)
    var_shift, var_rest = max(var_shift, floor), max(var_rest, floor)
    # per marker, 8x8 over (corner, axis) flattened as corner*2 + axis
    P = np.kron(np.full((4, 4), 0.25), np.eye(2))
    S_marker = var_shift * P + var_rest * (np.eye(8) - P)
    Jm = J.reshape(n, 8, 6)
    middle = np.einsum("nai,ab,nbj->ij", Jm, S_marker, Jm)
    covariance = JtJ_inv @ middle @ JtJ_inv
    sigma = float(np.sqrt((2 * var_shift + 6 * var_rest) / 8.0))  # mean per-coordinate sigma
    return 0.5 * (covariance + covariance.T), sigma


def model_error_covariance(
    J: np.ndarray, corners_px: np.ndarray, sigma_model_px: float
) -> np.ndarray:
    """6x6 pose covariance (``[rot rad, trans m]``, board frame) from a systematic pixel error
    shared by all corners of one view, propagated through the least-squares PnP.

    The shared error is the first-order (Taylor) expansion of any smooth pixel-error field
    over the view's extent: a common 2-D affine map of the view's corners, ``delta_k = t +
    L (p_k - c) / r`` with ``c`` the corners' centroid and ``r`` their RMS distance from it
    (px), its 6 coefficients (offset ``t``, linear part ``L``) independent with sigma
    ``sigma_model_px`` (so a linear term moves a corner at distance ``r`` by that many px).
    That covers the misfits no corner-noise estimate sees, because the pose absorbs most of
    them: intrinsics or distortion slightly off across the board (an offset plus a scale or
    stretch), a marker print or detector bias that makes every marker look larger, a rolling
    shutter's shear on a moving board. The pose moves by ``-G delta``,
    ``G = (J^T J)^-1 J^T``, so the covariance is ``sigma^2 (G A)(G A)^T`` with ``A`` the
    ``(2M,6)`` basis of the affine map. ``J`` is the ``(2M,6)`` reprojection Jacobian
    (:func:`pose_jacobian`), ``corners_px`` the matching ``(...,2)`` pixels."""
    pts = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    d = pts - pts.mean(axis=0)
    radius = float(np.sqrt((d**2).sum(axis=1).mean())) or 1.0
    d = d / radius
    A = np.zeros((2 * len(pts), 6))
    A[0::2, 0] = 1.0  # offset u
    A[1::2, 1] = 1.0  # offset v
    A[0::2, 2], A[0::2, 3] = d[:, 0], d[:, 1]  # u from (du, dv)
    A[1::2, 4], A[1::2, 5] = d[:, 0], d[:, 1]  # v from (du, dv)
    GA = np.linalg.solve(J.T @ J, J.T @ A)
    cov = sigma_model_px**2 * (GA @ GA.T)
    return 0.5 * (cov + cov.T)


def _faces_camera(T_cam_board: np.ndarray, object_points: np.ndarray, face: int,
                  normal: np.ndarray | None = None) -> bool:
    """True when the camera is on the outer side of the seen face (else the pose is a
    mirror solution: the markers could not be seen from there); ``normal`` the face's outward
    normal in the board frame (default: ``(0, 0, face)``, a flat board's two faces)."""
    if face == 0:
        return True
    if normal is None:
        normal = np.array([0.0, 0.0, float(face)])
    normal_cam = T_cam_board[:3, :3] @ normal
    centre_cam = T_cam_board[:3, :3] @ object_points.reshape(-1, 3).mean(0) + T_cam_board[:3, 3]
    return bool(normal_cam @ centre_cam < 0.0)


def _solve_faces(
    object_points: np.ndarray, corners_px: np.ndarray, faces: np.ndarray,
    intrinsics: CameraIntrinsics,
) -> tuple[np.ndarray, float, float] | None:
    """PnP of a view that sees several non-coplanar faces of a multi-face target: both IPPE
    solutions of the face with the most markers, each refined by Levenberg-Marquardt on every
    corner (``object_points`` ``(N,4,3)``, ``corners_px`` ``(N,4,2)``, ``faces`` ``(N,)``);
    the one with the lower error wins. ``(T_cam_board, ratio, angle_deg)`` as :func:`_solve`,
    the ratio and angle between the two refined solutions (the other faces usually settle
    the planar ambiguity: a small ratio)."""
    labels, counts = np.unique(faces, return_counts=True)
    best_face = labels[int(np.argmax(counts))]
    sel = faces == best_face
    obj = object_points.reshape(-1, 3).astype(np.float64).reshape(-1, 1, 3)
    img, K, dist = _cv_camera(corners_px, intrinsics)
    rows = np.repeat(sel, 4)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj[rows], img[rows], K, dist,
                                                 flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return None
    if not n:
        return None
    found = []
    for rvec, tvec in zip(rvecs, tvecs):
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec.copy(), tvec.copy())
        T = _from_rvec_tvec(rvec, tvec)
        r = reprojection_residuals(T, object_points, corners_px, intrinsics)
        found.append((float(np.sqrt((r**2).sum(-1).mean())), T))
    found.sort(key=lambda x: x[0])
    ratio, angle = 0.0, 0.0
    if len(found) > 1:
        ratio = found[0][0] / found[1][0] if found[1][0] > 0 else 1.0
        angle = rotation_angle_deg(found[0][1][:3, :3].T @ found[1][1][:3, :3])
    return found[0][1], ratio, angle


def _single_face(faces: np.ndarray) -> int:
    """The face label when every marker of a view is on one face, else 0 (several faces)."""
    seen = np.unique(faces)
    return int(seen[0]) if len(seen) == 1 else 0


def _too_few(board: Board, ids: np.ndarray, obj: np.ndarray, config: PoseConfig) -> str:
    """Why a view's measurements ``ids`` (board points ``obj`` ``(N,4,3)``) are too few for a
    pose, or "" when they are enough: ``min_markers`` ArUco markers, or, on a ChArUco target,
    ``min_charuco_corners`` distinct points (its saddle-corner quads' corners, each ArUco
    marker of a mixed target counting its 4)."""
    quad = board.saddle_quads(ids)
    n_markers = int((~quad).sum())
    if n_markers >= config.min_markers:
        return ""
    if not quad.any():
        return f"{len(ids)} < min_markers {config.min_markers}"
    n_points = 4 * n_markers + len(np.unique(np.round(obj[quad].reshape(-1, 3), 9), axis=0))
    if n_points >= config.min_charuco_corners:
        return ""
    return f"{n_points} corners < min_charuco_corners {config.min_charuco_corners}"


def estimate_board_pose(
    det: MarkerDetections,
    board: Board,
    intrinsics: CameraIntrinsics,
    config: PoseConfig | None = None,
    camera: str = "",
    frame: str = "",
) -> BoardObservation | RejectedView:
    """Board pose ``T_cam_board`` from one image's detections, or why there is none."""
    config = config or PoseConfig()
    on_board = np.array([int(i) in board.index_of for i in det.ids], dtype=bool)
    ids = det.ids[on_board].astype(int)
    corners = det.corners_px[on_board].astype(float)
    refined = det.refined[on_board]
    dropped: dict[str, list[int]] = {}

    def reject(reason: str, detail: str = "") -> RejectedView:
        return RejectedView(camera, frame, reason, int(len(ids)), detail)

    if det.refinement == "edges" and not config.use_unrefined_corners and len(ids):
        keep = refined.all(axis=1)
        if not keep.all():
            dropped["unrefined"] = ids[~keep].tolist()
            ids, corners = ids[keep], corners[keep]

    faces = board.faces[[board.index_of[int(i)] for i in ids]] if len(ids) else np.zeros(0)
    n_front, n_back = int(np.sum(faces == 1)), int(np.sum(faces == -1))
    if board.sheets:  # a multi-face target: a view sees several faces at once
        face = _single_face(faces)
    elif n_front and n_back and not config.allow_both_faces:
        if n_front == n_back:
            return reject("both_faces", f"{n_front} markers of each face; a camera sees one face")
        face = 1 if n_front > n_back else -1
        dropped["minority_face"] = ids[faces != face].tolist()
        ids, corners = ids[faces == face], corners[faces == face]
    else:
        face = 0 if (n_front and n_back) else (1 if n_front else -1)

    obj = board.object_points(ids) if len(ids) else np.zeros((0, 4, 3))
    short = _too_few(board, ids, obj, config)
    if short:
        return reject("too_few_markers", short)

    faces = board.faces_of(ids)
    while True:
        if board.sheets and face == 0:
            solved = _solve_faces(obj, corners, faces, intrinsics)
        else:
            solved = _solve(obj.reshape(-1, 3), corners.reshape(-1, 2), intrinsics, face != 0)
        if solved is None:
            return reject("pnp_failed")
        T_cam_board, ratio, flip_deg = solved
        resid = reprojection_residuals(T_cam_board, obj, corners, intrinsics)  # (N,4,2)
        per_marker = np.sqrt((resid**2).sum(-1).mean(-1))
        worst = int(np.argmax(per_marker))
        limit = max(config.outlier_factor * float(np.median(per_marker)), config.outlier_min_px)
        if per_marker[worst] <= limit or len(ids) <= 1:
            break
        keep = np.arange(len(ids)) != worst
        if _too_few(board, ids[keep], obj[keep], config):
            return reject(
                "outlier_markers",
                f"marker {ids[worst]} is {per_marker[worst]:.1f} px "
                "off and too few markers remain without it",
            )
        dropped.setdefault("outlier", []).append(int(ids[worst]))
        ids, corners, obj, faces = ids[keep], corners[keep], obj[keep], faces[keep]
        if board.sheets:
            face = _single_face(faces)

    n_pts = resid.shape[0] * 4
    rss = float((resid**2).sum())
    rms = float(np.sqrt(rss / n_pts))
    if ratio > config.max_ambiguity_ratio and flip_deg > config.ambiguity_min_angle_deg:
        return reject(
            "ambiguous",
            f"IPPE error ratio {ratio:.2f} > {config.max_ambiguity_ratio}"
            f" between poses {flip_deg:.1f} deg apart",
        )
    if rms > config.max_reprojection_rms_px:
        return reject("reprojection_rms", f"{rms:.2f} px > {config.max_reprojection_rms_px} px")
    if board.sheets:
        away = [int(f) for f in np.unique(faces)
                if not _faces_camera(T_cam_board, obj[faces == f], 1, board.face_normal(int(f)))]
        if away:
            return reject("face_away", f"the solved pose shows face(s) {away} turned away")
    elif not _faces_camera(T_cam_board, obj, face):
        return reject("face_away", "the solved pose shows the seen face turned away")

    # covariance of the least-squares pose, J for the right perturbation [omega, v] (Pose3)
    J = pose_jacobian(T_cam_board, obj, intrinsics)
    try:
        covariance, sigma = _pose_covariance(J, resid, config)
        fixed = config.model_error_px != "auto"
        # the floor for 1 px: scaled here when fixed, by the pose graph's estimate when auto
        unit = None if config.model_error_px == 0 else model_error_covariance(J, corners, 1.0)
        floor = config.model_error_px**2 * unit if fixed and unit is not None else None
        if floor is not None:
            covariance = covariance + floor
    except np.linalg.LinAlgError:
        return reject("degenerate", "the reprojection Jacobian is singular")
    return BoardObservation(
        camera,
        frame,
        T_cam_board,
        covariance,
        rms,
        int(len(ids)),
        face,
        ids,
        corners,
        obj,
        ratio,
        sigma,
        dropped,
        floor,
        None if fixed else unit,
    )


def board_poses(
    detections: dict[tuple[str, str], MarkerDetections],
    board: Board,
    rig: Rig,
    config: PoseConfig,
) -> tuple[list[BoardObservation], list[RejectedView]]:
    """The board pose of every view with markers, in (frame, camera) order, and the views the
    gates rejected."""
    observations: list[BoardObservation] = []
    rejected: list[RejectedView] = []
    for (cam, frame), det in sorted(detections.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        if len(det.ids) == 0:
            continue
        out = estimate_board_pose(det, board, rig.cameras[cam], config, cam, frame)
        (observations if isinstance(out, BoardObservation) else rejected).append(out)
    return observations, rejected


def pose_edges(observations: list[BoardObservation], config: CalibrationConfig) -> list[PoseEdge]:
    """The pose graph's edges, one ``T_cam_board`` per view in ``observations`` order (so a
    residual's ``index`` names its edge), weighted by the PnP covariance unless
    ``config.edge_covariance`` is off."""
    return [
        PoseEdge(o.camera, o.frame, o.T_cam_board, o.covariance, o.model_error_covariance,
                 o.model_error_unit)
        if config.edge_covariance else PoseEdge(o.camera, o.frame, o.T_cam_board)
        for o in observations
    ]
