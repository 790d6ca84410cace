"""Self-calibration by model selection: how much of the physical model the data can free.

A real rig differs from its files in a few known ways: the back sheet of the board glued off
its place, factory intrinsics a fraction of a percent off, lens distortion that rig.yaml does
not list. The bundle adjustment can estimate each (``bundle.board: refine``,
``bundle.intrinsics: refine``), but freeing parameters the data does not need costs accuracy:
on a clean rig, refining the focal lengths trades them against the camera distances (about 4x
the extrinsic error of the fixed model on a short set). ``auto`` therefore climbs a ladder of
models, each the last accepted one plus one group of parameters:

1. the nominal model (board file and rig.yaml as given, every camera exposing at the frame
   set's instant);
2. + time (per camera a clock offset and a rolling-shutter readout, per frame set the board's
   twist: :mod:`rgbd_calib.solve.time_model`), first, only when it fits better than every
   other first step (the back sheet, the lens alternatives below): a board or lens model must
   not absorb a timing error, nor the time model (whose per-set twists can mimic a little of
   anything) a misglued sheet or a wrong focal length. Tried only when the pose graph found
   views that disagree beyond their noise (a still board or synchronised cameras never pay
   for it); when it loses, it is tried again last, on top of the rest;
3. + the back sheet's pose (4 parameters for the rig; only for a double-sided board);
4. + focal lengths and principal points (``fx fy cx cy`` of ``bundle.intrinsics_params``,
   per camera), or those and the lens distortion coefficients of
   ``bundle.intrinsics_params``: two alternatives, tried only when the pose graph found a
   camera-level model error; the better one by BIC is kept.

A model is accepted when it calibrates more cameras, or the same cameras with a better fit by
the Bayesian information criterion on the markers both models kept::

    n ln(SSR_before / SSR_after) > k ln(n)

``n`` scalar residuals (8 per marker), ``k`` added parameters, ``SSR`` the sum of squared
corner residuals with each marker's RMS capped at ``bundle.outlier_px`` (a marker one model
loses does not decide). On a correct model the freed parameters lower SSR by about ``k``
sigma^2, far below ``k ln(n)`` (ln n ~ 9-12 here), so a clean rig keeps the nominal model and
its result unchanged; a misglued sheet or a 0.5 % focal error lowers it by orders of magnitude
more. A model on the same cameras must also predict data it was not fitted to better
(:func:`held_out`): each view's corners from the other cameras' views of its frame set; a
model whose extra freedom only took up misfit (per-set twists that two global shutters fit
exactly) passes the BIC and fails this. Pure maths on bundle results; the solves are run by
:mod:`rgbd_calib.solve.ladder`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..core.camera import PINHOLE_NAMES
from ..core.config import BundleConfig
from .blocks import OFF, BoardBlock, IntrinsicsBlock, ModelBlock, TimeBlock

FOCAL_CENTRE = PINHOLE_NAMES
PRIOR_TENSION = 3.0  # a refined parameter this many prior sigmas from rig.yaml: prior wrong
LOOSEN = 10.0  # ... and its priors are then widened this many times


@dataclass(frozen=True)
class ModelLevel:
    """One model of the ladder: whether the back sheet is refined and which intrinsics
    parameters (empty: the rig.yaml intrinsics are held)."""

    name: str
    board: bool
    intrinsics_params: tuple[str, ...] = ()
    time: bool = False

    @property
    def blocks(self) -> tuple[ModelBlock, ...]:
        """The model blocks this level frees (:mod:`rgbd_calib.solve.blocks`), in the order
        of its name."""
        return ((TimeBlock(),) if self.time else ()) + ((BoardBlock(),) if self.board else ()) \
            + ((IntrinsicsBlock(self.intrinsics_params),) if self.intrinsics_params else ())

    def bundle_config(self, base: BundleConfig) -> BundleConfig:
        """``base`` with this level's blocks on and the others off (explicit modes, never
        ``auto``)."""
        update: dict[str, Any] = dict(OFF)
        for block in self.blocks:
            update |= block.config_update()
        return base.model_copy(update=update)

    @property
    def distortion(self) -> bool:
        """Whether this level refines lens distortion (detection then bends the edge fit)."""
        return any(p not in FOCAL_CENTRE for p in self.intrinsics_params)


@dataclass(frozen=True)
class HeldOut:
    """Two models' corners predicted from the other cameras' views of their frame sets
    (``BundleResult.held_out_px``), on the markers both predicted: RMS (px, each marker's
    capped at ``bundle.outlier_px``) of the simpler model and of the richer one."""

    rms_before_px: float
    rms_after_px: float
    markers: int
    views: int

    @property
    def better(self) -> bool:
        return self.rms_after_px < self.rms_before_px

    def to_dict(self) -> dict[str, Any]:
        return {"rms_before_px": self.rms_before_px, "rms_after_px": self.rms_after_px,
                "markers": self.markers, "views": self.views}

    def phrase(self) -> str:
        return (f"held-out corners {self.rms_before_px:.3f} -> {self.rms_after_px:.3f} px on "
                f"{self.views} views")


def held_out(before: dict[tuple[str, str, int], float],
             after: dict[tuple[str, str, int], float], cap_px: float) -> HeldOut | None:
    """:class:`HeldOut` of two models' predicted marker RMS (``(camera, view, marker) ->
    px``) on their common markers; None when they share none."""
    common = before.keys() & after.keys()
    if not common:
        return None

    def rms(d: dict[tuple[str, str, int], float]) -> float:
        return math.sqrt(sum(min(d[k], cap_px) ** 2 for k in common) / len(common))

    return HeldOut(rms(before), rms(after), len(common), len({k[:2] for k in common}))


@dataclass(frozen=True)
class LevelFit:
    """How one level of the ladder fitted, against the level it was compared with."""

    level: ModelLevel
    cameras: int
    markers: int
    rms_px: float
    added_parameters: int = 0
    bic_gain: float | None = None  # n ln(SSR_before/SSR_after) - k ln(n); > 0 accepts
    accepted: bool = True
    reason: str = ""
    held_out: HeldOut | None = None  # against the level it was compared with

    def to_dict(self) -> dict[str, Any]:
        return {
            "level": self.level.name,
            "board": self.level.board,
            "time": self.level.time,
            "intrinsics_params": list(self.level.intrinsics_params),
            "cameras": self.cameras,
            "markers": self.markers,
            "rms_px": self.rms_px,
            "added_parameters": self.added_parameters,
            "bic_gain": self.bic_gain,
            "accepted": self.accepted,
            "reason": self.reason,
            "held_out": None if self.held_out is None else self.held_out.to_dict(),
        }


@dataclass(frozen=True)
class SelfCalibration:
    """The ladder as run: every level tried, the one chosen, and whether the corners were
    detected again with the refined lens model."""

    chosen: ModelLevel
    fits: list[LevelFit] = field(default_factory=list)
    redetected: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {
            "chosen": self.chosen.name,
            "board": self.chosen.board,
            "time": self.chosen.time,
            "intrinsics_params": list(self.chosen.intrinsics_params),
            "redetected": self.redetected,
            "levels": [f.to_dict() for f in self.fits],
        }


def is_auto(config: BundleConfig) -> bool:
    return "auto" in (config.board, config.intrinsics, config.time)


def base_level(config: BundleConfig) -> ModelLevel:
    """The model every level includes: what the config sets explicitly to ``refine``."""
    board, time = config.board == "refine", config.time == "refine"
    params = tuple(config.intrinsics_params) if config.intrinsics == "refine" else ()
    return ModelLevel(_name(board, params, time), board, params, time)


Step = tuple[bool, tuple[str, ...], bool]  # (board, intrinsics parameters, time) a level adds


TIME_STEP: Step = (False, (), True)


def candidate_groups(config: BundleConfig, double_sided: bool,
                     model_error: bool) -> list[list[Step]]:
    """What ``auto`` may add after the time challenge (:func:`time_challengers`), as groups of
    alternatives ``(board, intrinsics parameters, time)`` tried on the model accepted so far;
    the best of a group by BIC is kept. First the back sheet (board ``auto``, double-sided
    board); then, when the intrinsics are ``auto`` and the pose graph found a camera-level
    model error, fx fy cx cy, or those and the distortion coefficients of
    ``bundle.intrinsics_params`` (alternatives, not a chain: a lens error makes the focal step
    alone fit worse, not better); last time (``time: auto`` with a model error), on top of
    what was accepted (skipped when the time challenge already took it)."""
    groups: list[list[Step]] = []
    if config.board == "auto" and double_sided:
        groups.append([(True, (), False)])
    if config.intrinsics == "auto" and model_error:
        focal = tuple(p for p in config.intrinsics_params if p in FOCAL_CENTRE)
        every = tuple(config.intrinsics_params)
        groups.append([(False, g, False) for g in dict.fromkeys((focal, every)) if g])
    if config.time == "auto" and model_error:
        groups.append([TIME_STEP])
    return groups


def time_challengers(groups: list[list[Step]]) -> list[Step]:
    """The first steps time must beat to be taken before the others (every step of
    :func:`candidate_groups` but time itself); empty when time is not a candidate."""
    if [TIME_STEP] not in groups:
        return []
    return [step for g in groups for step in g if step != TIME_STEP]


def better(a: LevelFit, b: LevelFit) -> bool:
    """Whether ``a`` beats ``b`` (both accepted over the same base): more cameras, else the
    larger BIC gain (a gain of None, decided by cameras, ranks by corner RMS)."""
    if a.cameras != b.cameras:
        return a.cameras > b.cameras
    if a.bic_gain is not None and b.bic_gain is not None:
        return a.bic_gain > b.bic_gain
    return a.rms_px < b.rms_px


def extend(level: ModelLevel, step: Step) -> ModelLevel:
    board, time = level.board or step[0], level.time or step[2]
    params = level.intrinsics_params + tuple(
        p for p in step[1] if p not in level.intrinsics_params)
    return ModelLevel(_name(board, params, time), board, params, time)


def _name(board: bool, params: tuple[str, ...], time: bool = False) -> str:
    parts = (["time"] if time else []) + (["board"] if board else []) + (
        [" ".join(params)] if params else [])
    return " + ".join(parts) if parts else "nominal"


def prior_tension(bundle: Any, rig: Any) -> tuple[float, str, str] | None:
    """The refined intrinsics parameter furthest from its rig.yaml value in prior sigmas:
    ``(z, camera, parameter)``; None when no intrinsics were refined."""
    worst = None
    for cam, refined in bundle.intrinsics.items():
        prior_sigma = bundle.intrinsics_prior_sigma.get(cam, {})
        before, after = rig.cameras[cam].parameters, refined.parameters
        for name, sigma in prior_sigma.items():
            if sigma and sigma > 0:
                z = abs(after.get(name, 0.0) - before.get(name, 0.0)) / sigma
                if worst is None or z > worst[0]:
                    worst = (z, cam, name)
    return worst


def loosened(config: BundleConfig) -> BundleConfig:
    """``config`` with every intrinsics prior sigma :data:`LOOSEN` times wider."""
    prior = config.intrinsics_prior
    return config.model_copy(update={"intrinsics_prior": prior.model_copy(update={
        "intrinsics_prior_focal_pct": prior.intrinsics_prior_focal_pct * LOOSEN,
        "intrinsics_prior_center_px": prior.intrinsics_prior_center_px * LOOSEN,
        "intrinsics_prior_distortion": prior.intrinsics_prior_distortion * LOOSEN,
        "intrinsics_prior_tangential": prior.intrinsics_prior_tangential * LOOSEN,
    })})


def marker_terms(residuals: list[tuple[str, str, int, float]],
                 outliers: list[tuple[str, str, int, float]],
                 cap_px: float) -> dict[tuple[str, str, int], float]:
    """Per marker ``(camera, view, id)``: its squared corner residuals summed over 4 corners x
    2 axes (``8 rms^2``), the RMS capped at ``cap_px``; outlier markers count at the cap."""
    out = {(c, v, m): 8.0 * min(r, cap_px) ** 2 for c, v, m, r in residuals}
    out |= {(c, v, m): 8.0 * cap_px**2 for c, v, m, _ in outliers}
    return out


def compare(before: dict[tuple[str, str, int], float], cameras_before: int,
            after: dict[tuple[str, str, int], float], cameras_after: int,
            added_parameters: int) -> tuple[bool, float | None, str]:
    """Whether the richer model (``after``) is accepted over ``before``: more cameras wins,
    fewer loses, else the BIC on the common markers. Returns (accepted, BIC gain, reason)."""
    if cameras_after > cameras_before:
        return True, None, f"calibrates {cameras_after} cameras instead of {cameras_before}"
    if cameras_after < cameras_before:
        return False, None, f"calibrates {cameras_after} cameras instead of {cameras_before}"
    common = before.keys() & after.keys()
    if not common:
        return False, None, "no marker in common with the simpler model"
    ssr0 = sum(before[k] for k in common)
    ssr1 = sum(after[k] for k in common)
    n = 8 * len(common)
    if ssr1 <= 0.0 or ssr0 <= 0.0:
        return False, None, "degenerate residuals"
    gain = n * math.log(ssr0 / ssr1) - added_parameters * math.log(n)
    rms0, rms1 = math.sqrt(ssr0 / n), math.sqrt(ssr1 / n)
    verdict = "fits better than the parameters cost" if gain > 0 else (
        "does not fit better by more than the parameters cost")
    return gain > 0, gain, (f"{verdict} (corner RMS {rms0:.3f} -> {rms1:.3f} px on "
                            f"{len(common)} common markers, BIC gain {gain:.0f})")


def rms_px(terms: dict[tuple[str, str, int], float]) -> float:
    return math.sqrt(sum(terms.values()) / (8 * len(terms))) if terms else float("nan")
