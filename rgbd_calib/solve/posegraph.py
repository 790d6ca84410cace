"""Pose-graph optimisation of camera extrinsics from board poses (GTSAM; thesis section 3.3).

The graph of the thesis (Figure 3.3): one ``Pose3`` node per camera (``T_ref_cam``) and one per
board view (``T_ref_board``); every detection of view ``v`` by camera ``c`` is a
``BetweenFactorPose3(c, v)`` whose measurement is the PnP board pose ``T_cam_board``. GTSAM's
error of that factor is ``Logmap(T_cam_board^-1 @ T_ref_cam^-1 @ T_ref_board)``: a 6-vector
``[rotation rad, translation m]`` in the body frame of the board pose, whitened by the edge
covariance (same order and frame).

The solve, step by step (:func:`solve_pose_graph`):

1. drop stale edges (a camera that missed the board re-reported its previous pose),
2. initialise from the edges alone (:func:`initialise_from_edges`, a maximum spanning tree of
   the camera co-visibility graph with robust relative poses: no hand-measured guesses),
3. robust Levenberg-Marquardt with an M-estimator (or GNC), re-estimating the default
   isotropic edge sigmas from the residuals when the edges carry no covariance,
4. reject edges whose whitened residual exceeds the kernel threshold and re-solve until the
   inlier set is stable,
5. marginal covariances on a *Gaussian* graph of the final inliers, linearised at the
   solution, so that robust down-weighting does not inflate (or shrink) the claimed sigmas;
   a camera whose views all disagree the same way (a model error, kept with its noise scaled
   by its own variance factor before step 4: :func:`_camera_model_error`) enters with its
   views' information counted once.

The initialisation and the stale-edge test are numpy only (:mod:`rgbd_calib.solve.posegraph_init`);
the bundle adjustment on the marker corners is :mod:`rgbd_calib.solve.bundle`. gtsam is imported
in :mod:`rgbd_calib.solve` only; this module does no file I/O.
"""

from __future__ import annotations

import copy
from collections import Counter, defaultdict
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np
from scipy.stats import chi2

from ..core.config import PoseGraphConfig
from ..core.errors import CalibrationError
from ..core.geometry import invert_transform, orthonormalize, rotation_angle_deg
from ..model.results import CameraExtrinsics, Extrinsics, PoseEdge
from .posegraph_init import (
    REASON_NO_SHARED_VIEW,
    flag_stale_edges,
    initialise_from_edges,
    robust_mean_pose,
    working_distance_m,
)

# Median of a chi distribution with 3 dof: median |x| of an isotropic 3D Gaussian / sigma.
_CHI3_MEDIAN = float(np.sqrt(chi2.ppf(0.5, 3)))
# Median of chi^2 with 6 dof: the median squared whitened norm of a consistent 6-dof edge.
_CHI2_6_MEDIAN = float(chi2.ppf(0.5, 6))
# pose.model_error_px auto: a floor is estimated only when the typical view's squared whitened
# residual exceeds what its corner noise allows by this factor (its sigma by ~1.2x), and it
# is at most VIEW_FLOOR_MAX_PX (beyond that the views are no calibration's)
VIEW_FLOOR_RATIO = 1.5
VIEW_FLOOR_MAX_PX = 5.0


@dataclass(frozen=True)
class EdgeResidual:
    """Residual of edge ``index`` at a solution. ``used``: in the final optimisation;
    ``whitened_norm``: Mahalanobis norm of the 6-dof error; ``weight``: kernel weight at that
    norm; ``outlier``: ``whitened_norm > kernel_threshold``; ``translation_mm`` /
    ``rotation_deg``: size of ``T_cam_board_measured^-1 @ T_cam_board_predicted``."""

    index: int
    camera: str
    view: str
    used: bool
    stale: bool
    outlier: bool
    whitened_norm: float
    weight: float
    translation_mm: float
    rotation_deg: float

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass(frozen=True)
class CameraModelError:
    """A camera whose views disagree with the rig as a whole (a model error: intrinsics, board,
    distortion, sync), kept with its edge covariances scaled by ``variance_factor``.
    ``edges``: its edges in the graph; ``outliers_before``: how many exceeded the kernel threshold
    under the nominal noise; ``translation_mm`` / ``rotation_deg``: median size of its edge
    residuals at the final solution."""

    camera: str
    variance_factor: float
    edges: int
    outliers_before: int
    translation_mm: float
    rotation_deg: float

    @property
    def sigma_factor(self) -> float:
        return float(np.sqrt(self.variance_factor))

    def to_dict(self) -> dict[str, Any]:
        return {**{k: getattr(self, k) for k in self.__dataclass_fields__},
                "sigma_factor": self.sigma_factor}


