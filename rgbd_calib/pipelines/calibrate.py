"""The calibration pipeline: ``calibrate(dataset, board, config) -> CalibrationResult``.

One call per stage (:func:`calibrate`)::

    dataset (FolderDataset) -> detection (ArUco + unbiased corners, cached, in parallel:
        rgbd_calib.detect.run) -> [intrinsics from scratch] -> pose (per-view PnP, covariance,
        gates: rgbd_calib.solve.pose) -> [a long continuous recording thinned to runs of
        consecutive sets: rgbd_calib.solve.runs] -> pose graph (initialisation from the
        co-visibility spanning tree, robust solve, marginals: rgbd_calib.solve.posegraph) ->
        bundle adjustment with self-calibration (rgbd_calib.solve.ladder) [-> detection again
        with the refined lens] [-> the detectors' edge offsets taken out of the corners,
        solved again: rgbd_calib.solve.edge_offset] -> depth (rgbd_calib.depth.stage) -> joint
        solve -> checks -> result (extrinsics + uncertainty)

No file is written here except the detection cache; :mod:`rgbd_calib.outputs.writer` writes results.
"""

from __future__ import annotations

import os
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config import BundleConfig, CalibrationConfig
from ..core.errors import CalibrationError
from ..core.progress import Progress, start, timed
from ..depth.clouds import target_corners
from ..depth.information import with_bias_floor
from ..depth.stage import (
    DepthRefinement,
    board_views_per_camera,
    finish_pairs,
    measure_agreement,
    measure_depth,
    moved_beyond_board,
    unseen_board_views,
    view_pose_covariances,
    with_overlaps,
)
from ..detect.markers import MarkerDetections
from ..detect.probe import dictionary_family, probe_targets
from ..detect.run import detect_dataset
from ..model.board import CHECKERBOARD, Board, refined_board, refined_multiface
from ..model.board_file import load_board
from ..model.dataset import FolderDataset
from ..model.results import CameraExtrinsics, Extrinsics, cameras_from_solve
from ..model.rig import Rig
from ..solve import selfcal
from ..solve.bundle_problem import BundleProblem, BundleResult
from ..solve.intrinsics_init import InitialIntrinsics, initialise_intrinsics
from ..solve.ladder import (
    bundle_sound_first,
    edge_offset_modelled,
    lens_moved,
    marker_measurements,
    model_error_sigmas,
    refined_rig,
    self_calibrated_bundle,
    unsolved_views,
    warm_intrinsics,
)
from ..solve.pose import DROP_ADVICE, BoardObservation, RejectedView, board_poses, pose_edges
from ..solve.posegraph import PoseGraphResult, calibrate_pose_graph
from ..solve.runs import SetSelection, link_window_ms, select_sets
from ..solve.selfcal import SelfCalibration
from ..solve.stillness import SetMotion, board_motion
from ..solve.time_model import capture_offsets, set_times_ms
from ..solve.variance_components import estimate_factors
from ..sources.cache import open_dataset

# detections with the refined lens: at most this many passes, another one while some
# camera's lens moved by more than LENS_SETTLED_PX at its detected corners (see lens_moved)
REDETECTIONS = 3
# the depth stage's board pose at a camera's capture must be known to this (mm, 1 sigma; a
# bound: the errors were 3-5x smaller, race at 0.3 m/s). Within it the view's plane counts
# with that uncertainty (a random effect of the depth fit): 1 mm, before the planes were
# uncertain, left 6 of a moving race's 8 cameras without a depth model (fused bias 16.9 mm
# mean against 3.6 at 10 mm; docs/depth.md, 'The board at a camera's capture')
MAX_CAPTURE_POSE_SIGMA_MM = 10.0


@dataclass(frozen=True)
class CalibrationResult:
    """Everything a calibration produced, for the report and the exports."""

    extrinsics: Extrinsics
    observations: list[BoardObservation]
    rejected: list[RejectedView]
    posegraph: PoseGraphResult
    bundle: BundleResult | None
    config: CalibrationConfig
    detections_total: int
    timings_s: dict[str, float] = field(default_factory=dict)
    dataset_summary: dict[str, Any] = field(default_factory=dict)
    depth: DepthRefinement | None = None
    extrinsics_board_only: Extrinsics | None = None  # before depth refinement
    # camera -> factor its covariance was scaled by for a model error (see model_error_sigmas)
    model_error_factor: dict[str, float] = field(default_factory=dict)
    board: Board | None = None  # the board file calibrated with (board_refined.yaml's base)
    # bundle.board / bundle.intrinsics auto: the models tried and the one chosen
    self_calibration: SelfCalibration | None = None
    # cameras rig.yaml gave only the size of: their first intrinsics, from their own views
    initial_intrinsics: dict[str, InitialIntrinsics] = field(default_factory=dict)
    # the rig the solve started from: the dataset's, with those first intrinsics filled in
    rig: Rig | None = None
    # per frame set: where the cameras put the board, its speed, whether it moved
    motion: list[SetMotion] = field(default_factory=list)
    # a long continuous recording: the frame sets kept (bundle.max_sets)
    set_selection: SetSelection | None = None


