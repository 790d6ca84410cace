"""The calibration pipeline: ``calibrate(dataset, board, config) -> CalibrationResult``.

Stages, one module each::

    dataset (FolderDataset) -> detection (ArUco + unbiased corners, cached, in parallel)
        -> pose (per-view PnP, covariance, gates) -> graph (initialisation from the
        co-visibility spanning tree, robust pose graph, bundle adjustment, marginals)
        -> results (extrinsics + uncertainty)

No file is written here except the detection cache; :mod:`rgbd_calib.outputs.writer` writes results.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.config import BundleConfig, CalibrationConfig, DetectionConfig, PoseConfig
from ..core.errors import CalibrationError
from ..core.parallel import executor as make_executor
from ..core.progress import Progress, Tick, start, timed
from ..core.yamlio import atomic_write_text
from ..detect.markers import MarkerDetections, detect_job, init_detector
from ..model.board import Board, refined_board, refined_multiface
from ..model.dataset import FolderDataset
from ..model.results import CameraExtrinsics, Extrinsics, PoseEdge, cameras_from_solve
from ..model.rig import Rig
from ..solve import selfcal
from ..solve.intrinsics_init import InitialIntrinsics, initialise_intrinsics
from ..solve.pose import BoardObservation, RejectedView, estimate_board_pose
from ..solve.posegraph import (
    BundleResult,
    MarkerMeasurement,
    PoseGraphResult,
    RelativePose,
    bundle_adjust,
    calibrate_pose_graph,
    robust_mean_pose,
)
from ..solve.selfcal import SelfCalibration
from .refine import (
    DepthRefinement,
    board_views_per_camera,
    finish_pairs,
    measure_depth,
    moved_beyond_board,
)

# 2: colour PNGs read as grey by OpenCV's weights (libpng's own grey was 1 DN off on half the
# pixels), so detections of the same file differ slightly from a version-1 cache's
CACHE_VERSION = 2
CACHE_SAVE_EVERY_S = 30.0  # an interrupted detection loses at most about this much work
# detections with the refined lens: at most this many passes, another one while some
# camera's lens moved by more than LENS_SETTLED_PX at its detected corners (see lens_moved)
REDETECTIONS = 3
LENS_SETTLED_PX = 0.1
# a flagged camera whose corners fit within 2x the rig's RMS once the board or intrinsics
# were refined had its model error explained by them (see model_error_sigmas)
MODEL_ERROR_EXPLAINED = 4.0


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


# ----------------------------------------------------------------------------- detection stage
def _fingerprint(board: Board, config: DetectionConfig) -> str:
    text = json.dumps(
        [board.to_dict(), board.corners.tolist(), config.model_dump(), CACHE_VERSION],
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _lens_key(intrinsics: CameraIntrinsics) -> str:
    """What of a camera's model the edge fit depends on: nothing for a pinhole camera (its
    marker edges are straight), the whole model when the lens distorts (the fit bends the
    edges with it)."""
    if not intrinsics.has_distortion:
        return ""
    text = json.dumps(intrinsics.to_dict(), sort_keys=True, default=float)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def _file_key(path: Path) -> str:
    st = path.stat()
    return f"{st.st_size}:{st.st_mtime_ns}"


def detect_dataset(
    dataset: FolderDataset,
    board: Board,
    config: DetectionConfig,
    cache_path: Path | None = None,
    workers: int | None = None,
    progress: Tick | None = None,
    scheduler: str | None = None,
) -> dict[tuple[str, str], MarkerDetections]:
    """Detect markers in every colour image, in a process pool (or on the Dask cluster of
    ``scheduler``, :func:`rgbd_calib.core.parallel.executor`), reusing a cache.

    The cache (JSON) is keyed by the board and detection settings and, per image, by file
    size and modification time; it is saved every :data:`CACHE_SAVE_EVERY_S` seconds (and
    at least 500 images apart) so an interrupted run resumes where it stopped. Each image's
    entry is serialised once, to a JSON string: saving the whole cache every 500 images
    cost a 16 x 1000 set ~20 s of the main process's CPU (a 26 MB JSON, 32 times), and
    keeping the entries as Python objects would cost memory."""
    fingerprint = _fingerprint(board, config)
    lens = {c: _lens_key(i) for c, i in dataset.rig.cameras.items()}
    cached: dict[str, dict] = {}
    if cache_path is not None and cache_path.is_file():
        try:
            data = json.loads(cache_path.read_text())
            if data.get("fingerprint") == fingerprint:
                cached = data["images"]
        except (ValueError, KeyError):
            cached = {}  # a corrupt cache is only a cache: detect again
    results: dict[tuple[str, str], MarkerDetections] = {}
    entries: dict[str, str] = {}  # the cache's images: key -> its entry as JSON text
    jobs = []
    for fs in dataset.frame_sets():
        for cam, path in fs.color.items():
            key = f"{cam}/{fs.frame}"
            entry = cached.get(key)
            intr = dataset.rig.cameras[cam]
            if (entry is not None and entry.get("file") == _file_key(path)
                    and entry.get("lens", "") == lens[cam]):
                results[(cam, fs.frame)] = MarkerDetections.from_dict(entry["det"])
                if cache_path is not None:
                    entries[key] = json.dumps(entry)
            else:
                job = (cam, fs.frame, str(path), intr.width, intr.height)
                jobs.append(job + (intr,) if intr.has_distortion else job)
    if progress:
        progress(len(results))

    def keep(cam: str, frame: str, det: dict) -> None:
        results[(cam, frame)] = MarkerDetections.from_dict(det)
        if cache_path is not None:
            entry = {"file": _file_key(dataset.color_path(cam, frame)), "det": det}
            if lens[cam]:
                entry["lens"] = lens[cam]
            entries[f"{cam}/{frame}"] = json.dumps(entry)

    def save() -> None:
        if cache_path is not None:
            images = ", ".join(f"{json.dumps(k)}: {v}" for k, v in entries.items())
            text = f'{{"fingerprint": {json.dumps(fingerprint)}, "images": {{{images}}}}}'
            atomic_write_text(cache_path, text)

    workers = workers or os.cpu_count() or 1
    done_since_save, saved_at = 0, time.monotonic()
    executor = None
    if scheduler and jobs:
        # connected before the try: a scheduler that does not answer writes no cache
        executor = make_executor(scheduler=scheduler, initializer=init_detector,
                                 initargs=(board, config))
    elif workers > 1 and len(jobs) >= 8:
        executor = make_executor(workers, initializer=init_detector, initargs=(board, config))
    try:
        if executor is None:
            init_detector(board, config, threads=-1)
            iterator = map(detect_job, jobs)
        else:
            iterator = executor.map(detect_job, jobs, chunksize=4)
        for cam, frame, det in iterator:
            keep(cam, frame, det)
            done_since_save += 1
            if progress:
                progress(1)
            if done_since_save >= 500 and time.monotonic() - saved_at >= CACHE_SAVE_EVERY_S:
                save()
                done_since_save, saved_at = 0, time.monotonic()
    finally:
        if jobs:
            save()
        if executor is not None:
            executor.shutdown(cancel_futures=True)
    return results


# ----------------------------------------------------------------------------- pipeline
def calibrate(
    dataset: FolderDataset,
    board: Board,
    config: CalibrationConfig | None = None,
    cache_dir: Path | None = None,
    fixed_cameras: dict[str, np.ndarray] | None = None,
    progress: Progress | None = None,
) -> CalibrationResult:
    """Calibrate the extrinsics of every camera of ``dataset`` relative to its reference.

    ``fixed_cameras`` holds given cameras at ``T_ref_cam`` (adding a camera to a calibrated
    rig). Raises :class:`CalibrationError` when nothing can be calibrated."""
    config = config or CalibrationConfig()
    rig = dataset.rig
    timings: dict[str, float] = {}
    n_images = sum(len(fs.color) for fs in dataset.frame_sets())
    # 1. markers in every colour image (cached, in parallel)
    with timed(timings, "detection"):
        tick = start(progress, "detecting markers", n_images)
        cache = cache_dir / "detections.json" if cache_dir is not None else None
        detections = detect_dataset(dataset, board, config.detection, cache, config.workers, tick,
                                    config.scheduler)
    initial: dict[str, InitialIntrinsics] = {}
    if rig.unknown_intrinsics:
        # 1b. the cameras rig.yaml gives only the size of: intrinsics from their own views,
        #     then refined jointly in the bundle adjustment with the others (their prior)
        with timed(timings, "intrinsics_init"):
            initial = initialise_intrinsics(detections, board, rig)
        rig = rig.with_intrinsics({c: i.intrinsics for c, i in initial.items()})
        dataset = copy.copy(dataset)  # same frames, another rig: no re-scan
        dataset.rig = rig
        config = _with_scratch_intrinsics(config)
    # 2. one board pose per view (PnP, covariance, gates)
    with timed(timings, "pose"):
        observations, rejected = board_poses(detections, board, rig, config.pose)
    _check_views(dataset, detections, observations, rejected, n_images)
    # 3. robust pose graph over the views: initial extrinsics and board poses
    with timed(timings, "pose_graph"):
        pg = pose_graph(dataset, observations, config, fixed_cameras)
    unconnected = _unconnected(rig.names, observations, pg.unconnected)
    bundle, depth, board_only, ladder = None, None, None, None
    cameras, factors = model_error_sigmas(dict(pg.cameras), None, pg, config)
    if config.method == "bundle":
        # 4. bundle adjustment on the marker corners, freeing as much of the board and lens
        #    model as the data supports (bundle.board / bundle.intrinsics: auto)
        with timed(timings, "bundle"):
            bundle, measurements, solve, ladder = self_calibrated_bundle(
                observations, pg, rig, board, config, fixed_cameras, progress)
        lens_refined = (ladder.chosen.distortion if ladder is not None
                        else _refines_distortion(config.bundle))
        if lens_refined and (ladder is not None or board.charuco is None):
            # the corners were fitted along straight edges; with the refined lens the edges
            # are curved: detect again with it and solve the chosen model once more, again
            # while the views this adds move a camera's lens where its corners are
            lens_rig = refined_rig(rig, bundle)
            for _ in range(REDETECTIONS):
                with timed(timings, "redetection"):
                    relens = copy.copy(dataset)
                    relens.rig = lens_rig
                    tick = start(progress, "detecting markers with the refined lens", n_images)
                    cache = cache_dir / "detections_refined_lens.json" if cache_dir else None
                    detections = detect_dataset(relens, board, config.detection, cache,
                                                config.workers, tick, config.scheduler)
                    observations, rejected = board_poses(detections, board, lens_rig,
                                                         config.pose)
                with timed(timings, "bundle"):
                    # with the lens right, views its rig.yaml model failed pass PnP: add them
                    boards = {**pg.T_ref_board, **bundle.T_ref_board}
                    boards |= unsolved_views(observations, bundle.T_ref_cam, boards)
                    measurements = marker_measurements(observations, pg, rig, True, board,
                                                       True, boards)
                    bundle = bundle_sound_first(measurements, _camera_matrices(rig),
                                                rig.reference,
                                                {**pg.T_ref_cam, **bundle.T_ref_cam}, boards,
                                                solve, pg, fixed_cameras,
                                                intrinsics=rig.cameras,
                                                back_centre=back_centre(board),
                                                face_frames=face_frames(board))
                moved = lens_moved(lens_rig, bundle.intrinsics, observations)
                if not moved:
                    break
                lens_rig = lens_rig.with_intrinsics({c: bundle.intrinsics[c] for c in moved})
            if ladder is not None:
                ladder = replace(ladder, redetected=True)
        cameras, factors = model_error_sigmas(cameras_from_solve(bundle), bundle, pg, solve)
        if bundle.intrinsics:
            # the depth stage back-projects with the refined intrinsics (and their sigmas)
            dataset = copy.copy(dataset)  # same frames, another rig: no re-scan
            dataset.rig = refined_rig(rig, bundle)
        refine = _refine_method(config.refine, dataset, cameras)
        if refine != "none":
            # 5. depth: scale per camera, static clouds, pairwise registration
            board_only = Extrinsics(rig.reference, dict(cameras), dict(unconnected))
            T_ref_cam = {c: e.T_ref_cam for c, e in cameras.items()}
            # the board's faces where the bundle put them (a refined back sheet's thickness)
            model = bundle.board
            depth_board = (refined_board(board, model.T_front_back)
                           if model is not None and not model.held else board)
            if any(not f.held for f in bundle.faces):  # a multi-face target's refined faces
                depth_board = refined_multiface(board, {f.label: f.T_board_face
                                                        for f in bundle.faces if not f.held})
            with timed(timings, "depth"):
                views = board_views_per_camera(observations, T_ref_cam, bundle.T_ref_board)
                depth = measure_depth(dataset, depth_board, T_ref_cam, views,
                                      bundle.T_ref_board, refine, config.depth, progress,
                                      board_covariance={c: e.covariance
                                                        for c, e in cameras.items()},
                                      workers=config.workers, scheduler=config.scheduler)
            # 6. joint solve: corners and the accepted depth pairs
            if depth.used:
                try:
                    with timed(timings, "joint"):
                        joint = bundle_sound_first(measurements, _camera_matrices(rig),
                                                   rig.reference, T_ref_cam,
                                                   bundle.T_ref_board, solve, pg,
                                                   fixed_cameras, depth.relative_poses,
                                                   intrinsics=rig.cameras,
                                                   back_centre=back_centre(board),
                                                   face_frames=face_frames(board))
                except Exception as exc:  # noqa: BLE001 - the depth pairs must never end a run
                    depth = depth.with_fallback(f"the joint solve with the depth pairs failed "
                                                f"({type(exc).__name__}: {exc})".replace(
                                                    "\n", " "))
                else:
                    joint_cameras, joint_factors = model_error_sigmas(cameras_from_solve(joint),
                                                                      joint, pg, solve)
                    beyond = moved_beyond_board(cameras, joint_cameras)
                    if beyond:  # depth never moves a camera beyond its board uncertainty
                        depth = depth.with_fallback("; ".join(beyond.values()))
                    else:
                        bundle, cameras, factors = joint, joint_cameras, joint_factors
            # 7. checks: each pair's fit at the final extrinsics
            with timed(timings, "depth_check"):
                depth = finish_pairs(depth, {c: e.T_ref_cam for c, e in cameras.items()},
                                     config.depth,
                                     start(progress, "checking depth pairs", len(depth.pairs)))
    _explain_dropped(rig.names, pg.cameras, cameras, unconnected)
    extrinsics = Extrinsics(
        rig.reference, {c: cameras[c] for c in rig.names if c in cameras}, unconnected
    )
    return CalibrationResult(extrinsics, observations, rejected, pg, bundle, config, n_images,
                             timings, dataset.summary().to_dict(), depth, board_only,
                             model_error_factor=factors, board=board, self_calibration=ladder,
                             initial_intrinsics=initial, rig=rig)


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


# ----------------------------------------------------------------------------- stages
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


def _check_views(
    dataset: FolderDataset,
    detections: dict[tuple[str, str], MarkerDetections],
    observations: list[BoardObservation],
    rejected: list[RejectedView],
    n_images: int,
) -> None:
    """Stop with the reason when the views cannot link any camera to the reference (before the
    pose graph, whose own errors name no dataset)."""
    if not observations:
        total = sum(len(d.ids) for d in detections.values())
        raise CalibrationError(
            f"{dataset.path}: no usable board view in {n_images} images ({total} board markers "
            + ("detected); check that --board matches the printed board (dictionary, ids) and "
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


SMALL_MARKER_PX = 20.0  # markers narrower than this in the images: at ArUco's limit


def _why_dropped(detections: dict[tuple[str, str], MarkerDetections],
                 rejected: list[RejectedView]) -> str:
    """Why views with markers gave no pose, for an error message: the reasons by count, the
    advice for the most common, and the size of the markers in the images of those views
    (ArUco finds markers down to ~10 px; a pose needs a few of them)."""
    # the advice lives with the report's wording; imported here, on the error path only, so
    # that the pipeline (and every pool worker preloading it) does not load the report package
    from ..outputs.report.schema import DROP_ADVICE

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
        for mid, c, P in zip(o.ids, px, o.object_points):
            face = 1 if board is None else int(board.faces[board.index_of[int(mid)]])
            measurements.append(MarkerMeasurement(o.camera, o.frame, int(mid), c, P, face))
    return measurements


def unsolved_views(observations: list[BoardObservation], T_ref_cam: dict[str, np.ndarray],
                   T_ref_board: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """First ``T_ref_board`` (4x4, metres) of the frames that have no board pose in
    ``T_ref_board`` but a view by a camera of ``T_ref_cam``: the robust mean
    (:func:`~rgbd_calib.solve.posegraph.robust_mean_pose`) of ``T_ref_cam @ T_cam_board`` over those
    views.

    The pose graph solves only the frames that two cameras saw with the model it was given.
    With the intrinsics refined, a frame one camera alone saw still measures that camera's
    lens, and a view the rig.yaml lens failed (PnP's reprojection gate: an unlisted
    distortion is largest at the image's edge) is usable once the lens is refined. Those are
    the views that reach the image's edge. Measured (issue 13, ring seed 11 ``all``, board
    volume 2.5): every corner of cam3 beyond a normalised radius of 0.8 (the image corners are
    at 1.5) came from two such frames; without them its refined lens was 3.1 px off the truth
    inside its corners' hull and 40 px at the image corners, with them 0.13 px and 0.83 px."""
    views: dict[str, list[np.ndarray]] = {}
    for o in observations:
        if o.frame not in T_ref_board and o.camera in T_ref_cam:
            views.setdefault(o.frame, []).append(T_ref_cam[o.camera] @ o.T_cam_board)
    return {f: robust_mean_pose(np.stack(T)) for f, T in views.items()}