@dataclass(frozen=True)
class PoseGraphResult:
    """Solved pose graph: cameras with marginal uncertainty, board views, per-edge residuals.

    ``edges`` is the edge list the graph was solved on, as given to it (PnP covariances, no
    model-error floor): ``residuals[i]`` and every index of ``used_edges`` /
    ``stale_edges`` / ``outlier_edges`` point into it. Read the edges from here
    (:attr:`used_pose_edges`), never from a list rebuilt from later views: after the markers
    are detected again the views are not the ones this graph solved."""

    reference: str
    cameras: dict[str, CameraExtrinsics]
    T_ref_board: dict[str, np.ndarray]
    residuals: tuple[EdgeResidual, ...]
    unconnected: dict[str, str] = field(default_factory=dict)
    sigma_rotation_deg_default: float = float("nan")  # default edge sigmas finally used
    sigma_translation_mm_default: float = float("nan")
    stats: dict[str, Any] = field(default_factory=dict)
    model_error: dict[str, CameraModelError] = field(default_factory=dict)
    edges: tuple[PoseEdge, ...] = ()

    def __post_init__(self) -> None:
        if self.edges and len(self.edges) != len(self.residuals):
            raise CalibrationError(
                f"a pose-graph result with {len(self.edges)} edges but {len(self.residuals)} "
                "edge residuals: pass the edge list the graph was solved on")

    @property
    def T_ref_cam(self) -> dict[str, np.ndarray]:
        return {name: cam.T_ref_cam for name, cam in self.cameras.items()}

    @property
    def stale_edges(self) -> tuple[int, ...]:
        return tuple(r.index for r in self.residuals if r.stale)

    @property
    def outlier_edges(self) -> tuple[int, ...]:
        """Non-stale edges above the kernel threshold at the solution."""
        return tuple(r.index for r in self.residuals if r.outlier and not r.stale)

    @property
    def rejected_edges(self) -> tuple[int, ...]:
        """Outlier edges the solve left out (``reject_outliers``); with rejection off the
        outliers stay in the graph and are only flagged, so this is empty."""
        return tuple(r.index for r in self.residuals if r.outlier and not r.stale and not r.used)

    @property
    def used_edges(self) -> tuple[int, ...]:
        return tuple(r.index for r in self.residuals if r.used)

    @property
    def used_pose_edges(self) -> tuple[PoseEdge, ...]:
        """The edges of :attr:`used_edges`, from the edge list this graph was solved on."""
        if len(self.edges) != len(self.residuals):
            raise CalibrationError(
                "this pose-graph result does not carry the edges it was solved on "
                "(PoseGraphResult.edges); build it with solve_pose_graph or pass edges=")
        return tuple(self.edges[i] for i in self.used_edges)

    def to_extrinsics(self) -> Extrinsics:
        return Extrinsics(self.reference, dict(self.cameras), dict(self.unconnected))


# ---------------------------------------------------------------------------------------------
# GTSAM helpers


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    T = np.asarray(T, dtype=float)
    return gtsam.Pose3(gtsam.Rot3(orthonormalize(T[:3, :3])), gtsam.Point3(*T[:3, 3]))


def _kernel(config: PoseGraphConfig):
    """The GTSAM M-estimator of ``config.kernel`` with parameter ``kernel_threshold``."""
    if config.kernel == "none":
        return None
    m = gtsam.noiseModel.mEstimator
    factory = {"huber": m.Huber, "cauchy": m.Cauchy, "tukey": m.Tukey, "gm": m.GemanMcClure}
    return factory[config.kernel].Create(config.kernel_threshold)


def _kernel_weight(kernel, r: float) -> float:
    return 1.0 if kernel is None else float(kernel.weight(r))


class _EdgeNoise:
    """Gaussian noise model per edge: its own covariance, else the current default sigmas,
    times its camera's model-error variance factor (``camera_factor``, 1 when absent). The
    factor scales the corner-noise part; an edge's per-view model-error floor
    (``PoseEdge.model_error_covariance``) is added unscaled, or left out by the copy
    :meth:`without_floor` (the camera model-error test: a camera whose views all disagree
    the same way must still be found, and the floor would hide it)."""

    def __init__(self, edges: list[PoseEdge], config: PoseGraphConfig):
        self.edges = edges
        self.sigma_rot = float(np.radians(config.default_sigma_rotation_deg))
        self.sigma_trans = float(config.default_sigma_translation_mm) / 1000.0
        self.camera_factor: dict[str, float] = {}
        self.floor = True
        self._cache: dict[tuple[int, float], Any] = {}

    def forget(self) -> None:
        """Drop the models made so far: the edges' covariances changed."""
        self._cache.clear()

    def without_floor(self) -> _EdgeNoise:
        """A copy whose models leave out the per-view floor (``camera_factor`` shared)."""
        out = copy.copy(self)
        out.floor, out._cache = False, {}
        return out

    def default(self, factor: float = 1.0):
        return gtsam.noiseModel.Diagonal.Sigmas(
            np.sqrt(factor) * np.array([self.sigma_rot] * 3 + [self.sigma_trans] * 3)
        )

    def correlated(self, ids: list[int]) -> _EdgeNoise:
        """A copy for the marginals where each model-error camera's factor is also multiplied
        by its number of edges among ``ids``: its model error is common to all its views, so
        their information counts once (fully correlated errors do not average down), and the
        marginals of every camera chained through it inherit that."""
        out = copy.copy(self)
        count = Counter(self.edges[i].camera for i in ids)
        out.camera_factor = {c: f * max(count[c], 1) for c, f in self.camera_factor.items()}
        return out

    def models(self, ids: list[int]) -> dict[int, Any]:
        out = {}
        for i in ids:
            e = self.edges[i]
            f = self.camera_factor.get(e.camera, 1.0)
            if e.covariance is None:
                out[i] = self.default(f)
                continue
            if (i, f) not in self._cache:
                cov = np.asarray(e.covariance, float)
                if e.model_error_covariance is not None:
                    floor = np.asarray(e.model_error_covariance, float)
                    cov = f * (cov - floor) + (floor if self.floor else 0.0)
                else:
                    cov = f * cov
                self._cache[(i, f)] = gtsam.noiseModel.Gaussian.Covariance(cov)
            out[i] = self._cache[(i, f)]
        return out


