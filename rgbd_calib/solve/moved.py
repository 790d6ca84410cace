"""Has a camera moved since the calibration? The inference of ``check`` on its evidence.

A pose graph (GTSAM) of the evidence and one prior per camera at its calibrated pose with the
calibration's sigmas. The evidence (:class:`Evidence`) is of two kinds: measured depth pairs
(camera to camera) and, when the board is in the frames, each camera's PnP pose of the board
(:class:`BoardLink`, camera to a free board pose per frame set). A camera that moved makes
every measurement it is in disagree with those priors. Each kind has its own a-posteriori
variance factor (its chi-square over its share of the redundancy, at least 1): depth pairs miss
millimetres their noise model leaves out (surfaces that slide along rails and floors, a board
moving through a median), board poses miss what a moving board and unsynchronised cameras add;
each is scaled by what its own residuals show, so neither's optimism is taken for a knock.

Which cameras moved is found greedily (:func:`locate_moved`): free the camera whose prior costs
most (the drop in chi-square when it is removed), as long as that drop is significant and the
camera's move is beyond the tolerance; the majority that agrees with the calibration stays in
place. A camera is named only when the evidence says which one it is: when releasing another
camera explains the evidence about as well, both are ``unknown`` (one of them moved). Each
camera's move is then estimated with its own prior removed, with a sigma from the graph's
marginal plus the calibration's own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Literal

import gtsam
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..core.geometry import covariance_sigmas, invert_transform, transform_error
from ..model.results import CameraExtrinsics
from .bundle_problem import RelativePose

Status = Literal["in_place", "moved", "unknown"]


MOVED_CHI2 = 22.46  # chi-square, 6 dof, 0.1 %: a camera's prior is dropped only beyond this


@dataclass(frozen=True)
class Tolerance:
    """A move smaller than both of these is not reported as moved, however significant
    (a depth pair resolves millimetres, measured: docs/depth.md; a rig re-checked nightly
    should not alarm on noise)."""

    mm: float = 2.0
    deg: float = 0.2


@dataclass(frozen=True)
class CameraCheck:
    """One camera now against its calibration: ``moved_mm`` / ``moved_deg`` (camera centre in
    the reference frame, rotation angle) with 1-sigma ``sigma_mm`` / ``sigma_deg`` (graph
    marginal plus the calibration's), ``chi2``: how much the camera's calibrated pose
    disagrees with the depth (the drop in the graph's chi-square when its prior is removed,
    ~chi2(6) when it did not move), ``T_ref_cam_now``: its estimated pose now (in the
    calibration's reference frame), ``reason`` when the status is unknown."""

    camera: str
    status: Status
    moved_mm: float = float("nan")
    moved_deg: float = float("nan")
    sigma_mm: float = float("nan")
    sigma_deg: float = float("nan")
    chi2: float = float("nan")
    n_pairs: int = 0
    T_ref_cam_now: np.ndarray | None = None
    covariance_now: np.ndarray | None = None  # 6x6 body [rot, trans] of T_ref_cam_now
    reason: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "status": self.status, "moved_mm": self.moved_mm, "moved_deg": self.moved_deg,
            "sigma_mm": self.sigma_mm, "sigma_deg": self.sigma_deg, "chi2": self.chi2,
            "n_pairs": self.n_pairs, "reason": self.reason,
            "T_ref_cam_now": None if self.T_ref_cam_now is None else self.T_ref_cam_now.tolist(),
        }


@dataclass(frozen=True)
class BoardLink:
    """One camera's PnP pose of the board in one frame set of the checked recording:
    ``T_cam_board`` with its 6x6 covariance ``[rot, trans]`` in the board (body) frame (a
    :class:`~rgbd_calib.solve.pose.BoardObservation`'s)."""

    camera: str
    frame: str
    T_cam_board: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True)