def self_calibrated_bundle(
    observations: list[BoardObservation],
    pg: PoseGraphResult,
    rig: Rig,
    board: Board,
    config: CalibrationConfig,
    fixed_cameras: dict[str, np.ndarray] | None = None,
    progress: Progress | None = None,
) -> tuple[BundleResult, list[MarkerMeasurement], CalibrationConfig, SelfCalibration | None]:
    """The bundle adjustment with ``config.bundle``'s board and intrinsics models.

    Explicit modes (``fixed`` / ``refine``) solve once. With ``auto`` (either), the ladder of
    :mod:`rgbd_calib.solve.selfcal`: the nominal model first, then each richer model started from
    the last accepted solve, kept only when it calibrates more cameras or fits the common
    markers better than its extra parameters cost (BIC). Returns the chosen solve, its
    measurements, the configuration it was solved with (explicit modes, for the later joint
    solve) and the ladder (None for explicit modes)."""
    b = config.bundle
    K, centre = _camera_matrices(rig), back_centre(board)
    tick = start(progress, "bundle adjustment (models solved)", None)

    def solve(level: BundleConfig, init_cam: dict[str, np.ndarray],
              init_board: dict[str, np.ndarray], freed: bool):
        tick(1)
        cfg = config.model_copy(update={"bundle": level})
        refined = level.intrinsics == "refine"
        if refined:  # a frame one camera alone saw measures its lens
            init_board = {**init_board, **unsolved_views(observations, init_cam, init_board)}
        meas = marker_measurements(observations, pg, rig, refined_intrinsics=refined,
                                   board=board, keep_outlier_views=freed,
                                   boards=init_board if refined else None)
        result = bundle_sound_first(meas, K, rig.reference, init_cam, init_board, cfg, pg,
                                    fixed_cameras, intrinsics=rig.cameras, back_centre=centre,
                                    face_frames=face_frames(board))
        return result, meas, cfg

    if not selfcal.is_auto(b):
        result, meas, cfg = solve(b, pg.T_ref_cam, pg.T_ref_board, b.board == "refine")
        return result, meas, cfg, None
    errors = (CalibrationError, RuntimeError, ValueError, np.linalg.LinAlgError)
    cap = b.outlier_px
    level = selfcal.base_level(b)
    current, meas, cfg = solve(level.bundle_config(b), pg.T_ref_cam, pg.T_ref_board,
                               level.board)
    terms = selfcal.marker_terms(current.residuals_px, current.outliers, cap)
    fits = [selfcal.LevelFit(level, len(current.T_ref_cam), len(current.residuals_px),
                             selfcal.rms_px(terms), reason="the starting model")]

    def try_level(trial_level: selfcal.ModelLevel):
        """Solve ``trial_level`` from the accepted solve; (fit, solve, measurements, config,
        marker terms), the solve None when it failed."""
        init_cam = {**pg.T_ref_cam, **current.T_ref_cam}
        init_board = {**pg.T_ref_board, **current.T_ref_board}
        try:
            trial, t_meas, t_cfg = solve(trial_level.bundle_config(b), init_cam, init_board,
                                         True)
        except errors as exc:
            return (selfcal.LevelFit(trial_level, 0, 0, float("nan"), accepted=False,
                                     reason=f"the solve failed: {exc}"), None, [], cfg, {})
        n_cams = len({m.camera for m in t_meas} - set(fixed_cameras or {}))
        added = (selfcal.board_parameters(board) if trial_level.board and not level.board
                 else 0) + (
            len(trial_level.intrinsics_params) - len(level.intrinsics_params)) * n_cams
        t_terms = selfcal.marker_terms(trial.residuals_px, trial.outliers, cap)
        ok, gain, reason = selfcal.compare(terms, len(current.T_ref_cam), t_terms,
                                           len(trial.T_ref_cam), added)
        if ok and trial_level.board and not level.board and trial.board is not None \
                and trial.board.held:
            ok, reason = False, trial.board.held
        if ok and trial_level.board and not level.board and trial.faces \
                and all(f.held for f in trial.faces):
            ok, reason = False, "; ".join(f.held for f in trial.faces)
        tension = selfcal.prior_tension(trial, rig)
        if ok and tension is not None and tension[0] > selfcal.PRIOR_TENSION:
            # the data put a parameter several prior sigmas from rig.yaml: the prior is wrong
            # (another camera's file, a re-focused lens) and would bias the value and the
            # extrinsics towards it while the marginals stay small. Loosen it.
            z, cam, name = tension
            try:
                trial, t_meas, t_cfg = solve(selfcal.loosened(t_cfg.bundle),
                                             {**init_cam, **trial.T_ref_cam},
                                             {**init_board, **trial.T_ref_board}, True)
                t_terms = selfcal.marker_terms(trial.residuals_px, trial.outliers, cap)
                reason += (f"; {name} of {cam} came {z:.1f} prior sigmas from rig.yaml: "
                           f"priors loosened {selfcal.LOOSEN:.0f}x")
            except errors as exc:
                reason += f"; loosening the contradicted prior failed: {exc}"
        fit = selfcal.LevelFit(trial_level, len(trial.T_ref_cam), len(trial.residuals_px),
                               selfcal.rms_px(t_terms), added, gain, ok, reason)
        return fit, trial, t_meas, t_cfg, t_terms

    double_sided = bool(np.any(np.asarray(board.faces) < 0)) or len(board.face_labels) > 1
    queue = selfcal.candidate_groups(b, double_sided, bool(pg.model_error))
    # a group that a wrong model elsewhere hid (the back sheet judged through an undistorted
    # lens) is tried once more after a later group was accepted
    for _ in range(2):
        rejected, retry = [], False
        for group in queue:
            tried = [try_level(selfcal.extend(level, step)) for step in group
                     if selfcal.extend(level, step) != level]
            good = [t for t in tried if t[0].accepted]
            best = None
            for t in good:
                if best is None or selfcal.better(t[0], best[0]):
                    best = t
            fits += [t[0] if best is None or t is best or not t[0].accepted else
                     replace(t[0], accepted=False,
                             reason=t[0].reason + "; another model fits better")
                     for t in tried]
            if best is None:
                rejected.append(group)
                continue
            fit, current, meas, cfg, terms = best
            level, retry = fit.level, retry or bool(rejected)
        if not retry:
            break
        queue = rejected
    return current, meas, cfg, selfcal.SelfCalibration(level, fits)