def _lm(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, config: PoseGraphConfig
) -> tuple[gtsam.Values, int]:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    params.setAbsoluteErrorTol(1e-14)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    return result, int(optimizer.iterations())


class _Graph:
    """Keys, values and factor construction for one pose-graph problem."""

    def __init__(self, edges, fixed, T_ref_cam, T_ref_board, config):
        self.edges, self.fixed, self.config = edges, fixed, config
        self.cam_key = {c: gtsam.symbol("c", i) for i, c in enumerate(T_ref_cam)}
        self.view_key = {v: gtsam.symbol("v", i) for i, v in enumerate(T_ref_board)}
        self.values = gtsam.Values()
        for c, T in T_ref_cam.items():
            self.values.insert(self.cam_key[c], _pose3(T))
        for v, T in T_ref_board.items():
            self.values.insert(self.view_key[v], _pose3(T))
        self.kernel = _kernel(config)
        self._measured: dict[int, gtsam.Pose3] = {}  # edge -> its Pose3, made once

    def priors(self) -> list[gtsam.NonlinearFactor]:
        noise = gtsam.noiseModel.Isotropic.Sigma(6, self.config.prior_sigma)
        return [
            gtsam.PriorFactorPose3(self.cam_key[c], _pose3(T), noise) for c, T in self.fixed.items()
        ]

    def factor(self, i: int, noise) -> gtsam.BetweenFactorPose3:
        e = self.edges[i]
        if i not in self._measured:  # the robust solve builds each factor many times
            self._measured[i] = _pose3(e.T_cam_board)
        return gtsam.BetweenFactorPose3(
            self.cam_key[e.camera], self.view_key[e.view], self._measured[i], noise
        )

    def build(self, ids: list[int], noise: _EdgeNoise, robust: bool) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        for f in self.priors():
            graph.add(f)
        for i, model in noise.models(ids).items():
            if robust and self.kernel is not None:
                model = gtsam.noiseModel.Robust.Create(self.kernel, model)
            graph.add(self.factor(i, model))
        return graph

    def errors(
        self, ids: list[int], noise: _EdgeNoise, values: gtsam.Values
    ) -> tuple[np.ndarray, np.ndarray]:
        """Unwhitened ``(N,6)`` errors ``[rot, trans]`` and whitened norms ``(N,)``."""
        raw, white = np.zeros((len(ids), 6)), np.zeros(len(ids))
        for row, (i, model) in enumerate(noise.models(ids).items()):
            f = self.factor(i, model)
            raw[row] = f.unwhitenedError(values)
            white[row] = np.linalg.norm(model.whiten(raw[row]))
        return raw, white


def _connected_to(
    reference: str, edges: list[PoseEdge], ids: list[int], fixed: set[str]
) -> set[str]:
    """Cameras linked to the reference (or a fixed camera) through views with >= 2 edges."""
    by_view: dict[str, set[str]] = defaultdict(set)
    for i in ids:
        by_view[edges[i].view].add(edges[i].camera)
    neighbours: dict[str, set[str]] = defaultdict(set)
    for cams in by_view.values():
        for c in cams:
            neighbours[c] |= cams
    seen, stack = {reference} | fixed, [reference, *fixed]
    while stack:
        for n in neighbours[stack.pop()] - seen:
            seen.add(n)
            stack.append(n)
    return seen


def _estimate_sigmas(
    raw: np.ndarray, dof_fraction: float, floor: tuple[float, float]
) -> tuple[float, float]:
    """Robust per-axis sigmas (rad, m) from residuals of edges with default noise: for an
    isotropic 3D Gaussian ``median |e| = 1.538 sigma``; residuals are shrunk by the fit, so
    divide by ``sqrt(dof / n_measurements)``."""
    scale = _CHI3_MEDIAN * np.sqrt(dof_fraction)
    sigma_rot = float(np.median(np.linalg.norm(raw[:, :3], axis=1))) / scale
    sigma_trans = float(np.median(np.linalg.norm(raw[:, 3:], axis=1))) / scale
    return max(sigma_rot, floor[0]), max(sigma_trans, floor[1])


