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

Pure numpy rendering; cv2 only filters images. Written by
:class:`~rgbd_calib.model.dataset.FolderWriter`.

This module writes a dataset folder (:func:`synthesize`, :func:`synthesize_cached`) and
re-exports the parts: :mod:`.params` (the settings, the rig's types), :mod:`.layouts` (the
named rigs), :mod:`.imperfections` (lens, listed intrinsics, knocks, the printed board),
:mod:`.motion` (board poses), :mod:`.timing` (the board's motion during a frame set, the
cameras' clock offsets and rolling shutters), :mod:`.images` (one camera's colour and depth)
and :mod:`.ground_truth` (``ground_truth.yaml``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from ..core.errors import ConfigError
from ..core.geometry import invert_transform, pose_after_twist
from ..core.parallel import executor
from ..core.progress import Progress, start
from ..model.board import Board
from ..model.board_file import DATASET_BOARD_FILE, save_board
from ..model.dataset import FolderWriter, staged_folder
from ..model.rig import Rig
from .ground_truth import GroundTruth, load_ground_truth, write_ground_truth
from .images import (
    INK_BLACK,
    LIGHT_DIR_WORLD,
    PAPER_WHITE,
    _BoardModel,
    _grid,
    camera_rays,
    finish_color,
    finish_depth,
    render_background,
    render_board,
    render_board_moving,
)
from .imperfections import BoardPrint, board_print, bump_transform, face_perturbation
from .layouts import LAYOUTS, make_rig
from .motion import (
    CLOSEUP_STREAM,
    CLOSEUP_TARGETS,
    closeup_poses,
    marker_visibility,
    sample_board_poses,
)
from .params import SynthCamera, SynthParams, SynthRig, check_params
from .timing import SynthTiming, draw_timestamps_ms, draw_timing

__all__ = [
    "CLOSEUP_TARGETS",
    "INK_BLACK",
    "LAYOUTS",
    "LIGHT_DIR_WORLD",
    "PAPER_WHITE",
    "RENDER_KEY",
    "BoardPrint",
    "GroundTruth",
    "SynthCamera",
    "SynthDataset",
    "SynthParams",
    "SynthRig",
    "_BoardModel",
    "_grid",
    "board_print",
    "bump_transform",
    "camera_rays",
    "check_params",
    "closeup_poses",
    "face_perturbation",
    "finish_color",
    "finish_depth",
    "load_ground_truth",
    "make_rig",
    "marker_visibility",
    "render_background",
    "render_board",
    "render_board_moving",
    "render_key",
    "sample_board_poses",
    "synthesize",
    "synthesize_cached",
]


_WORKER: dict = {}


def _init_worker(state: dict) -> None:
    cv2.setNumThreads(1)  # one process per core already
    _WORKER.update(state)
    _WORKER["model"] = _BoardModel(state["board"], state["printed"])


def _render_frame(job: tuple[int, np.ndarray]) -> list[int]:
    """Render and write frame set ``job = (index, T_world_board)``; returns the indices (rig
    order) of the cameras that have it (the others dropped it: ``drop_rate``)."""
    index, T_world_board = job
    rig: SynthRig = _WORKER["rig"]
    params: SynthParams = _WORKER["params"]
    writer: FolderWriter = _WORKER["writer"]
    timing: SynthTiming | None = _WORKER["timing"]
    frame = f"{index:06d}"
    written = []
    for ci, cam in enumerate(rig.cameras):
        rng = np.random.default_rng([_WORKER["seed"], index, ci])
        if params.drop_rate > 0 and rng.random() < params.drop_rate:
            continue
        T_cam_world = invert_transform(cam.T_world_cam)
        T_cam_board = T_cam_world @ T_world_board
        if timing is None or not timing.moving(index):  # a still board: one pose for all
            color, depth = render_board(_WORKER["model"], cam, _WORKER["backgrounds"][ci],
                                        T_cam_board, params.supersample)
        else:
            color, depth = render_board_moving(
                _WORKER["model"], cam, _WORKER["backgrounds"][ci],
                _pose_at(rig, timing, index, T_cam_world, T_world_board),
                timing.offset_s[ci], timing.readout_s[ci], params.supersample)
        writer.write(cam.name, "color", frame, finish_color(color, params, rng))
        writer.write(cam.name, "depth", frame, finish_depth(depth, cam, params, rng))
        written.append(ci)
    return written


def _write_timestamps(writer: FolderWriter, rig: SynthRig, written: list[list[int]],
                      stamps_ms: np.ndarray) -> None:
    """Each camera's ``timestamps.csv``: a row per frame set it has (``written``), its time
    from ``stamps_ms`` (``(F, C)``, :func:`.timing.draw_timestamps_ms`). Written once the
    images are, inside the staged folder, so the render is published with them or not at
    all."""
    for ci, cam in enumerate(rig.cameras):
        times = {f"{f:06d}": float(stamps_ms[f, ci]) for f, cams in enumerate(written)
                 if ci in cams}
        if times:
            writer.write_timestamps(cam.name, times)


def _pose_at(rig: SynthRig, timing: SynthTiming, index: int, T_cam_world: np.ndarray,
             T_world_board: np.ndarray):
    """``tau -> T_cam_board`` of frame set ``index``: the reference-frame convention of
    :mod:`.timing`, ``T_ref_board(t_f + tau)``, seen from the camera."""
    T_world_ref = rig.cameras[rig.reference_index].T_world_cam
    T_ref_board = invert_transform(T_world_ref) @ T_world_board
    T_cam_ref = T_cam_world @ T_world_ref
    v, w = timing.v_mps[index], timing.w_radps[index]
    a, alpha = timing.a_mps2[index], timing.alpha_radps2[index]
    return lambda tau_s: T_cam_ref @ pose_after_twist(T_ref_board, v, w, tau_s, a, alpha)


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
    :func:`board_print`. A timed render (``params.timed``) also writes each camera's
    ``timestamps.csv`` (:func:`.timing.draw_timestamps_ms`)."""
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
    timing = draw_timing(rig, len(poses), seed, params) if params.timed else None
    if timing is not None and timing.burst > 1:  # each position -> its burst's frame sets
        T_world_ref = rig.cameras[rig.reference_index].T_world_cam
        T_ref_world = invert_transform(T_world_ref)
        poses = [T_world_ref @ timing.T_ref_board(f, T_ref_world @ poses[f // timing.burst])
                 for f in range(len(poses) * timing.burst)]
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
            "timing": timing,
        }
        jobs = list(enumerate(poses))
        tick = start(progress, "rendering frame sets", len(jobs))
        written: list[list[int]] = []  # per frame set: the cameras that have it
        if workers <= 1:
            _init_worker(state)
            for job in jobs:
                written.append(_render_frame(job))
                tick(1)
        else:
            with executor(workers, initializer=_init_worker, initargs=(state,)) as ex:
                for cams in ex.map(_render_frame, jobs, chunksize=1):
                    written.append(cams)
                    tick(1)
        if timing is not None:
            _write_timestamps(writer, rig, written, draw_timestamps_ms(timing, seed, params))
        write_ground_truth(tmp / "ground_truth.yaml", rig, poses, layout, seed, board, printed,
                           params, closeups, n_frames, timing)
        # the nominal board file, as a user has it; printed at its size, it says so (0: exact)
        save_board(replace(board, print_scale_sigma=0.0) if params.print_scale == 1.0
                   and board.print_scale_sigma is None else board, tmp / DATASET_BOARD_FILE)
    return SynthDataset(out, rig, poses)


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
