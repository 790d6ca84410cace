"""The one camera model: pinhole intrinsics plus a lens model (pure numpy).

Two lens models (:data:`LENS_MODELS`, ``model:`` in rig.yaml): ``opencv`` (the default, below)
and ``fisheye``, the equidistant model of ``cv2.fisheye`` and Kalibr's ``pinhole-equi``: with
``r = sqrt(x^2 + y^2)``, ``theta = atan(r)`` and the four coefficients ``k1 k2 k3 k4``,
``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` and
``x' = (theta_d / r) x, y' = (theta_d / r) y``.

Every projection, distortion and undistortion of the package goes through this module, so the
detection's edge fit, the PnP pixels fed to the bundle adjustment and the depth
back-projection agree to round-off.

Model (OpenCV ``cv::projectPoints``, calib3d "Camera Calibration and 3D Reconstruction"): a
camera-frame point ``(X, Y, Z)`` (metres) has normalized coordinates ``x = X/Z, y = Y/Z``;
with ``r^2 = x^2 + y^2`` and the coefficient list
``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tau_x tau_y]]]]`` (4, 5, 8, 12 or 14 values)

    radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
    x'' = x radial + 2 p1 x y + p2 (r^2 + 2 x^2) + s1 r^2 + s2 r^4
    y'' = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y + s3 r^2 + s4 r^4

then the tilted-sensor homography ``(x', y') ~ T(tau_x, tau_y) (x'', y'', 1)``
(``cv::detail::computeTiltProjectionMatrix``) and ``u = fx x' + cx, v = fy y' + cy``.
Pixel centres are at integer coordinates. Undistortion inverts the map by Newton's method
run to convergence (see :func:`undistort_normalized`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

DISTORTION_NAMES = (
    "k1",
    "k2",
    "p1",
    "p2",
    "k3",
    "k4",
    "k5",
    "k6",
    "s1",
    "s2",
    "s3",
    "s4",
    "tau_x",
    "tau_y",
)
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)
PINHOLE_NAMES = ("fx", "fy", "cx", "cy")  # the pinhole's parameters, before any lens's
OPENCV, FISHEYE = "opencv", "fisheye"
LENS_MODELS = (OPENCV, FISHEYE)
FISHEYE_NAMES = ("k1", "k2", "k3", "k4")  # cv2.fisheye's and Kalibr's equidistant k1..k4
# depth noise models of rig.yaml ``depth_noise`` (rgbd_calib.depth.noise.depth_noise): active stereo
# (RealSense D435, the default) or structured light (Kinect v1 / PrimeSense)
DEPTH_NOISE_MODELS = ("d435", "kinect-v1")

UNDISTORT_TOLERANCE = 1e-12  # normalized units (~1e-9 px at fx = 1000)
UNDISTORT_MAX_ITERATIONS = 50


# ----------------------------------------------------------------------------- pinhole
def project_pinhole(points_cam: ArrayLike, fx: float, fy: float, cx: float, cy: float) -> Array:
    """Pixels ``(...,2)`` of camera-frame points ``(...,3)`` (metres) through an ideal
    pinhole (no distortion)."""
    p = np.asarray(points_cam, dtype=float)
    uv = np.empty(p.shape[:-1] + (2,))
    uv[..., 0] = fx * (p[..., 0] / p[..., 2]) + cx
    uv[..., 1] = fy * (p[..., 1] / p[..., 2]) + cy
    return uv


def pinhole_point_jacobian(points_cam: ArrayLike, fx: float, fy: float) -> Array:
    """``(N,2,3)`` d(u,v)/d(X,Y,Z) of the ideal pinhole at camera-frame points ``(N,3)``
    (metres): ``[[fx/Z, 0, -fx X/Z^2], [0, fy/Z, -fy Y/Z^2]]``."""
    p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
    inv_z = 1.0 / p[:, 2]
    J = np.zeros((len(p), 2, 3))
    J[:, 0, 0] = fx * inv_z
    J[:, 1, 1] = fy * inv_z
    J[:, 0, 2] = -J[:, 0, 0] * p[:, 0] * inv_z
    J[:, 1, 2] = -J[:, 1, 1] * p[:, 1] * inv_z
    return J


def pinhole_pose_jacobian(points_cam: ArrayLike, fx: float, fy: float) -> Array:
    """``(N,2,6)`` d(u,v)/d(xi) of the ideal pinhole at camera-frame points ``(N,3)`` for a
    right perturbation of the camera's pose, ``T_world_cam Exp(xi)``, ``xi = [omega, v]``
    (GTSAM's ``PinholePose::project`` Dpose). It is :func:`pinhole_point_jacobian` times
    dp_cam/dxi = ``[[p_cam]x, -I]``, written out with x = X/Z, y = Y/Z:

        du/dxi = fx [x y, -(1 + x^2), y, -1/Z, 0, x/Z]
        dv/dxi = fy [1 + y^2, -x y, -x, 0, -1/Z, y/Z]"""
    p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
    inv_z = 1.0 / p[:, 2]
    x, y = p[:, 0] * inv_z, p[:, 1] * inv_z
    xy = x * y
    J = np.zeros((len(p), 2, 6))
    J[:, 0, 0] = fx * xy
    J[:, 0, 1] = -fx * (1.0 + x * x)
    J[:, 0, 2] = fx * y
    J[:, 0, 3] = -fx * inv_z
    J[:, 0, 5] = fx * x * inv_z
    J[:, 1, 0] = fy * (1.0 + y * y)
    J[:, 1, 1] = -fy * xy
    J[:, 1, 2] = -fy * x
    J[:, 1, 4] = -fy * inv_z
    J[:, 1, 5] = fy * y * inv_z
    return J


# ----------------------------------------------------------------------------- distortion
def _tilt_matrices(tau_x: float, tau_y: float) -> tuple[Array, Array, Array]:
    """OpenCV's tilt homography ``T`` (``computeTiltProjectionMatrix``) and its derivatives
    in tau_x and tau_y: with ``R = Ry(tau_y) Rx(tau_x)``,
    ``T = [[R22, 0, -R02], [0, R22, -R12], [0, 0, 1]] R``."""
    cx_, sx_ = np.cos(tau_x), np.sin(tau_x)
    cy_, sy_ = np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, cx_, sx_], [0.0, -sx_, cx_]])
    rot_y = np.array([[cy_, 0.0, -sy_], [0.0, 1.0, 0.0], [sy_, 0.0, cy_]])
    d_rot_x = np.array([[0.0, 0.0, 0.0], [0.0, -sx_, cx_], [0.0, -cx_, -sx_]])
    d_rot_y = np.array([[-sy_, 0.0, -cy_], [0.0, 0.0, 0.0], [cy_, 0.0, -sy_]])

    def proj_z(R: Array, affine: float) -> Array:
        return np.array([[R[2, 2], 0.0, -R[0, 2]], [0.0, R[2, 2], -R[1, 2]], [0.0, 0.0, affine]])

    R = rot_y @ rot_x
    T = proj_z(R, 1.0) @ R
    dT = [proj_z(dR, 0.0) @ R + proj_z(R, 1.0) @ dR for dR in (rot_y @ d_rot_x, d_rot_y @ rot_x)]
    return T, dT[0], dT[1]


@dataclass
class _Distorted:
    """Distorted normalized coordinates ``xd, yd`` (N,) of ideal ``x, y``, with (when asked)
    d(xd, yd)/d(x, y) as four (N,) arrays and d(xd, yd)/d(coefficients) ``(N,2,n)``."""

    xd: Array
    yd: Array
    j00: Array | None = None
    j01: Array | None = None
    j10: Array | None = None
    j11: Array | None = None
    J_coef: Array | None = None


def _distort(
    x: Array, y: Array, d: Array, jac_xy: bool = False, jac_coef: bool = False
) -> _Distorted:
    """OpenCV's distortion (module docstring) of normalized ``x, y`` (N,) with the 4, 5, 8, 12
    or 14 coefficients ``d``; the Brown-Conrady part is written as ``cv::projectPoints`` does."""
    n = d.size
    k1, k2, p1, p2 = d[:4]
    k3 = d[4] if n > 4 else 0.0
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    if n > 5:  # rational model
        k4, k5, k6 = d[5:8]
        denominator = 1 + k4 * r2 + k5 * r2 * r2 + k6 * r2 * r2 * r2
        radial = radial / denominator
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    if n > 8:  # thin prism
        s1, s2, s3, s4 = d[8:12]
        xd = xd + s1 * r2 + s2 * r2 * r2
        yd = yd + s3 * r2 + s4 * r2 * r2
    if n > 12:  # tilted sensor, exactly the identity when tau_x = tau_y = 0
        T, dT_x, dT_y = _tilt_matrices(d[12], d[13])
        inv_w = 1.0 / (T[2, 0] * xd + T[2, 1] * yd + T[2, 2])
        xt = (T[0, 0] * xd + T[0, 1] * yd + T[0, 2]) * inv_w
        yt = (T[1, 0] * xd + T[1, 1] * yd + T[1, 2]) * inv_w
        out = _Distorted(xt, yt)
    else:
        out = _Distorted(xd, yd)
    if not (jac_xy or jac_coef):
        return out

    r4 = r2 * r2
    d_radial = k1 + 2 * k2 * r2 + 3 * k3 * r4  # d radial / d r2 (numerator)
    if n > 5:
        d_radial = (d_radial - radial * (k4 + 2 * k5 * r2 + 3 * k6 * r4)) / denominator
    xy2 = 2 * x * y
    j00 = radial + 2 * x * x * d_radial + 2 * p1 * y + 6 * p2 * x
    j01 = xy2 * d_radial + 2 * p1 * x + 2 * p2 * y
    j10 = xy2 * d_radial + 2 * p1 * x + 2 * p2 * y
    j11 = radial + 2 * y * y * d_radial + 6 * p1 * y + 2 * p2 * x
    if n > 8:
        gx = 2 * (s1 + 2 * s2 * r2)
        gy = 2 * (s3 + 2 * s4 * r2)
        j00, j01, j10, j11 = j00 + x * gx, j01 + y * gx, j10 + x * gy, j11 + y * gy
    if n > 12:  # chain through the homography: d(xt)/d(xd) = (T0j - xt T2j) / w
        t00, t01 = (T[0, 0] - xt * T[2, 0]) * inv_w, (T[0, 1] - xt * T[2, 1]) * inv_w
        t10, t11 = (T[1, 0] - yt * T[2, 0]) * inv_w, (T[1, 1] - yt * T[2, 1]) * inv_w
        out.j00, out.j01 = t00 * j00 + t01 * j10, t00 * j01 + t01 * j11
        out.j10, out.j11 = t10 * j00 + t11 * j10, t10 * j01 + t11 * j11
    else:
        out.j00, out.j01, out.j10, out.j11 = j00, j01, j10, j11
    if not jac_coef:
        return out

    J = np.zeros((len(x), 2, n))
    scale = 1.0 / denominator if n > 5 else 1.0
    J[:, 0, 0], J[:, 1, 0] = x * r2 * scale, y * r2 * scale
    J[:, 0, 1], J[:, 1, 1] = x * r4 * scale, y * r4 * scale
    J[:, 0, 2], J[:, 1, 2] = xy2, r2 + 2 * y * y
    J[:, 0, 3], J[:, 1, 3] = r2 + 2 * x * x, xy2
    if n > 4:
        J[:, 0, 4], J[:, 1, 4] = x * r2 * r4 * scale, y * r2 * r4 * scale
    if n > 5:
        for j, power in ((5, r2), (6, r4), (7, r2 * r4)):
            J[:, 0, j] = -x * radial * power / denominator
            J[:, 1, j] = -y * radial * power / denominator
    if n > 8:
        J[:, 0, 8], J[:, 0, 9] = r2, r4
        J[:, 1, 10], J[:, 1, 11] = r2, r4
    if n > 12:
        J[:, 0, :12], J[:, 1, :12] = (
            t00[:, None] * J[:, 0, :12] + t01[:, None] * J[:, 1, :12],
            t10[:, None] * J[:, 0, :12] + t11[:, None] * J[:, 1, :12],
        )
        for j, dT in ((12, dT_x), (13, dT_y)):
            dh0 = dT[0, 0] * xd + dT[0, 1] * yd + dT[0, 2]
            dh1 = dT[1, 0] * xd + dT[1, 1] * yd + dT[1, 2]
            dh2 = dT[2, 0] * xd + dT[2, 1] * yd + dT[2, 2]
            J[:, 0, j] = (dh0 - xt * dh2) * inv_w
            J[:, 1, j] = (dh1 - yt * dh2) * inv_w
    out.J_coef = J
    return out


def _distort_equidistant(
    x: Array, y: Array, d: Array, jac_xy: bool = False, jac_coef: bool = False
) -> _Distorted:
    """The equidistant fisheye (module docstring) of normalized ``x, y`` (N,) with the four
    coefficients ``d``, and its derivatives as :func:`_distort` gives them."""
    k1, k2, k3, k4 = d[:4]
    r = np.sqrt(x * x + y * y)
    theta = np.arctan(r)
    t2 = theta * theta
    poly = 1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    theta_d = theta * poly
    small = r < 1e-12
    safe_r = np.where(small, 1.0, r)
    s = np.where(small, 1.0, theta_d / safe_r)  # theta_d / r -> 1 at the centre
    out = _Distorted(s * x, s * y)
    if not (jac_xy or jac_coef):
        return out
    # ds/dr = (theta_d'(theta) / (1 + r^2) - s) / r; (ds/dr) / r multiplies x x, x y, y y
    d_theta_d = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    g = np.where(small, 0.0, (d_theta_d / (1 + r * r) - s) / (safe_r * safe_r))
    out.j00, out.j01 = s + g * x * x, g * x * y
    out.j10, out.j11 = g * x * y, s + g * y * y
    if jac_coef:
        ux, uy = np.where(small, 0.0, x / safe_r), np.where(small, 0.0, y / safe_r)
        J = np.zeros((len(x), 2, 4))
        power = theta * t2
        for j in range(4):
            J[:, 0, j], J[:, 1, j] = ux * power, uy * power
            power = power * t2
        out.J_coef = J
    return out


def _lens(lens: str):
    """The distortion function of a lens model (:data:`LENS_MODELS`)."""
    return _distort_equidistant if lens == FISHEYE else _distort


def distort_normalized(xy: ArrayLike, dist: ArrayLike, lens: str = OPENCV) -> Array:
    """Distorted normalized coordinates ``(...,2)`` of ideal ones ``xy`` ``(...,2)``
    (OpenCV's model with the 4, 5, 8, 12 or 14 coefficients ``dist``, or ``lens`` fisheye's
    four)."""
    xy = np.asarray(xy, dtype=float)
    flat = xy.reshape(-1, 2)
    out = _lens(lens)(flat[:, 0], flat[:, 1], np.asarray(dist, dtype=float).reshape(-1))
    return np.column_stack([out.xd, out.yd]).reshape(xy.shape)


def undistort_normalized(
    xy_distorted: ArrayLike,
    dist: ArrayLike,
    tolerance: float = UNDISTORT_TOLERANCE,
    max_iterations: int = UNDISTORT_MAX_ITERATIONS,
    lens: str = OPENCV,
) -> Array:
    """Ideal normalized coordinates ``(...,2)`` whose distortion is ``xy_distorted``.

    Newton's method on ``distort(x) - x_d = 0`` with the analytic 2x2 Jacobian, started at
    ``x_d``; a point stops once its residual norm is below ``tolerance`` (normalized units).
    A step that does not reduce the residual is halved and retried (damped Newton), which
    keeps strong distortion from overshooting; a point whose step has been halved 30 times
    in a row sits at the round-off floor and stops too. Points that do not converge within
    ``max_iterations`` keep their best iterate, as ``cv2.undistortPoints`` does."""
    xy_d = np.asarray(xy_distorted, dtype=float)
    d = np.asarray(dist, dtype=float).reshape(-1)
    distort = _lens(lens)
    flat = xy_d.reshape(-1, 2)
    result = flat.copy()
    tol2 = tolerance * tolerance
    # working set: the points still iterating, as compact arrays
    idx = np.arange(len(flat))
    tx, ty = flat[:, 0].copy(), flat[:, 1].copy()  # targets
    x, y = tx.copy(), ty.copy()  # current iterate (start at the distorted point)
    best_x, best_y = x, y
    best_err = np.full(len(flat), np.inf)
    step_x = step_y = np.zeros(len(flat))
    scale = np.ones(len(flat))
    for _ in range(max_iterations + 1):
        f = distort(x, y, d, jac_xy=True)
        rx, ry = f.xd - tx, f.yd - ty
        err = rx * rx + ry * ry
        improved = err < best_err  # NaN inputs: never improved, dropped below
        # accept improved iterates and take a full Newton step from them
        best_x, best_y = np.where(improved, x, best_x), np.where(improved, y, best_y)
        best_err = np.where(improved, err, best_err)
        det = f.j00 * f.j11 - f.j01 * f.j10
        det = np.where(det != 0.0, det, 1e-300)
        step_x = np.where(improved, (f.j11 * rx - f.j01 * ry) / det, step_x)
        step_y = np.where(improved, (f.j00 * ry - f.j10 * rx) / det, step_y)
        scale = np.where(improved, 1.0, 0.5 * scale)
        done = (best_err <= tol2) | (scale < 2.0**-30) | ~np.isfinite(best_err)
        if np.any(done):
            result[idx[done], 0], result[idx[done], 1] = best_x[done], best_y[done]
            keep = ~done
            idx, tx, ty, best_x, best_y, best_err, step_x, step_y, scale = (
                a[keep] for a in (idx, tx, ty, best_x, best_y, best_err, step_x, step_y, scale)
            )
        if idx.size == 0:
            break
        x, y = best_x - scale * step_x, best_y - scale * step_y
    result[idx, 0], result[idx, 1] = best_x, best_y  # not converged: the best iterate
    return result.reshape(xy_d.shape)


# ----------------------------------------------------------------------------- the camera
@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole + OpenCV distortion model of one colour sensor (depth is aligned to it).

    ``distortion`` holds OpenCV's 4, 5, 8, 12 or 14 coefficients
    (``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tau_x tau_y]]]]``). ``depth_noise`` names the
    noise model of the depth aligned to this camera (one of :data:`DEPTH_NOISE_MODELS`): the
    depth stage weighs and accepts registrations by it, and a Kinect's noise is neither as
    large nor as independent from pixel to pixel as a D435's."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    depth_scale: float = 0.001  # metres per depth count
    depth_noise: str = "d435"
    lens: str = OPENCV  # the lens model (LENS_MODELS): its distortion's meaning

    @property
    def K(self) -> Array:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> Array:
        return np.asarray(self.distortion, dtype=float)

    @property
    def has_distortion(self) -> bool:
        """Whether pixels differ from the pinhole's: any nonzero coefficient, or a fisheye
        (its equidistant mapping bends rays with every coefficient zero)."""
        return self.lens == FISHEYE or bool(np.any(self.dist != 0.0))

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of the columns of :meth:`intrinsics_jacobian`: fx fy cx cy, then the
        distortion coefficients in OpenCV order (the fisheye's k1..k4)."""
        return PINHOLE_NAMES + self.coefficient_names

    @property
    def coefficient_names(self) -> tuple[str, ...]:
        """The names of :attr:`distortion`'s coefficients under this lens model."""
        if self.lens == FISHEYE:
            return FISHEYE_NAMES[: len(self.distortion)]
        return DISTORTION_NAMES[: len(self.distortion)]

    @property
    def parameters(self) -> dict[str, float]:
        """Each of :attr:`parameter_names` with its value."""
        return dict(zip(self.parameter_names,
                        (self.fx, self.fy, self.cx, self.cy, *self.distortion)))

    # ------------------------------------------------------------------ normalized <-> pixels
    def _to_normalized(self, pixels: Array) -> Array:
        return np.stack(
            [(pixels[..., 0] - self.cx) / self.fx, (pixels[..., 1] - self.cy) / self.fy], axis=-1
        )

    def _to_pixels(self, xy: Array) -> Array:
        return np.stack([self.fx * xy[..., 0] + self.cx, self.fy * xy[..., 1] + self.cy], axis=-1)

    def distort(self, xy: ArrayLike) -> Array:
        """Ideal normalized coordinates ``(...,2)`` -> distorted normalized coordinates."""
        xy = np.asarray(xy, dtype=float)
        return distort_normalized(xy, self.dist, self.lens) if self.has_distortion else xy.copy()

    def undistort(self, xy_distorted: ArrayLike) -> Array:
        """Distorted normalized coordinates ``(...,2)`` -> ideal normalized coordinates (the
        inverse of :meth:`distort`, see :func:`undistort_normalized`)."""
        xy_d = np.asarray(xy_distorted, dtype=float)
        if not self.has_distortion:
            return xy_d.copy()
        return undistort_normalized(xy_d, self.dist, lens=self.lens)

    def distort_pixels(self, ideal_px: ArrayLike) -> Array:
        """Ideal pinhole pixels ``(...,2)`` (this ``K``, no distortion) -> distorted pixels."""
        px = np.asarray(ideal_px, dtype=float)
        if not self.has_distortion:
            return px.copy()
        return self._to_pixels(distort_normalized(self._to_normalized(px), self.dist, self.lens))

    def undistort_pixels(self, pixels: ArrayLike) -> Array:
        """Distorted pixels ``(...,2)`` -> ideal pinhole pixels of the same ``K``: what a
        distortion-free projection (the bundle adjustment's factors) expects."""
        px = np.asarray(pixels, dtype=float)
        if not self.has_distortion:
            return px.copy()
        return self._to_pixels(undistort_normalized(self._to_normalized(px), self.dist,
                                                    lens=self.lens))

    def rays(self, u: ArrayLike, v: ArrayLike) -> Array:
        """Rays ``(N,3)`` with z = 1 through pixels ``(u, v)`` (pixel centres at integers),
        lens distortion removed: a pixel of depth ``z`` back-projects to ``z * ray``."""
        x = (np.asarray(u, dtype=float).reshape(-1) - self.cx) / self.fx
        y = (np.asarray(v, dtype=float).reshape(-1) - self.cy) / self.fy
        if self.has_distortion:
            xy = undistort_normalized(np.column_stack([x, y]), self.dist, lens=self.lens)
            x, y = xy[:, 0], xy[:, 1]
        return np.column_stack([x, y, np.ones_like(x)])

    # ------------------------------------------------------------------ projection
    def project(self, points_cam: ArrayLike) -> Array:
        """Project ``(...,3)`` camera-frame points (metres) to ``(...,2)`` pixels through the
        lens distortion (none when all coefficients are zero)."""
        p = np.asarray(points_cam, dtype=float)
        if not self.has_distortion:
            return project_pinhole(p, self.fx, self.fy, self.cx, self.cy)
        xy = np.stack([p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]], axis=-1)
        return self._to_pixels(distort_normalized(xy, self.dist, self.lens))

    def project_jacobian(self, points_cam: ArrayLike) -> tuple[Array, Array]:
        """Pixels ``(N,2)`` of camera-frame points ``(N,3)`` (metres) and d(u,v)/d(X,Y,Z)
        ``(N,2,3)`` (pixels per metre), distortion included."""
        p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
        if not self.has_distortion:
            return (
                project_pinhole(p, self.fx, self.fy, self.cx, self.cy),
                pinhole_point_jacobian(p, self.fx, self.fy),
            )
        inv_z = 1.0 / p[:, 2]
        x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        f = _lens(self.lens)(x, y, self.dist, jac_xy=True)
        # d(x, y)/d(X, Y, Z) = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
        J = np.empty((len(p), 2, 3))
        for row, focal, ja, jb in ((0, self.fx, f.j00, f.j01), (1, self.fy, f.j10, f.j11)):
            J[:, row, 0] = focal * ja * inv_z
            J[:, row, 1] = focal * jb * inv_z
            J[:, row, 2] = -focal * (ja * x + jb * y) * inv_z
        uv = np.column_stack([self.fx * f.xd + self.cx, self.fy * f.yd + self.cy])
        return uv, J

    def intrinsics_jacobian(self, points_cam: ArrayLike) -> Array:
        """``(N,2,4+len(distortion))`` d(u,v)/d(fx, fy, cx, cy, k1, k2, p1, p2, k3, ...) at
        camera-frame points ``(N,3)`` (metres); column names in :attr:`parameter_names`."""
        p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
        f = _lens(self.lens)(p[:, 0] / p[:, 2], p[:, 1] / p[:, 2], self.dist, jac_coef=True)
        J = np.zeros((len(p), 2, 4 + self.dist.size))
        J[:, 0, 0] = f.xd
        J[:, 1, 1] = f.yd
        J[:, 0, 2] = 1.0
        J[:, 1, 3] = 1.0
        J[:, 0, 4:] = self.fx * f.J_coef[:, 0]
        J[:, 1, 4:] = self.fy * f.J_coef[:, 1]
        return J

    def ray_coefficient_jacobian(self, xy: ArrayLike) -> Array:
        """d(ideal normalized x, y)/d(:attr:`coefficient_names`) ``(N,2,n)`` at ideal
        normalized points ``xy`` ``(N,2)``, the distorted pixel held fixed: how a pixel's ray
        moves with each lens coefficient, ``-(d distort/d xy)^-1 d distort/d coefficients``."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        f = _lens(self.lens)(xy[:, 0], xy[:, 1], self.dist, jac_xy=True, jac_coef=True)
        det = f.j00 * f.j11 - f.j01 * f.j10
        det = np.where(det != 0.0, det, 1e-300)[:, None]
        J = f.J_coef
        out = np.empty_like(J)
        out[:, 0] = -(f.j11[:, None] * J[:, 0] - f.j01[:, None] * J[:, 1]) / det
        out[:, 1] = -(-f.j10[:, None] * J[:, 0] + f.j00[:, None] * J[:, 1]) / det
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            **({"model": self.lens} if self.lens != OPENCV else {}),
            "distortion": list(self.distortion),
            "depth_scale": self.depth_scale,
            # written only when not the default: rig files of D435 rigs stay as they were
            **({"depth_noise": self.depth_noise} if self.depth_noise != "d435" else {}),
        }
