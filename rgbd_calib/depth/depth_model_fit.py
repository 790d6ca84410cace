"""Each camera's depth model estimated from the board (the model:
:mod:`rgbd_calib.core.depth_model`).

The colour calibration puts the board in every view it saw, metric through the printed markers
and independent of depth, so every depth pixel on the board face has a known true surface: the
face plane ``n . p = d`` (camera frame, m). Under the model's parameters ``theta`` each pixel
has a predicted measurement, the depth the camera reports for that plane
(:func:`predicted_depth_m`); the residual is measured minus predicted, in units of the depth
noise (the D435 model of :mod:`.noise`). Gauss-Newton with Huber weights (IRLS) solves for the
free parameters, with each view's plane error a random effect where its board pose's
covariance is known (``_solve``). The report's board-plane residuals are the corrected points'
signed distances to the plane (:func:`plane_residuals_m`).

Which terms a camera gets is chosen by evidence:

- forward selection over :data:`LADDER` (scale and disparity offset together, then the offset's
  gradients, its curvature, the depth-to-colour pose): at each step the first step in that
  order whose Wald statistic ``theta_t^T C_t^-1 theta_t`` exceeds ``k F_{k, views -
  parameters}(1 - P_FALSE_TERM)`` (never below ``k ln(views)``), ``C`` the cluster-robust
  covariance with the views as clusters, never below the model-based one. A step of ``k``
  parameters is tried only on more than ``k`` views (:func:`step_fits_views`);
- a camera given any term gets every term where its views can judge all of them
  (``depth.model_fit.model_terms: auto`` and :data:`EVERY_TERM_MIN_VIEWS`; ``all``: always),
  since over the board's depth range the terms trade with each other and one left out biases
  the rest beyond the board; ``evidence`` keeps the ladder's terms only;
- the model is applied only when it predicts each board view, refitted without that view,
  better than the raw depth does (:func:`held_out_cost`); otherwise the camera keeps the
  identity. A clean camera keeps the identity.

The measurements behind each rule (the terms' trade-offs, few views, plane errors):
docs/depth.md, "Few board views", "From 15 views", "The board's planes as uncertain as their
poses"."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.stats import chi2 as chi2_dist
from scipy.stats import f as f_dist

from ..core.camera import CameraIntrinsics
from ..core.config import DepthConfig
from ..core.depth_model import PARAMETERS, RATIO_MAX, RATIO_MIN, TERMS, DepthModel, identity_model
from ..core.geometry import skew
from .clouds import BoardFacePixels, DisparityMoment, face_sigma_z
from .noise import depth_noise

# the evidence ladder's steps, each a group of TERMS freed together (see the module docstring)
LADDER: tuple[tuple[str, ...], ...] = (("scale", "offset"), ("gradient",), ("curvature",),
                                       ("pose",))
P_FALSE_TERM = 1e-3  # chance that a term a clean camera does not need passes its test
MAX_PIXELS_PER_VIEW = 1500  # board pixels sampled per view (evenly)
GN_ITERATIONS = 8
BACKTRACK = tuple(0.5**k for k in range(20))  # Gauss-Newton step fractions tried in turn
MIN_CLUSTER_DOF = 4  # views beyond the parameters for the clustered (F) test
# depth.model_fit.model_terms auto: every term from two views beyond the parameters (the
# every-term fit's clustered covariance then has a view to spare; docs/depth.md, 'From 15
# views')
EVERY_TERM_MIN_VIEWS = len(PARAMETERS) + 2
# central-difference steps per parameter, in the model's units (scale, px, deg, mm)
STEP = {"scale": 1e-5, "d0": 1e-3, "dx": 1e-3, "dy": 1e-3, "dxx": 1e-3, "dxy": 1e-3,
        "dyy": 1e-3, "rx": 1e-3, "ry": 1e-3, "rz": 1e-3, "tx": 1e-2, "ty": 1e-2, "tz": 1e-2}
BANDS_M = (0.0, 1.0, 1.5, 2.0, 3.0, math.inf)  # distance bands of the board-plane residuals
GAP_SIGMAS = 3.0  # the applied model's distance from the every-term fit counts beyond this


@dataclass(frozen=True)
class BoardSamples:
    """One camera's depth pixels on the board: rays ``(N,3)`` (z = 1), measured depth (m),
    the face plane per pixel (unit normal ``(N,3)``, distance m), the depth noise sigma (m)
    and the view each pixel came from (index into ``frames``)."""

    rays: np.ndarray
    z_measured: np.ndarray
    normal: np.ndarray
    distance_m: np.ndarray
    sigma_z: np.ndarray
    view: np.ndarray
    frames: tuple[str, ...]
    pixels: np.ndarray  # (N,2) u, v
    # per view the covariance (3x3, 1/m^2) of the error of its face plane in inverse depth,
    # ``delta(1/z) = u . (x, y, 1)`` (:func:`plane_covariance`; zeros: the plane taken as
    # exact); None: every plane taken as exact
    plane_cov: np.ndarray | None = None

    @property
    def sigma_m(self) -> np.ndarray:
        """The noise of each residual (m): depth noise along the ray onto the normal."""
        return self.sigma_z * np.abs(np.sum(self.normal * self.rays, axis=1))


def plane_covariance(normal: np.ndarray, distance_m: float,
                     pose_covariance: np.ndarray) -> np.ndarray:
    """Covariance (3x3, 1/m^2) of a face plane's error in inverse depth from the covariance of
    the board pose it came from (6x6 ``[rot rad, trans m]``, a left perturbation in the
    camera frame: ``p -> p + omega x p + v``). The plane ``n . p = d`` seen along a ray
    ``(x, y, 1)`` is at ``1/z = n . ray / d``; the perturbation moves ``n`` by ``omega x n`` and
    ``d`` by ``n . v``, so ``delta(1/z) = u . ray`` with ``u = delta_n / d - n delta_d / d^2``,
    linear in the pose error: ``u = M xi``, covariance ``M C M^T``."""
    n = np.asarray(normal, dtype=float)
    d = float(distance_m)
    M = np.hstack([-skew(n) / d, -np.outer(n, n) / d**2])
    cov = M @ np.asarray(pose_covariance, dtype=float) @ M.T
    return 0.5 * (cov + cov.T)


def board_samples(intr: CameraIntrinsics, faces: list[tuple[str, BoardFacePixels]],
                  config: DepthConfig | None = None,
                  pose_covariance: dict[str, np.ndarray] | None = None) -> BoardSamples | None:
    """The depth pixels of the board ``faces`` (:func:`~.clouds.board_faces`: one camera's
    views), at most :data:`MAX_PIXELS_PER_VIEW` per view, sampled evenly; None without any.
    ``pose_covariance`` (frame -> the 6x6 covariance of the view's board pose in the camera
    frame, as :func:`plane_covariance` takes it) gives each view's plane its uncertainty: the
    fit then takes each plane's error as a random effect of the view (``_solve``); a view
    without one, or no ``pose_covariance``, keeps its plane exact."""
    config = config or DepthConfig()
    noise = depth_noise(intr, config)
    parts, frames = [], []
    for frame, face in faces:
        pick = np.linspace(0, face.us.size - 1, min(face.us.size, MAX_PIXELS_PER_VIEW))
        pick = np.unique(pick.astype(int))
        us, vs = face.us[pick], face.vs[pick]
        parts.append((intr.rays(us, vs), face.z_measured[pick],
                      np.tile(face.normal, (pick.size, 1)), np.full(pick.size, face.distance_m),
                      face_sigma_z(noise, intr, face.z_true[pick]),
                      np.full(pick.size, len(frames)), np.column_stack([us, vs])))
        frames.append(frame)
    if not parts:
        return None
    cols = [np.concatenate([p[i] for p in parts]) for i in range(7)]
    plane_cov = None
    if pose_covariance:
        plane_cov = np.zeros((len(frames), 3, 3))
        for v, (frame, face) in enumerate(faces):
            if frame in pose_covariance:
                plane_cov[v] = plane_covariance(face.normal, face.distance_m,
                                                pose_covariance[frame])
    return BoardSamples(cols[0], cols[1], cols[2], cols[3], cols[4], cols[5].astype(int),
                        tuple(frames), cols[6], plane_cov)


def plane_residuals_m(model: DepthModel, s: BoardSamples) -> np.ndarray:
    """Signed distance (m) of each corrected board pixel to its face plane (NaN: no depth)."""
    p = model.correct_points(s.rays, s.z_measured)
    return np.sum(s.normal * p, axis=1) - s.distance_m


def predicted_depth_m(model: DepthModel, s: BoardSamples,
                      inverse_offset: np.ndarray | float = 0.0) -> np.ndarray:
    """What each board pixel should have measured under ``model``: the true depth where the
    pixel's ray, moved by the model's pose, meets the face plane (``z = (d - n.t) / (n.R ray)``),
    through :meth:`DepthModel.measured_depth`. A function of the plane alone: fitting measured
    minus predicted keeps the noise out of the regressors (no errors-in-variables bias, which
    the corrected-point distance has: its Jacobian holds the noisy depth squared).
    ``inverse_offset`` (1/m, per pixel) moves the plane: ``1/z`` plus it (a view's plane error,
    ``_solve``)."""
    T = model.T_true_measured()
    inv = (np.einsum("ij,ij->i", s.normal, s.rays @ T[:3, :3].T)
           / (s.distance_m - s.normal @ T[:3, 3]))
    inv = inv + inverse_offset
    z = np.divide(1.0, inv, out=np.full_like(inv, -1.0), where=inv > 0)
    return model.measured_depth(s.rays[:, 0], s.rays[:, 1], z)


ROTATION_STEP_DEG = 1e-4  # central difference of the 3 x 3 rotation (error ~1e-9 relative)


def predicted_depth_jacobian(model: DepthModel, s: BoardSamples, names: tuple[str, ...],
                             inverse_offset: np.ndarray | float = 0.0,
                             ) -> tuple[np.ndarray, np.ndarray]:
    """The derivatives of :func:`predicted_depth_m` (m) by the parameters ``names`` (per unit
    of :data:`~rgbd_calib.core.depth_model.UNITS`: ``(N, k)``) and by ``inverse_offset``
    (1/m: ``(N,)``), in closed form through the chain ``plane -> 1/z -> z -> z_m`` (the
    rotation's derivative by central differences of the 3 x 3 matrix alone). Zero where the
    prediction has no answer or the model's ratio is held at its bound (the prediction is
    flat there). It equals the central differences of :func:`predicted_depth_m` at
    :data:`STEP` to their truncation error (tests/test_depth_physical.py) at a fraction of
    their cost: 27 predictions per Gauss-Newton iteration became one pass."""
    v = model.value
    T = model.T_true_measured()
    R, t = T[:3, :3], T[:3, 3]
    den = s.distance_m - s.normal @ t
    num = np.einsum("ij,ij->i", s.normal, s.rays @ R.T)
    inv = num / den + inverse_offset
    live = inv > 0
    z = np.divide(1.0, inv, out=np.zeros_like(inv), where=live)
    x, y = s.rays[:, 0], s.rays[:, 1]
    basis = {"d0": np.ones_like(x), "dx": x, "dy": y, "dxx": x * x, "dxy": x * y,
             "dyy": y * y}
    kappa = model.disparity_offset_px(x, y) / model.focal_baseline_px_m
    denom = 1.0 + z * kappa
    pos = denom > 1e-12
    denom = np.where(pos, denom, 1.0)
    ratio = v("scale") / denom
    live &= pos & (ratio > RATIO_MIN) & (ratio < RATIO_MAX)
    d_kappa = -v("scale") * z * z / (denom * denom)  # d z_m / d kappa
    d_inv = -(v("scale") / (denom * denom)) * z * z  # d z_m / d z  times  d z / d(1/z)
    cols = []
    for p in names:
        if p == "scale":
            col = z / denom
        elif p in basis:
            col = d_kappa * basis[p] / model.focal_baseline_px_m
        elif p in ("rx", "ry", "rz"):
            h = ROTATION_STEP_DEG
            up = model.with_values({p: v(p) + h}).T_true_measured()[:3, :3]
            dn = model.with_values({p: v(p) - h}).T_true_measured()[:3, :3]
            dR = (up - dn) / (2 * h)
            col = d_inv * np.einsum("ij,ij->i", s.normal, s.rays @ dR.T) / den
        else:  # tx ty tz (mm): 1/den grows by n_i / den^2
            k = "xyz".index(p[1])
            col = d_inv * num * s.normal[:, k] * 1e-3 / (den * den)
        cols.append(np.where(live, col, 0.0))
    J = np.column_stack(cols) if cols else np.zeros((len(z), 0))
    return J, np.where(live, d_inv, 0.0)


@dataclass(frozen=True)
class HeldOut:
    """How well a depth model predicts board views it was not fitted to: each view's pixels
    predicted by the model refitted without that view (``model``), and by the raw depth, no
    model (``identity``), as the Huber cost per pixel of the residuals in noise sigmas (0.5:
    the noise alone). ``rejected``: the model predicted them no better, and the camera keeps
    its raw depth."""

    model: float
    identity: float
    views: int
    rejected: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "identity": self.identity, "views": self.views,
                "rejected": self.rejected}


def held_out_cost(solve: _Solve, base: DepthModel, s: BoardSamples, huber_k: float
                  ) -> HeldOut | None:
    """:class:`HeldOut` of ``solve``'s model against ``base`` (the identity) on ``s``: each
    view left out in turn, the model moved by one Gauss-Newton step on the other views'
    pixels (exact for a model linear in its parameters; every view's plane where the colour
    calibration put it, no plane error fitted), the left-out pixels predicted on their plane.
    None without parameters or with fewer than 3 views."""
    n_views = len(s.frames)
    if not solve.names or n_views < 3:
        return None
    dp, _ = predicted_depth_jacobian(solve.model, s, solve.names)
    pred = predicted_depth_m(solve.model, s)
    r = np.where(pred > 0, s.z_measured - pred, np.nan) / s.sigma_z
    ok = np.isfinite(r)
    r, J = np.where(ok, r, 0.0), np.where(ok[:, None], -dp / s.sigma_z[:, None], 0.0)
    w = np.where(ok, _huber(r, huber_k), 0.0)
    H = J.T @ (w[:, None] * J)
    g_all = J.T @ (w * r)
    costs, raw = [], []
    raw_pred = predicted_depth_m(base, s)
    raw_r = np.where(raw_pred > 0, s.z_measured - raw_pred, np.nan) / s.sigma_z
    for v in range(n_views):
        m = (s.view == v) & ok & np.isfinite(raw_r)
        if not np.any(m):
            continue
        Hv = J[m].T @ (w[m, None] * J[m])
        gv = J[m].T @ (w[m] * r[m])
        # without view v the score is g_all - gv: the step that zeroes it
        delta = -np.linalg.lstsq(H - Hv, g_all - gv, rcond=None)[0]
        costs.append(_huber_cost(r[m] + J[m] @ delta, huber_k))
        raw.append(_huber_cost(raw_r[m], huber_k))
    if not costs:
        return None
    n = float(sum(c.size for c in costs))
    return HeldOut(float(sum(c.sum() for c in costs)) / n, float(sum(c.sum() for c in raw)) / n,
                   len(costs))


def _huber_cost(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 0.5 * a * a, k * a - 0.5 * k * k)


@dataclass(frozen=True)
class TermTest:
    """The evidence for one step of :data:`LADDER` when it was last tested (``term``: its terms
    joined by ``+``, e.g. ``scale+offset``): its Wald statistic, the threshold it had to
    exceed, and whether it was kept."""

    term: str
    wald: float
    threshold: float
    kept: bool

    def to_dict(self) -> dict[str, Any]:
        return {"term": self.term, "wald": self.wald, "threshold": self.threshold,
                "kept": self.kept}


@dataclass(frozen=True)
class DepthModelFit:
    """A camera's chosen :class:`DepthModel` with the tests of its terms and the board-plane
    residuals by distance band before (the identity) and after the model (mm): per band
    ``[z_min, z_max, n, median_before, median_after, p90_before, p90_after, noise]``, where
    p90 is of the absolute residual and ``noise`` the median 1-sigma depth noise there."""

    camera: str
    model: DepthModel
    tests: tuple[TermTest, ...]
    bands: tuple[tuple[float, ...], ...]
    n_views: int
    n_samples: int
    sigma_factor: float  # sqrt(chi2 / dof) of the chosen fit: the noise model's accuracy
    n_unseen_views: int = 0  # of n_views: the board where the camera did not detect it
    # depth.model_fit.model_terms auto kept the ladder's terms: n_views < EVERY_TERM_MIN_VIEWS
    too_few_views: bool = False
    # the fit with every term free whatever the ladder chose: what the data say of the depth
    # beyond the board (correction_sigma_mm); not written to files
    law_model: DepthModel | None = None
    law_names: tuple[str, ...] = ()
    law_cov: np.ndarray | None = None
    # the applied model's covariance (of ``model``'s free parameters, in the order of its
    # ``sigmas``); None: none estimated (the identity)
    model_cov: np.ndarray | None = None
    # each board view predicted by the model fitted without it, against the raw depth
    # (:class:`HeldOut`); None: the identity, nothing to judge
    held_out: HeldOut | None = None

    def correction_sigma_mm(self, z_measured_m: float, rays: np.ndarray | None = None) -> float:
        """1 sigma (mm) of the true depth this camera's data give for a measured depth
        ``z_measured_m``: the covariance of the fit with every term free propagated through
        :meth:`DepthModel.correct_points` (the depth along the ray and the depth-to-colour
        pose), on the image centre's ray, or of the mean over ``rays`` ((N,3), z = 1: where
        the cloud lies, whose bias is what the sigma is for). Beyond the board's depth range
        it grows fast (the stereo law extrapolated; docs/depth.md)."""
        if self.law_model is None or not self.law_names or self.law_cov is None:
            return 0.0
        return _depth_sigma_mm(self.law_model, self.law_names, self.law_cov, z_measured_m,
                               rays)

    def model_gap_mm(self, z_measured_m: float, rays: np.ndarray | None = None) -> float:
        """The applied model's true depth minus the every-term fit's (mm) for a measured depth
        ``z_measured_m`` on the image centre's ray (or their means over ``rays``): what the
        terms the applied model left out would move there. Within the board's range it is
        small (both fit the board); beyond, a left-out term that trades with the kept ones
        over the board's range (the depth sensor's ``tz`` with scale and offset) makes it the
        applied model's bias, which the every-term fit's sigma does not hold (docs/depth.md,
        'Few board views')."""
        if self.law_model is None or not self.law_names:
            return 0.0
        return 1e3 * (_depth_m(self.model, z_measured_m, rays)
                      - _depth_m(self.law_model, z_measured_m, rays))

    def model_gap_sigma_mm(self, z_measured_m: float, rays: np.ndarray | None = None) -> float:
        """1 sigma (mm) of :meth:`model_gap_mm` where the applied model is right: the applied
        model is then the efficient fit and the every-term fit's variance is its plus the
        gap's (Hausman), ``sqrt(sigma_all^2 - sigma_applied^2)``."""
        law = self.correction_sigma_mm(z_measured_m, rays)
        names = tuple(self.model.sigmas)  # the order of ``model_cov``
        own = (_depth_sigma_mm(self.model, names, self.model_cov, z_measured_m, rays)
               if names and self.model_cov is not None else 0.0)
        return math.sqrt(max(law * law - own * own, 0.0))

    @staticmethod
    def prior_moment(prior_deg: float = 0.0, prior_mm: float = 0.0,
                     ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`sensor_pose_moment` of a camera with no fit: zero and the prior's
        covariance (``prior_deg`` / ``prior_mm`` per axis; zeros without a prior)."""
        return np.zeros(6), np.diag((SENSOR_POSE_UNITS * np.array(
            [prior_deg] * 3 + [prior_mm] * 3)) ** 2)

    def disparity_moment(self) -> DisparityMoment | None:
        """What a cloud NOT corrected for this camera's disparity offset keeps of it (the
        clouds calibrate registers: divided by their depth-scale factor alone): the every-term
        fit's offset coefficients and their covariance, as a second moment about zero (an
        estimated bias the cloud carries, and what it may still be off). None without the
        every-term fit. A D435's offset of 0.2 px leaves such a cloud 4 cm short at 2 m,
        every point of it together, and a pair registered on it that far off."""
        if self.law_model is None or self.law_cov is None or not set(DISPARITY) <= set(
                self.law_names):
            return None
        k = [self.law_names.index(p) for p in DISPARITY]
        mean = np.array([self.law_model.value(p) for p in DISPARITY])
        return DisparityMoment(self.law_model.focal_baseline_px_m,
                               np.outer(mean, mean) + self.law_cov[np.ix_(k, k)])

    def sensor_pose_moment(self, prior_deg: float = 0.0, prior_mm: float = 0.0,
                           ) -> tuple[np.ndarray, np.ndarray]:
        """The rigid error ``eps`` (6, ``[omega rad, v m]``, GTSAM's order) that the depth
        sensor's pose leaves on a cloud that is not corrected for it (``measured = Exp(eps)
        true``, to first order: ``eps = -(rx, ry, rz, tx, ty, tz)``), and its covariance
        (6x6): the every-term fit's (which frees the pose whatever the ladder chose), combined
        with a zero-mean prior of ``prior_deg`` / ``prior_mm`` per axis where given (0: no
        prior). On a few views that fit leaves the pose nearly free (it trades with the
        disparity gradients over a flat board): the prior then holds it. Without the fit's
        pose terms: the prior alone (zeros without one)."""
        _, P = self.prior_moment(prior_deg, prior_mm)
        if self.law_model is None or self.law_cov is None or not set(SENSOR_POSE) <= set(
                self.law_names):
            return np.zeros(6), P
        k = [self.law_names.index(p) for p in SENSOR_POSE]
        eps = -SENSOR_POSE_UNITS * np.array([self.law_model.value(p) for p in SENSOR_POSE])
        C = SENSOR_POSE_UNITS[:, None] * self.law_cov[np.ix_(k, k)] * SENSOR_POSE_UNITS[None, :]
        if not np.any(P):
            return eps, C
        # the posterior of the fit (eps, C) and the prior (0, P), in the form that holds for a
        # nearly singular C: P - P (P + C)^-1 P and P (P + C)^-1 eps
        gain = np.linalg.solve(P + C, P).T  # P (P + C)^-1
        return gain @ eps, P - gain @ P

    def to_dict(self) -> dict[str, Any]:
        return {
            "camera": self.camera,
            "model": self.model.to_dict(),
            "tests": [t.to_dict() for t in self.tests],
            "bands": [dict(zip(("z_min_m", "z_max_m", "n", "median_before_mm",
                                "median_after_mm", "p90_before_mm", "p90_after_mm",
                                "noise_mm"), b)) for b in self.bands],
            "n_views": self.n_views,
            "n_samples": self.n_samples,
            "n_unseen_views": self.n_unseen_views,
            "sigma_factor": self.sigma_factor,
        } | ({"held_out": self.held_out.to_dict()} if self.held_out is not None else {})


SENSOR_POSE = ("rx", "ry", "rz", "tx", "ty", "tz")  # the depth sensor's pose terms
DISPARITY = ("d0", "dx", "dy", "dxx", "dxy", "dyy")  # the disparity offset's coefficients
SENSOR_POSE_UNITS = np.array([math.pi / 180.0] * 3 + [1e-3] * 3)  # deg, mm -> rad, m


def applied_pose_moment(correction: DepthModel | float | None, prior_deg: float = 0.0,
                        prior_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """What the depth sensor's pose may still leave on a cloud already corrected by
    ``correction`` (``check`` and ``refine`` register such clouds): zero, and the covariance
    of the rigid error ``eps`` (6, ``[omega rad, v m]``) the correction did not take out. A
    model whose ``terms`` free the pose took out its estimate: what remains is that
    estimate's error (its ``sigmas``, diagonal; the file keeps no correlations). A model that
    holds the pose at the factory value, a depth-scale factor or nothing took out nothing:
    the zero-mean prior of ``prior_deg`` / ``prior_mm`` per axis (zeros: the pose taken as
    exact)."""
    if isinstance(correction, DepthModel) and "pose" in correction.terms and set(
            SENSOR_POSE) <= set(correction.sigmas):
        sigma = np.array([correction.sigmas[p] for p in SENSOR_POSE])
        return np.zeros(6), np.diag((SENSOR_POSE_UNITS * sigma) ** 2)
    return DepthModelFit.prior_moment(prior_deg, prior_mm)


CENTRE_RAY = np.array([[0.0, 0.0, 1.0]])
FAR_RAYS = 256  # of a cloud's points beyond the board: the rays its far sigma is taken over


def _depth_m(model: DepthModel, z_measured_m: float, rays: np.ndarray | None) -> float:
    """``model``'s true depth (m) for a measured depth on the image centre's ray, or its mean
    over ``rays`` ((N,3), z = 1) where the model has an answer (NaN where it has none)."""
    r = CENTRE_RAY if rays is None else np.asarray(rays, dtype=float).reshape(-1, 3)
    z = model.correct_points(r, np.full(len(r), float(z_measured_m)))[:, 2]
    return float(np.mean(z[np.isfinite(z)])) if np.isfinite(z).any() else math.nan


def _depth_sigma_mm(model: DepthModel, names: tuple[str, ...], cov: np.ndarray,
                    z_measured_m: float, rays: np.ndarray | None) -> float:
    """1 sigma (mm) of :func:`_depth_m`, ``model``'s parameters ``names`` of covariance
    ``cov`` propagated by central differences."""
    J = np.array([(_depth_m(model.with_values({p: model.value(p) + STEP[p]}), z_measured_m,
                            rays)
                   - _depth_m(model.with_values({p: model.value(p) - STEP[p]}), z_measured_m,
                              rays)) / (2 * STEP[p])
                  for p in names])
    return float(1e3 * math.sqrt(max(float(J @ cov @ J), 0.0)))


@dataclass(frozen=True)
class BeyondBoard:
    """How much of a camera's cloud lies beyond the depths its model was fitted on, and how
    well its depth is known there: ``board_max_m`` the board's farthest depth (99th
    percentile), ``cloud_p90_m`` the 90th percentile of the cloud's depths, ``fraction`` of
    its points beyond ``board_max_m``, ``sigma_mm`` the applied model's 1-sigma error at
    ``cloud_p90_m``: the every-term fit's sigma there
    (:meth:`DepthModelFit.correction_sigma_mm`), or the applied model's distance from that
    fit (``model_gap_mm``, :meth:`DepthModelFit.model_gap_mm`) where that is larger and
    significant: beyond :data:`GAP_SIGMAS` of its own sigma if the applied model were right
    (:meth:`DepthModelFit.model_gap_sigma_mm`). A significant gap is the applied model's
    bias (the every-term fit is unbiased); an insignificant one is the every-term fit's own
    noise, which the sigma holds (the demo's race: gaps of 12-16 mm at 3.8 m from 12 views,
    1.8 of their sigmas, its clouds within 0.9 mm)."""

    camera: str
    board_max_m: float
    cloud_p90_m: float
    fraction: float
    sigma_mm: float
    model_gap_mm: float = 0.0

    def to_dict(self) -> dict[str, float]:
        return {"board_max_m": self.board_max_m, "cloud_p90_m": self.cloud_p90_m,
                "fraction": self.fraction, "sigma_mm": self.sigma_mm,
                "model_gap_mm": self.model_gap_mm}


def beyond_board(fit: DepthModelFit, z_cloud_m: np.ndarray,
                 rays: np.ndarray | None = None) -> BeyondBoard | None:
    """:class:`BeyondBoard` of the camera's cloud depths ``z_cloud_m`` (m; None without a
    depth range or points). With the points' ``rays`` ((N,3), z = 1) the sigma and the gap
    are taken over the rays of the points beyond the board (all points if none is; at most
    :data:`FAR_RAYS`), of their mean: where the cloud's far part lies in the image; without,
    on the image centre's ray, which misses what the gradients, curvature and pose tilt do
    off the centre."""
    z = np.asarray(z_cloud_m, dtype=float)
    ok = np.isfinite(z) & (z > 0)
    z = z[ok]
    rng = fit.model.depth_range_m
    if rng is None or z.size == 0:
        return None
    p90 = float(np.percentile(z, 90))
    far_rays = None
    if rays is not None:
        r = np.asarray(rays, dtype=float).reshape(-1, 3)[ok]
        beyond = r[z > rng[1]] if np.any(z > rng[1]) else r
        far_rays = beyond[np.linspace(0, len(beyond) - 1, min(FAR_RAYS, len(beyond))).astype(int)]
    gap, sigma = fit.model_gap_mm(p90, far_rays), fit.correction_sigma_mm(p90, far_rays)
    if abs(gap) > GAP_SIGMAS * fit.model_gap_sigma_mm(p90, far_rays):
        sigma = max(sigma, abs(gap))
    return BeyondBoard(fit.camera, float(rng[1]), p90, float(np.mean(z > rng[1])), sigma, gap)


def _huber(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


@dataclass(frozen=True)
class _Solve:
    model: DepthModel
    names: tuple[str, ...]
    cov: np.ndarray  # cluster-robust covariance of ``names`` (model units)
    chi2: float
    dof: int


def _solve(base: DepthModel, s: BoardSamples, names: tuple[str, ...], huber_k: float) -> _Solve:
    """Gauss-Newton with Huber IRLS for the parameters ``names`` (the others held at ``base``),
    and the covariance: the upper envelope of the sandwich ``H^-1 (sum_views g_v g_v^T) H^-1``
    of the views' score vectors and the model-based ``H^-1 max(chi2/dof, 1)``.

    A view whose plane has a covariance (``s.plane_cov``) gets its plane error ``u_v`` (3
    values, inverse depth: ``delta(1/z) = u_v . (x, y, 1)``) as a random effect: estimated
    with it, under the prior ``N(0, plane_cov_v)``, and marginalised out of ``H`` and the
    scores (Schur complement per view). A plane's error is a plane in inverse depth, the form
    the scale, offset, gradients and depth-to-colour pose take within one view, so it reaches
    all of them but the curvature; without it the board pose counts as exact, and views whose
    poses are off (the board where the camera did not detect it) make terms of their error
    (docs/depth.md, "The board's planes as uncertain as their poses")."""
    sigma = s.sigma_z
    n_views = len(s.frames)
    prior = _plane_priors(s)
    prior_sigma = {v: np.sqrt(np.diag(s.plane_cov[v]) + 1e-9 * np.trace(s.plane_cov[v]))
                   for v in prior}  # as _plane_priors' ridge: no zero sigma
    planes = np.zeros((n_views, 3))

    members = _ViewSpans(s.view, tuple(prior)) if prior else None

    def residual(m: DepthModel, offset: np.ndarray | float) -> np.ndarray:
        pred = predicted_depth_m(m, s, offset)
        return np.where(pred > 0, s.z_measured - pred, np.nan)

    def offsets(u: np.ndarray) -> np.ndarray | float:
        return np.einsum("ij,ij->i", u[s.view], s.rays) if prior else 0.0

    def weighted(m: DepthModel, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r = residual(m, offsets(u)) / sigma
        ok = np.isfinite(r)
        w = np.where(ok, _huber(np.where(ok, r, 0.0), huber_k), 0.0)
        return np.where(ok, r, 0.0), w, ok

    def jacobians(m: DepthModel, u: np.ndarray, ok: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray | None]:
        # the residual is measured minus predicted: its derivatives are the prediction's, negated
        dp, d_inv = predicted_depth_jacobian(m, s, names, offsets(u))
        J = np.where(ok[:, None], -dp / sigma[:, None], 0.0)
        if not prior:
            return J, None
        return J, np.where(ok, -d_inv / sigma, 0.0)[:, None] * s.rays

    def cost(r: np.ndarray, ok: np.ndarray, u: np.ndarray) -> tuple[float, int]:
        """The Huber cost of the whitened residuals ``r`` (``ok``: those that count) with the
        planes' priors at ``u``, and how many samples it counts."""
        a = np.abs(r[ok])
        rho = np.where(a <= huber_k, 0.5 * a * a, huber_k * a - 0.5 * huber_k**2)
        return (float(np.sum(rho)) + sum(0.5 * float(u[v] @ P @ u[v]) for v, P in prior.items()),
                int(np.count_nonzero(ok)))

    def cost_at(m: DepthModel, u: np.ndarray) -> tuple[float, int]:
        r = residual(m, offsets(u)) / sigma
        return cost(r, np.isfinite(r), u)

    model = base
    for _ in range(GN_ITERATIONS):
        r, w, ok = weighted(model, planes)
        J, B = jacobians(model, planes, ok)
        H, g, views = _reduced(J, B, r, w, members, prior, planes)
        if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
            break
        step = np.linalg.lstsq(H, -g, rcond=None)[0] if names else np.zeros(0)
        du = {v: -Hpp_inv @ (gp + Hmp.T @ step) for v, (Hpp_inv, Hmp, gp) in views.items()}
        # the full Gauss-Newton step where it lowers the cost (always, on a well-posed fit);
        # halved until it does where the parameters are barely held (a fit with as many
        # parameters as views: the step along a near-null direction can leave the model's
        # domain, every predicted depth negative)
        before, counted = cost(r, ok, planes)
        for t in BACKTRACK:
            m_t = model.with_values({p: model.value(p) + t * d for p, d in zip(names, step)})
            u_t = planes.copy()
            for v, d in du.items():
                u_t[v] += t * d
            after, n_t = cost_at(m_t, u_t)
            if n_t >= counted and after <= before * (1 + 1e-9) + 1e-9:
                break
        else:
            break  # no step lowers the cost: the solution
        moved = max((float(np.max(np.abs(t * d) / prior_sigma[v])) for v, d in du.items()),
                    default=0.0)  # the planes' largest step in their prior sigmas
        model, planes = m_t, u_t
        if (np.all(np.abs(t * step) < 1e-3 * np.array([STEP[p] for p in names]))
                and moved < 1e-3):
            break
    r, w, ok = weighted(model, planes)
    dof = max(int(np.count_nonzero(ok)) - len(names), 1)
    chi2 = float(np.sum(w * r * r)) + sum(float(planes[v] @ P @ planes[v])
                                          for v, P in prior.items())
    if not names:
        return _Solve(model, names, np.zeros((0, 0)), chi2, dof)
    # the last iteration's Jacobians (a step before the solution, as always): no second pass
    H, _, views = _reduced(J, B, r, w, members, prior, planes)
    Hinv = np.linalg.pinv(H)
    G = np.zeros((n_views, len(names)))
    np.add.at(G, s.view, J * (w * r)[:, None])
    for v, (Hpp_inv, Hmp, gp) in views.items():  # each view's score with its plane profiled
        G[v] -= Hmp @ Hpp_inv @ gp
    sandwich = Hinv @ (G.T @ G) @ Hinv * (n_views / max(n_views - 1, 1))
    model_based = Hinv * max(chi2 / dof, 1.0)
    # the smallest covariance at or above both in every direction: the sandwich of a few views
    # is singular in some directions, the model-based one blind to errors shared by a view
    e, V = np.linalg.eigh(sandwich - model_based)
    cov = model_based + (V * np.maximum(e, 0.0)) @ V.T
    return _Solve(model, names, cov, chi2, dof)