def _residual_size(
    T_ref_cam: np.ndarray, T_ref_board: np.ndarray, T_cam_board: np.ndarray
) -> tuple[float, float]:
    """(translation mm, rotation deg) of ``T_cam_board^-1 @ T_ref_cam^-1 @ T_ref_board``."""
    delta = invert_transform(T_cam_board) @ invert_transform(T_ref_cam) @ T_ref_board
    return float(np.linalg.norm(delta[:3, 3]) * 1000.0), rotation_angle_deg(delta[:3, :3])


def sigmas_from_covariance(T_ref_cam: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """1-sigma along the worst axis: rotation (deg) from the 3x3 rotation block; translation
    (mm) from the body-frame 3x3 translation block rotated into the reference frame,
    ``R_ref_cam @ S_tt @ R_ref_cam^T`` (a rotation keeps the eigenvalues, so this equals the
    body-frame value; the rotation documents the frame)."""
    R = T_ref_cam[:3, :3]
    rot = float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))
    trans = float(np.sqrt(max(np.linalg.eigvalsh(R @ cov[3:, 3:] @ R.T).max(), 0.0)))
    return float(np.degrees(rot)), trans * 1000.0


# ---------------------------------------------------------------------------------------------
# Solver


def solve_pose_graph(
    edges: list[PoseEdge],
    reference: str,
    init_T_ref_cam: dict[str, np.ndarray],
    init_T_ref_board: dict[str, np.ndarray],
    config: PoseGraphConfig | None = None,
    fixed_cameras: dict[str, np.ndarray] | None = None,
) -> PoseGraphResult:
    """Optimise ``T_ref_cam`` (per camera) and ``T_ref_board`` (per view), 4x4 in metres.

    Edges whose camera or view has no initial pose, views with fewer than two usable edges
    and (by default) stale edges are left out and reported with ``used=False``. The reference
    camera is held at the identity and each ``fixed_cameras[c]`` (``T_ref_cam``) at its pose
    by priors of ``config.prior_sigma``.

    Uncertainty: GTSAM ``Marginals`` of a graph with the final inlier edges under their plain
    Gaussian noise models (no robust kernel), linearised at the solution. Robust weights below
    one would otherwise scale the information of inliers down (Cauchy, GM at every residual)
    and inflate the sigmas; rejected edges would add no information anyway. With kernel
    ``'none'`` and no rejection every used edge enters. Per camera the result reports the 6x6
    body-frame covariance ``[rot rad, trans m]`` and the worst-axis 1-sigmas, see
    :func:`sigmas_from_covariance`."""
    config = config or PoseGraphConfig()
    given = tuple(edges)  # as given: the floor below replaces edges in the working list
    edges = list(given)
    fixed = {reference: np.eye(4)}
    for c, T in (fixed_cameras or {}).items():
        if c == reference and not np.allclose(T, np.eye(4), atol=1e-12):
            raise CalibrationError(
                f"the reference camera {reference!r} is the identity by definition; "
                "do not fix it elsewhere"
            )
        fixed[c] = np.asarray(T, dtype=float)
    init_cams = {**{c: np.asarray(T, float) for c, T in init_T_ref_cam.items()}, **fixed}
    stale = flag_stale_edges(edges)

    # 1. usable edges: initialised ends, not stale, on views seen twice, linked to the reference
    ids, cams = _usable_edges(
        edges,
        reference,
        init_cams,
        init_T_ref_board,
        stale if config.exclude_stale else set(),
        set(fixed),
    )
    views = list(dict.fromkeys(edges[i].view for i in ids))
    problem = _Graph(
        edges,
        fixed,
        {c: init_cams[c] for c in cams},
        {v: np.asarray(init_T_ref_board[v], float) for v in views},
        config,
    )
    noise = _EdgeNoise(edges, config)
    n_free = len(views) + len([c for c in cams if c not in fixed])

    # 2.-3. robust solve, default sigmas from the residuals, reject and re-solve
    values, used, stats = _robust_solve(problem, ids, noise, n_free, config)

    # 4. residuals of every edge at the solution
    _, white = problem.errors(ids, noise, values)
    white_of = dict(zip(ids, white, strict=True))
    T_ref_cam = {c: values.atPose3(problem.cam_key[c]).matrix() for c in cams}
    T_ref_board = {v: values.atPose3(problem.view_key[v]).matrix() for v in views}
    residuals = _residual_table(
        edges, T_ref_cam, T_ref_board, white_of, set(used), stale, problem.kernel, config
    )

    # 5. marginals on the Gaussian graph of the inliers, at the solution
    if config.kernel == "none" and not config.reject_outliers:
        inlier_ids = used
    else:
        inlier_ids = [i for i in used if white_of[i] <= config.kernel_threshold]
    covariances = _marginals(problem, inlier_ids, noise.correlated(inlier_ids), values, cams)
    dof = 6 * len(inlier_ids) - 6 * n_free
    chi2_sum = float(np.sum(np.square([white_of[i] for i in inlier_ids])))
    stats.update(
        edges_total=len(edges),
        edges_stale=len(stale),
        edges_candidate=len(ids),
        edges_used=len(used),
        edges_inlier=len(inlier_ids),
        edges_outlier=sum(1 for i in ids if white_of[i] > config.kernel_threshold),
        views=len(views),
        final_error=float(problem.build(used, noise, True).error(values)),
        variance_factor=chi2_sum / dof if dof > 0 else float("nan"),
    )
    unconnected = {
        c: REASON_NO_SHARED_VIEW for c in dict.fromkeys(e.camera for e in edges) if c not in cams
    }
    model_error = _model_error_table(
        residuals, noise.camera_factor, stats.pop("model_error_outliers", {})
    )
    return PoseGraphResult(
        reference,
        _camera_results(reference, T_ref_cam, covariances),
        T_ref_board,
        residuals,
        unconnected,
        float(np.degrees(noise.sigma_rot)),
        noise.sigma_trans * 1000.0,
        stats,
        model_error,
        edges=given,
    )