class Evidence:
    """What the check measured: depth ``pairs`` and board ``links``. Only links of frame sets
    seen by two cameras or more count (one camera's view of a free board says nothing)."""

    pairs: tuple[RelativePose, ...] = ()
    links: tuple[BoardLink, ...] = ()

    @staticmethod
    def of(pairs: list[RelativePose], links: list[BoardLink] | tuple = (),
           cameras: set[str] | None = None) -> Evidence:
        """The evidence of ``pairs`` and of the ``links`` of frames that two cameras of
        ``cameras`` (default: any) saw."""
        keep = [k for k in links if cameras is None or k.camera in cameras]
        seen: dict[str, set[str]] = {}
        for k in keep:
            seen.setdefault(k.frame, set()).add(k.camera)
        return Evidence(tuple(pairs), tuple(k for k in keep if len(seen[k.frame]) >= 2))

    def count(self, camera: str) -> tuple[int, int]:
        """The camera's depth pairs and board views."""
        return (sum(camera in (r.cam_a, r.cam_b) for r in self.pairs),
                sum(k.camera == camera for k in self.links))

    @property
    def frames(self) -> list[str]:
        return sorted({k.frame for k in self.links})

    def sizes(self) -> dict[str, int]:
        """Measurements (6 rows each) per kind."""
        return {"depth": len(self.pairs), "board": len(self.links)}


GROUPS = ("depth", "board")


@dataclass(frozen=True)
class _Solution:
    T: dict[str, np.ndarray]
    chi2: float
    covariance: dict[str, np.ndarray]
    chi2_group: dict[str, float]
    n_free_nodes: int  # free cameras and board poses (6 unknowns each)


def prior_covariance(e: CameraExtrinsics, floor_mm: float = 0.01,
                     floor_deg: float = 0.001) -> np.ndarray:
    """6x6 [rot, trans] covariance of a calibrated pose: its full marginal when the
    calibration kept one, else diagonal from its sigmas (each the root of a 3-axis trace, so
    up to sqrt(3) too wide per axis: never tighter than the calibration claimed); at least
    ``floor_mm`` / ``floor_deg`` per axis (the reference camera has no sigma)."""
    floor = np.r_[np.full(3, math.radians(floor_deg) ** 2), np.full(3, (floor_mm / 1e3) ** 2)]
    if e.covariance is not None and np.all(np.isfinite(e.covariance)):
        return np.asarray(e.covariance, dtype=float) + np.diag(floor)
    s_rot, s_mm = e.sigma_rotation_deg, e.sigma_translation_mm
    var = np.r_[np.full(3, math.radians(s_rot if math.isfinite(s_rot) else 0.0) ** 2),
                np.full(3, (s_mm if math.isfinite(s_mm) else 0.0) ** 2 / 1e6)]
    return np.diag(np.maximum(var, floor))


def _as_evidence(evidence: Evidence | list[RelativePose]) -> Evidence:
    return evidence if isinstance(evidence, Evidence) else Evidence(tuple(evidence))


def _start_values(T_prior: dict[str, np.ndarray], ev: Evidence,
                  free: set[str]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Starting poses: a free camera from a held neighbour's measurement (a depth pair, else
    a board seen by both), centimetres closer than its prior; each board from a held camera
    that saw it (else from any camera that did)."""
    board: dict[str, np.ndarray] = {}
    for k in sorted(ev.links, key=lambda k: k.camera in free):  # held cameras first
        board.setdefault(k.frame, T_prior[k.camera] @ k.T_cam_board)
    start = dict(T_prior)
    for c in free:
        found = False
        for r in ev.pairs:
            if r.cam_a == c and r.cam_b not in free:
                start[c], found = T_prior[r.cam_b] @ r.T_b_a, True
                break
            if r.cam_b == c and r.cam_a not in free:
                start[c], found = T_prior[r.cam_a] @ invert_transform(r.T_b_a), True
                break
        if not found:
            held = {k.frame for k in ev.links if k.camera not in free}
            for k in ev.links:
                if k.camera == c and k.frame in held:
                    start[c] = board[k.frame] @ invert_transform(k.T_cam_board)
                    break
    return start, board


def _solve(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
           evidence: Evidence | list[RelativePose], free: set[str],
           scale: dict[str, float] | None = None) -> _Solution:
    """Pose graph: a prior on every camera not in ``free``, every depth pair as a between
    factor of two cameras, every board link as one between a camera and its frame set's board
    pose (free); each kind's covariance times ``scale`` (its variance factor)."""
    ev = _as_evidence(evidence)
    scale = scale or {}
    names = sorted(T_prior)
    frames = ev.frames
    key = {c: i for i, c in enumerate(names)}
    bkey = {f: len(names) + i for i, f in enumerate(frames)}
    graph = gtsam.NonlinearFactorGraph()
    for c in names:
        if c not in free:
            graph.add(gtsam.PriorFactorPose3(key[c], gtsam.Pose3(T_prior[c]),
                                             gtsam.noiseModel.Gaussian.Covariance(cov_prior[c])))
    first_pair = graph.size()
    s_d = scale.get("depth", 1.0)
    for r in ev.pairs:
        graph.add(gtsam.BetweenFactorPose3(key[r.cam_b], key[r.cam_a], gtsam.Pose3(r.T_b_a),
                                           gtsam.noiseModel.Gaussian.Information(
                                               r.information / s_d)))
    first_link = graph.size()
    s_b = scale.get("board", 1.0)
    for k in ev.links:
        graph.add(gtsam.BetweenFactorPose3(key[k.camera], bkey[k.frame],
                                           gtsam.Pose3(k.T_cam_board),
                                           gtsam.noiseModel.Gaussian.Covariance(
                                               k.covariance * s_b)))
    start, board = _start_values(T_prior, ev, free)
    values = gtsam.Values()
    for c in names:
        values.insert(key[c], gtsam.Pose3(start[c]))
    for f in frames:
        values.insert(bkey[f], gtsam.Pose3(board[f]))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    marginals = gtsam.Marginals(graph, result)
    T = {c: result.atPose3(key[c]).matrix() for c in names}
    cov = {c: marginals.marginalCovariance(key[c]) for c in names}
    err = [2.0 * graph.at(i).error(result) for i in range(graph.size())]
    # chi-square per kind in the units of its unscaled covariance
    groups = {"prior": float(sum(err[:first_pair])),
              "depth": s_d * float(sum(err[first_pair:first_link])),
              "board": s_b * float(sum(err[first_link:]))}
    return _Solution(T, float(sum(err)), cov, groups, len(free) + len(frames))


