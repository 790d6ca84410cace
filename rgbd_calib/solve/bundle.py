"""Bundle adjustment of camera and board poses on the marker corners (GTSAM).

:func:`bundle_adjust` solves a :class:`BundleProblem` (its inputs: measurements, camera models,
initial poses, config; in the spirit of mrcal's ``optimization_inputs``): one view factor per
camera view holding all its markers, robust per marker
(:mod:`rgbd_calib.solve.bundle_factors`), the reference and any fixed cameras held by priors,
optionally the intrinsics (a vector per camera under a prior at rig.yaml), the board's back
sheet or a multi-face target's faces (board self-calibration) and camera-to-camera relative
poses (depth registration) in the same graph; the problem and result types are
:mod:`rgbd_calib.solve.bundle_problem`. Steps: the factor layout, initial values, solve
and drop outlier markers, the a-posteriori corner sigma, marginals. The pose graph that gives
the initial poses is :mod:`rgbd_calib.solve.posegraph`; no file I/O here.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.config import BundleConfig
from ..core.errors import CalibrationError
from ..core.geometry import move_rows
from .bundle_faces import (
    BoardModel,
    FaceModel,
    board_model_setup,
    board_prior_sigmas,
    face_models_setup,
    face_prior_sigmas,
    reference_component,
)
from .bundle_factors import (
    face_transform,
    lens_names,
    project_board,
    project_board_full,
    view_factor,
    view_factor_intrinsics,
    with_parameters,
)
from .bundle_problem import (
    BundleProblem,
    BundleResult,
    MarkerMeasurement,
    RelativePose,
    intrinsics_prior_sigmas,
    intrinsics_vector,
)
from .corner_noise import CornerNoise, estimate_corner_noise, first_noise, scale_covariance
from .edge_offset import measurements_without_offset, read_offsets
from .posegraph import sigmas_from_covariance
from .runs import RunCorrelation, link_window_ms, recording_runs, run_inflation
from .time_model import (
    READOUT_INIT_MS,
    MotionPrior,
    TimeModel,
    TimePrior,
    TwistPrior,
    acceleration_stencils,
    motion_link_factor,
    motion_links,
    project_timed,
    row_fraction,
    time_prior,
    timed_view_factor,
    twist_from_poses,
    twist_prior,
)

_BACK_SHEET_KEY = gtsam.symbol("f", 0)  # the back sheet's pose T_front_back (board refine)


@dataclass(frozen=True)
class _ViewGroup:
    """The markers of one (camera, view): their indices in the active list and stacked data."""

    camera: str
    view: str
    index: np.ndarray  # (n,) positions in the active measurement list
    object_points: np.ndarray  # (n,4,3)
    corners_px: np.ndarray  # (n,4,2)
    face: np.ndarray  # (n,) face label of each marker (-1: the back face)


def _group_views(active: list[MarkerMeasurement]) -> list[_ViewGroup]:
    """Group the measurements by (camera, view), in order of first appearance."""
    members: dict[tuple[str, str], list[int]] = defaultdict(list)
    for i, m in enumerate(active):
        members[(m.camera, m.view)].append(i)
    return [_ViewGroup(c, v, np.array(idx),
                       np.stack([active[i].object_points for i in idx]).astype(float),
                       np.stack([active[i].corners_px for i in idx]).astype(float),
                       np.array([active[i].face for i in idx], dtype=int))
            for (c, v), idx in members.items()]


def bundle_adjust(problem: BundleProblem) -> BundleResult:
    """Joint bundle adjustment of camera poses ``T_ref_cam`` and board poses ``T_ref_board``
    on the marker corners (one GTSAM CustomFactor per camera view holding all its markers,
    robust per marker: :func:`~rgbd_calib.solve.bundle_factors.view_factor`), optionally joined
    by camera-to-camera ``relative_poses`` (depth registration) as ``BetweenFactorPose3`` with
    their own information: one joint graph, one set of marginals. ``problem`` holds the inputs
    (:class:`BundleProblem`).

    With ``config.intrinsics == "fixed"`` the intrinsics are held (``K`` per camera) and the
    measurements are undistorted pinhole pixels. With ``"refine"`` each camera also gets a
    vector variable of the parameters ``config.intrinsics_params`` under a Gaussian prior at
    ``intrinsics`` (the rig.yaml models, required then; sigmas from
    :func:`intrinsics_prior_sigmas`), and the measurements are the RAW detected pixels,
    projected through the full model
    (:func:`~rgbd_calib.solve.bundle_factors.view_factor_intrinsics`). The reference camera
    (and any ``fixed_cameras``) carry a tight pose prior. Marginal covariances come from the
    converged graph, scaled by the a-posteriori variance factor when ``config.estimate_sigma``
    is on.

    With ``config.board == "refine"`` the back sheet's pose ``T_front_back`` is one more
    Pose3 variable (board self-calibration, :func:`~rgbd_calib.solve.bundle_factors.view_factor`
    with ``moving``): it moves the board points of the back-face measurements
    (``MarkerMeasurement.face == -1``), under a prior at the identity (the board file) with the
    config's sigmas on the in-plane offset, the rotation about the normal and the thickness; the
    tilts of a sheet glued flat on the panel are held by a tight prior. ``back_centre``
    (board-file centre of the back-marker grid, m; default: of the back markers measured) is
    where the offset is reported (:class:`BoardModel`). It is held at the board file, and
    ``result.board.held`` says why, when no view has markers of both faces: then a back-sheet
    shift is the same as a shift of those views' board poses.

    A multi-face target (``face_frames``: label -> nominal ``T_board_face`` of each
    non-reference face) gets, with ``config.board == "refine"``, one Pose3 correction
    ``Delta`` per such face instead (its true pose ``T_board_face @ Delta``, :class:`FaceModel`)
    under a prior at the identity with the ``board_prior_face_*`` sigmas on all 6 axes of the
    face frame; a face that no view sees together with a face already tied to the reference
    face is held (``result.faces[k].held``).

    With ``config.time == "refine"`` (the rig's ``intrinsics`` required: their image heights)
    every view factor predicts each corner at its own time
    (:func:`~rgbd_calib.solve.time_model.timed_view_factor`): per camera a Vector 2
    ``[offset_ms, readout_ms]`` under ``time_priors`` (the reference's offset held at 0),
    per view a twist under the ``time_twist_sigma_*`` prior, each view's ``capture_ms`` (its
    timestamps' offset) added to its camera's offset; ``result.time`` holds the estimates.

    ``edge_offset`` (camera -> px per edge) is taken out of each camera's edge-fitted corners
    first (:func:`~rgbd_calib.solve.edge_offset.without_offset`); ``result.edge_offset`` reads
    what is left in the residuals, on top of it. ``config.corners.corner_noise == "marker"`` weighs
    each marker's centre and shape by their own sigmas (:mod:`~rgbd_calib.solve.corner_noise`;
    ``corner_centre_ratio``, or read from a first solve, then solved again) and adds the rig's scale
    (``config.corners.scale_sigma_ppm``) to every camera's covariance; the board's printed size
    (``problem.board_scale_sigma``) is added the same way, in quadrature."""
    if problem.edge_offset:
        problem = replace(problem, measurements=measurements_without_offset(
            problem.measurements, problem.edge_offset))
    # the variables, their keys and priors; the measurements with initialised ends
    layout, kept, board_model, face_models = _factor_layout(problem)
    values = _initial_values(layout, problem.T_ref_cam, problem.T_ref_board,
                             problem.intrinsics_start)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(layout.config.max_iterations)
    params.setRelativeErrorTol(layout.config.relative_error_tol)
    # solve, drop the markers far off, re-solve
    solution = _solve_dropping_outliers(layout, kept, values, params)
    # the corner noise a posteriori (Foerstner's variance factor); with depth pairs, re-solve
    # with the corners at it, so that board and depth measurements are weighted against each
    # other by their real uncertainties
    config = layout.config
    corners = config.corners
    if corners.corner_noise == "marker" and solution.active and not corners.corner_centre_ratio:
        ratio = _noise(layout, solution).centre_ratio  # centre and shape weighed apart
        solution = _solve_at_sigma(layout, solution, CornerNoise(config.pixel_sigma, ratio),
                                   params)
    sigma_hat = solution.sigma_px(layout)
    sigma_marg = _noise_a_posteriori(layout, solution, sigma_hat)
    clock = None
    if layout.timed and config.time_model.time_twist_prior_from_data:  # priors against the corners
        # the clocks from the solve with the wide prior, which barely pulls their scale
        clock = _time_model(layout, solution.values, gtsam.Marginals(_build_graph(
            layout, solution.groups, sigma_marg, solution.connected, robust=False),
            solution.values))
        layout, solution = _twist_prior_from_data(layout, solution, sigma_marg, params)
        sigma_hat = solution.sigma_px(layout)
        sigma_marg = _noise_a_posteriori(layout, solution, sigma_hat)
    if layout.relative_poses and config.estimate_sigma:
        solution = _solve_at_sigma(layout, solution, sigma_marg, params)
    # marginals of the plain Gaussian graph at the solution
    result = _result(layout, solution, sigma_hat, sigma_marg, board_model, face_models, clock)
    if config.held_out:
        result = replace(result, held_out_px=_held_out(layout, solution, sigma_marg))
    return result


@dataclass(frozen=True)
class _TimeLayout:
    """The time model's part of a :class:`_FactorLayout`: its keys (empty without the time
    model), the clocks' priors and known capture times, the image heights (the rolling
    shutter's rows), the twist prior read from the data, the linked sets and the runs."""

    time_key: dict[str, int] = field(default_factory=dict)  # camera -> clock key; {}: no model
    twist_key: dict[str, int] = field(default_factory=dict)
    time_priors: dict[str, TimePrior] = field(default_factory=dict)
    capture_ms: dict[tuple[str, str], float] = field(default_factory=dict)
    heights: dict[str, int] = field(default_factory=dict)
    twist_sigma: TwistPrior | None = None  # the twist prior estimated from the data
    links: tuple[tuple[str, str, float], ...] = ()  # (set, next set, dt_s): motion prior
    runs: tuple[tuple[str, ...], ...] = ()  # the continuous stretches (runs.recording_runs)
    motion_prior: MotionPrior = MotionPrior()  # its scale (estimated from the data)


