"""Has a camera moved since the calibration? And if so, put it back (depth alone, no board).

A rig gets bumped: a camera knocked on its mount, a bracket that creeps. ``check`` takes one
frame set of the rig as it is now (or a few: their temporal median) and the calibration, and
decides per camera whether it is where the calibration says, from the depth clouds alone:

1. a static cloud per camera, with the calibration's depth-scale factors;
2. every overlapping pair registered (:func:`rgbd_calib.depth.registration.register_robust`):
   colored ICP from the calibrated relative pose and, when that does not fit the depth noise
   model (a camera knocked 5 cm / 5 deg is outside ICP's basin), the same ICP with a wider
   basin, then from a global alignment guided by the calibration (FPFH features + RANSAC,
   Rusu et al. ICRA 2009 / Open3D);
3. when the board is in the frames, its markers detected and each camera's PnP pose of it:
   two cameras that saw the board in one frame set measure their relative pose to a few
   tenths of a millimetre, where depth in a scene of walls and floor measures millimetres;
4. a pose graph of this evidence and one prior per camera at its calibrated pose with
   the calibration's sigmas, from which the moved cameras are found
   (:func:`rgbd_calib.solve.moved.locate_moved`).

:func:`check` is the library form of ``rgbd-calib check`` (``rgbd_calib.check``).
:func:`fix_moved` re-registers only the moved cameras against the others (from the check's
estimate, so from a start centimetres off) and solves for them with the others held at their
calibration. The reference camera is no exception: if it moved, the rest is re-expressed in
its new frame (the reference frame is, by contract, the reference camera's).
"""

from __future__ import annotations

import os
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..core.config import DepthConfig, DetectionConfig, PoseConfig, RegistrationMethod
from ..core.depth_model import DepthModel
from ..core.geometry import covariance_sigmas, invert_transform, transform_error
from ..core.progress import Progress, start
from ..depth.clouds import CameraCloud
from ..depth.registration import (
    DepthPair,
    PairRegistration,
    find_overlapping_pairs,
    pair_dicts,
)
from ..depth.stage import (
    applied_pose_moments,
    register_pairs,
    static_clouds,
    with_sensor_poses,
)
from ..detect.markers import MarkerDetections
from ..detect.run import detect_dataset
from ..model.board import Board
from ..model.calib_folder import calibration_board, load_calibration, with_refined_intrinsics
from ..model.dataset import FolderDataset
from ..model.results import CameraExtrinsics, Extrinsics
from ..solve.bundle_problem import RelativePose
from ..solve.edge_offset import without_offset
from ..solve.moved import (
    MOVED_CHI2,
    BoardLink,
    CameraCheck,
    Evidence,
    Tolerance,
    adjoint_map,
    anchored,
    kinds_disagree,
    locate_moved,
    prior_covariance,
    weighed_solve,
)
from ..solve.pose import BoardObservation, board_poses
from ..sources.cache import open_dataset


@dataclass(frozen=True)
class CheckResult:
    """Per camera :class:`CameraCheck`, the pairs (:class:`DepthPair`; their ``to_dict`` is
    check.json's entry) and the moved cameras in the order they were found."""

    cameras: dict[str, CameraCheck]
    pairs: list[DepthPair]
    tolerance: Tolerance
    timings_s: dict[str, float] = field(default_factory=dict)
    # the board's evidence: views, frame sets seen by two cameras or more, per camera views
    board: dict[str, Any] = field(default_factory=dict)
    variance_factors: dict[str, float] = field(default_factory=dict)

    @property
    def moved(self) -> list[str]:
        return [c for c, r in self.cameras.items() if r.status == "moved"]

    @property
    def unknown(self) -> list[str]:
        return [c for c, r in self.cameras.items() if r.status == "unknown"]

    def to_dict(self) -> dict[str, Any]:
        return {
            "moved": self.moved, "unknown": self.unknown,
            "tolerance": {"mm": self.tolerance.mm, "deg": self.tolerance.deg},
            "moved_chi2": MOVED_CHI2,
            "cameras": {c: r.to_dict() for c, r in self.cameras.items()},
            "pairs": pair_dicts(self.pairs), "board": self.board,
            "variance_factors": self.variance_factors, "timings_s": self.timings_s,
        }