def try_solve(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
              evidence: Evidence | list[RelativePose], free: set[str],
              scale: dict[str, float] | None = None) -> _Solution | None:
    """:func:`_solve`, or None when the evidence leaves a free camera undetermined (GTSAM's
    indeterminate system: e.g. one pair whose information lacks the direction an unknown
    depth scale explains)."""
    try:
        return _solve(T_prior, cov_prior, evidence, free, scale)
    except RuntimeError:
        return None


def _components(names: list[str], ev: Evidence) -> list[set[str]]:
    """The groups of cameras connected by pairs or by a board both saw (scipy's connected
    components; board poses are nodes of the graph, not of the groups returned)."""
    frames = ev.frames
    index = {c: i for i, c in enumerate(names)}
    index |= {("board", f): len(names) + i for i, f in enumerate(frames)}
    edges = [[index[r.cam_a], index[r.cam_b]] for r in ev.pairs]
    edges += [[index[k.camera], index[("board", k.frame)]] for k in ev.links]
    e = np.array(edges, dtype=int).reshape(-1, 2)
    n = len(index)
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return [{c for c in names if label[index[c]] == g} for g in np.unique(label[:len(names)])]


def anchored(names: list[str], evidence: Evidence | list[RelativePose], free: set[str]) -> bool:
    """Every connected group of cameras keeps at least one prior (else its pose is free)."""
    return all(group - free for group in _components(names, _as_evidence(evidence)))


def _camera_check(c: str, sol: _Solution, T_prior: dict[str, np.ndarray],
                  cov_prior: dict[str, np.ndarray], chi2: float, n_pairs: int,
                  status: Status) -> CameraCheck:
    deg, mm = transform_error(sol.T[c], T_prior[c])
    sigma_deg, sigma_mm = covariance_sigmas(sol.covariance[c] + cov_prior[c])
    return CameraCheck(
        c, status, moved_mm=mm, moved_deg=deg, sigma_mm=sigma_mm, sigma_deg=sigma_deg,
        chi2=chi2, n_pairs=n_pairs, T_ref_cam_now=sol.T[c],
        covariance_now=sol.covariance[c])


def variance_factors(sol: _Solution, evidence: Evidence | list[RelativePose]
                     ) -> dict[str, float]:
    """A-posteriori variance factor of each kind of evidence (``depth``, ``board``), at least
    1: its chi-square over its share of the redundancy (6 rows per measurement; the free
    cameras' and board poses' 6 unknowns each shared by the kinds in proportion to their
    rows). The pairs' sigmas come from the D435 noise model and miss what it leaves out
    (surfaces that slide along rails and floors, a noisy single frame); the board poses'
    from the corner noise miss a board moving while unsynchronised cameras capture it. Each is
    scaled up by what its own residuals show, as a bundle adjustment's sigma_0 does, so a few
    millimetres of pair error is not taken for a knocked camera."""
    ev = _as_evidence(evidence)
    n = ev.sizes()
    total = sum(n.values())
    out = {}
    for g in GROUPS:
        dof = 6.0 * n[g] - 6.0 * sol.n_free_nodes * (n[g] / total) if total else 0.0
        out[g] = max(1.0, sol.chi2_group[g] / dof) if dof > 0 else 1.0
    return out


