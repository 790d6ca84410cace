"""The depth stage over a rig: the RGB-D frames tighten the extrinsics.

Steps (one joint graph with the board):

1. depth-scale bias per camera from the board face, against the calibrated board poses;
2. a static cloud per camera (temporal median, board and moving things masked, scale
   applied);
3. overlapping camera pairs under the current extrinsics;
4. pairwise registration (colored ICP, Park et al. ICCV 2017, or kiss-icp's geometric ICP)
   with an information matrix; weak pairs rejected with a reason;
5. the accepted pairs become relative-pose factors in the bundle adjustment (done by the
   caller, :func:`rgbd_calib.pipelines.calibrate.calibrate`, or
   :func:`rgbd_calib.pipelines.refine.refine_extrinsics` without a board).

:func:`measure_depth` runs steps 1-4; the pairs run in a process pool (:func:`register_pairs`,
its workers :func:`_pool_init` / :func:`_pool_job`), the clouds in threads
(:func:`static_clouds`).
"""

from __future__ import annotations

import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from ..core.config import DepthConfig, RegistrationMethod
from ..core.depth_model import DepthModel
from ..core.errors import CalibrationError, DatasetError
from ..core.geometry import adjoint, invert_transform, transform_error
from ..core.parallel import executor
from ..core.progress import Progress, Tick, start, timed
from ..model.board import Board
from ..model.dataset import FolderDataset
from ..solve.bundle_problem import RelativePose
from .agreement import MIN_POINTS, FusedAgreement, NormalGrid, fused_agreement
from .clouds import (
    CameraCloud,
    DepthScaleEstimate,
    board_faces,
    estimate_depth_scale,
    fuse_clouds,
    in_view,
    static_cloud,
    target_corners,
)
from .depth_model_fit import (
    BeyondBoard,
    DepthModelFit,
    applied_pose_moment,
    beyond_board,
    board_samples,
    fit_depth_model,
)
from .information import tangent_error, with_covariance
from .overlap_models import OverlapUpdate, overlap_samples, recorrected, update_models
from .registration import (
    DepthPair,
    PairRegistration,
    failed_registration,
    find_overlapping_pairs,
    limit_registration_threads,
    one_line_error,
    pair_rmse_mm,
    register_pair,
    register_robust,
)

# why a camera with depth has no depth model (report.json depth.unmodelled)
NO_BOARD_DEPTH = ("no view of the board usable for depth (none detected by it, or the board's "
                  "pose at its capture uncertain by more than the gate)")
FEW_BOARD_PIXELS = "too few board pixels with depth in its views"


@dataclass(frozen=True)
class DepthRefinement:
    """What the depth stage measured; ``pairs`` its camera pairs (:class:`DepthPair`;
    ``DepthPair.to_dict`` is their report entry)."""

    method: str
    depth_scales: dict[str, DepthScaleEstimate]
    clouds: dict[str, CameraCloud]
    pairs: list[DepthPair]
    relative_poses: list[RelativePose]
    T_ref_cam_initial: dict[str, np.ndarray]  # extrinsics the pairs were registered from
    timings_s: dict[str, float] = field(default_factory=dict)
    skipped_cameras: dict[str, str] = field(default_factory=dict)  # camera -> why no cloud
    fallback: str | None = None  # why the result is the board's alone (no usable pair), if so
    note: str | None = None  # why registration was not needed (strong board data), if so
    weak_cameras: dict[str, str] | None = None  # cameras depth was run for (None: all)
    scale_source: dict[str, str] = field(default_factory=dict)  # board / given / unknown
    # refine: the pairs' variance factor of the joint solve (solve_variance_components)
    pair_variance_factor: float | None = None
    # calibrate: the bias (mm, deg per axis) added to each pair's covariance in that solve
    pair_bias_sigma: tuple[float, float] | None = None
    # calibrate: the prior (deg, mm per axis) of the depth sensors' poses the pairs carry
    # (with_sensor_poses); None: taken as exact, or no pair registered
    sensor_pose_sigma: tuple[float, float] | None = None
    # camera -> its depth model chosen by evidence from the board (the clouds are corrected)
    depth_models: dict[str, DepthModelFit] = field(default_factory=dict)
    # the overlapping pairs' surface distances at the final extrinsics (measure_agreement)
    agreement: FusedAgreement | None = None
    # camera -> how much of its cloud lies beyond the board's depths, known how well there
    beyond_board: dict[str, BeyondBoard] = field(default_factory=dict)
    # camera with depth -> why it has no depth model (its cloud is uncorrected)
    unmodelled: dict[str, str] = field(default_factory=dict)
    # the depth models updated by the overlaps' medians (with_overlaps); None: not run
    overlaps: OverlapUpdate | None = None
    # camera -> its cloud's normals as ``clouds`` holds it (estimated once by with_overlaps,
    # moved with each correction; measure_agreement reuses them); cameras absent: none yet
    normal_grids: dict[str, NormalGrid] = field(default_factory=dict)

    def status_dict(self) -> dict[str, Any]:
        """report.json ``depth``: ``status`` used / skipped / fallback, its ``reason``, the
        cameras the board constrained weakly (those depth was registered for) and, when some
        camera with depth got no depth model, ``unmodelled`` (camera -> why), and when the
        pairs were weighed in a solve, their ``pair_variance_factor`` (and in calibrate the
        bias added to their covariance, ``pair_bias_sigma_mm`` / ``_deg``), and when the
        pairs carry their depth sensors' poses, that pose's prior
        (``sensor_pose_sigma_deg`` / ``_mm``), and when the overlaps updated the depth
        models, ``overlap_models`` (:meth:`OverlapUpdate.to_dict`)."""
        status = ("fallback" if self.fallback else "skipped" if self.note
                  else "used" if self.relative_poses else "none")
        return {"status": status, "reason": self.fallback or self.note,
                "weak_cameras": dict(self.weak_cameras or {})} | (
                    {"unmodelled": dict(self.unmodelled)} if self.unmodelled else {}) | (
                    {"pair_variance_factor": self.pair_variance_factor}
                    if self.pair_variance_factor is not None else {}) | (
                    {"pair_bias_sigma_mm": self.pair_bias_sigma[0],
                     "pair_bias_sigma_deg": self.pair_bias_sigma[1]}
                    if self.pair_bias_sigma is not None else {}) | (
                    {"sensor_pose_sigma_deg": self.sensor_pose_sigma[0],
                     "sensor_pose_sigma_mm": self.sensor_pose_sigma[1]}
                    if self.sensor_pose_sigma is not None else {}) | (
                    {"overlap_models": self.overlaps.to_dict()}
                    if self.overlaps is not None else {})

    @property
    def used(self) -> bool:
        """Whether any pair went into the solve."""
        return bool(self.relative_poses) and self.fallback is None

    def with_fallback(self, reason: str) -> DepthRefinement:
        """This measurement with every pair unused: the solve keeps the board result."""
        pairs = [p.unused(reason) for p in self.pairs]
        return replace(self, pairs=pairs, relative_poses=[], fallback=reason)

    def depth_scale_dict(self) -> dict[str, dict[str, float]]:
        return {c: {"factor": e.factor, "sigma": e.sigma} for c, e in self.depth_scales.items()}

    def fused(self, T_ref_cam: dict[str, np.ndarray], voxel_m: float):
        """``(points_ref, colors, camera_index, camera_names)`` at the given extrinsics."""
        names = [c for c in self.clouds if c in T_ref_cam]
        pts, cols, idx = fuse_clouds({c: self.clouds[c] for c in names},
                                     {c: T_ref_cam[c] for c in names}, voxel_m)
        return pts, cols, idx, names


