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

This is the only module of the package that imports gtsam; it does no file I/O.
"""

from __future__ import annotations

import copy
from collections import Counter, defaultdict
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np
from scipy.stats import chi2

from ..core.camera import (
    DISTORTION_LENGTHS,
    DISTORTION_NAMES,
    CameraIntrinsics,
    pinhole_pose_jacobian,
    project_pinhole,
)
from ..core.config import BundleConfig, PoseGraphConfig
from ..core.errors import CalibrationError
from ..core.geometry import (
    adjoint,
    invert_transform,
    make_transform,
    matrix_to_rotvec,
    move_rows,
    orthonormalize,
    rotation_angle_deg,
    skew,
    transform_points,
)
from ..model.results import CameraExtrinsics, Extrinsics, PoseEdge

# Median of a chi distribution with 3 dof: median |x| of an isotropic 3D Gaussian / sigma.
_CHI3_MEDIAN = float(np.sqrt(chi2.ppf(0.5, 3)))
# Median of chi^2 with 6 dof: the median squared whitened norm of a consistent 6-dof edge.
_CHI2_6_MEDIAN = float(chi2.ppf(0.5, 6))
# pose.model_error_px auto: a floor is estimated only when the typical view's squared whitened
# residual exceeds what its corner noise allows by this factor (its sigma by ~1.2x), and it
# is at most VIEW_FLOOR_MAX_PX (beyond that the views are no calibration's)
VIEW_FLOOR_RATIO = 1.5
VIEW_FLOOR_MAX_PX = 5.0
REASON_NO_SHARED_VIEW = "shares no board view with any connected camera"


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
    """Solved pose graph: cameras with marginal uncertainty, board views, per-edge residuals."""

    reference: str
    cameras: dict[str, CameraExtrinsics]
    T_ref_board: dict[str, np.ndarray]
    residuals: tuple[EdgeResidual, ...]
    unconnected: dict[str, str] = field(default_factory=dict)
    sigma_rotation_deg_default: float = float("nan")  # default edge sigmas finally used
    sigma_translation_mm_default: float = float("nan")
    stats: dict[str, Any] = field(default_factory=dict)
    model_error: dict[str, CameraModelError] = field(default_factory=dict)

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

    def to_extrinsics(self) -> Extrinsics:
        return Extrinsics(self.reference, dict(self.cameras), dict(self.unconnected))


# ---------------------------------------------------------------------------------------------
# Stale edges and initialisation (numpy only)


def flag_stale_edges(edges: list[PoseEdge]) -> set[int]:
    """Indices of edges whose ``T_cam_board`` equals the same camera's previous edge exactly.

    The thesis recorder re-used the last detected pose when a camera missed the board, so such
    a row is not a measurement of its view. Order matters: "previous" is list (file) order."""
    stale: set[int] = set()
    previous: dict[str, np.ndarray] = {}
    for i, edge in enumerate(edges):
        T = np.asarray(edge.T_cam_board, dtype=float)
        last = previous.get(edge.camera)
        if last is not None and np.array_equal(T, last):
            stale.add(i)
        previous[edge.camera] = T
    return stale


def _pose_distances(T: np.ndarray, length_m: float) -> np.ndarray:
    """Pairwise distance of poses ``(N,4,4)``: ``|t_i - t_j| + length_m * angle(R_i^T R_j)``,
    i.e. how far a point ``length_m`` in front of the frame moves (metres)."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    cos = (np.einsum("iab,jab->ij", R, R) - 1.0) / 2.0
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    return np.linalg.norm(t[:, None] - t[None], axis=-1) + length_m * angle


def robust_mean_pose(T: np.ndarray, length_m: float = 1.0) -> np.ndarray:
    """Robust mean of pose estimates ``(N,4,4)`` of the same ``T_a_b``.

    The medoid (the estimate with the smallest median :func:`_pose_distances` to the others)
    is robust to < 50% gross outliers; the result is the chordal mean (SVD-projected sum of
    rotations, mean translation) of the estimates within 3x the median distance to the medoid,
    which recovers the averaging efficiency of a mean on the inliers."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    if len(T) <= 2:
        return T[0].copy()
    d = _pose_distances(T, length_m)
    medoid = int(np.argmin(np.median(d, axis=1)))
    to_medoid = d[medoid]
    keep = to_medoid <= 3.0 * np.median(to_medoid) + 1e-12
    out = np.eye(4)
    out[:3, :3] = orthonormalize(T[keep, :3, :3].sum(axis=0))
    out[:3, 3] = T[keep, :3, 3].mean(axis=0)
    return out


def _observations(edges: list[PoseEdge], skip: set[int]) -> dict[str, dict[str, np.ndarray]]:
    """view -> camera -> T_cam_board (first edge of a camera/view pair wins)."""
    obs: dict[str, dict[str, np.ndarray]] = defaultdict(dict)
    for i, e in enumerate(edges):
        if i not in skip:
            obs[e.view].setdefault(e.camera, np.asarray(e.T_cam_board, dtype=float))
    return obs


def _working_distance_m(edges: list[PoseEdge]) -> float:
    if not edges:
        return 1.0
    return max(float(np.median([np.linalg.norm(e.T_cam_board[:3, 3]) for e in edges])), 0.1)


def initialise_from_edges(
    edges: list[PoseEdge], reference: str
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, str]]:
    """Initial ``T_ref_cam`` and ``T_ref_board`` (4x4, metres) from the edges alone.

    1. Co-visibility graph of the cameras: weight of (a, b) = number of board views both see
       (stale edges ignored).
    2. Maximum spanning tree grown from ``reference`` (Prim; ties broken by camera order).
    3. Each tree edge gets ``T_camA_camB = robust_mean_pose({T_camA_board_v @ T_board_v_camB})``
       over the shared views (medoid + trimmed chordal mean, see :func:`robust_mean_pose`),
       and the poses are chained from the reference.
    4. A board view is initialised with the robust mean of ``T_ref_cam @ T_cam_board`` over its
       connected cameras when three or more see it, else from the one closest to the
       reference in the tree.

    Returns ``(init_T_ref_cam, init_T_ref_board, unconnected)`` where ``unconnected`` maps a
    camera that cannot be chained to the reference to the reason."""
    stale = flag_stale_edges(edges)
    obs = _observations(edges, stale)
    cameras = list(dict.fromkeys(e.camera for e in edges))
    if reference not in cameras:
        raise CalibrationError(
            f"reference camera {reference!r} has no board observation; pick a camera that saw "
            "the board"
        )
    order = {c: i for i, c in enumerate(cameras)}
    shared: dict[tuple[str, str], list[str]] = defaultdict(list)
    for view, seen in obs.items():
        names = sorted(seen, key=order.__getitem__)
        for ia, a in enumerate(names):
            for b in names[ia + 1 :]:
                shared[(a, b)].append(view)
                shared[(b, a)].append(view)
    length_m = _working_distance_m([e for i, e in enumerate(edges) if i not in stale])

    T_ref_cam = {reference: np.eye(4)}
    depth = {reference: 0}
    while True:  # Prim: the heaviest edge from the tree to a camera outside it
        frontier = [
            (len(shared[(a, b)]), -order[a], -order[b], a, b)
            for a in T_ref_cam
            for b in cameras
            if b not in T_ref_cam and (a, b) in shared
        ]
        if not frontier:
            break
        *_, a, b = max(frontier)
        T_a_b = robust_mean_pose(
            np.stack([obs[v][a] @ invert_transform(obs[v][b]) for v in shared[(a, b)]]), length_m
        )
        T_ref_cam[b] = T_ref_cam[a] @ T_a_b
        depth[b] = depth[a] + 1
    unconnected = {c: REASON_NO_SHARED_VIEW for c in cameras if c not in T_ref_cam}

    T_ref_board: dict[str, np.ndarray] = {}
    for view, seen in obs.items():
        connected = sorted((c for c in seen if c in T_ref_cam), key=lambda c: (depth[c], order[c]))
        if not connected:
            continue
        candidates = np.stack([T_ref_cam[c] @ seen[c] for c in connected])
        T_ref_board[view] = (
            robust_mean_pose(candidates, length_m) if len(connected) >= 3 else candidates[0]
        )
    return T_ref_cam, T_ref_board, unconnected


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


def _sigmas_from_covariance(T_ref_cam: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
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
    :func:`_sigmas_from_covariance`."""
    config = config or PoseGraphConfig()
    edges = list(edges)
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
    it would flag sound cameras: measured on the race render, 6 of 8); the returned values
    are the solve with the floor and the factors found.

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
                c, T, *_sigmas_from_covariance(T, covariances[c]), covariances[c]
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
    return PoseGraphResult(
        result.reference,
        result.cameras,
        result.T_ref_board,
        result.residuals,
        merged,
        result.sigma_rotation_deg_default,
        result.sigma_translation_mm_default,
        result.stats,
        result.model_error,
    )


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
    length_m = _working_distance_m([edges[i] for i in ids])
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


