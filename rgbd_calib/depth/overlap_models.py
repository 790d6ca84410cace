"""The cameras' overlaps as measurements on their depth models (issue 33, item 2).

Each camera's depth model is fitted on the board (:mod:`.depth_model_fit`), at the board's
depths; the scene beyond is an extrapolation, known to the board fit's covariance (5-20 mm at
3-4 m from a board held to 2 m). Where two cameras see one surface, at the board's extrinsics,
they must put it in one place: the median signed surface distance of the pair
(:mod:`.agreement`'s measure, the fused cloud's own) is a measurement of both cameras' depth
models that reaches where the board did not.

The update is linear-Gaussian. The prior is each camera's board-fitted model, over its free
terms, with that fit's covariance. The measurements are each overlapping pair's median,
``median(theta_a, theta_b) = 0``. The median's standard error comes from the spread of the
medians of image blocks (neighbouring pixels share their depth error), at least
:data:`SE_FLOOR_MM`, plus what the two cameras' extrinsic uncertainty moves it by. Its
Jacobian is that of the mean of the pair's central half: the points between its quartiles at
the board's models, held fixed, differentiated numerically once (the medians are nearly linear
in the parameters). A few Gauss-Newton steps, each from the current models' medians; the
posterior covariance is the models' new covariance.

Why the medians and not every point (tried first, ``tools/experiment_joint_depth.py``): per
point the mixed pixels, occluders and grazing surfaces of a real scene do not cancel, and the
fit took the whole rig 9-15 mm short. The pair's median is robust to them. And the overlaps
see differences between cameras only, never a shift the whole rig shares; that stays the
board's, through the prior. A camera whose board fit kept no term (the identity) is held as
it is, and anchors its pairs only as well as that fit knows its depth where they lie."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..core.depth_model import DepthModel
from .agreement import (
    MIN_POINTS,
    NormalGrid,
    Surface,
    image_blocks,
    match_points,
    median_se,
    plane_on_rays,
)
from .clouds import CameraCloud
from .depth_model_fit import STEP, DepthModelFit

OVERLAP_POINTS = 4000  # a's matched points per pair
SE_FLOOR_MM = 0.2  # a pair's median is not known better than this (the report's floor)
MAX_DISTANCE_M = 0.05  # a point farther from b's surface is not on it (the report's bound)
ITERATIONS = 3  # Gauss-Newton steps; measured: the medians settle after two
HELD_RAYS = 256  # of a pair's central half: the rays a held camera's depth sigma is taken over


@dataclass(frozen=True)
class OverlapSamples:
    """One pair's matched points as the cameras measured them: a's rays (z = 1) and depths
    ``(N,3)``, ``(N,)``; the window of b's pixels around each one's projection, their rays
    and depths ``(N,K,3)``, ``(N,K)`` and which are there ``(N,K)``; b's normal (b's frame)
    ``(N,3)``; the noise of each point's distance (m, :func:`~.agreement.match_points`'s, at
    least 0.1 mm: a per-point residual's scale, ``tools/experiment_joint_depth.py``); each
    point's image block in a (:func:`~.agreement.image_blocks`)."""

    cam_a: str
    cam_b: str
    rays_a: np.ndarray
    z_a: np.ndarray
    rays_b: np.ndarray
    z_b: np.ndarray
    valid_b: np.ndarray
    normal_b: np.ndarray
    sigma_m: np.ndarray
    block: np.ndarray

    def select(self, rows: np.ndarray) -> OverlapSamples:
        """These samples at ``rows`` only (every per-point array taken at them)."""
        return replace(self, **{f: getattr(self, f)[rows] for f in (
            "rays_a", "z_a", "rays_b", "z_b", "valid_b", "normal_b", "sigma_m", "block")})


@dataclass(frozen=True)
class PairMedian:
    """One pair's median signed surface distance (mm, + = a's depth beyond b's surface) and
    its standard error (mm: the blocks' spread, the floor and the extrinsics), over ``n``
    matched points."""

    cam_a: str
    cam_b: str
    median_mm: float
    se_mm: float
    n: int

    def to_dict(self) -> dict[str, Any]:
        return {"cam_a": self.cam_a, "cam_b": self.cam_b, "median_mm": self.median_mm,
                "se_mm": self.se_mm, "n": self.n}