def weak_cameras(covariance: dict[str, np.ndarray | None], config: DepthConfig,
                 ) -> dict[str, str]:
    """Cameras the board constrains weakly, with why: the worst direction of the marginal
    covariance (6x6, [rot rad, trans m]) above ``board_weak_sigma_deg`` in rotation or
    ``board_weak_sigma_mm`` in translation. A camera without a covariance counts as weak."""
    out: dict[str, str] = {}
    for cam, cov in covariance.items():
        if cov is None or not np.all(np.isfinite(cov)):
            out[cam] = "no board covariance"
            continue
        worst_deg = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3])[-1], 0.0))))
        worst_mm = float(1000.0 * np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], 0.0)))
        weak = config.uncertainty
        if worst_mm > weak.board_weak_sigma_mm or worst_deg > weak.board_weak_sigma_deg:
            out[cam] = f"board sigma {worst_mm:.3f} mm / {worst_deg:.4f} deg in its worst direction"
    return out


def measure_depth(dataset: FolderDataset, board: Board | None, T_ref_cam: dict[str, np.ndarray],
                  board_views: dict[str, dict[str, np.ndarray]] | None, T_ref_board:
                  dict[str, np.ndarray] | None,
                  method: RegistrationMethod | Literal["none"],
                  config: DepthConfig | None = None,
                  progress: Progress | None = None,
                  board_covariance: dict[str, np.ndarray | None] | None = None,
                  workers: int | None = None,
                  depth_scales: dict[str, float | DepthModel] | None = None,
                  scheduler: str | None = None,
                  unseen_views: dict[str, dict[str, np.ndarray]] | None = None,
                  pose_covariance: dict[str, dict[str, np.ndarray]] | None = None,
                  ) -> DepthRefinement:
    """Run steps 1-4 for every calibrated camera that has depth.

    ``board_views`` maps camera -> {frame: T_cam_board} of the views it saw (for the depth
    scale); ``T_ref_board`` maps frame -> board pose (for masking the board). Both may be
    None (refinement of an existing calibration without a board in view). ``unseen_views``
    (:func:`unseen_board_views`, same form) are the board where the camera did not detect it,
    for its depth model only; ``pose_covariance`` (camera -> frame -> 6x6:
    :func:`view_pose_covariances`) the uncertainty of each of those board poses, which the
    depth model takes into account (``depth.model_fit.model_plane_uncertainty``).

    With ``board_covariance`` (camera -> 6x6 marginal of the board solve) only pairs with a
    camera the board constrains weakly (:func:`weak_cameras`) are registered, and nothing but
    the depth scale is measured when the board constrains every camera well: depth adds no
    information there. The cameras' depth models and the pairs run in ``workers`` processes
    (default: all cores) or on the Dask cluster of ``scheduler``.

    ``depth_scales`` (camera -> depth model or factor of the calibration being refined:
    :func:`rgbd_calib.model.calib_folder.load_depth_corrections`) are used for cameras the
    board gives none for. A camera with neither has an unknown depth scale: its pairs'
    information leaves out what a depth-scale error would explain (``free_scale``).
    Intrinsics the rig marks as estimated (``dataset.rig.sigmas``) carry their uncertainty into
    each pair (:func:`rgbd_calib.depth.clouds.static_cloud`)."""
    config = config or DepthConfig()
    cams = [c for c in dataset.cameras if c in T_ref_cam and dataset.has_depth(c)]
    weak: dict[str, str] | None = None
    if board_covariance is not None:
        weak = weak_cameras({c: board_covariance.get(c) for c in cams
                             if c != dataset.rig.reference}, config)
    timings: dict[str, float] = {}
    with timed(timings, "depth_scale"):
        scales, models, unmodelled = _board_depth(dataset, cams, board, board_views, config,
                                                  progress, unseen_views, pose_covariance,
                                                  workers, scheduler)
        unmodelled = {c: why for c, why in unmodelled.items() if c not in (depth_scales or {})}

    no_pair = method != "none" and weak is not None and not weak
    with timed(timings, "clouds"):
        corrections = {c: models[c].model if c in models else scales[c].factor
                       if c in scales else (depth_scales or {}).get(c, 1.0) for c in cams}
        jobs = [(c, T_ref_cam[c], corrections[c]) for c in cams]
        # no registration: the clouds are for fused.ply and the cloud checks only
        cloud_config = (config.replaced(max_frames=min(
            config.clouds.max_frames, config.clouds.skipped_max_frames)) if no_pair else config)
        clouds, skipped = static_clouds(dataset, jobs, T_ref_board or {}, board, cloud_config,
                                        workers, start(progress, "static clouds", len(cams)),
                                        scheduler)
    far = {c: b for c in models if c in clouds
           if (b := beyond_board(models[c], clouds[c].points[:, 2],
                                 _rays(clouds[c].points))) is not None}

    if no_pair:
        # the clouds are still built: fused.ply and the report's cloud checks use them
        return DepthRefinement(
            method, scales, clouds, [], [], dict(T_ref_cam), timings, skipped,
            note=(f"not needed: the board alone holds every camera within "
                  f"{config.uncertainty.board_weak_sigma_mm} mm / "
                  f"{config.uncertainty.board_weak_sigma_deg} deg"),
            weak_cameras={}, depth_models=models, beyond_board=far, unmodelled=unmodelled)

    pairs: list[DepthPair] = []
    relative: list[RelativePose] = []
    sensor_pose: tuple[float, float] | None = None
    if method != "none" and len(clouds) >= 2:
        registering, moments = _registration_clouds(
            dataset, clouds, models, scales, T_ref_cam, T_ref_board, board,
            board_covariance is not None, config, workers, scheduler, timings, corrections)
        if moments:
            sensor_pose = (config.uncertainty.sensor_pose_sigma_deg,
                           config.uncertainty.sensor_pose_sigma_mm)
        with timed(timings, "registration"):
            intrinsics = {c: dataset.rig.cameras[c] for c in registering}
            overlaps = find_overlapping_pairs(registering, T_ref_cam, intrinsics, config)
            if weak is not None:
                overlaps = [ov for ov in overlaps if ov.cam_a in weak or ov.cam_b in weak]
            tick = start(progress, f"registering pairs ({method})", len(overlaps))
            # In calibrate (``board_covariance`` given) the factors were measured against the
            # board poses of this same, weak, board solve: their error is its board-pose error
            # over the board distance, as large as the board error the pairs are to correct
            # (measured: docs/depth.md). So there every pair leaves the directions a scale
            # error explains to the board; refine keeps given factors as known.
            known = (set() if board_covariance is not None
                     else set(scales) | set(depth_scales or {}))
            jobs = [(ov.cam_a, ov.cam_b, T_ref_cam[ov.cam_a], T_ref_cam[ov.cam_b],
                     (ov.cam_a not in known, ov.cam_b not in known)) for ov in overlaps]
            for ov, reg in zip(overlaps, register_pairs(registering, jobs, method, config,
                                                         workers, tick, scheduler=scheduler)):
                if reg.accepted and board_covariance is not None:
                    # the gate at the pair's own covariance: a move a depth sensor's pose
                    # explains is a depth error, and rejected
                    reg = consistent_with_board(reg, board_covariance, T_ref_cam, config)
                if reg.accepted:
                    # an accepted pair is weighed with what its sensors' poses may still hide
                    reg = with_sensor_poses(reg, moments)
                pairs.append(DepthPair(reg, ov))
                if reg.accepted:
                    relative.append(RelativePose(reg.cam_a, reg.cam_b, reg.T_b_a,
                                                 reg.solve_information()))
    depth = DepthRefinement(method, scales, clouds, pairs, relative, dict(T_ref_cam), timings,
                            skipped, weak_cameras=weak,
                            scale_source={c: "board" if c in scales else "given"
                                          if c in (depth_scales or {}) else "unknown"
                                          for c in clouds}, depth_models=models,
                            beyond_board=far, unmodelled=unmodelled,
                            sensor_pose_sigma=sensor_pose)
    if method != "none" and not relative:
        depth = depth.with_fallback(no_pair_reason(depth))
    return depth


