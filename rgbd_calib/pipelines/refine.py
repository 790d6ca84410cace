"""The ``refine`` command: depth-only refinement of an existing calibration (no board in
view), and its verdict.

:func:`refine` is the library form of the command (``rgbd_calib.refine``);
:func:`refine_extrinsics` runs the depth stage (:func:`rgbd_calib.depth.stage.measure_depth`)
from the initial extrinsics and solves a pose graph of the accepted pairs with a prior per
camera at its initial pose
(:func:`~rgbd_calib.solve.variance_components.solve_variance_components`);
:func:`refine_verdict` / :func:`fix_verdict` say in one line what came of it,
:func:`refine_summary` writes it for report.json. The earlier calibration is read with
:mod:`rgbd_calib.model.calib_folder`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..core.config import DepthConfig, RegistrationMethod
from ..core.depth_model import DepthModel
from ..core.errors import CalibrationError
from ..core.geometry import invert_transform, transform_error
from ..depth.registration import DepthPair
from ..depth.stage import DepthRefinement, finish_pairs, measure_depth, moved_beyond_board
from ..model.board import Board, thesis_board
from ..model.board_file import load_board
from ..model.calib_folder import load_calibration, with_refined_intrinsics
from ..model.dataset import FolderDataset
from ..model.results import CameraExtrinsics, Extrinsics, cameras_from_solve
from ..solve.bundle_problem import RelativePose
from ..solve.variance_components import solve_variance_components
from ..sources.cache import open_dataset


@dataclass(frozen=True)
class RefineResult:
    """What :func:`refine` produced: the refined ``extrinsics`` (``init`` itself where no
    depth pair could be used), the depth stage's measurements, the ``outcome``
    (:func:`refine_verdict`: ``verdict`` refined / unchanged / check, ``message``, each
    camera's move from ``init``), and what it ran on (for the report:
    :func:`rgbd_calib.outputs.writer.write_refine`)."""

    extrinsics: Extrinsics
    init: Extrinsics
    depth: DepthRefinement
    outcome: dict[str, Any]
    dataset: FolderDataset
    method: str
    init_path: Path | None = None  # the extrinsics.yaml it started from, when read from one
    # the depth models or factors it was given (load_depth_corrections)
    depth_scales: dict[str, float | DepthModel] = field(default_factory=dict)


def refine(dataset: FolderDataset | str | os.PathLike, init: Extrinsics | str | os.PathLike,
           method: RegistrationMethod = "colored-icp", config: DepthConfig | None = None,
           board: Board | str | os.PathLike | None = None,
           depth_scales: dict[str, float | DepthModel] | None = None,
           workers: int | None = None, progress=None,
           scheduler: str | None = None) -> RefineResult:
    """Depth-only refinement of an existing calibration, as ``rgbd-calib refine`` does it.

    ``dataset``: a :class:`FolderDataset` or a dataset folder's path (with depth; no board
    needed). ``init``: :class:`Extrinsics`, or a calibrate output folder or its
    ``extrinsics.yaml``: then, as the command does, the dataset is read with the intrinsics
    of its ``rig_refined.yaml``, and the depth models of its ``depth_model.yaml`` (else the
    depth-scale factors of its ``report.json``; unless ``depth_scales`` is given) and the
    board poses of its ``report.json`` are used, the board being ``board`` or the
    thesis board. ``board`` may be a board file's path. See :func:`refine_extrinsics`."""
    dataset = open_dataset(dataset)
    init_path, T_ref_board, board_cameras = None, None, None
    if not isinstance(init, Extrinsics):
        earlier = load_calibration(init)
        init_path, T_ref_board, board_cameras = (earlier.path, earlier.T_ref_board,
                                                 earlier.board_cameras)
        dataset = dataset.with_rig(with_refined_intrinsics(dataset.rig, init_path.parent)[0])
        depth_scales = earlier.depth_scales if depth_scales is None else depth_scales
        init, board = earlier.extrinsics, thesis_board() if board is None else board
    if isinstance(board, (str, os.PathLike)):
        board = load_board(board)
    ext, depth = refine_extrinsics(dataset, init, method, config, progress, depth_scales,
                                   workers, board, T_ref_board, board_cameras, scheduler)
    return RefineResult(ext, init, depth, refine_verdict(init, ext, depth), dataset, method,
                        init_path, dict(depth_scales or {}))


