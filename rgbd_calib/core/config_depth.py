"""The depth stage's settings (:class:`DepthConfig`), grouped by what they govern: the static
clouds, the depth model's fit to the board, the pairs' registration, their uncertainty and
their acceptance, under the three a user tunes (``model``, ``overlap_models``,
``fused_voxel_m``). A config file may give a grouped setting in its group
(``depth: {clouds: {max_frames: 8}}``) or, as before the groups, directly under ``depth:``
(:func:`~rgbd_calib.core.config_base.lift_flat`). Imports pydantic only."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, model_validator

from .config_base import Grouped, Section


class CloudsConfig(Section):
    """The static clouds: which depth pixels of which frames make each camera's temporal
    median cloud, and the D435 noise model that weighs them."""

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

    @model_validator(mode="after")
    def _check(self) -> CloudsConfig:
        if self.min_range_m >= self.max_range_m:
            raise ValueError("min_range_m must be smaller than max_range_m")
        return self


class ModelFitConfig(Section):
    """The depth model's fit to the board: which board pixels and views it reads, its robust
    loss and its terms."""

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


class RegistrationConfig(Section):
    """The overlapping pairs and their registration: overlap, the multi-scale ICP and its
    point selection."""

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

    @model_validator(mode="after")
    def _check(self) -> RegistrationConfig:
        if len(self.voxel_schedule_m) != len(self.iterations):
            raise ValueError("voxel_schedule_m and iterations need one entry per level")
        if any(b >= a for a, b in zip(self.voxel_schedule_m, self.voxel_schedule_m[1:])):
            raise ValueError("voxel_schedule_m must be strictly decreasing")
        if any(v <= 0 for v in self.voxel_schedule_m) or any(i < 1 for i in self.iterations):
            raise ValueError("voxel sizes must be positive and iterations at least 1")
        return self


class PairUncertaintyConfig(Section):
    """A registered pair's uncertainty and weight: where pairs are wanted, their
    information, and the factors, biases and poses added to it."""

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


class PairAcceptanceConfig(Section):
    """The gates a registered pair must pass to be used."""

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


#: DepthConfig's groups: name -> the section's model
GROUPS: dict[str, type[Section]] = {
    "clouds": CloudsConfig, "model_fit": ModelFitConfig, "registration": RegistrationConfig,
    "uncertainty": PairUncertaintyConfig, "acceptance": PairAcceptanceConfig,
}


class DepthConfig(Grouped):
    """Settings of the depth stage: the three a user tunes, then the groups (module
    docstring)."""

    GROUPS: ClassVar[dict[str, type[Section]]] = GROUPS

    model: Literal["auto", "none"] = Field(
        "auto",
        description="auto: each camera's depth model (scale, disparity-offset field, "
        "depth-to-colour pose; terms chosen by evidence from the board, depth_model.yaml) "
        "corrects its static cloud and fused.ply; none: no model is fitted and the clouds are "
        "divided by the depth-scale factor alone, as before the model (for comparison: "
        "docs/depth.md, 'Fused cloud against the true surfaces').",
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
    fused_voxel_m: float = Field(
        0.005, ge=0, description="Voxel size of the fused cloud (per camera; 0 keeps all)."
    )
    clouds: CloudsConfig = Field(default_factory=CloudsConfig)
    model_fit: ModelFitConfig = Field(default_factory=ModelFitConfig)
    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    uncertainty: PairUncertaintyConfig = Field(default_factory=PairUncertaintyConfig)
    acceptance: PairAcceptanceConfig = Field(default_factory=PairAcceptanceConfig)


