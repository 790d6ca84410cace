"""The depth model of one camera: measured depth -> true depth (pure numpy).

A stereo depth camera (RealSense D4xx; Kinect v1's structured light works the same way) measures
a disparity ``d`` and reports ``z = f B / d``. Its factory calibration leaves three errors that
the colour calibration cannot see (Intel, "Depth camera self-calibration", and the D400
"Tuning depth cameras for best performance" white papers):

- a **disparity offset** ``delta(x, y)`` (px) that varies smoothly over the image: the depth
  error ``dz = z^2 delta / (f B)`` grows with the square of the distance;
- a **scale** error ``s`` (a baseline or focal error: ``z_measured = s z`` at ``delta = 0``);
- a depth sensor whose pose relative to the colour camera is a little off its factory value, so
  depth aligned to colour is shifted: a small rigid motion of the back-projected points.

Model (depth aligned to colour; ``(x, y)`` the pixel's undistorted ray ``X/Z, Y/Z`` in the colour
camera, ``z_m`` the measured depth in metres)::

    kappa(x, y) = delta(x, y) / (f B)                      inverse-depth offset, 1/m
    delta(x, y) = d0 + dx x + dy y + dxx x^2 + dxy x y + dyy y^2      px
    1 / z      = s / z_m - kappa(x, y)           i.e.  z = z_m / (s - z_m kappa)
    p_true     = R p + t,    p = z (x, y, 1),    R = exp(rotation), small

so ``z_m = s z / (1 + z kappa)`` is what the camera reports for a surface at true depth ``z``.
The ratio ``r = s - z_m kappa = z_m / z`` (true over measured disparity) is bounded to
``[RATIO_MIN, RATIO_MAX]``: a fitted polynomial extrapolated to an image corner or a far wall can
reach ``r <= 0`` (an infinite or negative depth no sensor measures); bounded, the corrected depth
is finite, positive and increasing in the measured depth for every pixel and every model, and
:meth:`DepthModel.beyond_bounds` says which pixels the bound held (clouds drop and count them).
The identity model (``s = 1``, ``delta = 0``, ``R = I``, ``t = 0``) is a clean camera. The terms
are chosen by evidence (:mod:`rgbd_calib.depth.depth_model_fit`): a clean camera keeps the
identity. :func:`correct_depth_image` applies a model to a depth image for users' pipelines.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .camera import CameraIntrinsics
from .errors import RgbdCalibError

Array = NDArray[np.float64]

# the model's terms in the order the evidence ladder frees them, with their parameters
TERMS: dict[str, tuple[str, ...]] = {
    "scale": ("scale",),
    "offset": ("d0",),
    "gradient": ("dx", "dy"),
    "curvature": ("dxx", "dxy", "dyy"),
    "pose": ("rx", "ry", "rz", "tx", "ty", "tz"),
}
PARAMETERS: tuple[str, ...] = tuple(p for names in TERMS.values() for p in names)
# units of each parameter as written to depth_model.yaml and the report
UNITS = {"scale": "", "d0": "px", "dx": "px", "dy": "px", "dxx": "px", "dxy": "px",
         "dyy": "px", "rx": "deg", "ry": "deg", "rz": "deg", "tx": "mm", "ty": "mm", "tz": "mm"}
# the true depth over the measured one stays within [1 / RATIO_MAX, 1 / RATIO_MIN]: a D435's
# depth error is a few per cent at its far range (a 0.5 px disparity offset at 10 m: 16 %);
# a correction beyond 25 % is a model extrapolated past what its data support
RATIO_MIN, RATIO_MAX = 0.8, 1.25
D435_BASELINE_M = 0.050
KINECT_V1_BASELINE_M = 0.075


def default_focal_baseline(intr: CameraIntrinsics) -> float:
    """``f B`` (px m) of the camera's stereo pair: the colour focal length times the D435
    baseline (or Kinect v1's). Depth aligned to colour is resampled at the colour focal length,
    so the disparity offsets of a model are in pixels of that focal length."""
    baseline = KINECT_V1_BASELINE_M if intr.depth_noise == "kinect-v1" else D435_BASELINE_M
    return float(intr.fx) * baseline


def _rotation_matrix(rotvec: Array) -> Array:
    """Rodrigues: the rotation by the vector ``rotvec`` (rad)."""
    theta = float(np.linalg.norm(rotvec))
    if theta < 1e-15:
        return np.eye(3)
    k = rotvec / theta
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * Kx + (1.0 - np.cos(theta)) * Kx @ Kx


@dataclass(frozen=True)
class DepthModel:
    """One camera's depth model (see the module docstring); ``values`` by :data:`PARAMETERS`:
    ``scale`` (1 = exact), ``d0 .. dyy`` disparity offset coefficients (px), ``rx ry rz`` the
    depth-to-colour rotation correction (deg), ``tx ty tz`` its translation (mm).

    ``terms`` are the terms the data chose (empty: the identity), ``sigmas`` the marginal sigma
    of each estimated parameter (same units), ``depth_range_m`` and ``image_coverage`` what the
    data covered (the model is an extrapolation outside them)."""

    focal_baseline_px_m: float
    values: dict[str, float] = field(default_factory=dict)
    terms: tuple[str, ...] = ()
    sigmas: dict[str, float] = field(default_factory=dict)
    depth_range_m: tuple[float, float] | None = None
    image_coverage: float | None = None

    def value(self, name: str) -> float:
        return float(self.values.get(name, 1.0 if name == "scale" else 0.0))

    @property
    def is_identity(self) -> bool:
        return all(self.value(p) == (1.0 if p == "scale" else 0.0) for p in PARAMETERS)

    def vector(self) -> Array:
        """All parameters in :data:`PARAMETERS` order, in the units of :data:`UNITS`."""
        return np.array([self.value(p) for p in PARAMETERS])

    def with_values(self, values: dict[str, float], **kw: Any) -> DepthModel:
        return replace(self, values={**self.values, **{k: float(v) for k, v in values.items()}},
                       **kw)

    # ------------------------------------------------------------------ the maths
    def disparity_offset_px(self, x: Array, y: Array) -> Array:
        """``delta(x, y)`` (px) at undistorted ray coordinates ``x = X/Z, y = Y/Z``."""
        v = self.value
        return (v("d0") + v("dx") * x + v("dy") * y
                + v("dxx") * x * x + v("dxy") * x * y + v("dyy") * y * y)

    def _ratio(self, x: Array, y: Array, z_measured_m: Array) -> Array:
        """``r = s - z_m kappa(x, y)``, unbounded: the true over the measured disparity."""
        kappa = self.disparity_offset_px(np.asarray(x, float), np.asarray(y, float)) \
            / self.focal_baseline_px_m
        return self.value("scale") - np.asarray(z_measured_m, dtype=float) * kappa

    def beyond_bounds(self, x: Array, y: Array, z_measured_m: Array) -> Array:
        """Where the model's correction leaves ``[RATIO_MIN, RATIO_MAX]`` (bool, per pixel):
        the corrected depth there is the bound's, not the fitted formula's."""
        r = self._ratio(x, y, z_measured_m)
        return (np.asarray(z_measured_m) > 0) & ((r < RATIO_MIN) | (r > RATIO_MAX))

    def true_depth(self, x: Array, y: Array, z_measured_m: Array) -> Array:
        """The true z-depth (m) of pixels at rays ``(x, y)`` that measured ``z_measured_m``;
        0 where nothing was measured (``z_m <= 0`` or not finite). Finite, positive and
        increasing in ``z_m`` for any parameters: the ratio ``z_m / z`` is held within
        ``[RATIO_MIN, RATIO_MAX]`` (:meth:`beyond_bounds`)."""
        z_m = np.asarray(z_measured_m, dtype=float)
        ok = np.isfinite(z_m) & (z_m > 0)
        z_m = np.where(ok, z_m, 0.0)
        r = np.clip(np.nan_to_num(self._ratio(x, y, z_m), nan=1.0), RATIO_MIN, RATIO_MAX)
        return np.where(ok, z_m / r, 0.0)

    def measured_depth(self, x: Array, y: Array, z_true_m: Array) -> Array:
        """What the camera reports for a surface at true z-depth ``z_true_m`` (the inverse of
        :meth:`true_depth`, its bound included; for rendering), before the pose error."""
        z = np.asarray(z_true_m, dtype=float)
        ok = np.isfinite(z) & (z > 0)
        z = np.where(ok, z, 0.0)
        kappa = self.disparity_offset_px(np.asarray(x, float), np.asarray(y, float)) \
            / self.focal_baseline_px_m
        denom = 1.0 + z * kappa
        pos = denom > 1e-12
        r = np.where(pos, self.value("scale") / np.where(pos, denom, 1.0), RATIO_MAX)
        return np.where(ok, z * np.clip(r, RATIO_MIN, RATIO_MAX), 0.0)

    def warp_jacobian(self, points_measured: Array) -> Array:
        """``d p_true / d p_measured`` ``(N,3,3)`` at measured colour-frame points ``(N,3)``
        (m): the rigid correction's rotation times the derivative of the scaling along the
        rays, ``p -> p / r(x, y, z)`` (:meth:`true_depth`); where the ratio is held at its
        bound, the scaling alone. Surface normals move by its inverse transpose."""
        p = np.asarray(points_measured, dtype=float).reshape(-1, 3)
        z = p[:, 2]
        x, y = p[:, 0] / z, p[:, 1] / z
        v = self.value
        fb = self.focal_baseline_px_m
        kappa = self.disparity_offset_px(x, y) / fb
        r = v("scale") - z * kappa  # as _ratio
        held = (r < RATIO_MIN) | (r > RATIO_MAX)
        r = np.clip(r, RATIO_MIN, RATIO_MAX)
        k_x = (v("dx") + 2 * v("dxx") * x + v("dxy") * y) / fb
        k_y = (v("dy") + v("dxy") * x + 2 * v("dyy") * y) / fb
        # r = s - z kappa(X/Z, Y/Z): its gradient by (X, Y, Z)
        grad_r = -np.column_stack([k_x, k_y, kappa - x * k_x - y * k_y])
        grad_r[held] = 0.0
        J = np.eye(3)[None] / r[:, None, None] - p[:, :, None] * (grad_r / (r * r)[:, None])[
            :, None, :]
        return self.T_true_measured()[:3, :3] @ J

    def T_true_measured(self) -> Array:
        """4x4 rigid correction: true point = ``T @`` measured point (colour frame, metres)."""
        T = np.eye(4)
        T[:3, :3] = _rotation_matrix(np.radians([self.value("rx"), self.value("ry"),
                                                 self.value("rz")]))
        T[:3, 3] = 1e-3 * np.array([self.value("tx"), self.value("ty"), self.value("tz")])
        return T

    def correct_points(self, rays: Array, z_measured_m: Array,
                       drop_beyond_bounds: bool = False) -> Array:
        """True colour-frame points ``(N,3)`` (m) of pixels with rays ``(N,3)`` (z = 1,
        :meth:`CameraIntrinsics.rays`) and measured depths ``(N,)``; rows with no valid depth
        (and, with ``drop_beyond_bounds``, rows :meth:`beyond_bounds`) are NaN."""
        rays = np.asarray(rays, dtype=float).reshape(-1, 3)
        z = self.true_depth(rays[:, 0], rays[:, 1], z_measured_m)
        p = rays * z[:, None]
        T = self.T_true_measured()
        p = p @ T[:3, :3].T + T[:3, 3]
        p[z <= 0] = np.nan
        if drop_beyond_bounds:
            p[self.beyond_bounds(rays[:, 0], rays[:, 1], z_measured_m)] = np.nan
        return p

    def measured_points(self, points: Array) -> Array:
        """The inverse of :meth:`correct_points`: colour-frame points ``(N,3)`` as the camera
        measured them (on the ray of the pixel it saw them in) from the true ones; rows the
        model has no answer for are NaN."""
        T = self.T_true_measured()
        p = (np.asarray(points, dtype=float).reshape(-1, 3) - T[:3, 3]) @ T[:3, :3]
        z = p[:, 2]
        ok = z > 0
        x = np.where(ok, p[:, 0] / np.where(ok, z, 1.0), 0.0)
        y = np.where(ok, p[:, 1] / np.where(ok, z, 1.0), 0.0)
        zm = self.measured_depth(x, y, np.where(ok, z, 0.0))
        out = np.stack([x * zm, y * zm, zm], axis=1)
        out[~ok | (zm <= 0)] = np.nan
        return out

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict[str, Any]:
        return {
            "model": "stereo-disparity",
            "focal_baseline_px_m": float(self.focal_baseline_px_m),
            "terms": list(self.terms),
            "parameters": {p: self.value(p) for p in PARAMETERS},
            "units": dict(UNITS),
            "sigmas": {p: float(s) for p, s in self.sigmas.items()},
            "depth_range_m": None if self.depth_range_m is None else list(self.depth_range_m),
            "image_coverage": self.image_coverage,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "depth model") -> DepthModel:
        try:
            params = {str(k): float(v) for k, v in (data.get("parameters") or {}).items()}
            unknown = sorted(set(params) - set(PARAMETERS))
            if unknown:
                raise RgbdCalibError(f"{where}: unknown parameter(s) {', '.join(unknown)}; "
                                     f"expected some of {', '.join(PARAMETERS)}")
            rng = data.get("depth_range_m")
            return cls(
                focal_baseline_px_m=float(data["focal_baseline_px_m"]),
                values=params,
                terms=tuple(str(t) for t in data.get("terms") or ()),
                sigmas={str(k): float(v) for k, v in (data.get("sigmas") or {}).items()},
                depth_range_m=None if rng is None else (float(rng[0]), float(rng[1])),
                image_coverage=(None if data.get("image_coverage") is None
                                else float(data["image_coverage"])),
            )
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise RgbdCalibError(f"{where}: not a depth model ({exc!r}); write it as "
                                 "rgbd-calib calibrate does (docs/formats.md, depth_model.yaml)") \
                from exc


def identity_model(intr: CameraIntrinsics) -> DepthModel:
    return DepthModel(focal_baseline_px_m=default_focal_baseline(intr))


# ----------------------------------------------------------------------------- images
def _pixel_grid(intr: CameraIntrinsics) -> tuple[Array, Array]:
    v, u = np.mgrid[0:intr.height, 0:intr.width]
    return u.astype(float), v.astype(float)


def _bilinear(img: Array, u: Array, v: Array) -> Array:
    """``img`` sampled at pixels ``(u, v)``: bilinear where the four neighbours are all valid
    (> 0) and within 2 % of each other (one surface), else the nearest pixel; 0 outside."""
    h, w = img.shape
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    uc, vc = np.clip(u, 0, w - 1), np.clip(v, 0, h - 1)
    u0 = np.minimum(np.floor(uc).astype(int), w - 2)
    v0 = np.minimum(np.floor(vc).astype(int), h - 2)
    a, b = uc - u0, vc - v0
    q = np.stack([img[v0, u0], img[v0, u0 + 1], img[v0 + 1, u0], img[v0 + 1, u0 + 1]])
    wts = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])
    lo, hi = q.min(axis=0), q.max(axis=0)
    smooth = (lo > 0) & (hi - lo <= 0.02 * np.maximum(lo, 1e-9))
    nearest = img[np.rint(vc).astype(int), np.rint(uc).astype(int)]
    out = np.where(smooth, (q * wts).sum(axis=0), nearest)
    return np.where(inside, out, 0.0)


def warp_depth(depth_m: Array, intr: CameraIntrinsics, T_new_old: Array,
               iterations: int = 4) -> Array:
    """The depth image (m, 0 = none) of the surface in ``depth_m`` after its points move by
    ``T_new_old`` (4x4, colour frame; a small motion: a few pixels). Each output pixel finds
    the input pixel whose moved point lands on it by fixed-point iteration (inverse warping,
    so no holes), 0 where that leaves the image or meets no depth."""
    depth_m = np.asarray(depth_m, dtype=float)
    u, v = _pixel_grid(intr)
    shape = depth_m.shape
    rays_out = intr.rays(u, v)  # rays of the output pixels
    T_old_new = np.linalg.inv(T_new_old)
    # guess: the source pixel is where the output pixel's ray, at the depth found there,
    # maps back to under the inverse motion
    z = depth_m.reshape(-1)
    src_u, src_v = u.reshape(-1), v.reshape(-1)
    for _ in range(iterations):
        p_new = rays_out * np.where(z > 0, z, 1.0)[:, None]
        p_old = p_new @ T_old_new[:3, :3].T + T_old_new[:3, 3]
        uv = intr.project(p_old)
        src_u, src_v = uv[:, 0], uv[:, 1]
        z_old = _bilinear(depth_m, src_u, src_v)
        p_old = intr.rays(src_u, src_v) * z_old[:, None]
        p_new = p_old @ T_new_old[:3, :3].T + T_new_old[:3, 3]
        z = np.where(z_old > 0, p_new[:, 2], 0.0)
    return z.reshape(shape)


def correct_depth_image(model: DepthModel, depth: NDArray[Any], intr: CameraIntrinsics,
                        depth_scale: float | None = None) -> NDArray[Any]:
    """``depth`` (aligned to colour; 16-bit counts of ``depth_scale`` m, default the camera's,
    or float metres when ``depth`` is a float array) corrected by ``model``: the same image
    type, each pixel the true depth of the surface seen there. For live pipelines: apply it
    to every depth frame before back-projecting with the colour intrinsics."""
    depth = np.asarray(depth)
    if depth.shape != (intr.height, intr.width):
        raise RgbdCalibError(f"depth image is {depth.shape[1]}x{depth.shape[0]} but the camera "
                             f"is {intr.width}x{intr.height}; pass the depth aligned to colour")
    if model.is_identity:
        return depth.copy()
    counts = np.issubdtype(depth.dtype, np.integer)
    unit = (intr.depth_scale if depth_scale is None else depth_scale) if counts else 1.0
    z_m = depth.astype(float) * unit
    u, v = _pixel_grid(intr)
    rays = intr.rays(u, v)
    z = model.true_depth(rays[:, 0], rays[:, 1], z_m.reshape(-1)).reshape(z_m.shape)
    T = model.T_true_measured()
    if not np.allclose(T, np.eye(4)):
        z = warp_depth(z, intr, T)
    if counts:
        info = np.iinfo(depth.dtype)
        return np.clip(np.rint(z / unit), 0, info.max).astype(depth.dtype)
    return z.astype(depth.dtype)


def distort_depth_image(model: DepthModel, depth_true_m: Array,
                        intr: CameraIntrinsics) -> Array:
    """What a camera with ``model`` reports (m, aligned to colour) for a scene whose true depth
    is ``depth_true_m``: the inverse of :func:`correct_depth_image` (for rendering)."""
    z = np.asarray(depth_true_m, dtype=float)
    z = np.where(np.isfinite(z), z, 0.0)
    T = model.T_true_measured()
    if not np.allclose(T, np.eye(4)):
        z = warp_depth(z, intr, np.linalg.inv(T))
    u, v = _pixel_grid(intr)
    rays = intr.rays(u, v)
    return model.measured_depth(rays[:, 0], rays[:, 1], z.reshape(-1)).reshape(z.shape)
