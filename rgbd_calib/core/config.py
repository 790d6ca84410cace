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


# ----------------------------------------------------------------------------- depth
class DepthConfig(BaseModel, extra="forbid"):
    """Settings of the depth stage (static clouds, depth-scale bias, overlap, ICP)."""

    # static clouds
    max_frames: int = Field(
        15,
        ge=1,
        description="Frames per camera in the temporal median, sampled evenly over "
        "the set; the stack is (max_frames, H, W) float32, so memory stays bounded.",
    )
    skipped_max_frames: int = Field(
        5,
        ge=1,
        description="Frames per camera for the static clouds when the board constrains "
        "every camera and no pair is registered: the clouds then serve only fused.ply and "
        "the report's cloud checks (their sigma_z counts the frames; docs/depth.md, 'Worth "
        "its time').",
    )
    board_mask_margin_m: float = Field(
        0.03,
        ge=0,
        description="The board's panel is grown by this margin (all sides and both "
        "faces) before it is projected into a frame and masked out.",
    )
    board_mask_dilate_px: float = Field(
        3.0, ge=0, description="Extra dilation of the projected board mask (px)."
    )
    motion_k: float = Field(
        3.0,
        gt=0,
        description="A pixel whose depth spread over frames (1.4826 MAD) exceeds "
        "motion_k single-frame sigma_z is moving and dropped.",
    )
    min_samples: int = Field(
        3,
        ge=1,
        description="Fewest valid depth samples for a pixel of the median (capped by "
        "the frames in which the board left it free, but at least 2 when 2 frames or more "
        "were read).",
    )
    min_valid_fraction: float = Field(
        0.5,
        ge=0,
        le=1,
        description="Fewest valid samples as a fraction of the frames in "
        "which the pixel was not covered by the board (intermittent depth is dropped).",
    )
    min_range_m: float = Field(0.3, gt=0, description="Nearest depth kept (m).")
    max_range_m: float = Field(4.0, gt=0, description="Farthest depth kept (m).")
    edge_jump_sigmas: float | None = Field(
        10.0,
        gt=0,
        description="Drop depth-edge pixels (flying pixels): a disparity (1/z) jump "
        "to a 4-neighbour above this many single-frame disparity sigmas s/(f B). None keeps "
        "them.",
    )
    subpixel_px: float = Field(
        0.08, gt=0, description="D435 subpixel disparity error s (px) of the noise model."
    )
    baseline_m: float = Field(0.050, gt=0, description="D435 stereo baseline B (m).")
    depth_focal_px: float | None = Field(
        None,
        gt=0,
        description="Focal length f (px) of the noise model; None: the colour fx "
        "(depth is aligned to colour).",
    )
    # depth-scale bias
    scale_face_margin_m: float = Field(
        0.02,
        ge=0,
        description="Board-face pixels closer than this to the panel's outline are "
        "not used for the depth scale (mixed edge pixels).",
    )
    scale_max_view_angle_deg: float = Field(
        70.0,
        gt=0,
        lt=90,
        description="Frames that see the board face more obliquely are "
        "skipped for the depth scale.",
    )
    scale_max_frames: int = Field(
        40,
        ge=1,
        description="Board views per camera read for the depth scale and the depth model, "
        "sampled evenly (each gives a factor to ~0.01 %; the depth model needs the board's "
        "whole range of distances, docs/depth.md).",
    )
    scale_min_points: int = Field(
        200, ge=10, description="Fewest board-face pixels for a frame to count."
    )
    scale_huber_k: float = Field(
        1.5, gt=0, description="Huber threshold (sigmas) of the per-pixel and per-frame fits."
    )
    board_depth_gate: float = Field(
        0.03,
        gt=0,
        description="Board-face pixels whose measured depth over the face's is off the view's "
        "median by more than this are not the board (a hand, a mixed edge pixel) and are not "
        "used; in views where the camera did not detect the board (model_unseen_views) the "
        "median itself must be within it of 1, so a hidden board gives none (a D435's depth "
        "errors stay within 1-2 %).",
    )
    model_unseen_views: bool = Field(
        True,
        description="The depth model also reads the board in views where the camera did not "
        "detect its markers (too far, too oblique in colour) but the board, placed by the "
        "cameras that did, lies in its depth image (on five renders: the worst camera's "
        "fused-cloud bias lower on all five, the mean on four; docs/depth.md, 'The ladder's "
        "first step, the board a camera did not detect, the depth beyond the board').",
    )
    model_unseen_max_frames: int = Field(
        40, ge=0, description="Such views per camera read for the depth model, sampled evenly."
    )
    model_plane_uncertainty: bool = Field(
        True,
        description="The depth model takes each view's board plane as uncertain as the pose "
        "it came from (a view the camera detected: its own PnP covariance; the board it did "
        "not detect: its extrinsics' covariance and the time model's at its capture), each "
        "plane's error a random effect of the view; false: every plane exact, as before "
        "(docs/depth.md, 'The board's planes as uncertain as their poses').",
    )
    model: Literal["auto", "none"] = Field(
        "auto",
        description="auto: each camera's depth model (scale, disparity-offset field, "
        "depth-to-colour pose; terms chosen by evidence from the board, depth_model.yaml) "
        "corrects its static cloud and fused.ply; none: no model is fitted and the clouds are "
        "divided by the depth-scale factor alone, as before the model (for comparison: "
        "docs/depth.md, 'Fused cloud against the true surfaces').",
    )
    model_terms: Literal["auto", "evidence", "all"] = Field(
        "auto",
        description="Which terms a camera whose depth needs a model gets (the ladder decides "
        "the need: a clean camera keeps the identity). evidence: the terms the ladder "
        "accepted; all: every term free; auto: every term where the camera's board views can "
        "judge all 13 parameters (at least 15 views), the ladder's terms otherwise. Over a "
        "board's depth range the terms trade with each other and one left out biases the "
        "rest, most beyond the board: on eight renders of 24-40 frame sets every term gave "
        "the lower worst-camera fused-cloud bias on seven (the eighth worse) and 99 % of the "
        "parameters within 3 sigma (91 % with the ladder's); with 8 frame sets its 13 "
        "parameters are so loosely held that the scene lies 20-100 mm off (RMS) against 1-3 mm "
        "with the ladder's terms "
        "(docs/depth.md, 'Every term where the views can judge them').",
    )
    # overlap
    overlap_voxel_m: float = Field(
        0.05, gt=0, description="Voxel size of the clouds used to measure overlap."
    )
    overlap_distance_m: float = Field(
        0.05,
        gt=0,
        description="A point overlaps the other camera's cloud if a point of it "
        "lies within this distance (allow for the extrinsics' current error).",
    )
    min_overlap: float = Field(
        0.05,
        ge=0,
        le=1,
        description="Smallest overlap fraction (min over both directions) "
        "for a pair to be registered.",
    )
    # registration
    voxel_schedule_m: list[float] = Field(
        [0.04, 0.02, 0.01],
        min_length=1,
        description="Coarse-to-fine voxel sizes of the multi-scale ICP (m), strictly decreasing.",
    )
    iterations: list[int] = Field(
        [50, 30, 14], min_length=1, description="ICP iterations per voxel level."
    )
    normal_voxel_m: float = Field(
        0.02,
        gt=0,
        description="Normals are estimated once per cloud on its voxel means of "
        "this size and given to every level's points by nearest neighbour.",
    )
    normal_radius_m: float = Field(
        0.08,
        gt=0,
        description="Radius of the normal estimation (m): large enough to average "
        "the depth noise of far surfaces (D435 sigma_z grows with z^2).",
    )
    max_correspondence_factor: float = Field(
        1.0,
        gt=0,
        description="Correspondence distance of each level in voxels of that level "
        "(1.0 as in Open3D's multi-scale colored ICP example; 1.5 and 2.5 were less accurate "
        "on the synthetic rigs).",
    )
    lambda_geometric: float = Field(
        0.968,
        gt=0,
        le=1,
        description="Weight of the geometric term in colored ICP (Park et "
        "al. 2017, the rest is the photometric term).",
    )
    icp_backend: Literal["legacy", "tensor"] = Field(
        "legacy",
        description="Open3D API for colored ICP: 'legacy' (o3d.pipelines) or "
        "'tensor' (o3d.t, level by level); same result within 0.001 deg / 0.05 mm on the "
        "synthetic pairs, legacy 10-20% faster here: the levels are built once in numpy, so "
        "the tensor API's speed-up does not show.",
    )
    kiss_kernel_factor: float = Field(
        0.33,
        gt=0,
        description="Geometric ICP (kiss-icp): robust kernel scale in voxels of the level.",
    )
    kiss_max_points_per_voxel: int = Field(
        20, ge=1, description="Geometric ICP: points kept per voxel of kiss-icp's map."
    )
    kiss_max_iterations: int = Field(
        100,
        ge=1,
        description="Geometric ICP: iterations per level (kiss-icp stops earlier when converged).",
    )
    icp_max_sigma_z_m: float = Field(
        0.015,
        gt=0,
        description="Registration uses only points whose depth sigma (of the "
        "median, the camera's depth noise model) is below this (m): unweighted ICP is spoiled "
        "by far, noisy points (sigma_z grows with z^2; at 640x360 and 8 frames 0.015 m is "
        "reached near 2.5 m).",
    )
    max_incidence_deg: float = Field(
        80.0,
        gt=0,
        le=90,
        description="Before ICP, points whose surface the other camera "
        "would see from behind or more obliquely than this are dropped (thin rails and posts "
        "seen from opposite sides are not common surfaces).",
    )
    crop_margin_px: float = Field(
        20.0,
        ge=0,
        description="Before ICP each cloud is cropped to the other camera's view "
        "under the initial guess, grown by this many pixels.",
    )
    eval_distance_m: float = Field(
        0.05,
        gt=0,
        description="Correspondence distance of the point-to-plane RMSE reported "
        "before and after registration.",
    )
    board_weak_sigma_mm: float = Field(
        0.2,
        ge=0,
        description="calibrate registers depth pairs only for cameras whose board marginal "
        "has a direction with a larger translation sigma (mm) than this (or rotation above "
        "board_weak_sigma_deg): a pair's own sigma is 0.3-4 mm (docs/depth.md), so it adds "
        "nothing to a camera the board already holds tighter. 0 registers every pair.",
    )
    board_weak_sigma_deg: float = Field(
        0.01, ge=0, description="Same, rotation (deg) of the worst direction."
    )
    information_patch_m: float = Field(
        0.1,
        gt=0,
        description="Size of the surface patches (m) whose residuals are taken to err "
        "together in a pair's information (the cluster-robust sandwich of docs/depth.md): "
        "about the normal-estimation radius, over which neighbouring residuals share errors.",
    )
    lens_sigma_factor: float = Field(
        2.0,
        ge=0,
        description="A depth pair back-projected with intrinsics the bundle adjustment refined "
        "carries their uncertainty (docs/depth.md, 'Refined intrinsics'): their marginal sigma "
        "times this factor. 2: the refined fx fy cx cy of ring rigs were 0.65-2.2 of their "
        "marginal sigma off the truth in RMS (3 sets); the marginals treat every corner as "
        "independent. 0 takes refined intrinsics as exact.",
    )
    min_patches: int = Field(
        20,
        ge=2,
        description="Reject a pair whose correspondences cover fewer patches: its uncertainty "
        "cannot be estimated from so few independent pieces of surface.",
    )
    max_normalised_rms: float = Field(
        3.0,
        gt=0,
        description="Reject a pair whose point-to-plane residuals after ICP are, in RMS, more "
        "than this many times their noise-model sigma (rig.yaml depth_noise; far above the "
        "noise: a wrong local minimum, a moving scene or a depth error).",
    )
    min_improvement_chi2: float = Field(
        12.59,
        ge=0,
        description="Use a pair only if its registration is statistically better than the "
        "current extrinsics: the move from them, weighed by the pair's information, must "
        "exceed this chi-square with 6 dof (12.59: 5 % false-alarm rate). 0 accepts pairs "
        "that confirm the current extrinsics too.",
    )
    variance_component_iterations: int = Field(
        20,
        ge=1,
        description="refine: solves of the joint graph (the priors holding each camera to its "
        "--init pose, the accepted pairs) with each group's covariance scaled by its variance "
        "factor estimated from its residuals over its redundancy (Helmert / Foerstner "
        "variance-component estimation; never below 1), until the factors settle. Colored "
        "ICP's pairs carry a systematic error their noise model does not admit (docs/depth.md, "
        "refine (issue 14): factor 3.6-4.4 on the synthetic race); this weighs them by what "
        "their disagreement shows. 1: one plain solve, the pairs at their model information. "
        "calibrate: the same for its joint solve of the board's corners and the pairs (the "
        "pairs' factor alone, from pair_variance_floor up).",
    )
    pair_variance_floor: float = Field(
        4.0,
        ge=1.0,
        description="calibrate: the least factor the accepted pairs' covariance is multiplied "
        "by in the joint solve with the board's corners (variance-component estimation raises "
        "it when the pairs disagree with the board or each other beyond it). The pairs are "
        "registered only where the board is weak, so the board cannot show their bias there; "
        "measured against the truth, accepted pairs claim ~2x too small a sigma (factor 4-5; "
        "docs/depth.md, 'The pairs' factor in calibrate'). 1: the pairs at their information.",
    )
    pair_bias_sigma_mm: float = Field(
        0.3,
        ge=0.0,
        description="calibrate: a bias of every accepted depth pair (1 sigma per axis, mm) "
        "added to its covariance, after pair_variance_floor, in the joint solve with the "
        "board's corners: colored ICP's error that does not shrink with the pair's points "
        "(accepted pairs on true depth: median error 0.5 mm, i.e. 0.3 mm per axis; "
        "docs/depth.md, 'A bias floor for the pairs'). It keeps a pair from pulling a camera the "
        "board holds to a few tenths of a mm. 0: none.",
    )
    pair_bias_sigma_deg: float = Field(
        0.007, ge=0.0, description="Same, rotation (deg per axis; median error 0.011 deg)."
    )
    overlap_models: bool = Field(
        True,
        description="calibrate updates each camera's board-fitted depth model by the "
        "overlapping pairs' median surface distances at the final extrinsics (a linear-"
        "Gaussian update with the board fit as the prior: rgbd_calib/depth/overlap_models.py): "
        "the overlaps reach the scene beyond the board's depths, where the board fit "
        "extrapolates (docs/depth.md, 'The overlaps on the depth models'). false: the board's "
        "models alone (before 2026-11-30).",
    )
    sensor_pose_sigma_deg: float = Field(
        0.1,
        ge=0.0,
        description="calibrate registers pairs on clouds not corrected for the depth "
        "sensor's pose relative to the colour camera, so an accepted pair carries that pose's "
        "error: its covariance gains it (rgbd_calib/depth/stage.py with_sensor_poses), as the "
        "camera's depth model estimates it with this as its prior (deg per axis: how well a "
        "factory depth-to-colour rotation is known; the every-term fit alone leaves it free on "
        "the few views of a weak camera). check and refine register clouds corrected by the "
        "calibration's depth models: their pairs gain what the models leave of the pose (its "
        "sigmas where a model freed the pose, this prior where not). 0 with "
        "sensor_pose_sigma_mm 0: the pairs take the depth sensors' poses as exact (before "
        "2026-11-30).",
    )
    sensor_pose_sigma_mm: float = Field(
        1.0, ge=0.0, description="Same, translation (mm per axis)."
    )
    max_board_chi2: float = Field(
        22.46,
        gt=0,
        description="calibrate rejects a pair whose ICP move from the board's extrinsics is "
        "beyond what the board's uncertainty of the two cameras' relative pose plus the pair's "
        "own allows (chi-square, 6 dof; 22.46: 0.1 %): a wrong local minimum (ring rigs: "
        "facing cameras' pairs moved 5-320 mm from a board result good to 1 mm).",
    )
    min_correspondences: int = Field(
        500, ge=6, description="Reject a pair with fewer correspondences at the finest level."
    )
    min_fitness: float = Field(
        0.3,
        ge=0,
        le=1,
        description="Reject a pair when fewer than this fraction of the "
        "cropped source points find a correspondence at the finest level.",
    )
    max_rmse_mm: float = Field(
        15.0,
        gt=0,
        description="Reject a pair whose point-to-plane RMSE after registration exceeds this (mm).",
    )
    min_conditioning: float = Field(
        0.02,
        ge=0,
        le=1,
        description="Reject a pair whose normalised information (Gelfand et "
        "al. 2003; point-to-plane, plus the photometric term for colored ICP) has smallest / "
        "largest eigenvalue below this: a direction the overlap does not constrain (a single "
        "plane without texture). Measured: 0.02-0.12 for good pairs, < 0.001 for planes.",
    )
    max_correction_m: float = Field(
        0.15,
        gt=0,
        description="Reject a registration that moved the pair by more than this "
        "from the initial guess (m): a wrong local minimum.",
    )
    max_correction_deg: float = Field(10.0, gt=0, description="Same, rotation (deg).")
    fused_voxel_m: float = Field(
        0.005, ge=0, description="Voxel size of the fused cloud (per camera; 0 keeps all)."
    )

    @model_validator(mode="after")
    def _check(self) -> DepthConfig:
        if self.min_range_m >= self.max_range_m:
            raise ValueError("min_range_m must be smaller than max_range_m")
        if len(self.voxel_schedule_m) != len(self.iterations):
            raise ValueError("voxel_schedule_m and iterations need one entry per level")
        if any(b >= a for a, b in zip(self.voxel_schedule_m, self.voxel_schedule_m[1:])):
            raise ValueError("voxel_schedule_m must be strictly decreasing")
        if any(v <= 0 for v in self.voxel_schedule_m) or any(i < 1 for i in self.iterations):
            raise ValueError("voxel sizes must be positive and iterations at least 1")
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