def refine_extrinsics(dataset: FolderDataset, init: Extrinsics,
                      method: RegistrationMethod | Literal["none"] = "colored-icp",
                      config: DepthConfig | None = None,
                      progress=None,
                      depth_scales: dict[str, float | DepthModel] | None = None,
                      workers: int | None = None, board: Board | None = None,
                      T_ref_board: dict[str, np.ndarray] | None = None,
                      board_cameras: dict[str, list[str]] | None = None,
                      scheduler: str | None = None,
                      ) -> tuple[Extrinsics, DepthRefinement]:
    """Depth-only refinement of an existing calibration (no board in view): register the
    overlapping pairs from ``init`` and solve a pose graph of the accepted pairs, the
    reference held and every other camera held to its initial pose by a prior with its
    initial sigmas (when ``init`` has them): a good calibration is not pulled further than
    its own uncertainty allows by pairs 10-50x less certain. The priors and the pairs are two
    variance components, each weighed by its own variance factor (>= 1) estimated from its
    residuals (:func:`solve_variance_components`; ``depth.pair_variance_factor``). Cameras in
    no accepted pair keep their initial pose (and sigma).

    ``depth_scales`` (camera -> depth model or factor;
    :func:`rgbd_calib.model.calib_folder.load_depth_corrections`) are the depth corrections of
    the calibration ``init`` came from; a camera without one has an unknown depth scale and
    its pairs do not move it along the directions a scale error explains. With ``board``,
    ``T_ref_board`` (frame -> board pose of the starting calibration, e.g. its report.json
    ``board_views``) and ``board_cameras`` (frame -> cameras that saw it), the board is masked
    out of the clouds and cameras without a given factor get one estimated from the board
    face (as calibrate does). With no usable pair the result is ``init`` itself, with
    ``depth.fallback`` saying why."""
    if method == "none":
        raise CalibrationError("refine needs --method colored-icp or geometric")
    config = config or DepthConfig()
    T_init = {c: e.T_ref_cam for c, e in init.cameras.items() if c in dataset.rig.cameras}
    if init.reference not in T_init:
        raise CalibrationError(f"the reference camera {init.reference!r} of the initial "
                               "extrinsics is not in the dataset's rig.yaml")
    views = None
    if board is not None and T_ref_board and board_cameras:
        given = depth_scales or {}
        views = {}
        for frame, seen in board_cameras.items():
            for c in seen:
                if c in T_init and c not in given and frame in T_ref_board:
                    views.setdefault(c, {})[frame] = (invert_transform(T_init[c])
                                                      @ T_ref_board[frame])
    # the board poses come through the starting extrinsics: their covariance is each view's
    pose_covariance = {c: {f: init.cameras[c].covariance for f in frames}
                       for c, frames in (views or {}).items()
                       if init.cameras[c].covariance is not None}
    depth = measure_depth(dataset, board, T_init, views, T_ref_board, method, config,
                          progress, workers=workers, depth_scales=depth_scales,
                          scheduler=scheduler, pose_covariance=pose_covariance)
    if not depth.used:
        return init, finish_pairs(depth, T_init, config)
    priors = initial_pose_priors(init, T_init)
    try:
        res, factors = solve_variance_components(
            {c: dataset.rig.cameras[c].K for c in T_init}, init.reference, T_init,
            {"initial": priors, "pairs": depth.relative_poses},
            max_iterations=config.uncertainty.variance_component_iterations)
    except Exception as exc:  # noqa: BLE001 - the depth pairs must never end a run
        depth = depth.with_fallback(f"the pose graph of the depth pairs failed "
                                    f"({type(exc).__name__}: {exc})".replace("\n", " "))
        return init, finish_pairs(depth, T_init, config)
    solved = cameras_from_solve(res)
    cams = {c: solved.get(c, e) for c, e in init.cameras.items()}
    # never further from a calibration with sigmas than those sigmas allow
    beyond = moved_beyond_board({p.cam_a: CameraExtrinsics(p.cam_a, p.T_b_a, covariance=np.linalg
                                                           .inv(p.information))
                                 for p in priors}, cams)
    if beyond:
        depth = depth.with_fallback("; ".join(beyond.values()).replace("board", "initial"))
        return init, finish_pairs(depth, T_init, config)
    out = Extrinsics(init.reference, cams, dict(init.unconnected))
    depth = replace(depth, pair_variance_factor=factors["pairs"])
    return out, finish_pairs(depth, {c: e.T_ref_cam for c, e in cams.items()}, config)