def lens_moved(detected_with: Rig, refined: dict[str, CameraIntrinsics],
               observations: list[BoardObservation]) -> list[str]:
    """The cameras whose ``refined`` lens images the rays of their detected corners more than
    :data:`LENS_SETTLED_PX` from where the lens the corners were detected with
    (``detected_with``) does: their edge fit bent the marker edges by a model that has moved,
    so their corners should be detected again.

    It matters for the views that reach an image's corners: they fail PnP with rig.yaml's
    lens, so the first refined lens never saw them and is an extrapolation there. Measured
    (issue 13, ring seed 23 ``all``, board volume 2.5, 8 close-ups per camera): the corners
    of cam3's close-ups at a normalised radius of 1.3 came out 0.6 px off the truth with that
    lens, 0.06-0.13 px with the lens refined from them (0.05-0.18 px with the true one)."""
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


def refined_rig(rig: Rig, bundle: BundleResult) -> Rig:
    """``rig`` with the bundle adjustment's refined intrinsics (cameras it did not refine keep
    their rig.yaml model): what ``rig_refined.yaml`` holds."""
    return replace(rig.with_intrinsics(bundle.intrinsics), sigmas=dict(bundle.intrinsics_sigma))


def bundle_sound_first(
    measurements: list[MarkerMeasurement],
    K: dict[str, np.ndarray],
    reference: str,
    init_T_ref_cam: dict[str, np.ndarray],
    init_T_ref_board: dict[str, np.ndarray],
    config: CalibrationConfig,
    pg: PoseGraphResult,
    fixed_cameras: dict[str, np.ndarray] | None = None,
    relative_poses: list[RelativePose] = (),
    intrinsics: dict[str, CameraIntrinsics] | None = None,
    back_centre: np.ndarray | None = None,
    face_frames: dict[int, np.ndarray] | None = None,
) -> BundleResult:
    """:func:`~rgbd_calib.solve.posegraph.bundle_adjust`, so that a camera with a model error does not
    pull the others.

    The bundle weighs every corner alike; the corners of a camera whose model is off
    (``pg.model_error``) would bend the board poses and, through them, the sound cameras.
    When there are such cameras and at least one sound camera besides the reference, the
    sound cameras (with the reference and any fixed ones) are solved first on their own
    corners; then every camera, the sound ones held where the first solve put them, which
    places the model-error cameras against boards the sound cameras fixed. Sound cameras
    keep the first solve's covariance and board poses seen by it keep its values. Otherwise
    (no model error, or every camera has one) one joint solve.

    With the intrinsics or the back sheet refined (``bundle.intrinsics`` / ``bundle.board``
    ``"refine"``) the model error the pose graph saw is what the solve estimates: one joint
    solve. Solving the few sound cameras first and holding them would fix their poses (and
    lens) from a fraction of the views (measured: race, every lens 0.7 % / 3 px off,
    distortion unlisted, glued sheet: the sound set was the reference and one camera, and
    every other camera ended 2-6 mm / 0.1 deg off at claimed sigmas of 0.2-0.3 mm; one joint
    solve: 0.83 mm / 0.012 deg worst. Ring seed 23, glued sheet: the front-facing cameras
    0.09-0.13 mm off at sigmas of 0.025-0.035 mm; joint: 0.07-0.11 mm at 0.04-0.05 mm)."""
    fixed = dict(fixed_cameras or {})
    cams = {m.camera for m in measurements}
    sound = {c for c in cams if c not in pg.model_error} | {reference} | set(fixed)
    freed = "refine" in (config.bundle.intrinsics, config.bundle.board)
    joint = (freed or not pg.model_error or not (cams - sound)
             or len(sound - {reference} - set(fixed)) < 1)
    if joint:
        return bundle_adjust(measurements, K, reference, init_T_ref_cam, init_T_ref_board,
                             config.bundle, fixed_cameras, relative_poses,
                             intrinsics=intrinsics, back_centre=back_centre,
                             face_frames=face_frames)
    first = bundle_adjust([m for m in measurements if m.camera in sound], K, reference,
                          init_T_ref_cam, init_T_ref_board, config.bundle, fixed_cameras,
                          [r for r in relative_poses if {r.cam_a, r.cam_b} <= sound],
                          intrinsics=intrinsics, back_centre=back_centre,
                          face_frames=face_frames)
    held = {**first.T_ref_cam, **fixed}
    boards = {**init_T_ref_board, **first.T_ref_board}
    second = bundle_adjust(measurements, K, reference, {**init_T_ref_cam, **held}, boards,
                           config.bundle, held, relative_poses, intrinsics=intrinsics,
                           back_centre=back_centre, face_frames=face_frames)
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


