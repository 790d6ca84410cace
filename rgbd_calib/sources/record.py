"""Live capture of a calibration set from connected RealSense D435i cameras.

Each set is one colour + depth (aligned to colour) frame per camera, written in the folder
form of docs/formats.md as it is captured. ``rig.yaml`` is written first, from the devices'
factory intrinsics; each set is then put in place whole (:meth:`FolderWriter.write_set`), with
its row of each camera's ``timestamps.csv`` (the colour frames' librealsense timestamps), so
an interrupt never leaves half a set.

The device boundary is :class:`DeviceSource` (``serials()`` and ``open()``); the real one
wraps ``rs.context``/``rs.pipeline``. Tests pass a fake source there.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.errors import ConfigError, DatasetError
from ..core.interrupts import interrupt_handled
from ..model.dataset import FolderWriter
from ..model.rig import CAMERA_NAME, Rig
from .align import distortion_from_realsense
from .sync import one_clock

DEFAULT_MODE = (1280, 720, 30)  # width, height, fps: a D435i depth and colour mode
HW_SYNC_MASTER, HW_SYNC_SLAVE = 1, 2  # rs.option.inter_cam_sync_mode values (D400)
MARKER_IMAGE_WIDTH_PX = 640  # live marker counts run on images downscaled to this width
MAX_RESYNC_WAITS = 4  # extra waits per set to bring free-running cameras together


# --------------------------------------------------------------------------- device boundary
@dataclass(frozen=True)
class CapturedFrame:
    """One camera's frame: colour BGR ``(H,W,3)`` uint8, depth counts ``(H,W)`` uint16
    aligned to colour (or None), the colour frame's timestamp in milliseconds and its clock
    (librealsense's timestamp domain: ``global_time``, the host clock the device's is mapped
    to, librealsense's default; ``system_time``; or ``hardware_clock``, the camera's own)."""

    color: np.ndarray
    depth: np.ndarray | None
    timestamp_ms: float
    timestamp_domain: str = "global_time"


class CameraStream(Protocol):
    serial: str
    intrinsics: CameraIntrinsics  # colour intrinsics with the depth scale

    def wait(self, timeout_ms: int) -> CapturedFrame: ...

    def stop(self) -> None: ...


class DeviceSource(Protocol):
    def serials(self) -> list[str]: ...

    def open(self, serial: str, mode: tuple[int, int, int], sync_mode: int) -> CameraStream: ...


class RealSenseSource:
    """Connected RealSense cameras through pyrealsense2 (one pipeline per camera)."""

    def __init__(self, warmup_frames: int = 15):
        try:
            import pyrealsense2 as rs
        except ImportError as exc:  # e.g. libusb missing
            raise DatasetError(
                f"pyrealsense2 cannot be imported ({exc}); install librealsense's Python "
                "package and libusb-1.0"
            ) from None
        self._rs = rs
        self._ctx = rs.context()
        self._warmup = warmup_frames

    def serials(self) -> list[str]:
        rs = self._rs
        return [d.get_info(rs.camera_info.serial_number) for d in self._ctx.query_devices()]

    def open(self, serial: str, mode: tuple[int, int, int], sync_mode: int) -> CameraStream:
        return _RealSenseStream(self._rs, self._ctx, serial, mode, sync_mode, self._warmup)


class _RealSenseStream:
    def __init__(
        self, rs, ctx, serial: str, mode: tuple[int, int, int], sync_mode: int, warmup: int
    ):
        width, height, fps = mode
        self._rs = rs
        self.serial = serial
        self._pipe = rs.pipeline(ctx)
        cfg = rs.config()
        cfg.enable_device(serial)
        cfg.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
        cfg.enable_stream(rs.stream.color, width, height, rs.format.bgr8, fps)
        try:
            device = cfg.resolve(rs.pipeline_wrapper(self._pipe)).get_device()
        except RuntimeError:
            raise DatasetError(
                f"camera {serial}: mode {width}x{height}@{fps} is not available for both "
                "depth and colour; try 1280x720@30 or 848x480@30 (and a USB 3 port)"
            ) from None
        depth_sensor = device.first_depth_sensor()
        if sync_mode:
            if not depth_sensor.supports(rs.option.inter_cam_sync_mode):
                raise DatasetError(
                    f"camera {serial}: no hardware sync option; record without --hardware-sync"
                )
            depth_sensor.set_option(rs.option.inter_cam_sync_mode, float(sync_mode))
        profile = self._pipe.start(cfg)
        ci = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        self.intrinsics = CameraIntrinsics(
            ci.width,
            ci.height,
            ci.fx,
            ci.fy,
            ci.ppx,
            ci.ppy,
            distortion_from_realsense(str(ci.model), ci.coeffs, f"camera {serial}"),
            float(f"{depth_sensor.get_depth_scale():.7g}"),
        )
        self._align = rs.align(rs.stream.color)
        for _ in range(warmup):  # let auto-exposure settle
            self._pipe.wait_for_frames(5000)

    def wait(self, timeout_ms: int) -> CapturedFrame:
        try:
            frames = self._pipe.wait_for_frames(timeout_ms)
        except RuntimeError:
            raise DatasetError(
                f"camera {self.serial}: no frames for {timeout_ms} ms; check the cable "
                "(USB 3) and, with --hardware-sync, the sync wiring"
            ) from None
        aligned = self._align.process(frames)
        color = aligned.get_color_frame()
        depth = aligned.get_depth_frame()
        return CapturedFrame(
            np.asanyarray(color.get_data()).copy(),
            np.asanyarray(depth.get_data()).copy() if depth else None,
            float(color.get_timestamp()),
            str(color.get_frame_timestamp_domain()).split(".")[-1],
        )

    def stop(self) -> None:
        self._pipe.stop()


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class RecordStatus:
    """Progress after each written set (for a live display)."""

    sets_written: int
    frame: str  # stem of the set just written
    markers: dict[str, int]  # camera -> board markers detected (-1: no board given)
    spread_ms: float  # largest timestamp difference between the cameras of the set


@dataclass(frozen=True)
class RecordReport:
    out: Path
    cameras: list[str]
    sets_written: int
    interrupted: bool
    hardware_sync: bool
    mode: tuple[int, int, int]
    max_spread_ms: float
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "out": str(self.out),
            "cameras": list(self.cameras),
            "sets_written": self.sets_written,
            "interrupted": self.interrupted,
            "hardware_sync": self.hardware_sync,
            "mode": list(self.mode),
            "max_spread_ms": self.max_spread_ms,
            "notes": list(self.notes),
        }


# --------------------------------------------------------------------------- helpers
class MarkerCounter:
    """Board markers visible in a colour image (ArUco on a downscaled grey image)."""

    def __init__(self, board):
        self._ids = {int(i) for i in board.ids}
        self._detector = cv2.aruco.ArucoDetector(board.aruco_dict, cv2.aruco.DetectorParameters())

    def __call__(self, color_bgr: np.ndarray) -> int:
        grey = color_bgr if color_bgr.ndim == 2 else cv2.cvtColor(color_bgr, cv2.COLOR_BGR2GRAY)
        scale = min(1.0, MARKER_IMAGE_WIDTH_PX / grey.shape[1])
        if scale < 1.0:
            grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        _, ids, _ = self._detector.detectMarkers(grey)
        return 0 if ids is None else len({int(i) for i in np.ravel(ids)} & self._ids)


def _capture_set(
    streams: dict[str, CameraStream], fps: float, timeout_ms: int
) -> tuple[dict[str, CapturedFrame], float]:
    """One frame per camera; free-running cameras that lag the newest frame by more than
    half a frame period wait for their next frame (a few times at most)."""
    frames = {name: s.wait(timeout_ms) for name, s in streams.items()}
    half_period_ms = 500.0 / fps
    for _ in range(MAX_RESYNC_WAITS):
        newest = max(f.timestamp_ms for f in frames.values())
        late = [n for n, f in frames.items() if newest - f.timestamp_ms > half_period_ms]
        if not late:
            break
        for name in late:
            frames[name] = streams[name].wait(timeout_ms)
    times = [f.timestamp_ms for f in frames.values()]
    return frames, float(max(times) - min(times))


# --------------------------------------------------------------------------- record
def record(
    out: Path,
    n_sets: int | None = None,
    mode: tuple[int, int, int] = DEFAULT_MODE,
    hardware_sync: bool = False,
    board=None,
    names: Sequence[str] | None = None,
    device_source: DeviceSource | None = None,
    status_callback: Callable[[RecordStatus], None] | None = None,
    timeout_ms: int = 5000,
) -> RecordReport:
    """Capture synchronised sets from every connected camera into ``out`` (folder form).

    Stops after ``n_sets`` sets, or on Ctrl-C (KeyboardInterrupt) when ``n_sets`` is None;
    either way every written set is complete. With ``hardware_sync`` the first camera is
    the master (``inter_cam_sync_mode`` 1) and the others slaves (2). ``board`` enables the
    live marker count in :class:`RecordStatus`. Cameras are named by serial unless
    ``names`` (one per camera, in serial order) is given."""
    out = Path(out)
    _check_request(out, n_sets, mode)
    source = device_source if device_source is not None else RealSenseSource()
    serials, cam_names = _camera_names(source, names)
    count_markers = MarkerCounter(board) if board is not None else None

    created = not out.exists()
    streams: dict[str, CameraStream] = {}
    writer: FolderWriter | None = None
    interrupted = False
    max_spread = 0.0
    try:
        _open_streams(source, serials, cam_names, mode, hardware_sync, streams)
        # rig.yaml first, from the devices' factory intrinsics
        rig = Rig({n: streams[n].intrinsics for n in cam_names}, cam_names[0])
        writer = FolderWriter(out, rig)
        while n_sets is None or writer.sets_written < n_sets:
            frames, spread = _capture_set(streams, mode[2], timeout_ms)
            stem = _write_set(writer, rig, frames)
            max_spread = max(max_spread, spread)
            if status_callback:
                markers = {
                    n: count_markers(f.color) if count_markers else -1 for n, f in frames.items()
                }
                status_callback(RecordStatus(writer.sets_written, stem, markers, spread))
    except KeyboardInterrupt:  # the way to stop an open-ended recording
        interrupt_handled()
        interrupted = True
    finally:
        _stop_streams(streams)
        written = writer.sets_written if writer is not None else 0
        if written == 0 and created and out.exists():
            shutil.rmtree(out, ignore_errors=True)
    notes = []
    if not hardware_sync and len(cam_names) > 1:
        notes.append(
            f"cameras were free-running: frames of a set were up to {max_spread:.1f} ms "
            "apart; keep the board still while recording or use --hardware-sync"
        )
    return RecordReport(
        out, cam_names, written, interrupted, hardware_sync, tuple(mode), max_spread, notes
    )


def _check_request(out: Path, n_sets: int | None, mode: tuple[int, int, int]) -> None:
    """Refuse a bad set count, capture mode or a non-empty output folder before any camera
    is opened."""
    if n_sets is not None and n_sets < 1:
        raise ConfigError(f"--sets must be at least 1, got {n_sets}")
    width, height, fps = mode
    if min(width, height, fps) <= 0:
        raise ConfigError(f"capture mode {width}x{height}@{fps} is not valid")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DatasetError(
            f"{out}: output folder exists and is not empty; choose a new folder or delete it"
        )


def _camera_names(source: DeviceSource, names: Sequence[str] | None) -> tuple[list, list]:
    """The connected cameras' serials (sorted) and their names (``names`` or the serials)."""
    serials = sorted(source.serials())
    if not serials:
        raise DatasetError(
            "no RealSense camera connected; plug the D435i cameras into USB 3 ports (check "
            "with rs-enumerate-devices), or convert a recording with 'rgbd-calib convert'"
        )
    cam_names = list(names) if names else list(serials)
    if len(cam_names) != len(serials) or len(set(cam_names)) != len(cam_names):
        raise ConfigError(
            f"--names: give {len(serials)} unique name(s), one per camera "
            f"(serials {', '.join(serials)})"
        )
    bad = [n for n in cam_names if not CAMERA_NAME.match(n)]
    if bad:
        raise ConfigError(f"--names: {bad[0]!r} may only use letters, digits, '_' and '-'")
    return serials, cam_names


