"""Video files (one per camera) -> the folder form, colour only.

Each camera's video is read with ``cv2.VideoCapture``. Frames are grouped into sets by an
optional timestamps CSV (``sync_index,cam_id,frame_index,frame_time``, as Caliscope writes:
frames of one ``sync_index`` form a set; a camera's rows sorted by ``frame_index`` are its
video's frames in order; ``cam_id`` is the trailing number of the video's name, e.g.
``cam_2.mp4``) or, without it, by position (frame k of every video is set k). With the CSV,
each written frame's ``frame_time`` (seconds, Caliscope's one recording clock) goes into
``<camera>/timestamps.csv`` in milliseconds; without it there is none (a video's own frame
times start at 0 in each file and share no clock).

With a board, only the frames where it was seen and still are kept: the board's markers are
detected in every frame and a camera's view is kept when its corners moved at most
``still_px_s`` pixels per second (the largest corner displacement to the camera's previous and
next frames, times the frame rate): a moving board smears the corners and, between cameras
that are not hardware-synchronised, is seen at different places. A set without a kept view
is dropped. Without a board every ``step``-th set is kept. rig.yaml gets only each camera's
size (its intrinsics are calibrated from scratch, docs/formats.md).
"""

from __future__ import annotations

import csv
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..core.errors import ConfigError, DatasetError
from ..core.progress import Progress, start
from ..detect.markers import detect_markers
from ..model.board import Board
from ..model.board_file import DATASET_BOARD_FILE, save_board
from ..model.dataset import FolderWriter, staged_folder
from ..model.rig import CAMERA_NAME, Rig, placeholder_intrinsics
from .conversion import CameraCounts, ConversionReport

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")
# measured on shared/data/caliscope-charuco-4cam (6 fps, hand-held board): the corners moved a
# median 50-70 px/s between frames (10-12 px per frame), never under 2 px per frame; 100 px/s
# keeps 65-78 % of the views with a board, and drops the fast sweeps (up to ~300 px/s)
STILL_PX_S = 100.0
TIMESTAMP_COLUMNS = ("sync_index", "cam_id", "frame_index", "frame_time")


def is_video(path: Path) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


@dataclass(frozen=True)
class VideoCamera:
    """One video as read: its name, size, frame rate and frames (frame position -> set)."""

    name: str
    path: Path
    width: int
    height: int
    fps: float
    frames: int
    set_of_frame: dict[int, int]  # video frame position -> sync index


def _trailing_number(path: Path) -> int | None:
    m = re.search(r"(\d+)$", path.stem)
    return int(m.group(1)) if m else None


def read_timestamps(path: Path) -> dict[int, list[tuple[int, int, float]]]:
    """``cam_id -> [(frame_index, sync_index, frame_time s), ...]`` sorted by frame_index."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read the timestamps CSV ({exc}); check the path") \
            from exc
    if not rows or any(c not in rows[0] for c in TIMESTAMP_COLUMNS):
        raise DatasetError(
            f"{path}: a timestamps CSV needs the columns {','.join(TIMESTAMP_COLUMNS)}; "
            "give Caliscope's timestamps.csv or leave --timestamps out"
        )
    out: dict[int, list[tuple[int, int, float]]] = {}
    try:
        for r in rows:
            out.setdefault(int(r["cam_id"]), []).append(
                (int(r["frame_index"]), int(r["sync_index"]), float(r["frame_time"])))
    except ValueError as exc:
        raise DatasetError(f"{path}: a row holds a value that is not a number ({exc}); fix it") \
            from exc
    return {c: sorted(v) for c, v in out.items()}


def open_video(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise DatasetError(f"{path}: OpenCV cannot open this video; convert it to MP4 (H.264)")
    return cap


def frames_of(path: Path):
    """Every frame (BGR) of a video, in order."""
    cap = open_video(path)
    try:
        while True:
            ok, image = cap.read()
            if not ok:
                return
            yield image
    finally:
        cap.release()


def probe(path: Path, name: str, timestamps: list[tuple[int, int, float]] | None) -> VideoCamera:
    """Size, frame rate and frame count of a video (counted by decoding: container counts
    lie), and its frames' sets."""
    cap = open_video(path)
    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    cap.release()
    n, size = 0, (0, 0)
    for image in frames_of(path):
        n, size = n + 1, (image.shape[1], image.shape[0])
    if n == 0:
        raise DatasetError(f"{path}: the video has no frame OpenCV can decode; check the file")
    if timestamps is None:
        sets = {k: k for k in range(n)}
    else:
        sets = {k: row[1] for k, row in enumerate(timestamps[:n])}
    return VideoCamera(name, Path(path), size[0], size[1], fps if fps > 0 else 30.0, n, sets)


def board_motion(corners: list[dict[int, np.ndarray]]) -> np.ndarray:
    """Per frame the largest corner displacement (px) to the previous and next frames over the
    markers both saw; inf without a neighbour that saw a common marker, nan without markers."""
    out = np.full(len(corners), np.nan)
    for f, here in enumerate(corners):
        if not here:
            continue
        moves = []
        for g in (f - 1, f + 1):
            if 0 <= g < len(corners):
                common = here.keys() & corners[g].keys()
                if common:
                    moves.append(max(float(np.abs(here[i] - corners[g][i]).max())
                                     for i in common))
        out[f] = max(moves) if moves else np.inf
    return out