@dataclass(frozen=True)
class _FactorLayout:
    """What one bundle adjustment's factor graph is made of (see :func:`bundle_adjust`)."""

    config: BundleConfig
    K: dict[str, np.ndarray]
    cam_key: dict[str, int]
    view_key: dict[str, int]
    intr_key: dict[str, int]  # refined intrinsics only
    intrinsics: dict[str, CameraIntrinsics] | None
    names: tuple[str, ...]
    x0: dict[str, np.ndarray]
    prior_intr: dict[str, Any]
    fixed: dict[str, np.ndarray]  # the reference included
    relative_poses: Sequence[RelativePose]
    moving: tuple  # (key, face label, frame A or None) of every face pose solved
    refine: bool  # intrinsics refined: the view factors project raw pixels through the model
    reference: str
    cams: list[str]
    views: list[str]
    time: _TimeLayout = field(default_factory=_TimeLayout)  # the time model's part
    edge_offset: dict[str, float] = field(default_factory=dict)  # taken out of the corners
    board_scale_sigma: float = 0.0  # the printed board's size, relative 1 sigma

    @property
    def timed(self) -> bool:
        return bool(self.time.time_key)

    @property
    def stencils(self) -> dict[str, tuple[tuple[str, float], ...]]:
        """Per linked set, its acceleration from the twists (time_model.acceleration_stencils)."""
        return acceleration_stencils(self.time.links)

    def accelerations(self, values: gtsam.Values) -> dict[str, np.ndarray]:
        """Per linked set with every twist of its stencil in ``values``: its acceleration."""
        out = {}
        for v, stencil in self.stencils.items():
            keys = [(self.time.twist_key[u], c) for u, c in stencil]
            if all(values.exists(k) for k, _ in keys):
                out[v] = sum(c * values.atVector(k) for k, c in keys)
        return out

    def connected(self, values: gtsam.Values) -> set[str]:
        """The cameras with a pose in ``values``."""
        return {c for c in self.cams if values.exists(self.cam_key[c])}

    def reference_part(self, active: list[MarkerMeasurement], values: gtsam.Values):
        """:func:`~rgbd_calib.solve.bundle_faces.reference_component`, keeping the face poses
        (the back sheet's)."""
        out, sub = reference_component(active, values, self.cam_key, self.view_key,
                                        set(self.fixed), self.relative_poses, self.reference,
                                        self.intr_key)
        for key, _, _ in self.moving:
            sub.insert(key, values.atPose3(key))
        for owner_keys, pose_keys in ((self.time.time_key, self.cam_key),
                                      (self.time.twist_key, self.view_key)):
            for owner, k in owner_keys.items():
                if sub.exists(pose_keys[owner]) and values.exists(k):
                    sub.insert(k, values.atVector(k))
        return out, sub

    def marker_rms(self, groups: list[_ViewGroup], n: int, values: gtsam.Values) -> np.ndarray:
        """Each marker's RMS corner residual (px): sqrt(mean over the 4 corners of
        |uv - uv_meas|^2) of :meth:`marker_residuals`."""
        return np.sqrt(np.mean(np.sum(self.marker_residuals(groups, n, values) ** 2, axis=2),
                               axis=1))

    def marker_residuals(self, groups: list[_ViewGroup], n: int,
                         values: gtsam.Values) -> np.ndarray:
        """:func:`_marker_residuals` through the current models and face poses of ``values``."""
        timing = None
        if self.timed:
            timing = (self.time.heights, self.time.capture_ms,
                      {c: values.atVector(k) for c, k in self.time.time_key.items()
                       if values.exists(k)},
                      {v: values.atVector(k) for v, k in self.time.twist_key.items()
                       if values.exists(k)}, self.accelerations(values))
        return _marker_residuals(groups, n, values, self.cam_key, self.view_key, self.K,
                           _current_models(self, values),
                           moves=[(label, face_transform(values.atPose3(key).matrix(), A))
                                  for key, label, A in self.moving], timing=timing)


