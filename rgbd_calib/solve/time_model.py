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
The bundle adjustment (:mod:`rgbd_calib.solve.bundle`, ``bundle.time: refine``) builds its
graph from these factors and priors; :class:`TimeModel` is what it estimated.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field

import gtsam
import numpy as np

from ..core.camera import (
    CameraIntrinsics,
    pinhole_point_jacobian,
    pinhole_pose_jacobian,
    project_pinhole,
)
from ..core.geometry import move_rows, pose_after_twist
from .bundle_factors import (
    as_noise,
    face_transform,
    refined_model,
    robust_rows,
    with_parameters,
)
from .corner_noise import CornerNoise

MS = 1e-3  # seconds per millisecond: the time parameters are in ms
HELD_SIGMA = 1e-6  # sigma (ms) of a held time (the reference's offset, a global shutter): tighter
# makes the marginals' Cholesky fail beside the weak time priors (1e18 against 4e-4)


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
                  time_ms: np.ndarray, K, P_b: np.ndarray, s_row: np.ndarray,
                  jacobians: bool = True, columns: np.ndarray | None = None,
                  accel: np.ndarray | None = None):
    """Pixels (N,2) of board points ``P_b`` (N,3, m) each seen at its own time.

    Point i is seen at ``tau_i = 1e-3 (offset_ms + readout_ms s_i)`` (``time_ms = [offset_ms,
    readout_ms]``, ``s_row`` the row fractions, :func:`row_fraction`) after ``t_f``, on the
    board at ``T_ref_board(t_f + tau_i)`` (``twist = [w, v]``,
    :func:`rgbd_calib.core.geometry.pose_after_twist`):
    ``P_ref = E q + p_f + v tau`` with ``E = Exp(w tau)``, ``q = R_f P_b``; ``p_cam =
    R_rc^T (P_ref - t_rc)``, projected by ``K`` (a 3x3 pinhole matrix: undistorted pixels) or a
    :class:`~rgbd_calib.core.camera.CameraIntrinsics` (the full model: raw pixels). With
    ``jacobians``, d(u,v)/d of (N,2,k): camera (right perturbation, d(u,v)/dp_cam ``[[p]x,
    -I]``), board at ``t_f`` (right perturbation ``R_f Exp(dw), p_f + R_f dv``: dP_ref =
    [-E R_f [P_b]x, R_f]), twist (dP_ref/dw = -[E q]x J_l(w tau) tau, dP_ref/dv = tau I) and
    time (dP_ref/dtau = w x E q + v, dtau/d[offset_ms, readout_ms] = 1e-3 [1, s]), each chained
    through d(u,v)/dp_cam R_rc^T; then d(u,v)/dP_b (N,2,3) (= d(u,v)/dP_ref E R_f, what a
    face's pose moves); with a full model and ``columns``, also d(u,v)/d of those columns of
    :meth:`~rgbd_calib.core.camera.CameraIntrinsics.intrinsics_jacobian` (last).

    ``accel`` ``[alpha (rad/s^2), a (m/s^2)]``: the board accelerates through the capture
    (constant acceleration, the angular part taken along the turn): point i moves by the twist
    ``twist + accel tau_i / 2`` over ``tau_i``; its Jacobian is the twist's times ``tau_i / 2``
    (returned as d(u,v)/d twist: the caller chains it to whatever gives the acceleration)."""
    tau = MS * (time_ms[0] + time_ms[1] * s_row)  # (N,) seconds
    xi = np.asarray(twist, dtype=float)[None, :] * np.ones((len(tau), 1))
    if accel is not None:
        xi = xi + 0.5 * tau[:, None] * np.asarray(accel, dtype=float)
    w, v = xi[:, :3], xi[:, 3:]  # (N,3) each
    E, J_l = _so3_exp_and_left_jacobian(tau[:, None] * w)
    R_rb, p_rb = T_ref_board[:3, :3], T_ref_board[:3, 3]
    R_rc, t_rc = T_ref_cam[:3, :3], T_ref_cam[:3, 3]
    Eq = np.einsum("nij,nj->ni", E, P_b @ R_rb.T)
    P_ref = Eq + p_rb + tau[:, None] * v
    p = (P_ref - t_rc) @ R_rc  # R_rc^T (P_ref - t_rc), (N,3)
    full = not isinstance(K, np.ndarray)
    if not jacobians:
        return (K.project(p) if full else project_pinhole(p, K[0, 0], K[1, 1], K[0, 2],
                                                          K[1, 2])), None
    if full:
        uv, J_point = K.project_jacobian(p)
        J_cam = J_point @ _point_pose_jacobian(p)
    else:
        fx, fy = K[0, 0], K[1, 1]
        uv = project_pinhole(p, fx, fy, K[0, 2], K[1, 2])
        J_point = pinhole_point_jacobian(p, fx, fy)
        J_cam = pinhole_pose_jacobian(p, fx, fy)
    A = J_point @ R_rc.T  # d(u,v)/dP_ref (N,2,3)
    ER = E @ R_rb
    J_board = np.concatenate([A @ (-ER @ _skew_stack(P_b)), A @ R_rb], axis=2)
    J_w = A @ (-_skew_stack(Eq) @ J_l) * tau[:, None, None]
    J_v = A * tau[:, None, None]
    w_now, v_now = w, v  # the rates at tau_i: with an acceleration, twist + accel tau_i
    if accel is not None:
        w_now, v_now = w + 0.5 * tau[:, None] * accel[:3], v + 0.5 * tau[:, None] * accel[3:]
    # d Exp(phi)/d tau = [J_l(phi) dphi/dtau]x Exp(phi); J_l(phi) phi = phi without acceleration
    dP_dtau = np.cross(np.einsum("nij,nj->ni", J_l, w_now), Eq) + v_now  # (N,3)
    dtau = MS * np.stack([np.ones_like(s_row), s_row], axis=1)  # (N,2)
    J_time = np.einsum("nij,nj->ni", A, dP_dtau)[:, :, None] * dtau[:, None, :]
    out = (J_cam, J_board, np.concatenate([J_w, J_v], axis=2), J_time, A @ ER)
    if full and columns is not None:
        out += (K.intrinsics_jacobian(p)[:, :, columns],)
    return uv, out