def check_config(config: DepthConfig | None) -> DepthConfig:
    """The depth settings of a check: every pair that fits is a measurement, also one that
    confirms the calibration (``min_improvement_chi2`` 0), and a knocked camera's pair may
    move far (``max_correction`` 0.5 m / 30 deg: the correction of ``T_b_a`` is the knock's
    turn times the baseline, 0.15 m for 5 deg across a 1.7 m ring, beyond calibrate's
    wrong-minimum guard; here the noise-model fit guards against wrong minima)."""
    config = config or DepthConfig()
    return config.replaced(min_improvement_chi2=0.0,
                           max_correction_m=max(config.acceptance.max_correction_m, 0.5),
                           max_correction_deg=max(config.acceptance.max_correction_deg, 30.0))


def _jobs(pairs: list[tuple[str, str]], T: dict[str, np.ndarray],
          unknown_scale: set[str]) -> list:
    return [(a, b, T[a], T[b], (a in unknown_scale, b in unknown_scale)) for a, b in pairs]


MODEL_ERROR_PX = 0.1  # the board views' shared systematic (px) added to their PnP covariance


def board_links(observations: list[BoardObservation], cameras: set[str],
                model_error_px: float = MODEL_ERROR_PX) -> list[BoardLink]:
    """Each PnP pose of the board as a :class:`BoardLink` of the cameras in ``cameras``, its
    covariance the corner noise's plus a shared ``model_error_px`` per view (what the
    calibration's pose graph estimates as its model-error floor: a lens or a board slightly
    off moves all corners of a view together); only the frame sets that two of the cameras saw
    (:meth:`Evidence.of`)."""
    links = []
    for o in observations:
        if o.camera not in cameras:
            continue
        C = np.asarray(o.covariance, dtype=float)
        if o.model_error_unit is not None:
            C = C + model_error_px**2 * np.asarray(o.model_error_unit, dtype=float)
        links.append(BoardLink(o.camera, o.frame, np.asarray(o.T_cam_board, dtype=float), C))
    return list(Evidence.of([], links, cameras).links)


def board_evidence(dataset: FolderDataset, board: Board, cameras: set[str], calib: Extrinsics,
                   workers: int | None = None, progress: Progress | None = None,
                   scheduler: str | None = None, edge_offsets: dict[str, float] | None = None,
                   ) -> tuple[list[BoardLink], dict[str, Any], dict[str, np.ndarray]]:
    """The board in the checked frames: markers detected in every colour image
    (:func:`~rgbd_calib.detect.run.detect_dataset`, default settings, no cache), a PnP pose
    per view (:func:`~rgbd_calib.solve.pose.board_poses` with its gates), as
    :func:`board_links`; a summary for check.json (views, frame sets seen by two cameras or
    more, views per camera); and per frame where the board was (reference frame, through the
    calibration; the medoid of the cameras' views, so one knocked camera does not misplace it),
    for masking it out of the static clouds: a board waved through a few frames is not
    scene, and its remnants in a temporal median bias the depth pairs.

    ``edge_offsets`` (camera -> px per edge: the detector edge offsets the calibration
    modelled, ``bundle.edge_offset``) are taken out of the markers' corners first, so that the
    PnP poses are measured as the calibration's were (a 0.1 px offset is ~1.7 mm)."""
    n_images = len(dataset.frames) * len(dataset.cameras)
    detections = detect_dataset(dataset, board, DetectionConfig(), None, workers,
                                start(progress, "detecting the board", n_images), scheduler)
    detections = without_edge_offsets(detections, board, edge_offsets or {})
    observations, _ = board_poses(detections, board, dataset.rig, PoseConfig())
    links = board_links(observations, cameras)
    per_camera = dict(Counter(k.camera for k in links))
    by_frame: dict[str, list[np.ndarray]] = {}
    for o in observations:
        if o.camera in cameras:
            by_frame.setdefault(o.frame, []).append(calib.T_ref_cam(o.camera) @ o.T_cam_board)
    placed = {}
    for f, poses in by_frame.items():
        centres = np.array([T[:3, 3] for T in poses])
        cost = np.linalg.norm(centres[:, None] - centres[None], axis=2).sum(axis=1)
        placed[f] = poses[int(np.argmin(cost))]
    return links, {"views": len(observations), "frame_sets": len({k.frame for k in links}),
                   "views_used": per_camera, "model_error_px": MODEL_ERROR_PX,
                   "masked_frames": len(placed),
                   **({"edge_offsets_px": dict(sorted(edge_offsets.items()))}
                      if edge_offsets else {})}, placed