# ---------------------------------------------------------------------------- bundle adjustment
@dataclass(frozen=True)
class MarkerMeasurement:
    """One marker seen in one view: 4 pixels and their board points. The pixels are
    undistorted pinhole pixels when the intrinsics are fixed, the raw detected pixels when the
    bundle adjustment refines them (see :func:`bundle_adjust`)."""

    camera: str
    view: str
    marker_id: int
    corners_px: np.ndarray  # (4,2) pinhole pixels (fixed intrinsics) or raw pixels (refine)
    object_points: np.ndarray  # (4,3) board frame, metres
    face: int = 1  # +1 front, -1 back: a back marker moves with the back sheet (board refine);
    #               a multi-face target's face label (its face's pose moves it)


@dataclass(frozen=True)
class RelativePose:
    """A measured camera-to-camera pose ``T_b_a`` (maps camera a's points into camera b),
    e.g. from registering their depth clouds, with its 6x6 information in GTSAM order
    ``[rot, trans]`` for the right perturbation ``T_b_a @ Exp(xi)``."""

    cam_a: str
    cam_b: str
    T_b_a: np.ndarray
    information: np.ndarray

    def factor(self, key: dict[str, int]) -> gtsam.BetweenFactorPose3:
        """Its factor between the cameras' pose variables (camera -> ``key``):
        ``BetweenFactorPose3(b, a)`` predicts ``T_ref_b^-1 T_ref_a = T_b_a``; its error is
        ``Logmap(T_b_a_measured^-1 T_b_a)``, the right perturbation the information is for."""
        return gtsam.BetweenFactorPose3(key[self.cam_b], key[self.cam_a], gtsam.Pose3(self.T_b_a),
                                        gtsam.noiseModel.Gaussian.Information(self.information))


@dataclass(frozen=True)
class BundleResult:
    T_ref_cam: dict[str, np.ndarray]
    T_ref_board: dict[str, np.ndarray]
    covariance: dict[str, np.ndarray]  # camera -> 6x6 body-frame [rot, trans]
    sigma_rotation_deg: dict[str, float]
    sigma_translation_mm: dict[str, float]
    residuals_px: list[tuple[str, str, int, float]]  # (camera, view, marker, rms px)
    outliers: list[tuple[str, str, int, float]]
    pixel_sigma_estimated: float
    iterations: int
    final_error: float
    # refined intrinsics only (config.intrinsics == "refine"): camera -> the refined model,
    # camera -> {parameter: marginal sigma} and {parameter: prior sigma}, both in the order
    # of config.intrinsics_params
    intrinsics: dict[str, CameraIntrinsics] = field(default_factory=dict)
    intrinsics_sigma: dict[str, dict[str, float]] = field(default_factory=dict)
    intrinsics_prior_sigma: dict[str, dict[str, float]] = field(default_factory=dict)
    # board self-calibration (config.board == "refine"): the estimated back-sheet pose, its
    # 6x6 marginal [rot, trans] (right perturbation) and why it was held, if it was
    board: BoardModel | None = None
    # ... of a multi-face target: each non-reference face's estimated pose (empty otherwise)
    faces: tuple[FaceModel, ...] = ()


@dataclass(frozen=True)
class BoardModel:
    """The back sheet's pose relative to the front sheet as the bundle adjustment estimated it.

    ``T_front_back`` (4x4, metres, board frame) maps a back-face point of the board file to
    where the back sheet really is (the convention of ``ground_truth.yaml``, docs/synthetic.md);
    ``covariance`` is its 6x6 marginal ``[rot rad, trans m]`` for the right perturbation
    ``T_front_back @ Exp(xi)``; ``centre`` the board-file centre of the back-marker grid (m),
    about which the offset is reported. ``held`` names why it was not estimated (identity then).
    """

    T_front_back: np.ndarray
    covariance: np.ndarray
    centre: np.ndarray
    thickness_m: float  # the board file's
    held: str = ""

    @property
    def offset_mm(self) -> np.ndarray:
        """Shift (dx, dy, dz) mm of the back-grid centre: ``T_front_back c - c``."""
        c = self.centre
        return (self.T_front_back[:3, :3] @ c + self.T_front_back[:3, 3] - c) * 1000.0

    @property
    def rotation_deg(self) -> float:
        """Rotation of the back sheet about the board normal (+z, counter-clockwise seen from
        the front), degrees."""
        R = self.T_front_back[:3, :3]
        return float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))

    @property
    def thickness_mm(self) -> float:
        """The estimated thickness: the board file's minus the back sheet's z shift."""
        return (self.thickness_m - float(self.offset_mm[2]) / 1000.0) * 1000.0

    @property
    def sigmas(self) -> dict[str, float]:
        """Marginal 1-sigmas: offset x, y and thickness (mm) at the centre, rotation (deg).

        d(T c) = R [-[c]x, I] xi for the right perturbation xi = [w, v]."""
        R = self.T_front_back[:3, :3]
        c = self.centre
        J = np.zeros((4, 6))
        J[:3, :3] = -R @ skew(c)
        J[:3, 3:] = R
        J[3, 2] = 1.0  # rotation about z (small tilts held)
        s = np.sqrt(np.maximum(np.diag(J @ self.covariance @ J.T), 0.0))
        return {"offset_x_mm": float(s[0] * 1000), "offset_y_mm": float(s[1] * 1000),
                "thickness_mm": float(s[2] * 1000), "rotation_deg": float(np.degrees(s[3]))}