def _point_pose_jacobian(p: np.ndarray) -> np.ndarray:
    """dp_cam/dxi (N,3,6) of camera-frame points for a right perturbation of the camera's pose:
    ``[[p]x, -I]``."""
    J = np.zeros((len(p), 3, 6))
    J[:, :, :3] = _skew_stack(p)
    J[:, :, 3:] = -np.eye(3)
    return J


def _moved_point_jacobian(J_point_board: np.ndarray, rows: np.ndarray, P_b: np.ndarray,
                          M: np.ndarray) -> np.ndarray:
    """d(u,v)/dxi (N,2,6) of a face correction ``X`` (``X <- X Exp(xi)``, expressed in frame
    ``A``) from d(u,v)/dP_b: the face's rows of the moved board points ``P_b = M Q`` (``M = A X``,
    or ``X`` for the back sheet) move by ``M_R [-[Q]x, I] xi``; 0 on the other rows. (Without
    time this equals the board's Jacobian times ``Ad(M)``; with time the board moves through
    ``E R_f`` but its ``t_f`` perturbation does not, so the two differ.)"""
    J = np.zeros(J_point_board.shape[:2] + (6,))
    R = M[:3, :3]
    Q = (P_b[rows] - M[:3, 3]) @ R  # M^-1 P_b
    dP = np.concatenate([-R @ _skew_stack(Q), np.broadcast_to(R, (len(Q), 3, 3))], axis=2)
    J[rows] = J_point_board[rows] @ dP
    return J