@dataclass(frozen=True)
class PairsHeldOut:
    """How well the overlaps' update predicts pairs it was not made from: each pair's median
    (in its standard errors) predicted by the update made without that pair (``update``),
    and by the board's models alone (``board``), as the mean square over the pairs.
    ``rejected``: the update predicted them no better and the board's models are kept."""

    update: float
    board: float
    pairs: int
    rejected: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {"update": self.update, "board": self.board, "pairs": self.pairs,
                "rejected": self.rejected}


def normal_equations(prior_info: np.ndarray, moved: np.ndarray,
                     medians: list[PairMedian], jacobian: dict[tuple[str, str], np.ndarray],
                     ) -> tuple[np.ndarray, np.ndarray]:
    """``H`` and ``g`` of the linear-Gaussian update (the module docstring): the board fits'
    information ``prior_info`` about the parameters ``moved`` from them, and each pair's
    median (m) with its derivative ``jacobian`` (per m), weighed by its standard error."""
    H = prior_info.copy()
    g = prior_info @ moved
    for m in medians:
        J = jacobian[m.cam_a, m.cam_b]
        s2 = (m.se_mm * 1e-3) ** 2
        H += np.outer(J, J) / s2
        g += J * (m.median_mm * 1e-3) / s2
    return H, g


def held_out_pairs(prior_info: np.ndarray, before: list[PairMedian],
                   jacobian: dict[tuple[str, str], np.ndarray]) -> PairsHeldOut | None:
    """:class:`PairsHeldOut` of the linear-Gaussian update (the module docstring) at the
    board's models: each pair left out in turn, the others' information and medians
    (``before``, with their derivatives ``jacobian``) update the models, which then predict
    the left-out pair's median; None with fewer than 3 pairs."""
    rows = [(m, jacobian[m.cam_a, m.cam_b]) for m in before if (m.cam_a, m.cam_b) in jacobian]
    if len(rows) < 3:
        return None
    H, g = normal_equations(prior_info, np.zeros(len(prior_info)), [m for m, _ in rows],
                            jacobian)
    update, board = [], []
    for m, J in rows:
        s2 = (m.se_mm * 1e-3) ** 2
        step = -np.linalg.lstsq(H - np.outer(J, J) / s2, g - J * (m.median_mm * 1e-3) / s2,
                                rcond=None)[0]
        update.append((m.median_mm * 1e-3 + J @ step) ** 2 / s2)
        board.append((m.median_mm * 1e-3) ** 2 / s2)
    return PairsHeldOut(float(np.mean(update)), float(np.mean(board)), len(rows))


@dataclass(frozen=True)
class OverlapUpdate:
    """The depth models after the overlaps (cameras with free terms), their covariances (of
    the free terms, in the order of each model's ``sigmas``), and the pairs' medians before
    and after."""

    models: dict[str, DepthModel]
    covariances: dict[str, np.ndarray]
    before: tuple[PairMedian, ...]
    after: tuple[PairMedian, ...]
    iterations: int
    # camera -> how far the update moved its model in the board fit's covariance (chi-square,
    # as many dof as it has free parameters): a move beyond the board's uncertainty says the
    # board and the overlaps disagree
    shift_chi2: dict[str, float] = field(default_factory=dict)
    # each pair's median predicted by the update made without it, against the board's models
    # (:func:`held_out_pairs`); None: fewer than 3 pairs. ``held_out.rejected``: the update
    # predicts them no better and is not applied (the board's models stay)
    held_out: PairsHeldOut | None = None

    @property
    def applied(self) -> bool:
        return self.held_out is None or not self.held_out.rejected

    def to_dict(self) -> dict[str, Any]:
        return {"iterations": self.iterations,
                **({"held_out": self.held_out.to_dict()} if self.held_out is not None else {}),
                "cameras": {c: {"shift_chi2": self.shift_chi2.get(c),
                                "dof": len(self.models[c].sigmas)} for c in sorted(self.models)},
                "pairs": [{**b.to_dict(), "median_after_mm": a.median_mm,
                           "se_after_mm": a.se_mm} for b, a in zip(self.before, self.after)]}