def weighed_solve(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
                  evidence: Evidence | list[RelativePose], free: set[str],
                  iterations: int = 4) -> tuple[_Solution, dict[str, float]] | None:
    """:func:`try_solve` with each kind of evidence scaled by its own variance factor, found
    as variance-component estimation finds it (Foerstner 1979; the fixed point of factor =
    the kind's chi-square at that factor over its redundancy share, from 1): the solution and
    the factors, or None (undetermined)."""
    ev = _as_evidence(evidence)
    scale = {g: 1.0 for g in GROUPS}
    sol = try_solve(T_prior, cov_prior, ev, free)
    for _ in range(iterations):
        if sol is None:
            return None
        new = variance_factors(sol, ev)
        if all(abs(new[g] - scale[g]) <= 0.05 * scale[g] for g in GROUPS):
            break
        scale = new
        sol = try_solve(T_prior, cov_prior, ev, free, scale)
    return (sol, scale) if sol is not None else None


def locate_moved(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
                 evidence: Evidence | list[RelativePose], tolerance: Tolerance = Tolerance(),
                 chi2_threshold: float = MOVED_CHI2) -> dict[str, CameraCheck]:
    """Which cameras moved, from the calibrated poses ``T_prior`` (camera -> T_ref_cam) with
    their covariances and the ``evidence`` (depth pairs and board links): greedily free the
    camera whose prior the evidence contradicts most, while that is significant and its move
    exceeds ``tolerance``. Significance: the fall in chi-square (priors and evidence) when the
    camera's prior is removed, both solves with each kind of evidence scaled by the variance
    factors of the solve without that prior (:func:`weighed_solve`: a camera that moved
    inflates the factors of the solve that holds it), above ``chi2_threshold``. Then every
    camera's move with its own prior removed (the moved ones stay free), at the final factors.
    A camera in no measurement is ``unknown``. When releasing another camera explains the
    evidence about as well (its drop within ``chi2_threshold`` of the chosen one's), the
    evidence cannot tell which of them moved: both are ``unknown``, each ``reason`` naming the
    other and the move, and neither is put back by a fix."""
    ev = _as_evidence(evidence)
    names = sorted(T_prior)
    n_meas = {c: sum(ev.count(c)) for c in names}
    checkable = [c for c in names if n_meas[c]]
    moved: list[str] = []
    ambiguous: dict[str, list[str]] = {}
    weighed = weighed_solve(T_prior, cov_prior, ev, set()) if checkable else None
    s2 = weighed[1] if weighed is not None else {g: 1.0 for g in GROUPS}
    while weighed is not None:  # (None: the evidence determines nothing; every camera as is)
        drops: dict[str, tuple[float, tuple[_Solution, dict[str, float]]]] = {}
        for c in checkable:
            free = set(moved) | {c}
            if c in moved or not anchored(names, ev, free):
                continue
            trial = weighed_solve(T_prior, cov_prior, ev, free)
            held = try_solve(T_prior, cov_prior, ev, set(moved), trial[1]) if trial else None
            if trial is None or held is None:
                continue
            drops[c] = (held.chi2 - trial[0].chi2, trial)
        if not drops:
            break
        c = max(drops, key=lambda k: drops[k][0])
        drop, (sol, factors) = drops[c]
        if drop <= chi2_threshold:
            break
        deg, mm = transform_error(sol.T[c], T_prior[c])
        if mm <= tolerance.mm and deg <= tolerance.deg:
            break
        # another camera whose release explains the evidence about as well: it cannot
        # tell which of them moved (e.g. two cameras that overlap only each other)
        rivals = sorted(k for k, (d, _) in drops.items()
                        if k != c and d > chi2_threshold and d >= drop - chi2_threshold)
        if rivals:
            ambiguous[c] = rivals
        moved.append(c)
        s2 = factors
    out: dict[str, CameraCheck] = {}
    for c in names:
        if not n_meas[c]:
            out[c] = CameraCheck(c, "unknown", reason="no overlapping camera's depth fits its "
                                 "own (no accepted pair) and no board seen with another "
                                 "camera: cannot be checked")
            continue
        held = set(moved) - {c}
        if c in moved:
            with_prior = try_solve(T_prior, cov_prior, ev, held, s2)
            sol = try_solve(T_prior, cov_prior, ev, set(moved), s2)
            status: Status = "moved"
        elif anchored(names, ev, held | {c}):
            with_prior = try_solve(T_prior, cov_prior, ev, held, s2)
            sol = try_solve(T_prior, cov_prior, ev, held | {c}, s2)
            status = "in_place"
        else:  # its group has no other held camera: the move is relative to nothing
            out[c] = CameraCheck(c, "in_place", n_pairs=n_meas[c], chi2=0.0,
                                 reason="the only held camera of its overlapping group")
            continue
        if sol is None or with_prior is None:
            out[c] = CameraCheck(c, "moved" if c in moved else "unknown", n_pairs=n_meas[c],
                                 reason="its pairs leave its pose undetermined (e.g. one pair "
                                 "and an unknown depth scale): cannot be measured alone")
            continue
        out[c] = _camera_check(c, sol, T_prior, cov_prior,
                               max(with_prior.chi2 - sol.chi2, 0.0), n_meas[c], status)
    return _ambiguous_unknown(out, ambiguous, moved)