def _model_error_table(
    residuals: tuple[EdgeResidual, ...], factors: dict[str, float], before: dict[str, int]
) -> dict[str, CameraModelError]:
    """One :class:`CameraModelError` per camera with a variance factor above one."""
    out = {}
    for c, f in factors.items():
        if f <= 1.0:
            continue
        mine = [r for r in residuals if r.camera == c and np.isfinite(r.whitened_norm)]
        out[c] = CameraModelError(
            c,
            float(f),
            len(mine),
            int(before.get(c, 0)),
            float(np.median([r.translation_mm for r in mine])) if mine else float("nan"),
            float(np.median([r.rotation_deg for r in mine])) if mine else float("nan"),
        )
    return out


def _usable_edges(
    edges: list[PoseEdge],
    reference: str,
    init_cams: dict[str, np.ndarray],
    init_boards: dict[str, np.ndarray],
    excluded: set[int],
    fixed: set[str],
) -> tuple[list[int], list[str]]:
    """Edge indices to optimise and the cameras they connect (the reference and fixed ones
    included). Repeats until stable: dropping a camera can leave a view with one edge."""
    ids = [
        i
        for i, e in enumerate(edges)
        if i not in excluded and e.camera in init_cams and e.view in init_boards
    ]
    while True:
        per_view = Counter(edges[i].view for i in ids)
        linked = _connected_to(reference, edges, ids, fixed)
        kept = [i for i in ids if per_view[edges[i].view] >= 2 and edges[i].camera in linked]
        if kept == ids:
            break
        ids = kept
    if not ids:
        raise CalibrationError(
            "no board view is seen by two connected cameras; nothing to optimise "
            "(check the edges and the reference camera)"
        )
    return ids, [c for c in init_cams if c in linked]


def _robust_solve(
    problem: _Graph, ids: list[int], noise: _EdgeNoise, n_free: int, config: PoseGraphConfig
) -> tuple[gtsam.Values, list[int], dict[str, Any]]:
    """Robust LM (after GNC if asked); default sigmas re-estimated twice from the residuals;
    then reject / re-solve rounds. Returns the values, the edges of the last solve, stats."""
    stats: dict[str, Any] = {"iterations": 0, "reject_rounds": 0}
    values = problem.values
    if config.optimizer == "gnc":
        values, stats["gnc_outliers"] = _gnc(problem, ids, noise, values, config)
    values, stats["iterations"] = _lm(problem.build(ids, noise, robust=True), values, config)

    default_ids = [i for i in ids if problem.edges[i].covariance is None]
    if config.estimate_default_sigmas and default_ids:
        dof_fraction = max(1.0 - n_free / len(ids), 0.2)
        floor = (1e-3 * noise.sigma_rot, 1e-3 * noise.sigma_trans)
        for _ in range(2):
            raw, _ = problem.errors(default_ids, noise, values)
            noise.sigma_rot, noise.sigma_trans = _estimate_sigmas(raw, dof_fraction, floor)
            values, it = _lm(problem.build(ids, noise, robust=True), values, config)
            stats["iterations"] += it

    if any(problem.edges[i].model_error_unit is not None for i in ids):
        values, it, stats["view_floor"] = _estimate_view_floor(problem, ids, noise, values,
                                                                n_free, config)
        stats["iterations"] += it

    if config.camera_model_error:
        values, it, stats["model_error_outliers"] = _camera_model_error(
            problem, ids, noise, values, config
        )
        stats["iterations"] += it

    used = ids
    if config.reject_outliers:
        for _ in range(config.max_reject_rounds):
            _, white = problem.errors(ids, noise, values)
            inliers = [i for i, r in zip(ids, white, strict=True) if r <= config.kernel_threshold]
            if inliers == used:
                break
            used = inliers
            stats["reject_rounds"] += 1
            values, it = _lm(problem.build(used, noise, robust=True), values, config)
            stats["iterations"] += it
    return values, used, stats


