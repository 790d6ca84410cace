"""Time in the bundle adjustment: clock offsets, a rolling-shutter readout and a moving board.

The shared time convention (issue 32; docs/conventions.md's frames and ``T_a_b``):

- frame set ``f`` has a nominal time ``t_f``; ``T_ref_board[f]`` is the board pose at ``t_f``;
- over the set the board moves with a constant twist ``[w_f, v_f]`` (rad/s, m/s, both in the
  reference frame, rotation about the board origin):
  ``T_ref_board(t_f + tau) = [Exp_SO3(w_f tau) R_f | p_f + v_f tau]``;
- camera ``c`` exposes image row ``y`` (0 = top) of set ``f`` at
  ``t_f + offset_c + line_delay_c (y - (H - 1) / 2)``, ``line_delay_c = readout_c / (H - 1)``;
  the reference camera's offset is 0.

:func:`timed_view_factor` is :func:`rgbd_calib.solve.bundle_factors.view_factor` with each
corner predicted at its own time, with two more variables: the set's twist (a Vector 6
``[w (rad/s), v (m/s)]``, GTSAM's rotation-first order) and the camera's time parameters (a
Vector 2 ``[offset_ms, readout_ms]``: milliseconds both, the readout first to last row, so a
corner's time is ``tau = 1e-3 (offset_ms + readout_ms s)`` with the row fraction
``s = (v_meas - (H - 1) / 2) / (H - 1)`` in [-0.5, 0.5]; both columns of the Jacobian are then
of one size, which keeps the normal equations well conditioned). The row ``v_meas`` is the
MEASURED row of the corner, not the predicted one: the standard approximation of rolling-shutter
bundle adjustment (Hedborg et al. 2012, "Rolling shutter bundle adjustment"); its error is the
reprojection error times the line delay times the image speed, far below the corner noise.

Gauge: the images see only the products ``w_f tau`` and ``v_f tau``. Scaling every time by
``a`` and every twist by ``1 / a`` changes no pixel, so the time scale is unobservable from the
images alone: it needs an anchor, a known readout of one camera (a sensor property) or a clock
offset from timestamps (:class:`TimePrior` with a small sigma). Without one the weak priors
(:func:`twist_prior`, :func:`time_prior`) hold it; the poses are unaffected either way. The
offset and the readout of a camera separate only when the board moves in different directions
across sets or covers different rows (the offset moves every corner of a view alike, the
readout in proportion to its row).

All Jacobians are analytic (checked against central differences in tests/test_time_model.py).
:func:`solve_timed` solves such a graph on its own; the bundle adjustment does not use it yet.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from ..core.camera import pinhole_point_jacobian, pinhole_pose_jacobian, project_pinhole
from .bundle_factors import robust_rows
from .posegraph import sigmas_from_covariance

if TYPE_CHECKING:
    from .bundle import MarkerMeasurement

MS = 1e-3  # seconds per millisecond: the time parameters are in ms
HELD_SIGMA = 1e-9  # sigma of a held value (the reference's pose and offset, a global shutter)


def _skew_stack(a: np.ndarray) -> np.ndarray:
    """(N,3,3) cross-product matrices ``[a_i]x`` of the rows of ``a`` (N,3)."""
    S = np.zeros(a.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -a[..., 2], a[..., 1]
    S[..., 1, 0], S[..., 1, 2] = a[..., 2], -a[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -a[..., 1], a[..., 0]
    return S


def _so3_exp_and_left_jacobian(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Exp(phi_i)`` and its left Jacobian ``J_l(phi_i)`` (both (N,3,3)) of rotation vectors
    ``phi`` (N,3, rad): ``Exp(phi + d) = Exp(J_l(phi) d) Exp(phi)`` to first order, with
    ``Exp = I + a [phi]x + b [phi]x^2``, ``J_l = I + b [phi]x + c [phi]x^2``,
    ``a = sin t / t``, ``b = (1 - cos t) / t^2``, ``c = (t - sin t) / t^3`` (Barfoot, State
    Estimation for Robotics, eqs. 7.37 and 7.77); Taylor series below t = 1e-3."""
    t = np.linalg.norm(phi, axis=-1)
    small = t < 1e-3
    ts = np.where(small, 1.0, t)
    t2 = t * t
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(ts)) / ts**2)
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (ts - np.sin(ts)) / ts**3)
    S = _skew_stack(phi)
    S2 = S @ S
    eye = np.eye(3)
    return (eye + a[:, None, None] * S + b[:, None, None] * S2,
            eye + b[:, None, None] * S + c[:, None, None] * S2)