def _factor_layout(problem: BundleProblem) -> tuple[
        _FactorLayout, list[MarkerMeasurement], BoardModel | None, tuple[FaceModel, ...]]:
    """The keys, the priors and the face poses to solve; the measurements whose camera and view
    have an initial pose (and, refining intrinsics, a camera model); the back-sheet and face
    models to estimate (or why each is held)."""
    config, intrinsics = problem.config, problem.intrinsics
    refine = config.intrinsics == "refine"
    if refine and intrinsics is None:
        raise CalibrationError("refining intrinsics needs the rig's camera models")
    names = tuple(config.intrinsics_params)
    fixed = dict(problem.fixed_cameras or {})
    fixed.setdefault(problem.reference, np.eye(4))
    cams = sorted({m.camera for m in problem.measurements} | set(fixed)
                  | {c for r in problem.relative_poses for c in (r.cam_a, r.cam_b)})
    views = sorted({m.view for m in problem.measurements})
    cam_key = {c: gtsam.symbol("c", i) for i, c in enumerate(cams)}
    view_key = {v: gtsam.symbol("b", i) for i, v in enumerate(views)}
    intr_key = ({c: gtsam.symbol("k", i) for i, c in enumerate(cams) if c in intrinsics}
                if refine else {})
    kept = [m for m in problem.measurements
            if m.camera in problem.T_ref_cam and m.view in problem.T_ref_board]
    board_model = (None if problem.face_frames is not None
                   else board_model_setup(kept, config, problem.back_centre))
    solve_board = board_model is not None and not board_model.held
    face_models = face_models_setup(kept, config, problem.face_frames)
    moving = [(_BACK_SHEET_KEY, -1, None)] if solve_board else []  # (key, face label, frame A)
    moving += [(gtsam.symbol("f", m.label), m.label, m.T_nominal) for m in face_models
               if not m.held]
    x0, prior_intr = {}, {}
    if refine:
        kept = [m for m in kept if m.camera in intr_key]
        x0 = {c: intrinsics_vector(intrinsics[c], names) for c in intr_key}
        prior_intr = {c: gtsam.noiseModel.Diagonal.Sigmas(
            intrinsics_prior_sigmas(intrinsics[c], names, config)) for c in intr_key}
    timing = {}
    link_ms = link_window_ms(config.time_model.time_link_ms, problem.set_ms or {})
    if config.time == "refine":
        if intrinsics is None:
            raise CalibrationError("the time model needs the rig's camera models")
        timing = {"time_key": {c: gtsam.symbol("t", i) for i, c in enumerate(cams)},
                  "twist_key": {v: gtsam.symbol("w", i) for i, v in enumerate(views)},
                  "time_priors": {c: (problem.time_priors or {}).get(c, TimePrior())
                                  for c in cams},
                  "capture_ms": dict(problem.capture_ms or {}),
                  "heights": {c: intrinsics[c].height for c in cams if c in intrinsics},
                  "links": motion_links(problem.set_ms or {}, views, link_ms)}
        kept = [m for m in kept if m.camera in intrinsics]
    timing["runs"] = recording_runs(problem.set_ms or {}, views, link_ms)
    layout = _FactorLayout(config, problem.K, cam_key, view_key, intr_key, intrinsics, names,
                           x0, prior_intr, fixed, problem.relative_poses, tuple(moving), refine,
                           problem.reference, cams, views, _TimeLayout(**timing),
                           edge_offset=dict(problem.edge_offset or {}),
                           board_scale_sigma=problem.board_scale_sigma)
    return layout, kept, board_model, face_models