def _registration_clouds(dataset: FolderDataset, clouds: dict[str, CameraCloud],
                         models: dict[str, DepthModelFit], scales: dict[str, DepthScaleEstimate],
                         T_ref_cam: dict[str, np.ndarray],
                         T_ref_board: dict[str, np.ndarray] | None, board: Board | None,
                         calibrating: bool, config: DepthConfig, workers: int | None,
                         scheduler: str | None, timings: dict[str, float],
                         corrections: dict[str, float | DepthModel],
                         ) -> tuple[dict[str, CameraCloud], dict[str, tuple[np.ndarray,
                                                                           np.ndarray]]]:
    """The clouds the pairs register, and per camera what its depth sensor's pose may leave
    on its cloud (:func:`with_sensor_poses` widens the pairs by it; empty with
    ``depth.uncertainty.sensor_pose_sigma_deg`` and ``_mm`` 0, the poses taken as exact).

    calibrate (``calibrating``) registers only where the board is weak, which is where the
    depth models are fitted on few views: their extrapolation to the scene's depths has a
    variance the pairs' information leaves out (it frees only what a depth-scale error
    explains), and the pairs pulled the cameras by millimetres (weak race, 6 sets: 2.17 mm
    against 0.34 with the scale alone; docs/depth.md, 'Weak board data'). So its pairs
    register the clouds divided by the depth-scale factor, as before the models (fused.ply
    and the checks keep the models), and none of them is corrected for its sensor's pose
    (:func:`fit_pose_moments`) or its disparity offset: each pair carries both as an
    uncertainty (the offset through :class:`~rgbd_calib.depth.clouds.DisparityMoment`). refine
    registers the clouds as built, with their
    ``corrections`` (the models fitted here, else the scale factors, else the calibration's):
    :func:`applied_pose_moments`."""
    if not calibrating:
        return clouds, applied_pose_moments(corrections, clouds, config)
    registering = clouds
    if any(c in clouds for c in models):
        with timed(timings, "clouds"):  # a camera with a model has its scale estimate
            rebuilt, _ = static_clouds(dataset, [(c, T_ref_cam[c], scales[c].factor)
                                                 for c in models if c in clouds],
                                       T_ref_board or {}, board, config, workers, None,
                                       scheduler)
        # their disparity offsets are not taken out: each pair carries them
        registering = {**clouds, **{c: replace(cloud, disparity=models[c].disparity_moment())
                                    for c, cloud in rebuilt.items()}}
    prior = _pose_prior(config)
    return registering, ({} if prior is None else
                         fit_pose_moments({c: models.get(c) for c in registering}, prior))