def timed_view_factor(key_cam: int, key_board: int, key_twist: int, key_time: int,
                      K: np.ndarray | None, height_px: int, object_points: np.ndarray,
                      corners_px: np.ndarray, sigma: float | CornerNoise, robust: str,
                      robust_k: float, intr: tuple | None = None, names: tuple[str, ...] = (),
                      moving: list | None = None, known_ms: float = 0.0,
                      accel: tuple[tuple[int, float], ...] = ()):
    """All markers of one camera view in one factor, each corner predicted at its own time.

    As :func:`~rgbd_calib.solve.bundle_factors.view_factor` (pinhole ``K``, undistorted pixels
    ``corners_px`` (n,4,2), board points ``object_points`` (n,4,3) m, corner noise ``sigma``
    px, the same per-marker robust kernel through
    :func:`~rgbd_calib.solve.bundle_factors.robust_rows`), with keys: camera Pose3
    ``T_ref_cam``, board Pose3 ``T_ref_board`` at ``t_f``, [the camera's intrinsics vector,]
    [the face poses,] the set's twist Vector 6 ``[w (rad/s), v (m/s)]`` and the camera's time
    Vector 2 ``[offset_ms, readout_ms]``. Each corner's time uses its measured row (the
    module's docstring; image height ``height_px``).

    ``intr = (key_intr, base)`` refines the parameters ``names`` of the camera model ``base``
    (raw pixels, as :func:`~rgbd_calib.solve.bundle_factors.view_factor_intrinsics`);
    ``moving`` lists ``(key, flags, A)`` per face pose that moves the flagged markers (board
    self-calibration, as :func:`~rgbd_calib.solve.bundle_factors.view_factor`)
    (:func:`_moved_point_jacobian`).
    ``known_ms`` is the view's capture time after the set's nominal time as the cameras'
    timestamps say (ms; :func:`capture_offsets`), added to the camera's offset.
    ``accel`` ``((twist key, 1/s), ...)``: the board's acceleration through the capture as a
    combination of the twists of the set and its neighbours in a continuous recording
    (:func:`acceleration_stencils`), so that a board waved by hand is seen where it was, not
    where a constant twist would have carried it (``project_timed``'s ``accel``)."""
    n = len(object_points)
    measured = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    P_file = np.asarray(object_points, dtype=float).reshape(-1, 3)
    s_row = row_fraction(measured[:, 1], height_px)
    noise = as_noise(sigma)
    faces = [(key, np.repeat(np.asarray(flags, dtype=bool), 4), A)
             for key, flags, A in (moving or [])]
    keys = [key_cam, key_board]
    columns = None
    if intr:
        key_intr, base = intr
        padded, columns = refined_model(base, names)
        keys.append(key_intr)
    keys += [key for key, _, _ in faces] + [key_twist, key_time]
    own = sum(c for k, c in accel if k == key_twist)
    others = [(k, c) for k, c in accel if k != key_twist]
    keys += [k for k, _ in others]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None):
        X = [values.atPose3(key).matrix() for key, _, _ in faces]
        P_b = move_rows(P_file, [(rows, face_transform(x, A))
                                 for (_, rows, A), x in zip(faces, X)]) if faces else P_file
        model = with_parameters(padded, names, values.atVector(key_intr)) if intr else K
        acc = (sum(c * values.atVector(k) for k, c in accel) if accel else None)
        uv, J = project_timed(values.atPose3(key_cam).matrix(),
                              values.atPose3(key_board).matrix(), values.atVector(key_twist),
                              values.atVector(key_time) + [known_ms, 0.0], model, P_b, s_row,
                              H is not None, columns, acc)
        r = noise.whiten((uv - measured).reshape(n, 8))

        def blocks():
            J_cam, J_board, J_twist, J_time, J_pb = J[:5]
            out = [J_cam, J_board] + ([J[5]] if intr else [])
            out += [_moved_point_jacobian(J_pb, rows, P_b, x if A is None else A @ x)
                    for (_, rows, A), x in zip(faces, X)]
            t_ms = values.atVector(key_time) + [known_ms, 0.0]
            J_acc = J_twist * (0.5 * MS * (t_ms[0] + t_ms[1] * s_row))[:, None, None]
            out += [J_twist + own * J_acc, J_time] + [c * J_acc for _, c in others]
            return tuple(noise.whiten_rows(j.reshape(8 * n, -1)) for j in out)

        return robust_rows(r, blocks, H, robust, robust_k)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * n), keys, error)


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