@dataclass(frozen=True)
class _Solution:
    """A solve's state: the markers kept, their view groups, the cameras connected to the
    reference, the values, each marker's RMS (px), the last graph and optimiser, the markers
    dropped as outliers ``(camera, view, marker, rms px)``."""

    active: list[MarkerMeasurement]
    groups: list[_ViewGroup]
    connected: set[str]
    values: gtsam.Values
    rms: np.ndarray
    graph: gtsam.NonlinearFactorGraph
    optimizer: gtsam.LevenbergMarquardtOptimizer
    outliers: list[tuple[str, str, int, float]]

    def sigma_px(self, layout: _FactorLayout) -> float:
        """The a-posteriori corner sigma: sqrt(SSR / redundancy), 4 corners x (du^2 + dv^2)
        per marker RMS."""
        dof = _residual_dof(layout, len(self.active), self.values)
        return float(np.sqrt(np.sum(4 * self.rms**2) / dof))


def _noise(layout: _FactorLayout, solution: _Solution, corner_res=None) -> CornerNoise:
    """The corners' centre and shape sigmas a posteriori from ``solution``'s residuals."""
    n = len(solution.active)
    return estimate_corner_noise(
        layout.marker_residuals(solution.groups, n, solution.values) if corner_res is None
        else corner_res, 8 * n - _residual_dof(layout, n, solution.values))


def _noise_a_posteriori(layout: _FactorLayout, solution: _Solution,
                        sigma_hat: float) -> float | CornerNoise:
    """The corner noise of the marginals and later solves: ``pixel_sigma`` without
    ``estimate_sigma``, else ``sigma_hat`` or (``corner_noise: marker``) :func:`_noise`."""
    config = layout.config
    if not config.estimate_sigma:
        return config.pixel_sigma
    if config.corners.corner_noise == "marker" and solution.active:
        noise = _noise(layout, solution)
        return replace(noise, sigma_px=max(noise.sigma_px, 1e-3))
    return max(sigma_hat, 1e-3)


def _solve_dropping_outliers(layout: _FactorLayout, kept: list[MarkerMeasurement],
                             values: gtsam.Values,
                             params: gtsam.LevenbergMarquardtParams) -> _Solution:
    """Solve at ``config.pixel_sigma``; drop the markers whose RMS exceeds ``outlier_px`` and
    re-solve, up to three solves. Removing outliers can cut a camera (or a view) off the
    reference: that part is dropped too."""
    config = layout.config
    outliers: list[tuple[str, str, int, float]] = []
    active, values = layout.reference_part(kept, values)
    connected = layout.connected(values)
    for _ in range(3):
        groups = _group_views(active)
        graph = _build_graph(layout, groups, first_noise(config), connected)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        values = optimizer.optimize()
        rms = layout.marker_rms(groups, len(active), values)
        bad = rms > config.outlier_px
        if not np.any(bad):
            break
        outliers += [(m.camera, m.view, m.marker_id, float(r))
                     for m, r, b in zip(active, rms, bad) if b]
        active = [m for m, b in zip(active, bad) if not b]
        active, values = layout.reference_part(active, values)
        connected = layout.connected(values)
        groups = _group_views(active)
        rms = layout.marker_rms(groups, len(active), values)
    return _Solution(active, groups, connected, values, rms, graph, optimizer, outliers)


def _solve_at_sigma(layout: _FactorLayout, solution: _Solution, sigma: float | CornerNoise,
                    params: gtsam.LevenbergMarquardtParams) -> _Solution:
    """``solution`` solved again with the corners at noise ``sigma`` (px)."""
    graph = _build_graph(layout, solution.groups, sigma, solution.connected)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, solution.values, params)
    values = optimizer.optimize()
    rms = layout.marker_rms(solution.groups, len(solution.active), values)
    return replace(solution, values=values, rms=rms, graph=graph, optimizer=optimizer)


TWIST_PRIOR_STEPS = 2  # expectation-maximisation steps of the twist prior's scale
TWIST_FLOOR = TwistPrior(sigma_mps=0.005, sigma_dps=0.5)  # a board held still by hand


def _twist_prior_from_data(layout: _FactorLayout, solution: _Solution,
                           sigma: float | CornerNoise,
                           params: gtsam.LevenbergMarquardtParams,
                           ) -> tuple[_FactorLayout, _Solution]:
    """The twist prior's scale estimated from the frame sets' twists (empirical Bayes), the
    corners at noise ``sigma`` (px).

    The configured prior (``time_twist_sigma_*``: a board waved by hand, 0.5 m/s, 60 deg/s)
    is wide; where the board moved slower, a set seen by two cameras (whose twist its views
    barely fix with a global shutter) keeps the prior's spread, and the extrinsics' marginals
    claim several times their error. Each step sets the prior's variance to the mean over
    sets and axes of ``twist^2 + its marginal variance`` (the EM update of a zero-mean
    Gaussian's variance; linear and angular parts apart, floored at :data:`TWIST_FLOOR` and
    capped at the configured prior, what a hand does) and solves again. The extrinsics and
    their sigmas come from that solve; the clocks do not (:func:`bundle_adjust` keeps them
    from the solve before it): a prior as tight as the
    twists pulls them towards 0 and with them the clocks' scale, the gauge the timestamps
    anchor only weakly (measured: ring, +-16 ms, offsets 1.3x too large)."""
    for _ in range(TWIST_PRIOR_STEPS):
        graph = _build_graph(layout, solution.groups, sigma, solution.connected, robust=False)
        marginals = gtsam.Marginals(graph, solution.values)
        keys = [k for k in layout.time.twist_key.values() if solution.values.exists(k)]
        second = np.array([solution.values.atVector(k) ** 2
                           + np.diag(marginals.marginalCovariance(k)) for k in keys])
        sigma_w, sigma_v = np.sqrt(second[:, :3].mean()), np.sqrt(second[:, 3:].mean())
        cfg = layout.config  # what a hand does bounds it from above (time_twist_sigma_*)
        layout = replace(layout, time=replace(layout.time, twist_sigma=TwistPrior(
            sigma_mps=min(max(float(sigma_v), TWIST_FLOOR.sigma_mps),
                          cfg.time_model.time_twist_sigma_mps),
            sigma_dps=min(max(float(np.degrees(sigma_w)), TWIST_FLOOR.sigma_dps),
                          cfg.time_model.time_twist_sigma_dps)),
            motion_prior=_motion_prior_from_data(layout, solution.values, marginals)))
        solution = _solve_at_sigma(layout, solution, sigma, params)
    return layout, solution


