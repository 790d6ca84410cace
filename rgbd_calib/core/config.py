"""Every setting of a calibration run: one pydantic model per stage, combined in
:class:`CalibrationConfig`, and the YAML config file (:func:`load_config`, :func:`write_config`).

A YAML file may override any subset of the settings; unknown keys are errors (``extra="forbid"``),
so field names and defaults here are the user-facing config format (``config_resolved.yaml``
beside every result lists them all).

Imports pydantic and yaml only: validating a config (in the CLI, or in a detection worker that
receives one) must not load cv2, gtsam, open3d or kiss_icp (tests/test_config.py checks this).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from .camera import DISTORTION_NAMES
from .config_depth import DepthConfig
from .errors import ConfigError
from .settings import (
    apply_user_section,
    set_dotted,
    split_user_section,
    user_section_comments,
)
from .yamlio import read_yaml_mapping, to_builtin

Refinement = Literal["edges", "subpix", "none", "contour"]
# how a pair of depth clouds is registered: Open3D's colored ICP (Park et al. 2017) or kiss-icp's
# geometric ICP; the one definition of the names (config, CLI and the depth stage check them)
RegistrationMethod = Literal["colored-icp", "geometric"]
REGISTRATION_METHODS: tuple[str, ...] = get_args(RegistrationMethod)

# sqrt(chi2_6.ppf(0.99)): 99% of inlier 6-dof whitened residual norms lie below this.
DEFAULT_KERNEL_THRESHOLD = 4.1


# ----------------------------------------------------------------------------- detection
class DetectionConfig(BaseModel, extra="forbid"):
    """ArUco detection and corner refinement (the detection stage of the pipeline)."""

    refinement: Refinement = Field(
        "edges",
        description="Corner refinement: 'edges' fits lines to the four outer marker "
        "edges (unbiased; a corner it cannot fit gets OpenCV's SUBPIX refinement and "
        "refined=False); 'subpix', 'none' and 'contour' are OpenCV's CORNER_REFINE_* methods "
        "(biased 0.2-0.6 px towards the marker centre).",
    )
    charuco_corners: Literal["painted", "subpix", "opencv"] = Field(
        "painted",
        description="ChArUco boards: saddle-corner refinement of the corners OpenCV's "
        "CharucoDetector interpolated. 'painted' fills the detected markers with their "
        "square's white, then cornerSubPix on a window of 0.4 square; 'subpix' runs "
        "cornerSubPix on the raw image within the white margin around the markers; 'opencv' "
        "keeps the detector's own corners (docs/accuracy.md compares them).",
    )
    min_marker_perimeter_px: float = Field(
        40.0,
        gt=0,
        description="Smallest marker perimeter (px) the detector accepts; converted "
        "to OpenCV's minMarkerPerimeterRate for each image size.",
    )
    error_correction_rate: float = Field(
        0.6,
        ge=0.0,
        le=1.0,
        description="OpenCV errorCorrectionRate: fraction of the "
        "dictionary's correctable bits used. Lower it if foreign/stray ids appear.",
    )
    adaptive_thresh_win_size_min: int = Field(
        3, ge=3, description="OpenCV adaptive threshold: smallest window (px)."
    )
    adaptive_thresh_win_size_max: int = Field(
        23, ge=3, description="OpenCV adaptive threshold: largest window (px)."
    )
    adaptive_thresh_win_size_step: int = Field(
        10, ge=1, description="OpenCV adaptive threshold: window step (px)."
    )
    subpix_win_size_px: int = Field(
        5,
        ge=1,
        description="OpenCV cornerRefinementWinSize: upper bound of the SUBPIX half-window (px).",
    )
    subpix_relative_win_size: float = Field(
        1.0,
        gt=0,
        description="OpenCV relativeCornerRefinmentWinSize: SUBPIX half-window as a "
        "fraction of a marker module, capped by subpix_win_size_px. OpenCV's default 0.3 "
        "shrinks the window to ~1 px on small markers (corner RMS ~0.8 px on the synthetic "
        "renders); 1.0 measured best (~0.3 px RMS, ~0.2 px inward bias).",
    )
    subpix_max_iterations: int = Field(30, ge=1, description="SUBPIX iterations.")
    subpix_min_accuracy_px: float = Field(0.01, gt=0, description="SUBPIX stopping accuracy.")
    edge_span: tuple[float, float] = Field(
        (0.15, 0.85),
        description="Part of each edge sampled by the edge fit, as fractions of "
        "its length from its first corner; keeps away from the blurred corners.",
    )
    edge_corner_margin_px: float = Field(
        2.5,
        ge=0,
        description="Edge points stay at least this far (px) from either corner, "
        "where blur mixes in the quiet zone beyond the corner (pulls points inwards); "
        "tightens edge_span on small markers.",
    )
    edge_max_samples: int = Field(
        48,
        ge=4,
        description="At most this many pixel columns along an edge enter its fit "
        "(longer edges are subsampled).",
    )
    edge_band_modules: float = Field(
        0.8,
        gt=0,
        le=1.0,
        description="Half-width of the band of pixels fitted across an edge, "
        "in marker modules: the black border is one module wide, the data cells behind it are "
        "modelled, the quiet zone outside must be at least this wide.",
    )
    edge_band_px: tuple[float, float] = Field(
        (1.0, 4.0), description="The band half-width in pixels is clipped to this range."
    )
    blur_prior_px: tuple[float, float] = Field(
        (0.7, 0.3),
        description="Prior (mean, sigma) of the Gaussian blur width (px) of the "
        "edge model (pixel area and optics); later passes centre it on the image's median.",
    )
    edge_iterations: int = Field(
        6, ge=3, le=30, description="Levenberg-Marquardt iterations of the edge model per pass."
    )
    max_edge_residual: float = Field(
        0.08,
        gt=0,
        description="Largest RMS residual of an edge fit as a fraction of the "
        "edge's contrast (occlusion or a wrong edge make it large); raised per image by "
        "edge_residual_factor.",
    )
    edge_residual_factor: float | None = Field(
        1.5,
        gt=0,
        description="The residual bound adapts to the image: at least this many times the "
        "median relative residual of the image's edges (a real camera's sharpening and "
        "compression leave ~0.10 on every edge, renders 0.01-0.02), at most "
        "max_edge_residual_cap. None: the fixed max_edge_residual.",
    )
    max_edge_residual_cap: float = Field(
        0.25, gt=0, description="Upper limit of the adapted residual bound (see above)."
    )
    edge_passes: int = Field(
        2,
        ge=1,
        le=5,
        description="Edge-fit passes; each re-centres the band and the marker "
        "layout on the previous corners (one pass leaves ~0.05 px of OpenCV's inward offset).",
    )
    min_edge_length_px: float = Field(
        6.0, gt=0, description="Markers with a shorter side get OpenCV's SUBPIX corners."
    )
    min_edge_contrast: float = Field(
        20.0, gt=0, description="Smallest bright-dark difference (grey levels) of a usable edge."
    )
    min_edge_inliers: float = Field(
        0.5,
        gt=0,
        le=1,
        description="Fraction of an edge's band pixels that must be in the "
        "image and survive outlier rejection for its line to be used.",
    )
    max_corner_shift_px: float = Field(
        3.0,
        gt=0,
        description="An edge-fitted corner further than this from OpenCV's corner "
        "is rejected (the corner gets OpenCV's SUBPIX refinement and refined=False).",
    )
    refine_with_board: bool = Field(
        True,
        description="Run OpenCV's refineDetectedMarkers with the layout of the face seen "
        "most to recover markers the detector rejected (docs/accuracy.md, 'Measurements "
        "behind the detector's design').",
    )

    @model_validator(mode="after")
    def _check(self) -> DetectionConfig:
        lo, hi = self.edge_span
        if not 0.0 <= lo < hi <= 1.0:
            raise ValueError("edge_span must satisfy 0 <= start < end <= 1")
        if not 0 < self.edge_band_px[0] <= self.edge_band_px[1]:
            raise ValueError("edge_band_px must be (min, max) with 0 < min <= max")
        if self.adaptive_thresh_win_size_min > self.adaptive_thresh_win_size_max:
            raise ValueError("adaptive_thresh_win_size_min must not exceed the max")
        return self


# ----------------------------------------------------------------------------- pose
class PoseConfig(BaseModel, extra="forbid"):
    """Per-view PnP and its gates (the pose stage of the pipeline)."""

    min_markers: int = Field(
        4,
        ge=1,
        description="Fewest markers (4 corners each) a view needs. A stray detection "
        "carrying a board id is only recognisable against a consistent majority (with 4, one "
        "outlier faces 3); 1-3 markers also cover little of the board, leaving the planar flip "
        "and the tilt weak (measured: 5-30 mm errors with SUBPIX corners at 1.5 m).",
    )
    min_charuco_corners: int = Field(
        8,
        ge=4,
        description="ChArUco targets: fewest distinct saddle corners a view needs, "
        "whatever its marker count (a whole caliscope-size board is 4 quads; a view of 2 "
        "whole squares has 8 corners). OpenCV's corner interpolation has already checked "
        "each corner against its neighbouring markers, so no majority vote is needed; a "
        "weak view's covariance says how weak it is.",
    )
    max_reprojection_rms_px: float = Field(
        1.0,
        gt=0,
        description="Reject a view whose RMS reprojection error (after dropping "
        "outlier markers) is above this (px).",
    )
    max_ambiguity_ratio: float = Field(
        0.6,
        gt=0,
        le=1,
        description="Reject a view whose IPPE best/second-best reprojection "
        "error ratio is above this (planar flip ambiguity: both poses explain the corners).",
    )
    ambiguity_min_angle_deg: float = Field(
        2.0,
        ge=0,
        description="The ambiguity gate applies only when IPPE's two solutions are "
        "this far apart: a board seen face-on has two nearly equal, nearly identical "
        "solutions, which is no ambiguity.",
    )
    pixel_sigma_px: float | None = Field(
        None,
        gt=0,
        description="Corner noise (px, 1-sigma per axis) for the covariance; None "
        "estimates it per view from the residuals, s^2 = RSS / (2N - 6).",
    )
    min_pixel_sigma_px: float = Field(
        0.01,
        gt=0,
        description="Floor of the estimated corner noise (px): a few corners fitting "
        "too well must not make a view over-confident.",
    )
    sigma_prior_dof: float = Field(
        4.0,
        ge=0,
        description="Pseudo degrees of freedom pulling the estimated marker-shift "
        "noise towards the (larger) all-residual estimate; matters for views with few "
        "markers (see _pose_covariance).",
    )
    model_error_px: Annotated[float, Field(ge=0)] | Literal["auto"] = Field(
        "auto",
        description="Per-view model-error floor (px): sigma of a systematic pixel error "
        "shared by all corners of a view (a common 2-D affine map of its corners: offset, "
        "scale, stretch, shear; intrinsics or distortion slightly off, a marker bias, a "
        "rolling shutter), propagated through the PnP and added to the pose covariance "
        "(rgbd_calib/solve/pose.py::model_error_covariance). The corner-noise estimate cannot "
        "see "
        "it (the pose absorbs it), so without it the pose graph judges real-camera views by "
        "covariances far too small. 'auto' (the default) estimates it from the data: 0 "
        "unless the typical view disagrees with the rig by more than its corner noise "
        "allows, then the floor that makes the typical view consistent "
        "(rgbd_calib/solve/posegraph.py::_estimate_view_floor; docs/accuracy.md 'Per-view "
        "model-error floor'). A number fixes it (0 turns it off; 0.5 is what the real webcams of "
        "docs/accuracy.md need).",
    )
    @field_validator("model_error_px", mode="before")
    @classmethod
    def _number_or_auto(cls, value: Any) -> Any:
        # one message naming both forms, not the number branch's alone
        if isinstance(value, str) and value != "auto":
            try:
                return float(value)
            except ValueError:
                raise ValueError(
                    f"expected a number of pixels (>= 0) or 'auto', got {value!r}"
                ) from None
        return value

    outlier_factor: float = Field(
        5.0,
        gt=1,
        description="A marker whose RMS reprojection error exceeds "
        "max(outlier_factor * median marker error, outlier_min_px) is dropped, the pose "
        "re-solved (worst marker first).",
    )
    outlier_min_px: float = Field(2.0, gt=0, description="See outlier_factor (px).")
    allow_both_faces: bool = Field(
        False,
        description="Keep markers of both faces in one view. A camera cannot see both "
        "faces of the board (they face opposite ways), so by default the face with fewer "
        "markers is treated as wrong detections and dropped.",
    )
    use_unrefined_corners: bool = Field(
        False,
        description="With the 'edges' refinement, also use markers with a corner the "
        "edge fit could not refine (those keep OpenCV's corner, ~0.5 px inward).",
    )


# ----------------------------------------------------------------------------- graph
class PoseGraphConfig(BaseModel):
    """Settings of the pose-graph stage. Thresholds are in whitened units: the norm of the
    6-dof edge residual divided by its sigma (Mahalanobis distance)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kernel: Literal["huber", "cauchy", "tukey", "gm", "none"] = Field(
        "cauchy",
        description="Robust M-estimator on each edge ('gm' = Geman-McClure, "
        "'none' = plain least squares).",
    )
    kernel_threshold: float = Field(
        DEFAULT_KERNEL_THRESHOLD,
        gt=0.0,
        description="Kernel parameter k on the whitened 6-dof residual norm; also the outlier "
        "flag threshold. 4.1 = sqrt(chi2_6 99%).",
    )
    optimizer: Literal["lm", "gnc"] = Field(
        "lm",
        description="First robust solve: Levenberg-Marquardt with the kernel from a "
        "spanning-tree initialisation, or graduated non-convexity (GTSAM GncLMOptimizer).",
    )
    gnc_loss: Literal["gm", "tls"] = Field(
        "gm", description="GNC surrogate loss (Geman-McClure or truncated least squares)."
    )
    reject_outliers: bool = Field(
        True,
        description="After the robust solve, drop edges above kernel_threshold and "
        "re-solve until the inlier set is stable.",
    )
    max_reject_rounds: int = Field(4, ge=1, description="Cap on reject / re-solve rounds.")
    camera_model_error: bool = Field(
        True,
        description="A camera whose median edge residual exceeds kernel_threshold (most of "
        "its views disagree with the rig) has a model error (intrinsics, board, sync), not "
        "outlier views: keep it and scale its edge covariances by its own a-posteriori "
        "variance factor instead of rejecting its views (off: the camera is rejected).",
    )
    model_error_min_views: int = Field(
        3, ge=2, description="Fewest used edges of a camera for the model-error test."
    )
    exclude_stale: bool = Field(
        True, description="Leave out edges that repeat the same camera's previous pose exactly."
    )
    default_sigma_rotation_deg: float = Field(
        0.2, gt=0.0, description="1-sigma per rotation axis of an edge without covariance."
    )
    default_sigma_translation_mm: float = Field(
        2.0, gt=0.0, description="1-sigma per translation axis of an edge without covariance."
    )
    estimate_default_sigmas: bool = Field(
        True,
        description="Re-estimate the two default sigmas from the median residuals of "
        "the edges without covariance (robust variance-component estimate).",
    )
    prior_sigma: float = Field(
        1e-6,
        gt=0.0,
        description="Sigma (rad and m) of the priors holding the reference and fixed cameras.",
    )
    max_iterations: int = Field(100, ge=1, description="Levenberg-Marquardt iteration cap.")
    relative_error_tol: float = Field(1e-10, gt=0.0, description="LM relative error tolerance.")


