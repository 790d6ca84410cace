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
from typing import Annotated, Any, ClassVar, Literal, get_args

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from .config_base import Grouped, Section
from .config_bundle import BundleConfig
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
class ArucoConfig(Section):
    """OpenCV's ArUco detector parameters: the adaptive threshold's windows and the corner
    subpixel search (``refinement: subpix``)."""

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

    @model_validator(mode="after")
    def _check(self) -> ArucoConfig:
        if self.adaptive_thresh_win_size_min > self.adaptive_thresh_win_size_max:
            raise ValueError("adaptive_thresh_win_size_min must not exceed the max")
        return self


class EdgesConfig(Section):
    """The edge refinement of marker corners (``refinement: edges``): which pixels of each
    outline edge are fitted, how, and which fits are kept."""

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

    @model_validator(mode="after")
    def _check(self) -> EdgesConfig:
        a, b = self.edge_span
        if not 0.0 <= a < b <= 1.0:
            raise ValueError("edge_span must satisfy 0 <= start < end <= 1")
        lo, hi = self.edge_band_px
        if not 0.0 < lo <= hi:
            raise ValueError("edge_band_px must be (min, max) with 0 < min <= max")
        return self


class DetectionConfig(Grouped):
    """ArUco detection and corner refinement (the detection stage of the pipeline)."""

    GROUPS: ClassVar[dict[str, type[Section]]] = {"aruco": ArucoConfig, "edges": EdgesConfig}

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
    aruco: ArucoConfig = Field(default_factory=ArucoConfig)
    edges: EdgesConfig = Field(default_factory=EdgesConfig)

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
