"""The bundle stage run on a pose graph's result: its measurements, the sound-first solve, the
self-calibration ladder's solves and the model-error sigmas.

:func:`self_calibrated_bundle` solves the bundle adjustment with ``bundle.board`` /
``bundle.intrinsics``: once for an explicit mode, or up the ladder of models whose decisions
(which model next, is it better) are :mod:`rgbd_calib.solve.selfcal`'s. Every solve is one
:class:`~rgbd_calib.solve.bundle.BundleProblem` built by :func:`bundle_problem` and solved by
:func:`bundle_sound_first`; a caller re-solves it with ``dataclasses.replace`` (re-detected
corners, depth pairs). :func:`edge_offset_modelled` solves it again with each camera's
detector edge offset taken out of its corners where the residuals read one.
:func:`model_error_sigmas` makes the result's uncertainty honest when the pose graph found
cameras with a model error.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, replace

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.config import BundleConfig
from ..core.errors import CalibrationError
from ..core.progress import Progress, Tick, start
from ..model.board import Board
from ..model.results import CameraExtrinsics
from ..model.rig import Rig
from . import blocks, edge_offset, selfcal
from .bundle import bundle_adjust
from .bundle_factors import lens_names
from .bundle_problem import BundleProblem, BundleResult, MarkerMeasurement
from .pose import BoardObservation
from .posegraph import PoseGraphResult
from .posegraph_init import robust_mean_pose
from .time_model import anchored_priors

# a refined lens that images the detected corners' rays within this of the lens they were
# detected with has settled: no other detection (see lens_moved)
LENS_SETTLED_PX = 0.1
# a flagged camera whose corners fit within 2x the rig's RMS once the board or intrinsics
# were refined had its model error explained by them (see model_error_sigmas)
MODEL_ERROR_EXPLAINED = 4.0
# what a failed solve of a richer model raises: the model is not accepted, the ladder goes on
_SOLVE_ERRORS = (CalibrationError, RuntimeError, ValueError, np.linalg.LinAlgError)


# ----------------------------------------------------------------------------- the problem
def camera_matrices(rig: Rig) -> dict[str, np.ndarray]:
    """The 3x3 pinhole matrix of every camera of ``rig``."""
    return {c: rig.cameras[c].K for c in rig.names}


def face_frames(board: Board) -> dict[int, np.ndarray] | None:
    """A multi-face target's nominal face poses ``T_board_face`` (label -> 4x4, m) of the faces
    the board self-calibration may move (all but the reference face); None for a flat board
    (its back sheet is the :func:`back_centre` model)."""
    if not board.sheets:
        return None
    return {s.label: s.T_board_face for s in board.sheets if s.label != board.reference_face}


def back_centre(board: Board) -> np.ndarray | None:
    """Board-file centre (m) of the back-marker grid (its xy bounding box, on the back face):
    where the back sheet's offset is reported; None for a one-sided board."""
    back = board.corners[board.faces < 0].reshape(-1, 3)
    if not len(back):
        return None
    return np.r_[(back[:, :2].min(axis=0) + back[:, :2].max(axis=0)) / 2, -board.thickness]


def bundle_problem(measurements: list[MarkerMeasurement], rig: Rig, board: Board,
                   T_ref_cam: dict[str, np.ndarray], T_ref_board: dict[str, np.ndarray],
                   config: BundleConfig,
                   fixed_cameras: dict[str, np.ndarray] | None = None,
                   capture_ms: dict[tuple[str, str], float] | None = None,
                   set_ms: dict[str, float] | None = None) -> BundleProblem:
    """The bundle adjustment of ``measurements`` with ``rig``'s cameras (their pinhole
    matrices, and their models as the priors of refined intrinsics and their image heights for
    the time model) and ``board``'s back sheet or faces, started at ``T_ref_cam`` /
    ``T_ref_board`` (4x4, m); ``capture_ms`` the views' capture times from the cameras'
    timestamps (:func:`~rgbd_calib.solve.time_model.capture_offsets`), which anchor the time
    model's offsets (``config.time_model.time_offset_sigma_ms``); ``set_ms`` each frame set's
    time on the reference's clock (:func:`~rgbd_calib.solve.time_model.set_times_ms`), which ties
    consecutive sets by the motion prior."""
    capture_ms = capture_ms or {}
    return BundleProblem(measurements, camera_matrices(rig), rig.reference, T_ref_cam,
                         T_ref_board, config, fixed_cameras, intrinsics=rig.cameras,
                         back_centre=back_centre(board), face_frames=face_frames(board),
                         capture_ms=capture_ms,
                         time_priors=anchored_priors(rig.names, capture_ms,
                                                     config.time_model.time_offset_sigma_ms),
                         set_ms=set_ms, board_scale_sigma=board.print_scale_sigma or 0.0)


