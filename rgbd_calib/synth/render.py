"""Synthetic RGB-D rigs with ground truth: layouts, board motion and rendering.

A rig of cameras looks at a static textured scene (floor, walls, rails, boxes:
:mod:`rgbd_calib.synth.scene`) while the double-sided board moves through it. Colour is the exact
board texture (area-averaged over each pixel: pixels whose four corners disagree are
supersampled 8x8), lens blur and sensor noise. Depth is aligned to colour, with the D435
stereo noise model ``sigma_z = z^2 * s / (f * B)`` (Intel's depth-quality white paper, "RMS
error"), a per-camera scale bias, 1-count quantisation, dropout and range limits.

By default the cameras are ideal pinholes whose ``rig.yaml`` intrinsics are exact and the
board is exactly its board file. :class:`SynthParams` adds real-world imperfections
(docs/synthetic.md): lens distortion, rendered exactly (every pixel and sub-pixel ray comes
from the true camera model, :meth:`CameraIntrinsics.rays`, never a remap of a pinhole
image), ``rig.yaml`` intrinsics that are off from the truth, a back sheet glued off its
place, a thicker or thinner panel and a print at the wrong scale. ``ground_truth.yaml``
records the truth of each.

Pure numpy rendering; cv2 only filters images. Written by :class:`~rgbd_calib.model.dataset.FolderWriter`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..core.camera import DISTORTION_LENGTHS, CameraIntrinsics
from ..core.errors import ConfigError
from ..core.geometry import (
    invert_transform,
    look_at,
    make_transform,
    rotvec_to_matrix,
    transform_points,
)
from ..core.parallel import executor
from ..core.progress import Progress, start
from ..core.yamlio import write_yaml
from ..model.board import BACK, FRONT, Board, charuco_black_squares, printed_markers
from ..model.dataset import FolderWriter, staged_folder
from ..model.rig import Rig
from .scene import Rect, box, cast, pixel_rays, rect, shade_scene

LAYOUTS = ("thesis-line", "race", "race16", "ring")
LIGHT_DIR_WORLD = np.array([0.3, -0.4, 0.87]) / np.linalg.norm([0.3, -0.4, 0.87])
PAPER_WHITE, INK_BLACK, WOOD = 0.88, 0.07, 0.55
RIG_DISTORTIONS = ("zeros", "truth")  # what rig.yaml lists under --distortion
IMPERFECTION_STREAM = 0x5EED1  # rng stream of the rig.yaml intrinsics errors (seed, stream)
CLOSEUP_STREAM = 0xC105E  # rng stream of the close-up board poses (seed, stream)
# where a close-up's markers must reach, in turn (fractions of the image width and height):
# the four corners, then the middles of the four edges
CLOSEUP_TARGETS = ((0, 0), (1, 0), (1, 1), (0, 1), (0.5, 0), (1, 0.5), (0.5, 1), (0, 0.5))
CLOSEUP_REACH = 0.01  # ... and how close to it (image widths) ends the search
BUMP_STREAM = 0xB0A7  # rng stream of the knocks of --bump (seed, stream, camera index)


@dataclass(frozen=True)
class SynthParams:
    """Rendering and noise settings (units in the names)."""

    resolution: tuple[int, int] | None = None  # (width, height); None: the layout's default
    blur_sigma_px: float = 0.6
    color_noise_dn: float = 2.0
    depth_subpixel_px: float = 0.08  # D435 subpixel disparity error s
    depth_baseline_m: float = 0.050  # D435 stereo baseline B
    depth_bias: float = 0.0  # max |relative depth-scale error| per camera (uniform in +-)
    depth_dropout: float = 0.02  # fraction of valid depth pixels set to 0
    depth_min_m: float = 0.28
    depth_max_m: float = 6.0
    drop_rate: float = 0.0  # probability that a camera misses a frame entirely
    supersample: int = 8
    cameras: int | None = None  # camera count (ring only)
    # real-world imperfections (docs/synthetic.md); the defaults render the ideal rig
    distortion: tuple[float, ...] | None = None  # true OpenCV k1 k2 p1 p2 k3 of every camera
    rig_distortion: str = "zeros"  # rig.yaml lists "zeros" (as a D435 reports) or the "truth"
    intrinsics_error: tuple[float, float] = (0.0, 0.0)  # rig.yaml: max |focal error| %, max px
    glue: tuple[float, float, float] = (0.0, 0.0, 0.0)  # back sheet: dx mm, dy mm, rot deg
    thickness_error_mm: float = 0.0  # true panel thickness minus the board file's
    print_scale: float = 1.0  # printed size / board file size, both faces
    # multi-face target: every face but the reference one off its board-file pose by this
    # shift (mm) and turn (deg), each in a seeded direction of its own (a hand-built cube)
    face_error: tuple[float, float] = (0.0, 0.0)
    # cameras knocked after the calibration: (name, mm, deg) each, moved in a seeded direction
    bump: tuple[tuple[str, float, float], ...] = ()
    # the volume the board is moved through: the layout's box scaled by this about its centre
    board_volume: float = 1.0
    # extra frame sets per camera with the board close to it, out to its image's corners and
    # edges (as a user fills each camera's image to calibrate its lens): closeup_poses
    closeups: int = 0


def check_params(params: SynthParams) -> None:
    """Reject imperfection settings that cannot be rendered, naming the option."""
    if params.distortion is not None and len(params.distortion) not in DISTORTION_LENGTHS:
        raise ConfigError(
            f"--distortion: {len(params.distortion)} coefficients; give OpenCV's k1 k2 p1 p2 k3"
        )
    if params.rig_distortion not in RIG_DISTORTIONS:
        raise ConfigError(
            f"--rig-distortion {params.rig_distortion!r}: choose {' or '.join(RIG_DISTORTIONS)}"
        )
    f_pct, px = params.intrinsics_error
    if not (0 <= f_pct < 50 and px >= 0):
        raise ConfigError(
            f"--intrinsics-error {f_pct} {px}: give a focal error 0 <= F% < 50 and pixels >= 0"
        )
    if not (0.5 < params.print_scale < 2.0):
        raise ConfigError(f"--print-scale {params.print_scale}: expected a factor near 1")
    if not (0.1 <= params.board_volume <= 5.0):
        raise ConfigError(f"--board-volume {params.board_volume}: expected a factor in 0.1-5 "
                          "of the layout's board volume")
    if not (0 <= params.closeups <= 64):
        raise ConfigError(f"--closeups {params.closeups}: expected 0-64 frame sets per camera")
    mm, deg = params.face_error
    if not (0 <= mm < 100 and 0 <= deg < 30):
        raise ConfigError(f"--face-error {mm} {deg}: give a shift 0 <= mm < 100 and a turn "
                          "0 <= deg < 30")
    for name, mm, deg in params.bump:
        if not (mm >= 0 and 0 <= deg < 90):
            raise ConfigError(f"--bump {name} {mm} {deg}: give a shift >= 0 mm and a turn "
                              "0 <= deg < 90")


@dataclass(frozen=True)
class SynthCamera:
    """One camera: ``intrinsics`` is the truth the images are rendered with (lens distortion
    included); ``listed_intrinsics`` what its ``rig.yaml`` says (None: the truth)."""

    name: str
    intrinsics: CameraIntrinsics
    T_world_cam: np.ndarray
    depth_scale_bias: float = 1.0
    listed_intrinsics: CameraIntrinsics | None = None

    @property
    def rig_intrinsics(self) -> CameraIntrinsics:
        """The intrinsics written to ``rig.yaml``."""
        return self.intrinsics if self.listed_intrinsics is None else self.listed_intrinsics


@dataclass(frozen=True)
class SynthRig:
    """Cameras, scene and the board's workspace in the world frame (z up, metres)."""

    layout: str
    cameras: list[SynthCamera]
    scene: list[Rect]
    workspace_lo: np.ndarray
    workspace_hi: np.ndarray
    facing: str = "camera"  # how board normals are chosen: towards a random camera
    reference_index: int = 0  # the camera whose frame is the rig's reference

    @property
    def reference(self) -> str:
        return self.cameras[self.reference_index].name

    def T_ref_cam(self, cam: SynthCamera) -> np.ndarray:
        T_world_ref = self.cameras[self.reference_index].T_world_cam
        return invert_transform(T_world_ref) @ cam.T_world_cam