def without_edge_offsets(detections: dict[tuple[str, str], MarkerDetections], board: Board,
                         offsets: dict[str, float]) -> dict[tuple[str, str], MarkerDetections]:
    """``detections`` ((camera, frame) -> markers) with each camera's edge offset taken out of
    its ArUco markers' corners (:func:`~rgbd_calib.solve.edge_offset.without_offset`; a
    ChArUco square's saddle corners keep theirs)."""
    out = {}
    for key, det in detections.items():
        d = offsets.get(key[0], 0.0)
        if d and len(det.ids):
            fitted = ~board.saddle_quads(det.ids)
            corners = np.array(det.corners_px, dtype=float)
            corners[fitted] = without_offset(corners[fitted], d)
            det = replace(det, corners_px=corners)
        out[key] = det
    return out


def check_rig(clouds: dict[str, CameraCloud], calib: Extrinsics,
              overlaps: list[tuple[str, str]], method: RegistrationMethod = "colored-icp",
              config: DepthConfig | None = None, tolerance: Tolerance = Tolerance(),
              unknown_scale: set[str] = frozenset(), workers: int | None = None,
              tick=None, scheduler: str | None = None,
              links: list[BoardLink] | tuple = (),
              board: dict[str, Any] | None = None,
              sensor_poses: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
              ) -> CheckResult:
    """:func:`~rgbd_calib.depth.registration.register_robust` for each overlapping ``(cam_a,
    cam_b)`` from the calibrated extrinsics (in a process pool of ``workers``, or on the Dask
    cluster of ``scheduler``),
    then :func:`locate_moved` on the pairs that fit (``accepted``; the check needs the
    measurements that confirm the calibration too, so ``min_improvement_chi2`` is 0) and the
    board ``links`` (:func:`board_evidence`; ``board`` its summary). Cameras
    in ``unknown_scale`` have no depth-scale factor: their pairs leave out what a scale error
    explains. ``sensor_poses`` (:func:`~rgbd_calib.depth.stage.applied_pose_moments`) widen
    each accepted pair by what its depth sensors' poses may leave on the clouds
    (:func:`~rgbd_calib.depth.stage.with_sensor_poses`; None: the poses taken as exact).
    Cameras of ``calib`` with neither a cloud nor a board view are ``unknown``."""
    config = check_config(config)
    t0 = time.perf_counter()
    T = {c: e.T_ref_cam for c, e in calib.cameras.items()}
    regs = [_widened(r, sensor_poses) for r in register_pairs(
        clouds, _jobs(overlaps, T, set(unknown_scale)), method, config, workers, tick,
        robust=True, scheduler=scheduler)]
    t_reg = time.perf_counter() - t0
    pairs = [RelativePose(r.cam_a, r.cam_b, r.T_b_a, r.information) for r in regs if r.accepted]
    checked = set(clouds) | {k.camera for k in links}
    held = {c: T[c] for c in checked if c in T}
    cov = {c: prior_covariance(calib.cameras[c]) for c in held}
    evidence = Evidence.of(pairs, links, set(held))
    cams = locate_moved(held, cov, evidence, tolerance)
    for c in calib.cameras:
        if c not in cams:
            cams[c] = CameraCheck(c, "unknown", reason="no depth cloud (no depth frames or "
                                  "none usable) and no board seen with another camera")
    factors = _final_factors(held, cov, evidence, cams)
    return CheckResult(cams, [DepthPair(r) for r in regs], tolerance,
                       {"registration": t_reg, "total": time.perf_counter() - t0},
                       board or {}, factors)


def _final_factors(T: dict[str, np.ndarray], cov: dict[str, np.ndarray], evidence: Evidence,
                   cams: dict[str, CameraCheck]) -> dict[str, float]:
    """The variance factors of depth and board evidence with the moved cameras free (for
    check.json: how far each kind's residuals exceed its own sigmas)."""
    free = {c for c, r in cams.items() if r.status == "moved" and c in T}
    weighed = (weighed_solve(T, cov, evidence, free) if evidence.pairs or evidence.links
               else None)
    return weighed[1] if weighed is not None else {}


