"""The named layouts of a synthetic rig (``--layout``): camera poses and intrinsics, the
room and its rails and boxes, and the volume the board moves through."""

from __future__ import annotations

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.errors import ConfigError
from ..core.geometry import look_at
from .imperfections import (
    bump_cameras,
    camera_imperfections,
    depth_error_draws,
    true_depth_model,
)
from .params import SynthCamera, SynthParams, SynthRig
from .scene import Rect, box, rect

LAYOUTS = ("thesis-line", "race", "race16", "ring")


def _intrinsics(width: int, height: int, rng: np.random.Generator) -> CameraIntrinsics:
    """D435-like colour intrinsics (69 deg HFOV at 1280x720), varied per camera as the
    thesis's factory values vary (Table 4.1)."""
    s = width / 1280.0
    f = (633.0 + rng.uniform(-3.0, 10.0)) * s
    return CameraIntrinsics(
        width, height, f, f, width / 2 + rng.uniform(-4, 6) * s, height / 2 + rng.uniform(-5, 5) * s
    )


def _room(rng: np.random.Generator, half: float = 3.5, height: float = 3.0) -> list[Rect]:
    rects = [
        rect((-half, -half, 0), (2 * half, 0, 0), (0, 2 * half, 0), (0.55, 0.6, 0.62), 11, 0.08),
        rect((-half, -half, 0), (0, 2 * half, 0), (0, 0, height), (0.7, 0.72, 0.6), 21, 0.1),
        rect((half, half, 0), (0, -2 * half, 0), (0, 0, height), (0.6, 0.7, 0.75), 31, 0.1),
        rect((half, -half, 0), (-2 * half, 0, 0), (0, 0, height), (0.75, 0.65, 0.6), 41, 0.1),
        rect((-half, half, 0), (2 * half, 0, 0), (0, 0, height), (0.62, 0.7, 0.68), 51, 0.1),
    ]
    for k in range(6):  # boxes on the floor, away from the board's workspace
        ang = rng.uniform(0, 2 * np.pi)
        r = rng.uniform(2.2, 3.0)
        c = np.array([r * np.cos(ang), r * np.sin(ang)])
        size = rng.uniform(0.25, 0.6, 3)
        lo = (c[0] - size[0] / 2, c[1] - size[1] / 2, 0.0)
        hi = (c[0] + size[0] / 2, c[1] + size[1] / 2, size[2])
        rects += box(lo, hi, tuple(rng.uniform(0.35, 0.85, 3)), 100 + 10 * k, 0.04)
    return rects


def _race_rails(half_length: float) -> list[Rect]:
    """Two rails on each side of a race along x (y = +-0.45 m) on posts every 0.9 m."""
    rails: list[Rect] = []
    for y in (-0.45, 0.45):
        for z in (0.35, 0.75):
            rails += box(
                (-half_length, y - 0.02, z - 0.02),
                (half_length, y + 0.02, z + 0.02),
                (0.5, 0.52, 0.55),
                300 + int(10 * z),
                0.03,
            )
        for x in np.arange(-half_length + 0.2, half_length - 0.19, 0.9):
            rails += box(
                (x - 0.04, y - 0.04, 0.0),
                (x + 0.04, y + 0.04, 0.85),
                (0.45, 0.47, 0.5),
                400,
                0.03,
            )
    return rails


