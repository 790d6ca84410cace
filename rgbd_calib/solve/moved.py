"""Has a camera moved since the calibration? The inference of ``check`` on measured pairs.

A pose graph (GTSAM) of the measured depth pairs and one prior per camera at its calibrated
pose with the calibration's sigmas. A camera that moved makes every pair it is in disagree with
those priors. Which cameras moved is found greedily (:func:`locate_moved`): free the camera
whose prior costs most (the drop in chi-square when it is removed), as long as that drop is
significant and the camera's move is beyond the tolerance; the majority that agrees with the
calibration stays in place. Each camera's move is then estimated with its own prior removed,
with a sigma from the graph's marginal plus the calibration's own.
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
from .bundle import RelativePose

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
class _Solution:
    T: dict[str, np.ndarray]
    chi2: float
    covariance: dict[str, np.ndarray]


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


def _solve(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
           pairs: list[RelativePose], free: set[str]) -> _Solution:
    """Pose graph: a prior on every camera not in ``free``, every pair as a between factor;
    the free cameras start from a pair's measurement to a held camera."""
    names = sorted(T_prior)
    key = {c: i for i, c in enumerate(names)}
    graph = gtsam.NonlinearFactorGraph()
    for c in names:
        if c not in free:
            graph.add(gtsam.PriorFactorPose3(key[c], gtsam.Pose3(T_prior[c]),
                                             gtsam.noiseModel.Gaussian.Covariance(cov_prior[c])))
    for r in pairs:
        graph.add(gtsam.BetweenFactorPose3(key[r.cam_b], key[r.cam_a], gtsam.Pose3(r.T_b_a),
                                           gtsam.noiseModel.Gaussian.Information(r.information)))
    start = {c: T_prior[c] for c in names}
    for c in free:  # from a held neighbour's measurement (centimetres closer than the prior)
        for r in pairs:
            if r.cam_a == c and r.cam_b not in free:
                start[c] = T_prior[r.cam_b] @ r.T_b_a
                break
            if r.cam_b == c and r.cam_a not in free:
                start[c] = T_prior[r.cam_a] @ invert_transform(r.T_b_a)
                break
    values = gtsam.Values()
    for c in names:
        values.insert(key[c], gtsam.Pose3(start[c]))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    marginals = gtsam.Marginals(graph, result)
    T = {c: result.atPose3(key[c]).matrix() for c in names}
    cov = {c: marginals.marginalCovariance(key[c]) for c in names}
    return _Solution(T, 2.0 * graph.error(result), cov)


def try_solve(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
              pairs: list[RelativePose], free: set[str]) -> _Solution | None:
    """:func:`_solve`, or None when the pairs leave a free camera undetermined (GTSAM's
    indeterminate system: e.g. one pair whose information lacks the direction an unknown
    depth scale explains)."""
    try:
        return _solve(T_prior, cov_prior, pairs, free)
    except RuntimeError:
        return None


def _components(names: list[str], pairs: list[RelativePose]) -> list[set[str]]:
    """The groups of cameras connected by pairs (scipy's connected components)."""
    index = {c: i for i, c in enumerate(names)}
    edges = np.array([[index[r.cam_a], index[r.cam_b]] for r in pairs], dtype=int).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                       shape=(len(names), len(names)))
    _, label = connected_components(graph, directed=False)
    return [{c for c, k in zip(names, label) if k == g} for g in np.unique(label)]


def anchored(names: list[str], pairs: list[RelativePose], free: set[str]) -> bool:
    """Every connected group of cameras keeps at least one prior (else its pose is free)."""
    return all(group - free for group in _components(names, pairs))


def _camera_check(c: str, sol: _Solution, T_prior: dict[str, np.ndarray],
                  cov_prior: dict[str, np.ndarray], chi2: float, n_pairs: int,
                  status: Status, s2: float = 1.0) -> CameraCheck:
    deg, mm = transform_error(sol.T[c], T_prior[c])
    sigma_deg, sigma_mm = covariance_sigmas(s2 * sol.covariance[c] + cov_prior[c])
    return CameraCheck(
        c, status, moved_mm=mm, moved_deg=deg, sigma_mm=sigma_mm, sigma_deg=sigma_deg,
        chi2=chi2, n_pairs=n_pairs, T_ref_cam_now=sol.T[c],
        covariance_now=s2 * sol.covariance[c])


def variance_factor(sol: _Solution, n_pairs: int, n_free: int) -> float:
    """A-posteriori variance factor of a solve, at least 1: chi-square over its redundancy
    (6 per pair beyond the free cameras' 6). The pairs' sigmas come from the D435 noise model
    and miss what it leaves out (surfaces that slide along rails and floors, a noisy single
    frame); this scales them up by what the residuals show, as a bundle adjustment's
    sigma_0 does, so a few millimetres of pair error is not taken for a knocked camera."""
    dof = 6 * (n_pairs - n_free)
    return max(1.0, sol.chi2 / dof) if dof > 0 else 1.0