def row_fraction(v_px: np.ndarray, height_px: int) -> np.ndarray:
    """``s = (v - (H - 1) / 2) / (H - 1)``: a row's exposure time relative to the image middle,
    in units of the readout (first to last row); -0.5 on the top row, +0.5 on the bottom one."""
    return (np.asarray(v_px, dtype=float) - (height_px - 1) / 2.0) / (height_px - 1)


def project_timed(T_ref_cam: np.ndarray, T_ref_board: np.ndarray, twist: np.ndarray,
                  time_ms: np.ndarray, K: np.ndarray, P_b: np.ndarray, s_row: np.ndarray,
                  jacobians: bool = True):
    """Pinhole pixels (N,2) of board points ``P_b`` (N,3, m) each seen at its own time.

    Point i is seen at ``tau_i = 1e-3 (offset_ms + readout_ms s_i)`` (``time_ms = [offset_ms,
    readout_ms]``, ``s_row`` the row fractions, :func:`row_fraction`) after ``t_f``, on the
    board at ``T_ref_board(t_f + tau_i)`` (``twist = [w, v]``,
    :func:`rgbd_calib.core.geometry.pose_after_twist`):
    ``P_ref = E q + p_f + v tau`` with ``E = Exp(w tau)``, ``q = R_f P_b``; ``p_cam =
    R_rc^T (P_ref - t_rc)``. With ``jacobians``, d(u,v)/d of (N,2,k): camera (right
    perturbation, :func:`~rgbd_calib.core.camera.pinhole_pose_jacobian`), board at ``t_f``
    (right perturbation ``R_f Exp(dw), p_f + R_f dv``: dP_ref = [-E R_f [P_b]x, R_f]), twist
    (dP_ref/dw = -[E q]x J_l(w tau) tau, dP_ref/dv = tau I) and time (dP_ref/dtau =
    w x E q + v, dtau/d[offset_ms, readout_ms] = 1e-3 [1, s]), each chained through
    d(u,v)/dp_cam R_rc^T."""
    w, v = np.asarray(twist[:3], dtype=float), np.asarray(twist[3:], dtype=float)
    tau = MS * (time_ms[0] + time_ms[1] * s_row)  # (N,) seconds
    E, J_l = _so3_exp_and_left_jacobian(tau[:, None] * w)
    R_rb, p_rb = T_ref_board[:3, :3], T_ref_board[:3, 3]
    R_rc, t_rc = T_ref_cam[:3, :3], T_ref_cam[:3, 3]
    Eq = np.einsum("nij,nj->ni", E, P_b @ R_rb.T)
    P_ref = Eq + p_rb + tau[:, None] * v
    p = (P_ref - t_rc) @ R_rc  # R_rc^T (P_ref - t_rc), (N,3)
    fx, fy = K[0, 0], K[1, 1]
    uv = project_pinhole(p, fx, fy, K[0, 2], K[1, 2])
    if not jacobians:
        return uv, None
    A = pinhole_point_jacobian(p, fx, fy) @ R_rc.T  # d(u,v)/dP_ref (N,2,3)
    J_cam = pinhole_pose_jacobian(p, fx, fy)
    ER = E @ R_rb
    J_board = np.concatenate([A @ (-ER @ _skew_stack(P_b)), A @ R_rb], axis=2)
    J_w = A @ (-_skew_stack(Eq) @ J_l) * tau[:, None, None]
    J_v = A * tau[:, None, None]
    dP_dtau = np.cross(w, Eq) + v  # (N,3)
    dtau = MS * np.stack([np.ones_like(s_row), s_row], axis=1)  # (N,2)
    J_time = np.einsum("nij,nj->ni", A, dP_dtau)[:, :, None] * dtau[:, None, :]
    return uv, (J_cam, J_board, np.concatenate([J_w, J_v], axis=2), J_time)