# --------------------------------------------------------------------------- layouts
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
    """Camera poses, intrinsics, depth biases and scene of a named layout."""
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
    for name, T_world_cam in cams:
        bias = 1.0 + (
            rng.uniform(-params.depth_bias, params.depth_bias) if params.depth_bias > 0 else 0.0
        )
        cameras.append(SynthCamera(name, _intrinsics(width, height, rng), T_world_cam, bias))
    cameras = _camera_imperfections(cameras, seed, params)
    cameras = _bump(cameras, seed, params.bump)
    # race16: a central lower-tier camera (most views) rather than one at the race's end
    reference = [c.name for c in cameras].index("left_lo1") if layout == "race16" else 0
    if params.board_volume != 1.0:  # about the box's centre (1.0: the same floats as before)
        mid, half = (lo + hi) / 2, (hi - lo) / 2 * params.board_volume
        lo, hi = mid - half, mid + half
    return SynthRig(layout, cameras, scene, lo, hi, reference_index=reference)


def _camera_imperfections(
    cameras: list[SynthCamera], seed: int, params: SynthParams
) -> list[SynthCamera]:
    """True lens distortion and the intrinsics ``rig.yaml`` lists instead of the truth.

    The true distortion is ``params.distortion`` for every camera. ``rig.yaml`` lists it or
    zeros (``rig_distortion``), and focal lengths scaled by one factor ``1 + e`` (fx and fy
    together: a focal error keeps the aspect ratio), ``e`` uniform in +-F % , and ``cx``, ``cy``
    each shifted by a uniform +-PX pixels. The errors come from their own seeded stream (three
    unit draws per camera), so the rig, the board motion and the noise stay those of the same
    seed without them."""
    check_params(params)
    f_pct, px = params.intrinsics_error
    unit = np.random.default_rng([seed, IMPERFECTION_STREAM]).uniform(-1, 1, (len(cameras), 3))
    out = []
    for cam, (e_f, e_cx, e_cy) in zip(cameras, unit):
        truth = cam.intrinsics
        if params.distortion is not None:
            truth = replace(truth, distortion=tuple(float(d) for d in params.distortion))
        listed = truth
        if truth.has_distortion and params.rig_distortion == "zeros":
            listed = replace(listed, distortion=(0.0,) * 5)
        if f_pct > 0 or px > 0:
            scale = 1.0 + e_f * f_pct / 100.0
            listed = replace(
                listed,
                fx=truth.fx * scale,
                fy=truth.fy * scale,
                cx=truth.cx + e_cx * px,
                cy=truth.cy + e_cy * px,
            )
        if truth.has_distortion:
            _check_distortion(truth)
        out.append(
            replace(cam, intrinsics=truth, listed_intrinsics=None if listed is truth else listed)
        )
    return out


def bump_transform(seed: int, index: int, mm: float, deg: float) -> np.ndarray:
    """The knock ``T_cam_cam'`` of camera number ``index``: a turn of ``deg`` about a seeded
    random axis through the optical centre and a shift of ``mm`` along a seeded random
    direction (camera frame), from its own stream so the rest of the seed's rig stays."""
    rng = np.random.default_rng([seed, BUMP_STREAM, index])
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction /= np.linalg.norm(direction)
    return make_transform(rotvec_to_matrix(axis * np.radians(deg)), direction * mm / 1000.0)


def _bump(cameras: list[SynthCamera], seed: int,
          bump: tuple[tuple[str, float, float], ...]) -> list[SynthCamera]:
    """Cameras moved after the calibration (``--bump NAME MM DEG``): the same rig as the seed's
    without it, but the named cameras' poses knocked by :func:`bump_transform`."""
    names = [c.name for c in cameras]
    knocks = {}
    for name, mm, deg in bump:
        if name not in names:
            raise ConfigError(f"--bump {name}: no such camera; this layout has "
                              f"{', '.join(names)}")
        knocks[name] = bump_transform(seed, names.index(name), mm, deg)
    return [replace(c, T_world_cam=c.T_world_cam @ knocks[c.name]) if c.name in knocks else c
            for c in cameras]


def _check_distortion(K: CameraIntrinsics, step_px: int = 8) -> None:
    """The lens model must map the image one-to-one (no fold inside it), or the per-pixel
    rays are not the truth: every pixel's ray projects back onto it and the model's Jacobian
    keeps its orientation."""
    u = np.append(np.arange(-0.5, K.width - 0.5, step_px), K.width - 0.5)
    v = np.append(np.arange(-0.5, K.height - 0.5, step_px), K.height - 0.5)
    uu, vv = (a.ravel() for a in np.meshgrid(u, v))
    rays = K.rays(uu, vv)
    uv, J = K.project_jacobian(rays)
    round_trip_px = np.max(np.abs(uv - np.column_stack([uu, vv])))
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    if not (round_trip_px < 1e-6 and np.all(det > 0)):
        raise ConfigError(
            f"--distortion {list(K.distortion)}: the lens model folds over inside the "
            f"{K.width}x{K.height} image; give smaller coefficients"
        )