@dataclass(frozen=True)
class FaceModel:
    """A multi-face target's face as the bundle adjustment estimated it (board
    self-calibration): the face's true pose is ``T_board_face = T_nominal @ Delta``, ``Delta``
    (4x4, metres, in the nominal face frame: x, y in the sheet, z its outward normal) the
    correction, ``covariance`` its 6x6 marginal ``[rot rad, trans m]`` for the right
    perturbation ``Delta @ Exp(xi)`` (face frame), ``centre`` the face-frame centre of its
    markers, about which the shift is reported. ``held`` names why it was not estimated."""

    label: int
    T_nominal: np.ndarray
    Delta: np.ndarray
    covariance: np.ndarray
    centre: np.ndarray
    held: str = ""

    @property
    def T_board_face(self) -> np.ndarray:
        return self.T_nominal @ self.Delta

    @property
    def offset_mm(self) -> np.ndarray:
        """Shift (x, y along the sheet, z along the normal; mm) of the markers' centre."""
        c = self.centre
        return (self.Delta[:3, :3] @ c + self.Delta[:3, 3] - c) * 1000.0

    @property
    def rotation_deg(self) -> np.ndarray:
        """Turn as a rotation vector (degrees; x, y tilts, z about the normal)."""
        return np.degrees(matrix_to_rotvec(self.Delta[:3, :3]))

    @property
    def sigmas(self) -> dict[str, list[float]]:
        """Marginal 1-sigmas of the centre's shift (mm, face x, y, z) and of the turn (deg,
        about face x, y, z): d(Delta c) = R [-[c]x, I] xi."""
        R, c = self.Delta[:3, :3], self.centre
        J = np.zeros((6, 6))
        J[:3, :3] = -R @ skew(c)
        J[:3, 3:] = R
        J[3:, :3] = np.eye(3)
        s = np.sqrt(np.maximum(np.diag(J @ self.covariance @ J.T), 0.0))
        return {"offset_mm": (s[:3] * 1000).tolist(), "rotation_deg": np.degrees(s[3:]).tolist()}

    def to_dict(self) -> dict[str, Any]:
        held = bool(self.held)
        return {"face": int(self.label), "held": self.held or None,
                "offset_mm": None if held else self.offset_mm.tolist(),
                "rotation_deg": None if held else self.rotation_deg.tolist(),
                "sigmas": None if held else self.sigmas,
                "T_board_face": self.T_board_face.tolist()}


def _project(T_ref_cam: np.ndarray, T_ref_board: np.ndarray, K: np.ndarray,
             P_b: np.ndarray, jacobians: bool = True):
    """Pinhole projection of board points ``P_b`` (N,3) through T_ref_cam and T_ref_board.

    p_cam = T_ref_cam^-1 T_ref_board p_board = R_cb P_b + t_cb, projected by the camera model
    (:mod:`rgbd_calib.core.camera`; the pixels are already undistorted). Returns the pixels (N,2)
    and, with ``jacobians``, d(u,v)/dxi (N,2,6) for the camera and for the board, for right
    perturbations T <- T Exp([w, v]) (GTSAM's Pose3 convention, rotation first): J_cam is
    :func:`~rgbd_calib.core.camera.pinhole_pose_jacobian` (dp_cam/dxi_cam = [[p_cam]x, -I]) and,
    as Exp(-xi) T_cb = T_cb Exp(-Ad(T_cb^-1) xi), the board Jacobian is
    J_board = -J_cam Ad(T_cb) (equal to d(u,v)/dp_cam R_cb [-[P_b]x, I])."""
    R_rc, t_rc = T_ref_cam[:3, :3], T_ref_cam[:3, 3]
    R_cb = R_rc.T @ T_ref_board[:3, :3]
    t_cb = R_rc.T @ (T_ref_board[:3, 3] - t_rc)
    p = P_b @ R_cb.T + t_cb  # (N,3) camera frame
    fx, fy = K[0, 0], K[1, 1]
    uv = project_pinhole(p, fx, fy, K[0, 2], K[1, 2])
    if not jacobians:
        return uv, None, None
    J_cam = pinhole_pose_jacobian(p, fx, fy)
    J_board = J_cam @ -adjoint(make_transform(R_cb, t_cb))
    return uv, J_cam, J_board