def _pose_prior(config: DepthConfig) -> tuple[float, float] | None:
    """The depth sensors' pose prior (deg, mm per axis), None when both are 0: the poses
    taken as exact."""
    prior = (config.uncertainty.sensor_pose_sigma_deg, config.uncertainty.sensor_pose_sigma_mm)
    return None if prior == (0.0, 0.0) else prior


def _board_depth(dataset: FolderDataset, cams: list[str], board: Board | None,
                 board_views: dict[str, dict[str, np.ndarray]] | None, config: DepthConfig,
                 progress: Progress | None,
                 unseen_views: dict[str, dict[str, np.ndarray]] | None = None,
                 pose_covariance: dict[str, dict[str, np.ndarray]] | None = None,
                 workers: int | None = 1, scheduler: str | None = None,
                 ) -> tuple[dict[str, DepthScaleEstimate], dict[str, DepthModelFit],
                            dict[str, str]]:
    """Per camera with board views: its depth scale (:func:`estimate_depth_scale`) and its
    depth model chosen by evidence (:func:`fit_depth_model`) from those views and its
    ``unseen_views`` (:func:`unseen_board_views`). The clouds are corrected by the model; the
    reported factor (and refine's) is still the scale estimate's, of the views it detected (not
    yet the model's scale: with a second term chosen its sigma grows beyond what refine
    needs). Third: with ``config.model`` auto, each camera that got no model and why.

    One camera per task (:func:`_camera_board_depth`, each reads its own images), in
    ``workers`` processes (1: here; None: all cores) or on the Dask cluster of ``scheduler``
    (:func:`rgbd_calib.core.parallel.executor`): the same result in any of them."""
    scales: dict[str, DepthScaleEstimate] = {}
    models: dict[str, DepthModelFit] = {}
    if board is None or board_views is None:
        return scales, models, {}
    unmodelled = {c: NO_BOARD_DEPTH for c in cams} if config.model == "auto" else {}
    tick = start(progress, "depth model per camera", len(cams))
    jobs = [(dataset, c, board_views.get(c, {}), (unseen_views or {}).get(c, {}), board, config,
             (pose_covariance or {}).get(c)) for c in cams]
    with_views = sum(1 for job in jobs if job[2])
    n = min(workers or os.cpu_count() or 1, with_views)
    # as the pairs and the static clouds: a pool (or the cluster) only for two tasks or more
    pool = executor(n, scheduler) if with_views > 1 and (scheduler or n > 1) else None
    with pool or nullcontext():
        # map: in order, so the result is the serial one
        done = (pool.map(_camera_board_depth, *zip(*jobs)) if pool is not None
                else (_camera_board_depth(*job) for job in jobs))
        for c, (scale, model, why) in zip(cams, done):
            if scale is not None:
                scales[c] = scale
            if model is not None:
                models[c] = model
                unmodelled.pop(c, None)
            elif why is not None and c in unmodelled:
                unmodelled[c] = why
            tick(1)
    return scales, models, unmodelled


def _camera_board_depth(dataset: FolderDataset, c: str, views: dict[str, np.ndarray],
                        unseen: dict[str, np.ndarray], board: Board, config: DepthConfig,
                        pose_covariance: dict[str, np.ndarray] | None,
                        ) -> tuple[DepthScaleEstimate | None, DepthModelFit | None, str | None]:
    """One camera's part of :func:`_board_depth`: ``(scale, model, why no model)`` from its
    board ``views`` (frame -> ``T_cam_board``) and the views it did not detect (``unseen``);
    ``(None, None, FEW_BOARD_PIXELS)`` when its board pixels with depth are too few for a
    scale, ``(None, None, None)`` without views."""
    if not views:
        return None, None, None
    faces = board_faces(dataset, c, views, board, config)  # each image read once
    try:
        scale = estimate_depth_scale(dataset, c, views, board, config, faces)
    except (CalibrationError, DatasetError):
        return None, None, FEW_BOARD_PIXELS  # the factor stays 1 (reported)
    if config.model != "auto":
        return scale, None, None
    unseen_config = config.replaced(scale_max_frames=max(
        config.model_fit.model_unseen_max_frames, 1))
    far = (board_faces(dataset, c, unseen, board, unseen_config, detected=False)
           if config.model_fit.model_unseen_max_frames else [])
    samples = board_samples(dataset.rig.cameras[c], faces + far, config,
                            pose_covariance if config.model_fit.model_plane_uncertainty
                            else None)
    model = replace(fit_depth_model(c, samples, dataset.rig.cameras[c], config),
                    n_unseen_views=len(far))
    return scale, model, None


def unseen_board_views(T_ref_cam: dict[str, np.ndarray], T_ref_board: dict[str, np.ndarray],
                       seen: dict[str, dict[str, np.ndarray]], board: Board | None,
                       dataset: FolderDataset, config: DepthConfig,
                       at_capture: dict[str, dict[str, np.ndarray]] | None = None,
                       ) -> dict[str, dict[str, np.ndarray]]:
    """camera -> {frame: T_cam_board} of the frame sets whose board the camera did not
    detect (or did not use) but whose board, placed by the cameras that did, has a corner of its
    box in the camera's image within its depth range: the board seen in depth only, often far
    beyond the range the camera detects it in. :func:`rgbd_calib.depth.clouds.board_face_pixels`
    then keeps the face pixels whose depth agrees with the face (``board_depth_gate``), so an
    occluded board gives none. ``at_capture`` (camera -> frame -> the board pose at that
    camera's capture, by the time model; :func:`board_views_per_camera`) replaces
    ``T_ref_board`` and leaves out the sets it lacks."""
    out: dict[str, dict[str, np.ndarray]] = {}
    if board is None or not config.model_fit.model_unseen_views:
        return out
    corners = target_corners(board)
    for c, T_rc in T_ref_cam.items():
        if c not in dataset.rig.cameras or not dataset.has_depth(c):
            continue
        intr = dataset.rig.cameras[c]
        T_cr = invert_transform(T_rc)
        boards = T_ref_board if at_capture is None else at_capture.get(c, {})
        for frame, T_rb in boards.items():
            if frame in seen.get(c, {}):
                continue
            T_cb = T_cr @ T_rb
            pts = corners @ T_cb[:3, :3].T + T_cb[:3, 3]
            if np.any(in_view(intr, pts, 0.0, config.clouds.min_range_m,
                              config.clouds.max_range_m)):
                out.setdefault(c, {})[frame] = T_cb
    return out