def locate_moved(T_prior: dict[str, np.ndarray], cov_prior: dict[str, np.ndarray],
                 pairs: list[RelativePose], tolerance: Tolerance = Tolerance(),
                 chi2_threshold: float = MOVED_CHI2) -> dict[str, CameraCheck]:
    """Which cameras moved, from the calibrated poses ``T_prior`` (camera -> T_ref_cam) with
    their covariances and the measured ``pairs``: greedily free the camera whose prior the
    pairs contradict most, while that is significant (the chi-square drop, over the variance
    factor of the solve without that prior, above ``chi2_threshold``) and its move exceeds
    ``tolerance``; then every camera's move with its own prior removed (the moved ones stay
    free), its covariance scaled by the final variance factor. A camera in no pair is
    ``unknown``. When another camera's release explains the pairs about as well (its drop
    within ``chi2_threshold`` of the chosen one's), the chosen camera's ``reason`` names it:
    the depth cannot tell which of them moved."""
    names = sorted(T_prior)
    n_pairs = {c: sum(c in (r.cam_a, r.cam_b) for r in pairs) for c in names}
    checkable = [c for c in names if n_pairs[c]]
    moved: list[str] = []
    ambiguous: dict[str, list[str]] = {}
    s2 = 1.0
    base = try_solve(T_prior, cov_prior, pairs, set()) if pairs else None
    if base is not None:
        s2 = variance_factor(base, len(pairs), 0)
        while True:
            drops: dict[str, tuple[float, _Solution]] = {}
            for c in checkable:
                free = set(moved) | {c}
                if c in moved or not anchored(names, pairs, free):
                    continue
                sol = try_solve(T_prior, cov_prior, pairs, free)
                if sol is None:
                    continue
                drop = (base.chi2 - sol.chi2) / variance_factor(sol, len(pairs), len(free))
                drops[c] = (drop, sol)
            if not drops:
                break
            c = max(drops, key=lambda k: drops[k][0])
            drop, sol = drops[c]
            if drop <= chi2_threshold:
                break
            deg, mm = transform_error(sol.T[c], T_prior[c])
            if mm <= tolerance.mm and deg <= tolerance.deg:
                break
            # another camera whose release explains the pairs about as well: the depth cannot
            # tell which of them moved (e.g. two cameras that overlap only each other)
            rivals = sorted(k for k, (d, _) in drops.items()
                            if k != c and d > chi2_threshold and d >= drop - chi2_threshold)
            if rivals:
                ambiguous[c] = rivals
            moved.append(c)
            base = sol
            s2 = variance_factor(sol, len(pairs), len(moved))
    out: dict[str, CameraCheck] = {}
    for c in names:
        if not n_pairs[c]:
            out[c] = CameraCheck(c, "unknown", reason="no overlapping camera's depth fits its "
                                 "own (no accepted pair): cannot be checked")
            continue
        held = set(moved) - {c}
        if c in moved:
            with_prior = try_solve(T_prior, cov_prior, pairs, held)
            sol = base
            status: Status = "moved"
        elif anchored(names, pairs, held | {c}):
            with_prior = base
            sol = try_solve(T_prior, cov_prior, pairs, held | {c})
            status = "in_place"
        else:  # its group has no other held camera: the move is relative to nothing
            out[c] = CameraCheck(c, "in_place", n_pairs=n_pairs[c], chi2=0.0,
                                 reason="the only held camera of its overlapping group")
            continue
        if sol is None or with_prior is None:
            out[c] = CameraCheck(c, "moved" if c in moved else "unknown", n_pairs=n_pairs[c],
                                 reason="its pairs leave its pose undetermined (e.g. one pair "
                                 "and an unknown depth scale): cannot be measured alone")
            continue
        out[c] = _camera_check(c, sol, T_prior, cov_prior,
                               max(with_prior.chi2 - sol.chi2, 0.0) / s2, n_pairs[c], status, s2)
        rivals = [k for k in ambiguous.get(c, []) if k not in moved]  # a moved one is no rival
        if rivals:
            out[c] = replace(out[c], reason=(
                f"or {', '.join(rivals)}: the depth cannot tell which moved (releasing "
                "either explains the pairs about as well; they overlap too few other cameras)"))
    return out


def adjoint_map(T_a_b: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose3(T_a_b).AdjointMap()`` (6x6, [rot, trans]): the same matrix as
    :func:`rgbd_calib.core.geometry.adjoint`, computed by GTSAM (the check's covariances were
    always carried with it)."""
    return gtsam.Pose3(T_a_b).AdjointMap()