def measured_rays(cloud: CameraCloud, model: DepthModel | None) -> tuple[np.ndarray, np.ndarray]:
    """Each point's ray (z = 1) and measured depth: ``model`` undone (NaN where it has no
    answer)."""
    pts = cloud.points.astype(float)
    if model is not None and not model.is_identity:
        pts = model.measured_points(pts)
    z = pts[:, 2]
    return pts / np.where(np.isfinite(z) & (z > 0), z, np.nan)[:, None], z


def overlap_samples(clouds: dict[str, CameraCloud], T_ref_cam: dict[str, np.ndarray],
                    pairs: list[tuple[str, str]], models: dict[str, DepthModel],
                    seed: int = 0, grids: dict[str, NormalGrid] | None = None,
                    ) -> list[OverlapSamples]:
    """The matched points of every pair of ``pairs`` (clouds as corrected by ``models``),
    matched as the report matches them (:func:`~.agreement.match_points`); ``grids`` the
    clouds' normals where known (else estimated here)."""
    rng = np.random.default_rng(seed)
    used = {x for p in pairs for x in p
            if x in clouds and x in T_ref_cam and clouds[x].n_points >= MIN_POINTS}
    surf = {c: Surface.of(clouds[c], (grids or {}).get(c)) for c in used}
    raw = {c: measured_rays(clouds[c], models.get(c)) for c in used}
    out = []
    for a, b in pairs:
        if a not in surf or b not in surf:
            continue
        cloud_a = clouds[a]
        pick = rng.choice(cloud_a.n_points, min(cloud_a.n_points, 4 * OVERLAP_POINTS),
                          replace=False)
        m = match_points(cloud_a, surf[b], np.linalg.inv(T_ref_cam[b]) @ T_ref_cam[a], pick,
                         MAX_DISTANCE_M)
        keep = np.flatnonzero(np.isfinite(raw[a][1][m.ia]))[:OVERLAP_POINTS]
        if keep.size < 200:
            continue
        ia, idx = m.ia[keep], m.idx[keep]
        valid = idx >= 0
        jb = np.where(valid, idx, 0)
        valid &= np.isfinite(raw[b][1][jb])
        out.append(OverlapSamples(a, b, raw[a][0][ia], raw[a][1][ia],
                                  np.nan_to_num(raw[b][0][jb]),
                                  np.nan_to_num(raw[b][1][jb], nan=1.0), valid,
                                  m.normal_b[keep], np.maximum(m.sigma[keep], 1e-4),
                                  image_blocks(cloud_a.pixels[ia], cloud_a.intrinsics)))
    return out