MOTION_FLOOR = MotionPrior(q_mps=0.01, q_dps=1.0)  # a board moved at a steady pace


def _motion_prior_from_data(layout: _FactorLayout, values: gtsam.Values,
                            marginals: gtsam.Marginals) -> MotionPrior:
    """The motion prior's scale from the linked sets' twist changes (the EM update, as
    :func:`_twist_prior_from_data`'s: per axis ``(change^2 + its marginal variance) / dt``,
    averaged over links, linear and angular parts apart, floored at :data:`MOTION_FLOOR`);
    ``layout``'s own without links."""
    rows = []
    for f, g, dt_s in layout.time.links:
        kf, kg = layout.time.twist_key[f], layout.time.twist_key[g]
        if not (values.exists(kf) and values.exists(kg)):
            continue
        d = values.atVector(kg) - values.atVector(kf)
        C = marginals.jointMarginalCovariance([kf, kg]).fullMatrix()
        var = np.diag(C[:6, :6]) + np.diag(C[6:, 6:]) - 2.0 * np.diag(C[:6, 6:])
        rows.append((d**2 + var) / dt_s)
    if not rows:
        return layout.time.motion_prior
    second = np.array(rows)
    return MotionPrior(q_mps=max(float(np.sqrt(second[:, 3:].mean())), MOTION_FLOOR.q_mps),
                       q_dps=max(float(np.degrees(np.sqrt(second[:, :3].mean()))),
                                 MOTION_FLOOR.q_dps))


def _result(layout: _FactorLayout, solution: _Solution, sigma_hat: float,
            sigma_marg: float | CornerNoise,
            board_model: BoardModel | None, face_models: tuple[FaceModel, ...],
            clock: TimeModel | None = None) -> BundleResult:
    """The :class:`BundleResult` of ``solution``: marginals of the plain Gaussian graph at the
    solution, corners weighted by ``sigma_marg`` so that the relative-pose factors keep their
    own weight (inlier Huber weights are 1 and the outliers were removed)."""
    values = solution.values
    marg_graph = _build_graph(layout, solution.groups, sigma_marg, solution.connected,
                              robust=False)
    marginals = gtsam.Marginals(marg_graph, values)
    out_cam, cov, s_rot, s_trans = _camera_marginals(layout.cams, values, layout.cam_key,
                                                     layout.fixed, marginals)
    # the corner residuals at the solution, once: the runs' correlation and the edge offsets
    corner_res = (layout.marker_residuals(solution.groups, len(solution.active), values)
                  if solution.active else np.zeros((0, 4, 2)))
    runs = _run_correlation(layout, solution, corner_res)
    corners = layout.config.corners
    scale_ppm = math.hypot(corners.scale_sigma_ppm if corners.corner_noise == "marker" else 0.0,
                           1e6 * layout.board_scale_sigma)
    for c in cov:
        if c in runs:
            cov[c] = cov[c] * runs[c].factor
        if scale_ppm and c not in layout.fixed:
            cov[c] = cov[c] + scale_covariance(out_cam[c], scale_ppm * 1e-6)
        s_rot[c], s_trans[c] = sigmas_from_covariance(out_cam[c], cov[c])
    boards = {v: values.atPose3(layout.view_key[v]).matrix() for v in layout.views
              if values.exists(layout.view_key[v])}
    residuals = [(m.camera, m.view, m.marker_id, r)
                 for m, r in zip(solution.active, solution.rms.tolist())]
    refined, sigma_intr, sigma_prior = _refined_intrinsics(layout, values, marginals)
    sigma_intr = {c: {k: s * np.sqrt(runs[c].factor) if c in runs else s for k, s in d.items()}
                  for c, d in sigma_intr.items()}
    if board_model is not None and not board_model.held:
        board_model = replace(board_model, T_front_back=values.atPose3(_BACK_SHEET_KEY).matrix(),
                              covariance=np.asarray(marginals.marginalCovariance(_BACK_SHEET_KEY)))
    face_models = tuple(m if m.held else replace(
        m, Delta=values.atPose3(gtsam.symbol("f", m.label)).matrix(),
        covariance=np.asarray(marginals.marginalCovariance(gtsam.symbol("f", m.label))))
        for m in face_models)
    return BundleResult(out_cam, boards, cov, s_rot, s_trans, residuals, solution.outliers,
                        sigma_hat, solution.optimizer.iterations(),
                        solution.graph.error(values), refined, sigma_intr, sigma_prior,
                        board_model, face_models,
                        _inflated(_with_prior(clock, layout) if clock is not None
                                  else _time_model(layout, values, marginals), runs),
                        runs, relative_pose_fit(layout.relative_poses, layout.cam_key,
                                                solution.connected, values, marginals),
                        read_offsets(solution.active, corner_res, layout.edge_offset),
                        _noise(layout, solution, corner_res) if solution.active else None,
                        scale_ppm)


HELD_OUT_ITERATIONS = 20  # a held-out board pose from a few views converges in 3-6


