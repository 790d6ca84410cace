"""Recordings -> the folder form: which reader a source needs, and :func:`convert` itself.

Every colour frame is decoded once and staged on disk; when all sources are read, colour is
paired with the nearest depth frame of the same camera, cameras are matched by timestamp, and
the staged files are renamed into ``<camera>/{color,depth}/<frame>.png``, each camera's colour
frame times into ``<camera>/timestamps.csv`` (:func:`shared_clock`: when the cameras' times
share a clock). Everything happens in a temporary sibling folder that is renamed into place
at the end.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.depth_model import DepthModel, correct_depth_image
from ..core.errors import ConfigError, DatasetError
from ..core.progress import Progress, start
from ..model.dataset import FolderWriter, staged_folder
from ..model.rig import CAMERA_NAME, Rig
from .align import align_depth_to_color
from .realsense import read_sdk
from .ros import read_ros
from .staging import StagedCamera, Stager
from .sync import clock_notes, match_cameras, pair_depth, shared_clock

RECORDING_SUFFIXES = (".bag", ".db3", ".mcap")


@dataclass(frozen=True)
class CameraCounts:
    """What happened to one camera's colour frames."""

    frames_read: int  # colour frames in the source
    matched: int  # written into a synchronised set
    unmatched: int  # no other camera within the sync tolerance: not written
    dropped: int  # sets written without this camera
    without_depth: int  # written, but no depth frame within one frame period

    def to_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class ConversionReport:
    out: Path
    cameras: list[str]
    sync_reference: str  # the camera whose timeline the sets follow
    frames_written: int  # synchronised sets (frame stems)
    sync_tolerance_ms: float
    counts: dict[str, CameraCounts]
    intrinsics_source: dict[str, str]
    depth_source: dict[str, str]
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "out": str(self.out),
            "cameras": list(self.cameras),
            "sync_reference": self.sync_reference,
            "frames_written": self.frames_written,
            "sync_tolerance_ms": self.sync_tolerance_ms,
            "counts": {c: n.to_dict() for c, n in self.counts.items()},
            "intrinsics_source": dict(self.intrinsics_source),
            "depth_source": dict(self.depth_source),
            "notes": list(self.notes),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ConversionReport:
        return cls(
            out=Path(d["out"]),
            cameras=list(d["cameras"]),
            sync_reference=d["sync_reference"],
            frames_written=int(d["frames_written"]),
            sync_tolerance_ms=float(d["sync_tolerance_ms"]),
            counts={c: CameraCounts(**n) for c, n in d["counts"].items()},
            intrinsics_source=dict(d["intrinsics_source"]),
            depth_source=dict(d["depth_source"]),
            notes=list(d.get("notes", [])),
        )


