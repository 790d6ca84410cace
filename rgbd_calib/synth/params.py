"""The settings of a synthetic render (:class:`SynthParams`, checked by :func:`check_params`)
and the synthetic rig it renders (:class:`SynthRig` of :class:`SynthCamera`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.camera import DISTORTION_LENGTHS, FISHEYE, LENS_MODELS, OPENCV, CameraIntrinsics
from ..core.depth_model import DepthModel
from ..core.errors import ConfigError
from ..core.geometry import invert_transform
from .scene import Rect

RIG_DISTORTIONS = ("zeros", "truth")  # what rig.yaml lists under --distortion


@dataclass(frozen=True)
class SynthParams:
    """Rendering and noise settings (units in the names)."""

    resolution: tuple[int, int] | None = None  # (width, height); None: the layout's default
    blur_sigma_px: float = 0.6
    color_noise_dn: float = 2.0
    depth_subpixel_px: float = 0.08  # D435 subpixel disparity error s
    depth_baseline_m: float = 0.050  # D435 stereo baseline B
    depth_bias: float = 0.0  # max |relative depth-scale error| per camera (uniform in +-)
    # each camera's depth errors (core.depth_model; docs/synthetic.md, "Depth errors"): the
    # disparity offset d0 and each field coefficient dx .. dyy uniform in +-these (px), the
    # depth-to-colour pose off by a rotation vector and a shift, each component uniform in
    # +-(deg, mm)
    depth_disparity_offset_px: float = 0.0
    depth_disparity_field_px: float = 0.0
    depth_pose_error: tuple[float, float] = (0.0, 0.0)
    depth_dropout: float = 0.02  # fraction of valid depth pixels set to 0
    depth_min_m: float = 0.28
    depth_max_m: float = 6.0
    drop_rate: float = 0.0  # probability that a camera misses a frame entirely
    supersample: int = 8
    cameras: int | None = None  # camera count (ring only)
    # real-world imperfections (docs/synthetic.md); the defaults render the ideal rig
    distortion: tuple[float, ...] | None = None  # true OpenCV k1 k2 p1 p2 k3 of every camera
    rig_distortion: str = "zeros"  # rig.yaml lists "zeros" (as a D435 reports) or the "truth"
    lens: str = OPENCV  # the lens model of ``distortion``: OpenCV's, or a fisheye's k1..k4
    intrinsics_error: tuple[float, float] = (0.0, 0.0)  # rig.yaml: max |focal error| %, max px
    glue: tuple[float, float, float] = (0.0, 0.0, 0.0)  # back sheet: dx mm, dy mm, rot deg
    thickness_error_mm: float = 0.0  # true panel thickness minus the board file's
    print_scale: float = 1.0  # printed size / board file size, both faces
    # the printer's ink spreads this far beyond the file's black edges (mm; negative: thinner),
    # both faces: every marker edge that much outward, each white bit that much smaller
    ink_spread_mm: float = 0.0
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
    # time (docs/synthetic.md, "Time"): the board's speed (m/s) and turn rate (deg/s) during
    # each frame set, each non-reference camera's clock offset within +-sync_offset_ms, and
    # the rolling-shutter readout (first to last row, ms) of every colour camera
    motion: tuple[float, float] = (0.0, 0.0)
    sync_offset_ms: float = 0.0
    rolling_shutter_ms: float = 0.0
    # a timed render's timestamps.csv: each stamp's error (Gaussian sigma, ms); the truth in
    # ground_truth.yaml stays exact
    timestamp_jitter_ms: float = 0.5
    # a continuous recording: each board position held for `burst` consecutive frame sets at
    # `frame_rate` fps, the board moving along one trajectory with the constant linear and angular
    # acceleration `acceleration` (m/s^2, deg/s^2; seeded directions) (docs/synthetic.md)
    burst: int = 1
    acceleration: tuple[float, float] = (0.0, 0.0)
    # the recording's frame rate (fps): a burst's consecutive frame sets are 1/frame_rate apart
    frame_rate: float = 30.0

    @property
    def depth_errors(self) -> bool:
        """Whether any depth-error setting beyond ``depth_bias`` is on (the render then lists
        them under ``params`` in ``ground_truth.yaml``)."""
        return any(x != 0 for x in (self.depth_disparity_offset_px,
                                    self.depth_disparity_field_px, *self.depth_pose_error))

    @property
    def timed(self) -> bool:
        """Whether any of the time settings is on (the render then has a ``time:`` truth)."""
        return self.burst > 1 or self.frame_rate != 30.0 or any(
            x != 0 for x in (*self.motion, self.sync_offset_ms, self.rolling_shutter_ms,
                             *self.acceleration))


def check_params(params: SynthParams) -> None:
    """Reject imperfection settings that cannot be rendered, naming the option."""
    if params.lens not in LENS_MODELS:
        raise ConfigError(f"lens {params.lens!r}: choose {' or '.join(LENS_MODELS)}")
    if params.lens == FISHEYE and (params.distortion is None or len(params.distortion) != 4):
        raise ConfigError("--fisheye: give the lens's four coefficients K1 K2 K3 K4 "
                          "(equidistant, cv2.fisheye's)")
    if (params.lens != FISHEYE and params.distortion is not None
            and len(params.distortion) not in DISTORTION_LENGTHS):
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
    if not (-0.5 <= params.ink_spread_mm <= 0.5):
        raise ConfigError(f"--ink-spread {params.ink_spread_mm}: give an ink spread of -0.5 to "
                          "0.5 mm (a laser print spreads ~0.05-0.1 mm)")
    if not (0.1 <= params.board_volume <= 5.0):
        raise ConfigError(f"--board-volume {params.board_volume}: expected a factor in 0.1-5 "
                          "of the layout's board volume")
    if not (0 <= params.closeups <= 64):
        raise ConfigError(f"--closeups {params.closeups}: expected 0-64 frame sets per camera")
    mm, deg = params.face_error
    if not (0 <= mm < 100 and 0 <= deg < 30):
        raise ConfigError(f"--face-error {mm} {deg}: give a shift 0 <= mm < 100 and a turn "
                          "0 <= deg < 30")
    speed_mps, rate_dps = params.motion
    if not (0 <= speed_mps <= 3 and 0 <= rate_dps <= 360):
        raise ConfigError(f"--motion {speed_mps} {rate_dps}: give a board speed 0-3 m/s and a "
                          "turn rate 0-360 deg/s")
    if not (0 <= params.sync_offset_ms <= 100):
        raise ConfigError(f"--sync-offset-ms {params.sync_offset_ms}: give a largest camera "
                          "clock offset of 0-100 ms")
    if not (0 <= params.rolling_shutter_ms <= 100):
        raise ConfigError(f"--rolling-shutter-ms {params.rolling_shutter_ms}: give a colour "
                          "readout time (first to last row) of 0-100 ms")
    if not (1 <= params.burst <= 30):
        raise ConfigError(f"--burst {params.burst}: give 1-30 consecutive frame sets per "
                          "board position")
    if not (1 <= params.frame_rate <= 120):
        raise ConfigError(f"--frame-rate {params.frame_rate}: give a recording's frame rate of "
                          "1-120 fps")
    accel_mps2, accel_dps2 = params.acceleration
    if not (0 <= accel_mps2 <= 30 and 0 <= accel_dps2 <= 3000):
        raise ConfigError(f"--acceleration {accel_mps2} {accel_dps2}: give 0-30 m/s^2 and "
                          "0-3000 deg/s^2")
    if not (0 <= params.timestamp_jitter_ms <= 50):
        raise ConfigError(f"--timestamp-jitter-ms {params.timestamp_jitter_ms}: give a "
                          "timestamp error (sigma) of 0-50 ms")
    _check_depth_errors(params)
    for name, mm, deg in params.bump:
        if not (mm >= 0 and 0 <= deg < 90):
            raise ConfigError(f"--bump {name} {mm} {deg}: give a shift >= 0 mm and a turn "
                              "0 <= deg < 90")


# the largest depth errors rendered: a disparity offset of a few pixels already moves a
# surface at 3 m by metres at 848x480 (f B ~ 21 px m); a pose error of degrees and centimetres
MAX_DISPARITY_PX = 5.0
MAX_POSE_ERROR = (5.0, 50.0)  # deg, mm


def _check_depth_errors(params: SynthParams) -> None:
    """The depth-error settings are non-negative half-widths below the limits above."""
    for option, px in (("--depth-disparity-offset", params.depth_disparity_offset_px),
                       ("--depth-disparity-field", params.depth_disparity_field_px)):
        if not (0 <= px <= MAX_DISPARITY_PX):
            raise ConfigError(f"{option} {px}: give a largest disparity error of "
                              f"0-{MAX_DISPARITY_PX:g} px (e.g. 0.1)")
    deg, mm = params.depth_pose_error
    if not (0 <= deg <= MAX_POSE_ERROR[0] and 0 <= mm <= MAX_POSE_ERROR[1]):
        raise ConfigError(f"--depth-pose-error {deg} {mm}: give a largest turn of "
                          f"0-{MAX_POSE_ERROR[0]:g} deg and shift of 0-{MAX_POSE_ERROR[1]:g} mm "
                          "(e.g. 0.2 1)")


@dataclass(frozen=True)
class SynthCamera:
    """One camera: ``intrinsics`` is the truth the images are rendered with (lens distortion
    included); ``listed_intrinsics`` what its ``rig.yaml`` says (None: the truth).

    ``depth_model`` is the camera's true depth model (:class:`DepthModel`: the depth it
    reports for a true depth is its ``measured_depth``, after its pose error); its ``scale``
    is ``depth_scale_bias``. None: the depth errors are ``depth_scale_bias`` alone."""

    name: str
    intrinsics: CameraIntrinsics
    T_world_cam: np.ndarray
    depth_scale_bias: float = 1.0
    listed_intrinsics: CameraIntrinsics | None = None
    depth_model: DepthModel | None = None

    def __post_init__(self) -> None:
        if self.depth_model is not None and self.depth_model.value("scale") != \
                self.depth_scale_bias:
            raise ValueError(f"camera {self.name}: depth_model.scale "
                             f"{self.depth_model.value('scale')} is not depth_scale_bias "
                             f"{self.depth_scale_bias}")

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