# ----------------------------------------------------------------------------- pipeline
def calibrate(
    dataset: FolderDataset | str | os.PathLike,
    board: Board | str | os.PathLike,
    config: CalibrationConfig | None = None,
    cache_dir: str | os.PathLike | None = None,
    fixed_cameras: dict[str, np.ndarray] | None = None,
    progress: Progress | None = None,
) -> CalibrationResult:
    """Calibrate the extrinsics of every camera of ``dataset`` (a :class:`FolderDataset` or a
    dataset folder's path) relative to its reference, with ``board`` (a :class:`Board` or a
    board file's path); ``cache_dir`` keeps the detections (``detections.json``).

    ``fixed_cameras`` holds given cameras at ``T_ref_cam`` (adding a camera to a calibrated
    rig). Raises :class:`CalibrationError` when nothing can be calibrated."""
    dataset = open_dataset(dataset)
    board = load_board(board) if isinstance(board, (str, os.PathLike)) else board
    cache_dir = Path(cache_dir) if cache_dir is not None else None
    config = config or CalibrationConfig()
    n_images = sum(len(fs.color) for fs in dataset.frame_sets())
    run = _with_link_window(_Run(dataset, board, config, cache_dir, fixed_cameras, progress,
                                 {}, n_images))
    # 1. markers in every colour image (cached, in parallel)
    with timed(run.timings, "detection"):
        detections = _detect(run, dataset, "detecting markers", "detections.json")
    # 1b. the cameras rig.yaml gives only the size of: intrinsics from their own views (a
    # camera that saw none of the board's markers: another board in the images, named)
    _check_board_seen(run.dataset, detections, board)
    run, initial = _intrinsics_from_scratch(run, detections)
    # 2. one board pose per view (PnP, covariance, gates)
    with timed(run.timings, "pose"):
        views = _Views(*board_poses(detections, board, run.rig, run.config.pose))
    run, stand_in = _reference_with_views(run, views.observations)
    _check_views(run.dataset, detections, views.observations, views.rejected, n_images,
                 run.board)
    # 2b. a long continuous recording: runs of consecutive sets spread over it
    run, views = _thinned(run, views)
    # 3. robust pose graph over the views: initial extrinsics and board poses
    with timed(run.timings, "pose_graph"):
        pg = pose_graph(run.dataset, views.observations, run.config, fixed_cameras)
    unconnected = _unconnected(run.rig.names, views.observations, pg.unconnected)
    if stand_in is not None:
        unconnected[stand_in] = (
            f"{unconnected[stand_in]}; so the reference frame is {run.rig.reference!r}, the "
            f"camera with the most board views: record the board in {stand_in}'s view, or "
            "name the reference you want in rig.yaml")
    solved = _Solved(views, *model_error_sigmas(dict(pg.cameras), None, pg, run.config.bundle))
    if run.config.method == "bundle":
        # 4. bundle adjustment on the marker corners (and detection with a refined lens)
        solved = _bundle(run, pg, views)
        # 5.-7. depth: scale, clouds, pairwise registration; joint solve; each pair's check
        solved = _depth(run, pg, solved, unconnected)
    return _result(run, pg, solved, unconnected, initial)


@dataclass(frozen=True)
class _Run:
    """What every stage of one calibration reads: the dataset (its rig with any first
    intrinsics), the board, the config, the cache folder, the held cameras, the progress, the
    timings being filled in (s, by stage) and the number of colour images."""

    dataset: FolderDataset
    board: Board
    config: CalibrationConfig
    cache_dir: Path | None
    fixed_cameras: dict[str, np.ndarray] | None
    progress: Progress | None
    timings: dict[str, float]
    n_images: int
    selection: SetSelection | None = None  # the frame sets kept of a long recording

    @property
    def rig(self) -> Rig:
        return self.dataset.rig


@dataclass(frozen=True)
class _Views:
    """The board pose of every view with markers, and the views the gates rejected."""

    observations: list[BoardObservation]
    rejected: list[RejectedView]