def signed_distances(ma: DepthModel, mb: DepthModel, o: OverlapSamples, T_b_a: np.ndarray,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """a's points corrected by ``ma`` against the plane of b's window corrected by ``mb``
    where b's ray through a's point meets it, along b's normal (m, + = a's depth beyond b's
    surface; NaN where no plane); with a's points and the planes' points in b's frame."""
    pa = ma.correct_points(o.rays_a, o.z_a) @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    k = o.z_b.shape[1]
    q = mb.correct_points(o.rays_b.reshape(-1, 3), o.z_b.reshape(-1)).reshape(-1, k, 3)
    valid = o.valid_b & np.isfinite(q[..., 2])
    centre, ok, _ = plane_on_rays(np.nan_to_num(q, nan=1.0), valid, pa[:, :2] / pa[:, 2:])
    d = -np.einsum("ij,ij->i", pa - centre, o.normal_b)
    return np.where(ok, d, np.nan), pa, centre


def _extrinsics_variance(o: OverlapSamples, central: np.ndarray, pa: np.ndarray,
                         centre: np.ndarray, T_b_a: np.ndarray,
                         cov: dict[str, np.ndarray | None]) -> float:
    """What the two cameras' extrinsic uncertainty (body-frame ``[rot, trans]`` 6x6 each)
    moves the mean of the central half by (m^2): a turn or shift of a moves its points, of b
    its surface, each seen along b's normal."""
    n = o.normal_b[central]
    R = T_b_a[:3, :3]
    p_a = (pa[central] - T_b_a[:3, 3]) @ R  # a's points in a's frame
    n_a = n @ R  # b's normal in a's frame
    J_a = -np.hstack([np.cross(p_a, n_a), n_a]).mean(axis=0)
    J_b = np.hstack([np.cross(centre[central], n), n]).mean(axis=0)
    var = 0.0
    for J, c in ((J_a, o.cam_a), (J_b, o.cam_b)):
        C = cov.get(c)
        if C is not None and np.all(np.isfinite(C)):
            var += float(J @ C @ J)
    return var


def _held_variance(fit: DepthModelFit, points: np.ndarray) -> float:
    """What a held camera's depth may be off by where the pair lies (m^2): its board fit's
    every-term sigma of the mean depth over ``points`` (its own frame, as measured), or the
    gap to that fit where larger (as :func:`~.depth_model_fit.beyond_board` counts it)."""
    pts = points[np.isfinite(points[:, 2]) & (points[:, 2] > 0)]
    if pts.shape[0] == 0:
        return 0.0
    pts = pts[:: max(1, pts.shape[0] // HELD_RAYS)]
    z = float(np.median(pts[:, 2]))
    rays = pts / pts[:, 2:]
    mm = max(fit.correction_sigma_mm(z, rays), abs(fit.model_gap_mm(z, rays)))
    return (1e-3 * mm) ** 2


def _statistics(models: dict[str, DepthModel], o: OverlapSamples, T_b_a: np.ndarray,
                cov: dict[str, np.ndarray | None], held: dict[str, DepthModelFit],
                ) -> tuple[PairMedian, np.ndarray] | None:
    """The pair's median (with its standard error) and its central half, or None when fewer
    than 100 points have a surface."""
    d, pa, centre = signed_distances(models[o.cam_a], models[o.cam_b], o, T_b_a)
    ok = np.isfinite(d)
    if np.count_nonzero(ok) < 100:
        return None
    med = float(np.median(d[ok]))
    q1, q3 = np.percentile(d[ok], [25, 75])
    central = np.flatnonzero(ok & (d >= q1) & (d <= q3))
    se2 = (max(median_se(d[ok], o.block[ok]), SE_FLOOR_MM * 1e-3) ** 2
           + _extrinsics_variance(o, central, pa, centre, T_b_a, cov))
    if o.cam_a in held:
        se2 += _held_variance(held[o.cam_a], o.rays_a[central] * o.z_a[central, None])
    if o.cam_b in held:
        se2 += _held_variance(held[o.cam_b], centre[central])
    return PairMedian(o.cam_a, o.cam_b, 1e3 * med, 1e3 * float(np.sqrt(se2)),
                      int(np.count_nonzero(ok))), central


def _central_mean(models: dict[str, DepthModel], o: OverlapSamples, T_b_a: np.ndarray
                  ) -> float:
    """The mean signed distance of ``o`` (its central half, :meth:`OverlapSamples.select`)."""
    return float(np.nanmean(signed_distances(models[o.cam_a], models[o.cam_b], o, T_b_a)[0]))


def _jacobian(models: dict[str, DepthModel], o: OverlapSamples, T_b_a: np.ndarray,
              central: np.ndarray, free: dict[str, tuple[str, ...]],
              index: dict[tuple[str, str], int]) -> np.ndarray:
    """The derivative of the pair's central mean by every free parameter (forward
    differences of :data:`~.depth_model_fit.STEP`; each point's distance is its own, so the
    central half is computed alone)."""
    o = o.select(central)
    base = _central_mean(models, o, T_b_a)
    J = np.zeros(len(index))
    for c in (o.cam_a, o.cam_b):
        for p in free.get(c, ()):
            trial = {**models, c: models[c].with_values({p: models[c].value(p) + STEP[p]})}
            J[index[c, p]] = (_central_mean(trial, o, T_b_a) - base) / STEP[p]
    return J


def update_models(models: dict[str, DepthModel], covariances: dict[str, np.ndarray],
                  overlaps: list[OverlapSamples], T_ref_cam: dict[str, np.ndarray],
                  extrinsics_cov: dict[str, np.ndarray | None] | None = None,
                  held: dict[str, DepthModelFit] | None = None,
                  iterations: int = ITERATIONS) -> OverlapUpdate | None:
    """The linear-Gaussian update of the models of the cameras in ``covariances`` (camera ->
    covariance of its model's free parameters, in the order of its ``sigmas``) by the pairs'
    medians (module docstring); every other camera of ``models`` is held. A held camera
    with a board fit in ``held`` (its model the identity, say: the board saw no need for a
    term) is no better known where the pair lies than that fit says beyond the board: its
    pairs' standard errors gain that (:func:`_held_variance`). None when no pair involves a
    camera with free parameters."""
    held = held or {}
    free = {c: tuple(models[c].sigmas) for c in covariances if models[c].sigmas}
    overlaps = [o for o in overlaps if (o.cam_a in free or o.cam_b in free)
                and o.cam_a in models and o.cam_b in models]
    if not overlaps or not free:
        return None
    index = {(c, p): k for k, (c, p) in enumerate((c, p) for c in sorted(free)
                                                  for p in free[c])}
    n = len(index)
    prior_info = np.zeros((n, n))
    theta0 = np.zeros(n)
    for c, ps in free.items():
        k = [index[c, p] for p in ps]
        prior_info[np.ix_(k, k)] = np.linalg.pinv(covariances[c])
        theta0[k] = [models[c].value(p) for p in ps]
    cov = extrinsics_cov or {}
    T_b_a = {(o.cam_a, o.cam_b): np.linalg.inv(T_ref_cam[o.cam_b]) @ T_ref_cam[o.cam_a]
             for o in overlaps}
    current = dict(models)
    before: list[PairMedian] = []
    H = prior_info
    done = 0
    jacobian: dict[tuple[str, str], np.ndarray] = {}  # at the board's models: nearly linear
    for it in range(iterations):
        theta = np.array([current[c].value(p) for c, p in index])
        medians = []
        for o in overlaps:
            T = T_b_a[o.cam_a, o.cam_b]
            got = _statistics(current, o, T, cov, held)
            if got is None:
                continue
            pm, central = got
            medians.append(pm)
            if (o.cam_a, o.cam_b) not in jacobian:
                jacobian[o.cam_a, o.cam_b] = _jacobian(current, o, T, central, free, index)
        if it == 0:
            before = medians
        if not medians:
            return None
        H, g = normal_equations(prior_info, theta - theta0, medians, jacobian)
        step = -np.linalg.solve(H, g)
        current = {c: (m.with_values({p: m.value(p) + step[index[c, p]] for p in free[c]})
                       if c in free else m) for c, m in current.items()}
        done = it + 1
        if np.all(np.abs(step) < 1e-2 * np.array([STEP[p] for _, p in index])):
            break
    post = np.linalg.inv(H)
    after = []
    for o in overlaps:
        got = _statistics(current, o, T_b_a[o.cam_a, o.cam_b], cov, held)
        if got is not None:
            after.append(got[0])
    by_pair = {(m.cam_a, m.cam_b): m for m in after}
    pairs_before = tuple(m for m in before if (m.cam_a, m.cam_b) in by_pair)
    out_models, out_cov, shift = {}, {}, {}
    moved = np.array([current[c].value(p) for c, p in index]) - theta0
    for c, ps in free.items():
        k = [index[c, p] for p in ps]
        C = post[np.ix_(k, k)]
        out_cov[c] = C
        shift[c] = float(moved[k] @ prior_info[np.ix_(k, k)] @ moved[k])
        out_models[c] = replace(current[c], sigmas={p: float(np.sqrt(max(C[i, i], 0.0)))
                                                    for i, p in enumerate(ps)})
    held_pairs = held_out_pairs(prior_info, before, jacobian)
    if held_pairs is not None and held_pairs.update >= held_pairs.board:
        held_pairs = replace(held_pairs, rejected=True)
    return OverlapUpdate(out_models, out_cov, pairs_before,
                         tuple(by_pair[m.cam_a, m.cam_b] for m in pairs_before), done, shift,
                         held_pairs)


def recorrected(cloud: CameraCloud, old: DepthModel | None, new: DepthModel) -> CameraCloud:
    """``cloud`` (corrected by ``old``) corrected by ``new`` instead: each point back to the
    depth the camera measured on its ray, then through ``new``; points either model has no
    answer for, or whose correction ``new`` holds at its physical bound, are dropped."""
    rays, z = measured_rays(cloud, old)
    pts = new.correct_points(rays, z, drop_beyond_bounds=True)
    ok = np.isfinite(pts[:, 0]) & np.isfinite(z)
    return replace(cloud.select(ok), points=pts[ok].astype(cloud.points.dtype))