@dataclass(frozen=True)
class CheckRun:
    """A check with what it was measured from (the clouds and the overlapping pairs), so a
    fix reuses them."""

    result: CheckResult
    clouds: dict[str, CameraCloud]
    overlaps: list[tuple[str, str]]
    scale_source: dict[str, str]  # camera -> "given" (the calibration's factor) / "unknown"
    links: tuple[BoardLink, ...] = ()  # the board's evidence (board_evidence)
    # camera -> what its depth sensor's pose may leave on its cloud (applied_pose_moments)
    sensor_poses: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def moved(self) -> list[str]:
        """The cameras found moved (``rgbd-calib check`` exits 1 when there are any)."""
        return self.result.moved

    @property
    def unknown(self) -> list[str]:
        """The cameras that could not be checked (exit 4 when no camera moved)."""
        return self.result.unknown


def check(dataset: FolderDataset | str | os.PathLike, calib: Extrinsics | str | os.PathLike,
          method: RegistrationMethod = "colored-icp", config: DepthConfig | None = None,
          tolerance: Tolerance = Tolerance(),
          depth_scales: dict[str, float | DepthModel] | None = None,
          workers: int | None = None, progress: Progress | None = None,
          scheduler: str | None = None, board: Board | None = None,
          edge_offsets: dict[str, float] | None = None) -> CheckRun:
    """Has a camera moved since the calibration ``calib``? As ``rgbd-calib check`` decides it.

    ``dataset``: a :class:`FolderDataset` or a dataset folder's path (one or a few frame sets
    of the rig as it is now, with depth; the board in view is evidence too, not needed).
    ``calib``: :class:`Extrinsics`, or a calibrate output folder or its ``extrinsics.yaml``:
    then, as the command does, the dataset is read with the intrinsics of its
    ``rig_refined.yaml``, the depth corrections beside it are used (unless ``depth_scales`` is
    given) and, without ``board``, the board is the calibration's
    (:func:`~rgbd_calib.model.calib_folder.calibration_board`), and its modelled detector edge
    offsets are taken out of the board's corners (unless ``edge_offsets`` is given). Returns the
    :class:`CheckRun`: ``moved``, ``unknown`` and ``result`` (per camera its status, move and
    sigma; ``result.to_dict()`` is check.json's content). See :func:`check_dataset`."""
    dataset = open_dataset(dataset)
    if not isinstance(calib, Extrinsics):
        earlier = load_calibration(calib)
        dataset = dataset.with_rig(with_refined_intrinsics(dataset.rig,
                                                           earlier.path.parent)[0])
        depth_scales = earlier.depth_scales if depth_scales is None else depth_scales
        edge_offsets = earlier.edge_offsets if edge_offsets is None else edge_offsets
        calib = earlier.extrinsics
        if board is None:
            board = calibration_board(earlier.path.parent, dataset.path)[0]
    return check_dataset(dataset, calib, depth_scales, method, config, tolerance, workers,
                         progress, scheduler, board, edge_offsets)


def check_dataset(dataset: FolderDataset, calib: Extrinsics,
                  depth_scales: dict[str, float | DepthModel] | None = None,
                  method: RegistrationMethod = "colored-icp",
                  config: DepthConfig | None = None, tolerance: Tolerance = Tolerance(),
                  workers: int | None = None, progress: Progress | None = None,
                  scheduler: str | None = None, board: Board | None = None,
                  edge_offsets: dict[str, float] | None = None) -> CheckRun:
    """Check ``dataset`` (one or a few frame sets of the rig as it is now; anything in view is
    scene) against ``calib``: a static cloud per calibrated camera with
    depth (its ``depth_scales`` entry: the calibration's depth model or factor), the pairs
    that overlap under the calibration (with a wider overlap search, 0.15 m, than
    calibrate's: a knocked camera's cloud lies centimetres off), with ``board`` the board's
    poses (:func:`board_evidence`, ``edge_offsets`` taken out of its corners), then
    :func:`check_rig`."""
    config = config or DepthConfig()
    scales = depth_scales or {}
    links: list[BoardLink] = []
    summary: dict[str, Any] = {"used": False}
    placed: dict[str, np.ndarray] = {}
    if board is not None:
        t0 = time.perf_counter()
        links, summary, placed = board_evidence(dataset, board, set(calib.cameras) & set(
            dataset.cameras), calib, workers, progress, scheduler, edge_offsets)
        summary = {"used": bool(links), **summary, "time_s": time.perf_counter() - t0}
    cams = [c for c in dataset.cameras if c in calib.cameras and dataset.has_depth(c)]
    clouds, skipped = static_clouds(
        dataset, [(c, calib.T_ref_cam(c), scales.get(c, 1.0)) for c in cams], placed, board,
        config, workers, start(progress, "static clouds", len(cams)), scheduler)
    T = {c: calib.T_ref_cam(c) for c in clouds}
    wide = config.replaced(overlap_distance_m=max(config.registration.overlap_distance_m, 0.15))
    overlaps = [(o.cam_a, o.cam_b) for o in find_overlapping_pairs(
        clouds, T, {c: dataset.rig.cameras[c] for c in clouds}, wide)]
    tick = start(progress, f"registering pairs ({method})", len(overlaps))
    unknown = {c for c in clouds if c not in scales}
    poses = applied_pose_moments(scales, clouds, config)
    result = check_rig(clouds, calib, overlaps, method, config, tolerance, unknown, workers,
                       tick, scheduler, links, summary, poses)
    for c, why in skipped.items():
        if not any(k.camera == c for k in links):
            result.cameras[c] = CameraCheck(c, "unknown", reason=f"no depth cloud: {why}")
    return CheckRun(result, clouds, overlaps,
                    {c: "unknown" if c in unknown else "given" for c in clouds}, tuple(links),
                    poses)