@dataclass(frozen=True)
class _Solved:
    """The calibration so far: the views, the cameras with honest sigmas and the model-error
    factors (:func:`~rgbd_calib.solve.ladder.model_error_sigmas`), and with the bundle method
    the bundle, its problem, the self-calibration ladder, the depth stage and the extrinsics
    before it."""

    views: _Views
    cameras: dict[str, CameraExtrinsics]
    factors: dict[str, float]
    bundle: BundleResult | None = None
    problem: BundleProblem | None = None
    ladder: SelfCalibration | None = None
    depth: DepthRefinement | None = None
    board_only: Extrinsics | None = None


def _detect(run: _Run, dataset: FolderDataset, label: str,
            cache_name: str) -> dict[tuple[str, str], MarkerDetections]:
    """:func:`~rgbd_calib.detect.run.detect_dataset` of ``dataset`` (the run's, or with a
    refined rig), cached as ``cache_name`` in the cache folder."""
    tick = start(run.progress, label, run.n_images)
    cache = run.cache_dir / cache_name if run.cache_dir is not None else None
    return detect_dataset(dataset, run.board, run.config.detection, cache, run.config.workers,
                          tick, run.config.scheduler)


def _intrinsics_from_scratch(
    run: _Run, detections: dict[tuple[str, str], MarkerDetections]
) -> tuple[_Run, dict[str, InitialIntrinsics]]:
    """The first intrinsics of the cameras rig.yaml gives only the size of, from their own
    views, then refined jointly in the bundle adjustment with the others (their prior): the
    run with them in its rig and its config refining them. Unchanged when rig.yaml gives
    every camera's intrinsics."""
    if not run.rig.unknown_intrinsics:
        return run, {}
    with timed(run.timings, "intrinsics_init"):
        initial = initialise_intrinsics(detections, run.board, run.rig)
    rig = run.rig.with_intrinsics({c: i.intrinsics for c, i in initial.items()})
    return replace(run, dataset=run.dataset.with_rig(rig),
                   config=_with_scratch_intrinsics(run.config)), initial


def _bundle(run: _Run, pg: PoseGraphResult, views: _Views) -> _Solved:
    """The bundle adjustment, freeing as much of the board and lens model as the data supports
    (``bundle.board`` / ``bundle.intrinsics``: auto); with a refined lens distortion the
    corners are detected again with it (:func:`_redetect`)."""
    config = run.config
    with timed(run.timings, "bundle"):
        bundle, problem, ladder = self_calibrated_bundle(
            views.observations, pg, run.rig, run.board, config.bundle, run.fixed_cameras,
            run.progress, _capture_ms(run), _set_ms(run))
    solved = _Solved(views, {}, {}, bundle, problem, ladder)
    lens_refined = (ladder.chosen.distortion if ladder is not None
                    else _refines_distortion(config.bundle))
    if lens_refined and (ladder is not None or run.board.pattern is None):
        solved = _redetect(run, pg, solved)
    if config.bundle.corners.edge_offset == "auto":  # the detector's edge offset, where it is read
        with timed(run.timings, "bundle"):
            bundle, problem = edge_offset_modelled(solved.problem, solved.bundle,
                                                   pg.model_error)
        solved = replace(solved, bundle=bundle, problem=problem)
    bundle = solved.bundle
    cameras, factors = model_error_sigmas(cameras_from_solve(bundle), bundle, pg,
                                          solved.problem.config)
    return replace(solved, cameras=cameras, factors=factors)


def _redetect(run: _Run, pg: PoseGraphResult, solved: _Solved) -> _Solved:
    """The corners were fitted along straight edges; with the refined lens the edges are
    curved: detect again with it and solve the chosen model once more, again (up to
    :data:`REDETECTIONS` times) while the views this adds move a camera's lens where its
    corners are (:func:`~rgbd_calib.solve.ladder.lens_moved`)."""
    bundle, problem, config = solved.bundle, solved.problem, run.config
    lens_rig = refined_rig(run.rig, bundle)
    for _ in range(REDETECTIONS):
        with timed(run.timings, "redetection"):
            detections = _detect(run, run.dataset.with_rig(lens_rig),
                                 "detecting markers with the refined lens",
                                 "detections_refined_lens.json")
            views = _kept(_Views(*board_poses(detections, run.board, lens_rig, config.pose)),
                          run.selection)
        with timed(run.timings, "bundle"):
            # with the lens right, views its rig.yaml model failed pass PnP: add them
            boards = {**pg.T_ref_board, **bundle.T_ref_board}
            boards |= unsolved_views(views.observations, bundle.T_ref_cam, boards)
            measurements = marker_measurements(views.observations, pg, run.rig, True,
                                               run.board, True, boards)
            problem = replace(problem, measurements=measurements,
                              T_ref_cam={**pg.T_ref_cam, **bundle.T_ref_cam}, T_ref_board=boards,
                              intrinsics_start=warm_intrinsics(problem, bundle))
            bundle = bundle_sound_first(problem, pg.model_error)
        moved = lens_moved(lens_rig, bundle.intrinsics, views.observations)
        if not moved:
            break
        lens_rig = lens_rig.with_intrinsics({c: bundle.intrinsics[c] for c in moved})
    ladder = replace(solved.ladder, redetected=True) if solved.ladder is not None else None
    return replace(solved, views=views, bundle=bundle, problem=problem, ladder=ladder)