def is_recording(path: Path) -> bool:
    """True for what :func:`convert` reads (a bag file or a ROS 2 bag folder)."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in RECORDING_SUFFIXES


def _topics(path: Path) -> list[str]:
    """Topic names of a bag (rosbags when installed; sqlite3 for bare .db3 files)."""
    if path.is_file() and path.suffix.lower() == ".db3":
        try:
            con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
            try:
                return [r[0] for r in con.execute("SELECT name FROM topics")]
            finally:
                con.close()
        except sqlite3.DatabaseError as exc:
            raise DatasetError(
                f"{path}: not a rosbag2/RealSense .db3 file ({exc}); check the file"
            ) from None
    try:
        from rosbags.rosbag1 import Reader as Reader1
        from rosbags.rosbag2 import Reader as Reader2
    except ImportError:
        if path.suffix.lower() == ".bag":
            head = path.read_bytes()[: 4 << 20]
            if not head.startswith(b"#ROSBAG V2.0"):
                raise DatasetError(f"{path}: not a rosbag v1 file; check the file") from None
            if b"/file_version" in head or b"/device_0/" in head:
                return ["/file_version"]
        raise DatasetError(
            f"{path}: reading ROS bags needs the 'rosbags' package; pip install 'rgbd-calib[ros]'"
        ) from None
    try:
        with Reader1(path) if path.suffix.lower() == ".bag" else Reader2(path) as reader:
            return [c.topic for c in reader.connections]
    except Exception as exc:  # rosbags raises several unrelated types for foreign files
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DatasetError(
            f"{path}: not a readable RealSense or ROS bag ({first}); "
            "is the file complete and a .bag/.db3/.mcap recording?"
        ) from None


def _is_sdk_recording(topics: list[str]) -> bool:
    return any(t == "/file_version" or t.startswith("/device_") for t in topics)


def check_source(path: Path) -> None:
    if not path.exists():
        raise DatasetError(f"{path}: recording not found; check the path")
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise DatasetError(
                f"{path}: folder is not a ROS 2 bag (no metadata.yaml); pass the bag "
                "folder, a .bag/.db3/.mcap file, or use a dataset folder directly"
            )
    elif path.suffix.lower() not in RECORDING_SUFFIXES:
        raise DatasetError(
            f"{path}: unsupported recording type {path.suffix or '(no suffix)'!r}; "
            "expected a RealSense .bag/.db3 file or a ROS bag (.bag, .db3, .mcap, folder)"
        )


def convert(
    sources: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    names: Sequence[str] | None = None,
    sync_tolerance_ms: float | None = None,
    progress: Progress | None = None,
    depth_models: dict[str, DepthModel] | None = None,
) -> ConversionReport:
    """Convert recordings into the folder form (docs/formats.md) at ``out`` (videos:
    :func:`rgbd_calib.sources.dispatch.convert` takes either).

    ``names`` renames the cameras, in the order they are found (sources in order, the
    cameras of one ROS bag in namespace order). ``sync_tolerance_ms`` is how far apart two
    cameras' frames may be and still form a set; default half the reference camera's frame
    period. ``progress`` (:mod:`rgbd_calib.core.progress`) has a stage per source read and one for
    writing the frame sets. ``depth_models`` (camera name -> :class:`DepthModel`, e.g.
    :func:`rgbd_calib.load_depth_models` of a calibration) writes those cameras' depth
    corrected (:func:`~rgbd_calib.core.depth_model.correct_depth_image`); every name must be
    one of the converted cameras."""
    out = Path(out)
    sources = [Path(s) for s in sources]
    if not sources:
        raise ConfigError("convert: give at least one recording")
    if sync_tolerance_ms is not None and not sync_tolerance_ms > 0:
        raise ConfigError(f"--sync-tolerance-ms must be positive, got {sync_tolerance_ms}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DatasetError(
            f"{out}: output folder exists and is not empty; choose a new folder or delete it"
        )
    kinds = []
    for src in sources:
        check_source(src)
        kinds.append("sdk" if _is_sdk_recording(_topics(src)) else "ros")
    with staged_folder(out) as tmp:
        stager = Stager(tmp)
        cams: list[StagedCamera] = []
        for src, kind in zip(sources, kinds):
            if kind == "sdk":
                cams.append(read_sdk(src, stager, progress))
            else:
                cams.extend(read_ros(src, stager, progress))
        _assign_names(cams, names)
        _check_model_names(cams, depth_models or {})
        report = _write_sets(cams, tmp, out, sync_tolerance_ms, progress, depth_models or {})
        shutil.rmtree(stager.root)
    return report


def _with_scale(cam: StagedCamera) -> CameraIntrinsics:
    assert cam.intrinsics is not None
    i = cam.intrinsics
    return CameraIntrinsics(
        i.width, i.height, i.fx, i.fy, i.cx, i.cy, i.distortion, cam.depth_scale
    )


def _assign_names(cams: list[StagedCamera], names: Sequence[str] | None) -> None:
    if names:
        if len(names) != len(cams):
            found = ", ".join(c.key for c in cams)
            raise ConfigError(
                f"--names: {len(names)} name(s) given but {len(cams)} camera(s) found "
                f"({found}); give one name per camera in that order"
            )
        for cam, name in zip(cams, names):
            if not CAMERA_NAME.match(name):
                raise ConfigError(f"--names: {name!r} may only use letters, digits, '_' and '-'")
            cam.name = name
    seen: dict[str, str] = {}
    for cam in cams:
        if cam.name in seen:
            raise ConfigError(
                f"{cam.key} and {seen[cam.name]} both give camera name {cam.name!r}; "
                "pass --names with one unique name per camera"
            )
        seen[cam.name] = cam.key


def _check_model_names(cams: list[StagedCamera], models: dict[str, DepthModel]) -> None:
    names = [c.name for c in cams]
    if unknown := sorted(set(models) - set(names)):
        raise ConfigError(
            f"--depth-model names {', '.join(unknown)}, not among the converted cameras "
            f"({', '.join(names)}); pass --names so that the cameras carry the calibration's "
            "names")
    if raw := [c.name for c in cams if c.name in models and not c.depths]:
        raise ConfigError(f"--depth-model: {', '.join(raw)} recorded no depth to correct")


def _write_sets(
    cams: list[StagedCamera],
    root: Path,
    out: Path,
    sync_tolerance_ms: float | None,
    progress: Progress | None,
    models: dict[str, DepthModel],
) -> ConversionReport:
    """Match the cameras' staged frames into sets and write them, with rig.yaml, into the
    folder form at ``root`` (renamed to ``out`` later)."""
    reference, sync_tolerance_ms, sets = match_cameras(cams, sync_tolerance_ms)
    # rig.yaml: the first camera found is the calibration's reference
    rig = Rig({c.name: _with_scale(c) for c in cams}, cams[0].name)
    writer = FolderWriter(root, rig, depth_cameras=[c.name for c in cams if c.depths])
    matched, without_depth, times = _move_frames(cams, sets, writer, progress, models)
    if shared_clock(cams):  # else the times of different cameras cannot be compared
        for name, table in times.items():
            writer.write_timestamps(name, table)
    counts = {
        c.name: CameraCounts(
            frames_read=len(c.colors),
            matched=matched[c.name],
            unmatched=len(c.colors) - matched[c.name],
            dropped=len(sets) - matched[c.name],
            without_depth=without_depth[c.name],
        )
        for c in cams
    }
    return ConversionReport(
        out=out,
        cameras=[c.name for c in cams],
        sync_reference=reference,
        frames_written=len(sets),
        sync_tolerance_ms=float(sync_tolerance_ms),
        counts=counts,
        intrinsics_source={c.name: c.intrinsics_source for c in cams},
        depth_source={c.name: c.depth_source for c in cams},
        notes=clock_notes(cams) + ([
            f"depth corrected by the depth model of {', '.join(sorted(models))} "
            "(--depth-model)"] if models else []),
    )


def _move_frames(
    cams: list[StagedCamera],
    sets: list[dict[str, int]],
    writer: FolderWriter,
    progress: Progress | None,
    models: dict[str, DepthModel],
) -> tuple[dict[str, int], dict[str, int], dict[str, dict[str, float]]]:
    """Move each set's staged colour frames into place, each with its paired depth frame
    (aligned here when raw; corrected by the camera's depth model in ``models``). Per camera:
    colour frames written, those without depth, and each written frame's capture time
    (stem -> the colour frame's timestamp, ms)."""
    by_name = {c.name: c for c in cams}
    depth_of = {c.name: pair_depth(c) for c in cams}
    matched = {c.name: 0 for c in cams}
    without_depth = {c.name: 0 for c in cams}
    times: dict[str, dict[str, float]] = {c.name: {} for c in cams}
    tick = start(progress, "writing frame sets", len(sets))
    for k, group in enumerate(sets):
        stem = f"{k:06d}"
        for name, i in group.items():
            cam = by_name[name]
            _check_color_size(cam, cam.colors[i].path)
            os.replace(cam.colors[i].path, writer.path(name, "color", stem))
            times[name][stem] = cam.colors[i].t_ms
            matched[name] += 1
            depth = depth_of[name].get(i)
            if depth is None:
                without_depth[name] += 1
            elif cam.depth_raw or name in models:
                img = (_align_staged(cam, depth.path) if cam.depth_raw
                       else cv2.imread(str(depth.path), cv2.IMREAD_UNCHANGED))
                if name in models:
                    img = correct_depth_image(models[name], img, _with_scale(cam))
                writer.write(name, "depth", stem, img)
            else:  # copied, not moved: a depth frame may serve two colour frames
                shutil.copyfile(depth.path, writer.path(name, "depth", stem))
        tick(1)
    return matched, without_depth, times


def _check_color_size(cam: StagedCamera, path: Path) -> None:
    assert cam.intrinsics is not None
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.shape[:2] != (cam.intrinsics.height, cam.intrinsics.width):
        shape = "unreadable" if img is None else f"{img.shape[1]}x{img.shape[0]}"
        raise DatasetError(
            f"{cam.key}: colour frame is {shape} but its camera_info says "
            f"{cam.intrinsics.width}x{cam.intrinsics.height}; the recording is "
            "inconsistent"
        )


def _align_staged(cam: StagedCamera, path: Path) -> np.ndarray:
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert cam.intrinsics is not None and cam.depth_intrinsics is not None
    assert cam.T_color_depth is not None
    if raw is None or raw.shape != (cam.depth_intrinsics.height, cam.depth_intrinsics.width):
        raise DatasetError(
            f"{cam.key}: raw depth frame does not match its depth camera_info size; the "
            "recording is inconsistent"
        )
    return align_depth_to_color(
        raw, cam.depth_intrinsics, cam.intrinsics, cam.T_color_depth, cam.depth_scale
    )