def _robust_weight_loss(kind: str, k: float, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weight w(d) and loss rho(d) of GTSAM's M-estimators at whitened norms ``d`` (vector).

    Huber: w = 1 for d <= k else k/d; rho = d^2/2 for d <= k else k (d - k/2).
    Cauchy: w = k^2 / (k^2 + d^2); rho = k^2/2 log(1 + d^2/k^2). 'none': w = 1, rho = d^2/2."""
    if kind == "huber":
        small = d <= k
        w = np.where(small, 1.0, k / np.where(small, 1.0, d))
        rho = np.where(small, d * d / 2, k * (d - k / 2))
    elif kind == "cauchy":
        k2 = k * k
        w = k2 / (k2 + d * d)
        rho = 0.5 * k2 * np.log(1.0 + d * d / k2)
    else:
        w, rho = np.ones_like(d), d * d / 2
    return w, rho


def _robust_rows(r: np.ndarray, blocks, H: list[np.ndarray] | None, robust: str,
                 robust_k: float) -> np.ndarray:
    """The per-marker robust kernel of a view factor (see :func:`_view_factor`).

    ``r`` (n,8) whitened residuals of n markers; ``blocks()`` the whitened Jacobians
    (8n, d_k) of the factor's keys, called only when ``H`` is given (a linearisation); they
    are written into ``H`` scaled by sqrt(w(d_m)) row by row. Returns the factor's error."""
    if robust not in ("huber", "cauchy"):
        if H is not None:
            for k, J in enumerate(blocks()):
                H[k] = J
        return r.reshape(-1)
    d = np.sqrt(np.einsum("ij,ij->i", r, r))
    w, rho = _robust_weight_loss(robust, robust_k, d)
    if H is None:
        scale = np.sqrt(2.0 * rho) / np.where(d > 0, d, 1.0)
        return (r * np.where(d > 0, scale, 1.0)[:, None]).reshape(-1)
    sw = np.repeat(np.sqrt(w), 8)[:, None]
    for k, J in enumerate(blocks()):
        H[k] = J * sw
    return r.reshape(-1) * sw[:, 0]


def _face_transform(X: np.ndarray, A: np.ndarray | None) -> np.ndarray:
    """The board-frame move ``C = A X A^-1`` of a face whose correction ``X`` is expressed in
    the frame ``A`` (a multi-face target's nominal face pose); ``X`` itself when ``A`` is None
    (the back sheet's ``T_front_back``, a board-frame transform)."""
    return X if A is None else A @ X @ invert_transform(A)


def _back_sheet_jacobian(J_board: np.ndarray, back: np.ndarray,
                         T_front_back: np.ndarray) -> np.ndarray:
    """d(u,v)/dxi (N,2,6) of the back-sheet pose from the board pose's ``J_board``: with
    ``T_front_back <- T_front_back Exp(xi)``, ``T_ref_board T_front_back Exp(xi) =
    T_ref_board Exp(Ad(T_front_back) xi) T_front_back``, so J = J_board Ad(T_front_back) on
    the back-face rows and 0 on the front-face ones."""
    J = np.zeros_like(J_board)
    J[back] = J_board[back] @ adjoint(T_front_back)
    return J


def _face_jacobian(J_board: np.ndarray, rows: np.ndarray, X: np.ndarray,
                   A: np.ndarray | None) -> np.ndarray:
    """d(u,v)/dxi (N,2,6) of a face's correction ``X`` (``X <- X Exp(xi)``, expressed in frame
    ``A``): ``T_ref_board A X Exp(xi) A^-1 = T_ref_board Exp(Ad(A X) xi) C``, so J = J_board
    Ad(A X) on the face's rows (:func:`_back_sheet_jacobian` when ``A`` is None)."""
    return _back_sheet_jacobian(J_board, rows, X if A is None else A @ X)


def _view_factor(key_cam: int, key_board: int, K: np.ndarray, object_points: np.ndarray,
                 corners_px: np.ndarray, sigma: float, robust: str, robust_k: float,
                 moving: list | None = None):
    """All markers of one camera view in one factor, each marker with its own robust kernel.

    It reproduces, marker by marker, what a per-marker ``Robust(kernel, Isotropic(8, sigma))``
    noise model does in GTSAM, so the optimiser sees the same cost and the same linear
    systems. For marker m, r_m = (uv_m - uv_m_meas) / sigma (8-vector, whitened), d_m = |r_m|:

    - cost: sum_m rho(d_m), GTSAM's ``Robust::loss``; the callback, called with ``H = None``
      for an error evaluation, returns r_m * sqrt(2 rho(d_m)) / d_m so that the factor's
      ``0.5 |e|^2`` under a unit noise model equals that sum;
    - linearisation (iteratively re-weighted least squares, GTSAM's ``Robust::WhitenSystem``):
      rows r_m and J_m / sigma scaled by sqrt(w(d_m)), with w the kernel weight at the
      current point; w = 1 and rho = d^2/2 without a kernel (the plain Gaussian graph).

    ``object_points`` (n,4,3), ``corners_px`` (n,4,2) undistorted pinhole pixels. The factor's
    ``unwhitenedError`` is therefore the loss-scaled whitened residual, not pixels.

    With ``moving`` (board self-calibration) the markers of each listed face are moved by that
    face's pose, a Pose3 variable (:func:`_view_factor_faces`)."""
    if moving:
        return _view_factor_faces(key_cam, key_board, moving, K, None, (),
                                  object_points, corners_px, sigma, robust, robust_k)
    n = len(object_points)
    measured = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    P_b = np.asarray(object_points, dtype=float).reshape(-1, 3)
    inv_sigma = 1.0 / sigma

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None):
        uv, J_cam, J_board = _project(values.atPose3(key_cam).matrix(),
                                      values.atPose3(key_board).matrix(), K, P_b, H is not None)
        r = ((uv - measured) * inv_sigma).reshape(n, 8)
        return _robust_rows(r, lambda: (J_cam.reshape(-1, 6) * inv_sigma,
                                        J_board.reshape(-1, 6) * inv_sigma), H, robust, robust_k)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * n), [key_cam, key_board], error)


# ------------------------------------------------------------------ bundle with intrinsics
def _with_parameters(base: CameraIntrinsics, names: tuple[str, ...],
                     x: np.ndarray) -> CameraIntrinsics:
    """``base`` with the parameters ``names`` set to ``x`` (distortion names index OpenCV's
    coefficient list; the list is padded with zeros to hold the last name)."""
    values = dict(zip(names, np.asarray(x, dtype=float).tolist()))
    dist = list(_padded_distortion(base, names))
    for i, name in enumerate(DISTORTION_NAMES[:len(dist)]):
        dist[i] = values.get(name, dist[i])
    return CameraIntrinsics(base.width, base.height,
                            values.get("fx", base.fx), values.get("fy", base.fy),
                            values.get("cx", base.cx), values.get("cy", base.cy),
                            tuple(dist), base.depth_scale, base.depth_noise)


def _padded_distortion(base: CameraIntrinsics, names: tuple[str, ...]) -> tuple[float, ...]:
    """``base.distortion`` padded with zeros to OpenCV's next valid length (4, 5, 8, 12, 14)
    that holds every distortion coefficient of ``names``."""
    need = max([DISTORTION_NAMES.index(n) + 1 for n in names if n in DISTORTION_NAMES]
               + [len(base.distortion)])
    length = next(n for n in DISTORTION_LENGTHS if n >= need)
    return tuple(base.distortion) + (0.0,) * (length - len(base.distortion))


def intrinsics_vector(base: CameraIntrinsics, names: tuple[str, ...]) -> np.ndarray:
    """The values of the parameters ``names`` of ``base`` (missing coefficients are 0)."""
    padded = CameraIntrinsics(base.width, base.height, base.fx, base.fy, base.cx, base.cy,
                              _padded_distortion(base, names), base.depth_scale)
    table = padded.parameters
    return np.array([table[n] for n in names], dtype=float)


def intrinsics_prior_sigmas(base: CameraIntrinsics, names: tuple[str, ...],
                            config: BundleConfig) -> np.ndarray:
    """Prior sigmas of the parameters ``names``: focal in percent of its value, centre in
    pixels, p1/p2 tangential, every other coefficient with the distortion sigma."""
    out = []
    for n in names:
        if n in ("fx", "fy"):
            out.append(config.intrinsics_prior_focal_pct / 100.0 * getattr(base, n))
        elif n in ("cx", "cy"):
            out.append(config.intrinsics_prior_center_px)
        elif n in ("p1", "p2"):
            out.append(config.intrinsics_prior_tangential)
        else:
            out.append(config.intrinsics_prior_distortion)
    return np.array(out, dtype=float)