def _depth(run: _Run, pg: PoseGraphResult, solved: _Solved,
           unconnected: dict[str, str]) -> _Solved:
    """Depth (``refine``): per camera its scale and static cloud, the overlapping pairs
    registered, back-projected with the refined intrinsics (and their sigmas); then the joint
    solve with the accepted pairs and each pair's check at the final extrinsics."""
    bundle, cameras = solved.bundle, solved.cameras
    dataset = run.dataset
    if bundle.intrinsics:  # back-projected with the refined intrinsics (and their sigmas)
        dataset = dataset.with_rig(refined_rig(run.rig, bundle))
    refine = _refine_method(run.config.refine, dataset, cameras)
    if refine == "none":
        return solved
    board_only = Extrinsics(run.rig.reference, dict(cameras), dict(unconnected))
    T_ref_cam = {c: e.T_ref_cam for c, e in cameras.items()}
    with timed(run.timings, "depth"):
        board = _depth_board(run.board, bundle)
        at_capture, capture_sigma = _boards_at_capture(bundle, board, T_ref_cam)
        views = board_views_per_camera(solved.views.observations, T_ref_cam, bundle.T_ref_board,
                                       at_capture)
        unseen = unseen_board_views(T_ref_cam, bundle.T_ref_board, views, board, dataset,
                                    run.config.depth, at_capture)
        covariance = {c: e.covariance for c, e in cameras.items()}
        depth = measure_depth(dataset, board, T_ref_cam, views,
                              bundle.T_ref_board, refine, run.config.depth, run.progress,
                              board_covariance=covariance,
                              workers=run.config.workers, scheduler=run.config.scheduler,
                              unseen_views=unseen,
                              pose_covariance=view_pose_covariances(
                                  solved.views.observations, views, unseen, covariance,
                                  capture_sigma))
    solved = replace(solved, depth=depth, board_only=board_only)
    if depth.used:
        solved = _joint_solve(run, pg, solved, T_ref_cam)
    depth = solved.depth
    with timed(run.timings, "depth_check"):
        depth = finish_pairs(depth, {c: e.T_ref_cam for c, e in solved.cameras.items()},
                             run.config.depth,
                             start(run.progress, "checking depth pairs", len(depth.pairs)))
    with timed(run.timings, "overlap_models"):
        depth = with_overlaps(depth, {c: e.T_ref_cam for c, e in solved.cameras.items()},
                              {c: e.covariance for c, e in solved.cameras.items()},
                              run.config.depth)
    with timed(run.timings, "fused_agreement"):
        depth = measure_agreement(depth, {c: e.T_ref_cam for c, e in solved.cameras.items()},
                                  run.config.depth)
    return replace(solved, depth=depth)


def _boards_at_capture(bundle: BundleResult, board: Board, T_ref_cam: dict[str, np.ndarray],
                       ) -> tuple[dict[str, dict[str, np.ndarray]] | None,
                                  dict[str, dict[str, float]] | None]:
    """camera -> set -> the board pose at that camera's capture by the time model, for the
    depth stage (its depth pixels must meet the face where it was when the camera saw it); the
    sets where the twist's uncertainty moves the board's outermost point by more than
    ``MAX_CAPTURE_POSE_SIGMA_MM`` are left out. Second, the same sets' that uncertainty (m).
    None, None without a time model: the board is taken as still and the cameras as
    synchronised, as the solve did."""
    if bundle.time is None:
        return None, None
    lever = float(np.linalg.norm(target_corners(board), axis=1).max())
    out: dict[str, dict[str, np.ndarray]] = {}
    sigma: dict[str, dict[str, float]] = {}
    for c in T_ref_cam:
        for v, T in bundle.T_ref_board.items():
            moved = bundle.time.board_at_capture(c, v, T, lever)
            if moved is not None and moved[1] <= MAX_CAPTURE_POSE_SIGMA_MM:
                out.setdefault(c, {})[v] = moved[0]
                sigma.setdefault(c, {})[v] = moved[1] * 1e-3
    return out, sigma