READOUT_INIT_MS = 10.0  # every readout starts here: a nonzero time breaks the standstill saddle


STEADY_CLOCK_MS = 2.0  # timestamp differences spread less than this: one offset per camera
_SMOOTHING = 5  # frame sets in the running median of drifting differences


def capture_offsets(timestamps: dict[str, dict[str, float] | None],
                    reference: str) -> dict[tuple[str, str], float]:
    """Each view's capture time after its frame set's nominal time (the reference camera's
    capture), from the cameras' timestamps (camera -> frame -> ms, None without a
    ``timestamps.csv``): ``(camera, frame) -> ms`` for every frame both have a time for.

    The raw differences ``t_camera - t_reference`` carry both timestamps' jitter. Where a
    camera's differences hold steady (robust spread under :data:`STEADY_CLOCK_MS`: cameras
    sharing a clock, or a recording too short to drift) each of its views gets their median,
    which averages the jitter out; where they do not (free-running cameras drift against each
    other, and the pairing of nearest frames slips by a frame period), each view gets the
    running median of :data:`_SMOOTHING` neighbouring sets in capture order, which keeps the
    drift and the slips. Empty when the reference has no timestamps."""
    ref = timestamps.get(reference)
    if not ref:
        return {}
    out: dict[tuple[str, str], float] = {}
    for c, times in timestamps.items():
        frames = sorted((f for f in (times or {}) if f in ref), key=lambda f: ref[f])
        if not frames:
            continue
        d = np.array([times[f] - ref[f] for f in frames])
        centre = float(np.median(d))
        if 1.4826 * float(np.median(np.abs(d - centre))) < STEADY_CLOCK_MS:
            out |= {(c, f): centre for f in frames}
            continue
        half = _SMOOTHING // 2
        out |= {(c, f): float(np.median(d[max(i - half, 0):i + half + 1]))
                for i, f in enumerate(frames)}
    return out


def anchored_priors(cameras: Collection[str], capture_ms: dict[tuple[str, str], float],
                    offset_sigma_ms: float) -> dict[str, TimePrior]:
    """The time priors of cameras whose views have timestamped capture times: their offset
    is then the latency beyond what the timestamps say, 0 +- ``offset_sigma_ms``; the other
    cameras keep the weak default (:class:`TimePrior`)."""
    stamped = {c for c, _ in capture_ms}
    return {c: TimePrior(offset_sigma_ms=offset_sigma_ms) if c in stamped else TimePrior()
            for c in cameras}


MAX_LINK_MS = 100.0  # consecutive frame sets further apart are not linked by the motion prior


@dataclass(frozen=True)
class MotionPrior:
    """The board's motion between consecutive frame sets of a continuous recording: white
    noise on its acceleration (Barfoot, State Estimation for Robotics, 11.3: the constant-
    velocity Gaussian-process prior), so over ``dt`` seconds the twist changes by a Gaussian of
    variance ``q^2 dt`` per axis and the pose follows the twist. ``q_mps``: m/s per sqrt(s)
    (linear), ``q_dps``: deg/s per sqrt(s) (angular). A hand changes a board's speed by about
    0.1 m/s in a frame period: 0.5 m/s/sqrt(s); estimated from the data by default."""

    q_mps: float = 0.5
    q_dps: float = 50.0


def set_times_ms(timestamps: dict[str, dict[str, float] | None],
                 reference: str) -> dict[str, float]:
    """Each frame set's nominal time on the reference camera's clock (ms): the reference's
    stamp where it has the set, else another stamped camera's minus that camera's median
    difference to the reference (the median over such cameras). Empty when the reference
    has no timestamps."""
    ref = timestamps.get(reference)
    if not ref:
        return {}
    shift = {}
    for c, times in timestamps.items():
        common = [times[f] - ref[f] for f in (times or {}) if f in ref]
        if common:
            shift[c] = float(np.median(common))
    out = dict(ref)
    others: dict[str, list[float]] = {}
    for c, times in timestamps.items():
        if c == reference or c not in shift:
            continue
        for f, t in (times or {}).items():
            if f not in ref:
                others.setdefault(f, []).append(t - shift[c])
    return out | {f: float(np.median(ts)) for f, ts in others.items()}


