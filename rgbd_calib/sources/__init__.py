"""Recordings as sources of a calibration set, converted into the folder form of docs/formats.md.

- RealSense SDK recordings, one file per camera: ``.bag`` (rosbag v1, SDK before 2.56) and
  ``.db3`` (SDK 2.56+), read by :mod:`.realsense`.
- realsense-ros bags: ROS 1 ``.bag``, ROS 2 folders (sqlite3 or mcap) or their bare
  ``.db3``/``.mcap`` files, read by :mod:`.ros`.
- Video files, one per camera (colour only, intrinsics unknown), with an optional timestamps
  CSV: :func:`convert_videos` (:mod:`.video`) keeps the frames where the board is still.

Readers stage decoded frames (:mod:`.staging`); :mod:`.sync` pairs colour with depth and
matches cameras by timestamp; :mod:`.conversion` writes the frame sets; :func:`convert`
(:mod:`.dispatch`) takes recordings or videos;
:mod:`.cache` converts once for ``calibrate RECORDINGS...``.
"""

from .align import align_depth_to_color, distortion_from_realsense, extrinsics_matrix
from .cache import CACHE_MARKER, cached_report, convert_to_cache, dataset_folder
from .conversion import RECORDING_SUFFIXES, CameraCounts, ConversionReport, is_recording
from .dispatch import convert
from .sync import match_frames
from .video import VIDEO_SUFFIXES, convert_videos, is_video

__all__ = [
    "CACHE_MARKER",
    "RECORDING_SUFFIXES",
    "VIDEO_SUFFIXES",
    "CameraCounts",
    "ConversionReport",
    "align_depth_to_color",
    "cached_report",
    "convert",
    "convert_to_cache",
    "convert_videos",
    "dataset_folder",
    "distortion_from_realsense",
    "extrinsics_matrix",
    "is_recording",
    "is_video",
    "match_frames",
]