def timed_view_factor(key_cam: int, key_board: int, key_twist: int, key_time: int,
                      K: np.ndarray, height_px: int, object_points: np.ndarray,
                      corners_px: np.ndarray, sigma: float, robust: str, robust_k: float):
    """All markers of one camera view in one factor, each corner predicted at its own time.

    As :func:`~rgbd_calib.solve.bundle_factors.view_factor` (pinhole ``K``, undistorted pixels
    ``corners_px`` (n,4,2), board points ``object_points`` (n,4,3) m, corner noise ``sigma``
    px, the same per-marker robust kernel through
    :func:`~rgbd_calib.solve.bundle_factors.robust_rows`), with keys: camera Pose3
    ``T_ref_cam``, board Pose3 ``T_ref_board`` at ``t_f``, the set's twist Vector 6
    ``[w (rad/s), v (m/s)]`` and the camera's time Vector 2 ``[offset_ms, readout_ms]``. Each
    corner's time uses its measured row (the module's docstring; image height ``height_px``).
    """
    n = len(object_points)
    measured = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    P_b = np.asarray(object_points, dtype=float).reshape(-1, 3)
    s_row = row_fraction(measured[:, 1], height_px)
    inv_sigma = 1.0 / sigma

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None):
        uv, J = project_timed(values.atPose3(key_cam).matrix(), values.atPose3(key_board).matrix(),
                              values.atVector(key_twist), values.atVector(key_time), K, P_b,
                              s_row, H is not None)
        r = ((uv - measured) * inv_sigma).reshape(n, 8)
        return robust_rows(r, lambda: tuple(j.reshape(8 * n, -1) * inv_sigma for j in J),
                           H, robust, robust_k)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * n),
                              [key_cam, key_board, key_twist, key_time], error)


@dataclass(frozen=True)
class TwistPrior:
    """Sigmas of the weak zero-mean prior on each set's twist: a board waved by hand moves at
    well under 3 m/s and 300 deg/s."""

    sigma_mps: float = 3.0
    sigma_dps: float = 300.0


@dataclass(frozen=True)
class TimePrior:
    """A Gaussian prior on a camera's ``[offset_ms, readout_ms]``: weak by default (offset
    0 +- 50 ms; readout 0 +- 50 ms, so 0..100 ms within two sigma). A known readout (a sensor
    property) or an offset from timestamps, with a small sigma, anchors the time scale (the
    module's docstring); its means are also the solve's initial values."""

    offset_ms: float = 0.0
    offset_sigma_ms: float = 50.0
    readout_ms: float = 0.0
    readout_sigma_ms: float = 50.0


def twist_prior(key_twist: int, prior: TwistPrior = TwistPrior()) -> gtsam.PriorFactorVector:
    """The weak zero-mean prior on a set's twist ``[w (rad/s), v (m/s)]``."""
    w = np.radians(prior.sigma_dps)
    sigmas = np.array([w, w, w, prior.sigma_mps, prior.sigma_mps, prior.sigma_mps])
    return gtsam.PriorFactorVector(key_twist, np.zeros(6),
                                   gtsam.noiseModel.Diagonal.Sigmas(sigmas))


def time_prior(key_time: int, prior: TimePrior = TimePrior(), reference: bool = False,
               rolling_shutter: bool = True) -> gtsam.PriorFactorVector:
    """The prior on a camera's ``[offset_ms, readout_ms]``: the reference camera's offset held
    at 0 (the gauge of the clock), a camera without a rolling shutter's readout held at 0; the
    rest as ``prior`` says (the reference's readout stays free with a rolling shutter)."""
    mean = np.array([0.0 if reference else prior.offset_ms,
                     prior.readout_ms if rolling_shutter else 0.0])
    sigmas = np.array([HELD_SIGMA if reference else prior.offset_sigma_ms,
                       prior.readout_sigma_ms if rolling_shutter else HELD_SIGMA])
    return gtsam.PriorFactorVector(key_time, mean, gtsam.noiseModel.Diagonal.Sigmas(sigmas))


