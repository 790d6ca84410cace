"""The depth sensor's noise model: per-pixel depth sigma of a disparity sensor.

Depth noise follows a disparity model, ``sigma_z = z^2 * s / (f * B)`` with the disparity error
``s`` (px), the focal length ``f`` (px) and the baseline ``B`` (m) of the depth sensor: Intel's
D435 model (RealSense "Depth camera tuning / depth quality" white paper, RMS error) by default,
or a Kinect v1 (structured light) for a camera whose rig.yaml entry says
``depth_noise: kinect-v1`` (:func:`depth_noise`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.config import DepthConfig


def d435_sigma_z(z_m: np.ndarray, focal_px: float, subpixel_px: float = 0.08,
                 baseline_m: float = 0.050) -> np.ndarray:
    """D435 depth RMS error (m) at depth ``z_m``: ``z^2 s / (f B)`` (Intel depth white paper)."""
    z = np.asarray(z_m, dtype=float)
    return z * z * subpixel_px / (focal_px * baseline_m)


@dataclass(frozen=True)
class DepthNoise:
    """Per-pixel depth noise of a disparity sensor: ``sigma_z = z^2 s / (f B)``.

    ``correlation_px`` is the side of the image square over which pixels share their error: a
    mean of ``k`` neighbouring pixels holds ``max(1, k / correlation_px^2)`` independent
    errors, not ``k``. Stereo matching and structured light both correlate over their matching
    window; the synthetic D435 noise is drawn per pixel (1)."""

    subpixel_px: float
    baseline_m: float
    focal_px: float
    correlation_px: float = 1.0

    @property
    def disparity_sigma(self) -> float:
        """Sigma of the inverse depth (1/m): ``s / (f B)``."""
        return self.subpixel_px / (self.focal_px * self.baseline_m)

    def sigma_z(self, z_m: np.ndarray) -> np.ndarray:
        """Single-frame, single-pixel depth sigma (m) at depth ``z_m``."""
        return d435_sigma_z(z_m, self.focal_px, self.subpixel_px, self.baseline_m)


# Kinect v1 (structured light, IR camera f ~ 580 px, projector-camera baseline 7.5 cm;
# Khoshelham & Elberink, Sensors 2012), its disparity quantised to 1/8 px; its errors are
# shared by about 4x4 neighbouring pixels (measured: docs/depth.md).
KINECT_V1_NOISE = DepthNoise(subpixel_px=0.125, baseline_m=0.075, focal_px=580.0,
                             correlation_px=4.0)


def depth_noise(intr: CameraIntrinsics, config: DepthConfig) -> DepthNoise:
    """The depth noise model of a camera: its rig.yaml ``depth_noise`` (``kinect-v1``: the
    :data:`KINECT_V1_NOISE` constants), else the D435 model with ``config``'s ``subpixel_px``
    and ``baseline_m`` at ``depth_focal_px`` (default: the colour fx, depth being aligned to
    colour)."""
    if intr.depth_noise == "kinect-v1":
        return KINECT_V1_NOISE
    clouds = config.clouds
    return DepthNoise(clouds.subpixel_px, clouds.baseline_m, clouds.depth_focal_px or intr.fx)


_MEDIAN_EFFICIENCY = math.pi / 2.0  # var(median of n Gaussian samples) ~ pi/2 * sigma^2 / n


def median_efficiency(n: np.ndarray) -> np.ndarray:
    """var(median of n Gaussian samples) * n / sigma^2: pi/2 for many samples, 1 for one or two
    (their median is their mean)."""
    return np.where(np.asarray(n) <= 2, 1.0, _MEDIAN_EFFICIENCY)