def _project_full(T_ref_cam: np.ndarray, T_ref_board: np.ndarray, intr: CameraIntrinsics,
                  columns: np.ndarray | None, P_b: np.ndarray, jacobians: bool = True):
    """As :func:`_project`, through the full camera model ``intr`` (distortion included):
    pixels (N,2) and, with ``jacobians``, d(u,v)/dxi (N,2,6) of the camera and of the board
    and d(u,v)/d(intrinsics) (N,2,len(columns)), ``columns`` indexing
    :meth:`~rgbd_calib.core.camera.CameraIntrinsics.intrinsics_jacobian`. The pose Jacobians are
    d(u,v)/dp_cam (``project_jacobian``) times dp_cam/dxi_cam = ``[[p_cam]x, -I]``, the board's
    as in :func:`_project`."""
    R_rc, t_rc = T_ref_cam[:3, :3], T_ref_cam[:3, 3]
    R_cb = R_rc.T @ T_ref_board[:3, :3]
    t_cb = R_rc.T @ (T_ref_board[:3, 3] - t_rc)
    p = P_b @ R_cb.T + t_cb
    if not jacobians:
        return intr.project(p), None, None, None
    uv, J_point = intr.project_jacobian(p)
    dp_dxi = np.zeros((len(p), 3, 6))
    dp_dxi[:, 0, 1], dp_dxi[:, 0, 2] = -p[:, 2], p[:, 1]  # [p]x: Exp(-w) p = p + p x w
    dp_dxi[:, 1, 0], dp_dxi[:, 1, 2] = p[:, 2], -p[:, 0]
    dp_dxi[:, 2, 0], dp_dxi[:, 2, 1] = -p[:, 1], p[:, 0]
    dp_dxi[:, :, 3:] = -np.eye(3)
    J_cam = J_point @ dp_dxi
    J_board = J_cam @ -adjoint(make_transform(R_cb, t_cb))
    J_intr = intr.intrinsics_jacobian(p)[:, :, columns]
    return uv, J_cam, J_board, J_intr


def _view_factor_intrinsics(key_cam: int, key_board: int, key_intr: int,
                            base: CameraIntrinsics, names: tuple[str, ...],
                            object_points: np.ndarray, corners_px: np.ndarray, sigma: float,
                            robust: str, robust_k: float, moving: list | None = None):
    """:func:`_view_factor` with the camera's intrinsics as a third variable: a vector of the
    parameters ``names`` (the rest of ``base`` held), the board points projected through the
    full model (distortion included) onto the RAW detected pixels ``corners_px`` (n,4,2).
    Same per-marker robust kernel; Jacobians w.r.t. camera pose, board pose, intrinsics
    (and the face poses with ``moving``, :func:`_view_factor_faces`)."""
    if moving:
        return _view_factor_faces(key_cam, key_board, moving, None, (key_intr, base),
                                  names, object_points, corners_px, sigma, robust, robust_k)
    n = len(object_points)
    measured = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    P_b = np.asarray(object_points, dtype=float).reshape(-1, 3)
    inv_sigma = 1.0 / sigma
    padded = CameraIntrinsics(base.width, base.height, base.fx, base.fy, base.cx, base.cy,
                              _padded_distortion(base, names), base.depth_scale)
    columns = np.array([padded.parameter_names.index(nm) for nm in names])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None):
        intr = _with_parameters(padded, names, values.atVector(key_intr))
        uv, J_cam, J_board, J_intr = _project_full(
            values.atPose3(key_cam).matrix(), values.atPose3(key_board).matrix(), intr,
            columns, P_b, H is not None)
        r = ((uv - measured) * inv_sigma).reshape(n, 8)
        return _robust_rows(r, lambda: (J_cam.reshape(-1, 6) * inv_sigma,
                                        J_board.reshape(-1, 6) * inv_sigma,
                                        J_intr.reshape(-1, len(names)) * inv_sigma),
                            H, robust, robust_k)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * n),
                              [key_cam, key_board, key_intr], error)


def _view_factor_faces(key_cam: int, key_board: int, moving: list,
                       K: np.ndarray | None, intr: tuple, names: tuple[str, ...],
                       object_points: np.ndarray, corners_px: np.ndarray, sigma: float,
                       robust: str, robust_k: float):
    """The view factor with face poses as variables (board self-calibration): ``moving`` lists
    ``(key, flags, A)`` per face seen, ``flags`` (n,) marking its markers, ``A`` the frame its
    correction ``X`` (Pose3 ``key``) is expressed in (None: the board frame, the back sheet's
    ``T_front_back``); a flagged marker's corners are ``A X A^-1 @ object_point``
    (:func:`rgbd_calib.core.geometry.move_rows`). Pinhole ``K`` (fixed intrinsics), or
    ``intr = (key_intr, base)`` for refined ones (as :func:`_view_factor_intrinsics`). Keys:
    camera, board, [intrinsics,] the faces; same per-marker robust kernel."""
    n = len(object_points)
    measured = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    P_file = np.asarray(object_points, dtype=float).reshape(-1, 3)
    faces = [(key, np.repeat(np.asarray(flags, dtype=bool), 4), A) for key, flags, A in moving]
    inv_sigma = 1.0 / sigma
    keys = [key_cam, key_board]
    if intr:
        key_intr, base = intr
        padded = CameraIntrinsics(base.width, base.height, base.fx, base.fy, base.cx, base.cy,
                                  _padded_distortion(base, names), base.depth_scale)
        columns = np.array([padded.parameter_names.index(nm) for nm in names])
        keys.append(key_intr)
    keys += [key for key, _, _ in faces]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None):
        X = [values.atPose3(key).matrix() for key, _, _ in faces]
        P_b = move_rows(P_file, [(rows, _face_transform(x, A))
                                   for (_, rows, A), x in zip(faces, X)])
        T_cam, T_board = values.atPose3(key_cam).matrix(), values.atPose3(key_board).matrix()
        if intr:
            model = _with_parameters(padded, names, values.atVector(key_intr))
            uv, J_cam, J_board, J_intr = _project_full(T_cam, T_board, model, columns, P_b,
                                                       H is not None)
        else:
            uv, J_cam, J_board = _project(T_cam, T_board, K, P_b, H is not None)
        r = ((uv - measured) * inv_sigma).reshape(n, 8)

        def blocks():
            out = [J_cam.reshape(-1, 6) * inv_sigma, J_board.reshape(-1, 6) * inv_sigma]
            if intr:
                out.append(J_intr.reshape(-1, len(names)) * inv_sigma)
            out += [_face_jacobian(J_board, rows, x, A).reshape(-1, 6) * inv_sigma
                    for (_, rows, A), x in zip(faces, X)]
            return out

        return _robust_rows(r, blocks, H, robust, robust_k)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * n), keys, error)


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