# --------------------------------------------------------------------------- the printed board
@dataclass(frozen=True)
class BoardPrint:
    """The physical board against its board file (which stays nominal).

    In the board frame (metres): a front-face corner ``p`` of the board file is really at
    ``diag(S, S, 1) p`` and a back-face corner at ``T_front_back diag(S, S, 1) p``, with ``S``
    the print scale. ``T_front_back`` maps the (scaled) board-file position of a back-sheet
    point to where the back sheet really is: a rotation by ``rot`` about the board normal
    (+z, counter-clockwise seen from the front) through the centre of the printed back-marker
    grid, then the in-plane shift ``(dx, dy)`` and ``-(thickness_m - board.thickness)`` along
    z. The panel is ``thickness_m`` thick (its back face at ``z = -thickness_m``)."""

    thickness_m: float
    print_scale: float = 1.0
    T_front_back: np.ndarray = field(default_factory=lambda: np.eye(4))
    # a multi-face target: the true pose T_board_face of each face (label -> 4x4, metres);
    # empty: every face where the board file puts it
    face_poses: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def is_nominal(self) -> bool:
        return self.print_scale == 1.0 and bool(np.all(self.T_front_back == np.eye(4)))

    def corners(self, board: Board) -> np.ndarray:
        """True board-frame corners ``(M,4,3)`` (metres) of the board file's markers."""
        if board.sheets:
            out = board.corners.copy()
            for f, T_true in self.face_poses.items():
                sel = board.faces == f
                T = T_true @ invert_transform(board.T_board_face(f))
                out[sel] = transform_points(T, out[sel].reshape(-1, 3)).reshape(-1, 4, 3)
            return out
        scaled = board.corners * np.array([self.print_scale, self.print_scale, 1.0])
        back = board.faces == BACK
        scaled[back] = transform_points(self.T_front_back, scaled[back].reshape(-1, 3)).reshape(
            -1, 4, 3
        )
        return scaled

    def file_xy(self, face: int, xy: np.ndarray) -> np.ndarray:
        """Board-file coordinates ``(N,2)`` of points ``xy`` (board frame, metres) on the true
        ``face``: the inverse of :meth:`corners`, for the texture look-up."""
        if face == BACK:
            T_back_front = invert_transform(self.T_front_back)
            xy = xy @ T_back_front[:2, :2].T + T_back_front[:2, 3]
        return xy / self.print_scale


def face_perturbation(label: int, mm: float, deg: float) -> np.ndarray:
    """The error ``Delta`` (4x4, face frame) of face ``label`` of a hand-built target: a shift
    of ``mm`` and a turn of ``deg`` about axes drawn from a stream seeded by the label (the true
    face pose is ``T_board_face @ Delta``)."""
    rng = np.random.default_rng([16, int(label) % 2**31])
    axis_t, axis_r = rng.normal(size=3), rng.normal(size=3)
    t = axis_t / np.linalg.norm(axis_t) * mm / 1000.0
    w = axis_r / np.linalg.norm(axis_r) * np.radians(deg)
    return make_transform(rotvec_to_matrix(w), t)


def board_print(board: Board, params: SynthParams) -> BoardPrint:
    """The :class:`BoardPrint` of ``params.glue``, ``thickness_error_mm`` and ``print_scale``
    (a double-sided board), or of ``params.face_error`` (a multi-face target)."""
    if board.sheets:
        if (tuple(params.glue) != (0, 0, 0) or params.thickness_error_mm != 0
                or params.print_scale != 1.0):
            raise ConfigError("--glue, --thickness-error and --print-scale describe a "
                              "double-sided board; for a multi-face target use --face-error")
        mm, deg = params.face_error
        if (mm, deg) == (0, 0):
            return BoardPrint(board.thickness)
        return BoardPrint(board.thickness, face_poses={
            s.label: s.T_board_face @ face_perturbation(s.label, mm, deg)
            for s in board.sheets if s.label != board.reference_face})
    if tuple(params.face_error) != (0, 0):
        raise ConfigError("--face-error moves the faces of a multi-face target; for a "
                          "double-sided board use --glue / --thickness-error")
    scale = float(params.print_scale)
    dx_mm, dy_mm, rot_deg = params.glue
    thickness_m = board.thickness + params.thickness_error_mm / 1000.0
    if not thickness_m > 0:
        raise ConfigError(
            f"--thickness-error {params.thickness_error_mm}: the board would be "
            f"{thickness_m * 1000:g} mm thick; give a smaller error"
        )
    if (dx_mm, dy_mm, rot_deg, params.thickness_error_mm) == (0, 0, 0, 0):
        return BoardPrint(thickness_m, scale)
    back = board.corners[board.faces == BACK].reshape(-1, 3)
    if len(back):
        centre_xy = scale * (back[:, :2].min(axis=0) + back[:, :2].max(axis=0)) / 2
    else:
        x0, x1, y0, y1 = board.panel
        centre_xy = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    R = rotvec_to_matrix([0.0, 0.0, np.radians(rot_deg)])
    centre = np.array([centre_xy[0], centre_xy[1], 0.0])
    shift = np.array([dx_mm / 1000.0, dy_mm / 1000.0, board.thickness - thickness_m])
    return BoardPrint(thickness_m, scale, make_transform(R, centre - R @ centre + shift))


# --------------------------------------------------------------------------- board motion
def marker_visibility(
    board: Board,
    cam: SynthCamera,
    T_world_board: np.ndarray,
    min_px: float = 12.0,
    max_angle_deg: float = 70.0,
) -> int:
    """How many markers a camera sees whole, facing it, and at least ``min_px`` wide."""
    T_cam_board = invert_transform(cam.T_world_cam) @ T_world_board
    return len(_visible_corners(board, cam, T_cam_board, min_px, max_angle_deg))


def sample_board_poses(
    rig: SynthRig,
    board: Board,
    n_frames: int,
    rng: np.random.Generator,
    min_cameras: int = 2,
    min_markers: int = 6,
) -> list[np.ndarray]:
    """Random board poses ``T_world_board`` seen by at least ``min_cameras`` cameras.

    The board centre is uniform in the workspace; its front normal points at a random camera
    (or away from it, showing the back), tilted by up to 35 deg and rolled by up to 25 deg, so
    distance and obliquity vary from frame to frame. Visibility is judged with the nominal
    board and the cameras' pinhole part, so a seed gives the same poses with or without the
    imperfections of :class:`SynthParams`."""
    pinholes = [
        replace(c, intrinsics=replace(c.intrinsics, distortion=(0.0,) * 5))
        if c.intrinsics.has_distortion
        else c
        for c in rig.cameras
    ]
    centre_b = np.array(
        [
            (board.panel[0] + board.panel[1]) / 2,
            (board.panel[2] + board.panel[3]) / 2,
            -board.thickness / 2,
        ]
    )
    if board.sheets:  # a multi-face target: its markers' centre
        centre_b = board.corners.reshape(-1, 3).mean(axis=0)
    poses: list[np.ndarray] = []
    attempts = 0
    while len(poses) < n_frames:
        attempts += 1
        if attempts > 2000 * n_frames:
            raise ConfigError(
                "could not place the board in view of two cameras; the board is "
                "too large or small for this layout"
            )
        c = rng.uniform(rig.workspace_lo, rig.workspace_hi)
        cam = rig.cameras[rng.integers(len(rig.cameras))]
        to_cam = cam.T_world_cam[:3, 3] - c
        to_cam /= np.linalg.norm(to_cam)
        if rng.random() < 0.5:
            to_cam = -to_cam  # show the back face to this camera's side
        tilt_axis = np.cross(to_cam, rng.normal(size=3))
        tilt_axis /= np.linalg.norm(tilt_axis)
        z_axis = rotvec_to_matrix(tilt_axis * np.radians(rng.uniform(0, 35))) @ to_cam
        up = np.array([0.0, 0.0, 1.0])
        x_axis = np.cross(up, z_axis)
        x_axis /= np.linalg.norm(x_axis)
        y_axis = np.cross(z_axis, x_axis)
        R = np.column_stack([x_axis, y_axis, z_axis])
        R = R @ rotvec_to_matrix([0, 0, np.radians(rng.uniform(-25, 25))])
        if board.sheets:  # turn a random face (not always the first) towards to_cam
            face = board.face_labels[rng.integers(len(board.face_labels))]
            R = R @ board.T_board_face(face)[:3, :3].T
        T_world_board = make_transform(R, c - R @ centre_b)
        seen = [marker_visibility(board, k, T_world_board) for k in pinholes]
        if sum(s >= min_markers for s in seen) >= min_cameras:
            poses.append(T_world_board)
    return poses


