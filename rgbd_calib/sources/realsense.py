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

from ..errors import DatasetError
from ..progress import Progress, start
from ..rig import CameraIntrinsics
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
        cam.colors.append(StagedFrame(t, stager.put(_rs_color_to_bgr(color, str(path)))))
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
        cam.depths.append(StagedFrame(t, stager.put(aligned.astype(np.uint16, copy=False))))

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