def bundle_adjust(measurements: list[MarkerMeasurement], K: dict[str, np.ndarray],
                  reference: str, init_T_ref_cam: dict[str, np.ndarray],
                  init_T_ref_board: dict[str, np.ndarray], config: BundleConfig = BundleConfig(),
                  fixed_cameras: dict[str, np.ndarray] | None = None,
                  relative_poses: list[RelativePose] = (),
                  intrinsics: dict[str, CameraIntrinsics] | None = None,
                  back_centre: np.ndarray | None = None,
                  face_frames: dict[int, np.ndarray] | None = None) -> BundleResult:
    """Joint bundle adjustment of camera poses ``T_ref_cam`` and board poses ``T_ref_board``
    on the marker corners (one GTSAM CustomFactor per camera view holding all its markers,
    robust per marker: :func:`_view_factor`), optionally joined by camera-to-camera
    ``relative_poses`` (depth registration) as ``BetweenFactorPose3`` with their own
    information: one joint graph, one set of marginals.

    With ``config.intrinsics == "fixed"`` the intrinsics are held (``K`` per camera) and the
    measurements are undistorted pinhole pixels. With ``"refine"`` each camera also gets a
    vector variable of the parameters ``config.intrinsics_params`` under a Gaussian prior at
    ``intrinsics`` (the rig.yaml models, required then; sigmas from
    :func:`intrinsics_prior_sigmas`), and the measurements are the RAW detected pixels,
    projected through the full model (:func:`_view_factor_intrinsics`). The reference camera
    (and any ``fixed_cameras``) carry a tight pose prior. Marginal covariances come from the
    converged graph, scaled by the a-posteriori variance factor when ``config.estimate_sigma``
    is on.

    With ``config.board == "refine"`` the back sheet's pose ``T_front_back`` is one more
    Pose3 variable (board self-calibration, :func:`_view_factor_back`): it moves the board
    points of the back-face measurements (``MarkerMeasurement.face == -1``), under a prior at
    the identity (the board file) with the config's sigmas on the in-plane offset, the rotation
    about the normal and the thickness; the tilts of a sheet glued flat on the panel are held
    by a tight prior. ``back_centre`` (board-file centre of the back-marker grid, m; default:
    of the back markers measured) is where the offset is reported (:class:`BoardModel`). It is
    held at the board file, and ``result.board.held`` says why, when no view has markers of
    both faces: then a back-sheet shift is the same as a shift of those views' board poses.

    A multi-face target (``face_frames``: label -> nominal ``T_board_face`` of each
    non-reference face) gets, with ``config.board == "refine"``, one Pose3 correction
    ``Delta`` per such face instead (its true pose ``T_board_face @ Delta``, :class:`FaceModel`)
    under a prior at the identity with the ``board_prior_face_*`` sigmas on all 6 axes of the
    face frame; a face that no view sees together with a face already tied to the reference
    face is held (``result.faces[k].held``)."""
    refine = config.intrinsics == "refine"
    if refine and intrinsics is None:
        raise CalibrationError("refining intrinsics needs the rig's camera models")
    names = tuple(config.intrinsics_params)
    fixed = dict(fixed_cameras or {})
    fixed.setdefault(reference, np.eye(4))
    cams = sorted({m.camera for m in measurements} | set(fixed)
                  | {c for r in relative_poses for c in (r.cam_a, r.cam_b)})
    views = sorted({m.view for m in measurements})
    cam_key = {c: gtsam.symbol("c", i) for i, c in enumerate(cams)}
    view_key = {v: gtsam.symbol("b", i) for i, v in enumerate(views)}
    intr_key = ({c: gtsam.symbol("k", i) for i, c in enumerate(cams) if c in intrinsics}
                if refine else {})
    kept = [m for m in measurements if m.camera in init_T_ref_cam and m.view in init_T_ref_board]
    key_back = gtsam.symbol("f", 0)
    board_model = None if face_frames is not None else _board_model_setup(kept, config,
                                                                           back_centre)
    solve_board = board_model is not None and not board_model.held
    face_models = _face_models_setup(kept, config, face_frames)
    moving = [(key_back, -1, None)] if solve_board else []  # (key, face label, frame A)
    moving += [(gtsam.symbol("f", m.label), m.label, m.T_nominal) for m in face_models
               if not m.held]
    if refine:
        kept = [m for m in kept if m.camera in intr_key]
        x0 = {c: intrinsics_vector(intrinsics[c], names) for c in intr_key}
        prior_intr = {c: gtsam.noiseModel.Diagonal.Sigmas(
            intrinsics_prior_sigmas(intrinsics[c], names, config)) for c in intr_key}

    problem = _BundleProblem(config, K, cam_key, view_key, intr_key, intrinsics, names,
                             x0 if refine else {}, prior_intr if refine else {}, fixed,
                             relative_poses, tuple(moving), refine)

    values = _initial_values(problem, cams, views, init_T_ref_cam, init_T_ref_board)

    def component(active, values):
        """:func:`_reference_component`, keeping the face poses (the back sheet's)."""
        out, sub = _reference_component(active, values, cam_key, view_key, set(fixed),
                                        relative_poses, reference, intr_key)
        for key, _, _ in moving:
            sub.insert(key, values.atPose3(key))
        return out, sub

    def marker_rms(groups, n, values):
        return _marker_rms(groups, n, values, cam_key, view_key, K,
                           _current_models(problem, values),
                           moves=[(label, _face_transform(values.atPose3(key).matrix(), A))
                                  for key, label, A in moving])

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    outliers: list[tuple[str, str, int, float]] = []
    active, values = component(kept, values)
    connected = {c for c in cams if values.exists(cam_key[c])}
    for _ in range(3):  # solve, drop markers far off, re-solve
        groups = _group_views(active)
        graph = _build_graph(problem, groups, config.pixel_sigma, connected)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        values = optimizer.optimize()
        rms = marker_rms(groups, len(active), values)
        bad = rms > config.outlier_px
        if not np.any(bad):
            break
        outliers += [(m.camera, m.view, m.marker_id, float(r))
                     for m, r, b in zip(active, rms, bad) if b]
        active = [m for m, b in zip(active, bad) if not b]
        # removing outliers can cut a camera (or a view) off the reference: drop that part
        active, values = component(active, values)
        connected = {c for c in cams if values.exists(cam_key[c])}
        groups = _group_views(active)
        rms = marker_rms(groups, len(active), values)
    dof = _residual_dof(problem, len(active), values)
    sigma_hat = float(np.sqrt(np.sum(4 * rms**2) / dof))  # 4 corners x (du^2+dv^2)
    # marginals of the plain Gaussian graph at the solution, corners weighted by the
    # a-posteriori sigma (Foerstner's variance factor) so that the relative-pose factors keep
    # their own weight; inlier Huber weights are 1 and outliers were removed above
    sigma_marg = max(sigma_hat, 1e-3) if config.estimate_sigma else config.pixel_sigma
    if relative_poses and config.estimate_sigma:
        # re-solve with the corners at their estimated noise, so that board and depth
        # measurements are weighted against each other by their real uncertainties
        graph = _build_graph(problem, groups, sigma_marg, connected)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        values = optimizer.optimize()
        rms = marker_rms(groups, len(active), values)
    marg_graph = _build_graph(problem, groups, sigma_marg, connected, robust=False)
    marginals = gtsam.Marginals(marg_graph, values)
    out_cam, cov, s_rot, s_trans = _camera_marginals(cams, values, cam_key, fixed, marginals)
    boards = {v: values.atPose3(view_key[v]).matrix() for v in views if values.exists(view_key[v])}
    residuals = [(m.camera, m.view, m.marker_id, r) for m, r in zip(active, rms.tolist())]
    refined, sigma_intr, sigma_prior = _refined_intrinsics(problem, values, marginals)
    if solve_board:
        board_model = replace(board_model, T_front_back=values.atPose3(key_back).matrix(),
                              covariance=np.asarray(marginals.marginalCovariance(key_back)))
    face_models = tuple(m if m.held else replace(
        m, Delta=values.atPose3(gtsam.symbol("f", m.label)).matrix(),
        covariance=np.asarray(marginals.marginalCovariance(gtsam.symbol("f", m.label))))
        for m in face_models)
    return BundleResult(out_cam, boards, cov, s_rot, s_trans, residuals, outliers, sigma_hat,
                        optimizer.iterations(), graph.error(values), refined, sigma_intr,
                        sigma_prior, board_model, face_models)