def view_pose_covariances(observations, seen: dict[str, dict[str, np.ndarray]],
                          unseen: dict[str, dict[str, np.ndarray]],
                          camera_covariance: dict[str, np.ndarray | None],
                          capture_sigma_m: dict[str, dict[str, float]] | None = None,
                          ) -> dict[str, dict[str, np.ndarray]]:
    """camera -> frame -> the covariance (6x6 ``[rot rad, trans m]``, a left perturbation in
    the camera frame) of the board pose each depth view of the camera uses (``seen``:
    :func:`board_views_per_camera`; ``unseen``: :func:`unseen_board_views`). A view the camera
    detected: its own PnP covariance (``observations``), since its corners fix the board in
    the camera whatever the extrinsics. The board it did not detect comes through its
    extrinsics: their covariance (``camera_covariance``, body frame of ``T_ref_cam``, which is
    the camera frame of ``T_cam_board``), plus, with a time model, the board's uncertainty at
    the camera's capture (``capture_sigma_m``: camera -> frame -> m, on each axis)."""
    own = {(o.camera, o.frame): o for o in observations}
    out: dict[str, dict[str, np.ndarray]] = {}
    for c, views in seen.items():
        for frame in views:
            o = own.get((c, frame))
            if o is not None and o.covariance is not None:
                A = adjoint(o.T_cam_board)
                out.setdefault(c, {})[frame] = A @ np.asarray(o.covariance, dtype=float) @ A.T
    for c, views in unseen.items():
        C = camera_covariance.get(c)
        for frame in views:
            cov = np.zeros((6, 6)) if C is None else np.array(C, dtype=float)
            s = (capture_sigma_m or {}).get(c, {}).get(frame, 0.0)
            cov[3:, 3:] += s**2 * np.eye(3)
            if np.trace(cov) > 0:
                out.setdefault(c, {})[frame] = cov
    return out


# --------------------------------------------------------------------------- pairs
_POOL_CLOUDS: dict[str, CameraCloud] = {}


_POOL_ARGS: tuple[str, DepthConfig, bool] | None = None


def _pool_init(clouds: dict[str, CameraCloud], method: str, config: DepthConfig,
               robust: bool = False) -> None:
    """Worker initializer (local pool or Dask worker): the clouds and settings of this run
    (replacing an earlier run's on a long-lived Dask worker), one thread per registration."""
    global _POOL_ARGS
    limit_registration_threads(1)
    _POOL_CLOUDS.clear()
    _POOL_CLOUDS.update(clouds)
    _POOL_ARGS = (method, config, robust)


Job = tuple[str, str, np.ndarray, np.ndarray, tuple[bool, bool]]


def _pool_job(job: Job) -> PairRegistration:
    assert _POOL_ARGS is not None
    a, b, T_ref_a, T_ref_b, free_scale = job
    method, config, robust = _POOL_ARGS
    return _register_safely(_POOL_CLOUDS[a], _POOL_CLOUDS[b], T_ref_a, T_ref_b, method,
                            config, free_scale, robust)


def register_pairs(clouds: dict[str, CameraCloud],
                   jobs: list[Job], method: RegistrationMethod,
                   config: DepthConfig, workers: int | None = None, tick=None,
                   robust: bool = False, scheduler: str | None = None,
                   ) -> list[PairRegistration]:
    """Register every ``(cam_a, cam_b, T_ref_a, T_ref_b, free_scale)`` of ``jobs`` (in order), in a
    process pool of ``workers`` (default: all cores; 1 or a single job runs here), or on the
    Dask cluster of ``scheduler`` (:func:`rgbd_calib.core.parallel.executor`). Each worker receives
    the clouds once; a failing pair is rejected, never raised. ``robust``:
    :func:`register_robust` (a global alignment when ICP from the given extrinsics does not
    fit: a knocked camera)."""
    n = min(workers or os.cpu_count() or 1, len(jobs))
    if n <= 1 and not (scheduler and len(jobs) > 1):
        out = []
        for a, b, T_ref_a, T_ref_b, free_scale in jobs:
            out.append(_register_safely(clouds[a], clouds[b], T_ref_a, T_ref_b, method, config,
                                        free_scale, robust))
            if tick:
                tick(1)
        return out
    used = {c for a, b, *_ in jobs for c in (a, b)}
    init_args = ({c: clouds[c] for c in used}, method, config, robust)
    with executor(n, scheduler, initializer=_pool_init, initargs=init_args) as pool:
        futures = [pool.submit(_pool_job, job) for job in jobs]
        out = []
        for (a, b, T_ref_a, T_ref_b, _), future in zip(jobs, futures):
            try:
                out.append(future.result())
            except Exception as exc:  # noqa: BLE001 - a worker that died takes one pair
                T_b_a0 = invert_transform(T_ref_b) @ np.asarray(T_ref_a, dtype=float)
                out.append(failed_registration(a, b, method, T_b_a0, "registration process "
                                               f"failed: {type(exc).__name__}: {exc}"))
            if tick:
                tick(1)
        return out