INTRINSICS_NAMES = ("fx", "fy", "cx", "cy", *DISTORTION_NAMES)


class BundleConfig(BaseModel):
    """Joint bundle adjustment on marker corners (camera and board poses; intrinsics fixed, or
    refined under a prior at the rig.yaml values)."""

    model_config = ConfigDict(extra="forbid")
    pixel_sigma: float = Field(
        0.25,
        gt=0,
        description="prior corner noise (px); re-estimated "
        "from the residuals after the solve when estimate_sigma is on",
    )
    estimate_sigma: bool = Field(
        True,
        description="scale marginals by the a-posteriori "
        "variance factor (RSS / degrees of freedom)",
    )
    robust: Literal["huber", "cauchy", "none"] = "huber"
    robust_k: float = Field(
        3.0, gt=0, description="kernel threshold on a marker's whitened residual norm"
    )
    outlier_px: float = Field(
        3.0,
        gt=0,
        description="a marker whose RMS corner residual after "
        "the solve exceeds this is reported as an outlier and dropped",
    )
    max_iterations: int = Field(100, ge=1)
    relative_error_tol: float = 1e-10
    intrinsics: Literal["fixed", "refine", "auto"] = Field(
        "auto",
        description="fixed: the rig.yaml intrinsics are taken as exact and the corners are "
        "undistorted with them; refine: the parameters of intrinsics_params are estimated per "
        "camera with the rig.yaml values as a Gaussian prior, projecting through the full "
        "camera model (distortion included) onto the raw detected corners; auto: only when the "
        "pose graph finds a camera-level model error, first fx fy cx cy, then the distortion "
        "parameters of intrinsics_params, each kept only when the corners fit better than "
        "the added parameters cost (BIC; see rgbd_calib/selfcal.py); with distortion refined "
        "the markers are detected again with the refined lens",
    )
    intrinsics_params: list[str] = Field(
        default_factory=lambda: ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"],
        min_length=1,
        description="parameters refined per camera (names of OpenCV's model: fx fy cx cy k1 k2 "
        "p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 tau_x tau_y); the others stay at their rig.yaml values. "
        "Distortion is constrained only where the board went: a set that never reaches the "
        "image corners leaves the model there an extrapolation (the report's coverage "
        "warning); leaving k3 out of a lens that has one biases the rest (docs/accuracy.md)",
    )
    intrinsics_prior_focal_pct: float = Field(
        1.0,
        gt=0,
        description="prior sigma of fx and fy, percent of the rig.yaml value (factory "
        "calibrations of RGB-D cameras are typically good to ~0.5-1 %)",
    )
    intrinsics_prior_center_px: float = Field(
        10.0, gt=0, description="prior sigma of cx and cy (px)"
    )
    intrinsics_prior_distortion: float = Field(
        0.1,
        gt=0,
        description="prior sigma of the radial, thin-prism and tilt coefficients (k1..k6, "
        "s1..s4, tau_x, tau_y; unitless): loose against a mild lens, whose k1 is ~0.05-0.2",
    )
    intrinsics_prior_tangential: float = Field(
        0.01,
        gt=0,
        description="prior sigma of the tangential coefficients p1, p2 (unitless; decentring "
        "of a mounted lens is ~1e-3)",
    )

    board: Literal["fixed", "refine", "auto"] = Field(
        "auto",
        description="fixed: the board file's geometry is exact; refine: the pose of the back "
        "sheet relative to the front sheet (in-plane offset, rotation about the normal, "
        "thickness) is estimated with the board file as a Gaussian prior (a misglued back "
        "sheet). Observable only when some view has both faces seen (by different cameras); "
        "otherwise it is held and the result says so. Refine also keeps the pose graph's "
        "outlier views for the bundle adjustment (a misglued sheet makes every back-facing "
        "view an outlier), leaving bad markers to its per-marker kernel. Measured (race, "
        "848x480, 20 frames): glued 1.5/-1.0 mm, 0.3 deg: fixed drops the 4 back-facing "
        "cameras, refine keeps all 8 within 0.11 mm / 0.003 deg; clean: fixed 0.140 mm, "
        "refine 0.131 mm worst. auto: refined when the board is double-sided and the refined "
        "sheet calibrates more cameras or fits the corners better than its 4 parameters cost "
        "(BIC; rgbd_calib/selfcal.py), else the board file's geometry. A multi-face target "
        "(type: multiface): each face but the first gets a 6-dof pose correction instead, "
        "under the board_prior_face_* sigmas, observable when a view sees it with another "
        "face",
    )
    board_prior_offset_mm: float = Field(
        3.0, gt=0, description="prior sigma of the back sheet's in-plane offset (mm, per axis)"
    )
    board_prior_rotation_deg: float = Field(
        1.0, gt=0, description="prior sigma of the back sheet's rotation about the normal (deg)"
    )
    board_prior_thickness_mm: float = Field(
        1.0, gt=0, description="prior sigma of the board's thickness (mm)"
    )
    board_prior_face_offset_mm: float = Field(
        3.0, gt=0, description="multi-face target (a cube, an L): prior sigma of each "
        "non-reference face's shift from its board-file pose (mm, per axis of the face frame; "
        "a hand-assembled target is a few mm off)"
    )
    board_prior_face_rotation_deg: float = Field(
        1.0, gt=0, description="multi-face target: prior sigma of each non-reference face's "
        "turn from its board-file pose (deg, per axis of the face frame)"
    )
    time: Literal["fixed", "refine", "auto"] = Field(
        "auto",
        description="fixed: every camera sees the board at the frame set's instant, each "
        "image exposed at once (the timeless model); refine: per camera a clock offset and a "
        "rolling-shutter readout (ms), per frame set the board's twist (linear and angular "
        "velocity), each corner predicted at its own row's time (rgbd_calib/solve/"
        "time_model.py; docs/conventions.md 'Time'); the offsets' priors come from the "
        "cameras' timestamps.csv when the dataset has them (they fix the time scale, which the "
        "images alone do not). auto: tried, as an alternative to the board's back sheet, "
        "when the pose graph finds views that disagree beyond their noise, and kept only when "
        "it fits the corners better than its parameters cost (BIC) and better than the "
        "board; a still board or synchronised cameras keep the timeless model",
    )
    corner_noise: Literal["marker", "independent"] = Field(
        "independent",
        description="the corners' noise model. marker: each marker's centre and shape weighed "
        "apart, both sigmas estimated from the residuals and the bundle solved again at them "
        "(an edge-fitted marker's corners err together in shape: its centre errs ~2x less "
        "than independent corners would; rgbd_calib/solve/corner_noise.py); independent: "
        "every corner at one sigma",
    )
    corner_centre_ratio: float | None = Field(
        None,
        gt=0,
        description="with corner_noise: marker, the markers' centre-to-shape sigma ratio; "
        "None: read from a first solve (calibrate reads it once and holds it for the rest of "
        "the run: the self-calibration's trials, the depth stage's joint solve)",
    )
    scale_sigma_ppm: float = Field(
        25.0,
        ge=0,
        description="with corner_noise: marker, the rig's scale as the detector sees the board "
        "is known to this (ppm of each camera's distance from the reference) and added to its "
        "covariance: measured on renders, the detected board is 12-27 ppm larger than drawn, "
        "an error no number of views averages out (docs/accuracy.md)",
    )
    edge_offset: Literal["auto", "off"] = Field(
        "auto",
        description="a detector that sees every marker edge a fraction of a pixel outside "
        "where it is (blur, sharpening, ink spread: +0.05..+0.16 px on real prints) moves the "
        "extrinsics ~18 mm per px. auto: per camera the offset its corner residuals read is "
        "taken out of its ArUco corners and the bundle solved again, for a camera whose "
        "reading is >= 5 standard errors and >= 0.01 px (a clean camera keeps none; "
        "rgbd_calib/solve/edge_offset.py); off: read and reported only",
    )
    held_out: bool = Field(
        False, description="also predict each view's corners from the other cameras' views "
        "of its frame set (the self-calibration ladder sets it on its trials: a richer model "
        "is kept only when it predicts them better)"
    )
    time_offset_sigma_ms: float = Field(
        1.0, gt=0, description="sigma of each camera's clock offset about what its "
        "timestamps.csv says (ms): the timestamps' jitter and the host's latency"
    )
    time_twist_sigma_mps: float = Field(
        0.5, gt=0, description="prior sigma of the board's speed during a frame set (m/s, "
        "per axis): a board held or waved by hand"
    )
    time_twist_sigma_dps: float = Field(
        60.0, gt=0, description="prior sigma of the board's turn rate during a frame set "
        "(deg/s, per axis)"
    )
    time_twist_prior_from_data: bool = Field(
        True, description="re-estimate the twist prior's two sigmas from the frame sets' "
        "twists (empirical Bayes, rgbd_calib/solve/bundle.py _twist_prior_from_data), starting "
        "from time_twist_sigma_*: a slowly moved board otherwise keeps the wide prior's "
        "spread, and the sigmas claim several times the error (race, 0.1 m/s, global "
        "shutter: RMS error/sigma 0.15)"
    )
    time_link_ms: Annotated[float, Field(ge=0)] | Literal["auto"] = Field(
        "auto", description="frame sets of a continuous recording no further apart than "
        "this (ms, from the timestamps) are tied by a motion prior (the board's twist changes "
        "smoothly: white-noise acceleration, its scale estimated from the data; rgbd_calib/"
        "solve/time_model.py MotionPrior): consecutive frames then measure the board's "
        "motion, which makes clock offsets with a global shutter and a readout between "
        "synchronised cameras observable; 0: never; auto: 1.5 frame periods of the "
        "recording (its median gap between frame sets, counting gaps up to 200 ms, a 5 fps "
        "camera's), at least 100 ms (rgbd_calib/solve/runs.py link_window_ms)"
    )
    max_sets: int = Field(
        150, ge=0, description="a continuous recording (runs of frame sets time_link_ms "
        "apart) with more frame sets that see the board than this is thinned to about this "
        "many: its stretches keep their best runs of set_run_length consecutive sets, each "
        "camera at least max_sets / 5 views (rgbd_calib/solve/runs.py select_sets). A "
        "minute at 30 fps is 1800 sets of near-duplicate poses, which would make the time "
        "model's bundle adjustment take tens of minutes; 0: keep every set"
    )
    set_run_length: int = Field(
        3, ge=1, description="consecutive frame sets kept together when a recording is "
        "thinned (max_sets): the motion prior measures the board's twist from them"
    )

    @model_validator(mode="after")
    def _known_intrinsics(self) -> BundleConfig:
        unknown = [n for n in self.intrinsics_params if n not in INTRINSICS_NAMES]
        if unknown:
            raise ValueError(
                f"unknown intrinsics parameter(s) {', '.join(unknown)}; choose from "
                + " ".join(INTRINSICS_NAMES)
            )
        if len(set(self.intrinsics_params)) != len(self.intrinsics_params):
            raise ValueError("intrinsics_params lists a parameter twice")
        return self