def _visible_corners(board: Board, cam: SynthCamera, T_cam_board: np.ndarray,
                     min_px: float = 12.0, max_angle_deg: float = 70.0) -> np.ndarray:
    """Pixels ``(N,4,2)`` of the markers ``cam`` sees whole (through its true lens), facing
    it (each face from its own side only: the others hide it) and at least ``min_px`` wide;
    through a distorting lens, points beyond the widest ray of the image are never counted
    (the lens polynomial may fold them back into it)."""
    K = cam.intrinsics
    r_max = np.inf
    if K.has_distortion:
        edge_u = np.array([0.0, K.width / 2, K.width - 1.0, 0.0, K.width - 1.0, 0.0,
                           K.width / 2, K.width - 1.0])
        edge_v = np.array([0.0, 0.0, 0.0, K.height / 2, K.height / 2, K.height - 1.0,
                           K.height - 1.0, K.height - 1.0])
        r_max = np.hypot(*K.rays(edge_u, edge_v)[:, :2].T).max()
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    out = []
    for face in board.face_labels:
        pts = board.corners[board.faces == face].reshape(-1, 3) @ R.T + t
        if np.any(pts[:, 2] < 0.2):
            continue
        centre = pts.mean(axis=0)
        if -((R @ board.face_normal(face)) @ centre) / np.linalg.norm(centre) < np.cos(
                np.radians(max_angle_deg)):
            continue
        inside_fov = (np.hypot(pts[:, 0], pts[:, 1]) / pts[:, 2] <= r_max).reshape(-1, 4)
        uv = K.project(pts).reshape(-1, 4, 2)
        inside = np.all((uv[..., 0] > 2) & (uv[..., 0] < K.width - 3) & (uv[..., 1] > 2)
                        & (uv[..., 1] < K.height - 3) & inside_fov, axis=1)
        size = np.linalg.norm(uv[:, 0] - uv[:, 1], axis=1)
        out.append(uv[inside & (size >= min_px)])
    return np.concatenate(out) if out else np.zeros((0, 4, 2))


def closeup_poses(rig: SynthRig, board: Board, per_camera: int, rng: np.random.Generator,
                  min_markers: int = 6, attempts: int = 200) -> list[tuple[str, np.ndarray]]:
    """``per_camera`` board poses ``T_world_board`` close to each camera, ``(camera, pose)``
    in camera order: what a user records to calibrate a lens, the board waved near the
    camera until it has filled the image out to its corners.

    Close-up ``k`` of a camera aims at :data:`CLOSEUP_TARGETS` ``[k % 8]`` (a corner of the
    image, then the middle of an edge), through the true lens (a user sees the real image;
    unlike the regular frames these poses change with ``--distortion``). A draw: the board's
    marker corner furthest out towards the target (in the camera frame) 0.3-0.8 m from the
    camera on the ray of a pixel 3-10 px inside the target (3-30 px from a corner on each
    axis: through a barrel lens the image's corner is an acute wedge of rays that a square
    marker does not reach into), the board facing the camera (either face, tilted up to 35
    deg, rolled up to 45 deg; 10 deg for a corner, which a board corner fits only about square
    to it). Of ``attempts`` draws the first whose visible markers
    (:func:`_visible_corners`, at least ``min_markers``) come within :data:`CLOSEUP_REACH` of
    the target is kept, else the one that came closest. Other cameras may see it too."""
    out = []
    for cam in rig.cameras:
        K = cam.intrinsics
        c0 = np.array([K.cx, K.cy])
        for k in range(per_camera):
            unit = np.array(CLOSEUP_TARGETS[k % len(CLOSEUP_TARGETS)], dtype=float)
            target = unit * [K.width - 1, K.height - 1]
            inward = np.sign(0.5 - unit)  # towards the image centre, per axis (0 along an edge)
            corner = bool(np.all(inward))
            # a board corner fits an image corner only about square to it, and not right into
            # it: through a barrel lens the image's corner is an acute wedge of rays
            roll_deg, inset_px = (10.0, 30.0) if corner else (45.0, 10.0)
            best, best_gap = None, np.inf
            for _ in range(attempts):
                pixel = target + inward * rng.uniform(3, inset_px, 2)
                ray = K.rays(pixel[:1], pixel[1:])[0]
                view = K.rays(*(c0 + 0.7 * (target - c0))[:, None])[0]  # the board's middle
                to_cam = -view / np.linalg.norm(view)  # board normal towards the camera
                face = FRONT if rng.random() < 0.5 else BACK
                z_axis = to_cam * face  # the back face towards it: the normal away
                tilt_axis = np.cross(z_axis, rng.normal(size=3))
                tilt_axis /= np.linalg.norm(tilt_axis)
                z_axis = rotvec_to_matrix(tilt_axis * np.radians(rng.uniform(0, 35))) @ z_axis
                x_axis = np.cross([0.0, -1.0, 0.0], z_axis)  # image up is -y
                x_axis /= np.linalg.norm(x_axis)
                R = np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])
                R = R @ rotvec_to_matrix([0, 0, np.radians(rng.uniform(-roll_deg, roll_deg))])
                corners = board.corners[board.faces == face].reshape(-1, 3)
                anchor = corners[np.argmax(corners @ R.T @ np.append(-inward, 0.0))]
                T_cam_board = make_transform(
                    R, ray / np.linalg.norm(ray) * rng.uniform(0.3, 0.8) - R @ anchor)
                seen = _visible_corners(board, cam, T_cam_board)
                if len(seen) < min_markers:
                    continue
                gap = np.linalg.norm(seen.reshape(-1, 2) - target, axis=1).min()
                if gap < best_gap:
                    best, best_gap = cam.T_world_cam @ T_cam_board, gap
                if gap < CLOSEUP_REACH * K.width:
                    break
            if best is None:
                raise ConfigError(f"--closeups: no board pose near {cam.name} shows "
                                  f"{min_markers} markers; the board is too large for its image")
            out.append((cam.name, best))
    return out


