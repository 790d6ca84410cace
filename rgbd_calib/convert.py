"""Convert RealSense recordings into the folder form of docs/formats.md.

Sources:

- RealSense SDK recordings, one file per camera: ``.bag`` (rosbag v1, SDK before 2.56) and
  ``.db3`` (SDK 2.56+). Read with pyrealsense2 playback (not real time); depth is aligned to
  colour with ``rs.align(rs.stream.color)``; the camera is named by its serial number.
- realsense-ros bags: ROS 1 ``.bag``, ROS 2 folders (sqlite3 or mcap) or their bare
  ``.db3``/``.mcap`` files, read with ``rosbags``. Per camera namespace ``<ns>``:
  ``<ns>/color/image_raw`` + ``<ns>/color/camera_info``, and depth from
  ``<ns>/aligned_depth_to_color/image_raw`` (preferred) or ``<ns>/depth/image_rect_raw`` +
  ``<ns>/depth/camera_info`` + ``<ns>/extrinsics/depth_to_color`` (aligned here, the way
  librealsense does it). Several cameras in one bag are told apart by namespace.

Every colour frame is decoded once and staged on disk; when all sources are read, colour is
paired with the nearest depth frame of the same camera, cameras are matched by timestamp, and
the staged files are renamed into ``<camera>/{color,depth}/<frame>.png``. Everything happens in
a temporary sibling folder that is renamed into place at the end.
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import shutil
import sqlite3
import threading
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import ConfigError, DatasetError
from .progress import Progress, start
from .rig import CAMERA_NAME, CameraIntrinsics, Rig, save_rig
from .yamlio import atomic_write_text

RECORDING_SUFFIXES = (".bag", ".db3", ".mcap")
ROS_DEPTH_SCALE = 0.001  # realsense-ros publishes 16UC1 depth in millimetres
DEFAULT_FPS = 30.0  # frame rate assumed when a stream has a single frame
CACHE_MARKER = ".rgbd-calib-source.json"
PLAYBACK_END_IDLE_POLLS = 5  # 0.1 s polls without frames after playback stopped = the end

# realsense-ros topic suffixes below a camera namespace
COLOR_TOPIC = "/color/image_raw"
COLOR_INFO_TOPIC = "/color/camera_info"
ALIGNED_DEPTH_TOPIC = "/aligned_depth_to_color/image_raw"
DEPTH_TOPIC = "/depth/image_rect_raw"
DEPTH_INFO_TOPIC = "/depth/camera_info"
EXTRINSICS_TOPIC = "/extrinsics/depth_to_color"

# realsense2_camera_msgs/msg/Extrinsics (ROS 2); ROS 1 bags carry their own definition
_EXTRINSICS_MSG = "float64[9] rotation\nfloat64[3] translation\n"


# --------------------------------------------------------------------------- results
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


# --------------------------------------------------------------------------- geometry
def extrinsics_matrix(rotation: Sequence[float], translation: Sequence[float]) -> np.ndarray:
    """``T_to_from`` (4x4, metres) of a librealsense ``rs2_extrinsics`` from->to.

    librealsense stores ``rotation`` column-major (rs_sensor.h; realsense-ros copies it
    verbatim into its Extrinsics message), so the 9 numbers are R's columns, not its rows."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(rotation, dtype=float).reshape(3, 3).T
    T[:3, 3] = np.asarray(translation, dtype=float)
    return T


def distortion_from_realsense(model: str, coeffs: Sequence[float], where: str) -> tuple:
    """OpenCV ``k1 k2 p1 p2 k3`` from a librealsense distortion model.

    librealsense orders Brown-Conrady coefficients ``[k1, k2, p1, p2, k3]`` (rs_types.h), the
    OpenCV order. D400 colour streams report "inverse Brown-Conrady" with coefficients that
    realsense-ros publishes unchanged as ``plumb_bob`` (and librealsense PR #13833 argues they
    are forward Brown-Conrady): they are passed through as the OpenCV model. Modified
    Brown-Conrady differs from OpenCV only in second-order tangential terms."""
    name = model.split(".")[-1]
    if name == "none":
        return (0.0,) * 5
    if name in ("brown_conrady", "inverse_brown_conrady", "modified_brown_conrady"):
        return tuple(float(c) for c in list(coeffs)[:5])
    raise DatasetError(
        f"{where}: colour distortion model {name!r} is not a Brown-Conrady model; "
        "rgbd-calib supports D400 colour streams only"
    )