def select_views(cams: list[VideoCamera], board: Board | None, step: int, still_px_s: float,
                 progress: Progress | None) -> tuple[dict[int, set[str]], list[str]]:
    """``sync index -> cameras`` to write, and notes on what was kept."""
    notes: list[str] = []
    if board is None:
        every = sorted({s for c in cams for s in c.set_of_frame.values()})[::step]
        return {s: {c.name for c in cams if s in c.set_of_frame.values()} for s in every}, [
            f"no --board: every {step}. frame set kept ({len(every)})"]
    keep: dict[int, set[str]] = {}
    for cam in cams:
        tick = start(progress, f"detecting the board in {cam.path.name}", cam.frames)
        corners = []
        for image in frames_of(cam.path):
            det = detect_markers(image, board)
            corners.append({int(i): c for i, c in zip(det.ids, det.corners_px)})
            tick(1)
        speed = board_motion(corners) * cam.fps
        seen = int(np.sum(~np.isnan(speed)))
        still = [k for k, v in enumerate(speed) if v <= still_px_s]
        for k in still:
            if k in cam.set_of_frame:
                keep.setdefault(cam.set_of_frame[k], set()).add(cam.name)
        notes.append(f"{cam.name}: board seen in {seen} of {cam.frames} frames, still "
                     f"(<= {still_px_s:g} px/s) in {len(still)}")
    return dict(sorted(keep.items())), notes


def convert_videos(
    videos: Sequence[Path],
    out: Path,
    names: Sequence[str] | None = None,
    timestamps: Path | None = None,
    board: Board | None = None,
    step: int = 1,
    still_px_s: float = STILL_PX_S,
    progress: Progress | None = None,
) -> ConversionReport:
    """Convert one video per camera into the folder form at ``out`` (colour only, rig.yaml
    with the sizes only); see the module docstring for the frame selection."""
    out = Path(out)
    videos = [Path(v) for v in videos]
    if step < 1 or not still_px_s > 0:
        raise ConfigError("--step must be >= 1 and --still-px-s positive")
    for v in videos:
        if not v.is_file():
            raise DatasetError(f"{v}: video not found; check the path")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DatasetError(
            f"{out}: output folder exists and is not empty; choose a new folder or delete it")
    cam_names = list(names) if names else [v.stem for v in videos]
    if len(cam_names) != len(videos) or len(set(cam_names)) != len(cam_names):
        raise ConfigError(f"--names: give {len(videos)} unique names, one per video in order")
    for n in cam_names:
        if not CAMERA_NAME.match(n):
            raise ConfigError(f"camera name {n!r} may only use letters, digits, '_' and '-'; "
                              "pass --names")
    table = read_timestamps(timestamps) if timestamps else None
    cams = []
    frame_time_s: dict[str, list[float]] = {}  # camera -> video frame position -> time (s)
    for i, (v, n) in enumerate(zip(videos, cam_names)):
        rows = None
        if table is not None:
            cam_id = _trailing_number(v)
            cam_id = cam_id if cam_id in table else i
            if cam_id not in table:
                raise DatasetError(f"{timestamps}: no row for {v.name} (cam_id {cam_id}); "
                                   "name the videos by cam_id (cam_0.mp4, ...)")
            rows = table[cam_id]
            frame_time_s[n] = [r[2] for r in rows]
        cams.append(probe(v, n, rows))
    keep, notes = select_views(cams, board, step, still_px_s, progress)
    for c in cams:
        if table is not None and c.frames != len(c.set_of_frame):
            notes.append(f"{c.name}: {c.frames} frames in the video, "
                         f"{len(c.set_of_frame)} with a timestamp row (the rest skipped)")
    rig = Rig({c.name: placeholder_intrinsics(c.width, c.height) for c in cams}, cams[0].name,
              unknown_intrinsics=frozenset(c.name for c in cams))
    written = dict.fromkeys(cam_names, 0)
    with staged_folder(out) as tmp:
        writer = FolderWriter(tmp, rig, depth_cameras=[])
        for cam in cams:
            tick = start(progress, f"writing {cam.name}", cam.frames)
            times_ms: dict[str, float] = {}
            for k, image in enumerate(frames_of(cam.path)):
                s = cam.set_of_frame.get(k)
                if s is not None and cam.name in keep.get(s, ()):
                    writer.write(cam.name, "color", f"{s:06d}", image)
                    written[cam.name] += 1
                    if cam.name in frame_time_s:  # the timestamps CSV's frame_time
                        times_ms[f"{s:06d}"] = 1000.0 * frame_time_s[cam.name][k]
                tick(1)
            if times_ms:
                writer.write_timestamps(cam.name, times_ms)
        if board is not None:  # calibrate reads it when --board is not given
            save_board(board, tmp / DATASET_BOARD_FILE)
    spread = _spread_ms(table, keep) if table else 0.0
    if table:
        notes.append(f"cameras of a kept set up to {spread:.1f} ms apart (timestamps CSV)")
    counts = {c.name: CameraCounts(c.frames, written[c.name], c.frames - written[c.name],
                                   len(keep) - written[c.name], written[c.name]) for c in cams}
    return ConversionReport(out, cam_names, cams[0].name, len(keep), spread, counts,
                            dict.fromkeys(cam_names, "none (calibrated from scratch)"),
                            dict.fromkeys(cam_names, "none"), notes)


def _spread_ms(table: dict[int, list[tuple[int, int, float]]], keep: dict[int, set[str]]) -> float:
    """Largest difference of frame times (ms) within a kept set."""
    times: dict[int, list[float]] = {}
    for rows in table.values():
        for _, s, t in rows:
            if s in keep:
                times.setdefault(s, []).append(t)
    return max((1000.0 * (max(v) - min(v)) for v in times.values()), default=0.0)