def _ambiguous_unknown(out: dict[str, CameraCheck], ambiguous: dict[str, list[str]],
                       moved: list[str]) -> dict[str, CameraCheck]:
    """A released camera whose release a rival's explains about as well: it and the rivals
    are ``unknown`` (one of them moved; the evidence cannot say which), never named moved or
    in place."""
    for c, rivals in ambiguous.items():
        rivals = [k for k in rivals if k not in moved]  # a moved one is no rival
        if not rivals or out[c].status != "moved":
            continue
        move = f"{out[c].moved_mm:.1f} mm / {out[c].moved_deg:.2f} deg"
        out[c] = replace(out[c], status="unknown", reason=(
            f"it or {', '.join(rivals)} moved ({move} if it was {c}): the evidence cannot tell "
            "which (releasing either explains it about as well; they overlap too few other "
            "cameras); hold the board where both see it, or re-calibrate"))
        for k in rivals:
            out[k] = replace(out[k], status="unknown", reason=(
                f"it or {c} moved (the evidence cannot tell which: releasing either explains "
                f"it about as well; {c} would have moved {move})"))
    return out


def kinds_disagree(T: dict[str, np.ndarray], cov: dict[str, np.ndarray], evidence: Evidence,
                   fixed: set[str]) -> dict[str, str]:
    """Per fixed camera seen by both kinds of evidence: where the depth pairs alone and the
    board alone put it (the others held at ``T`` with ``cov``), when the two are further apart
    than their sigmas allow (Mahalanobis distance squared of the difference beyond
    :data:`MOVED_CHI2`): a fixed pose the evidence does not agree on. Each kind is scaled by
    its own variance factor."""
    out = {}
    for c in sorted(fixed):
        n_depth, n_board = evidence.count(c)
        if not (n_depth and n_board):
            continue
        held = sorted(T)
        sols = []
        for ev in (Evidence(evidence.pairs), Evidence.of([], evidence.links, set(held))):
            if not sum(ev.count(c)) or not anchored(held, ev, {c}):
                break
            weighed = weighed_solve(T, cov, ev, {c})
            if weighed is None:
                break
            sols.append(weighed[0])
        if len(sols) < 2:
            continue
        d = np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(sols[0].T[c]).between(
            gtsam.Pose3(sols[1].T[c]))))
        C = sols[0].covariance[c] + sols[1].covariance[c]  # body frames ~equal: close poses
        m2 = float(d @ np.linalg.solve(C, d))
        if m2 > MOVED_CHI2:
            deg, mm = transform_error(sols[0].T[c], sols[1].T[c])
            out[c] = (f"the depth pairs and the board put it {mm:.1f} mm / {deg:.2f} deg "
                      f"apart, beyond their sigmas (chi2 {m2:.0f})")
    return out


def adjoint_map(T_a_b: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose3(T_a_b).AdjointMap()`` (6x6, [rot, trans]): the same matrix as
    :func:`rgbd_calib.core.geometry.adjoint`, computed by GTSAM (the check's covariances were
    always carried with it)."""
    return gtsam.Pose3(T_a_b).AdjointMap()