def initial_pose_priors(init: Extrinsics, T_init: dict[str, np.ndarray]) -> list[RelativePose]:
    """One prior per non-reference camera of ``init`` with finite sigmas, as a relative pose
    from the camera to the reference (``T_ref_cam`` itself) with a diagonal information from
    its ``sigma_rotation_deg`` / ``sigma_translation_mm`` on each axis (those are roots of
    the 3-axis traces, so per axis this is up to sqrt(3) too wide: the prior never claims
    more than the calibration did)."""
    out = []
    for c, e in init.cameras.items():
        if c == init.reference or c not in T_init:
            continue
        s_rot, s_mm = e.sigma_rotation_deg, e.sigma_translation_mm
        if not (np.isfinite(s_rot) and np.isfinite(s_mm) and s_rot > 0 and s_mm > 0):
            continue
        var = np.r_[np.full(3, np.radians(s_rot) ** 2), np.full(3, (s_mm / 1000.0) ** 2)]
        out.append(RelativePose(c, init.reference, T_init[c], np.diag(1.0 / var)))
    return out


def camera_moves(init: Extrinsics, result: Extrinsics) -> dict[str, dict[str, float]]:
    """Per camera of both: its move from ``init`` to ``result`` (``moved_mm``, ``moved_deg``)
    and its ``initial_sigma_mm`` (NaN when ``init`` has none)."""
    moves = {}
    for c, e in result.cameras.items():
        if c in init.cameras:
            deg, mm = transform_error(e.T_ref_cam, init.cameras[c].T_ref_cam)
            moves[c] = {"moved_mm": mm, "moved_deg": deg,
                        "initial_sigma_mm": init.cameras[c].sigma_translation_mm}
    return moves


def fix_verdict(init: Extrinsics, fixed: Extrinsics, moved: list[str],
                pairs: list[DepthPair], unconfirmed: dict[str, str] | None = None,
                ) -> dict[str, Any]:
    """``refine --fix-others`` in one line: ``verdict`` ``unchanged`` (no camera moved),
    ``refined`` (the evidence confirms every fixed camera) or ``check`` (it does not confirm
    one: ``unconfirmed``, camera -> why, :class:`rgbd_calib.pipelines.check.FixResult`;
    without it, a moved camera in no accepted pair), the ``message``, per camera its move
    (:func:`camera_moves`) and ``unconfirmed``."""
    cameras = camera_moves(init, fixed)
    if not moved:
        return {"verdict": "unchanged", "message": "no camera moved beyond the tolerance: "
                "the extrinsics are --init's", "cameras": cameras, "unconfirmed": {}}
    if unconfirmed is None:
        unconfirmed = {c: "no pair fits after re-registration: its pose is the check's rough "
                       "estimate" for c in moved
                       if not any(c in (p.cam_a, p.cam_b) and p.accepted for p in pairs)}
    moves = [f"{c} {cameras[c]['moved_mm']:.1f} mm / {cameras[c]['moved_deg']:.2f} deg (now "
             f"sigma {fixed.cameras[c].sigma_translation_mm:.2f} mm / "
             f"{fixed.cameras[c].sigma_rotation_deg:.3f} deg)" for c in moved]
    return {"verdict": "check" if unconfirmed else "refined",
            "message": "re-registered " + "; ".join(moves)
            + "".join(f"; {c}: {why}" for c, why in unconfirmed.items()),
            "cameras": cameras, "unconfirmed": dict(unconfirmed)}