def _depth_board(board: Board, bundle: BundleResult) -> Board:
    """The board's faces where the bundle put them (a refined back sheet's thickness, a
    multi-face target's refined faces)."""
    model = bundle.board
    depth_board = (refined_board(board, model.T_front_back)
                   if model is not None and not model.held else board)
    if any(not f.held for f in bundle.faces):
        depth_board = refined_multiface(board, {f.label: f.T_board_face
                                                for f in bundle.faces if not f.held})
    return depth_board


PAIR_FACTOR_TOLERANCE = 0.01  # relative change of the pairs' variance factor that ends it


def _joint_solve(run: _Run, pg: PoseGraphResult, solved: _Solved,
                 T_ref_cam: dict[str, np.ndarray]) -> _Solved:
    """The corners and the accepted depth pairs in one solve, started at the board-only
    cameras ``T_ref_cam``, the pairs' covariance times their variance factor (``depth.
    pair_variance_factor``): from ``depth.uncertainty.pair_variance_floor``, the solve is
    repeated with the factor times the pairs' chi-square over their redundancy in it
    (:func:`~rgbd_calib.solve.bundle.relative_pose_fit`: variance-component estimation; the
    corners' sigma is estimated as always), never below the floor, until it changes by less
    than :data:`PAIR_FACTOR_TOLERANCE` or after
    ``depth.uncertainty.variance_component_iterations`` solves; each pair's covariance also
    gains the bias ``depth.uncertainty.pair_bias_sigma_mm`` / ``_deg``
    (:func:`~rgbd_calib.depth.information.with_bias_floor`: colored ICP's error that does not
    shrink with its points).
    Colored ICP's pairs carry a bias their information does not show, and where the board is
    weak (the only cameras they are registered for) it cannot show it either: weighed by
    their information alone, short recordings came out up to 4 sigma off, 0.2 mm cameras
    pulled to 0.8 mm (docs/depth.md, "The pairs' factor in calibrate"). The depth pairs
    never end a run nor move a camera beyond its board uncertainty: either, and the pairs
    are marked unused (the board-only result stays)."""
    depth = solved.depth
    problem = replace(solved.problem, T_ref_cam=T_ref_cam,
                      T_ref_board=solved.bundle.T_ref_board)

    cfg = run.config.depth

    def solve(factors: dict[str, float]):
        joint = bundle_sound_first(replace(problem, relative_poses=[
            replace(r, information=with_bias_floor(
                r.information / factors["pairs"], cfg.uncertainty.pair_bias_sigma_deg,
                cfg.uncertainty.pair_bias_sigma_mm))
            for r in depth.relative_poses]), pg.model_error)
        fit = np.array(joint.relative_pose_fit).reshape(-1, 2)
        return joint, {"pairs": (fit[:, 0], fit[:, 1])}

    try:
        with timed(run.timings, "joint"):
            joint, factors = estimate_factors(
                solve, {"pairs": run.config.depth.uncertainty.pair_variance_floor},
                run.config.depth.uncertainty.variance_component_iterations, PAIR_FACTOR_TOLERANCE)
    except Exception as exc:  # noqa: BLE001 - the depth pairs must never end a run
        return replace(solved, depth=depth.with_fallback(
            f"the joint solve with the depth pairs failed "
            f"({type(exc).__name__}: {exc})".replace("\n", " ")))
    depth = replace(depth, pair_variance_factor=factors["pairs"],
                    pair_bias_sigma=(cfg.uncertainty.pair_bias_sigma_mm,
                                     cfg.uncertainty.pair_bias_sigma_deg))
    joint_cameras, joint_factors = model_error_sigmas(cameras_from_solve(joint), joint, pg,
                                                      solved.problem.config)
    beyond = moved_beyond_board(solved.cameras, joint_cameras)
    if beyond:
        return replace(solved, depth=depth.with_fallback("; ".join(beyond.values())))
    return replace(solved, bundle=joint, cameras=joint_cameras, factors=joint_factors,
                   depth=depth)


