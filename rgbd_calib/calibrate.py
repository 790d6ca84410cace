"""The calibration pipeline: ``calibrate(dataset, board, config) -> CalibrationResult``.

Stages, one module each::

    dataset (FolderDataset) -> detection (ArUco + unbiased corners, cached, in parallel)
        -> pose (per-view PnP, covariance, gates) -> graph (initialisation from the
        co-visibility spanning tree, robust pose graph, bundle adjustment, marginals)
        -> results (extrinsics + uncertainty)

No file is written here except the detection cache; :mod:`rgbd_calib.outputs` writes results.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .board import Board
from .config import CalibrationConfig, DetectionConfig
from .dataset import FolderDataset
from .detection import MarkerDetections, detect_job, init_detector
from .errors import CalibrationError
from .graph import (
    BundleResult,
    MarkerMeasurement,
    PoseGraphResult,
    bundle_adjust,
    calibrate_pose_graph,
)
from .parallel import process_context
from .pose import BoardObservation, RejectedView, estimate_board_pose, undistort_pixels
from .refine import DepthRefinement, board_views_per_camera, finish_pairs, measure_depth
from .results import CameraExtrinsics, Extrinsics, PoseEdge
from .yamlio import atomic_write_text

CACHE_VERSION = 1


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


# ----------------------------------------------------------------------------- detection stage
def _fingerprint(board: Board, config: DetectionConfig) -> str:
    text = json.dumps(
        [board.to_dict(), board.corners.tolist(), config.model_dump(), CACHE_VERSION],
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _file_key(path: Path) -> str:
    st = path.stat()
    return f"{st.st_size}:{st.st_mtime_ns}"


def detect_dataset(
    dataset: FolderDataset,
    board: Board,
    config: DetectionConfig,
    cache_path: Path | None = None,
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[tuple[str, str], MarkerDetections]:
    """Detect markers in every colour image, in a process pool, reusing a cache.

    The cache (JSON) is keyed by the board and detection settings and, per image, by file
    size and modification time; it is saved every few hundred images so an interrupted run
    resumes where it stopped."""
    fingerprint = _fingerprint(board, config)
    cached: dict[str, dict] = {}
    if cache_path is not None and cache_path.is_file():
        try:
            data = json.loads(cache_path.read_text())
            if data.get("fingerprint") == fingerprint:
                cached = data["images"]
        except (ValueError, KeyError):
            cached = {}  # a corrupt cache is only a cache: detect again
    results: dict[tuple[str, str], MarkerDetections] = {}
    jobs = []
    for fs in dataset.frame_sets():
        for cam, path in fs.color.items():
            key = f"{cam}/{fs.frame}"
            entry = cached.get(key)
            if entry is not None and entry.get("file") == _file_key(path):
                results[(cam, fs.frame)] = MarkerDetections.from_dict(entry["det"])
            else:
                intr = dataset.rig.cameras[cam]
                jobs.append((cam, fs.frame, str(path), intr.width, intr.height))
    if progress:
        progress(len(results))

    def save() -> None:
        if cache_path is None:
            return
        images = {
            f"{c}/{f}": {"file": _file_key(dataset.color_path(c, f)), "det": d.to_dict()}
            for (c, f), d in results.items()
        }
        atomic_write_text(cache_path, json.dumps({"fingerprint": fingerprint, "images": images}))

    workers = workers or os.cpu_count() or 1
    done_since_save = 0
    try:
        if workers <= 1 or len(jobs) < 8:
            init_detector(board, config, threads=-1)
            iterator = map(detect_job, jobs)
            executor = None
        else:
            executor = ProcessPoolExecutor(
                workers,
                mp_context=process_context(),
                initializer=init_detector,
                initargs=(board, config),
            )
            iterator = executor.map(detect_job, jobs, chunksize=4)
        for cam, frame, det in iterator:
            results[(cam, frame)] = MarkerDetections.from_dict(det)
            done_since_save += 1
            if progress:
                progress(1)
            if done_since_save >= 500:
                save()
                done_since_save = 0
    finally:
        if jobs:
            save()
        if jobs and executor is not None:
            executor.shutdown(cancel_futures=True)
    return results


# ----------------------------------------------------------------------------- pipeline
def calibrate(
    dataset: FolderDataset,
    board: Board,
    config: CalibrationConfig | None = None,
    cache_dir: Path | None = None,
    fixed_cameras: dict[str, np.ndarray] | None = None,
    progress: Callable[[str, int, int], Callable[[int], None]] | None = None,
) -> CalibrationResult:
    """Calibrate the extrinsics of every camera of ``dataset`` relative to its reference.

    ``fixed_cameras`` holds given cameras at ``T_ref_cam`` (adding a camera to a calibrated
    rig). Raises :class:`CalibrationError` when nothing can be calibrated."""
    config = config or CalibrationConfig()
    timings: dict[str, float] = {}
    rig = dataset.rig
    t0 = time.perf_counter()
    n_images = sum(len(fs.color) for fs in dataset.frame_sets())
    tick = progress("detecting markers", n_images, 0) if progress else None
    cache = cache_dir / "detections.json" if cache_dir is not None else None
    detections = detect_dataset(dataset, board, config.detection, cache, config.workers, tick)
    timings["detection"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    observations: list[BoardObservation] = []
    rejected: list[RejectedView] = []
    for (cam, frame), det in sorted(detections.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        if len(det.ids) == 0:
            continue
        out = estimate_board_pose(det, board, rig.cameras[cam], config.pose, cam, frame)
        (observations if isinstance(out, BoardObservation) else rejected).append(out)
    timings["pose"] = time.perf_counter() - t0
    if not observations:
        total = sum(len(d.ids) for d in detections.values())
        raise CalibrationError(
            f"{dataset.path}: no usable board view in {n_images} images ({total} board markers "
            "detected); check that --board matches the printed board (dictionary, ids) and that "
            "the board is in view"
        )

    t0 = time.perf_counter()
    edges = [
        PoseEdge(o.camera, o.frame, o.T_cam_board, o.covariance if config.edge_covariance else None)
        for o in observations
    ]
    reference = rig.reference
    seen = {o.camera for o in observations}
    if reference not in seen:
        raise CalibrationError(
            f"{dataset.path}: the reference camera {reference!r} has no usable board view; "
            "record the board in its view or choose another reference in rig.yaml"
        )
    reference_frames = {o.frame for o in observations if o.camera == reference}
    if not any(o.camera != reference and o.frame in reference_frames for o in observations):
        raise CalibrationError(  # before the pose graph, whose own error names no dataset
            f"{dataset.path}: no camera shares a board view with the reference "
            f"{reference!r}; move the board where two cameras see it at once"
        )
    pg = calibrate_pose_graph(edges, reference, config.graph, fixed_cameras)
    timings["pose_graph"] = time.perf_counter() - t0
    unconnected = dict(pg.unconnected)
    for cam in rig.names:
        if cam not in seen and cam not in unconnected:
            unconnected[cam] = (
                "no usable board view (board never detected, or every view was rejected)"
            )
    if len(pg.cameras) < 2:
        raise CalibrationError(
            f"{dataset.path}: no camera shares a board view with the reference "
            f"{reference!r}; move the board where two cameras see it at once"
        )

    bundle = None
    depth = None
    board_only = None
    cameras = dict(pg.cameras)
    if config.method == "bundle":
        t0 = time.perf_counter()
        measurements = []
        stale_or_out = {
            pg.residuals[i].view + "/" + pg.residuals[i].camera for i in pg.outlier_edges
        }
        for o in observations:
            if o.camera not in pg.cameras or o.frame not in pg.T_ref_board:
                continue
            if f"{o.frame}/{o.camera}" in stale_or_out:
                continue
            px = undistort_pixels(o.corners_px, rig.cameras[o.camera])
            for mid, c, P in zip(o.ids, px, o.object_points):
                measurements.append(MarkerMeasurement(o.camera, o.frame, int(mid), c, P))
        K = {c: rig.cameras[c].K for c in rig.names}
        bundle = bundle_adjust(
            measurements, K, reference, pg.T_ref_cam, pg.T_ref_board, config.bundle, fixed_cameras
        )
        cameras = {
            c: CameraExtrinsics(
                c,
                bundle.T_ref_cam[c],
                bundle.sigma_rotation_deg[c],
                bundle.sigma_translation_mm[c],
                bundle.covariance[c],
            )
            for c in bundle.T_ref_cam
        }
        timings["bundle"] = time.perf_counter() - t0
        refine = config.refine
        if refine == "auto":
            refine = "colored-icp" if any(dataset.has_depth(c) for c in cameras) else "none"
        if refine != "none":
            board_only = Extrinsics(reference, dict(cameras), dict(unconnected))
            t0 = time.perf_counter()
            T_cam = {c: e.T_ref_cam for c, e in cameras.items()}
            depth = measure_depth(dataset, board, T_cam,
                                  board_views_per_camera(observations, T_cam, bundle.T_ref_board),
                                  bundle.T_ref_board, refine, config.depth, progress)
            timings["depth"] = time.perf_counter() - t0
            if depth.relative_poses:
                t0 = time.perf_counter()
                bundle = bundle_adjust(measurements, K, reference, T_cam, bundle.T_ref_board,
                                       config.bundle, fixed_cameras, depth.relative_poses)
                cameras = {c: CameraExtrinsics(c, bundle.T_ref_cam[c],
                                               bundle.sigma_rotation_deg[c],
                                               bundle.sigma_translation_mm[c],
                                               bundle.covariance[c])
                           for c in bundle.T_ref_cam}
                timings["joint"] = time.perf_counter() - t0
            t0 = time.perf_counter()  # each pair's fit at the final extrinsics, error maps
            depth = finish_pairs(depth, {c: e.T_ref_cam for c, e in cameras.items()},
                                 config.depth)
            timings["depth_check"] = time.perf_counter() - t0
    for cam in pg.cameras:
        if cam not in cameras and cam not in unconnected:
            unconnected[cam] = (
                "every board view linking it to the other cameras was rejected as an outlier; "
                "check its intrinsics (rig.yaml) and frame synchronisation"
            )
    for cam in rig.names:
        if cam not in cameras and cam not in unconnected:
            unconnected[cam] = "not connected to the reference after outlier rejection"
    extrinsics = Extrinsics(
        reference, {c: cameras[c] for c in rig.names if c in cameras}, unconnected
    )
    return CalibrationResult(
        extrinsics,
        observations,
        rejected,
        pg,
        bundle,
        config,
        n_images,
        timings,
        dataset.summary().to_dict(),
        depth,
        board_only,
    )