def refined_rig(rig: Rig, bundle: BundleResult) -> Rig:
    """``rig`` with the bundle adjustment's refined intrinsics (cameras it did not refine keep
    their rig.yaml model): what ``rig_refined.yaml`` holds."""
    return replace(rig.with_intrinsics(bundle.intrinsics), sigmas=dict(bundle.intrinsics_sigma))


# ----------------------------------------------------------------------------- measurements
def marker_measurements(
    observations: list[BoardObservation], pg: PoseGraphResult, rig: Rig,
    refined_intrinsics: bool = False, board: Board | None = None,
    keep_outlier_views: bool = False, boards: dict[str, np.ndarray] | None = None,
) -> list[MarkerMeasurement]:
    """The bundle adjustment's measurements: every marker of every view the pose graph kept
    (its cameras and boards solved, the view not a stale edge nor an outlier the pose graph
    rejected: with ``graph.reject_outliers`` off, flagged outliers stay in), in undistorted
    pinhole pixels.

    With ``refined_intrinsics`` the pixels are the detected ones (the bundle adjustment
    projects through the full model it refines) and the pose graph's outlier views are kept:
    they were judged with the rig.yaml intrinsics, which refining assumes may be wrong (a
    0.7 % focal error makes the per-view PnP poses of a camera disagree by 5-20 mm, and the
    pose graph then flags every view of a camera); the bundle adjustment's per-marker kernel
    and outlier test still remove bad markers.

    ``keep_outlier_views`` keeps them too (board self-calibration: with a misglued back sheet
    the per-view PnP poses of the nominal board put every back-facing camera's views off by
    the glue error, and the pose graph flags them all). ``board`` gives each measurement its
    face (front when None). ``boards`` (frame -> ``T_ref_board``, :func:`unsolved_views`)
    admits frames the pose graph has no board pose for."""
    keep = refined_intrinsics or keep_outlier_views
    edges = pg.stale_edges if keep else pg.rejected_edges
    dropped = {pg.residuals[i].view + "/" + pg.residuals[i].camera for i in edges}
    measurements = []
    for o in observations:
        if o.camera not in pg.cameras or (o.frame not in pg.T_ref_board
                                          and o.frame not in (boards or {})):
            continue
        if f"{o.frame}/{o.camera}" in dropped:
            continue
        px = o.corners_px if refined_intrinsics else (
            rig.cameras[o.camera].undistort_pixels(o.corners_px))
        saddle = (board.saddle_quads(o.ids) if board is not None
                  else np.zeros(len(o.ids), dtype=bool))
        for mid, c, P, s in zip(o.ids, px, o.object_points, saddle):
            face = 1 if board is None else int(board.faces[board.index_of[int(mid)]])
            measurements.append(MarkerMeasurement(o.camera, o.frame, int(mid), c, P, face,
                                                  not bool(s)))
    return measurements