@dataclass(frozen=True)
class _BundleProblem:
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
    fixed: dict[str, np.ndarray]
    relative_poses: list[RelativePose]
    moving: tuple  # (key, face label, frame A or None) of every face pose solved
    refine: bool  # intrinsics refined: the view factors project raw pixels through the model

    @property
    def solve_board(self) -> bool:
        return bool(self.moving)


def _build_graph(p: _BundleProblem, groups: list[_ViewGroup], sigma: float,
                 connected: set[str], robust: bool = True) -> gtsam.NonlinearFactorGraph:
    """The factor graph: one view factor per (camera, view) at corner noise ``sigma`` (px),
    robust per marker unless ``robust`` is off, the priors (fixed cameras, intrinsics, back
    sheet) and the relative poses between ``connected`` cameras."""
    config = p.config
    graph = gtsam.NonlinearFactorGraph()
    kind = config.robust if robust else "none"
    for g in groups:
        seen = [(key, g.face == label, A) for key, label, A in p.moving
                if np.any(g.face == label)]
        extra = {"moving": seen} if seen else {}
        if p.refine:
            graph.add(_view_factor_intrinsics(
                p.cam_key[g.camera], p.view_key[g.view], p.intr_key[g.camera],
                p.intrinsics[g.camera], p.names, g.object_points, g.corners_px, sigma, kind,
                config.robust_k, **extra))
        else:
            graph.add(_view_factor(p.cam_key[g.camera], p.view_key[g.view], p.K[g.camera],
                                   g.object_points, g.corners_px, sigma, kind,
                                   config.robust_k, **extra))
    for key, _, A in p.moving:
        graph.add(gtsam.PriorFactorPose3(key, gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(
            _board_prior_sigmas(config) if A is None else _face_prior_sigmas(config))))
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
    return graph


def _initial_values(p: _BundleProblem, cams: list[str], views: list[str],
                    init_T_ref_cam: dict[str, np.ndarray],
                    init_T_ref_board: dict[str, np.ndarray]) -> gtsam.Values:
    """Camera poses (fixed ones where they are held), board poses, the intrinsics' prior
    values and the back sheet at the board file: the solve's starting point."""
    values = gtsam.Values()
    for c in cams:
        T = p.fixed.get(c, init_T_ref_cam.get(c))
        if T is not None:
            values.insert(p.cam_key[c], gtsam.Pose3(T))
    for v in views:
        if v in init_T_ref_board:
            values.insert(p.view_key[v], gtsam.Pose3(init_T_ref_board[v]))
    for c, k in p.intr_key.items():
        if values.exists(p.cam_key[c]):
            values.insert(k, p.x0[c])
    for key, _, _ in p.moving:
        values.insert(key, gtsam.Pose3())
    return values


def _current_models(p: _BundleProblem, values: gtsam.Values) -> dict[str, CameraIntrinsics] | None:
    """The current camera models (refined intrinsics), None when the intrinsics are fixed."""
    if not p.refine:
        return None
    return {c: _with_parameters(p.intrinsics[c], p.names, values.atVector(k))
            for c, k in p.intr_key.items() if values.exists(k)}


def _refined_intrinsics(p: _BundleProblem, values: gtsam.Values, marginals: gtsam.Marginals):
    """The refined camera models, their marginal sigmas and their prior sigmas, by parameter
    name (all empty when the intrinsics are fixed)."""
    refined = _current_models(p, values) or {}
    sigma = {c: dict(zip(p.names, np.sqrt(np.diag(
        marginals.marginalCovariance(p.intr_key[c]))).tolist())) for c in refined}
    prior = {c: dict(zip(p.names, p.prior_intr[c].sigmas().tolist())) for c in refined}
    return refined, sigma, prior


def _residual_dof(p: _BundleProblem, n_markers: int, values: gtsam.Values) -> int:
    """Redundancy of the corner fit: 8 residuals per marker less the free parameters (6 per
    unheld pose, the intrinsics vectors, 4 for the back sheet: its tilts are held; 6 for
    each face of a multi-face target)."""
    n_intr = sum(values.exists(k) for k in p.intr_key.values())
    n_back = len(p.moving)
    face_params = sum(4 if A is None else 6 for _, _, A in p.moving)
    return max(8 * n_markers - 6 * (values.size() - n_intr - n_back - len(p.fixed))
               - len(p.names) * n_intr - face_params, 1)


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
        s_rot[c], s_trans[c] = _sigmas_from_covariance(T, C)
    return out_cam, cov, s_rot, s_trans


BOARD_TILT_SIGMA_RAD = 1e-6  # a sheet glued flat on the panel does not tilt: held


def _board_prior_sigmas(config: BundleConfig) -> np.ndarray:
    """Prior sigmas of ``T_front_back`` in GTSAM's order ``[rx, ry, rz, tx, ty, tz]``."""
    return np.array([BOARD_TILT_SIGMA_RAD, BOARD_TILT_SIGMA_RAD,
                     np.radians(config.board_prior_rotation_deg),
                     config.board_prior_offset_mm / 1000.0, config.board_prior_offset_mm / 1000.0,
                     config.board_prior_thickness_mm / 1000.0])


def _face_prior_sigmas(config: BundleConfig) -> np.ndarray:
    """Prior sigmas of a multi-face target's face correction ``Delta`` (face frame, GTSAM's
    order ``[rx, ry, rz, tx, ty, tz]``)."""
    r = np.radians(config.board_prior_face_rotation_deg)
    t = config.board_prior_face_offset_mm / 1000.0
    return np.array([r, r, r, t, t, t])


def _union_find():
    """``(find, union)`` of a disjoint-set forest over hashable items (path halving): the
    connected parts of a graph given edge by edge."""
    parent: dict = {}

    def find(x):
        parent.setdefault(x, x)
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    def union(a, b) -> None:
        parent[find(a)] = find(b)

    return find, union


def _face_models_setup(measurements: list[MarkerMeasurement], config: BundleConfig,
                       face_frames: dict[int, np.ndarray] | None) -> tuple[FaceModel, ...]:
    """The faces of a multi-face target to estimate (``held`` empty) or why each is held;
    empty for a double-sided board or with ``config.board`` fixed. A face's pose is
    observable when it is tied to the reference face (the one not in ``face_frames``)
    through views that see two faces at once."""
    if config.board != "refine" or not face_frames:
        return ()
    find, union = _union_find()
    faces_of: dict[str, set[int]] = defaultdict(set)
    points: dict[int, list[np.ndarray]] = defaultdict(list)
    for m in measurements:
        faces_of[m.view].add(m.face)
        points[m.face].append(m.object_points)
    for seen in faces_of.values():
        first, *rest = sorted(seen)
        for f in rest:
            union(f, first)
    reference = [f for f in {m.face for m in measurements} if f not in face_frames]
    ref_root = find(reference[0]) if reference else None
    out = []
    for label, T in sorted(face_frames.items()):
        centre = np.zeros(3)
        if points[label]:
            P = transform_points(invert_transform(T), np.concatenate(points[label]).reshape(-1, 3))
            centre = np.r_[(P[:, :2].min(axis=0) + P[:, :2].max(axis=0)) / 2, 0.0]
        held = ""
        if not points[label]:
            held = f"face {label} was never seen: its pose is held at the board file"
        elif ref_root is None or find(label) != ref_root:
            held = (f"no view sees face {label} together with a face tied to the reference "
                    "face: its pose is unobservable, held at the board file")
        out.append(FaceModel(label, np.asarray(T, float), np.eye(4), np.zeros((6, 6)), centre,
                             held))
    return tuple(out)