def _held_out(layout: _FactorLayout, solution: _Solution,
              sigma: float | CornerNoise) -> dict[tuple[str, str, int], float]:
    """Each marker's corner RMS (px) as predicted from the OTHER cameras' views of its frame
    set: per (camera, view) of a set two or more cameras saw, the set's board pose (and, with
    the time model, its twist under the twist prior) solved from the other views alone, every
    camera, lens, clock and face held at the solution, and this view's corners predicted at
    it. A model whose extra freedom only absorbs misfit (a per-set twist two global shutters
    fit exactly, a lens bent to one camera's corners) predicts them worse than the simpler
    model; one that is physical, better. The cameras' parameters saw each view once among
    many (a leave-one-view-out on the set level, not a refit)."""
    by_view: dict[str, list[_ViewGroup]] = defaultdict(list)
    for g in solution.groups:
        by_view[g.view].append(g)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(HELD_OUT_ITERATIONS)
    params.setRelativeErrorTol(1e-5)
    configured = layout.config.time_model
    twist_sigma = layout.time.twist_sigma or TwistPrior(configured.time_twist_sigma_mps,
                                                        configured.time_twist_sigma_dps)
    values, out = solution.values, {}
    for view, groups in by_view.items():
        if len(groups) < 2:
            continue
        free = {layout.view_key[view]} | (
            {layout.time.twist_key[view]} if layout.timed else set())
        for g in groups:
            graph, start = gtsam.NonlinearFactorGraph(), gtsam.Values()
            for h in groups:
                if h is g:
                    continue
                factor = _view_factor(layout, h, sigma, layout.config.robust)
                graph.add(factor)
                for k in factor.keys():
                    if not start.exists(k):
                        _insert_held(graph, start, values, k, k not in free)
            if layout.timed:
                graph.add(twist_prior(layout.time.twist_key[view], twist_sigma))
            try:
                solved = gtsam.LevenbergMarquardtOptimizer(graph, start, params).optimize()
            except RuntimeError:
                continue
            at = gtsam.Values(values)
            for k in free:
                if solved.exists(k):
                    at.update(k, solved.atPose3(k) if k == layout.view_key[view]
                              else solved.atVector(k))
            alone = replace(g, index=np.arange(len(g.index)))
            res = layout.marker_residuals([alone], len(g.index), at)
            rms = np.sqrt(np.mean(np.sum(res**2, axis=2), axis=1))
            ids = [solution.active[i].marker_id for i in g.index]
            out |= {(g.camera, g.view, m): float(r) for m, r in zip(ids, rms)}
    return out


_POSE_SYMBOLS = {ord("c"), ord("b"), ord("f")}  # camera, board and face keys are Pose3