# --------------------------------------------------------------------------- rendering
BODY_INSET_M = 1e-4  # a multi-face target's plates and body sit this far inside its sheets


def _moved(r: Rect, T: np.ndarray) -> Rect:
    """Rectangle ``r`` (given in a face frame) in the frame ``T`` maps that frame into."""
    R = T[:3, :3]
    return Rect(R @ r.origin + T[:3, 3], R @ r.u_axis, R @ r.v_axis, r.size_u, r.size_v,
                r.albedo, r.texture_seed, r.texture_cell_m)


@dataclass
class _BoardModel:
    """The board as six rectangles in the board frame plus marker look-up per face.

    ``printed`` (None: exactly the board file) is where the physical board's sheets and back
    face really are; the markers are looked up in board-file coordinates through its inverse,
    so a glued-off or scaled print stays as sharp as the nominal one."""

    board: Board
    printed: BoardPrint | None = None
    rects: list[Rect] = field(init=False)
    trees: dict[int, cKDTree] = field(init=False)
    cells: dict[int, np.ndarray] = field(init=False)
    ids: np.ndarray = field(init=False)  # the printed ArUco markers, corners and faces
    corners: np.ndarray = field(init=False)
    faces: np.ndarray = field(init=False)
    black_squares: np.ndarray | None = field(init=False)  # ChArUco only: (rows, cols)
    sheets: list[_BoardModel] = field(init=False, default_factory=list)  # multi-face: per face

    @property
    def thickness(self) -> float:
        return self.board.thickness if self.printed is None else self.printed.thickness_m

    def __post_init__(self) -> None:
        b = self.board
        if b.sheets:
            self._multiface()
            return
        x0, x1, y0, y1 = b.panel
        t = self.thickness
        w, h = x1 - x0, y1 - y0
        self.rects = [
            rect((x0, y0, 0), (w, 0, 0), (0, h, 0), (1, 1, 1), 0),  # front, normal +z
            rect((x0, y0, -t), (0, h, 0), (w, 0, 0), (1, 1, 1), 0),  # back, normal -z
            rect((x0, y0, -t), (w, 0, 0), (0, 0, t), (1, 1, 1), 0),  # bottom edge
            rect((x0, y1, -t), (0, 0, t), (w, 0, 0), (1, 1, 1), 0),  # top edge
            rect((x0, y0, -t), (0, 0, t), (0, h, 0), (1, 1, 1), 0),  # left edge
            rect((x1, y0, -t), (0, h, 0), (0, 0, t), (1, 1, 1), 0),  # right edge
        ]
        # the printed markers: the board's own, or a ChArUco board's ArUco markers (its
        # "markers" are saddle-corner quads, see board.CharucoSpec) and its black squares
        self.ids, self.corners, self.faces = printed_markers(b)
        self.black_squares = (None if b.charuco is None
                              else charuco_black_squares(b.charuco, b.dictionary))
        self.trees = {
            f: cKDTree(self.corners[self.faces == f].mean(axis=1)[:, :2])
            for f in (FRONT, BACK)
            if np.any(self.faces == f)
        }
        self.cells = {int(i): b.marker_cells(int(i)) for i in self.ids}

    def _multiface(self) -> None:
        """A multi-face target: rectangle k < F is face k's sheet (its panel at the true face
        pose, its own single-face model giving the print), then each face's plate
        (``thickness`` behind its sheet) and the ``body`` box, both inset by
        :data:`BODY_INSET_M` so that no wood surface coincides with a printed one."""
        b = self.board
        poses = dict((self.printed.face_poses if self.printed is not None else None) or {})
        self.sheets = [_BoardModel(s.board) for s in b.sheets]
        sheets, plates = [], []
        e, t = BODY_INSET_M, b.thickness
        for s in b.sheets:
            T = poses.get(s.label, s.T_board_face)
            x0, x1, y0, y1 = s.board.panel
            sheets.append(_moved(rect((x0, y0, 0), (x1 - x0, 0, 0), (0, y1 - y0, 0),
                                      (1, 1, 1), 0), T))
            plates += [_moved(r, T) for r in box((x0 + e, y0 + e, -t), (x1 - e, y1 - e, -e),
                                                 (1, 1, 1), 0)]
        body = [] if b.body is None else box(np.add(b.body[0], e), np.subtract(b.body[1], e),
                                             (1, 1, 1), 0)
        self.rects = sheets + plates + body
        self.ids, self.corners, self.faces = printed_markers(b)
        self.black_squares, self.trees, self.cells = None, {}, {}

    def reflectance(self, hit_index: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Reflectance of board hits: ink, paper or the panel's edge."""
        out = np.full(hit_index.shape, WOOD)
        if self.sheets:  # a multi-face target: face k's print on rectangle k, wood elsewhere
            for k, sheet in enumerate(self.sheets):
                sel = np.nonzero(hit_index == k)[0]
                if sel.size:
                    out[sel] = sheet.reflectance(np.zeros(sel.size, int), a[sel], b[sel])
            return out
        x0, _, y0, _ = self.board.panel
        for rect_index, face in ((0, FRONT), (1, BACK)):
            sel = np.nonzero(hit_index == rect_index)[0]
            if sel.size == 0:
                continue
            out[sel] = PAPER_WHITE
            if face not in self.trees:
                continue
            xy = (
                np.column_stack([x0 + a[sel], y0 + b[sel]])
                if face == FRONT
                else np.column_stack([x0 + b[sel], y0 + a[sel]])
            )
            if self.printed is not None and not self.printed.is_nominal:
                xy = self.printed.file_xy(face, xy)
            if self.black_squares is not None:
                out[sel] = self._squares(xy)
            ids = self.ids[self.faces == face]
            corners = self.corners[self.faces == face][:, :, :2]
            k = min(2, len(ids))
            _, cand = self.trees[face].query(xy, k=k)
            cand = cand.reshape(len(sel), k)
            for j in range(k):
                c = corners[cand[:, j]]
                e1, e3 = c[:, 1] - c[:, 0], c[:, 3] - c[:, 0]
                d = xy - c[:, 0]
                u = np.einsum("ij,ij->i", d, e1) / np.einsum("ij,ij->i", e1, e1)
                v = np.einsum("ij,ij->i", d, e3) / np.einsum("ij,ij->i", e3, e3)
                inside = (u >= 0) & (u < 1) & (v >= 0) & (v < 1)
                for m in np.unique(cand[inside, j]):
                    pick = inside & (cand[:, j] == m)
                    cells = self.cells[int(ids[m])]
                    n = cells.shape[0]
                    val = cells[(v[pick] * n).astype(int), (u[pick] * n).astype(int)]
                    out[sel[pick]] = np.where(val > 127, PAPER_WHITE, INK_BLACK)
            spec = self.board.charuco
            if spec is not None and spec.inverted:  # white on black within the chessboard
                inv = sel[(xy[:, 0] >= 0) & (xy[:, 0] < spec.squares_x * spec.square_length)
                          & (xy[:, 1] >= 0) & (xy[:, 1] < spec.height)]
                out[inv] = PAPER_WHITE + INK_BLACK - out[inv]
        return out

    def _squares(self, xy: np.ndarray) -> np.ndarray:
        """Paper or ink of a ChArUco board's chessboard at board-frame points ``(N,2)`` (m)."""
        spec = self.board.charuco
        col = np.floor(xy[:, 0] / spec.square_length).astype(int)
        row = np.floor((spec.height - xy[:, 1]) / spec.square_length).astype(int)
        inside = (col >= 0) & (col < spec.squares_x) & (row >= 0) & (row < spec.squares_y)
        out = np.full(len(xy), PAPER_WHITE)
        black = np.zeros(len(xy), dtype=bool)
        black[inside] = self.black_squares[row[inside], col[inside]]
        out[black] = INK_BLACK
        return out


@dataclass
class _Background:
    color: np.ndarray  # HxWx3 float BGR [0,1]
    depth: np.ndarray  # HxW metres (inf: no surface)
    rays: np.ndarray | None = None  # HxWx3 pixel-centre rays of a distorted lens (z = 1)


def camera_rays(K: CameraIntrinsics, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """Camera-frame rays ``(N,3)`` with z = 1 through pixels ``(us, vs)`` of the true camera:
    the lens model's converged undistortion (:meth:`CameraIntrinsics.rays`), or the pinhole
    formula of earlier renders when the lens has no distortion (bit-identical images)."""
    return K.rays(us, vs) if K.has_distortion else pixel_rays(K.K, us, vs)


def _grid(K: CameraIntrinsics, shape: tuple[int, int]) -> tuple[int, int] | None:
    """:func:`cast`'s row/column culling needs rays whose x varies along columns only and y
    along rows only: true of a pinhole's pixel grid, not of a distorted one."""
    return None if K.has_distortion else shape


def render_background(scene: list[Rect], cam: SynthCamera, samples: int = 2) -> _Background:
    """Static scene seen by a camera: colour box-filtered over ``samples^2`` rays per pixel,
    depth (camera z of the hit, as an aligned D435 depth image stores it) at pixel centres."""
    K = cam.intrinsics
    T_cam_world = invert_transform(cam.T_world_cam)
    light = T_cam_world[:3, :3] @ LIGHT_DIR_WORLD
    vs, us = np.mgrid[0 : K.height, 0 : K.width].astype(float)
    grid = _grid(K, us.shape)
    color = np.zeros((K.height, K.width, 3))
    for i in range(samples):
        for j in range(samples):
            du, dv = (i + 0.5) / samples - 0.5, (j + 0.5) / samples - 0.5
            rays = camera_rays(K, (us + du).ravel(), (vs + dv).ravel())
            hits = cast(scene, T_cam_world, rays, grid=grid)
            color += shade_scene(scene, hits, light, T_cam_world).reshape(color.shape)
    rays = camera_rays(K, us.ravel(), vs.ravel())
    depth = cast(scene, T_cam_world, rays, grid=grid).depth.reshape(K.height, K.width)
    centre_rays = rays.reshape(K.height, K.width, 3) if K.has_distortion else None
    return _Background(color / samples**2, depth, centre_rays)


def _board_bbox(model: _BoardModel, K: CameraIntrinsics, T_cam_board: np.ndarray, rays=None):
    """Pixel box ``(u0, u1, v0, v1)`` that holds the board's image, or None.

    Pinhole: the box of the projected panel corners. Distorted lens (its pixel-centre
    ``rays``, HxWx3): straight edges image as curves, so it is the box of the pixels whose
    ray falls in the ray-space box of the corners, 2 pixels wider (pixel corners and sub-pixel
    samples reach half a pixel beyond a centre)."""
    x0, x1, y0, y1 = model.board.panel
    t = model.thickness
    pts = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (0.0, -t)])
    if model.sheets:  # a multi-face target: the corners of every rectangle
        pts = np.array([r.origin + i * r.size_u * r.u_axis + j * r.size_v * r.v_axis
                        for r in model.rects for i in (0, 1) for j in (0, 1)])
    pc = pts @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    if np.all(pc[:, 2] <= 0.01):
        return None
    if np.any(pc[:, 2] <= 0.01):
        return 0, K.width - 1, 0, K.height - 1
    if rays is not None:
        xy = pc[:, :2] / pc[:, 2:]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        inside = (
            (rays[..., 0] >= lo[0])
            & (rays[..., 0] <= hi[0])
            & (rays[..., 1] >= lo[1])
            & (rays[..., 1] <= hi[1])
        )
        rows, cols = np.nonzero(np.any(inside, axis=1))[0], np.nonzero(np.any(inside, axis=0))[0]
        if rows.size == 0:
            return None
        return (
            max(cols[0] - 2, 0),
            min(cols[-1] + 2, K.width - 1),
            max(rows[0] - 2, 0),
            min(rows[-1] + 2, K.height - 1),
        )
    uv = K.project(pc)
    u0 = max(int(np.floor(uv[:, 0].min())) - 1, 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + 1, K.width - 1)
    v0 = max(int(np.floor(uv[:, 1].min())) - 1, 0)
    v1 = min(int(np.ceil(uv[:, 1].max())) + 1, K.height - 1)
    if u0 > u1 or v0 > v1:
        return None
    return u0, u1, v0, v1


