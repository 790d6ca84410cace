"""One entry for every source kind (``rgbd-calib convert``, ``rgbd_calib.convert``):
recordings go to :func:`.conversion.convert`, one video per camera to
:func:`.video.convert_videos`."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from ..core.depth_model import DepthModel
from ..core.errors import ConfigError
from ..core.progress import Progress
from ..model.board import Board
from ..model.board_file import DATASET_BOARD_FILE, load_board, save_board
from ..model.depth_model_file import load_depth_models
from .conversion import ConversionReport
from .conversion import convert as convert_recordings
from .video import STILL_PX_S, convert_videos, is_video


def convert(
    sources: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    names: Sequence[str] | None = None,
    sync_tolerance_ms: float | None = None,
    progress: Progress | None = None,
    *,
    timestamps: str | os.PathLike | None = None,
    board: Board | str | os.PathLike | None = None,
    step: int = 1,
    still_px_s: float | None = None,
    depth_models: dict[str, DepthModel] | str | os.PathLike | None = None,
) -> ConversionReport:
    """Convert recordings (RealSense ``.bag``/``.db3``, ROS bags), or one video per camera,
    into the folder form (docs/formats.md) at ``out``. Recordings take ``names`` and
    ``sync_tolerance_ms``; videos (all the sources, never mixed with recordings) take
    ``names``, ``timestamps`` (the CSV grouping frames into sets), ``board`` (a
    :class:`~rgbd_calib.model.board.Board` or a board file's path: keep the views where it is
    seen and still), ``step`` and ``still_px_s``, as the command's options. ``board`` with
    recordings or videos is written into the dataset as board.yaml. Recordings with
    ``depth_models`` (camera -> :class:`~rgbd_calib.core.depth_model.DepthModel`, or a
    ``depth_model.yaml`` / calibrate output folder) get those cameras' depth corrected."""
    sources = [Path(s) for s in sources]
    videos = [is_video(s) for s in sources]
    if isinstance(depth_models, (str, os.PathLike)):
        depth_models = load_depth_models(depth_models)
    if isinstance(board, (str, os.PathLike)):
        board = load_board(board)
    if not any(videos):
        report = convert_recordings(sources, out, names, sync_tolerance_ms, progress,
                                    depth_models)
        if board is not None:  # the dataset's own board: calibrate reads it without --board
            save_board(board, Path(out) / DATASET_BOARD_FILE)
        return report
    if not all(videos):
        raise ConfigError("convert: give either video files or recordings, not both")
    if depth_models:
        raise ConfigError("convert: --depth-model corrects depth; videos have none")
    return convert_videos(sources, Path(out), names, Path(timestamps) if timestamps else None,
                          board, step, still_px_s or STILL_PX_S, progress)