def unsolved_views(observations: list[BoardObservation], T_ref_cam: dict[str, np.ndarray],
                   T_ref_board: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """First ``T_ref_board`` (4x4, metres) of the frames that have no board pose in
    ``T_ref_board`` but a view by a camera of ``T_ref_cam``: the robust mean
    (:func:`~rgbd_calib.solve.posegraph_init.robust_mean_pose`) of ``T_ref_cam @ T_cam_board``
    over those views.

    The pose graph solves only the frames that two cameras saw with the model it was given.
    With the intrinsics refined, a frame one camera alone saw still measures that camera's
    lens, and a view the rig.yaml lens failed (PnP's reprojection gate: an unlisted
    distortion is largest at the image's edge) is usable once the lens is refined. Those are
    the views that reach the image's edge, where a refined lens is otherwise an extrapolation
    (measured: docs/accuracy.md, 'Measurements behind the solver's design')."""
    views: dict[str, list[np.ndarray]] = {}
    for o in observations:
        if o.frame not in T_ref_board and o.camera in T_ref_cam:
            views.setdefault(o.frame, []).append(T_ref_cam[o.camera] @ o.T_cam_board)
    return {f: robust_mean_pose(np.stack(T)) for f, T in views.items()}


def lens_moved(detected_with: Rig, refined: dict[str, CameraIntrinsics],
               observations: list[BoardObservation]) -> list[str]:
    """The cameras whose ``refined`` lens images the rays of their detected corners more than
    :data:`LENS_SETTLED_PX` from where the lens the corners were detected with
    (``detected_with``) does: their edge fit bent the marker edges by a model that has moved,
    so their corners should be detected again.

    It matters for the views that reach an image's corners: they fail PnP with rig.yaml's
    lens, so the first refined lens never saw them and is an extrapolation there; detected
    again with the lens refined from them, their corners move by several times their noise
    (measured: docs/accuracy.md, 'Measurements behind the solver's design')."""
    corners: dict[str, list[np.ndarray]] = {}
    for o in observations:
        corners.setdefault(o.camera, []).append(o.corners_px.reshape(-1, 2))
    moved = []
    for cam, model in refined.items():
        if cam not in corners or cam not in detected_with.cameras:
            continue
        px = np.concatenate(corners[cam])
        rays = detected_with.cameras[cam].rays(px[:, 0], px[:, 1])
        if np.linalg.norm(model.project(rays) - px, axis=1).max() > LENS_SETTLED_PX:
            moved.append(cam)
    return moved


# ----------------------------------------------------------------------------- the solves
def bundle_sound_first(problem: BundleProblem, model_error: Collection[str]) -> BundleResult:
    """:func:`~rgbd_calib.solve.bundle.bundle_adjust` of ``problem``, so that a camera with a
    model error (``model_error``: the pose graph's, ``PoseGraphResult.model_error``) does not
    pull the others.

    The bundle weighs every corner alike; the corners of a camera whose model is off would
    bend the board poses and, through them, the sound cameras. When there are such cameras
    and at least one sound camera besides the reference, the sound cameras (with the
    reference and any fixed ones) are solved first on their own corners; then every camera,
    the sound ones held where the first solve put them, which places the model-error cameras
    against boards the sound cameras fixed. Sound cameras keep the first solve's covariance
    and board poses seen by it keep its values. Otherwise (no model error, or every camera has
    one) one joint solve.

    With the intrinsics, the back sheet or time refined (``bundle.intrinsics`` /
    ``bundle.board`` / ``bundle.time`` ``"refine"``) the model error the pose graph saw is
    what the solve estimates: one joint solve. Solving the few sound cameras first and
    holding them would fix their poses (and lens) from a fraction of the views, several times
    worse than the joint solve at claimed sigmas far too small (measured: docs/accuracy.md,
    'Measurements behind the solver's design')."""
    reference, fixed = problem.reference, dict(problem.fixed_cameras or {})
    cams = {m.camera for m in problem.measurements}
    sound = {c for c in cams if c not in model_error} | {reference} | set(fixed)
    freed = "refine" in (problem.config.intrinsics, problem.config.board, problem.config.time)
    joint = (freed or not model_error or not (cams - sound)
             or len(sound - {reference} - set(fixed)) < 1)
    if joint:
        return bundle_adjust(problem)
    first = bundle_adjust(replace(
        problem, config=problem.config.model_copy(update={"held_out": False}),
        measurements=[m for m in problem.measurements if m.camera in sound],
        relative_poses=[r for r in problem.relative_poses if {r.cam_a, r.cam_b} <= sound]))
    held = {**first.T_ref_cam, **fixed}
    boards = {**problem.T_ref_board, **first.T_ref_board}
    second = bundle_adjust(replace(problem, T_ref_cam={**problem.T_ref_cam, **held},
                                   T_ref_board=boards, fixed_cameras=held))
    keep = set(first.T_ref_cam)
    return replace(
        second,
        T_ref_board={**second.T_ref_board,
                     **{v: T for v, T in first.T_ref_board.items() if v in second.T_ref_board}},
        covariance={**second.covariance,
                    **{c: first.covariance[c] for c in keep}},
        sigma_rotation_deg={**second.sigma_rotation_deg,
                            **{c: first.sigma_rotation_deg[c] for c in keep}},
        sigma_translation_mm={**second.sigma_translation_mm,
                              **{c: first.sigma_translation_mm[c] for c in keep}},
        outliers=first.outliers + [o for o in second.outliers if o not in first.outliers],
    )


def warm_intrinsics(problem: BundleProblem, result: BundleResult
                    ) -> dict[str, CameraIntrinsics] | None:
    """Where a re-solve of ``problem`` starts its refined intrinsics: ``result``'s estimate
    (the priors stay at the rig's), else where ``problem`` started them."""
    return dict(result.intrinsics) if result.intrinsics else problem.intrinsics_start


def edge_offset_modelled(problem: BundleProblem, result: BundleResult,
                         model_error: Collection[str]) -> tuple[BundleResult, BundleProblem]:
    """``problem`` solved again with each camera's detector edge offset taken out of its
    corners, for the cameras whose ``result`` reads one the data support
    (:func:`~rgbd_calib.solve.edge_offset.significant`); unchanged when none does.

    A fixed-point iteration: the poses absorb a little of the offset (~4 % on the race and
    ring renders), so each solve reads the rest from its residuals and the next takes the sum
    out, until no modelled camera's reading moves by :data:`~rgbd_calib.solve.edge_offset.
    CONVERGED_PX` (one or two solves). Each solve starts at the last one's poses. The offset's
    own standard error (~0.001 px, ~0.02 mm of extrinsics) is not added to the covariance."""
    modelled = edge_offset.significant(result.edge_offset)
    if not modelled:
        return result, problem
    for _ in range(edge_offset.ITERATIONS):
        problem = replace(problem, edge_offset=modelled,
                          T_ref_cam={**problem.T_ref_cam, **result.T_ref_cam},
                          T_ref_board={**problem.T_ref_board, **result.T_ref_board},
                          intrinsics_start=warm_intrinsics(problem, result))
        result = bundle_sound_first(problem, model_error)
        read = result.edge_offset
        moved = max((abs(read[c].residual_px) for c in modelled if c in read), default=0.0)
        modelled = {c: read[c].offset_px if c in read else d for c, d in modelled.items()}
        if moved < edge_offset.CONVERGED_PX:
            break
    return result, problem


@dataclass(frozen=True)
class _Ladder:
    """What every solve of one self-calibration run measures: the views, the pose graph that
    kept them, the rig and board they are measured with, the held cameras, the progress tick
    (one per solve)."""

    observations: list[BoardObservation]
    pg: PoseGraphResult
    rig: Rig
    board: Board
    fixed_cameras: dict[str, np.ndarray] | None
    tick: Tick
    capture_ms: dict[tuple[str, str], float] | None = None
    set_ms: dict[str, float] | None = None

    def solve(self, level: BundleConfig, init_cam: dict[str, np.ndarray],
              init_board: dict[str, np.ndarray], freed: bool,
              start: BundleResult | None = None) -> tuple[BundleResult, BundleProblem]:
        """The bundle adjustment with ``level``'s board and intrinsics models, started at
        ``init_cam`` / ``init_board`` and at ``start``'s refined intrinsics (a simpler
        model's solve: warm, the priors unchanged); ``freed`` keeps the pose graph's outlier
        views."""
        self.tick(1)
        refined = level.intrinsics == "refine"
        if refined:  # a frame one camera alone saw measures its lens
            init_board = {**init_board,
                          **unsolved_views(self.observations, init_cam, init_board)}
        meas = marker_measurements(self.observations, self.pg, self.rig,
                                   refined_intrinsics=refined, board=self.board,
                                   keep_outlier_views=freed,
                                   boards=init_board if refined else None)
        problem = bundle_problem(meas, self.rig, self.board, init_cam, init_board, level,
                                 self.fixed_cameras, self.capture_ms, self.set_ms)
        if start is not None:
            problem = replace(problem, intrinsics_start=warm_intrinsics(problem, start))
        return bundle_sound_first(problem, self.pg.model_error), problem


@dataclass(frozen=True)
class _Step:
    """A level tried: how it fitted, its solve and problem (None when the solve failed) and its
    markers' capped terms (:func:`rgbd_calib.solve.selfcal.marker_terms`)."""

    fit: selfcal.LevelFit
    result: BundleResult | None
    problem: BundleProblem | None
    terms: dict[tuple[str, str, int], float]


def _in_the_rigs_lens_names(config: BundleConfig, rig: Rig) -> BundleConfig:
    """``config`` with its ``intrinsics_params`` named as the rig's lenses name them when
    every camera has the same lens model (a fisheye rig frees k1..k4, and the ladder's levels
    say so); a mixed rig keeps the configuration's names (each camera maps them,
    :func:`~rgbd_calib.solve.bundle_factors.lens_names`)."""
    lenses = {c.lens for c in rig.cameras.values()}
    if len(lenses) != 1:
        return config
    names = lens_names(next(iter(rig.cameras.values())), tuple(config.intrinsics_params))
    if list(names) == list(config.intrinsics_params):
        return config
    return config.model_copy(update={"intrinsics_params": list(names)})


def self_calibrated_bundle(
    observations: list[BoardObservation],
    pg: PoseGraphResult,
    rig: Rig,
    board: Board,
    config: BundleConfig,
    fixed_cameras: dict[str, np.ndarray] | None = None,
    progress: Progress | None = None,
    capture_ms: dict[tuple[str, str], float] | None = None,
    set_ms: dict[str, float] | None = None,
) -> tuple[BundleResult, BundleProblem, selfcal.SelfCalibration | None]:
    """The bundle adjustment with ``config``'s board and intrinsics models.

    Explicit modes (``fixed`` / ``refine``) solve once. With ``auto`` (either), the ladder of
    :mod:`rgbd_calib.solve.selfcal`: the nominal model first, then each richer model started
    from the last accepted solve, kept only when it calibrates more cameras or fits the common
    markers better than its extra parameters cost (BIC). Returns the chosen solve, its problem
    (measurements and the explicit config it was solved with, for the later solves) and the
    ladder (None for explicit modes). ``capture_ms``: the views' capture times from the
    cameras' timestamps, and ``set_ms`` the frame sets' times, for the time model
    (:func:`bundle_problem`)."""
    ladder = _Ladder(observations, pg, rig, board, fixed_cameras,
                     start(progress, "bundle adjustment (models solved)", None), capture_ms,
                     set_ms)
    config = _in_the_rigs_lens_names(config, rig)
    if not selfcal.is_auto(config):
        result, problem = ladder.solve(config, pg.T_ref_cam, pg.T_ref_board,
                                       "refine" in (config.board, config.time))
        return result, replace(problem, config=held_corner_ratio(problem.config, result)), None
    level = selfcal.base_level(config)
    result, problem = ladder.solve(_trial_config(level, config), pg.T_ref_cam, pg.T_ref_board,
                                   level.board or level.time)
    given_ratio = config.corners.corner_centre_ratio  # later solves hold the one read first
    config = held_corner_ratio(config, result)
    problem = replace(problem, config=held_corner_ratio(problem.config, result))
    terms = selfcal.marker_terms(result.residuals_px, result.outliers, config.outlier_px)
    start_fit = selfcal.LevelFit(level, len(result.T_ref_cam), len(result.residuals_px),
                                 selfcal.rms_px(terms), reason="the starting model")
    start_step = _Step(start_fit, result, problem, terms)
    chosen, fits = _climb(ladder, config, start_step)
    result, problem = chosen.result, chosen.problem
    if chosen.fit.level.time:
        # at the configured tolerance, with the twist prior from the data: once, on the model
        # chosen (the prior's steps cost several solves; the comparisons do not need it); its
        # config otherwise the trial's (priors a contradiction loosened stay loosened); the
        # corners' centre-to-shape ratio read again (the timeless first solve's took motion
        # for centre noise: 0.50 against 0.38 on a moving race)
        result, problem = _solved_again(problem, result, {
            "time_twist_prior_from_data": config.time_model.time_twist_prior_from_data,
            "relative_error_tol": config.relative_error_tol,
            "max_iterations": config.max_iterations,
            "corner_centre_ratio": given_ratio}, pg.model_error)
    elif chosen is not start_step and config.corners.corner_noise == "marker" and not given_ratio:
        # the ratio read again on the richer model chosen
        result, problem = _solved_again(problem, result, {"corner_centre_ratio": None},
                                        pg.model_error)
    # the run's later solves (edge offset, depth pairs) need no held-out prediction
    problem = replace(problem, config=problem.config.model_copy(update={"held_out": False}))
    return result, problem, selfcal.SelfCalibration(chosen.fit.level, fits)


def _solved_again(problem: BundleProblem, result: BundleResult, update: dict,
                  model_error: Collection[str]) -> tuple[BundleResult, BundleProblem]:
    """``problem`` solved once more from ``result``'s poses with ``update`` to its config, the
    corners' ratio then held at what that solve read; ``(result, problem)`` when it fails (the
    trial's solve stands)."""
    again = replace(problem, config=problem.config.replaced(**update),
                    T_ref_cam={**problem.T_ref_cam, **result.T_ref_cam},
                    T_ref_board={**problem.T_ref_board, **result.T_ref_board},
                    intrinsics_start=warm_intrinsics(problem, result))
    try:
        solved = bundle_sound_first(again, model_error)
    except _SOLVE_ERRORS:
        return result, problem
    return solved, replace(again, config=held_corner_ratio(again.config, solved))


def held_corner_ratio(config: BundleConfig, result: BundleResult) -> BundleConfig:
    """``config`` with ``corner_noise: marker``'s centre-to-shape ratio held at what
    ``result`` read (unless given): the run's later solves (the ladder's trials, the edge
    offset's, the depth stage's joint solve) weigh the corners alike without reading it again
    in a solve of their own."""
    if (config.corners.corner_noise != "marker" or config.corners.corner_centre_ratio
            or result.corner_noise is None):
        return config
    return config.replaced(corner_centre_ratio=result.corner_noise.centre_ratio)


# a timed level the ladder compares stops at this relative decrease of its error: along the
# clocks' scale (a gauge only weak priors hold) and on a still board (time unobservable)
# Levenberg-Marquardt creeps on for ~100 iterations (intrinsics-error race: 11 s instead of 1),
# while BIC gains are thousands; the chosen model is solved again at the configured tolerance
TIME_TRIAL_TOL = 1e-6
# ... and at most this many iterations. A moving board's trial takes 6-38; an unsynchronised
# rolling-shutter race without timestamps (clocks +-16 ms, 16 sets) needed ~50 to reach its
# clocks: stopped at 40 (the cap before 2026-12-08) its time trial was judged on a solve
# halfway (corner RMS 0.17 px against 0.05 converged), lost the held-out check, and a lens
# took up the motion (31 mm, CHECK); the tolerance above still stops the creeping trials
TIME_TRIAL_ITERATIONS = 100


def _trial_config(level: selfcal.ModelLevel, config: BundleConfig) -> BundleConfig:
    """``level``'s config for a solve the ladder compares: the twist prior as configured (its
    estimate from the data is for the model chosen, :func:`self_calibrated_bundle`), a timed
    level to :data:`TIME_TRIAL_TOL` and :data:`TIME_TRIAL_ITERATIONS`."""
    update: dict = {"time_twist_prior_from_data": False, "held_out": True}
    if level.time:
        update["relative_error_tol"] = max(config.relative_error_tol, TIME_TRIAL_TOL)
        update["max_iterations"] = min(config.max_iterations, TIME_TRIAL_ITERATIONS)
    return level.bundle_config(config).replaced(**update)


def _climb(ladder: _Ladder, config: BundleConfig,
           current: _Step) -> tuple[_Step, list[selfcal.LevelFit]]:
    """Up the ladder from ``current``: first the time challenge (:func:`_time_challenge`),
    then each group of alternatives tried from the accepted solve, the best accepted one
    (:func:`rgbd_calib.solve.selfcal.better`) taken. A group that a wrong model elsewhere hid
    (the back sheet judged through an undistorted lens) is tried once more after a later
    group was accepted. Returns the chosen step and every fit."""
    fits = [current.fit]
    board = ladder.board
    double_sided = bool(np.any(np.asarray(board.faces) < 0)) or len(board.face_labels) > 1
    queue = selfcal.candidate_groups(config, double_sided, bool(ladder.pg.model_error))
    solved: dict[tuple[str, str], _Step] = {}  # (base, level) -> its step: solved once

    def attempt(level: selfcal.ModelLevel, base: _Step) -> _Step:
        key = (base.fit.level.name, level.name)
        if key not in solved:
            solved[key] = _try_level(ladder, config, level, base)
        return solved[key]

    current, fits = _time_challenge(selfcal.time_challengers(queue), attempt, current, fits)
    for _ in range(2):
        rejected, retry = [], False
        for group in queue:
            level = current.fit.level
            tried = [attempt(selfcal.extend(level, step), current)
                     for step in group if selfcal.extend(level, step) != level]
            best = None
            for t in tried:
                if t.fit.accepted and (best is None or selfcal.better(t.fit, best.fit)):
                    best = t
            fits += [t.fit if best is None or t is best or not t.fit.accepted else
                     replace(t.fit, accepted=False,
                             reason=t.fit.reason + "; another model fits better")
                     for t in tried if t.fit not in fits]  # a retry from the same base: once
            if best is None:
                if tried:
                    rejected.append(group)
                continue
            current, retry = best, retry or bool(rejected)
        if not retry:
            break
        queue = rejected
    return current, fits


def _time_challenge(challengers: list, attempt, current: _Step,
                    fits: list[selfcal.LevelFit]) -> tuple[_Step, list[selfcal.LevelFit]]:
    """Time taken first only when it fits better than every other first step (the back
    sheet, the lens alternatives): its per-set twists and per-camera clocks can mimic a
    little of a misglued sheet or a wrong focal length, and those, a little of a timing error.
    The challengers' solves are reused by the groups that follow; when time loses, it is
    recorded as not kept (and tried again last, on top of what the others give)."""
    if not challengers:
        return current, fits
    level = current.fit.level
    timed = attempt(selfcal.extend(level, selfcal.TIME_STEP), current)
    if not timed.fit.accepted:
        return current, fits + [timed.fit]
    rivals = [attempt(selfcal.extend(level, step), current) for step in challengers]
    better = [r for r in rivals if r.fit.accepted and selfcal.better(r.fit, timed.fit)]
    if not better:
        return timed, fits + [timed.fit] + [replace(
            r.fit, accepted=False, reason=r.fit.reason + "; the time model fits better")
            for r in rivals if r.fit.accepted]
    rival = better[0].fit
    return current, fits + [replace(timed.fit, accepted=False, reason=(
        f"{timed.fit.reason}; but + {rival.level.name} fits better (BIC gain "
        f"{rival.bic_gain if rival.bic_gain is None else round(rival.bic_gain)}): tried "
        "again after it"))]


def _try_level(ladder: _Ladder, config: BundleConfig, trial_level: selfcal.ModelLevel,
               current: _Step) -> _Step:
    """Solve ``trial_level`` from the accepted solve ``current`` and judge it against it:
    BIC on the common markers (:func:`rgbd_calib.solve.selfcal.compare`), not accepted when
    the freed board or faces were held anyway; a prior the data contradicts is loosened and
    the level solved again."""
    level, accepted = current.fit.level, current.result
    init_cam = {**ladder.pg.T_ref_cam, **accepted.T_ref_cam}
    init_board = {**ladder.pg.T_ref_board, **accepted.T_ref_board}
    try:
        trial, problem = ladder.solve(_trial_config(trial_level, config), init_cam, init_board,
                                      True, accepted)
    except _SOLVE_ERRORS as exc:
        return _Step(selfcal.LevelFit(trial_level, 0, 0, float("nan"), accepted=False,
                                      reason=f"the solve failed: {_first_line(exc)}"),
                     None, None, {})
    cams = {m.camera for m in problem.measurements}
    rig = blocks.RigShape(len(cams), len(cams - set(ladder.fixed_cameras or {})),
                          len({m.view for m in problem.measurements}), ladder.board)
    added = blocks.added(level.blocks, trial_level.blocks, rig)
    terms = selfcal.marker_terms(trial.residuals_px, trial.outliers, config.outlier_px)
    ok, gain, reason = selfcal.compare(current.terms, len(accepted.T_ref_cam), terms,
                                       len(trial.T_ref_cam), added)
    pinned = blocks.newly_held(level.blocks, trial_level.blocks, trial) if ok else None
    if pinned:  # a block freed but held anyway: the data cannot move it
        ok, reason = False, pinned
    tension = selfcal.prior_tension(trial, ladder.rig)
    if ok and tension is not None and tension[0] > selfcal.PRIOR_TENSION:
        # the data put a parameter several prior sigmas from rig.yaml: the prior is wrong
        # (another camera's file, a re-focused lens) and would bias the value and the
        # extrinsics towards it while the marginals stay small. Loosen it.
        z, cam, name = tension
        try:
            trial, problem = ladder.solve(selfcal.loosened(problem.config),
                                          {**init_cam, **trial.T_ref_cam},
                                          {**init_board, **trial.T_ref_board}, True, trial)
            terms = selfcal.marker_terms(trial.residuals_px, trial.outliers, config.outlier_px)
            reason += (f"; {name} of {cam} came {z:.1f} prior sigmas from rig.yaml: "
                       f"priors loosened {selfcal.LOOSEN:.0f}x")
        except _SOLVE_ERRORS as exc:
            reason += f"; loosening the contradicted prior failed: {_first_line(exc)}"
    ok, reason, held = _held_out_judged(ok, reason, accepted, trial, config, gain is not None)
    fit = selfcal.LevelFit(trial_level, len(trial.T_ref_cam), len(trial.residuals_px),
                           selfcal.rms_px(terms), added, gain, ok, reason, held)
    return _Step(fit, trial, problem, terms)


def _held_out_judged(ok: bool, reason: str, base: BundleResult, trial: BundleResult,
                     config: BundleConfig, same_cameras: bool,
                     ) -> tuple[bool, str, selfcal.HeldOut | None]:
    """The BIC's decision ``ok`` checked on data neither model was fitted to: the corners of
    each view predicted from the other cameras' views of its set (``held_out_px``). A richer
    model on the same cameras that predicts them no better is not kept, whatever its in-sample
    fit (a per-set twist, a lens or a back sheet that took up misfit); one that calibrates more
    cameras keeps the BIC's decision, with the figure said."""
    held = selfcal.held_out(base.held_out_px, trial.held_out_px, config.outlier_px)
    if held is None:
        return ok, reason, None
    if ok and same_cameras and not held.better:
        return False, f"{reason}; but it predicts {held.phrase()} (worse)", held
    return ok, f"{reason}; {held.phrase()}", held


def _first_line(exc: Exception) -> str:
    """An exception's first non-empty line (GTSAM's run over several)."""
    return next((line.strip() for line in str(exc).splitlines() if line.strip()),
                type(exc).__name__)


# ----------------------------------------------------------------------------- honest sigmas
def model_error_sigmas(
    cameras: dict[str, CameraExtrinsics],
    bundle: BundleResult | None,
    pg: PoseGraphResult,
    config: BundleConfig,
) -> tuple[dict[str, CameraExtrinsics], dict[str, float]]:
    """Honest uncertainty when the pose graph found cameras with a model error.

    The pose graph's marginals are the honest ones then: a model-error camera's edges carry
    its a-posteriori variance factor and, being common to all its views, count once (see
    ``_EdgeNoise.correlated`` in :mod:`rgbd_calib.solve.posegraph`), and every camera chained
    to the reference through it inherits that. The bundle adjustment weighs every corner
    alike, so after it each camera's covariance is scaled up until it covers the pose
    graph's (the largest generalised eigenvalue of the pair) and, for a model-error camera,
    by at least its own corners' variance factor (``mean(rms^2) / 2`` over the bundle's corner
    sigma^2) times its number of views. A model-error camera the bundle lost (every marker
    beyond ``outlier_px``) keeps its pose-graph estimate. ``bundle`` None: the pose graph's
    cameras are already honest. ``config``: the bundle's (its corner sigma and models).
    Returns the cameras and, per model-error camera, its total factor over its nominal
    covariance (pose-graph variance factor x edges, or the bundle scale)."""
    out = dict(cameras)
    factors = {c: m.variance_factor * max(m.edges, 1) for c, m in pg.model_error.items()}
    if bundle is None or not pg.model_error:
        return out, factors
    sigma_px = (max(bundle.pixel_sigma_estimated, 1e-3) if config.estimate_sigma
                else config.pixel_sigma)
    if "refine" in (config.board, config.intrinsics, config.time):
        # the pose graph judged the views with the nominal board, rig.yaml intrinsics and
        # every camera at the set's instant; the bundle freed that model. When every flagged
        # camera's corners now fit like the rest of the rig, the freed model explained the
        # error: nothing is left to inflate.
        own = {c: _corner_variance_factor(bundle, c, sigma_px) for c in pg.model_error}
        if all(f <= MODEL_ERROR_EXPLAINED for f in own.values()):
            return out, dict.fromkeys(pg.model_error, 1.0)
    for c, graph_cam in pg.cameras.items():
        if c not in out:
            if c in pg.model_error:
                out[c] = graph_cam
            continue
        e = out[c]
        f = _cover_factor(e.covariance, graph_cam.covariance)
        if c in pg.model_error:
            views = len({r[1] for r in bundle.residuals_px if r[0] == c})
            f = max(f, _corner_variance_factor(bundle, c, sigma_px) * max(views, 1))
            factors[c] = f
        if f > 1.0 and e.covariance is not None:
            out[c] = CameraExtrinsics(c, e.T_ref_cam, e.sigma_rotation_deg * np.sqrt(f),
                                      e.sigma_translation_mm * np.sqrt(f), e.covariance * f)
    return out, factors


def _corner_variance_factor(bundle: BundleResult, camera: str, sigma_px: float) -> float:
    """``mean(rms^2) / 2 / sigma_px^2`` over the camera's markers in the bundle (each rms is
    over 4 corners x 2 axes, hence the 2): about 1 when its corners fit like the rig's."""
    rms = np.array([r[3] for r in bundle.residuals_px if r[0] == camera])
    return float(np.mean(rms**2) / 2.0) / sigma_px**2 if len(rms) else 1.0


def _cover_factor(cov: np.ndarray | None, target: np.ndarray | None) -> float:
    """Smallest ``f >= 1`` with ``f * cov >= target`` (both 6x6, same frame and order): the
    largest eigenvalue of ``L^-1 target L^-T``, ``cov = L L^T``; 1 when either is missing
    or ``cov`` is singular (the reference, a fixed camera)."""
    if cov is None or target is None or not np.all(np.isfinite(target)):
        return 1.0
    try:
        L = np.linalg.cholesky(np.asarray(cov, float))
    except np.linalg.LinAlgError:
        return 1.0
    A = np.linalg.solve(L, np.linalg.solve(L, np.asarray(target, float)).T)
    return max(float(np.linalg.eigvalsh((A + A.T) / 2).max()), 1.0)