def _open_streams(
    source: DeviceSource,
    serials: list[str],
    cam_names: list[str],
    mode: tuple[int, int, int],
    hardware_sync: bool,
    streams: dict[str, CameraStream],
) -> None:
    """Open every camera into ``streams`` (filled as they open, so a failure stops the ones
    already open); with ``hardware_sync`` the first is the master, the others slaves."""
    for k, (serial, name) in enumerate(zip(serials, cam_names)):
        sync_mode = 0 if not hardware_sync else (HW_SYNC_MASTER if k == 0 else HW_SYNC_SLAVE)
        streams[name] = source.open(serial, mode, sync_mode)


def _write_set(writer: FolderWriter, rig: Rig, frames: dict[str, CapturedFrame]) -> str:
    """Check the frames' size against the rig and write them as the next set; its stem."""
    for name, frame in frames.items():
        intr = rig.cameras[name]
        if frame.color.shape[:2] != (intr.height, intr.width):
            raise DatasetError(
                f"camera {name}: frame is {frame.color.shape[1]}x"
                f"{frame.color.shape[0]} but its intrinsics say "
                f"{intr.width}x{intr.height}"
            )
    stem = f"{writer.sets_written:06d}"
    # each camera's timestamps.csv gets the set's row, when the cameras' clocks are one
    shared = one_clock([f.timestamp_domain for f in frames.values()])
    writer.write_set(
        stem,
        {n: f.color for n, f in frames.items()},
        {
            n: f.depth.astype(np.uint16, copy=False)
            for n, f in frames.items()
            if f.depth is not None
        },
        {n: f.timestamp_ms for n, f in frames.items()} if shared else None,
    )
    return stem


def _stop_streams(streams: dict[str, CameraStream]) -> None:
    for stream in streams.values():
        try:
            stream.stop()
        except Exception:  # a camera unplugged mid-run must not hide the real error
            pass