# --------------------------------------------------------------------------- fix
def _sigmas(c: str, T: np.ndarray, C: np.ndarray) -> CameraExtrinsics:
    return CameraExtrinsics(c, T, *covariance_sigmas(C), C)


def reexpress(cams: dict[str, CameraExtrinsics], ref: str,
              covariance: dict[str, np.ndarray]) -> dict[str, CameraExtrinsics]:
    """The rig in the frame of its reference camera as it is now (``cams[ref]`` is where it
    moved to, in the old frame): ``T_new_c = inv(T_ref_now) @ T_c``. Each camera's covariance
    (body frame, [rot, trans]) gains the reference's: a right perturbation ``xi`` of
    ``T_ref_now`` is ``-Ad(inv(T_new_c)) xi`` of ``T_new_c``; ``covariance`` gives the other
    cameras' own (the calibration's for the cameras in place)."""
    T_now = cams[ref].T_ref_cam
    C_ref = cams[ref].covariance
    if C_ref is None or not np.all(np.isfinite(C_ref)):
        C_ref = np.full((6, 6), np.nan)
    T_new_old = invert_transform(T_now)
    out = {}
    for c, e in cams.items():
        if c == ref:
            out[c] = CameraExtrinsics(c, np.eye(4), 0.0, 0.0)  # exact by definition
            continue
        T = T_new_old @ e.T_ref_cam
        Ad = adjoint_map(invert_transform(T))
        own = covariance.get(c, e.covariance)
        own = own if own is not None else np.zeros((6, 6))
        out[c] = _sigmas(c, T, Ad @ C_ref @ Ad.T + own)
    return out