def motion_links(set_ms: dict[str, float], views: Collection[str],
                 max_ms: float = MAX_LINK_MS) -> tuple[tuple[str, str, float], ...]:
    """``(view, next view, dt_s)`` for every two of ``views`` consecutive in time no more
    than ``max_ms`` apart: the frame sets of a continuous recording the motion prior ties."""
    timed = sorted((set_ms[v], v) for v in views if v in set_ms)
    return tuple((f, g, (tg - tf) * MS) for (tf, f), (tg, g) in zip(timed, timed[1:])
                 if 0.0 < tg - tf <= max_ms)


def acceleration_stencils(links: tuple[tuple[str, str, float], ...],
                          ) -> dict[str, tuple[tuple[str, float], ...]]:
    """Per linked frame set, its acceleration as a finite difference of twists: ``((set,
    coefficient 1/s), ...)``, central between the previous and the next set where both are
    linked, one-sided at a run's ends. Sets without a link have none (a lone set's acceleration
    is not observable: its twist alone carries the motion)."""
    prev = {g: (f, dt) for f, g, dt in links}
    nxt = {f: (g, dt) for f, g, dt in links}
    out = {}
    for v in prev.keys() | nxt.keys():
        if v in prev and v in nxt:
            (p, dp), (n, dn) = prev[v], nxt[v]
            out[v] = ((n, 1.0 / (dp + dn)), (p, -1.0 / (dp + dn)))
        elif v in nxt:
            n, dn = nxt[v]
            out[v] = ((n, 1.0 / dn), (v, -1.0 / dn))
        else:
            p, dp = prev[v]
            out[v] = ((v, 1.0 / dp), (p, -1.0 / dp))
    return out


def _so3_right_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """``J_r^-1(phi)`` (3x3): ``Log(Exp(phi) Exp(d)) = phi + J_r^-1(phi) d`` to first order."""
    t = float(np.linalg.norm(phi))
    S = _skew_stack(phi[None])[0]
    if t < 1e-6:
        return np.eye(3) + 0.5 * S + S @ S / 12.0
    c = 1.0 / t**2 - (1.0 + np.cos(t)) / (2.0 * t * np.sin(t))
    return np.eye(3) + 0.5 * S + c * (S @ S)


def motion_link_factor(key_board_f: int, key_twist_f: int, key_board_g: int, key_twist_g: int,
                       dt_s: float, prior: MotionPrior = MotionPrior()) -> gtsam.CustomFactor:
    """The motion prior between frame sets ``f`` and ``g`` = f + ``dt_s`` of a continuous
    recording (:class:`MotionPrior`): errors ``Log(R_g R_f^T) - w_f dt``, ``p_g - p_f -
    v_f dt``, ``w_g - w_f``, ``v_g - v_f`` (the module's twist convention), under the
    constant-velocity prior's covariance ``q^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` per axis
    between each pose error and its twist's change. Analytic Jacobians (board poses: GTSAM's
    right perturbation ``[dw, dv]``)."""
    qw2, qv2 = np.radians(prior.q_dps) ** 2, prior.q_mps**2
    block = np.array([[dt_s**3 / 3.0, dt_s**2 / 2.0], [dt_s**2 / 2.0, dt_s]])
    cov = np.zeros((12, 12))
    for axis in range(3):  # error rows: rot 0-2, pos 3-5, dw 6-8, dv 9-11
        for q2, (i, j) in ((qw2, (axis, 6 + axis)), (qv2, (3 + axis, 9 + axis))):
            cov[np.ix_([i, j], [i, j])] = q2 * block
    noise = gtsam.noiseModel.Gaussian.Covariance(cov)
    eye = np.eye(3)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None):
        Tf, Tg = values.atPose3(key_board_f).matrix(), values.atPose3(key_board_g).matrix()
        xf, xg = values.atVector(key_twist_f), values.atVector(key_twist_g)
        Rf, Rg = Tf[:3, :3], Tg[:3, :3]
        phi = gtsam.Rot3.Logmap(gtsam.Rot3(Rg @ Rf.T))
        e = np.concatenate([phi - dt_s * xf[:3], Tg[:3, 3] - Tf[:3, 3] - dt_s * xf[3:],
                            xg - xf])
        if H is not None:
            Jinv = _so3_right_jacobian_inverse(phi)
            Hf, Hg = np.zeros((12, 6)), np.zeros((12, 6))
            Hf[:3, :3], Hg[:3, :3] = -Jinv @ Rf, Jinv @ Rf
            Hf[3:6, 3:], Hg[3:6, 3:] = -Rf, Rg
            Hwf, Hwg = np.zeros((12, 6)), np.zeros((12, 6))
            Hwf[:3, :3], Hwf[3:6, 3:] = -dt_s * eye, -dt_s * eye
            Hwf[6:, :], Hwg[6:, :] = -np.eye(6), np.eye(6)
            H[0], H[1], H[2], H[3] = Hf, Hwf, Hg, Hwg
        return e

    return gtsam.CustomFactor(noise, [key_board_f, key_twist_f, key_board_g, key_twist_g],
                              error)