def _estimate_view_floor(
    problem: _Graph,
    ids: list[int],
    noise: _EdgeNoise,
    values: gtsam.Values,
    n_free: int,
    config: PoseGraphConfig,
) -> tuple[gtsam.Values, int, dict[str, float]]:
    """Estimate the per-view model-error floor (``pose.model_error_px: auto``) and add it to
    the edges that carry its unit covariance (``PoseEdge.model_error_unit``).

    A variance component: each view's covariance is its corner noise ``C`` plus ``s^2 U``, the
    floor of a model error of ``s`` px shared by its corners (:func:`pose.model_error_covariance`).
    At the robust solution of the graph without it, the typical view's squared whitened
    residual ``median(r^2)`` is compared with what its corner noise allows,
    ``chi2_6 median * (1 - free poses / edges)`` (the view poses absorb part of each edge's
    six degrees of freedom). When it exceeds that by more than :data:`VIEW_FLOOR_RATIO`
    (the views disagree beyond their corner noise: intrinsics, distortion, a marker bias, a
    rolling shutter), ``s`` is set so that the median is the allowed one; else the floor is
    0 and nothing changes (renders, whose views agree within their corner noise). The median
    makes it the *typical* view's misfit: a few bad views are the outlier test's, and a
    camera whose every view is off is the camera model-error test's, which whitens without
    the floor (it runs after this, so no camera factor scales ``C`` here). Edges are
    replaced in ``problem.edges`` (shared with ``noise``); the graph is re-solved with the
    floor when one was set.

    Returns the values, LM iterations and ``{"model_error_px": s, "misfit_ratio": median /
    allowed at s = 0, "edges": edges judged}``."""
    judged = [i for i in ids if problem.edges[i].model_error_unit is not None
              and problem.edges[i].covariance is not None]
    if not judged:
        return values, 0, {"model_error_px": 0.0, "misfit_ratio": float("nan"), "edges": 0}
    raw, _ = problem.errors(judged, noise, values)
    C = np.stack([np.asarray(problem.edges[i].covariance, float) for i in judged])
    U = np.stack([np.asarray(problem.edges[i].model_error_unit, float) for i in judged])
    allowed = _CHI2_6_MEDIAN * max(1.0 - n_free / len(ids), 0.2)

    def typical(s2: float) -> float:
        w = np.linalg.solve(C + s2 * U, raw[..., None])[..., 0]
        return float(np.median(np.einsum("ni,ni->n", raw, w)))

    ratio = typical(0.0) / allowed
    out = {"model_error_px": 0.0, "misfit_ratio": ratio, "edges": len(judged)}
    if not ratio > VIEW_FLOOR_RATIO:
        return values, 0, out
    lo, hi = 0.0, 0.01
    while typical(hi) > allowed and hi < VIEW_FLOOR_MAX_PX**2:
        lo, hi = hi, 4.0 * hi
    for _ in range(40):  # bisection on s^2: the median falls monotonically as s grows
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if typical(mid) > allowed else (lo, mid)
    s2 = min(hi, VIEW_FLOOR_MAX_PX**2)
    for i in judged:
        e = problem.edges[i]
        floor = s2 * np.asarray(e.model_error_unit, float)
        problem.edges[i] = replace(e, covariance=np.asarray(e.covariance, float) + floor,
                                   model_error_covariance=floor)
    noise.forget()
    values, it = _lm(problem.build(ids, noise, robust=True), values, config)
    out["model_error_px"] = float(np.sqrt(s2))
    return values, it, out