def _plane_priors(s: BoardSamples) -> dict[int, np.ndarray]:
    """view -> the information (inverse covariance) of its plane error, for the views whose
    plane has a usable covariance (a singular one, e.g. a pose known exactly along some
    direction, through its inverse with a tiny ridge; a non-finite one leaves the plane
    exact)."""
    if s.plane_cov is None:
        return {}
    out = {}
    for v, C in enumerate(s.plane_cov):
        scale = float(np.trace(C))
        if scale > 0 and np.all(np.isfinite(C)):  # a pose without a usable covariance: exact
            out[v] = np.linalg.inv(C + 1e-9 * scale * np.eye(3))
    return out


class _ViewSpans:
    """Each of the views ``views``' samples as one span ``[a, b)`` of the samples put in view
    order (``order``; None when they are in view order already, as :func:`board_samples`
    gives them), so that per-view sums are slices, not gathers."""

    def __init__(self, view: np.ndarray, views: tuple[int, ...]):
        order = np.argsort(view, kind="stable")
        self.order = None if np.array_equal(order, np.arange(len(view))) else order
        ordered = view if self.order is None else view[order]
        self.spans = [(int(a), int(b)) for a, b in zip(np.searchsorted(ordered, views, "left"),
                                                      np.searchsorted(ordered, views, "right"))]

    def ordered(self, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
        return arrays if self.order is None else tuple(a[self.order] for a in arrays)


def _reduced(J: np.ndarray, B: np.ndarray | None, r: np.ndarray, w: np.ndarray,
             members: _ViewSpans | None, prior: dict[int, np.ndarray], planes: np.ndarray,
             ) -> tuple[np.ndarray, np.ndarray, dict[int, tuple[np.ndarray, ...]]]:
    """The normal equations of the model's parameters with each random-effect view's plane
    marginalised (Schur complement): ``H``, the gradient ``g`` and per such view
    ``(Hpp^-1, Hmp, gp)`` to recover its plane's step (``members``: each view's samples,
    in the order of ``prior``)."""
    H = J.T @ (w[:, None] * J)
    g = J.T @ (w * r)
    views = {}
    if not prior or members is None:
        return H, g, views
    Js, Bs, rs, wB = members.ordered(J, B, r, w[:, None] * B)
    for (v, P), (a, b) in zip(prior.items(), members.spans):
        Hpp = Bs[a:b].T @ wB[a:b] + P
        Hmp = Js[a:b].T @ wB[a:b]
        gp = wB[a:b].T @ rs[a:b] + P @ planes[v]
        Hpp_inv = np.linalg.inv(Hpp)
        H -= Hmp @ Hpp_inv @ Hmp.T
        g -= Hmp @ Hpp_inv @ gp
        views[v] = (Hpp_inv, Hmp, gp)
    return H, g, views


def _params(step: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(p for t in step for p in TERMS[t])


def _wald(solve: _Solve, step: tuple[str, ...]) -> float:
    names = _params(step)
    idx = [solve.names.index(p) for p in names]
    theta = np.array([solve.model.value(p) - (1.0 if p == "scale" else 0.0) for p in names])
    C = solve.cov[np.ix_(idx, idx)]
    return float(theta @ np.linalg.pinv(C) @ theta)


def step_fits_views(n_step_params: int, n_views: int) -> bool:
    """Whether a ladder step of ``n_step_params`` parameters can be judged from ``n_views``
    board views: fewer parameters than views, so that the step's block of its cluster-robust
    covariance can be full rank (the module docstring)."""
    return n_step_params < n_views


def _threshold(step: tuple[str, ...], n_views: int, n_params: int) -> float:
    """What the Wald statistic of ``step`` must exceed: ``k F_{k, V - p}(1 - P)`` with ``V``
    views (the clusters) and ``p`` parameters in the trial (the small-sample law of a
    cluster-robust Wald test), never below the BIC's ``k ln V``. With fewer than
    :data:`MIN_CLUSTER_DOF` views to spare the clustered covariance cannot be judged and the
    chi-square quantile applies (the covariance is then at least the model-based one)."""
    k = len(_params(step))
    dof = n_views - n_params
    q = (k * float(f_dist.ppf(1.0 - P_FALSE_TERM, k, dof)) if dof >= MIN_CLUSTER_DOF
         else float(chi2_dist.ppf(1.0 - P_FALSE_TERM, k)))
    return max(q, k * math.log(max(n_views, 2)))


def _bands(before: np.ndarray, after: np.ndarray, z: np.ndarray,
           noise: np.ndarray) -> tuple[tuple[float, ...], ...]:
    out = []
    for lo, hi in zip(BANDS_M[:-1], BANDS_M[1:]):
        m = (z >= lo) & (z < hi) & np.isfinite(before) & np.isfinite(after)
        if np.count_nonzero(m) < 50:
            continue
        out.append((lo, hi, int(np.count_nonzero(m)),
                    float(np.median(before[m]) * 1e3), float(np.median(after[m]) * 1e3),
                    float(np.percentile(np.abs(before[m]), 90) * 1e3),
                    float(np.percentile(np.abs(after[m]), 90) * 1e3),
                    float(np.median(noise[m]) * 1e3)))
    return tuple(out)


def fit_depth_model(camera: str, samples: BoardSamples, intr: CameraIntrinsics,
                    config: DepthConfig | None = None) -> DepthModelFit:
    """The camera's depth model chosen by evidence from its board ``samples`` (see the module
    docstring), with its sigmas and the board-plane residuals before and after."""
    config = config or DepthConfig()
    base = identity_model(intr)
    n_views = len(samples.frames)
    chosen: list[str] = []
    current = identity = _solve(base, samples, (), config.model_fit.scale_huber_k)
    tests: dict[tuple[str, ...], TermTest] = {}
    while True:
        best = None
        for step in LADDER:
            if step[0] in chosen:
                continue
            names = tuple(p for t in TERMS if t in chosen or t in step for p in TERMS[t])
            if not step_fits_views(len(_params(step)), n_views):
                continue
            trial = _solve(current.model, samples, names, config.model_fit.scale_huber_k)
            wald, thr = _wald(trial, step), _threshold(step, n_views, len(names))
            tests[step] = TermTest("+".join(step), wald, thr, False)
            if wald > thr and best is None:  # the first in the ladder's order that passes
                best = (wald / thr, step, trial)
        if best is None:
            break
        chosen.extend(best[1])
        current = best[2]
        tests[best[1]] = replace(tests[best[1]], kept=True)
    # what the data say of the depth beyond the board, whatever the ladder chose: every term
    # free (the terms it left out are there on a real camera, only too small to show here)
    law = (current if current.names == PARAMETERS
           else _solve(current.model, samples, PARAMETERS, config.model_fit.scale_huber_k))
    # the camera needs a model: all of it, where the views can judge every term
    # (EVERY_TERM_MIN_VIEWS)
    judged = n_views >= EVERY_TERM_MIN_VIEWS
    too_few_views = bool(chosen) and config.model_fit.model_terms == "auto" and not judged
    terms = config.model_fit.model_terms
    if chosen and (terms == "all" or (terms == "auto" and judged)):
        chosen, current = [t for t in TERMS], law
    # kept only where it predicts board views it was not fitted to better than the raw depth
    held = held_out_cost(current, base, samples, config.model_fit.scale_huber_k) if chosen else None
    if held is not None and held.model >= held.identity:
        held, chosen, current, too_few_views = replace(held, rejected=True), [], identity, False
    sig = np.sqrt(np.maximum(np.diag(current.cov), 0.0)) if current.names else np.zeros(0)
    z = samples.z_measured
    model = DepthModel(
        base.focal_baseline_px_m, {p: current.model.value(p) for p in PARAMETERS
                                   if p in current.names},
        tuple(t for t in TERMS if t in chosen), dict(zip(current.names, map(float, sig))),
        (float(np.percentile(z, 1)), float(np.percentile(z, 99))),
        _image_coverage(samples.pixels, intr))
    before = plane_residuals_m(base, samples)
    after = plane_residuals_m(model, samples)
    # banded by the board's depth along each ray, not the measured one (whose noise would
    # select the pixels that read long into the far bands)
    z = samples.distance_m / np.sum(samples.normal * samples.rays, axis=1)
    return DepthModelFit(camera, model, tuple(tests[t] for t in LADDER if t in tests),
                         _bands(before, after, z, samples.sigma_m), n_views, len(z),
                         float(math.sqrt(current.chi2 / current.dof)),
                         law_model=law.model, law_names=law.names, law_cov=law.cov,
                         model_cov=current.cov if current.names else None,
                         too_few_views=too_few_views, held_out=held)


def _image_coverage(pixels: np.ndarray, intr: CameraIntrinsics, cells: int = 8) -> float:
    """Fraction of a ``cells`` x ``cells`` grid over the image that has board samples."""
    cu = np.clip(pixels[:, 0] * cells // intr.width, 0, cells - 1)
    cv = np.clip(pixels[:, 1] * cells // intr.height, 0, cells - 1)
    return float(len(set(zip(cu.tolist(), cv.tolist()))) / cells**2)