@dataclass(frozen=True)
class TimedSolution:
    """The poses, the board's motion and the cameras' clocks of :func:`solve_timed`.

    ``T_ref_cam`` (camera -> 4x4, m), ``T_ref_board`` (view -> 4x4, m, the board at ``t_f``),
    ``twist`` (view -> ``[w (rad/s), v (m/s)]``, reference frame), ``offset_ms`` and
    ``readout_ms`` per camera; the marginal 1-sigmas of each (GTSAM Marginals of the plain
    Gaussian graph at the solution, corner noise ``pixel_sigma``), the cameras' 6x6 pose
    covariances (``[rot, trans]``, right perturbation) and their worst-axis sigmas;
    ``residual_rms_px`` the RMS of the corners' 2-D reprojection errors."""

    T_ref_cam: dict[str, np.ndarray]
    T_ref_board: dict[str, np.ndarray]
    twist: dict[str, np.ndarray]
    offset_ms: dict[str, float]
    readout_ms: dict[str, float]
    sigma_twist: dict[str, np.ndarray]  # view -> 6 sigmas [rad/s x3, m/s x3]
    sigma_offset_ms: dict[str, float]
    sigma_readout_ms: dict[str, float]
    covariance: dict[str, np.ndarray]
    sigma_rotation_deg: dict[str, float]
    sigma_translation_mm: dict[str, float]
    residual_rms_px: float
    iterations: int
    final_error: float


def _view_groups(measurements: Sequence[MarkerMeasurement]):
    """``(camera, view, object_points (n,4,3), corners_px (n,4,2))`` per camera view."""
    members: dict[tuple[str, str], list] = defaultdict(list)
    for m in measurements:
        members[(m.camera, m.view)].append(m)
    return [(c, v, np.stack([m.object_points for m in ms]).astype(float),
             np.stack([m.corners_px for m in ms]).astype(float))
            for (c, v), ms in members.items()]