def _register_safely(cloud_a: CameraCloud, cloud_b: CameraCloud, T_ref_a: np.ndarray,
                     T_ref_b: np.ndarray, method: RegistrationMethod, config: DepthConfig,
                     free_scale: tuple[bool, bool] = (False, False), robust: bool = False,
                     ) -> PairRegistration:
    """:func:`register_pair` (or with ``robust`` :func:`register_robust`), with any failure of
    this one pair turned into its rejection (both already catch the ICP libraries' own errors;
    this is the last net, so that one pair never ends a run)."""
    try:
        if robust:
            return register_robust(cloud_a, cloud_b, T_ref_a, T_ref_b, method, config,
                                   free_scale)
        return register_pair(cloud_a, cloud_b, T_ref_a, T_ref_b, method, config, free_scale)
    except Exception as exc:  # noqa: BLE001 - deliberately any error of this pair
        T_b_a0 = invert_transform(T_ref_b) @ np.asarray(T_ref_a, dtype=float)
        return failed_registration(cloud_a.camera, cloud_b.camera, method, T_b_a0,
                                   f"registration failed: {type(exc).__name__}: "
                                   f"{one_line_error(exc)}")


# --------------------------------------------------------------------------- clouds
def _cloud_job(dataset: FolderDataset, camera: str, T_ref_board: dict[str, np.ndarray],
               T_ref_cam: np.ndarray, board: Board | None, config: DepthConfig,
               factor: float | DepthModel) -> tuple[CameraCloud | None, str | None]:
    """One camera's :func:`static_cloud` with its depth-scale factor or depth model, or why it
    has none (a failure here costs this camera only)."""
    try:
        if isinstance(factor, DepthModel):
            return static_cloud(dataset, camera, T_ref_board, T_ref_cam, board, config,
                                depth_model=factor), None
        return static_cloud(dataset, camera, T_ref_board, T_ref_cam, board, config,
                            depth_scale_factor=factor), None
    except (DatasetError, ValueError, MemoryError) as exc:
        return None, one_line_error(exc)


def static_clouds(dataset: FolderDataset,
                  jobs: list[tuple[str, np.ndarray, float | DepthModel]],
                  T_ref_board: dict[str, np.ndarray], board: Board | None,
                  config: DepthConfig, workers: int | None = None, tick: Tick | None = None,
                  scheduler: str | None = None,
                  ) -> tuple[dict[str, CameraCloud], dict[str, str]]:
    """The static cloud of every ``(camera, T_ref_cam, depth-scale factor or model)`` of
    ``jobs``, one camera per task: in ``workers`` threads of this process (default: all
    cores) or on the Dask cluster of ``scheduler``
    (:func:`rgbd_calib.core.parallel.executor`; a Dask worker reads
    the depth frames itself and must see the dataset at the same path): ``(clouds,
    skipped)``, skipped = camera -> why it has no cloud.

    Threads, not the process pool: a cloud is numpy and OpenCV work on whole frames (they
    release the GIL), its arrays stay where they are made instead of being pickled back, and
    threads start at once (measured: docs/depth.md)."""
    n = min(workers or os.cpu_count() or 1, len(jobs))
    args = [(dataset, c, T_ref_board, T, board, config, f) for c, T, f in jobs]
    if scheduler and len(jobs) > 1:
        pool = executor(n, scheduler)
    elif n > 1:
        pool = ThreadPoolExecutor(n, thread_name_prefix="static-cloud")
    else:
        pool = None
    results = []
    with pool or nullcontext():
        try:
            # map: in order, and a dead Dask worker explained
            mapped = (pool.map(_cloud_job, *zip(*args)) if pool is not None
                      else (_cloud_job(*a) for a in args))
            for result in mapped:
                results.append(result)
                if tick:
                    tick(1)
        except BaseException:  # Ctrl-C: the cameras not started are dropped, not waited for
            if isinstance(pool, ThreadPoolExecutor):  # (a Dask executor's exit cancels them)
                pool.shutdown(wait=False, cancel_futures=True)
            raise
    clouds = {c: cloud for (c, _, _), (cloud, _) in zip(jobs, results) if cloud is not None}
    skipped = {c: why for (c, _, _), (_, why) in zip(jobs, results) if why is not None}
    return clouds, skipped


# --------------------------------------------------------------------------- against the board
def consistent_with_board(reg: PairRegistration, board_covariance: dict[str, np.ndarray | None],
                          T_ref_cam: dict[str, np.ndarray], config: DepthConfig,
                          ) -> PairRegistration:
    """``reg``, rejected when ICP's move from the board's ``T_b_a`` is beyond what the board
    and the pair allow together: ``xi^T (C_rel + C_pair)^-1 xi > acceptance.max_board_chi2`` with
    ``C_rel = C_a + Ad(T_a_b) C_b Ad(T_a_b)^T`` the board marginals of the two cameras
    carried to the right perturbation of ``T_b_a`` (``T_b_a Exp(xi_a - Ad(T_a_b) xi_b)``;
    their correlation is left out, which widens the gate) and ``C_pair`` the pair's own
    covariance. Such a move is a wrong local minimum or a depth error, not a correction."""
    a, b = reg.cam_a, reg.cam_b
    covs = [board_covariance.get(c) for c in (a, b)]
    if any(c is None or not np.all(np.isfinite(c)) for c in covs):
        return reg
    Ad = adjoint(invert_transform(T_ref_cam[a]) @ T_ref_cam[b])
    total = covs[0] + Ad @ covs[1] @ Ad.T + reg.covariance
    xi = tangent_error(reg.T_b_a_initial, reg.T_b_a)
    try:
        chi2 = float(xi @ np.linalg.solve(total, xi))
    except np.linalg.LinAlgError:
        return reg
    if chi2 <= config.acceptance.max_board_chi2:
        return reg
    return replace(reg, accepted=False, rejected_by=("beyond_extrinsics",), reason=(
        f"ICP moved {reg.correction_mm:.2f} mm / {reg.correction_deg:.3f} deg from the board's "
        f"extrinsics, beyond their uncertainty and the pair's (chi2 {chi2:.0f} > "
        f"{config.acceptance.max_board_chi2}, 6 dof): a wrong local minimum or a depth error"))


