"""The time model (rgbd_calib.solve.time_model) on exact synthetic corners: its view factor,
and the bundle adjustment solving it (``bundle.time: refine``).

No renderer: a few cameras look at a board grid; each frame set's board moves with a twist,
each camera has a clock offset and a rolling-shutter readout (the shared convention of issue
32), and each corner is projected at its own row's time by solving the implicit row equation
to convergence, so its 'measured' row is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.config import BundleConfig
from rgbd_calib.core.geometry import (
    invert_transform,
    look_at,
    make_transform,
    rotvec_to_matrix,
    transform_error,
)
from rgbd_calib.solve.bundle import BundleProblem, MarkerMeasurement, bundle_adjust
from rgbd_calib.solve.bundle_factors import project_board, view_factor
from rgbd_calib.solve.time_model import (
    HELD_SIGMA,
    TimePrior,
    TwistPrior,
    project_timed,
    time_prior,
    timed_view_factor,
    twist_prior,
)

WIDTH, HEIGHT = 640, 360
K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 179.5], [0.0, 0.0, 1.0]])
SPEED_MPS, RATE_DPS = 0.3, 30.0
READOUT_MS = 25.0  # every camera's rolling-shutter readout, first to last row
OFFSET_MAX_MS = 16.0  # non-reference offsets uniform in +-this
NOISE_FREE_REL = 1e-6  # noise-free recovery, relative (times, twists) / m and rad (poses)
JACOBIAN_RTOL = 1e-6
SAME_POSE_M, SAME_POSE_RAD = 1e-9, 1e-9  # still board: timed and timeless solves agree


@dataclass(frozen=True)
class Scene:
    T_ref_cam: dict[str, np.ndarray]
    T_ref_board: dict[str, np.ndarray]  # at t_f
    twist: dict[str, np.ndarray]  # [w rad/s, v m/s], reference frame
    offset_ms: dict[str, float]
    readout_ms: dict[str, float]
    measurements: list[MarkerMeasurement]


def board_points() -> np.ndarray:
    """(12,4,3) corners of a 4x3 grid of 8 cm markers at a 12 cm pitch, board frame (m)."""
    square = np.array([[0, 0, 0], [0.08, 0, 0], [0.08, 0.08, 0], [0, 0.08, 0]], dtype=float)
    return np.stack([square + [0.12 * i, 0.12 * j, 0.0] for j in range(3) for i in range(4)])


def project_exact(T_ref_cam, T_ref_board, twist, offset_ms, readout_ms, P_b) -> np.ndarray:
    """Pixels (N,2) of board points, each at the time of the row it is imaged on: the
    convention written out independently of the module (rotvec_to_matrix for Exp), the row
    equation v = proj_v(T(t(v))) iterated to a fixed point (it contracts by line delay x image
    speed, ~1e-2 per step)."""
    T_cam_ref = invert_transform(T_ref_cam)
    R_f, p_f = T_ref_board[:3, :3], T_ref_board[:3, 3]
    out = np.empty((len(P_b), 2))
    for i, P in enumerate(P_b):
        v_row = (HEIGHT - 1) / 2.0
        for _ in range(100):
            tau = 1e-3 * (offset_ms + readout_ms * (v_row - (HEIGHT - 1) / 2.0) / (HEIGHT - 1))
            P_ref = rotvec_to_matrix(twist[:3] * tau) @ R_f @ P + p_f + twist[3:] * tau
            p = T_cam_ref[:3, :3] @ P_ref + T_cam_ref[:3, 3]
            uv = K[:2, :2] @ (p[:2] / p[2]) + K[:2, 2]
            done = abs(uv[1] - v_row) < 1e-12
            v_row = uv[1]
            if done:
                break
        out[i] = uv
    return out


def make_scene(seed: int, n_cams: int = 4, n_sets: int = 6, moving: bool = True,
               readout_ms: float = READOUT_MS, noise_px: float = 0.0) -> Scene:
    """Cameras on an arc 1.6 m around the board, boards facing them; per set a twist of
    SPEED_MPS along a random direction and RATE_DPS about a random axis; offsets drawn in
    +-OFFSET_MAX_MS (reference 0); every corner inside the image."""
    rng = np.random.default_rng(seed)
    centre = np.array([0.0, 0.0, 1.2])
    angles = np.radians(np.linspace(-40, 40, n_cams))
    eyes = [centre + 1.6 * np.array([np.sin(a), -np.cos(a), 0.0]) for a in angles]
    eyes = [eyes[n_cams // 2]] + eyes[:n_cams // 2] + eyes[n_cams // 2 + 1:]  # reference mid
    T_world_cam = [look_at(e, centre + rng.normal(0, 0.05, 3)) for e in eyes]
    T_ref_world = invert_transform(T_world_cam[0])
    cams = [f"cam{i}" for i in range(n_cams)]
    T_ref_cam = {c: T_ref_world @ T for c, T in zip(cams, T_world_cam)}
    offset = {c: (0.0 if i == 0 else float(rng.uniform(-OFFSET_MAX_MS, OFFSET_MAX_MS)))
              for i, c in enumerate(cams)}
    readout = dict.fromkeys(cams, readout_ms)
    P_b = board_points().reshape(-1, 3)
    half = np.array([0.22, 0.16, 0.0])  # board-frame centre of the grid
    boards, twists, meas = {}, {}, []
    for f in range(n_sets):
        view = f"set{f:02d}"
        while True:
            c_world = centre + rng.uniform([-0.15, -0.2, -0.15], [0.15, 0.2, 0.15])
            R = look_at(c_world, np.mean(eyes, axis=0))[:3, :3]
            R = rotvec_to_matrix(rng.normal(0, 0.2, 3)) @ R
            T_world_board = make_transform(R, c_world - R @ half)
            T_b = T_ref_world @ T_world_board
            d = rng.normal(size=(2, 3))
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            tw = (np.r_[np.radians(RATE_DPS) * d[0], SPEED_MPS * d[1]] if moving
                  else np.zeros(6))
            tw[:3] = T_ref_world[:3, :3] @ tw[:3]
            tw[3:] = T_ref_world[:3, :3] @ tw[3:]
            uvs = {c: project_exact(T_ref_cam[c], T_b, tw, offset[c], readout[c], P_b)
                   for c in cams}
            if all(np.all((uv > 5) & (uv < [WIDTH - 6, HEIGHT - 6])) for uv in uvs.values()):
                break
        boards[view], twists[view] = T_b, tw
        for c in cams:
            uv = uvs[c] + rng.normal(0, noise_px, uvs[c].shape) if noise_px else uvs[c]
            for m in range(len(P_b) // 4):
                meas.append(MarkerMeasurement(c, view, m, uv[4 * m:4 * m + 4],
                                              P_b[4 * m:4 * m + 4]))
    return Scene(T_ref_cam, boards, twists, offset, readout, meas)


def perturbed(T: np.ndarray, rng: np.random.Generator, rot_rad: float = 0.01,
              trans_m: float = 0.01) -> np.ndarray:
    return T @ make_transform(rotvec_to_matrix(rng.normal(0, rot_rad, 3)),
                              rng.normal(0, trans_m, 3))


@dataclass(frozen=True)
class Solved:
    """What a test reads of a timed bundle adjustment (BundleResult and its TimeModel)."""

    T_ref_cam: dict
    T_ref_board: dict
    twist: dict
    offset_ms: dict
    readout_ms: dict
    sigma_offset_ms: dict
    sigma_readout_ms: dict
    sigma_twist: dict
    residual_rms_px: float


def solve_timed(measurements, cams, init_cam, init_board, *, pixel_sigma: float,
                time_priors=None, twist_sigma: TwistPrior = TwistPrior(),
                max_iterations: int = 100, from_data: bool = False) -> Solved:
    """The bundle adjustment with ``bundle.time: refine``: board and intrinsics held, no
    robust kernel, marginals at the given corner sigma (as the tests' noise is known), the
    twist prior as given (``from_data``: estimated from the twists)."""
    config = BundleConfig(time="refine", board="fixed", intrinsics="fixed", robust="none",
                          estimate_sigma=False, pixel_sigma=pixel_sigma,
                          max_iterations=max_iterations, relative_error_tol=1e-12,
                          time_twist_sigma_mps=twist_sigma.sigma_mps,
                          time_twist_sigma_dps=twist_sigma.sigma_dps,
                          time_twist_prior_from_data=from_data)
    model = CameraIntrinsics(WIDTH, HEIGHT, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    r = bundle_adjust(BundleProblem(measurements, dict.fromkeys(cams, K), "cam0", init_cam,
                                    init_board, config, intrinsics=dict.fromkeys(cams, model),
                                    time_priors=time_priors))
    t = r.time
    rms = np.array([x[3] for x in r.residuals_px])
    return Solved(r.T_ref_cam, r.T_ref_board, t.twist, t.offset_ms, t.readout_ms,
                  t.sigma_offset_ms, t.sigma_readout_ms, t.sigma_twist,
                  float(np.sqrt(np.mean(rms**2))))


def solve_scene(scene: Scene, seed: int, pixel_sigma: float, **kwargs) -> Solved:
    rng = np.random.default_rng(seed + 1000)
    return solve_timed(scene.measurements, list(scene.T_ref_cam),
                       {c: perturbed(T, rng) for c, T in scene.T_ref_cam.items()},
                       {v: perturbed(T, rng) for v, T in scene.T_ref_board.items()},
                       pixel_sigma=pixel_sigma, **kwargs)


# the time scale's anchor: the reference camera's readout known (a sensor property)
ANCHOR = {"cam0": TimePrior(readout_ms=READOUT_MS, readout_sigma_ms=1e-6)}


def _factor_values(rng):
    T_cam = perturbed(np.eye(4), rng, 0.2, 0.1)
    T_board = make_transform(rotvec_to_matrix([np.pi + 0.2, 0.1, -0.3]), [-0.2, -0.1, 1.3])
    values = gtsam.Values()
    values.insert(1, gtsam.Pose3(T_cam))
    values.insert(2, gtsam.Pose3(T_board))
    values.insert(3, np.r_[rng.normal(0, 0.5, 3), rng.normal(0, 0.3, 3)])
    values.insert(4, np.array([7.3, 24.0]))
    return values


def _central_differences(factor, values: gtsam.Values, key: int, dim: int, pose: bool,
                         steps: np.ndarray) -> np.ndarray:
    """d(error)/d(variable ``key``) of ``factor`` at ``values`` by central differences, step
    ``steps[j]`` on coordinate j: a Pose3 moved by its retract (``pose``), a vector by adding."""
    numeric = []
    for j, h in enumerate(steps):
        plus, minus = gtsam.Values(values), gtsam.Values(values)
        delta = np.zeros(dim)
        delta[j] = h
        if pose:
            plus.update(key, values.atPose3(key).retract(delta))
            minus.update(key, values.atPose3(key).retract(-delta))
        else:
            plus.update(key, values.atVector(key) + delta)
            minus.update(key, values.atVector(key) - delta)
        numeric.append((factor.unwhitenedError(plus) - factor.unwhitenedError(minus)) / (2 * h))
    return np.stack(numeric, axis=1)


def test_jacobians_match_central_differences(rng):
    """Every Jacobian block of the timed view factor (camera, board at t_f, twist, time) equals
    central differences of its error (Pose3 retract, vector add) to rtol 1e-6 (atol 1e-6 of
    the block's largest entry); no robust kernel (its re-weighting is robust_rows', shared with
    the timeless factors)."""
    values = _factor_values(rng)
    obj = board_points()
    px = project_timed(values.atPose3(1).matrix(), values.atPose3(2).matrix(),
                       values.atVector(3), values.atVector(4), K, obj.reshape(-1, 3),
                       np.zeros(48), False)[0].reshape(-1, 4, 2) + rng.normal(0, 2.0, (12, 4, 2))
    factor = timed_view_factor(1, 2, 3, 4, K, HEIGHT, obj, px, 0.5, "none", 3.0)
    A, _ = factor.linearize(values).jacobian()
    col = 0
    for key, dim, pose in ((1, 6, True), (2, 6, True), (3, 6, False), (4, 2, False)):
        numeric = _central_differences(factor, values, key, dim, pose, np.full(dim, 1e-6))
        block = A[:, col:col + dim]
        scale = np.abs(numeric).max()
        assert scale > 1e-3, f"key {key}: the data do not depend on it"
        np.testing.assert_allclose(block, numeric, rtol=JACOBIAN_RTOL,
                                   atol=JACOBIAN_RTOL * scale, err_msg=f"key {key}")
        col += dim


def test_no_time_projects_as_the_timeless_factor(rng):
    """With a zero twist the timed projection and its pose Jacobians are the timeless ones
    (bundle_factors.project_board), whatever the time parameters."""
    values = _factor_values(rng)
    P_b = board_points().reshape(-1, 3)
    T_cam, T_board = values.atPose3(1).matrix(), values.atPose3(2).matrix()
    uv0, J_cam0, J_board0 = project_board(T_cam, T_board, K, P_b)
    uv, (J_cam, J_board, _, J_time, _) = project_timed(T_cam, T_board, np.zeros(6),
                                                   np.array([12.0, 30.0]), K, P_b,
                                                   rng.uniform(-0.5, 0.5, len(P_b)))
    np.testing.assert_allclose(uv, uv0, atol=1e-12)
    np.testing.assert_allclose(J_cam, J_cam0, atol=1e-9)
    np.testing.assert_allclose(J_board, J_board0, atol=1e-9)
    assert np.all(J_time == 0.0)


def test_time_scale_is_a_gauge():
    """Times x a and twists / a give the same pixels (only w tau, v tau are seen): the reason
    the time scale needs an anchor."""
    scene = make_scene(3, n_sets=1)
    v = "set00"
    P_b = board_points().reshape(-1, 3)
    s = np.linspace(-0.5, 0.5, len(P_b))
    for c, T in scene.T_ref_cam.items():
        t = np.array([scene.offset_ms[c], scene.readout_ms[c]])
        uv = project_timed(T, scene.T_ref_board[v], scene.twist[v], t, K, P_b, s, False)[0]
        uv2 = project_timed(T, scene.T_ref_board[v], scene.twist[v] / 2.5, 2.5 * t, K, P_b, s,
                            False)[0]
        still = project_timed(T, scene.T_ref_board[v], np.zeros(6), t, K, P_b, s, False)[0]
        np.testing.assert_allclose(uv2, uv, atol=1e-9)
        assert np.abs(still - uv).max() > 0.5  # the motion itself is seen (px)


def test_exact_corners_follow_the_factor():
    """The exactly projected corners (implicit row equation) are the factor's prediction at the
    truth: the measured-row approximation is exact when the measured row is exact."""
    scene = make_scene(4, n_sets=2)
    for m in scene.measurements[:48]:
        s = (m.corners_px[:, 1] - (HEIGHT - 1) / 2) / (HEIGHT - 1)
        uv = project_timed(scene.T_ref_cam[m.camera], scene.T_ref_board[m.view],
                           scene.twist[m.view],
                           np.array([scene.offset_ms[m.camera], scene.readout_ms[m.camera]]),
                           K, m.object_points, s, False)[0]
        np.testing.assert_allclose(uv, m.corners_px, atol=1e-9)


def _assert_recovered(sol, scene, rel):
    for c in scene.T_ref_cam:
        deg, mm = transform_error(sol.T_ref_cam[c], scene.T_ref_cam[c])
        assert mm / 1000 < rel and np.radians(deg) < rel, (c, mm, deg)
        assert abs(sol.offset_ms[c] - scene.offset_ms[c]) < rel * OFFSET_MAX_MS, c
        assert abs(sol.readout_ms[c] - scene.readout_ms[c]) < rel * READOUT_MS, c
    for v, tw in scene.twist.items():
        deg, mm = transform_error(sol.T_ref_board[v], scene.T_ref_board[v])
        assert mm / 1000 < rel and np.radians(deg) < rel, (v, mm, deg)
        np.testing.assert_allclose(sol.twist[v], tw, atol=rel * np.abs(tw).max())


def test_noise_free_recovers_offsets_readouts_twists_and_poses():
    """Exact corners, poses perturbed by ~1 cm / 0.6 deg, twists 0, offsets 0, readouts 0 except
    the reference's (the anchor, known): with the priors 1000x weaker than the defaults every
    offset, readout, twist and pose comes back to 1e-6; with the default weak priors their pull
    stays under a tenth of a sigma (it is ~1e-3 of the values at a 0.1 px corner sigma)."""
    scene = make_scene(0)
    weak = {c: TimePrior(readout_ms=READOUT_MS if c == "cam0" else 0.0,
                         readout_sigma_ms=1e-6 if c == "cam0" else 5e4, offset_sigma_ms=5e4)
            for c in scene.T_ref_cam}
    sol = solve_scene(scene, 0, pixel_sigma=0.1, time_priors=weak,
                      twist_sigma=TwistPrior(sigma_mps=3e3, sigma_dps=3e5))
    assert sol.residual_rms_px < 1e-6
    _assert_recovered(sol, scene, NOISE_FREE_REL)
    default = solve_scene(scene, 0, pixel_sigma=0.1, time_priors=ANCHOR)
    for c in list(scene.T_ref_cam)[1:]:
        assert abs(default.offset_ms[c] - scene.offset_ms[c]) < 0.1 * default.sigma_offset_ms[c]
        assert abs(default.readout_ms[c] - READOUT_MS) < 0.1 * default.sigma_readout_ms[c]


def test_without_an_anchor_poses_and_time_ratios_are_right_the_scale_is_not():
    """No anchor, default priors, a rough readout guess of 10 +- 50 ms for every camera (also
    the initial value): the priors set the time scale, so the offsets come out scaled by one
    common factor (0.7 here) with sigmas that say so (error within 3 sigma), while the pixels,
    every pose and the scale-free ratios offset_c / readout_ref are right."""
    scene = make_scene(1)
    guess = {c: TimePrior(readout_ms=10.0) for c in scene.T_ref_cam}
    sol = solve_scene(scene, 1, pixel_sigma=0.1, time_priors=guess, max_iterations=300)
    assert sol.residual_rms_px < 1e-4
    scale = sol.readout_ms["cam0"] / READOUT_MS
    assert abs(scale - 1.0) > 0.1  # the priors' choice, not the truth
    for c, T in scene.T_ref_cam.items():
        deg, mm = transform_error(sol.T_ref_cam[c], T)
        assert mm < 0.01 and deg < 1e-3, (c, mm, deg)
        ratio = sol.offset_ms[c] / sol.readout_ms["cam0"]
        assert abs(ratio - scene.offset_ms[c] / READOUT_MS) < 1e-4, c
        assert abs(sol.readout_ms[c] / sol.readout_ms["cam0"] - 1.0) < 1e-4, c
        if c != "cam0":
            assert abs(sol.offset_ms[c] - scene.offset_ms[c]) < 3 * sol.sigma_offset_ms[c], c


def test_noisy_offsets_within_three_sigma_and_sigmas_honest():
    """0.1 px corner noise over 6 seeds: every offset within 3 sigma of the truth; the RMS of
    error / sigma of the offsets and readouts in 0.5-2 (the claimed sigmas are honest)."""
    z_offset, z_readout = [], []
    for seed in range(6):
        scene = make_scene(10 + seed, noise_px=0.1)
        sol = solve_scene(scene, seed, pixel_sigma=0.1, time_priors=ANCHOR)
        for c in list(scene.T_ref_cam)[1:]:
            z = (sol.offset_ms[c] - scene.offset_ms[c]) / sol.sigma_offset_ms[c]
            assert abs(z) < 3.0, (seed, c, sol.offset_ms[c], scene.offset_ms[c],
                                  sol.sigma_offset_ms[c])
            z_offset.append(z)
            z_readout.append((sol.readout_ms[c] - READOUT_MS) / sol.sigma_readout_ms[c])
    rms_off, rms_ro = np.sqrt(np.mean(np.square(z_offset))), np.sqrt(np.mean(np.square(z_readout)))
    assert 0.5 <= rms_off <= 2.0, rms_off
    assert 0.5 <= rms_ro <= 2.0, rms_ro


def test_still_board_global_shutter_keeps_the_timeless_solution():
    """Twist 0 and no rolling shutter, 0.1 px noise: the time parameters and twists are
    unobservable (zero Jacobians at twist 0 and offset 0): they stay at their priors' means
    with the priors' sigmas, and the poses equal those of the timeless view factor to 1e-9."""
    scene = make_scene(2, moving=False, readout_ms=0.0, noise_px=0.1)
    rng = np.random.default_rng(77)
    init_cam = {c: perturbed(T, rng) for c, T in scene.T_ref_cam.items()}
    init_board = {v: perturbed(T, rng) for v, T in scene.T_ref_board.items()}
    cams = list(scene.T_ref_cam)
    held = dict.fromkeys(cams, TimePrior(readout_sigma_ms=HELD_SIGMA))  # global shutters
    sol = solve_timed(scene.measurements, cams, init_cam, init_board, pixel_sigma=0.1,
                      time_priors=held)
    prior = TimePrior()
    for c in cams[1:]:
        assert sol.offset_ms[c] == 0.0 and abs(sol.readout_ms[c]) < 1e-8
        assert abs(sol.sigma_offset_ms[c] / prior.offset_sigma_ms - 1) < 1e-6
    for v in scene.T_ref_board:
        np.testing.assert_allclose(sol.twist[v], 0.0, atol=0.0)
        np.testing.assert_allclose(sol.sigma_twist[v][3:], TwistPrior().sigma_mps, rtol=1e-6)
    # the timeless graph: same markers, same reference prior, same solver
    cam_key = {c: gtsam.symbol("c", i) for i, c in enumerate(sorted(cams))}
    views = sorted(scene.T_ref_board)
    view_key = {v: gtsam.symbol("b", i) for i, v in enumerate(views)}
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for c in cams:
        for v in views:
            ms = [m for m in scene.measurements if m.camera == c and m.view == v]
            graph.add(view_factor(cam_key[c], view_key[v], K,
                                  np.stack([m.object_points for m in ms]),
                                  np.stack([m.corners_px for m in ms]), 0.1, "none", 3.0))
        values.insert(cam_key[c], gtsam.Pose3(np.eye(4) if c == "cam0" else init_cam[c]))
    for v in views:
        values.insert(view_key[v], gtsam.Pose3(init_board[v]))
    graph.add(gtsam.PriorFactorPose3(cam_key["cam0"], gtsam.Pose3(),
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    timeless = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    for c in cams:
        deg, mm = transform_error(sol.T_ref_cam[c], timeless.atPose3(cam_key[c]).matrix())
        assert mm / 1000 < SAME_POSE_M and np.radians(deg) < SAME_POSE_RAD, (c, mm, deg)
    deg, mm = transform_error(sol.T_ref_cam["cam1"], scene.T_ref_cam["cam1"])
    assert mm > 1e-4  # the noise moved it off the truth: the agreement is not trivial


def test_prior_factors_hold_the_gauge():
    """The reference's offset prior is tight, its readout free with a rolling shutter; a global
    shutter's readout is held; the twist prior has the stated sigmas."""
    ref = time_prior(1, reference=True, rolling_shutter=True).noiseModel().sigmas()
    glob = time_prior(2, TimePrior(offset_sigma_ms=20.0), rolling_shutter=False)
    assert ref[0] == HELD_SIGMA <= 1e-6 and ref[1] == 50.0  # held: 1e-6 ms
    np.testing.assert_allclose(glob.noiseModel().sigmas(), [20.0, HELD_SIGMA])
    tw = twist_prior(3, TwistPrior(sigma_mps=2.0, sigma_dps=180.0)).noiseModel().sigmas()
    np.testing.assert_allclose(tw, [np.pi] * 3 + [2.0] * 3)


def test_jacobians_with_a_refined_lens_a_moving_face_and_timestamps(rng):
    """The timed factor with everything else the bundle adjustment may free at once: the
    intrinsics (raw pixels through k1 k2 p1 p2), a back sheet whose pose moves the back-face
    markers, and a view's timestamp offset added to the camera's clock: every block (camera,
    board, intrinsics, sheet, twist, time) equals central differences; the timestamp offset
    acts as the same shift of the camera's offset."""
    values = _factor_values(rng)
    base = CameraIntrinsics(WIDTH, HEIGHT, 500.0, 505.0, 318.0, 181.0, (0.05, -0.02, 1e-3, -5e-4))
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")
    values.insert(5, np.array([502.0, 503.0, 320.0, 180.0, 0.04, -0.01, 5e-4, -2e-4]))
    values.insert(6, gtsam.Pose3(make_transform(rotvec_to_matrix([0, 0, 0.01]),
                                                [0.002, -0.001, 0.0005])))
    obj = board_points()
    back = np.arange(12) >= 6  # the last six markers on the back sheet
    obj[back, :, 2] = -0.006
    px = project_timed(values.atPose3(1).matrix(), values.atPose3(2).matrix(),
                       values.atVector(3), values.atVector(4), base, obj.reshape(-1, 3),
                       np.zeros(48), False)[0].reshape(-1, 4, 2) + rng.normal(0, 2.0, (12, 4, 2))
    factor = timed_view_factor(1, 2, 3, 4, None, HEIGHT, obj, px, 0.5, "none", 3.0,
                               intr=(5, base), names=names, moving=[(6, back, None)],
                               known_ms=-4.0)
    A, _ = factor.linearize(values).jacobian()
    col = 0
    for key, dim, pose in ((1, 6, True), (2, 6, True), (5, 8, False), (6, 6, True),
                           (3, 6, False), (4, 2, False)):
        steps = np.full(dim, 1e-6) if pose or key != 5 else (
            1e-6 * np.maximum(np.abs(values.atVector(5)), 1e-3))  # relative for the lens
        numeric = _central_differences(factor, values, key, dim, pose, steps)
        block = A[:, col:col + dim]
        scale = np.abs(numeric).max()
        assert scale > 1e-3, f"key {key}: the data do not depend on it"
        np.testing.assert_allclose(block, numeric, rtol=1e-5, atol=1e-5 * scale,
                                   err_msg=f"key {key}")
        col += dim
    # the timestamp offset is a shift of the camera's clock
    shifted = gtsam.Values(values)
    shifted.update(4, values.atVector(4) + [-4.0, 0.0])
    plain = timed_view_factor(1, 2, 3, 4, None, HEIGHT, obj, px, 0.5, "none", 3.0,
                              intr=(5, base), names=names, moving=[(6, back, None)])
    np.testing.assert_allclose(plain.unwhitenedError(shifted), factor.unwhitenedError(values),
                               atol=1e-12)


def test_the_twist_prior_comes_from_the_data():
    """The wide configured twist prior (0.5 m/s, 60 deg/s per axis) is re-estimated from the
    sets' twists (empirical Bayes): with the board at SPEED_MPS and RATE_DPS along random
    directions, each axis' RMS is speed / sqrt(3); the estimate lands within 35 % of it (6
    sets: the RMS of 18 draws), and the offsets stay within 3 sigma."""
    scene = make_scene(5, noise_px=0.1)
    sol = bundle_solve(scene, from_data=True)
    prior = sol.time.twist_prior
    assert abs(prior.sigma_mps / (SPEED_MPS / np.sqrt(3)) - 1) < 0.35, prior
    assert abs(prior.sigma_dps / (RATE_DPS / np.sqrt(3)) - 1) < 0.35, prior
    fixed = bundle_solve(scene, from_data=False).time.twist_prior
    assert (fixed.sigma_mps, fixed.sigma_dps) == (0.5, 60.0)
    for c in list(scene.T_ref_cam)[1:]:
        assert abs(sol.time.offset_ms[c] - scene.offset_ms[c]) < 3 * sol.time.sigma_offset_ms[c]


def bundle_solve(scene: Scene, from_data: bool):
    """The default bundle configuration with time (the twist prior from the data or not),
    anchored by the reference's known readout, corners at 0.1 px."""
    rng = np.random.default_rng(99)
    cams = list(scene.T_ref_cam)
    config = BundleConfig(time="refine", board="fixed", intrinsics="fixed", pixel_sigma=0.1,
                          time_twist_prior_from_data=from_data)
    model = CameraIntrinsics(WIDTH, HEIGHT, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    return bundle_adjust(BundleProblem(
        scene.measurements, dict.fromkeys(cams, K), "cam0",
        {c: perturbed(T, rng) for c, T in scene.T_ref_cam.items()},
        {v: perturbed(T, rng) for v, T in scene.T_ref_board.items()}, config,
        intrinsics=dict.fromkeys(cams, model), time_priors=ANCHOR))
