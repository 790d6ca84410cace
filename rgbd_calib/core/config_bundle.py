"""The bundle adjustment's settings (:class:`BundleConfig`): the solve's own and the models'
switches a user tunes (``intrinsics``, ``board``, ``time``), then one group per model block
for experts: the intrinsics' prior, the board's prior, the time model's priors and the corner
noise. A config file may give a grouped setting in its group
(``bundle: {board_prior: {board_prior_offset_mm: 1.0}}``) or, as before the groups, directly
under ``bundle:``. Imports pydantic only."""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal

from pydantic import Field, model_validator

from .camera import DISTORTION_NAMES
from .config_base import Grouped, Section

INTRINSICS_NAMES = ("fx", "fy", "cx", "cy", *DISTORTION_NAMES)


class IntrinsicsPriorConfig(Section):
    """The prior on refined intrinsics: how far from rig.yaml's each parameter may go (1
    sigma)."""

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


class BoardPriorConfig(Section):
    """The prior on the board's model: the back sheet's and the faces' poses against the
    board file's (1 sigma)."""

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


class TimeModelConfig(Section):
    """The time model's priors: the clock offsets', the board's twist per frame set, and the
    window that links consecutive sets."""

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


class CornerNoiseConfig(Section):
    """The noise of a marker's corners: its model, the centre-to-shape ratio, the scale the
    detector sees and the edge offset."""

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


GROUPS: dict[str, type[Section]] = {
    "intrinsics_prior": IntrinsicsPriorConfig,
    "board_prior": BoardPriorConfig,
    "time_model": TimeModelConfig,
    "corners": CornerNoiseConfig,
}


class BundleConfig(Grouped):
    """Joint bundle adjustment on marker corners (camera and board poses; intrinsics fixed, or
    refined under a prior at the rig.yaml values)."""

    GROUPS: ClassVar[dict[str, type[Section]]] = GROUPS

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
    held_out: bool = Field(
        False, description="also predict each view's corners from the other cameras' views "
        "of its frame set (the self-calibration ladder sets it on its trials: a richer model "
        "is kept only when it predicts them better)"
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
    intrinsics_prior: IntrinsicsPriorConfig = Field(default_factory=IntrinsicsPriorConfig)
    board_prior: BoardPriorConfig = Field(default_factory=BoardPriorConfig)
    time_model: TimeModelConfig = Field(default_factory=TimeModelConfig)
    corners: CornerNoiseConfig = Field(default_factory=CornerNoiseConfig)

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