def fit_pose_moments(models: dict[str, DepthModelFit | None], prior: tuple[float, float],
                     ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """camera -> what its depth sensor's pose leaves on a cloud NOT corrected for it (the
    clouds calibrate registers: :func:`_registration_clouds`), as :func:`with_sensor_poses`
    takes it: the every-term fit's estimate and covariance with the zero-mean ``prior`` (deg,
    mm per axis; config ``depth.uncertainty.sensor_pose_sigma_deg`` / ``_mm``:
    :meth:`~rgbd_calib.depth.depth_model_fit.DepthModelFit.sensor_pose_moment`), the prior
    alone for a camera without a fit (None)."""
    return {c: DepthModelFit.prior_moment(*prior) if m is None else m.sensor_pose_moment(*prior)
            for c, m in models.items()}


def applied_pose_moments(corrections: dict[str, float | DepthModel], cameras,
                         config: DepthConfig) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """camera -> what its depth sensor's pose may still leave on a cloud corrected by
    ``corrections`` (the models or factors ``check`` and ``refine`` build their clouds with;
    a camera of ``cameras`` without one has none): :func:`applied_pose_moment`. Empty with
    ``depth.uncertainty.sensor_pose_sigma_deg`` and ``_mm`` 0 (the poses taken as exact)."""
    prior = _pose_prior(config)
    return {} if prior is None else {c: applied_pose_moment(corrections.get(c), *prior)
                                     for c in cameras}


def with_sensor_poses(reg: PairRegistration,
                      moments: dict[str, tuple[np.ndarray, np.ndarray]]) -> PairRegistration:
    """``reg`` with its covariance widened by what its cameras' depth sensors' poses
    (relative to their colour cameras) may leave on the clouds it registered: ``moments``
    maps camera -> ``(eps, C)``, the rigid error ``measured = Exp(eps) true`` of its cloud and
    that error's covariance (:func:`fit_pose_moments` for clouds not corrected for the pose,
    as calibrate registers them; :func:`applied_pose_moments` for clouds corrected by a
    depth model, as check and refine do); a camera not in it is exact. A cloud turned by
    ``eps`` moves the registered ``T_b_a`` by ``Ad(T_a_b) eps_b - eps_a`` (right
    perturbation), and the pair's covariance gains that move's second moment about zero: the
    estimates are a bias the pair carries (taking them out of ``T_b_a`` instead measured no
    better in calibrate: they trade with the disparity gradients), the covariances what they
    may still be off. Without it a 0.13 deg depth-to-colour rotation passed into a 2-view
    camera's extrinsics at 4 of its sigmas (docs/depth.md, 'The depth sensor's pose in the
    pairs')."""
    if reg.cam_a not in moments and reg.cam_b not in moments:
        return reg
    exact = (np.zeros(6), np.zeros((6, 6)))
    (eps_a, C_a), (eps_b, C_b) = (moments.get(c, exact) for c in (reg.cam_a, reg.cam_b))
    Ad = adjoint(invert_transform(reg.T_b_a))
    beta = Ad @ eps_b - eps_a  # the move the estimated sensor poses predict
    B = np.outer(beta, beta) + C_a + Ad @ C_b @ Ad.T
    return replace(reg, information=with_covariance(reg.information, B))


BEYOND_BOARD_CHI2 = 16.81  # chi-square, 6 dof, 1 %


def _rays(points: np.ndarray) -> np.ndarray:
    """The rays (z = 1) through a cloud's points (camera frame, z > 0 where valid)."""
    z = points[:, 2:3]
    return points / np.where(z > 0, z, 1.0)


def moved_beyond_board(board_only: dict[str, Any], joint: dict[str, Any]) -> dict[str, str]:
    """Cameras the joint solve with the depth pairs moved further from the board-only result
    than the board's own uncertainty allows (camera -> why): the move ``xi`` (right
    perturbation, [rot, trans]) weighed by the board marginal, ``xi^T Cov^-1 xi``, above
    :data:`BEYOND_BOARD_CHI2`. Both arguments map camera -> :class:`CameraExtrinsics`."""
    out = {}
    for c, b in board_only.items():
        if c not in joint or b.covariance is None or not np.all(np.isfinite(b.covariance)):
            continue
        xi = tangent_error(b.T_ref_cam, joint[c].T_ref_cam)
        try:
            chi2 = float(xi @ np.linalg.solve(b.covariance, xi))
        except np.linalg.LinAlgError:
            continue
        if chi2 > BEYOND_BOARD_CHI2:
            deg, mm = transform_error(joint[c].T_ref_cam, b.T_ref_cam)
            out[c] = (f"{c} moved {mm:.2f} mm / {deg:.3f} deg from the board result "
                      f"(chi2 {chi2:.0f} > {BEYOND_BOARD_CHI2} under its board covariance)")
    return out


def board_views_per_camera(observations, T_ref_cam: dict[str, np.ndarray],
                           T_ref_board: dict[str, np.ndarray],
                           at_capture: dict[str, dict[str, np.ndarray]] | None = None,
                           ) -> dict[str, dict[str, np.ndarray]]:
    """camera -> {frame: T_cam_board} from the calibrated poses, for the views each camera
    used (the board pose is the joint estimate, not the single-view PnP). ``at_capture``
    (camera -> frame -> T_ref_board at that camera's capture: a moving board seen by
    unsynchronised cameras, by the time model) replaces ``T_ref_board``; a view it lacks (its
    pose at the camera's capture too uncertain) is left out."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for o in observations:
        boards = T_ref_board if at_capture is None else at_capture.get(o.camera, {})
        if o.camera in T_ref_cam and o.frame in boards:
            out.setdefault(o.camera, {})[o.frame] = (invert_transform(T_ref_cam[o.camera])
                                                     @ boards[o.frame])
    return out


# --------------------------------------------------------------------------- outcome
def no_pair_reason(depth: DepthRefinement) -> str:
    """One line: why no pair could be used (for the fallback warning)."""
    if len(depth.clouds) < 2:
        why = "; ".join(f"{c}: {r}" for c, r in depth.skipped_cameras.items())
        return f"fewer than 2 cameras have a static cloud{f' ({why})' if why else ''}"
    if not depth.pairs:
        return "no camera pair overlaps under the current extrinsics"
    agree = sum(p.agrees for p in depth.pairs)
    return (f"all {len(depth.pairs)} camera pairs were rejected"
            + (f" ({agree} of them agree with the current extrinsics within their own "
               "uncertainty: nothing to correct)" if agree else ""))


def finish_pairs(depth: DepthRefinement, T_ref_cam: dict[str, np.ndarray],
                 config: DepthConfig | None = None, tick: Tick | None = None) -> DepthRefinement:
    """Add each pair's point-to-plane RMSE at the final extrinsics (``rmse_final_mm``), on
    the same points and metric as its ``rmse_before_mm`` / ``rmse_after_mm`` (which it equals,
    without recomputing, when neither camera moved: a fallback or a skipped pair's cameras);
    ``tick(1)`` after each pair."""
    pairs = []
    for p in depth.pairs:
        a, b = p.cam_a, p.cam_b
        final = None
        if a in T_ref_cam and b in T_ref_cam and all(
                np.array_equal(T_ref_cam[c], depth.T_ref_cam_initial[c]) for c in (a, b)):
            final = p.registration.rmse_before_mm
        elif a in T_ref_cam and b in T_ref_cam:
            final = pair_rmse_mm(depth.clouds[a], depth.clouds[b], depth.T_ref_cam_initial[a],
                                 depth.T_ref_cam_initial[b], T_ref_cam[a], T_ref_cam[b], config)
        pairs.append(replace(p, rmse_final_mm=final, finished=True))
        if tick is not None:
            tick(1)
    return replace(depth, pairs=pairs)


def with_overlaps(depth: DepthRefinement, T_ref_cam: dict[str, np.ndarray],
                  extrinsics_cov: dict[str, np.ndarray | None],
                  config: DepthConfig | None = None) -> DepthRefinement:
    """``depth`` with its depth models updated by the overlapping pairs' medians at the
    final extrinsics ``T_ref_cam`` (their covariances ``extrinsics_cov``;
    :mod:`.overlap_models`) and its clouds corrected by them; unchanged with
    ``depth.overlap_models`` off, without two clouds or a pair with a modelled camera. A
    camera without a board fit (``unmodelled``: its raw depth) takes no part."""
    config = config or DepthConfig()
    fits = {c: f for c, f in depth.depth_models.items()
            if c in depth.clouds and f.model_cov is not None and f.model.sigmas}
    # a camera without a board fit (its raw depth) is known to nothing: its pairs say nothing
    clouds = {c: k for c, k in depth.clouds.items() if c in T_ref_cam and c in depth.depth_models}
    if not config.overlap_models or not fits or len(clouds) < 2:
        return depth
    models = {c: depth.depth_models[c].model for c in clouds}
    held = {c: depth.depth_models[c] for c in clouds if c not in fits}
    pairs = [(o.cam_a, o.cam_b) for o in find_overlapping_pairs(clouds, T_ref_cam, None, config)]
    grids = _normal_grids(clouds, pairs, depth.normal_grids)
    try:
        update = update_models(models, {c: f.model_cov for c, f in fits.items()},
                               overlap_samples(clouds, T_ref_cam, pairs, models, grids=grids),
                               T_ref_cam, extrinsics_cov, held)
    except (np.linalg.LinAlgError, ValueError) as exc:
        warnings.warn(f"the depth models could not be updated by the overlaps "
                      f"({type(exc).__name__}: {one_line_error(exc)})", RuntimeWarning,
                      stacklevel=2)
        return depth
    if update is None:
        return replace(depth, normal_grids=grids)
    if not update.applied:  # held-out pairs predicted no better: the board's models stay
        return replace(depth, overlaps=update, normal_grids=grids)
    fitted = {c: replace(depth.depth_models[c], model=m, model_cov=update.covariances[c])
              for c, m in update.models.items()}
    moved = {c: recorrected(depth.clouds[c], models[c], m) for c, m in update.models.items()}
    grids = {c: g.moved(models[c], update.models[c]) if c in update.models else g
             for c, g in grids.items()}
    return replace(depth, depth_models={**depth.depth_models, **fitted},
                   clouds={**depth.clouds, **moved}, overlaps=update, normal_grids=grids)


def _normal_grids(clouds: dict[str, CameraCloud], pairs: list[tuple[str, str]],
                  known: dict[str, NormalGrid]) -> dict[str, NormalGrid]:
    """The :class:`NormalGrid` of every cloud in ``pairs``: ``known``'s, or estimated."""
    used = {c for p in pairs for c in p if c in clouds and clouds[c].n_points >= MIN_POINTS}
    return {c: known[c] if c in known else NormalGrid.of(clouds[c].points) for c in used}


def measure_agreement(depth: DepthRefinement, T_ref_cam: dict[str, np.ndarray],
                      config: DepthConfig | None = None,
                      models: dict[str, DepthModel] | None = None) -> DepthRefinement:
    """``depth`` with the fused cloud's agreement (:func:`fused_agreement`) at ``T_ref_cam``:
    every pair whose clouds overlap there, before and after the depth models (``models``,
    default the stage's own fits)."""
    config = config or DepthConfig()
    clouds = {c: k for c, k in depth.clouds.items() if c in T_ref_cam}
    if len(clouds) < 2:
        return depth
    pairs = [(o.cam_a, o.cam_b) for o in find_overlapping_pairs(clouds, T_ref_cam, None, config)]
    if models is None:
        models = {c: f.model for c, f in depth.depth_models.items()}
    try:
        agreement = fused_agreement(clouds, T_ref_cam, pairs, models, grids=depth.normal_grids)
    except Exception as exc:  # noqa: BLE001 - a measurement of the result never ends a run
        warnings.warn(f"the fused cloud's agreement could not be measured "
                      f"({type(exc).__name__}: {one_line_error(exc)})", RuntimeWarning,
                      stacklevel=2)
        return depth
    return replace(depth, agreement=agreement)