def render_board(
    model: _BoardModel,
    cam: SynthCamera,
    bg: _Background,
    T_cam_board: np.ndarray,
    supersample: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free colour (HxWx3 float, BGR [0,1]) and depth (HxW metres) with the board.

    Exact area coverage: pixels whose four corners hit the same surface with the same
    reflectance are uniform; the rest are averaged over ``supersample^2`` rays. Every ray
    (pixel corner, centre or sub-pixel sample) comes from the true camera model
    (:func:`camera_rays`), so a distorted lens is rendered exactly, anti-aliasing included."""
    color = bg.color.copy()
    depth = bg.depth.copy()
    K = cam.intrinsics
    if K.has_distortion and bg.rays is None:
        raise ValueError("render_board: a distorted camera needs render_background's rays")
    box_ = _board_bbox(model, K, T_cam_board, bg.rays)
    if box_ is None:
        return color, depth
    u0, u1, v0, v1 = box_
    light = T_cam_board[:3, :3].T @ (invert_transform(cam.T_world_cam)[:3, :3] @ LIGHT_DIR_WORLD)
    face_shade = np.array([0.55 + 0.45 * abs(r.normal @ light) for r in model.rects])

    def trace(us: np.ndarray, vs: np.ndarray, grid=None, shade: bool = True, rays=None):
        if rays is None:
            rays = camera_rays(K, us, vs)
        hits = cast(model.rects, T_cam_board, rays, grid=None if grid is None else _grid(K, grid))
        if not shade:
            return hits, None
        refl = model.reflectance(hits.index, hits.a, hits.b)
        value = np.where(hits.index >= 0, refl * face_shade[np.maximum(hits.index, 0)], np.nan)
        return hits, value

    cv_, cu_ = np.mgrid[v0 : v1 + 2, u0 : u1 + 2].astype(float) - 0.5
    hits_c, val_c = trace(cu_.ravel(), cv_.ravel(), grid=cu_.shape)
    key = np.where(hits_c.index >= 0, hits_c.index * 10 + (val_c * 8).round(), -1)
    key = key.reshape(cv_.shape)
    val_c = val_c.reshape(cv_.shape)
    same = (
        (key[:-1, :-1] == key[1:, :-1])
        & (key[:-1, :-1] == key[:-1, 1:])
        & (key[:-1, :-1] == key[1:, 1:])
    )
    region_bg = color[v0 : v1 + 1, u0 : u1 + 1]
    region_depth_bg = bg.depth[v0 : v1 + 1, u0 : u1 + 1]
    # pixel-centre depth decides occlusion between the board and the static scene
    cvv, cuu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1].astype(float)
    centre_rays = None if bg.rays is None else bg.rays[v0 : v1 + 1, u0 : u1 + 1].reshape(-1, 3)
    hits_p, _ = trace(cuu.ravel(), cvv.ravel(), grid=cuu.shape, shade=False, rays=centre_rays)
    z_board = hits_p.depth.reshape(cvv.shape)
    board_front = z_board < region_depth_bg
    uniform_board = same & (key[:-1, :-1] >= 0) & board_front
    out = region_bg.copy()
    out[uniform_board] = val_c[:-1, :-1][uniform_board][:, None]
    mixed = ~same
    if np.any(mixed):
        mv, mu = np.nonzero(mixed)
        s = supersample
        offs = (np.arange(s) + 0.5) / s - 0.5
        ov, ou = np.meshgrid(offs, offs, indexing="ij")
        us = (mu[:, None] + u0 + ou.ravel()[None]).ravel()
        vs = (mv[:, None] + v0 + ov.ravel()[None]).ravel()
        hits_s, val_s = trace(us, vs)
        zbg = np.repeat(region_depth_bg[mv, mu], s * s)
        vis = (hits_s.index >= 0) & (hits_s.depth < zbg)
        bgc = np.repeat(region_bg[mv, mu], s * s, axis=0)
        samp = np.where(vis[:, None], val_s[:, None], bgc)
        out[mv, mu] = samp.reshape(-1, s * s, 3).mean(axis=1)
    color[v0 : v1 + 1, u0 : u1 + 1] = out
    depth[v0 : v1 + 1, u0 : u1 + 1] = np.where(board_front, z_board, region_depth_bg)
    return color, depth


def finish_color(color: np.ndarray, params: SynthParams, rng: np.random.Generator) -> np.ndarray:
    """Lens blur, sensor noise and 8-bit quantisation."""
    img = color * 255.0
    if params.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), params.blur_sigma_px)
    if params.color_noise_dn > 0:
        img = img + rng.normal(0.0, params.color_noise_dn, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def finish_depth(
    depth_m: np.ndarray, cam: SynthCamera, params: SynthParams, rng: np.random.Generator
) -> np.ndarray:
    """D435 depth: noise sigma_z = z^2 s / (f B), scale bias, range limits, dropout, counts."""
    K = cam.intrinsics
    z = np.where(np.isfinite(depth_m), depth_m, 0.0)
    sigma = z**2 * params.depth_subpixel_px / (K.fx * params.depth_baseline_m)
    z = (z + rng.normal(0.0, 1.0, z.shape) * sigma) * cam.depth_scale_bias
    valid = (z >= params.depth_min_m) & (z <= params.depth_max_m)
    valid &= rng.random(z.shape) >= params.depth_dropout
    counts = np.where(valid, np.rint(z / K.depth_scale), 0)
    return np.clip(counts, 0, 65535).astype(np.uint16)


# --------------------------------------------------------------------------- dataset writer
_WORKER: dict = {}


def _init_worker(state: dict) -> None:
    cv2.setNumThreads(1)  # one process per core already
    _WORKER.update(state)
    _WORKER["model"] = _BoardModel(state["board"], state["printed"])


def _render_frame(job: tuple[int, np.ndarray]) -> None:
    index, T_world_board = job
    rig: SynthRig = _WORKER["rig"]
    params: SynthParams = _WORKER["params"]
    writer: FolderWriter = _WORKER["writer"]
    frame = f"{index:06d}"
    for ci, cam in enumerate(rig.cameras):
        rng = np.random.default_rng([_WORKER["seed"], index, ci])
        if params.drop_rate > 0 and rng.random() < params.drop_rate:
            continue
        T_cam_board = invert_transform(cam.T_world_cam) @ T_world_board
        color, depth = render_board(
            _WORKER["model"], cam, _WORKER["backgrounds"][ci], T_cam_board, params.supersample
        )
        writer.write(cam.name, "color", frame, finish_color(color, params, rng))
        writer.write(cam.name, "depth", frame, finish_depth(depth, cam, params, rng))


@dataclass(frozen=True)
class SynthDataset:
    path: Path
    rig: SynthRig
    board_poses: list[np.ndarray]


def synthesize(
    out: Path,
    layout: str,
    n_frames: int,
    seed: int,
    board: Board,
    params: SynthParams = SynthParams(),
    workers: int | None = None,
    progress: Progress | None = None,
) -> SynthDataset:
    """Render a rig into the folder form of docs/formats.md, with ``ground_truth.yaml``.

    Written into a temporary sibling folder and renamed into place at the end, so an
    interrupted run never leaves a half-written dataset under ``out``. ``rig.yaml`` holds
    what each camera's :attr:`SynthCamera.rig_intrinsics` says, the images are rendered with
    the truth; ``board`` is the board file a user calibrates with, the physical board is its
    :func:`board_print`."""
    out = Path(out)
    if n_frames < 1:
        raise ConfigError("--frames must be at least 1")
    if out.exists() and any(out.iterdir()):
        raise ConfigError(
            f"{out}: output folder exists and is not empty; choose a new folder or delete it"
        )
    rig = make_rig(layout, seed, params)
    printed = board_print(board, params)
    rng = np.random.default_rng(seed + 1)
    poses = sample_board_poses(rig, board, n_frames, rng)
    closeups = closeup_poses(rig, board, params.closeups,
                             np.random.default_rng([seed, CLOSEUP_STREAM]))
    poses += [T for _, T in closeups]  # after the regular frames, which stay as without them
    with staged_folder(out) as tmp:
        writer = FolderWriter(
            tmp, Rig({c.name: c.rig_intrinsics for c in rig.cameras}, rig.reference)
        )
        workers = workers or os.cpu_count() or 1
        if workers <= 1:
            backgrounds = [render_background(rig.scene, cam) for cam in rig.cameras]
        else:
            with executor(workers) as ex:
                backgrounds = list(
                    ex.map(render_background, [rig.scene] * len(rig.cameras), rig.cameras)
                )
        state = {
            "rig": rig,
            "params": params,
            "writer": writer,
            "seed": seed,
            "board": board,
            "printed": printed,
            "backgrounds": backgrounds,
        }
        jobs = list(enumerate(poses))
        tick = start(progress, "rendering frame sets", len(jobs))
        if workers <= 1:
            _init_worker(state)
            for job in jobs:
                _render_frame(job)
                tick(1)
        else:
            with executor(workers, initializer=_init_worker, initargs=(state,)) as ex:
                for _ in ex.map(_render_frame, jobs, chunksize=1):
                    tick(1)
        T_world_ref = rig.cameras[rig.reference_index].T_world_cam
        T_ref_world = invert_transform(T_world_ref)
        write_yaml(
            tmp / "ground_truth.yaml",
            {
                "reference": rig.reference,
                "T_ref_cam": {c.name: rig.T_ref_cam(c) for c in rig.cameras},
                "T_ref_board": {f"{i:06d}": T_ref_world @ T for i, T in enumerate(poses)},
                "depth_scale_bias": {c.name: c.depth_scale_bias for c in rig.cameras},
                "layout": layout,
                "seed": seed,
                "board": {
                    **board.to_dict(),  # the board file, nominal
                    "T_front_back": printed.T_front_back,
                    "print_scale": printed.print_scale,
                    "thickness_m": printed.thickness_m,
                    **({"T_board_face": {s.label: printed.face_poses.get(s.label,
                                                                         s.T_board_face)
                                         for s in board.sheets}} if board.sheets else {}),
                },
                "intrinsics": {c.name: c.intrinsics.to_dict() for c in rig.cameras},
                "params": {
                    k: _plain(v) for k, v in params.__dict__.items()
                },
                "bumped": {name: {"mm": mm, "deg": deg} for name, mm, deg in params.bump},
                "closeups": {f"{n_frames + i:06d}": name
                             for i, (name, _) in enumerate(closeups)},
            },
        )
    return SynthDataset(out, rig, poses)


def _plain(value):
    """Tuples (nested too) as lists, for YAML."""
    return [_plain(v) for v in value] if isinstance(value, (tuple, list)) else value


RENDER_KEY = "render_key.json"  # beside a cached render: what it was rendered from


def render_key(layout: str, n_frames: int, seed: int, board: Board, params: SynthParams) -> str:
    """What a render depends on: its arguments and the renderer's own source (every module of
    ``synth/`` and the camera model, so a changed renderer renders again), as a short hash."""
    import hashlib
    import json

    from ..core import camera

    files = sorted(Path(__file__).parent.glob("*.py")) + [Path(camera.__file__)]  # synth/
    sources = [f.read_bytes() for f in files]
    args = json.dumps([layout, n_frames, seed, board.to_dict(), repr(params)], default=str)
    digest = hashlib.sha256(args.encode())
    for src in sources:
        digest.update(src)
    return digest.hexdigest()[:16]


def synthesize_cached(
    out: Path,
    layout: str,
    n_frames: int,
    seed: int,
    board: Board,
    params: SynthParams = SynthParams(),
    workers: int | None = None,
    progress: Progress | None = None,
) -> tuple[Path, bool]:
    """:func:`synthesize` into ``out`` unless ``out`` already holds the same render (same
    arguments, same renderer: :func:`render_key`, kept in ``out``'s sibling
    ``<out>.render_key.json``); returns ``(out, reused)``. A reused render keeps its files'
    times, so a calibration's detection cache stays valid too."""
    import json
    import shutil

    out = Path(out)
    key_file = out.with_name(out.name + "." + RENDER_KEY)
    key = render_key(layout, n_frames, seed, board, params)
    try:
        cached = json.loads(key_file.read_text()).get("key")
    except (OSError, ValueError, AttributeError):
        cached = None
    if cached == key and (out / "ground_truth.yaml").is_file():
        return out, True
    key_file.unlink(missing_ok=True)
    if out.exists():
        shutil.rmtree(out)
    synthesize(out, layout, n_frames, seed, board, params, workers, progress)
    key_file.write_text(json.dumps({"key": key}) + "\n")
    return out, False