def _camera_model_error(
    problem: _Graph,
    ids: list[int],
    noise: _EdgeNoise,
    values: gtsam.Values,
    config: PoseGraphConfig,
    rounds: int = 4,
) -> tuple[gtsam.Values, int, dict[str, int]]:
    """Find the cameras with a model error and scale their edge noise (``noise.camera_factor``).

    The rule: a camera whose *median* whitened edge residual (whitened without the per-view
    model-error floor, which would hide exactly this) exceeds ``kernel_threshold`` has
    most of its views outside the threshold. Outlier rejection is for the few views that
    disagree with the others of their camera (blur, a wrong detection, a sync glitch); when
    the typical view disagrees, rejecting would remove the camera, and what disagrees is the
    camera's model (intrinsics, distortion, the board's back sheet, time offset). Such a
    camera keeps its views; its edge covariances are multiplied by its own robust
    a-posteriori variance factor ``median(r^2) / median(chi2_6)`` (the median: a single bad
    view does not set it), so its whitened residuals become chi2-consistent again and the
    usual rejection can then still drop its single outlier views. Re-solved and re-tested
    until no camera is flagged (factors multiply); the median over a camera's edges is
    measured at the robust solution of the whole graph, so one camera cannot hide another.

    The test is made on the graph without the per-view model-error floor, solved so (the
    floor would hide a camera-wide misfit, and residuals of the floor's solve judged without
    it would flag sound cameras; measured: docs/accuracy.md, 'Measurements behind the
    solver's design'); the returned values are the solve with the floor and the factors found.

    Returns the values, LM iterations and, per flagged camera, its outlier count before."""
    iterations, before = 0, {}
    plain = noise.without_floor()
    has_floor = any(problem.edges[i].model_error_covariance is not None for i in ids)
    plain_values = values
    for _ in range(rounds):
        if has_floor:
            plain_values, it = _lm(problem.build(ids, plain, robust=True), plain_values, config)
            iterations += it
        _, white = problem.errors(ids, plain, plain_values)
        per_camera: dict[str, list[float]] = defaultdict(list)
        for i, r in zip(ids, white, strict=True):
            per_camera[problem.edges[i].camera].append(float(r))
        flagged = {
            c: float(np.median(np.square(r))) / _CHI2_6_MEDIAN
            for c, r in per_camera.items()
            if len(r) >= config.model_error_min_views
            and float(np.median(r)) > config.kernel_threshold
        }
        if not flagged:
            break
        for c, factor in flagged.items():
            before.setdefault(c, sum(1 for r in per_camera[c] if r > config.kernel_threshold))
            noise.camera_factor[c] = noise.camera_factor.get(c, 1.0) * factor
        if not has_floor:
            plain_values, it = _lm(problem.build(ids, noise, robust=True), plain_values, config)
            iterations += it
    if has_floor and before:
        values, it = _lm(problem.build(ids, noise, robust=True), values, config)
        iterations += it
    elif not has_floor:
        values = plain_values
    return values, iterations, before


def _residual_table(
    edges: list[PoseEdge],
    T_ref_cam: dict[str, np.ndarray],
    T_ref_board: dict[str, np.ndarray],
    white_of: dict[int, float],
    used: set[int],
    stale: set[int],
    kernel,
    config: PoseGraphConfig,
) -> tuple[EdgeResidual, ...]:
    """One :class:`EdgeResidual` per edge; whitened norm NaN (weight 0) for edges not in the
    graph, sizes NaN when the camera or the view has no pose."""
    rows = []
    for i, e in enumerate(edges):
        in_graph = i in white_of
        r = float(white_of[i]) if in_graph else float("nan")
        if e.camera in T_ref_cam and e.view in T_ref_board:
            mm, deg = _residual_size(T_ref_cam[e.camera], T_ref_board[e.view], e.T_cam_board)
        else:
            mm, deg = float("nan"), float("nan")
        rows.append(
            EdgeResidual(
                index=i,
                camera=e.camera,
                view=e.view,
                used=i in used,
                stale=i in stale,
                outlier=in_graph and r > config.kernel_threshold,
                whitened_norm=r,
                weight=_kernel_weight(kernel, r) if in_graph else 0.0,
                translation_mm=mm,
                rotation_deg=deg,
            )
        )
    return tuple(rows)


def _camera_results(
    reference: str, T_ref_cam: dict[str, np.ndarray], covariances: dict[str, np.ndarray]
) -> dict[str, CameraExtrinsics]:
    """CameraExtrinsics with marginal sigmas; the reference is the gauge, exact by definition
    (zero covariance); a camera without a marginal gets NaN sigmas."""
    out = {}
    for c, T in T_ref_cam.items():
        if c == reference:
            out[c] = CameraExtrinsics(c, np.eye(4), 0.0, 0.0, np.zeros((6, 6)))
        elif c in covariances:
            out[c] = CameraExtrinsics(
                c, T, *sigmas_from_covariance(T, covariances[c]), covariances[c]
            )
        else:
            out[c] = CameraExtrinsics(c, T)
    return out


def _gnc(
    problem: _Graph,
    ids: list[int],
    noise: _EdgeNoise,
    values: gtsam.Values,
    config: PoseGraphConfig,
) -> tuple[gtsam.Values, int]:
    """Graduated non-convexity (Yang et al., RA-L 2020) via GTSAM's ``GncLMOptimizer`` on the
    Gaussian graph; the priors are declared known inliers. The inlier threshold is the factor
    error ``0.5 k^2`` (GTSAM's ``barcSq``) so it matches ``kernel_threshold``."""
    graph = problem.build(ids, noise, robust=False)
    params = gtsam.GncLMParams()
    params.setLossType(gtsam.GncLossType.GM if config.gnc_loss == "gm" else gtsam.GncLossType.TLS)
    params.setKnownInliers(list(range(len(problem.fixed))))
    optimizer = gtsam.GncLMOptimizer(graph, values, params)
    optimizer.setInlierCostThresholds(0.5 * config.kernel_threshold**2)
    result = optimizer.optimize()
    weights = np.asarray(optimizer.getWeights())[len(problem.fixed) :]
    return result, int(np.sum(weights < 0.5))