def _result(run: _Run, pg: PoseGraphResult, solved: _Solved, unconnected: dict[str, str],
            initial: dict[str, InitialIntrinsics]) -> CalibrationResult:
    """The result: every camera not calibrated given a reason, the extrinsics in rig order."""
    rig, cameras = run.rig, solved.cameras
    _explain_dropped(rig.names, pg.cameras, cameras, unconnected)
    extrinsics = Extrinsics(
        rig.reference, {c: cameras[c] for c in rig.names if c in cameras}, unconnected
    )
    return CalibrationResult(extrinsics, solved.views.observations, solved.views.rejected, pg,
                             solved.bundle, run.config, run.n_images, run.timings,
                             run.dataset.summary().to_dict(), solved.depth, solved.board_only,
                             model_error_factor=solved.factors, board=run.board,
                             self_calibration=solved.ladder, initial_intrinsics=initial,
                             rig=rig, motion=_motion(run, pg, solved.views, extrinsics),
                             set_selection=run.selection)


def _capture_ms(run: _Run) -> dict[tuple[str, str], float]:
    """Each view's capture time after its set's reference view (ms; from timestamps.csv)."""
    return capture_offsets({c: run.dataset.timestamps_ms(c) for c in run.rig.names},
                           run.rig.reference)


def _set_ms(run: _Run) -> dict[str, float]:
    """Each frame set's time on the reference camera's clock (ms; from timestamps.csv)."""
    return set_times_ms({c: run.dataset.timestamps_ms(c) for c in run.rig.names},
                        run.rig.reference)


def _with_link_window(run: _Run) -> _Run:
    """The run with ``bundle.time_model.time_link_ms`` as a number (``auto``: from the
    recording's frame period, :func:`~rgbd_calib.solve.runs.link_window_ms`), so the stages and
    ``config_resolved.yaml`` use and show one window."""
    bundle = run.config.bundle
    if bundle.time_model.time_link_ms != "auto":
        return run
    link_ms = round(link_window_ms("auto", _set_ms(run)), 1)
    config = run.config.model_copy(update={"bundle": bundle.replaced(time_link_ms=link_ms)})
    return replace(run, config=config)


def _thinned(run: _Run, views: _Views) -> tuple[_Run, _Views]:
    """A continuous recording with more than ``bundle.max_sets`` frame sets that see the
    board: the run with its :func:`~rgbd_calib.solve.runs.select_sets` and the views of the
    sets kept; any other dataset unchanged."""
    config = run.config.bundle
    seen: dict[str, dict[str, int]] = defaultdict(dict)
    for o in views.observations:
        seen[o.frame][o.camera] = o.n_markers
    selection = select_sets(_set_ms(run), seen, config.max_sets, config.set_run_length,
                            config.time_model.time_link_ms)
    if selection is None:
        return run, views
    return replace(run, selection=selection), _kept(views, selection)


def _kept(views: _Views, selection: SetSelection | None) -> _Views:
    """``views`` of the frame sets ``selection`` kept (all without one)."""
    if selection is None:
        return views
    keep = set(selection.kept)
    return _Views([o for o in views.observations if o.frame in keep],
                  [r for r in views.rejected if r.frame in keep])


def _motion(run: _Run, pg: PoseGraphResult, views: _Views,
            extrinsics: Extrinsics) -> list[SetMotion]:
    """Per frame set: did the board move (:func:`~rgbd_calib.solve.stillness.board_motion`)?"""
    x0, x1, y0, y1 = run.board.panel
    outliers = {(pg.residuals[i].camera, pg.residuals[i].view) for i in pg.outlier_edges}
    return board_motion(((o.camera, o.frame, o.T_cam_board) for o in views.observations),
                        {c: e.T_ref_cam for c, e in extrinsics.cameras.items()}, outliers,
                        np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0]), _capture_ms(run))


def _with_scratch_intrinsics(config: CalibrationConfig) -> CalibrationConfig:
    """``config`` for a rig with cameras calibrated from scratch: ``bundle.intrinsics: auto``
    (the default) becomes ``refine`` (auto would hold those cameras' first estimates as exact
    unless the pose graph found a model error); an explicit ``fixed`` holds them."""
    if config.bundle.intrinsics != "auto":
        return config
    return config.model_copy(update={
        "bundle": config.bundle.model_copy(update={"intrinsics": "refine"})})


def _refines_distortion(bundle: BundleConfig) -> bool:
    return bundle.intrinsics == "refine" and any(
        p not in selfcal.FOCAL_CENTRE for p in bundle.intrinsics_params)