@dataclass(frozen=True)
class GroundTruth:
    """``ground_truth.yaml`` of a synthetic set (never read by the calibration itself).

    ``intrinsics`` are the true camera models the images were rendered with (empty for a set
    written before they were recorded: its ``rig.yaml`` is then exact). ``T_front_back``,
    ``print_scale`` and ``thickness_m`` (None: the board file's) describe the physical board
    (:class:`BoardPrint`); absent, the board is exactly its board file. ``closeups`` names
    the camera each close-up frame set was posed for (``--closeups``; empty without)."""

    reference: str
    T_ref_cam: dict[str, np.ndarray]
    T_ref_board: dict[str, np.ndarray]
    depth_scale_bias: dict[str, float]
    intrinsics: dict[str, CameraIntrinsics] = field(default_factory=dict)
    T_front_back: np.ndarray = field(default_factory=lambda: np.eye(4))
    print_scale: float = 1.0
    thickness_m: float | None = None
    closeups: dict[str, str] = field(default_factory=dict)  # frame -> camera (--closeups)
    T_board_face: dict[int, np.ndarray] = field(default_factory=dict)  # multi-face: true poses

    def board_print(self, board: Board) -> BoardPrint:
        """The physical board of this set, for the board file ``board`` it was rendered with."""
        thickness = board.thickness if self.thickness_m is None else self.thickness_m
        return BoardPrint(thickness, self.print_scale, self.T_front_back,
                          dict(self.T_board_face))


