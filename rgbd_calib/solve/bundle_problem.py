"""The inputs and the result of one bundle adjustment (:mod:`rgbd_calib.solve.bundle`), as
data: a marker seen in a view, a measured camera-to-camera pose, the problem whole (as mrcal's
``optimization_inputs``, re-solved with one thing changed by ``dataclasses.replace``) and what
the solve returns; and the intrinsics' parameter vector and prior sigmas both the solve and the
ladder read. No solving here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.config import BundleConfig
from .bundle_faces import BoardModel, FaceModel
from .bundle_factors import lens_names, padded_distortion
from .corner_noise import CornerNoise
from .edge_offset import EdgeOffset
from .runs import RunCorrelation
from .time_model import TimeModel, TimePrior


@dataclass(frozen=True)
class MarkerMeasurement:
    """One marker seen in one view: 4 pixels and their board points. The pixels are
    undistorted pinhole pixels when the intrinsics are fixed, the raw detected pixels when the
    bundle adjustment refines them (see :func:`bundle_adjust`)."""

    camera: str
    view: str
    marker_id: int
    corners_px: np.ndarray  # (4,2) pinhole pixels (fixed intrinsics) or raw pixels (refine)
    object_points: np.ndarray  # (4,3) board frame, metres
    face: int = 1  # +1 front, -1 back: a back marker moves with the back sheet (board refine);
    #               a multi-face target's face label (its face's pose moves it)
    edge_fitted: bool = True  # an ArUco marker's corners (False: a ChArUco square's saddles)


@dataclass(frozen=True)
class RelativePose:
    """A measured camera-to-camera pose ``T_b_a`` (maps camera a's points into camera b),
    e.g. from registering their depth clouds, with its 6x6 information in GTSAM order
    ``[rot, trans]`` for the right perturbation ``T_b_a @ Exp(xi)``."""

    cam_a: str
    cam_b: str
    T_b_a: np.ndarray
    information: np.ndarray

    def factor(self, key: dict[str, int]) -> gtsam.BetweenFactorPose3:
        """Its factor between the cameras' pose variables (camera -> ``key``):
        ``BetweenFactorPose3(b, a)`` predicts ``T_ref_b^-1 T_ref_a = T_b_a``; its error is
        ``Logmap(T_b_a_measured^-1 T_b_a)``, the right perturbation the information is for."""
        return gtsam.BetweenFactorPose3(key[self.cam_b], key[self.cam_a], gtsam.Pose3(self.T_b_a),
                                        gtsam.noiseModel.Gaussian.Information(self.information))


@dataclass(frozen=True)
class BundleResult:
    T_ref_cam: dict[str, np.ndarray]
    T_ref_board: dict[str, np.ndarray]
    covariance: dict[str, np.ndarray]  # camera -> 6x6 body-frame [rot, trans]
    sigma_rotation_deg: dict[str, float]
    sigma_translation_mm: dict[str, float]
    residuals_px: list[tuple[str, str, int, float]]  # (camera, view, marker, rms px)
    outliers: list[tuple[str, str, int, float]]
    pixel_sigma_estimated: float
    iterations: int
    final_error: float
    # refined intrinsics only (config.intrinsics == "refine"): camera -> the refined model,
    # camera -> {parameter: marginal sigma} and {parameter: prior sigma}, both in the order
    # of config.intrinsics_params
    intrinsics: dict[str, CameraIntrinsics] = field(default_factory=dict)
    intrinsics_sigma: dict[str, dict[str, float]] = field(default_factory=dict)
    intrinsics_prior_sigma: dict[str, dict[str, float]] = field(default_factory=dict)
    # board self-calibration (config.board == "refine"): the estimated back-sheet pose, its
    # 6x6 marginal [rot, trans] (right perturbation) and why it was held, if it was
    board: BoardModel | None = None
    # ... of a multi-face target: each non-reference face's estimated pose (empty otherwise)
    faces: tuple[FaceModel, ...] = ()
    # the time model (config.time == "refine"): clocks, readouts and the board's motion
    time: TimeModel | None = None
    # consecutive frames of a continuous recording: per camera the correlation of their corner
    # errors and the variance factor applied to its sigmas (rgbd_calib/solve/runs.py)
    run_correlation: dict[str, RunCorrelation] = field(default_factory=dict)
    # per relative pose of the problem, in its order: its whitened chi-square at the solution
    # and its redundancy number (:func:`relative_pose_fit`); (0, 0) for one not in the solve
    relative_pose_fit: tuple[tuple[float, float], ...] = ()
    # per camera: the edge offset its corner residuals read (:mod:`rgbd_calib.solve.edge_offset`)
    edge_offset: dict[str, EdgeOffset] = field(default_factory=dict)
    # the corners' centre and shape noise read from the residuals; the rig scale's sigma (ppm)
    corner_noise: CornerNoise | None = None  # in every covariance (corners.corner_noise: marker)
    # the rig scale's relative sigma (ppm) in every covariance: the marker model's
    # (config.corners.scale_sigma_ppm) and the board's printed size (board_scale_sigma) together
    scale_sigma_ppm: float = 0.0
    # config.held_out: each marker's corner RMS (px) predicted from the other cameras' views of
    # its frame set, (camera, view, marker) -> px (rgbd_calib/solve/bundle.py _held_out)
    held_out_px: dict[tuple[str, str, int], float] = field(default_factory=dict)


@dataclass(frozen=True)
class BundleProblem:
    """The inputs of one bundle adjustment, whole (as mrcal's ``optimization_inputs``): a
    caller re-solves it with one thing changed by ``dataclasses.replace(problem, config=...,
    T_ref_cam=...)``. Poses are 4x4, metres; see :func:`bundle_adjust` for how each is used."""

    measurements: Sequence[MarkerMeasurement]
    K: dict[str, np.ndarray]  # camera -> 3x3 pinhole matrix (fixed intrinsics)
    reference: str  # the camera held at the identity
    T_ref_cam: dict[str, np.ndarray]  # initial camera poses
    T_ref_board: dict[str, np.ndarray]  # initial board poses, per view
    config: BundleConfig = field(default_factory=BundleConfig)
    fixed_cameras: dict[str, np.ndarray] | None = None  # camera -> T_ref_cam held
    relative_poses: Sequence[RelativePose] = ()  # depth registration's camera-to-camera poses
    intrinsics: dict[str, CameraIntrinsics] | None = None  # rig.yaml models: refine's priors
    back_centre: np.ndarray | None = None  # board-file centre of the back-marker grid (m)
    face_frames: dict[int, np.ndarray] | None = None  # multi-face: label -> T_board_face
    # the time model: (camera, view) -> capture time after the set's (ms, from timestamps) and
    # the priors of the cameras' [offset, readout] (default: weak, TimePrior())
    capture_ms: dict[tuple[str, str], float] | None = None
    time_priors: dict[str, TimePrior] | None = None
    # the time model: each frame set's nominal time (ms, from timestamps): consecutive sets
    # of a continuous recording are tied by the motion prior (time_model.motion_links)
    set_ms: dict[str, float] | None = None
    # refine: where the refined intrinsics start (a simpler model's or the last solve's
    # estimate; camera -> model); their priors stay at ``intrinsics``. None: at the priors
    intrinsics_start: dict[str, CameraIntrinsics] | None = None
    # per camera its detector's edge offset (px per edge), taken out of its edge-fitted
    # corners before the solve (rgbd_calib/solve/edge_offset.py; estimated by ladder.py)
    edge_offset: dict[str, float] | None = None
    # how well the board's printed size is known (relative 1 sigma; the board file's
    # print_scale_sigma): the rig's scale, added to every solved camera's covariance
    board_scale_sigma: float = 0.0


def intrinsics_vector(base: CameraIntrinsics, names: tuple[str, ...]) -> np.ndarray:
    """The values of the parameters ``names`` of ``base`` (missing coefficients are 0)."""
    names = lens_names(base, names)
    padded = replace(base, distortion=padded_distortion(base, names))
    table = padded.parameters
    return np.array([table[n] for n in names], dtype=float)


def intrinsics_prior_sigmas(base: CameraIntrinsics, names: tuple[str, ...],
                            config: BundleConfig) -> np.ndarray:
    """Prior sigmas of the parameters ``names``: focal in percent of its value, centre in
    pixels, p1/p2 tangential, every other coefficient with the distortion sigma."""
    out = []
    prior = config.intrinsics_prior
    for n in lens_names(base, names):
        if n in ("fx", "fy"):
            out.append(prior.intrinsics_prior_focal_pct / 100.0 * getattr(base, n))
        elif n in ("cx", "cy"):
            out.append(prior.intrinsics_prior_center_px)
        elif n in ("p1", "p2"):
            out.append(prior.intrinsics_prior_tangential)
        else:
            out.append(prior.intrinsics_prior_distortion)
    return np.array(out, dtype=float)