# ----------------------------------------------------------------------------- checks
def _reference_with_views(run: _Run, observations: list[BoardObservation],
                          ) -> tuple[_Run, str | None]:
    """When rig.yaml's reference has no usable board view but other cameras share views, the
    run with the camera of the most views shared with another camera as its reference (rig
    order breaks ties) and the camera it stands in for: the rest of the rig is calibrated, the
    reference is reported not calibrated with the reason (a POOR result, exit 3) instead of
    nothing at all. Unchanged when the reference has a view, when no camera shares one (the
    checks that follow say why), and when cameras are held at given poses (their frame is the
    reference's)."""
    reference = run.rig.reference
    cameras_of: dict[str, set[str]] = defaultdict(set)
    for o in observations:
        cameras_of[o.frame].add(o.camera)
    if run.fixed_cameras or any(reference in cams for cams in cameras_of.values()):
        return run, None
    shared = defaultdict(int)
    for cams in cameras_of.values():
        if len(cams) > 1:
            for c in cams:
                shared[c] += 1
    if not shared:
        return run, None
    order = {c: i for i, c in enumerate(run.rig.names)}
    new = min(shared, key=lambda c: (-shared[c], order[c]))
    rig = replace(run.rig, reference=new)
    return replace(run, dataset=run.dataset.with_rig(rig)), reference


def _check_views(
    dataset: FolderDataset,
    detections: dict[tuple[str, str], MarkerDetections],
    observations: list[BoardObservation],
    rejected: list[RejectedView],
    n_images: int,
    board: Board | None = None,
) -> None:
    """Stop with the reason when the views cannot link any camera to the reference (before the
    pose graph, whose own errors name no dataset). With no usable view at all, the images are
    probed for another target (:func:`wrong_board`): a wrong or forgotten ``--board`` is said
    to be one, with the board file to pass."""
    if not observations:
        total = sum(len(d.ids) for d in detections.values())
        other = wrong_board(dataset, board) if board is not None else None
        raise CalibrationError(
            f"{dataset.path}: no usable board view in {n_images} images ({total} board markers "
            + (f"detected); {other}" if other else
               "detected); check that --board matches the printed board (dictionary, ids) and "
               "that the board is in view" if not rejected or not total else
               f"detected); {_why_dropped(detections, rejected)}")
        )
    reference = dataset.rig.reference
    if reference not in {o.camera for o in observations}:
        mine = [r for r in rejected if r.camera == reference]
        found = sum(len(d.ids) for (c, _), d in detections.items() if c == reference)
        raise CalibrationError(
            f"{dataset.path}: the reference camera {reference!r} has no usable board view"
            + (f" ({_why_dropped(detections, mine)})" if mine else
               f" ({found} board markers detected in its images)")
            + "; record the board in its view or choose another reference in rig.yaml"
        )
    reference_frames = {o.frame for o in observations if o.camera == reference}
    if not any(o.camera != reference and o.frame in reference_frames for o in observations):
        raise _no_shared_view(dataset)


def _check_board_seen(dataset: FolderDataset,
                      detections: dict[tuple[str, str], MarkerDetections], board: Board) -> None:
    """Before the intrinsics from scratch, which need the board's views: when a camera rig.yaml
    gives only the size of found no marker of ``board`` and the images show another target
    (:func:`wrong_board`), stop with what they show and the board file to pass (the scratch
    intrinsics would otherwise be blamed for a forgotten ``--board``)."""
    seen = {c for (c, _), d in detections.items() if len(d.ids)}
    if not (dataset.rig.unknown_intrinsics - seen):
        return
    other = wrong_board(dataset, board)
    if other:
        raise CalibrationError(f"{dataset.path}: {other}")


PROBE_IMAGES = 8  # images probed for another target when no view of the board is usable


def wrong_board(dataset: FolderDataset, board: Board) -> str | None:
    """When the images show another target than ``board`` (another marker family, printed
    inverted, or a ChArUco board where a marker board was given, or the reverse): what they
    show and which board file to pass; None when they show nothing else
    (:func:`rgbd_calib.detect.probe.probe_targets` on up to :data:`PROBE_IMAGES` images spread
    over the cameras and frames)."""
    pairs = [(c, f) for f in dataset.frames for c in dataset.cameras
             if dataset.color_path(c, f) is not None]
    picked = [pairs[int(i)] for i in np.unique(np.linspace(0, len(pairs) - 1, PROBE_IMAGES)
                                               .round().astype(int))] if pairs else []
    guess = probe_targets([dataset.read_color(c, f) for c, f in picked])
    if guess is None:
        return None
    charuco = board.charuco is not None
    inverted = bool(board.charuco.inverted) if charuco else False
    if (guess.family() == dictionary_family(board.dictionary) and guess.inverted == inverted
            and guess.charuco == charuco and guess.border_bits == board.border_bits):
        return None
    if guess.border_bits == 2:
        return (f"the images show {guess.describe()}, not the {board.board_type} board "
                f"{board.name!r} given; give --board Kalibr's target file of that grid as it "
                "is (target_type: aprilgrid) or a type: aprilgrid board file; "
                "configs/board_aprilgrid_kalibr.yaml is such a file")
    given = ("checkerboard" if board.board_type == CHECKERBOARD else
             f"{board.dictionary}{' inverted' if inverted else ''} "
             f"{'ChArUco' if charuco else 'marker'} board")
    example = ("configs/board_charuco_caliscope.yaml is such a file" if guess.charuco else
               "configs/board_thesis.yaml is such a file")
    return (f"the images show {guess.describe()}, not the {given} given; give --board "
            f"the file of the board recorded (type: {'charuco' if guess.charuco else 'aruco'}, "
            f"dictionary: {guess.dictionary}{', inverted: true' if guess.inverted else ''}; "
            f"{example})")