# ----------------------------------------------------------------------------- whole run
class CalibrationConfig(BaseModel):
    """Every setting of a calibration run; a YAML file may override any subset."""

    model_config = ConfigDict(extra="forbid")
    detection: DetectionConfig = Field(default_factory=DetectionConfig)
    pose: PoseConfig = Field(default_factory=PoseConfig)
    graph: PoseGraphConfig = Field(default_factory=PoseGraphConfig)
    bundle: BundleConfig = Field(default_factory=BundleConfig)
    depth: DepthConfig = Field(default_factory=DepthConfig)
    refine: Literal["auto", RegistrationMethod, "none"] = Field(
        "auto",
        description="depth refinement after the board solve: colored ICP, kiss-icp's "
        "geometric ICP, or none; auto = colored-icp when the dataset has depth (bundle method "
        "only)",
    )
    method: Literal["bundle", "posegraph"] = Field(
        "bundle",
        description="final estimate: joint bundle adjustment on marker corners "
        "(initialised from the pose graph) or the pose graph alone (the thesis method)",
    )
    workers: int | None = Field(None, ge=1, description="detection processes; default: all cores")
    scheduler: str | None = Field(
        None,
        pattern=r"^\S+$",
        description="address of a Dask distributed scheduler (tcp://HOST:8786) whose workers "
        "run the detection and the depth pair registrations instead of local processes "
        "(workers then does not apply); they must see the dataset at the same path",
    )
    edge_covariance: bool = Field(
        True,
        description="weight pose-graph edges by their PnP "
        "covariance (off: one isotropic sigma for every edge, as the "
        "thesis did)",
    )