def make_rig(layout: str, seed: int, params: SynthParams) -> SynthRig:
    """Camera poses, intrinsics, depth biases and models, and scene of a named layout."""
    rng = np.random.default_rng(seed)
    scene = _room(rng)
    cams: list[tuple[str, np.ndarray]] = []
    if layout == "thesis-line":
        # Four cameras in a line, 0.4 m apart, the last one turned inwards (thesis Fig. 4.2,
        # Table 4.3: cam10 about 30 deg yawed and 0.17 m forward).
        default_res = (1280, 720)
        for k in range(4):
            eye = np.array([0.4 * k, 0.0, 1.2]) + rng.normal(0, 0.01, 3)
            target = np.array([0.4 * k, 2.0, 0.9])
            if k == 3:
                eye += [-0.15, 0.17, 0.0]
                target = np.array([0.3, 2.0, 0.9])
            cams.append((f"cam{7 + k}", look_at(eye, target + rng.normal(0, 0.03, 3))))
        lo, hi = np.array([-0.1, 0.9, 0.75]), np.array([1.3, 1.9, 1.35])
    elif layout == "race":
        # A cattle race along x: rails on both sides, two rows of cameras facing each other
        # across it, so one row sees the board's front while the other sees its back.
        default_res = (848, 480)
        for side, y in (("left", -1.15), ("right", 1.15)):
            for k, x in enumerate((-0.9, -0.3, 0.3, 0.9)):
                eye = np.array([x, y, 1.75]) + rng.normal(0, 0.02, 3)
                target = np.array([0.75 * x, 0.0, 1.15]) + rng.normal(0, 0.05, 3)
                cams.append((f"{side}{k}", look_at(eye, target)))
        scene += _race_rails(half_length=2.0)
        lo, hi = np.array([-0.95, -0.15, 0.95]), np.array([0.95, 0.15, 1.45])
    elif layout == "race16":
        # The seed's full rig: 16 cameras along a longer race, on both sides and in two tiers
        # (an upper row looking down onto the back, a lower row looking across at the flank),
        # so neighbours overlap along the race, facing cameras see opposite board faces and
        # the tiers share views above each other.
        default_res = (848, 480)
        for side, y in (("left", -1.2), ("right", 1.2)):
            for tier, z, aim_z in (("hi", 2.1, 1.05), ("lo", 1.35, 1.2)):
                for k, x in enumerate((-1.35, -0.45, 0.45, 1.35)):
                    eye = np.array([x, y * (0.95 if tier == "hi" else 1.0), z])
                    target = np.array([0.85 * x, 0.0, aim_z]) + rng.normal(0, 0.05, 3)
                    cams.append(
                        (f"{side}_{tier}{k}", look_at(eye + rng.normal(0, 0.02, 3), target))
                    )
        scene += _race_rails(half_length=2.7)
        lo, hi = np.array([-1.45, -0.15, 0.95]), np.array([1.45, 0.15, 1.5])
    elif layout == "ring":
        default_res = (1280, 720)
        n = params.cameras or 6
        for k in range(n):
            ang = 2 * np.pi * k / n
            eye = np.array([1.7 * np.cos(ang), 1.7 * np.sin(ang), 1.5]) + rng.normal(0, 0.02, 3)
            cams.append(
                (f"cam{k}", look_at(eye, np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.05, 3)))
            )
        lo, hi = np.array([-0.35, -0.35, 0.8]), np.array([0.35, 0.35, 1.25])
    else:
        raise ConfigError(f"unknown layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    width, height = params.resolution or default_res
    cameras = []
    depth_units = depth_error_draws(seed, len(cams))  # a stream of their own
    for (name, T_world_cam), unit in zip(cams, depth_units):
        bias = 1.0 + (
            rng.uniform(-params.depth_bias, params.depth_bias) if params.depth_bias > 0 else 0.0
        )
        intr = _intrinsics(width, height, rng)
        cameras.append(SynthCamera(name, intr, T_world_cam, bias,
                                   depth_model=true_depth_model(intr, bias, unit, params)))
    cameras = camera_imperfections(cameras, seed, params)
    cameras = bump_cameras(cameras, seed, params.bump)
    # race16: a central lower-tier camera (most views) rather than one at the race's end
    reference = [c.name for c in cameras].index("left_lo1") if layout == "race16" else 0
    if params.board_volume != 1.0:  # about the box's centre (1.0: the same floats as before)
        mid, half = (lo + hi) / 2, (hi - lo) / 2 * params.board_volume
        lo, hi = mid - half, mid + half
    return SynthRig(layout, cameras, scene, lo, hi, reference_index=reference)
