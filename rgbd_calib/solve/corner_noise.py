"""The noise of a marker's four corners: its centre and its shape weighed apart.

An edge-fitted marker's corners are the intersections of its four fitted outline lines, so they
do not err independently: noise that moves the outline's lines apart or together (the edge
fit's threshold, blur, the bits' pull) changes the marker's shape and leaves its centre where
it was. Measured on renders against the true corners (docs/accuracy.md, "Honest sigmas on
short recordings"): the corners err by 0.030 px, their mean by 0.0065 px, where four
independent corners would give 0.015. A model that takes every corner as independent counts
that shape noise as pose information lost, and its covariances come out 2-4x too wide in
variance on short recordings.

:class:`CornerNoise` splits each marker's 8 residuals (4 corners x (u, v)) into two orthogonal
subspaces: the centre (the corners' mean, broadcast to the four: 2 dimensions, what a
translation of the marker moves) and the shape (the rest: 6 dimensions), each with its own
sigma. Its covariance ``sigma_shape^2 P_s + sigma_centre^2 P_c`` (``P`` the orthogonal
projectors) is whitened by ``P_s / sigma_shape + P_c / sigma_centre``. With the two sigmas
equal it is the independent model. :func:`estimate_corner_noise` reads both sigmas from a
solve's corner residuals (variance components, as Foerstner's factor for one group);
:func:`scale_covariance` is what no number of views averages out, the rig's scale as the
detector sees the board. Pure numpy (and the bundle's config); used by
:mod:`rgbd_calib.solve.bundle_factors`, :mod:`rgbd_calib.solve.bundle` and
:mod:`rgbd_calib.solve.ladder`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.config import BundleConfig

MIN_MARKERS = 50  # fewer markers than this keep the independent model: too few to split
RATIO_BOUNDS = (0.2, 2.0)  # the centre-to-shape sigma ratio an estimate is clipped to


@dataclass(frozen=True)
class CornerNoise:
    """A marker's corner noise: ``sigma_px`` in the shape subspace, ``sigma_px * centre_ratio``
    in the centre subspace (per dimension of an orthonormal basis of each; the centre's
    coordinate along a unit basis vector is twice the corners' mean, so a marker's mean
    corner errs by ``centre_sigma_px / 2`` per axis). ``centre_ratio == 1``: every corner
    independent at ``sigma_px``."""

    sigma_px: float
    centre_ratio: float = 1.0

    @property
    def centre_sigma_px(self) -> float:
        """The centre subspace's sigma (px per dimension)."""
        return self.sigma_px * self.centre_ratio

    @property
    def independent(self) -> bool:
        return self.centre_ratio == 1.0

    def whiten(self, r: np.ndarray) -> np.ndarray:
        """Residuals ``(n, 8)`` (4 corners x (u, v) per marker, px) whitened: ``r /
        sigma_shape`` plus each marker's corner mean times ``1 / sigma_centre - 1 /
        sigma_shape``."""
        return self.whiten_rows(np.asarray(r, dtype=float)[..., None])[..., 0]

    def whiten_rows(self, J: np.ndarray) -> np.ndarray:
        """Jacobian rows grouped by marker (``(8 n, d)``, or ``(n, 8, d)``) whitened as
        :meth:`whiten` does residuals. Same shape as ``J``."""
        J = np.asarray(J, dtype=float)
        inv = 1.0 / self.sigma_px
        if self.independent:
            return J * inv
        y = J.reshape(-1, 4, 2, J.shape[-1])
        mean = y.mean(axis=1, keepdims=True)
        return (y * inv + mean * (inv / self.centre_ratio - inv)).reshape(J.shape)


def split_sums(residuals_px: np.ndarray) -> tuple[float, float]:
    """The corner residuals ``(n, 4, 2)`` px split into the centre and the shape subspace:
    their sums of squares ``(SS_centre, SS_shape)``; the two add up to the whole sum."""
    r = np.asarray(residuals_px, dtype=float).reshape(-1, 4, 2)
    mean = r.mean(axis=1, keepdims=True)
    return float(4.0 * np.sum(mean**2)), float(np.sum((r - mean) ** 2))


def estimate_corner_noise(residuals_px: np.ndarray, n_parameters: int) -> CornerNoise:
    """Both sigmas of :class:`CornerNoise` from a solve's corner residuals ``(n, 4, 2)`` px
    with ``n_parameters`` free parameters: each subspace's sum of squares over its redundancy.
    A pose moves a marker's corners together, so the parameters are charged to the centre
    subspace (at most half its ``2 n`` dimensions; the rest to the shape): with thousands of
    markers and a few hundred parameters the split moves either sigma by a few percent at
    most. Fewer than :data:`MIN_MARKERS` markers: the independent model at the overall
    sigma. The ratio is clipped to :data:`RATIO_BOUNDS`."""
    r = np.asarray(residuals_px, dtype=float).reshape(-1, 4, 2)
    n = len(r)
    ss_c, ss_s = split_sums(r)
    if n < MIN_MARKERS:
        dof = max(8 * n - n_parameters, 1)
        return CornerNoise(float(np.sqrt((ss_c + ss_s) / dof)) if n else 1.0)
    p_centre = min(n_parameters, n)
    p_shape = n_parameters - p_centre
    sigma_s = np.sqrt(ss_s / max(6 * n - p_shape, 1))
    sigma_c = np.sqrt(ss_c / max(2 * n - p_centre, 1))
    if sigma_s <= 0:
        return CornerNoise(max(float(sigma_c), 1e-9))
    ratio = float(np.clip(sigma_c / sigma_s, *RATIO_BOUNDS))
    return CornerNoise(float(sigma_s), ratio)


def scale_covariance(T_ref_cam: np.ndarray, sigma: float) -> np.ndarray:
    """The 6x6 covariance (body frame ``[rot, trans]``, GTSAM's right perturbation) a camera's
    pose takes from the rig's scale known to a relative ``sigma``: the board is the metric
    reference, and a board that the detector sees larger by ``s`` puts every camera at
    ``(1 - s)`` times its distance from the reference, ``t -> (1 - s) t``. Rank one, along
    ``[0, R^T t]``."""
    j = np.concatenate([np.zeros(3), T_ref_cam[:3, :3].T @ T_ref_cam[:3, 3]])
    return sigma**2 * np.outer(j, j)


def first_noise(config: BundleConfig) -> float | CornerNoise:
    """The corner noise a bundle adjustment's first solve takes: ``pixel_sigma`` for every
    corner, or with ``corner_noise: marker`` and a known ``corner_centre_ratio`` both sigmas
    at that ratio (the solve is then not repeated)."""
    if config.corners.corner_noise == "marker" and config.corners.corner_centre_ratio:
        return CornerNoise(config.pixel_sigma, config.corners.corner_centre_ratio)
    return config.pixel_sigma