def twist_from_poses(T_f: np.ndarray, T_g: np.ndarray, dt_s: float) -> np.ndarray:
    """The twist ``[w, v]`` that moves ``T_f`` to ``T_g`` in ``dt_s`` (the module's
    convention): a starting value for a linked set's twist."""
    phi = gtsam.Rot3.Logmap(gtsam.Rot3(T_g[:3, :3] @ T_f[:3, :3].T))
    return np.concatenate([phi, T_g[:3, 3] - T_f[:3, 3]]) / dt_s


@dataclass(frozen=True)
class TimeModel:
    """The bundle adjustment's time estimates (``bundle.time: refine``).

    Per camera: ``offset_ms`` (its clock's offset from the reference beyond what its
    timestamps say; the whole offset without timestamps) and ``readout_ms`` (first to last
    row), with marginal 1-sigmas. Per frame set: the board's ``twist`` ``[w (rad/s), v (m/s)]``
    (reference frame) and its sigmas. ``anchored``: the cameras whose offsets are anchored by
    timestamps; with none, the time scale is a gauge (docs/conventions.md 'Time') and the
    offsets, readouts and speeds are known only up to a common factor (the poses are not
    affected). ``capture_ms``: the timestamps' per-view offsets used; ``twist_prior`` the
    twist prior's sigmas the final solve used (estimated from the data by default)."""

    offset_ms: dict[str, float]
    sigma_offset_ms: dict[str, float]
    readout_ms: dict[str, float]
    sigma_readout_ms: dict[str, float]
    twist: dict[str, np.ndarray]
    sigma_twist: dict[str, np.ndarray]
    anchored: tuple[str, ...] = ()
    capture_ms: dict[tuple[str, str], float] | None = None
    twist_prior: TwistPrior | None = None  # the twist prior's sigmas in the final solve
    # continuous recordings: the linked sets' accelerations [alpha, a] (rad/s^2, m/s^2), how
    # many sets the motion prior linked, and its scale in the final solve
    acceleration: dict[str, np.ndarray] = field(default_factory=dict)
    linked_sets: int = 0
    motion_prior: MotionPrior | None = None
    # each camera's offset prior sigma (ms): the timestamps' jitter where they anchor it, else
    # the wide prior of frames matched by index (nothing bounds them but a recording's sense)
    offset_prior_sigma_ms: dict[str, float] = field(default_factory=dict)

    @property
    def speed_mps(self) -> dict[str, float]:
        """The board's speed in each frame set (m/s, at the board origin)."""
        return {v: float(np.linalg.norm(t[3:])) for v, t in self.twist.items()}

    @property
    def rate_dps(self) -> dict[str, float]:
        """The board's turn rate in each frame set (deg/s)."""
        return {v: float(np.degrees(np.linalg.norm(t[:3]))) for v, t in self.twist.items()}

    def project(self, camera: str, view: str, T_ref_cam: np.ndarray, T_ref_board: np.ndarray,
                model: CameraIntrinsics, P_b: np.ndarray, rows_px: np.ndarray) -> np.ndarray:
        """Pixels (N,2) of board points ``P_b`` (N,3, m) seen by ``camera`` in ``view``, each
        at the time of its image row ``rows_px`` (N,): :func:`project_timed` through the
        camera ``model`` with this model's clock and twist; at the set's instant when the
        camera or view was not in the solve."""
        if camera not in self.offset_ms or view not in self.twist:
            time_ms, twist = np.zeros(2), np.zeros(6)
        else:
            known = (self.capture_ms or {}).get((camera, view), 0.0)
            time_ms = np.array([self.offset_ms[camera] + known, self.readout_ms[camera]])
            twist = self.twist[view]
        return project_timed(T_ref_cam, T_ref_board, twist, time_ms, model, P_b,
                             row_fraction(rows_px, model.height), False,
                             accel=self.acceleration.get(view))[0]

    def board_at_capture(self, camera: str, view: str, T_ref_board: np.ndarray,
                         lever_m: float) -> tuple[np.ndarray, float] | None:
        """The board pose of set ``view`` (``T_ref_board``: at the set's instant) at
        ``camera``'s capture, under the set's twist and acceleration; with how uncertain that
        makes a board point ``lever_m`` from the board origin (mm: the twist's sigmas times the
        time moved). The capture is the camera's offset (timestamps plus estimate): the middle
        row of its colour image is exposed then (:func:`row_fraction`, docs/conventions.md
        'Time'), and its global-shutter depth image with it. None when the set or camera was
        not solved."""
        if view not in self.twist or camera not in self.offset_ms:
            return None
        known = (self.capture_ms or {}).get((camera, view))
        offset = (self.offset_ms[camera] + known if known is not None
                  else self.total_offset_ms(camera))
        tau_ms = offset
        w, v = self.twist[view][:3], self.twist[view][3:]
        acc = self.acceleration.get(view)
        T = pose_after_twist(T_ref_board, v, w, MS * tau_ms,
                             None if acc is None else acc[3:], None if acc is None else acc[:3])
        sw, sv = self.sigma_twist[view][:3], self.sigma_twist[view][3:]
        return T, float((np.linalg.norm(sv) + np.linalg.norm(sw) * lever_m) * abs(tau_ms))

    def total_offset_ms(self, camera: str) -> float:
        """The camera's median capture time after the reference's: its timestamps' median
        offset plus the estimated one."""
        known = [t for (c, _), t in (self.capture_ms or {}).items() if c == camera]
        return self.offset_ms[camera] + (float(np.median(known)) if known else 0.0)

    def to_dict(self) -> dict:
        speed = np.array(list(self.speed_mps.values()) or [0.0])
        rate = np.array(list(self.rate_dps.values()) or [0.0])
        return {
            "anchored_by_timestamps": sorted(self.anchored),
            # how the frame sets were matched, which is what bounds the offsets a priori
            "frames_matched_by": "timestamps" if self.anchored else "index",
            "cameras": {c: {"offset_ms": self.total_offset_ms(c),
                            "offset_beyond_timestamps_ms": self.offset_ms[c],
                            "offset_sigma_ms": self.sigma_offset_ms[c],
                            "offset_prior_sigma_ms": self.offset_prior_sigma_ms.get(c),
                            "readout_ms": self.readout_ms[c],
                            "readout_sigma_ms": self.sigma_readout_ms[c]}
                        for c in sorted(self.offset_ms)},
            "board_speed_mps": {"median": float(np.median(speed)), "max": float(speed.max())},
            "board_rate_dps": {"median": float(np.median(rate)), "max": float(rate.max())},
        } | ({"linked_sets": self.linked_sets,
              "motion_prior": {"q_mps": self.motion_prior.q_mps,
                               "q_dps": self.motion_prior.q_dps}}
             if self.linked_sets and self.motion_prior is not None else {})