def load_ground_truth(path: Path) -> GroundTruth:
    from ..core.yamlio import matrix4, read_yaml_mapping
    from ..model.rig import parse_camera

    path = Path(path)
    if path.is_dir():
        path = path / "ground_truth.yaml"
    data = read_yaml_mapping(path, "ground truth")
    board = data.get("board") or {}
    thickness = board.get("thickness_m")
    return GroundTruth(
        str(data["reference"]),
        {k: matrix4(v, f"{path}: T_ref_cam.{k}") for k, v in data["T_ref_cam"].items()},
        {str(k): matrix4(v, f"{path}: T_ref_board.{k}") for k, v in data["T_ref_board"].items()},
        {k: float(v) for k, v in data.get("depth_scale_bias", {}).items()},
        {
            str(k): parse_camera(v, f"{path}: intrinsics.{k}")
            for k, v in (data.get("intrinsics") or {}).items()
        },
        matrix4(board["T_front_back"], f"{path}: board.T_front_back")
        if "T_front_back" in board
        else np.eye(4),
        float(board.get("print_scale", 1.0)),
        None if thickness is None else float(thickness),
        {str(k): str(v) for k, v in (data.get("closeups") or {}).items()},
        {int(k): matrix4(v, f"{path}: board.T_board_face.{k}")
         for k, v in (board.get("T_board_face") or {}).items()},
    )