def _marginals(
    problem: _Graph, ids: list[int], noise: _EdgeNoise, values: gtsam.Values, cams: list[str]
) -> dict[str, np.ndarray]:
    """6x6 body-frame marginal covariance of each camera (NaN-free or missing)."""
    graph = problem.build(ids, noise, robust=False)
    keys = set(graph.keyVector())
    subset = gtsam.Values()
    for key in keys:
        subset.insert(key, values.atPose3(key))
    try:
        marginals = gtsam.Marginals(graph, subset)
    except RuntimeError:  # indeterminant system: a camera lost all its inlier edges
        return {}
    return {
        c: np.asarray(marginals.marginalCovariance(problem.cam_key[c]))
        for c in cams
        if problem.cam_key[c] in keys
    }


def calibrate_pose_graph(
    edges: list[PoseEdge],
    reference: str,
    config: PoseGraphConfig | None = None,
    fixed_cameras: dict[str, np.ndarray] | None = None,
) -> PoseGraphResult:
    """Initialise from the edges (:func:`initialise_from_edges`) and solve
    (:func:`solve_pose_graph`); cameras that cannot be chained to the reference are reported
    in ``result.unconnected``."""
    init_cam, init_board, unconnected = initialise_from_edges(edges, reference)
    result = solve_pose_graph(edges, reference, init_cam, init_board, config, fixed_cameras)
    merged = {**result.unconnected, **unconnected}
    return replace(result, unconnected=merged)


def refit_board_nodes(
    edges: list[PoseEdge],
    T_ref_cam: dict[str, np.ndarray],
    config: PoseGraphConfig | None = None,
) -> tuple[EdgeResidual, ...]:
    """Residuals of every edge after optimising only the board views, cameras held at
    ``T_ref_cam`` (4x4, metres).

    With the camera fixed, ``BetweenFactorPose3(c, v, T_cam_board)`` equals a
    ``PriorFactorPose3(v, T_ref_cam @ T_cam_board)`` with the same body-frame noise, so each
    view is a robust average of its cameras' predictions. Same kernel, threshold and default
    sigmas as ``config`` (no sigma re-estimation, no rejection); stale edges are left out when
    ``config.exclude_stale``; views with fewer than two usable edges are not refitted. Used to
    compare camera sets (ours vs. a published result) on the same footing."""
    config = config or PoseGraphConfig()
    edges = list(edges)
    stale = flag_stale_edges(edges)
    excluded = stale if config.exclude_stale else set()
    ids = [i for i, e in enumerate(edges) if i not in excluded and e.camera in T_ref_cam]
    per_view = Counter(edges[i].view for i in ids)
    ids = [i for i in ids if per_view[edges[i].view] >= 2]
    length_m = working_distance_m([edges[i] for i in ids])
    noise = _EdgeNoise(edges, config)
    models = noise.models(ids)
    kernel = _kernel(config)
    view_key = {
        v: gtsam.symbol("v", n) for n, v in enumerate(dict.fromkeys(edges[i].view for i in ids))
    }
    predicted = {i: T_ref_cam[edges[i].camera] @ edges[i].T_cam_board for i in ids}
    by_view: dict[str, list[int]] = defaultdict(list)
    for i in ids:
        by_view[edges[i].view].append(i)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    factors = {}
    for v, members in by_view.items():
        values.insert(
            view_key[v],
            _pose3(robust_mean_pose(np.stack([predicted[i] for i in members]), length_m)),
        )
        for i in members:
            factors[i] = gtsam.PriorFactorPose3(view_key[v], _pose3(predicted[i]), models[i])
            model = (
                models[i] if kernel is None else gtsam.noiseModel.Robust.Create(kernel, models[i])
            )
            graph.add(gtsam.PriorFactorPose3(view_key[v], _pose3(predicted[i]), model))
    if ids:
        values, _ = _lm(graph, values, config)
    white_of = {
        i: float(np.linalg.norm(models[i].whiten(f.unwhitenedError(values))))
        for i, f in factors.items()
    }
    T_ref_board = {v: values.atPose3(key).matrix() for v, key in view_key.items()}
    return _residual_table(
        edges, T_ref_cam, T_ref_board, white_of, set(factors), stale, kernel, config
    )


def median_edge_residual(
    residuals: tuple[EdgeResidual, ...] | list[EdgeResidual], used_only: bool = True
) -> tuple[float, float]:
    """Median (translation mm, rotation deg) over the used (or all finite) edge residuals."""
    chosen = [r for r in residuals if (r.used or not used_only) and np.isfinite(r.translation_mm)]
    if not chosen:
        return float("nan"), float("nan")
    return (
        float(np.median([r.translation_mm for r in chosen])),
        float(np.median([r.rotation_deg for r in chosen])),
    )