IN_MEMORY = "(extrinsics given in memory)"  # report.json refine.init of a library refine


def refine_summary(init_path: Path | None, method: str, verdict: dict[str, Any],
                   scale_source: dict[str, str], moved: list[str] | None = None,
                   ) -> dict[str, Any]:
    """report.json ``refine`` (docs/report_schema.md) of a depth-only run from its verdict
    (:func:`refine_verdict` or, with ``moved``, the ``--fix-others`` :func:`fix_verdict`) and
    each camera's depth-scale source (``board`` / ``given`` / ``unknown``; ``none``: the
    camera has no depth cloud)."""
    return {
        "init": str(Path(init_path).resolve()) if init_path is not None else IN_MEMORY,
        "registration": method,
        "fix_others": moved is not None,
        "outcome": verdict["verdict"],
        "message": verdict["message"],
        "moved_since_init": list(moved or []),
        "unconfirmed": dict(verdict.get("unconfirmed", {})),
        "pair_variance_factor": verdict.get("pair_variance_factor"),
        "cameras": {c: {**m, "depth_scale_source": scale_source.get(c, "none")}
                    for c, m in verdict["cameras"].items()},
    }


def refine_verdict(init: Extrinsics, result: Extrinsics, depth: DepthRefinement,
                   ) -> dict[str, Any]:
    """The refine run in one line plus its evidence: ``verdict`` ``refined`` (pairs used),
    ``unchanged`` (no usable pair: the result is the initial calibration) or ``check``
    (cameras moved by more than 3 of their initial sigmas, or depth scales unknown), the
    ``message``, and per camera its move from ``init`` (mm, deg)."""
    moves = camera_moves(init, result)
    unknown = sorted(c for c, src in depth.scale_source.items() if src == "unknown")
    far = sorted(c for c, m in moves.items()
                 if np.isfinite(m["initial_sigma_mm"]) and m["initial_sigma_mm"] > 0
                 and m["moved_mm"] > 3.0 * m["initial_sigma_mm"])
    n_used = sum(p.accepted for p in depth.pairs)
    f = depth.pair_variance_factor
    weighed = (f" (their covariance x{f:.2f}: variance factor from their residuals)"
               if f is not None and f > 1.0 else "")
    notes = []
    if unknown:
        notes.append(f"depth scale unknown for {', '.join(unknown)} (no report.json with "
                     "depth_scale_factor next to --init): their pairs were not allowed to move "
                     "them along the directions a depth-scale error explains")
    if depth.fallback:
        verdict = "unchanged"
        notes.insert(0, f"no usable pair ({depth.fallback}): the extrinsics are the initial "
                        "ones")
    elif far:
        verdict = "check"
        notes.insert(0, f"{n_used} pairs used{weighed}; {', '.join(far)} moved by more than "
                        "3 initial sigmas: the depth and the initial calibration disagree")
    else:
        verdict = "check" if unknown else "refined"
        notes.insert(0, f"{n_used} of {len(depth.pairs)} pairs used{weighed}")
    return {"verdict": verdict, "message": "; ".join(notes), "cameras": moves,
            "depth_scale_source": dict(depth.scale_source),
            "pair_variance_factor": depth.pair_variance_factor}