def align_depth_to_color(
    depth: np.ndarray,
    depth_intr: CameraIntrinsics,
    color_intr: CameraIntrinsics,
    T_color_depth: np.ndarray,
    depth_scale: float,
) -> np.ndarray:
    """Depth counts ``(H_d,W_d)`` uint16 re-rendered in the colour camera ``(H_c,W_c)``.

    ``T_color_depth`` (4x4, metres) maps depth-camera points into the colour camera. Follows
    librealsense's ``align_z_to_other`` (src/proc/align.cpp): each depth pixel's footprint,
    its corners at +-0.5 px deprojected at its depth, is projected into the colour image and
    every colour pixel it covers takes the nearest depth (z-buffer). 0 = no depth."""
    depth = np.asarray(depth)
    out_w, out_h = color_intr.width, color_intr.height
    if _same_geometry(depth_intr, color_intr, T_color_depth):
        return depth.astype(np.uint16, copy=True)
    v, u = np.nonzero(depth)
    counts = depth[v, u].astype(np.uint16)
    z = counts * float(depth_scale)

    def corner_pixels(offset: float) -> np.ndarray:
        uv = np.column_stack([u + offset, v + offset]).astype(float)
        if depth_intr.has_distortion:
            xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), depth_intr.K, depth_intr.dist).reshape(
                -1, 2
            )
        else:
            xy = (uv - [depth_intr.cx, depth_intr.cy]) / [depth_intr.fx, depth_intr.fy]
        p_depth = np.column_stack([xy * z[:, None], z])
        p_color = p_depth @ T_color_depth[:3, :3].T + T_color_depth[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.trunc(color_intr.project(p_color) + 0.5)

    x0, y0 = corner_pixels(-0.5).T
    x1, y1 = corner_pixels(0.5).T
    ok = (x0 >= 0) & (y0 >= 0) & (x1 < out_w) & (y1 < out_h) & (x1 >= x0) & (y1 >= y0)
    x0, y0, x1, y1, counts = (a[ok].astype(np.int64) for a in (x0, y0, x1, y1, counts))
    flat = np.full(out_w * out_h, np.iinfo(np.uint16).max, dtype=np.uint16)
    w, h = x1 - x0, y1 - y0
    for dy in range(int(h.max(initial=-1)) + 1):
        for dx in range(int(w.max(initial=-1)) + 1):
            sel = (dx <= w) & (dy <= h)
            np.minimum.at(flat, (y0[sel] + dy) * out_w + x0[sel] + dx, counts[sel])
    flat[flat == np.iinfo(np.uint16).max] = 0
    return flat.reshape(out_h, out_w)


def _same_geometry(a: CameraIntrinsics, b: CameraIntrinsics, T_b_a: np.ndarray) -> bool:
    """Depth already in colour geometry: alignment is the identity (no resampling)."""
    same_k = (a.width, a.height) == (b.width, b.height) and np.allclose(
        [a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=0, atol=1e-6
    )
    n = max(a.dist.size, b.dist.size)
    same_d = np.allclose(np.pad(a.dist, (0, n - a.dist.size)), np.pad(b.dist, (0, n - b.dist.size)))
    return bool(same_k and same_d and np.allclose(T_b_a, np.eye(4), atol=1e-9))


# --------------------------------------------------------------------------- staging
@dataclass
class _Frame:
    t_ms: float
    path: Path


@dataclass
class _Camera:
    """One camera's staged frames and calibration while its sources are read."""

    key: str  # where it came from (file or namespace), for messages
    name: str
    intrinsics: CameraIntrinsics | None = None
    intrinsics_source: str = ""
    depth_source: str = "none (colour-only camera)"
    colors: list[_Frame] = field(default_factory=list)
    depths: list[_Frame] = field(default_factory=list)
    depth_raw: bool = False  # depths are raw depth-camera images that still need aligning
    depth_intrinsics: CameraIntrinsics | None = None
    T_color_depth: np.ndarray | None = None
    depth_scale: float = 0.001
    fps: float | None = None
    timestamp_domain: str = ""


class _Stager:
    """Writes decoded images once into ``<tmp>/.staging`` and hands out their paths."""

    def __init__(self, root: Path):
        self.root = root / ".staging"
        self.root.mkdir(parents=True)
        self._n = 0

    def put(self, image: np.ndarray) -> Path:
        self._n += 1
        path = self.root / f"{self._n:08d}.png"
        _write_png(path, image)
        return path


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise DatasetError(f"{path}: could not encode the image as PNG")
    path.write_bytes(buf.tobytes())


def _median_period_ms(times: Iterable[float], fps: float | None) -> float:
    t = np.sort(np.fromiter(times, dtype=float))
    steps = np.diff(t)
    steps = steps[steps > 0]
    if steps.size:
        return float(np.median(steps))
    return 1000.0 / (fps or DEFAULT_FPS)


# --------------------------------------------------------------------------- source types
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


def _check_source(path: Path) -> None:
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


# --------------------------------------------------------------------------- SDK reader
def _rs_color_to_bgr(frame, where: str) -> np.ndarray:
    import pyrealsense2 as rs

    fmt = frame.get_profile().format()
    data = np.asanyarray(frame.get_data())
    conversions = {
        rs.format.rgb8: cv2.COLOR_RGB2BGR,
        rs.format.rgba8: cv2.COLOR_RGBA2BGR,
        rs.format.bgra8: cv2.COLOR_BGRA2BGR,
        rs.format.yuyv: cv2.COLOR_YUV2BGR_YUYV,
        rs.format.uyvy: cv2.COLOR_YUV2BGR_UYVY,
    }
    if fmt == rs.format.bgr8 or fmt == rs.format.y8:
        return data.copy()
    if fmt in conversions:
        if fmt in (rs.format.yuyv, rs.format.uyvy):
            vf = frame.as_video_frame()
            data = data.reshape(vf.get_height(), vf.get_width(), 2)
        return cv2.cvtColor(data, conversions[fmt])
    raise DatasetError(f"{where}: colour format {fmt} is not supported; record RGB8 or BGR8")


def _read_sdk(path: Path, stager: _Stager, progress: Progress | None) -> _Camera:
    """One camera from a RealSense SDK recording, depth aligned with rs.align."""
    import pyrealsense2 as rs

    try:
        device = rs.context().load_device(str(path))
    except RuntimeError as exc:
        raise DatasetError(f"{path}: librealsense cannot play this recording ({exc})") from None
    playback = device.as_playback()
    playback.set_real_time(False)
    serial = (
        device.get_info(rs.camera_info.serial_number)
        if device.supports(rs.camera_info.serial_number)
        else path.stem
    )
    chosen: dict[Any, tuple[Any, Any]] = {}  # stream -> (sensor, profile)
    for sensor in device.query_sensors():
        for profile in sensor.get_stream_profiles():
            st = profile.stream_type()
            if st in (rs.stream.color, rs.stream.depth) and st not in chosen:
                chosen[st] = (sensor, profile)
    if rs.stream.color not in chosen:
        raise DatasetError(
            f"{path}: recording has no colour stream; record colour and depth together"
        )
    color_profile = chosen[rs.stream.color][1].as_video_stream_profile()
    ci = color_profile.get_intrinsics()
    cam = _Camera(key=str(path), name=_sanitize(serial))
    cam.intrinsics = CameraIntrinsics(
        ci.width,
        ci.height,
        ci.fx,
        ci.fy,
        ci.ppx,
        ci.ppy,
        distortion_from_realsense(str(ci.model), ci.coeffs, str(path)),
    )
    cam.intrinsics_source = f"{path.name}: colour stream profile ({str(ci.model).split('.')[-1]})"
    cam.fps = float(color_profile.fps())
    identity = False
    if rs.stream.depth in chosen:
        depth_profile = chosen[rs.stream.depth][1].as_video_stream_profile()
        # float32 in librealsense: keep its shortest decimal form (0.001, not 0.00100000005)
        cam.depth_scale = float(f"{device.first_depth_sensor().get_depth_scale():.7g}")
        di = depth_profile.get_intrinsics()
        depth_intr = CameraIntrinsics(
            di.width, di.height, di.fx, di.fy, di.ppx, di.ppy, tuple(di.coeffs)
        )
        ex = depth_profile.get_extrinsics_to(color_profile)
        identity = _same_geometry(
            depth_intr, cam.intrinsics, extrinsics_matrix(ex.rotation, ex.translation)
        )
        cam.depth_source = (
            "depth stream already in colour geometry" if identity else "rs.align(rs.stream.color)"
        )
        cam.fps = min(cam.fps, float(depth_profile.fps()))
    pair_tol_ms = 1000.0 / cam.fps  # a colour frame takes the nearest depth within one period
    tick = start(progress, f"reading {path.name}", None)

    frames: queue.Queue = queue.Queue(maxsize=4)  # back-pressure: playback waits for us
    stopping = threading.Event()

    def on_frame(frame) -> None:
        while not stopping.is_set():
            try:
                frames.put(frame, timeout=0.1)
                return
            except queue.Full:
                continue

    pair: dict[str, Any] = {}
    composer = rs.processing_block(
        lambda _f, src: src.frame_ready(src.allocate_composite_frame([pair["d"], pair["c"]]))
    )
    composed = rs.frame_queue(2, keep_frames=True)
    composer.start(composed)
    align = rs.align(rs.stream.color)

    def emit(color, depth) -> None:
        t = color.get_timestamp()
        cam.timestamp_domain = str(color.get_frame_timestamp_domain()).split(".")[-1]
        cam.colors.append(_Frame(t, stager.put(_rs_color_to_bgr(color, str(path)))))
        tick(1)
        if depth is None or abs(depth.get_timestamp() - t) > pair_tol_ms:
            return
        if identity:
            aligned = np.asanyarray(depth.get_data())
        else:
            pair["d"], pair["c"] = depth, color
            composer.invoke(color)
            frameset = composed.wait_for_frame(5000).as_frameset()
            aligned = np.asanyarray(align.process(frameset).get_depth_frame().get_data())
        cam.depths.append(_Frame(t, stager.put(aligned.astype(np.uint16, copy=False))))

    def nearest(color, depths):
        t = color.get_timestamp()
        return min(depths, key=lambda d: abs(d.get_timestamp() - t), default=None)

    sensors = {id(s): s for s, _ in chosen.values()}
    opened = []
    try:
        for sensor in sensors.values():
            sensor.open([p for s, p in chosen.values() if s is sensor])
            opened.append(sensor)
        # playback starts with the first sensor: hold it until every sensor listens, or the
        # other sensors' first frames are lost
        playback.pause()
        for sensor in opened:
            sensor.start(on_frame)
        playback.resume()
        recent_depths: deque = deque(maxlen=3)
        pending: list = []
        has_depth = rs.stream.depth in chosen
        idle_after_stop = 0
        while True:
            try:
                frame = frames.get(timeout=0.1)
            except queue.Empty:
                # playback reports "stopped" when its reader reaches the end of the file,
                # possibly before the sensors have dispatched the last frames: wait a little
                if playback.current_status() == rs.playback_status.stopped:
                    idle_after_stop += 1
                    if idle_after_stop >= PLAYBACK_END_IDLE_POLLS:
                        break
                continue
            idle_after_stop = 0
            if frame.get_profile().stream_type() == rs.stream.depth:
                recent_depths.append(frame)
                t_d = frame.get_timestamp()
                while pending and pending[0].get_timestamp() <= t_d:
                    c = pending.pop(0)
                    emit(c, nearest(c, recent_depths))
            elif not has_depth:
                emit(frame, None)
            else:
                pending.append(frame)
                if len(pending) > 4:  # depth stalled: do not hold colour frames forever
                    c = pending.pop(0)
                    emit(c, nearest(c, recent_depths))
        for c in pending:
            emit(c, nearest(c, recent_depths))
        pending.clear()
        recent_depths.clear()
    finally:
        stopping.set()
        while not frames.empty():
            frames.get_nowait()
        for sensor in opened:
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError:
                pass
    if not cam.colors:
        raise DatasetError(f"{path}: recording holds no colour frames")
    return cam


# --------------------------------------------------------------------------- ROS reader
def _sanitize(name: str) -> str:
    clean = "".join(ch if CAMERA_NAME.match(ch) else "_" for ch in name).strip("_")
    return clean or "camera"


def _namespace_names(namespaces: list[str]) -> list[str]:
    """Camera names from namespaces: drop the parts all cameras share (``/camera/camera1``,
    ``/camera/camera2`` -> camera1, camera2; ``/left/camera``, ``/right/camera`` -> left,
    right); a single camera is named by its last namespace part."""
    parts = [[p for p in ns.split("/") if p] for ns in namespaces]
    if len(parts) == 1:
        return [_sanitize(parts[0][-1] if parts[0] else "camera")]
    while all(len(p) > 1 for p in parts) and len({p[0] for p in parts}) == 1:
        parts = [p[1:] for p in parts]
    while all(len(p) > 1 for p in parts) and len({p[-1] for p in parts}) == 1:
        parts = [p[:-1] for p in parts]
    return [_sanitize("_".join(p) if p else "camera") for p in parts]


def _stamp_ms(msg, fallback_ns: int) -> float:
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is not None:
        sec = getattr(stamp, "sec", getattr(stamp, "secs", 0))
        nsec = getattr(stamp, "nanosec", getattr(stamp, "nsecs", 0))
        if sec or nsec:
            return sec * 1e3 + nsec * 1e-6
    return fallback_ns * 1e-6


def _ros_image(msg, where: str) -> tuple[np.ndarray, bool]:
    """(image, is_depth) of a sensor_msgs/Image: BGR/grey uint8 or depth uint16 (mm)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    enc = str(msg.encoding).lower()
    raw = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
    if raw.size < h * step:
        raise DatasetError(f"{where}: truncated image message ({raw.size} of {h * step} bytes)")
    rows = raw[: h * step].reshape(h, step)
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc1": 1, "8uc3": 3}
    if enc in channels:
        img = (
            rows[:, : w * channels[enc]].reshape(h, w, channels[enc])
            if channels[enc] > 1
            else rows[:, :w]
        )
        if enc == "rgb8":
            img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        elif enc == "rgba8":
            img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGR)
        elif enc == "bgra8":
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        return np.ascontiguousarray(img), False
    if enc in ("16uc1", "mono16"):
        dt = np.dtype(">u2" if msg.is_bigendian else "<u2")
        img = rows[:, : w * 2].copy().view(dt).reshape(h, w)
        return img.astype(np.uint16), True
    if enc == "32fc1":  # metres -> millimetre counts
        dt = np.dtype(">f4" if msg.is_bigendian else "<f4")
        metres = rows[:, : w * 4].copy().view(dt).reshape(h, w)
        mm = np.where(np.isfinite(metres) & (metres > 0), np.rint(metres * 1000.0), 0)
        return np.clip(mm, 0, 65535).astype(np.uint16), True
    raise DatasetError(
        f"{where}: image encoding {msg.encoding!r} is not supported "
        "(rgb8, bgr8, mono8, 16UC1, mono16, 32FC1)"
    )


def _ros_camera_info(msg, where: str) -> CameraIntrinsics:
    K = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), dtype=float)
    D = [float(v) for v in getattr(msg, "d", getattr(msg, "D", []))]
    model = str(msg.distortion_model or "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial", "brown_conrady", ""):
        raise DatasetError(
            f"{where}: distortion model {model!r} is not supported (plumb_bob, rational_polynomial)"
        )
    D = (D + [0.0] * 5)[: max(5, len(D))] if D else [0.0] * 5
    if K.size != 9 or K[0] <= 0:
        raise DatasetError(f"{where}: camera_info has no calibration (K is zero)")
    return CameraIntrinsics(
        int(msg.width),
        int(msg.height),
        float(K[0]),
        float(K[4]),
        float(K[2]),
        float(K[5]),
        tuple(D),
    )


def _ros_typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(_EXTRINSICS_MSG, "realsense2_camera_msgs/msg/Extrinsics"))
    return store


def _read_ros(path: Path, stager: _Stager, progress: Progress | None) -> list[_Camera]:
    """Every realsense-ros camera of one ROS 1/ROS 2 bag."""
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([path], default_typestore=_ros_typestore())
        reader.open()
    except Exception as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DatasetError(f"{path}: cannot open the bag ({first})") from None
    try:
        by_topic = {}
        for con in reader.connections:
            by_topic.setdefault(con.topic, []).append(con)
        namespaces = sorted(t[: -len(COLOR_TOPIC)] for t in by_topic if t.endswith(COLOR_TOPIC))
        if not namespaces:
            shown = ", ".join(sorted(by_topic)[:6]) or "none"
            raise DatasetError(
                f"{path}: no colour image topic (<camera>/color/image_raw) in the bag "
                f"(topics: {shown}); record realsense-ros with colour enabled"
            )
        cams: dict[str, _Camera] = {}
        routes: dict[str, tuple[_Camera, str]] = {}
        total = 0
        for ns, name in zip(namespaces, _namespace_names(namespaces)):
            cam = _Camera(key=f"{path.name}:{ns or '/'}", name=name, depth_scale=ROS_DEPTH_SCALE)
            cams[ns] = cam
            routes[ns + COLOR_TOPIC] = (cam, "color")
            routes[ns + COLOR_INFO_TOPIC] = (cam, "color_info")
            total += sum(c.msgcount for c in by_topic[ns + COLOR_TOPIC])
            aligned = by_topic.get(ns + ALIGNED_DEPTH_TOPIC, [])
            if sum(c.msgcount for c in aligned):
                routes[ns + ALIGNED_DEPTH_TOPIC] = (cam, "depth")
                cam.depth_source = f"{ns}{ALIGNED_DEPTH_TOPIC}"
            elif sum(c.msgcount for c in by_topic.get(ns + DEPTH_TOPIC, [])):
                routes[ns + DEPTH_TOPIC] = (cam, "depth")
                routes[ns + DEPTH_INFO_TOPIC] = (cam, "depth_info")
                routes[ns + EXTRINSICS_TOPIC] = (cam, "extrinsics")
                cam.depth_raw = True
                cam.depth_source = f"{ns}{DEPTH_TOPIC} aligned by rgbd-calib"
        connections = [c for t in routes if t in by_topic for c in by_topic[t]]
        tick = start(progress, f"reading {path.name}", total)
        for con, t_ns, data in reader.messages(connections=connections):
            cam, kind = routes[con.topic]
            if kind == "color_info" and cam.intrinsics is not None:
                continue
            if kind == "depth_info" and cam.depth_intrinsics is not None:
                continue
            if kind == "extrinsics" and cam.T_color_depth is not None:
                continue
            where = f"{path}: {con.topic}"
            try:
                msg = reader.deserialize(data, con.msgtype)
            except Exception as exc:
                raise DatasetError(f"{where}: undecodable message ({exc})") from None
            if kind == "color_info":
                cam.intrinsics = _ros_camera_info(msg, where)
                cam.intrinsics_source = f"{con.topic} ({msg.distortion_model or 'plumb_bob'})"
            elif kind == "depth_info":
                cam.depth_intrinsics = _ros_camera_info(msg, where)
            elif kind == "extrinsics":
                cam.T_color_depth = extrinsics_matrix(msg.rotation, msg.translation)
            else:
                img, is_depth = _ros_image(msg, where)
                if is_depth != (kind == "depth"):
                    raise DatasetError(
                        f"{where}: encoding {msg.encoding!r} does not fit a {kind} topic"
                    )
                frame = _Frame(_stamp_ms(msg, t_ns), stager.put(img))
                (cam.depths if kind == "depth" else cam.colors).append(frame)
                if kind == "color":
                    tick(1)
    finally:
        reader.close()
    for ns, cam in cams.items():
        if cam.intrinsics is None:
            raise DatasetError(
                f"{path}: no {ns}{COLOR_INFO_TOPIC} message; record the camera_info topic "
                "with the images"
            )
        if cam.depth_raw and (cam.depth_intrinsics is None or cam.T_color_depth is None):
            raise DatasetError(
                f"{path}: {ns}{DEPTH_TOPIC} needs {ns}{DEPTH_INFO_TOPIC} and "
                f"{ns}{EXTRINSICS_TOPIC} to be aligned; record them, or enable "
                "align_depth in realsense-ros"
            )
        cam.timestamp_domain = "ros header stamp"
    return list(cams.values())


# --------------------------------------------------------------------------- matching
def _pair_depth(cam: _Camera) -> dict[int, _Frame]:
    """Colour index -> nearest depth frame within one colour frame period."""
    if not cam.depths:
        return {}
    t_depth = np.array([d.t_ms for d in cam.depths])
    order = np.argsort(t_depth)
    t_sorted = t_depth[order]
    tol = _median_period_ms((c.t_ms for c in cam.colors), cam.fps)
    out: dict[int, _Frame] = {}
    for i, c in enumerate(cam.colors):
        k = int(np.searchsorted(t_sorted, c.t_ms))
        cands = [j for j in (k - 1, k) if 0 <= j < t_sorted.size]
        j = min(cands, key=lambda j: abs(t_sorted[j] - c.t_ms))
        if abs(t_sorted[j] - c.t_ms) <= tol + 1e-6:
            out[i] = cam.depths[order[j]]
    return out


def match_frames(times_ms: dict[str, np.ndarray], tolerance_ms: float) -> list[dict[str, int]]:
    """Group frames of several cameras into synchronised sets.

    The camera with the most frames is the reference; each of its frames takes, from every
    other camera, the nearest frame within ``tolerance_ms`` (one frame per set, the closest
    claim wins). Frames left over are grouped the same way among themselves, so a set may
    lack the reference camera. With several cameras a set needs at least two of them.
    Returns sets as ``{camera: frame index}`` in time order."""
    remaining = {c: np.arange(len(t)) for c, t in times_ms.items()}
    min_size = 2 if len(times_ms) > 1 else 1
    sets: list[dict[str, int]] = []
    while True:
        live = [c for c in times_ms if remaining[c].size]
        if len(live) < min_size:
            break
        ref = max(live, key=lambda c: remaining[c].size)
        ref_idx = remaining[ref]
        ref_t = times_ms[ref][ref_idx]
        groups: list[dict[str, int]] = [{ref: int(i)} for i in ref_idx]
        for cam in live:
            if cam == ref:
                continue
            idx = remaining[cam][np.argsort(times_ms[cam][remaining[cam]])]
            t = times_ms[cam][idx]
            k = np.clip(np.searchsorted(t, ref_t), 1, max(t.size - 1, 1))
            left = np.clip(k - 1, 0, t.size - 1)
            right = np.clip(k, 0, t.size - 1)
            pick = np.where(np.abs(t[left] - ref_t) <= np.abs(t[right] - ref_t), left, right)
            dt = np.abs(t[pick] - ref_t)
            best: dict[int, tuple[float, int]] = {}
            for g, (p, d) in enumerate(zip(pick, dt)):
                if d <= tolerance_ms and (p not in best or d < best[p][0]):
                    best[int(p)] = (float(d), g)
            for p, (_, g) in best.items():
                groups[g][cam] = int(idx[p])
        used = {c: set() for c in live}
        for g in groups:
            if len(g) >= min_size:
                sets.append(g)
                for c, i in g.items():
                    used[c].add(i)
        # the reference's frames are settled either way; other cameras keep what is unused
        remaining[ref] = np.array([], dtype=int)
        for c in live:
            if c != ref:
                remaining[c] = np.array([i for i in remaining[c] if i not in used[c]], dtype=int)
    sets.sort(key=lambda g: min(times_ms[c][i] for c, i in g.items()))
    return sets


# --------------------------------------------------------------------------- convert
def convert(
    sources: Sequence[Path],
    out: Path,
    names: Sequence[str] | None = None,
    sync_tolerance_ms: float | None = None,
    progress: Progress | None = None,
) -> ConversionReport:
    """Convert recordings into the folder form (docs/formats.md) at ``out``.

    ``names`` renames the cameras, in the order they are found (sources in order, the
    cameras of one ROS bag in namespace order). ``sync_tolerance_ms`` is how far apart two
    cameras' frames may be and still form a set; default half the reference camera's frame
    period. ``progress`` (:mod:`rgbd_calib.progress`) has a stage per source read and one for
    writing the frame sets."""
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
        _check_source(src)
        kinds.append("sdk" if _is_sdk_recording(_topics(src)) else "ros")
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir(parents=True)
        stager = _Stager(tmp)
        cams: list[_Camera] = []
        for src, kind in zip(sources, kinds):
            if kind == "sdk":
                cams.append(_read_sdk(src, stager, progress))
            else:
                cams.extend(_read_ros(src, stager, progress))
        _assign_names(cams, names)
        report = _write_sets(cams, tmp, out, sync_tolerance_ms, progress)
        shutil.rmtree(stager.root)
        # rig.yaml: the first camera found is the calibration's reference
        save_rig(Rig({c.name: _with_scale(c) for c in cams}, cams[0].name), tmp / "rig.yaml")
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return report


def _with_scale(cam: _Camera) -> CameraIntrinsics:
    assert cam.intrinsics is not None
    i = cam.intrinsics
    return CameraIntrinsics(
        i.width, i.height, i.fx, i.fy, i.cx, i.cy, i.distortion, cam.depth_scale
    )


def _assign_names(cams: list[_Camera], names: Sequence[str] | None) -> None:
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


def _write_sets(
    cams: list[_Camera],
    tmp: Path,
    out: Path,
    sync_tolerance_ms: float | None,
    progress: Progress | None,
) -> ConversionReport:
    """Pair, match and move staged frames into ``<camera>/{color,depth}/<frame>.png``."""
    times = {c.name: np.array([f.t_ms for f in c.colors]) for c in cams}
    reference = max(cams, key=lambda c: len(c.colors)).name
    by_name = {c.name: c for c in cams}
    if sync_tolerance_ms is None:
        ref = by_name[reference]
        sync_tolerance_ms = 0.5 * _median_period_ms(times[reference], ref.fps)
    sets = match_frames(times, sync_tolerance_ms)
    if not sets:
        raise DatasetError(
            f"{', '.join(c.key for c in cams)}: no frames of different cameras lie within "
            f"{sync_tolerance_ms:.1f} ms of each other; check that the recordings overlap in "
            "time (global time enabled) or raise --sync-tolerance-ms"
        )
    depth_of = {c.name: _pair_depth(c) for c in cams}
    notes = []
    domains = {c.timestamp_domain for c in cams}
    if len(cams) > 1 and "hardware_clock" in domains:
        notes.append(
            "some recordings use the camera's hardware clock: timestamps of different "
            "cameras share no common clock, so their matching may be wrong; enable "
            "global time when recording"
        )
    for c in cams:
        (tmp / c.name / "color").mkdir(parents=True)
        if c.depths:
            (tmp / c.name / "depth").mkdir(parents=True)
    matched = {c.name: 0 for c in cams}
    tick = start(progress, "writing frame sets", len(sets))
    without_depth = {c.name: 0 for c in cams}
    for k, group in enumerate(sets):
        stem = f"{k:06d}"
        for name, i in group.items():
            cam = by_name[name]
            assert cam.intrinsics is not None
            color = cam.colors[i].path
            img = cv2.imread(str(color), cv2.IMREAD_UNCHANGED)
            if img is None or img.shape[:2] != (cam.intrinsics.height, cam.intrinsics.width):
                shape = "unreadable" if img is None else f"{img.shape[1]}x{img.shape[0]}"
                raise DatasetError(
                    f"{cam.key}: colour frame is {shape} but its camera_info says "
                    f"{cam.intrinsics.width}x{cam.intrinsics.height}; the recording is "
                    "inconsistent"
                )
            os.replace(color, tmp / name / "color" / f"{stem}.png")
            matched[name] += 1
            depth = depth_of[name].get(i)
            if depth is None:
                without_depth[name] += 1
                continue
            target = tmp / name / "depth" / f"{stem}.png"
            if cam.depth_raw:
                _write_png(target, _align_staged(cam, depth.path))
            else:
                shutil.copyfile(depth.path, target)  # a depth frame may serve two colours
        tick(1)
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
        notes=notes,
    )


def _align_staged(cam: _Camera, path: Path) -> np.ndarray:
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


# --------------------------------------------------------------------------- cache
def _source_stamp(sources: Sequence[Path], names, sync_tolerance_ms) -> dict[str, Any]:
    entries = []
    for src in sources:
        files = sorted(p for p in src.rglob("*") if p.is_file()) if src.is_dir() else [src]
        stats = [p.stat() for p in files]
        entries.append(
            {
                "path": str(src.resolve()),
                "size": sum(s.st_size for s in stats),
                "mtime_ns": max((s.st_mtime_ns for s in stats), default=0),
            }
        )
    return {"sources": entries, "names": list(names or []), "sync_tolerance_ms": sync_tolerance_ms}


def convert_to_cache(
    source: Path | Sequence[Path],
    cache_dir: Path,
    names: Sequence[str] | None = None,
    sync_tolerance_ms: float | None = None,
    progress: Progress | None = None,
) -> Path:
    """Folder form of a recording under ``cache_dir``, converted once.

    A second call returns the earlier conversion while every source's size and modification
    time are unchanged; otherwise the cached folder is converted again. The conversion's
    report is kept beside it (:func:`cached_report`)."""
    sources = [Path(source)] if isinstance(source, (str, Path)) else [Path(s) for s in source]
    for src in sources:
        _check_source(src)
    stamp = _source_stamp(sources, names, sync_tolerance_ms)
    key = hashlib.sha1(
        json.dumps([e["path"] for e in stamp["sources"]] + stamp["names"]).encode()
    ).hexdigest()[:12]
    folder = Path(cache_dir) / f"{_sanitize(sources[0].stem)}-{key}"
    if _read_marker(folder).get("source") == stamp:
        return folder
    if folder.exists():
        shutil.rmtree(folder)
    report = convert(sources, folder, names, sync_tolerance_ms, progress)
    atomic_write_text(
        folder / CACHE_MARKER,
        json.dumps({"source": stamp, "report": report.to_dict()}, indent=1),
    )
    return folder


def _read_marker(folder: Path) -> dict[str, Any]:
    try:
        data = json.loads((Path(folder) / CACHE_MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def cached_report(folder: Path) -> ConversionReport | None:
    """The report of the conversion that made ``folder`` in a cache; None for any other
    folder (a dataset folder, say)."""
    data = _read_marker(folder).get("report")
    try:
        return ConversionReport.from_dict(data) if isinstance(data, dict) else None
    except (KeyError, TypeError, ValueError):
        return None


def dataset_folder(
    sources: Sequence[Path],
    cache_dir: Path,
    names: Sequence[str] | None = None,
    sync_tolerance_ms: float | None = None,
    progress: Progress | None = None,
) -> Path:
    """The folder form to calibrate from: a dataset folder as it is, or recordings converted
    once into ``cache_dir`` (see :func:`convert_to_cache`; converted again when a recording
    changes).

    One source that is not a recording (no .bag/.db3/.mcap suffix, not a ROS 2 bag folder) is
    taken as a dataset folder: :class:`FolderDataset` then names what is wrong with it.
    ``names`` and ``sync_tolerance_ms`` apply to recordings only."""
    sources = [Path(s) for s in sources]
    if not sources:
        raise ConfigError("give a dataset folder or at least one recording")
    single = sources[0]
    if len(sources) == 1 and not is_recording(single):
        if names or sync_tolerance_ms is not None:
            raise ConfigError(
                f"{single}: --names and --sync-tolerance-ms apply to recordings, not to a "
                "dataset folder; drop them (camera names come from its rig.yaml)"
            )
        return single
    for src in sources:
        if src.is_dir() and not is_recording(src):
            raise DatasetError(
                f"{src}: a dataset folder cannot be mixed with recordings; pass either one "
                "dataset folder or only recordings"
            )
    return convert_to_cache(sources, cache_dir, names, sync_tolerance_ms, progress)