def fix_moved(clouds: dict[str, CameraCloud], calib: Extrinsics, check: CheckResult,
              overlaps: list[tuple[str, str]], method: RegistrationMethod = "colored-icp",
              config: DepthConfig | None = None, max_passes: int = 3,
              unknown_scale: set[str] = frozenset(), workers: int | None = None,
              scheduler: str | None = None, links: list[BoardLink] | tuple = (),
              sensor_poses: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
              ) -> FixResult:
    """Re-register the moved cameras of ``check`` against the others and solve for them with
    the others held at their calibration (priors with its sigmas); only pairs with a moved
    camera count. Each moved camera starts from the check's estimate (its pairs' ICP, after
    the global alignment where needed) and is re-registered from each new estimate, up to
    ``max_passes`` times, until it moves less than 0.1 mm / 0.01 deg: ICP crops each cloud to
    the other camera's view under the start, so a start centimetres off leaves points out.
    The board ``links`` of the check (:func:`board_evidence`) are evidence too, and each pair
    is widened by ``sensor_poses`` as in :func:`check_rig` (``CheckRun.sensor_poses``). Covariances
    are the graph marginals with each kind of evidence scaled by its variance factor
    (:func:`~rgbd_calib.solve.moved.variance_factors`). Returns the extrinsics (the
    cameras in place keep their calibration exactly; if the reference moved, everything is
    re-expressed in its new frame), the last pass's pairs and the fixed cameras the evidence
    does not confirm (:class:`FixResult`)."""
    config = check_config(config)
    moved = set(check.moved)
    if not moved:
        return FixResult(calib, [])
    T_now = {c: e.T_ref_cam for c, e in calib.cameras.items()}
    cov_now: dict[str, np.ndarray | None] = {}
    for c in moved:
        T_now[c] = check.cameras[c].T_ref_cam_now
        cov_now[c] = check.cameras[c].covariance_now
    jobs = [(a, b) for a, b in overlaps
            if (a in moved or b in moved) and a in clouds and b in clouds]
    held = sorted({c for c in clouds if c in T_now}
                  | {k.camera for k in links if k.camera in T_now})
    cov = {c: prior_covariance(calib.cameras[c]) for c in held}
    regs: list[PairRegistration] = []
    solved: set[str] = set()
    for _ in range(max_passes):
        regs = [_within_fix_reach(_widened(r, sensor_poses)) for r in register_pairs(
            clouds, _jobs(jobs, T_now, set(unknown_scale)), method, config, workers,
            robust=True, scheduler=scheduler)]
        pairs = [RelativePose(r.cam_a, r.cam_b, r.T_b_a, r.information)
                 for r in regs if r.accepted]
        evidence = Evidence.of(pairs, links, set(held))
        free = {c for c in moved if sum(evidence.count(c))}
        if not free or not anchored(held, evidence, free):
            break
        weighed = weighed_solve({c: T_now[c] for c in held}, cov, evidence, free)
        if weighed is None:
            break
        sol = weighed[0]
        steps = [transform_error(sol.T[c], T_now[c]) for c in free]  # (deg, mm) each
        for c in free:
            T_now[c], cov_now[c] = sol.T[c], sol.covariance[c]
        solved |= free
        if all(mm < 0.1 and deg < 0.01 for deg, mm in steps):
            break
    cams = dict(calib.cameras)
    for c in moved:
        C = cov_now.get(c)
        cams[c] = _sigmas(c, T_now[c], C if C is not None else np.full((6, 6), np.nan))
    ref = calib.reference
    if ref in moved:
        cams = reexpress(cams, ref, {c: cov[c] for c in cov if c not in moved})
    out = Extrinsics(ref, cams, dict(calib.unconnected))
    evidence = Evidence.of([RelativePose(r.cam_a, r.cam_b, r.T_b_a, r.information)
                            for r in regs if r.accepted], links, set(held))
    return FixResult(out, [DepthPair(r, re_registered_for=tuple(sorted({r.cam_a, r.cam_b}
                                                                       & set(moved))))
                           for r in regs],
                     {**{c: NOTHING_FITS for c in sorted(moved - solved)},
                      **kinds_disagree({c: T_now[c] for c in held}, cov, evidence, moved)})


NOTHING_FITS = ("no pair fits after re-registration and no board view measures it: its pose "
                "is the check's rough estimate")
FIX_REACH = (100.0, 10.0)  # mm, deg: how far a fix's pair may move from the check's estimate


def _widened(r: PairRegistration, sensor_poses: dict[str, tuple[np.ndarray, np.ndarray]] | None,
             ) -> PairRegistration:
    """An accepted pair weighed with what its depth sensors' poses may leave on its clouds."""
    return with_sensor_poses(r, sensor_poses) if r.accepted and sensor_poses else r


def _within_fix_reach(r: PairRegistration) -> PairRegistration:
    """A fix starts from the check's estimate of where the camera is now (millimetres from it,
    the board's and the depth's evidence together): a pair that moves it further than
    :data:`FIX_REACH` found another minimum (a guided global alignment can lock onto a
    repeated structure half a metre away) and is rejected, not weighed."""
    mm, deg = FIX_REACH
    if r.accepted and (r.correction_mm > mm or r.correction_deg > deg):
        return replace(r, accepted=False, rejected_by=("fix_reach",), reason=(
            f"moved {r.correction_mm:.0f} mm / {r.correction_deg:.1f} deg from the check's "
            f"estimate (a fix's limit: {mm:.0f} mm / {deg:.0f} deg): another minimum"))
    return r


@dataclass(frozen=True)
class FixResult:
    """What :func:`fix_moved` made: the ``extrinsics``, the last pass's ``pairs``
    (:class:`~rgbd_calib.depth.registration.DepthPair`) and, per fixed camera the evidence
    does not confirm, why (``unconfirmed``: nothing measured it, or its depth pairs and board
    views disagree, :func:`~rgbd_calib.solve.moved.kinds_disagree`): such a camera's pose is
    CHECK, not GOOD."""

    extrinsics: Extrinsics
    pairs: list[DepthPair]
    unconfirmed: dict[str, str] = field(default_factory=dict)
