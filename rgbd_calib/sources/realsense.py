"""One camera from a RealSense SDK recording (``.bag`` before SDK 2.56, ``.db3`` after).

Read with pyrealsense2 playback (not real time), sensor by sensor; depth is aligned to colour
with ``rs.align(rs.stream.color)``; the camera is named by its serial number.
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.errors import DatasetError
from ..core.progress import Progress, start
from .align import distortion_from_realsense, extrinsics_matrix, same_geometry
from .staging import StagedCamera, StagedFrame, Stager, sanitize_name

PLAYBACK_END_IDLE_POLLS = 5  # 0.1 s polls without frames after playback stopped = the end


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


def read_sdk(path: Path, stager: Stager, progress: Progress | None) -> StagedCamera:
    """One camera from a RealSense SDK recording, depth aligned with rs.align."""
    import pyrealsense2 as rs

    try:
        device = rs.context().load_device(str(path))
    except RuntimeError as exc:
        raise DatasetError(f"{path}: librealsense cannot play this recording ({exc})") from None
    playback = device.as_playback()
    playback.set_real_time(False)
    chosen = _choose_streams(rs, device, path)
    cam, identity = _describe_camera(rs, device, chosen, path)
    sink = _FrameSink(
        rs, cam, stager, identity, path, start(progress, f"reading {path.name}", None)
    )
    _play(rs, playback, chosen, sink)
    if not cam.colors:
        raise DatasetError(f"{path}: recording holds no colour frames")
    return cam


def _choose_streams(rs, device, path: Path) -> dict[Any, tuple[Any, Any]]:
    """The first colour and depth stream of the recording: stream -> (sensor, profile)."""
    chosen: dict[Any, tuple[Any, Any]] = {}
    for sensor in device.query_sensors():
        for profile in sensor.get_stream_profiles():
            st = profile.stream_type()
            if st in (rs.stream.color, rs.stream.depth) and st not in chosen:
                chosen[st] = (sensor, profile)
    if rs.stream.color not in chosen:
        raise DatasetError(
            f"{path}: recording has no colour stream; record colour and depth together"
        )
    return chosen


def _describe_camera(rs, device, chosen, path: Path) -> tuple[StagedCamera, bool]:
    """The camera named by its serial, with its colour intrinsics, depth scale and frame
    rate; and whether its depth stream is already in colour geometry (no alignment)."""
    serial = (
        device.get_info(rs.camera_info.serial_number)
        if device.supports(rs.camera_info.serial_number)
        else path.stem
    )
    color_profile = chosen[rs.stream.color][1].as_video_stream_profile()
    ci = color_profile.get_intrinsics()
    cam = StagedCamera(key=str(path), name=sanitize_name(serial))
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
        identity = same_geometry(
            depth_intr, cam.intrinsics, extrinsics_matrix(ex.rotation, ex.translation)
        )
        cam.depth_source = (
            "depth stream already in colour geometry" if identity else "rs.align(rs.stream.color)"
        )
        cam.fps = min(cam.fps, float(depth_profile.fps()))
    return cam, identity


class _FrameSink:
    """Stages a colour frame and the nearest of the depth frames around it, aligned to
    colour with rs.align (or as it is when depth is already in colour geometry)."""

    def __init__(self, rs, cam: StagedCamera, stager: Stager, identity: bool, path: Path, tick):
        self._cam, self._stager, self._identity, self._where = cam, stager, identity, str(path)
        self._tick = tick
        assert cam.fps is not None
        self._pair_tol_ms = 1000.0 / cam.fps  # the nearest depth within one frame period
        # rs.align takes a frameset: a processing block composes one from the chosen pair
        pair: dict[str, Any] = {}
        self._pair = pair
        self._composer = rs.processing_block(
            lambda _f, src: src.frame_ready(src.allocate_composite_frame([pair["d"], pair["c"]]))
        )
        self._composed = rs.frame_queue(2, keep_frames=True)
        self._composer.start(self._composed)
        self._align = rs.align(rs.stream.color)

    def emit(self, color, depths) -> None:
        """Stage ``color`` and, when one lies within a frame period, its nearest depth."""
        cam = self._cam
        t = color.get_timestamp()
        depth = min(depths, key=lambda d: abs(d.get_timestamp() - t), default=None)
        cam.timestamp_domain = str(color.get_frame_timestamp_domain()).split(".")[-1]
        cam.colors.append(StagedFrame(t, self._stager.put(_rs_color_to_bgr(color, self._where))))
        self._tick(1)
        if depth is None or abs(depth.get_timestamp() - t) > self._pair_tol_ms:
            return
        if self._identity:
            aligned = np.asanyarray(depth.get_data())
        else:
            self._pair["d"], self._pair["c"] = depth, color
            self._composer.invoke(color)
            frameset = self._composed.wait_for_frame(5000).as_frameset()
            aligned = np.asanyarray(self._align.process(frameset).get_depth_frame().get_data())
        cam.depths.append(StagedFrame(t, self._stager.put(aligned.astype(np.uint16, copy=False))))


def _play(rs, playback, chosen, sink: _FrameSink) -> None:
    """Play the recording to its end through the sensors' callbacks into ``sink``."""
    frames: queue.Queue = queue.Queue(maxsize=4)  # back-pressure: playback waits for us
    stopping = threading.Event()

    def on_frame(frame) -> None:
        while not stopping.is_set():
            try:
                frames.put(frame, timeout=0.1)
                return
            except queue.Full:
                continue

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
        _dispatch(rs, playback, frames, sink, has_depth=rs.stream.depth in chosen)
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


def _dispatch(rs, playback, frames: queue.Queue, sink: _FrameSink, has_depth: bool) -> None:
    """Hand every colour frame to ``sink`` with the depth frames around it, until playback
    ends. A colour frame waits for the next depth frame (at most 4 colour frames queue up),
    so its nearest depth frame is known."""
    recent_depths: deque = deque(maxlen=3)
    pending: list = []
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
                sink.emit(pending.pop(0), recent_depths)
        elif not has_depth:
            sink.emit(frame, ())
        else:
            pending.append(frame)
            if len(pending) > 4:  # depth stalled: do not hold colour frames forever
                sink.emit(pending.pop(0), recent_depths)
    for c in pending:
        sink.emit(c, recent_depths)
    pending.clear()
    recent_depths.clear()