def _board_model_setup(measurements: list[MarkerMeasurement], config: BundleConfig,
                       back_centre: np.ndarray | None) -> BoardModel | None:
    """The back-sheet model to estimate (``held`` empty) or the reason it is held; None when
    ``config.board`` is fixed."""
    if config.board != "refine":
        return None
    back = [m.object_points for m in measurements if m.face < 0]
    if not back:
        return BoardModel(np.eye(4), np.zeros((6, 6)), np.zeros(3), 0.0,
                          "the back face was never seen: the back sheet's pose is "
                          "unobservable, held at the board file")
    P = np.concatenate(back).reshape(-1, 3)
    thickness_m = float(-np.mean(P[:, 2]))
    if back_centre is None:
        back_centre = np.r_[(P[:, :2].min(axis=0) + P[:, :2].max(axis=0)) / 2, -thickness_m]
    faces_of: dict[str, set[int]] = defaultdict(set)
    for m in measurements:
        faces_of[m.view].add(m.face)
    held = ""
    if not any(len(f) == 2 for f in faces_of.values()):
        held = ("no board view has both faces seen at once (by different cameras): the back "
                "sheet's pose is unobservable, held at the board file")
    return BoardModel(np.eye(4), np.zeros((6, 6)), np.asarray(back_centre, float),
                      thickness_m, held)


def _reference_component(active: list[MarkerMeasurement], values: gtsam.Values,
                         cam_key: dict, view_key: dict, fixed: set[str],
                         relative_poses, reference: str, intr_key: dict | None = None):
    """Keep the measurements and values connected to the reference camera (a camera or view
    cut off from it has no determined pose: its marginals would be singular); ``intr_key``
    (camera -> intrinsics vector key) keeps the intrinsics of the kept cameras."""
    find, union = _union_find()
    for camera, view in dict.fromkeys((m.camera, m.view) for m in active):
        union("c:" + camera, "v:" + view)
    for r in relative_poses:
        union("c:" + r.cam_a, "c:" + r.cam_b)
    for c in fixed:  # fixed cameras are tied to the reference frame by their priors
        union("c:" + c, "c:" + reference)
    root = find("c:" + reference)
    cameras = {c for c in cam_key if find("c:" + c) == root}
    kept = [m for m in active if m.camera in cameras]
    sub = gtsam.Values()
    for c, k in cam_key.items():
        if values.exists(k) and find("c:" + c) == root:
            sub.insert(k, values.atPose3(k))
    for v, k in view_key.items():
        if values.exists(k) and find("v:" + v) == root:
            sub.insert(k, values.atPose3(k))
    for c, k in (intr_key or {}).items():
        if values.exists(k) and find("c:" + c) == root:
            sub.insert(k, values.atVector(k))
    return kept, sub


def _marker_rms(groups: list[_ViewGroup], n: int, values: gtsam.Values, cam_key: dict,
                view_key: dict, K: dict,
                models: dict[str, CameraIntrinsics] | None = None, moves=()) -> np.ndarray:
    """RMS corner residual (px) of each of the ``n`` active markers at ``values``:
    sqrt(mean over the 4 corners of |uv - uv_meas|^2), vectorised per camera view; through
    the full camera ``models`` when given (refined intrinsics), else the pinhole ``K``; each
    face's markers moved by its board-frame move ``C`` of ``moves`` ``(label, C)`` (board
    self-calibration)."""
    out = np.empty(n)
    for g in groups:
        T_cam = values.atPose3(cam_key[g.camera]).matrix()
        T_board = values.atPose3(view_key[g.view]).matrix()
        P_b = g.object_points.reshape(-1, 3)
        if moves:
            P_b = move_rows(P_b, [(np.repeat(g.face == label, 4), C) for label, C in moves])
        if models is not None:
            uv = _project_full(T_cam, T_board, models[g.camera], None, P_b, jacobians=False)[0]
        else:
            uv, _, _ = _project(T_cam, T_board, K[g.camera], P_b, jacobians=False)
        d2 = np.sum((uv.reshape(-1, 4, 2) - g.corners_px) ** 2, axis=2)
        out[g.index] = np.sqrt(np.mean(d2, axis=1))
    return out


def relative_pose_redundancy(reference: str, T_ref_cam: dict[str, np.ndarray],
                             relative_poses: list[RelativePose],
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Per relative pose of a pose graph with ``reference`` held, linearised at ``T_ref_cam``
    (camera -> 4x4, m): its whitened chi-square ``e^T W e`` and its redundancy number
    ``r = 6 - tr(A_f (A^T A)^+ A_f^T)`` (``A`` the whitened Jacobian of the graph without the
    reference's columns, ``A_f`` the rows of that factor; Foerstner 1979), the share of the
    graph's redundancy its residual carries. A pose with a camera not in ``T_ref_cam`` (cut
    off from the reference: not in the solve) gets 0 for both. Arrays follow
    ``relative_poses``."""
    used = [i for i, r in enumerate(relative_poses)
            if r.cam_a in T_ref_cam and r.cam_b in T_ref_cam]
    chi2_f, redundancy = np.zeros(len(relative_poses)), np.zeros(len(relative_poses))
    if not used:
        return chi2_f, redundancy
    cams = sorted({reference} | {c for i in used for c in (relative_poses[i].cam_a,
                                                          relative_poses[i].cam_b)})
    key = {c: gtsam.symbol("c", i) for i, c in enumerate(cams)}
    graph = gtsam.NonlinearFactorGraph()
    for i in used:
        graph.add(relative_poses[i].factor(key))
    values = gtsam.Values()
    ordering = gtsam.Ordering()
    for c in cams:
        values.insert(key[c], gtsam.Pose3(T_ref_cam[c]))
        ordering.push_back(key[c])
    A, b = graph.linearize(values).jacobian(ordering)
    k = cams.index(reference)  # held: its columns go
    A = np.delete(A, np.s_[6 * k:6 * k + 6], axis=1)
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    U = U[:, s > s.max() * 1e-12] if s.size else U  # rank-revealing: a free direction adds 0
    h = np.sum(U**2, axis=1)  # the hat matrix's diagonal
    chi2_f[used] = np.sum(np.reshape(b, (len(used), 6)) ** 2, axis=1)
    redundancy[used] = 6.0 - np.sum(np.reshape(h, (len(used), 6)), axis=1)
    return chi2_f, redundancy