SMALL_MARKER_PX = 20.0  # markers narrower than this in the images: at ArUco's limit


def _why_dropped(detections: dict[tuple[str, str], MarkerDetections],
                 rejected: list[RejectedView]) -> str:
    """Why views with markers gave no pose, for an error message: the reasons by count, the
    advice for the most common, and the size of the markers in the images of those views
    (ArUco finds markers down to ~10 px; a pose needs a few of them)."""
    counts: dict[str, int] = {}
    for r in rejected:
        counts[r.reason] = counts.get(r.reason, 0) + 1
    reasons = sorted(counts.items(), key=lambda kv: -kv[1])
    sides = [float(np.linalg.norm(np.diff(d.corners_px, axis=1, append=d.corners_px[:, :1]),
                                  axis=-1).mean())
             for r in rejected
             if (d := detections.get((r.camera, r.frame))) is not None and len(d)]
    dropped = (f"all {len(rejected)} views with markers were dropped ("
               + ", ".join(f"{k} {n}" for k, n in reasons) + ")")
    mismatch = ("check that --board matches the printed board (layout, marker length, ids: "
                "markers of another board of the same dictionary are found too)")
    if sides and np.median(sides) < SMALL_MARKER_PX:
        return (f"{dropped}; the markers found were {np.median(sides):.0f} px wide (median), "
                f"at ArUco's limit: bring the board closer or print larger markers, and "
                f"{mismatch}")
    return f"{dropped}: {DROP_ADVICE.get(reasons[0][0], 'see the reasons')}; {mismatch}"


def _no_shared_view(dataset: FolderDataset) -> CalibrationError:
    return CalibrationError(
        f"{dataset.path}: no camera shares a board view with the reference "
        f"{dataset.rig.reference!r}; move the board where two cameras see it at once"
    )


def pose_graph(
    dataset: FolderDataset,
    observations: list[BoardObservation],
    config: CalibrationConfig,
    fixed_cameras: dict[str, np.ndarray] | None,
) -> PoseGraphResult:
    """The robust pose graph of the per-view board poses (edges weighted by their PnP
    covariance unless ``config.edge_covariance`` is off)."""
    edges = pose_edges(observations, config)
    pg = calibrate_pose_graph(edges, dataset.rig.reference, config.graph, fixed_cameras)
    if len(pg.cameras) < 2:
        raise _no_shared_view(dataset)
    return pg


def _unconnected(
    names: list[str], observations: list[BoardObservation], unconnected: dict[str, str]
) -> dict[str, str]:
    """The pose graph's unconnected cameras, plus every camera without a usable view."""
    out = dict(unconnected)
    seen = {o.camera for o in observations}
    for cam in names:
        if cam not in seen and cam not in out:
            out[cam] = "no usable board view (board never detected, or every view was rejected)"
    return out


def _refine_method(refine: str, dataset: FolderDataset, cameras: dict[str, Any]) -> str:
    """``auto`` is colored ICP when any calibrated camera has depth, else none."""
    if refine == "auto":
        return "colored-icp" if any(dataset.has_depth(c) for c in cameras) else "none"
    return refine


def _explain_dropped(
    names: list[str],
    graph_cameras: dict[str, Any],
    cameras: dict[str, CameraExtrinsics],
    unconnected: dict[str, str],
) -> None:
    """Give every camera that is not in the result a reason in ``unconnected``."""
    for cam in graph_cameras:
        if cam not in cameras and cam not in unconnected:
            unconnected[cam] = (
                "every board view linking it to the other cameras was rejected as an outlier; "
                "check its intrinsics (rig.yaml) and frame synchronisation"
            )
    for cam in names:
        if cam not in cameras and cam not in unconnected:
            unconnected[cam] = "not connected to the reference after outlier rejection"