def _insert_held(graph: gtsam.NonlinearFactorGraph, start: gtsam.Values, values: gtsam.Values,
                 key: int, held: bool) -> None:
    """``key``'s value from ``values`` into ``start``; ``held``: with a tight prior there."""
    if gtsam.Symbol(key).chr() in _POSE_SYMBOLS:
        x = values.atPose3(key)
        start.insert(key, x)
        if held:
            graph.add(gtsam.PriorFactorPose3(key, x, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    else:
        x = values.atVector(key)
        start.insert(key, x)
        if held:
            graph.add(gtsam.PriorFactorVector(key, x,
                                              gtsam.noiseModel.Isotropic.Sigma(len(x), 1e-6)))


def relative_pose_fit(relative_poses: Sequence[RelativePose], cam_key: dict[str, int],
                      connected: set[str], values: gtsam.Values, marginals: gtsam.Marginals,
                      ) -> tuple[tuple[float, float], ...]:
    """Per relative pose: ``(e^T W e, r)``, its whitened chi-square at ``values`` and its
    redundancy number ``r = 6 - tr(A_f Sigma_ab A_f^T)`` (``A_f`` its whitened Jacobian,
    ``Sigma_ab`` the joint marginal of its two cameras from ``marginals``: the whole graph's,
    corners included; Foerstner 1979), the share of the graph's redundancy its residual
    carries; (0, 0) for one between cameras not both in ``connected``. A variance factor of
    the relative poses is ``sum chi2 / sum r`` (:mod:`rgbd_calib.solve.variance_components`)."""
    out = []
    for rel in relative_poses:
        if rel.cam_a not in connected or rel.cam_b not in connected:
            out.append((0.0, 0.0))
            continue
        factor = rel.factor(cam_key)
        A, _ = factor.linearize(values).jacobian()
        keys = gtsam.KeyVector([cam_key[rel.cam_b], cam_key[rel.cam_a]])
        cov = marginals.jointMarginalCovariance(keys).fullMatrix()
        out.append((2.0 * factor.error(values), 6.0 - float(np.trace(A @ cov @ A.T))))
    return tuple(out)


def _stencil_keys(p: _FactorLayout, stencil: tuple[tuple[str, float], ...],
                  in_graph: set[str]) -> tuple[tuple[int, float], ...]:
    """A set's acceleration stencil as twist keys, empty unless all its sets are solved."""
    if not all(u in in_graph for u, _ in stencil):
        return ()
    return tuple((p.time.twist_key[u], c) for u, c in stencil)


def _run_correlation(layout: _FactorLayout, solution: _Solution, corner_res: np.ndarray,
                     ) -> dict[str, RunCorrelation]:
    """:func:`~rgbd_calib.solve.runs.run_inflation` of the solution's corner residuals
    ``corner_res`` (n, 4, 2) over the layout's runs of consecutive frames (empty without
    runs)."""
    if not layout.time.runs:
        return {}
    return run_inflation(layout.time.runs, {(m.camera, m.view, m.marker_id): r
                                       for m, r in zip(solution.active, corner_res)})


def _inflated(clock: TimeModel | None, runs: dict[str, RunCorrelation]) -> TimeModel | None:
    """``clock`` with each camera's offset and readout sigmas scaled by its run factor."""
    if clock is None or not runs:
        return clock
    k = {c: np.sqrt(runs[c].factor) if c in runs else 1.0 for c in clock.offset_ms}
    return replace(clock, sigma_offset_ms={c: s * k[c] for c, s in clock.sigma_offset_ms.items()},
                   sigma_readout_ms={c: s * k[c] for c, s in clock.sigma_readout_ms.items()})


def _build_graph(p: _FactorLayout, groups: list[_ViewGroup], sigma: float | CornerNoise,
                 connected: set[str], robust: bool = True) -> gtsam.NonlinearFactorGraph:
    """The factor graph: one view factor per (camera, view) at corner noise ``sigma`` (px),
    robust per marker unless ``robust`` is off, the priors (fixed cameras, intrinsics, back
    sheet) and the relative poses between ``connected`` cameras."""
    config = p.config
    graph = gtsam.NonlinearFactorGraph()
    kind = config.robust if robust else "none"
    stencils, in_graph = (p.stencils, {g.view for g in groups}) if p.timed else ({}, set())
    for g in groups:
        graph.add(_view_factor(p, g, sigma, kind,
                               _stencil_keys(p, stencils.get(g.view, ()), in_graph)))
    for key, _, A in p.moving:
        graph.add(gtsam.PriorFactorPose3(key, gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(
            board_prior_sigmas(config) if A is None else face_prior_sigmas(config))))
    for c, k in p.intr_key.items():
        if c in connected:
            graph.add(gtsam.PriorFactorVector(k, p.x0[c], p.prior_intr[c]))
    prior = gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)
    for c, T in p.fixed.items():
        graph.add(gtsam.PriorFactorPose3(p.cam_key[c], gtsam.Pose3(T), prior))
    for rel in p.relative_poses:
        if rel.cam_a not in connected or rel.cam_b not in connected:
            continue  # a pair cut off from the reference constrains nothing we solve
        graph.add(rel.factor(p.cam_key))
    if p.timed:
        for c in connected:
            graph.add(time_prior(p.time.time_key[c], p.time.time_priors[c], c == p.reference))
        twist_sigma = p.time.twist_sigma or TwistPrior(config.time_model.time_twist_sigma_mps,
                                                  config.time_model.time_twist_sigma_dps)
        seen = dict.fromkeys(g.view for g in groups)
        for v in seen:
            graph.add(twist_prior(p.time.twist_key[v], twist_sigma))
        for f, g, dt_s in p.time.links:
            if f in seen and g in seen:
                graph.add(motion_link_factor(p.view_key[f], p.time.twist_key[f], p.view_key[g],
                                             p.time.twist_key[g], dt_s, p.time.motion_prior))
    return graph


def _view_factor(p: _FactorLayout, g: _ViewGroup, sigma: float | CornerNoise, kind: str,
                 accel: tuple[tuple[int, float], ...] = ()) -> gtsam.CustomFactor:
    """The view factor of ``g``: timed, through refined intrinsics, or pinhole, with the face
    poses that move its markers; ``accel`` its acceleration stencil's twist keys (timed)."""
    config = p.config
    seen = [(key, g.face == label, A) for key, label, A in p.moving if np.any(g.face == label)]
    extra = {"moving": seen} if seen else {}
    if p.timed:
        intr = (p.intr_key[g.camera], p.intrinsics[g.camera]) if p.refine else None
        return timed_view_factor(
            p.cam_key[g.camera], p.view_key[g.view], p.time.twist_key[g.view],
            p.time.time_key[g.camera], p.K.get(g.camera), p.time.heights[g.camera], g.object_points,
            g.corners_px, sigma, kind, config.robust_k, intr, p.names, **extra,
            known_ms=p.time.capture_ms.get((g.camera, g.view), 0.0), accel=accel)
    if p.refine:
        return view_factor_intrinsics(
            p.cam_key[g.camera], p.view_key[g.view], p.intr_key[g.camera],
            p.intrinsics[g.camera], p.names, g.object_points, g.corners_px, sigma, kind,
            config.robust_k, **extra)
    return view_factor(p.cam_key[g.camera], p.view_key[g.view], p.K[g.camera],
                       g.object_points, g.corners_px, sigma, kind, config.robust_k, **extra)


def _initial_values(p: _FactorLayout, init_T_ref_cam: dict[str, np.ndarray],
                    init_T_ref_board: dict[str, np.ndarray],
                    intrinsics_start: dict[str, CameraIntrinsics] | None = None,
                    ) -> gtsam.Values:
    """Camera poses (fixed ones where they are held), board poses, the intrinsics at
    ``intrinsics_start`` (a simpler model's estimate) or else their prior values, and the back
    sheet at the board file: the solve's starting point."""
    values = gtsam.Values()
    for c in p.cams:
        T = p.fixed.get(c, init_T_ref_cam.get(c))
        if T is not None:
            values.insert(p.cam_key[c], gtsam.Pose3(T))
    for v in p.views:
        if v in init_T_ref_board:
            values.insert(p.view_key[v], gtsam.Pose3(init_T_ref_board[v]))
    for c, k in p.intr_key.items():
        if values.exists(p.cam_key[c]):
            start = (intrinsics_start or {}).get(c)
            values.insert(k, p.x0[c] if start is None else intrinsics_vector(start, p.names))
    for key, _, _ in p.moving:
        values.insert(key, gtsam.Pose3())
    for c, k in p.time.time_key.items():  # a nonzero readout breaks the standstill saddle
        if values.exists(p.cam_key[c]):
            prior = p.time.time_priors[c]
            free = prior.readout_sigma_ms > READOUT_INIT_MS  # not a known or held readout
            readout = prior.readout_ms or (READOUT_INIT_MS if free else 0.0)
            values.insert(k, np.array([0.0 if c == p.reference else prior.offset_ms, readout]))
    starts: dict[str, list[np.ndarray]] = {}  # linked sets: the twist between their poses
    for f, g, dt_s in p.time.links:
        if f in init_T_ref_board and g in init_T_ref_board:
            x = twist_from_poses(init_T_ref_board[f], init_T_ref_board[g], dt_s)
            starts.setdefault(f, []).append(x)
            starts.setdefault(g, []).append(x)
    for v, k in p.time.twist_key.items():
        if values.exists(p.view_key[v]):
            values.insert(k, np.mean(starts[v], axis=0) if v in starts else np.zeros(6))
    return values


def _time_model(p: _FactorLayout, values: gtsam.Values,
                marginals: gtsam.Marginals) -> TimeModel | None:
    """The time model's estimates and marginal sigmas (None without it)."""
    if not p.timed:
        return None
    times = {c: values.atVector(k) for c, k in p.time.time_key.items() if values.exists(k)}
    t_sig = {c: np.sqrt(np.diag(marginals.marginalCovariance(p.time.time_key[c]))) for c in times}
    twists = {v: values.atVector(k) for v, k in p.time.twist_key.items() if values.exists(k)}
    return TimeModel(
        offset_ms={c: float(t[0]) for c, t in times.items()},
        sigma_offset_ms={c: 0.0 if c == p.reference else float(t_sig[c][0]) for c in times},
        readout_ms={c: float(t[1]) for c, t in times.items()},
        sigma_readout_ms={c: float(t_sig[c][1]) for c in times},
        twist=twists,
        sigma_twist={v: np.sqrt(np.diag(marginals.marginalCovariance(p.time.twist_key[v])))
                     for v in twists},
        anchored=tuple(sorted({c for c, _ in p.time.capture_ms} & set(times))),
        capture_ms=dict(p.time.capture_ms),
        twist_prior=p.time.twist_sigma or TwistPrior(p.config.time_model.time_twist_sigma_mps,
                                                p.config.time_model.time_twist_sigma_dps),
        acceleration=p.accelerations(values),
        linked_sets=len({v for f, g, _ in p.time.links for v in (f, g)}),
        motion_prior=p.time.motion_prior,
        offset_prior_sigma_ms={c: 0.0 if c == p.reference else p.time.time_priors[c].offset_sigma_ms
                               for c in times})


def _with_prior(clock: TimeModel, p: _FactorLayout) -> TimeModel:
    """``clock`` with the twist and motion priors the final solve used."""
    return replace(clock, twist_prior=p.time.twist_sigma, motion_prior=p.time.motion_prior)


def _current_models(p: _FactorLayout, values: gtsam.Values) -> dict[str, CameraIntrinsics] | None:
    """The current camera models (refined intrinsics), None when the intrinsics are fixed."""
    if not p.refine:
        return None
    return {c: with_parameters(p.intrinsics[c], p.names, values.atVector(k))
            for c, k in p.intr_key.items() if values.exists(k)}


def _refined_intrinsics(p: _FactorLayout, values: gtsam.Values, marginals: gtsam.Marginals):
    """The refined camera models, their marginal sigmas and their prior sigmas, by parameter
    name (all empty when the intrinsics are fixed)."""
    refined = _current_models(p, values) or {}
    sigma = {c: dict(zip(lens_names(p.intrinsics[c], p.names), np.sqrt(np.diag(
        marginals.marginalCovariance(p.intr_key[c]))).tolist())) for c in refined}
    prior = {c: dict(zip(lens_names(p.intrinsics[c], p.names),
                         p.prior_intr[c].sigmas().tolist())) for c in refined}
    return refined, sigma, prior


def _residual_dof(p: _FactorLayout, n_markers: int, values: gtsam.Values) -> int:
    """Redundancy of the corner fit: 8 residuals per marker less the free parameters (6 per
    unheld pose, the intrinsics vectors, 4 for the back sheet: its tilts are held; 6 for
    each face of a multi-face target)."""
    n_intr = sum(values.exists(k) for k in p.intr_key.values())
    n_intr_params = sum(len(lens_names(p.intrinsics[c], p.names))
                        for c, k in p.intr_key.items() if values.exists(k))
    n_back = len(p.moving)
    face_params = sum(4 if A is None else 6 for _, _, A in p.moving)
    n_time = sum(values.exists(k) for k in p.time.time_key.values())
    n_twist = sum(values.exists(k) for k in p.time.twist_key.values())
    time_params = 2 * n_time - (1 if n_time else 0) + 6 * n_twist  # the reference's offset held
    return max(8 * n_markers - 6 * (values.size() - n_intr - n_back - len(p.fixed)
                                    - n_time - n_twist)
               - n_intr_params - face_params - time_params, 1)


def _camera_marginals(cams: list[str], values: gtsam.Values, cam_key: dict[str, int],
                      fixed: dict[str, np.ndarray], marginals: gtsam.Marginals):
    """Per solved camera: ``T_ref_cam``, its 6x6 marginal covariance (zeros when held) and
    the rotation (deg) / translation (mm) sigmas."""
    out_cam, cov, s_rot, s_trans = {}, {}, {}, {}
    for c in cams:
        if not values.exists(cam_key[c]):
            continue
        T = values.atPose3(cam_key[c]).matrix()
        out_cam[c] = T
        C = np.zeros((6, 6)) if c in fixed else marginals.marginalCovariance(cam_key[c])
        cov[c] = C
        s_rot[c], s_trans[c] = sigmas_from_covariance(T, C)
    return out_cam, cov, s_rot, s_trans


def _marker_residuals(groups: list[_ViewGroup], n: int, values: gtsam.Values, cam_key: dict,
                      view_key: dict, K: dict,
                      models: dict[str, CameraIntrinsics] | None = None, moves=(),
                      timing=None) -> np.ndarray:
    """The corner residuals ``uv - uv_meas`` (n, 4, 2; px) of the ``n`` active markers at
    ``values``, vectorised per camera view; through
    the full camera ``models`` when given (refined intrinsics), else the pinhole ``K``; each
    face's markers moved by its board-frame move ``C`` of ``moves`` ``(label, C)`` (board
    self-calibration); each corner at its own time with ``timing`` ``(heights, capture_ms,
    time per camera, twist per view, acceleration per linked view)`` (the time model)."""
    out = np.empty((n, 4, 2))
    for g in groups:
        T_cam = values.atPose3(cam_key[g.camera]).matrix()
        T_board = values.atPose3(view_key[g.view]).matrix()
        P_b = g.object_points.reshape(-1, 3)
        if moves:
            P_b = move_rows(P_b, [(np.repeat(g.face == label, 4), C) for label, C in moves])
        if timing is not None:
            heights, capture, times, twists, accels = timing
            known = capture.get((g.camera, g.view), 0.0)
            uv = project_timed(T_cam, T_board, twists[g.view], times[g.camera] + [known, 0.0],
                               K[g.camera] if models is None else models[g.camera], P_b,
                               row_fraction(g.corners_px.reshape(-1, 2)[:, 1], heights[g.camera]),
                               False, accel=accels.get(g.view))[0]
        elif models is not None:
            uv = project_board_full(T_cam, T_board, models[g.camera], None, P_b, jacobians=False)[0]
        else:
            uv, _, _ = project_board(T_cam, T_board, K[g.camera], P_b, jacobians=False)
        out[g.index] = uv.reshape(-1, 4, 2) - g.corners_px
    return out