def load_config(path: Path | None, **overrides: Any) -> CalibrationConfig:
    """CalibrationConfig from an optional YAML file (any subset of keys), then overrides.

    ``overrides`` map dotted keys (``"graph.kernel"``) to values; ``None`` leaves a key alone.
    Raises :class:`ConfigError` with one line naming the file, the setting and the fix."""
    data = read_yaml_mapping(path, "config file") if path else {}
    data = apply_user_section(data, str(path or "options"))
    for dotted, value in overrides.items():
        if value is not None:
            set_dotted(data, dotted, value)
    try:
        return CalibrationConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise ConfigError(
            f"{path or 'options'}: {where}: {err['msg']}; fix this setting "
            "(config_resolved.yaml beside any result lists them all)"
        ) from None


def write_config(config: BaseModel, path: Path) -> None:
    """Write the resolved ``config`` (every setting, defaults included) as YAML, in field order
    (a :class:`CalibrationConfig`: its ``user:`` section first, :mod:`.settings`);
    :func:`load_config` reads it back to the same config."""
    data = to_builtin(config.model_dump())
    if isinstance(config, CalibrationConfig):
        text = user_section_comments() + yaml.safe_dump(split_user_section(data),
                                                        sort_keys=False)
    else:
        text = yaml.safe_dump(data, sort_keys=False)
    Path(path).write_text(text)