def model_error_sigmas(
    cameras: dict[str, CameraExtrinsics],
    bundle: BundleResult | None,
    pg: PoseGraphResult,
    config: CalibrationConfig,
) -> tuple[dict[str, CameraExtrinsics], dict[str, float]]:
    """Honest uncertainty when the pose graph found cameras with a model error.

    The pose graph's marginals are the honest ones then: a model-error camera's edges carry
    its a-posteriori variance factor and, being common to all its views, count once (see
    ``_EdgeNoise.correlated`` in :mod:`rgbd_calib.solve.posegraph`), and every camera chained to the
    reference through it inherits that. The bundle adjustment weighs every corner alike, so
    after it each camera's covariance is scaled up until it covers the pose graph's (the
    largest generalised eigenvalue of the pair) and, for a model-error camera, by at least
    its own corners' variance factor (``mean(rms^2) / 2`` over the bundle's corner sigma^2)
    times its number of views. A model-error camera the bundle lost (every marker beyond
    ``outlier_px``) keeps its pose-graph estimate. ``bundle`` None: the pose graph's cameras
    are already honest. Returns the cameras and, per model-error camera, its total factor
    over its nominal covariance (pose-graph variance factor x edges, or the bundle scale)."""
    out = dict(cameras)
    factors = {c: m.variance_factor * max(m.edges, 1) for c, m in pg.model_error.items()}
    if bundle is None or not pg.model_error:
        return out, factors
    b = config.bundle
    sigma_px = max(bundle.pixel_sigma_estimated, 1e-3) if b.estimate_sigma else b.pixel_sigma
    if b.board == "refine" or b.intrinsics == "refine":
        # the pose graph judged the views with the nominal board and rig.yaml intrinsics; the
        # bundle freed that model. When every flagged camera's corners now fit like the rest
        # of the rig, the freed model explained the error: nothing is left to inflate.
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


def _camera_matrices(rig: Rig) -> dict[str, np.ndarray]:
    return {c: rig.cameras[c].K for c in rig.names}


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