def solve_timed(measurements: Sequence[MarkerMeasurement], K: dict[str, np.ndarray],
                height_px: dict[str, int], reference: str, T_ref_cam: dict[str, np.ndarray],
                T_ref_board: dict[str, np.ndarray], *,
                rolling_shutter: Collection[str] | None = None,
                time_priors: dict[str, TimePrior] | None = None,
                twist_sigma: TwistPrior = TwistPrior(), pixel_sigma: float = 0.25,
                robust: str = "none", robust_k: float = 3.0,
                max_iterations: int = 100) -> TimedSolution:
    """Camera poses, board poses, each set's twist and each camera's clock, jointly on the
    marker corners (undistorted pinhole pixels; measurements shaped as
    :class:`rgbd_calib.solve.bundle.MarkerMeasurement`, their ``view`` the frame set).

    One :func:`timed_view_factor` per camera view; the reference camera's pose held at the
    identity and its offset at 0; ``rolling_shutter`` names the cameras whose readout is free
    (default: every camera), the others' is held at 0; :func:`time_prior` per camera from
    ``time_priors`` (default :class:`TimePrior`) and :func:`twist_prior` per set. Initial
    values: the given poses (e.g. the timeless bundle adjustment's), every twist 0, the time
    parameters at their priors' means (the product ``w tau`` has no gradient where both are
    0: with every mean 0 the time model stays at the timeless solution). Levenberg-Marquardt;
    marginals without the robust kernel."""
    cams = sorted({m.camera for m in measurements} | {reference})
    views = sorted({m.view for m in measurements})
    cam_key = {c: gtsam.symbol("c", i) for i, c in enumerate(cams)}
    time_key = {c: gtsam.symbol("t", i) for i, c in enumerate(cams)}
    view_key = {v: gtsam.symbol("b", i) for i, v in enumerate(views)}
    twist_key = {v: gtsam.symbol("w", i) for i, v in enumerate(views)}
    rolling = set(cams if rolling_shutter is None else rolling_shutter)
    priors = {c: (time_priors or {}).get(c, TimePrior()) for c in cams}
    groups = _view_groups(measurements)

    def graph_at(kind: str) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        for c, v, obj, px in groups:
            graph.add(timed_view_factor(cam_key[c], view_key[v], twist_key[v], time_key[c],
                                        K[c], height_px[c], obj, px, pixel_sigma, kind,
                                        robust_k))
        graph.add(gtsam.PriorFactorPose3(cam_key[reference], gtsam.Pose3(np.eye(4)),
                                         gtsam.noiseModel.Isotropic.Sigma(6, HELD_SIGMA)))
        for c in cams:
            graph.add(time_prior(time_key[c], priors[c], c == reference, c in rolling))
        for v in views:
            graph.add(twist_prior(twist_key[v], twist_sigma))
        return graph

    values = gtsam.Values()
    for c in cams:
        values.insert(cam_key[c], gtsam.Pose3(np.eye(4) if c == reference else T_ref_cam[c]))
        p = priors[c]
        values.insert(time_key[c], np.array([0.0 if c == reference else p.offset_ms,
                                             p.readout_ms if c in rolling else 0.0]))
    for v in views:
        values.insert(view_key[v], gtsam.Pose3(T_ref_board[v]))
        values.insert(twist_key[v], np.zeros(6))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    graph = graph_at(robust)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    marginals = gtsam.Marginals(graph_at("none"), result)
    return _timed_solution(result, marginals, cams, views, cam_key, time_key, view_key,
                           twist_key, reference, groups, K, height_px, optimizer,
                           graph.error(result))


def _timed_solution(values: gtsam.Values, marginals: gtsam.Marginals, cams, views, cam_key,
                    time_key, view_key, twist_key, reference, groups, K, height_px,
                    optimizer, final_error: float) -> TimedSolution:
    """Read the solution and its marginals out of GTSAM's values."""
    T_cam = {c: values.atPose3(cam_key[c]).matrix() for c in cams}
    cov = {c: (np.zeros((6, 6)) if c == reference
               else np.asarray(marginals.marginalCovariance(cam_key[c]))) for c in cams}
    sig = {c: sigmas_from_covariance(T_cam[c], cov[c]) for c in cams}
    times = {c: values.atVector(time_key[c]) for c in cams}
    time_sigma = {c: np.sqrt(np.diag(marginals.marginalCovariance(time_key[c]))) for c in cams}
    twist = {v: values.atVector(twist_key[v]) for v in views}
    sq, count = 0.0, 0
    for c, v, obj, px in groups:
        uv, _ = project_timed(T_cam[c], values.atPose3(view_key[v]).matrix(), twist[v],
                              times[c], K[c], obj.reshape(-1, 3),
                              row_fraction(px.reshape(-1, 2)[:, 1], height_px[c]), False)
        sq += float(np.sum((uv - px.reshape(-1, 2)) ** 2))
        count += len(uv)
    return TimedSolution(
        T_ref_cam=T_cam,
        T_ref_board={v: values.atPose3(view_key[v]).matrix() for v in views},
        twist=twist,
        offset_ms={c: float(times[c][0]) for c in cams},
        readout_ms={c: float(times[c][1]) for c in cams},
        sigma_twist={v: np.sqrt(np.diag(marginals.marginalCovariance(twist_key[v])))
                     for v in views},
        sigma_offset_ms={c: float(time_sigma[c][0]) for c in cams},
        sigma_readout_ms={c: float(time_sigma[c][1]) for c in cams},
        covariance=cov,
        sigma_rotation_deg={c: sig[c][0] for c in cams},
        sigma_translation_mm={c: sig[c][1] for c in cams},
        residual_rms_px=float(np.sqrt(sq / max(count, 1))),
        iterations=optimizer.iterations(),
        final_error=float(final_error))
