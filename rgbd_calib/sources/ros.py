"""realsense-ros cameras from ROS 1 ``.bag`` files and ROS 2 bags (sqlite3 or mcap), via rosbags.

Per camera namespace ``<ns>``: ``<ns>/color/image_raw`` + ``<ns>/color/camera_info``, and depth
from ``<ns>/aligned_depth_to_color/image_raw`` (preferred) or ``<ns>/depth/image_rect_raw`` +
``<ns>/depth/camera_info`` + ``<ns>/extrinsics/depth_to_color`` (then aligned by the
conversion, the way librealsense does it). Several cameras in one bag are told apart by
namespace.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.errors import DatasetError
from ..core.progress import Progress, start
from .align import extrinsics_matrix
from .staging import StagedCamera, StagedFrame, Stager, sanitize_name

ROS_DEPTH_SCALE = 0.001  # realsense-ros publishes 16UC1 depth in millimetres

# realsense-ros topic suffixes below a camera namespace
COLOR_TOPIC = "/color/image_raw"
COLOR_INFO_TOPIC = "/color/camera_info"
ALIGNED_DEPTH_TOPIC = "/aligned_depth_to_color/image_raw"
DEPTH_TOPIC = "/depth/image_rect_raw"
DEPTH_INFO_TOPIC = "/depth/camera_info"
EXTRINSICS_TOPIC = "/extrinsics/depth_to_color"

# realsense2_camera_msgs/msg/Extrinsics (ROS 2); ROS 1 bags carry their own definition
_EXTRINSICS_MSG = "float64[9] rotation\nfloat64[3] translation\n"


def _namespace_names(namespaces: list[str]) -> list[str]:
    """Camera names from namespaces: drop the parts all cameras share (``/camera/camera1``,
    ``/camera/camera2`` -> camera1, camera2; ``/left/camera``, ``/right/camera`` -> left,
    right); a single camera is named by its last namespace part."""
    parts = [[p for p in ns.split("/") if p] for ns in namespaces]
    if len(parts) == 1:
        return [sanitize_name(parts[0][-1] if parts[0] else "camera")]
    while all(len(p) > 1 for p in parts) and len({p[0] for p in parts}) == 1:
        parts = [p[1:] for p in parts]
    while all(len(p) > 1 for p in parts) and len({p[-1] for p in parts}) == 1:
        parts = [p[:-1] for p in parts]
    return [sanitize_name("_".join(p) if p else "camera") for p in parts]


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


def read_ros(path: Path, stager: Stager, progress: Progress | None) -> list[StagedCamera]:
    """Every realsense-ros camera of one ROS 1/ROS 2 bag."""
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([path], default_typestore=_ros_typestore())
        reader.open()
    except Exception as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DatasetError(f"{path}: cannot open the bag ({first})") from None
    try:
        by_topic: dict[str, list] = {}
        for con in reader.connections:
            by_topic.setdefault(con.topic, []).append(con)
        cams, routes = _plan_cameras(path, by_topic)
        connections = [c for t in routes if t in by_topic for c in by_topic[t]]
        total = sum(c.msgcount for ns in cams for c in by_topic[ns + COLOR_TOPIC])
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
            _take_message(cam, kind, msg, t_ns, con.topic, stager, where)
            if kind == "color":
                tick(1)
    finally:
        reader.close()
    _check_complete(path, cams)
    return list(cams.values())


def _plan_cameras(
    path: Path, by_topic: dict[str, list]
) -> tuple[dict[str, StagedCamera], dict[str, tuple[StagedCamera, str]]]:
    """One camera per namespace with a colour topic, and which topics feed it as what
    (``topic -> (camera, kind)``): aligned depth when the bag has it, else raw depth with
    what aligning it needs."""
    namespaces = sorted(t[: -len(COLOR_TOPIC)] for t in by_topic if t.endswith(COLOR_TOPIC))
    if not namespaces:
        shown = ", ".join(sorted(by_topic)[:6]) or "none"
        raise DatasetError(
            f"{path}: no colour image topic (<camera>/color/image_raw) in the bag "
            f"(topics: {shown}); record realsense-ros with colour enabled"
        )
    cams: dict[str, StagedCamera] = {}
    routes: dict[str, tuple[StagedCamera, str]] = {}
    for ns, name in zip(namespaces, _namespace_names(namespaces)):
        cam = StagedCamera(key=f"{path.name}:{ns or '/'}", name=name, depth_scale=ROS_DEPTH_SCALE)
        cam.timestamp_domain = "ros header stamp"
        cams[ns] = cam
        routes[ns + COLOR_TOPIC] = (cam, "color")
        routes[ns + COLOR_INFO_TOPIC] = (cam, "color_info")
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
    return cams, routes


def _take_message(
    cam: StagedCamera, kind: str, msg, t_ns: int, topic: str, stager: Stager, where: str
) -> None:
    """Store a decoded message of ``kind`` (see :func:`_plan_cameras`) on its camera."""
    if kind == "color_info":
        cam.intrinsics = _ros_camera_info(msg, where)
        cam.intrinsics_source = f"{topic} ({msg.distortion_model or 'plumb_bob'})"
    elif kind == "depth_info":
        cam.depth_intrinsics = _ros_camera_info(msg, where)
    elif kind == "extrinsics":
        cam.T_color_depth = extrinsics_matrix(msg.rotation, msg.translation)
    else:
        img, is_depth = _ros_image(msg, where)
        if is_depth != (kind == "depth"):
            raise DatasetError(f"{where}: encoding {msg.encoding!r} does not fit a {kind} topic")
        frame = StagedFrame(_stamp_ms(msg, t_ns), stager.put(img))
        (cam.depths if kind == "depth" else cam.colors).append(frame)


def _check_complete(path: Path, cams: dict[str, StagedCamera]) -> None:
    """Every camera needs its colour camera_info; raw depth also its own and the extrinsics."""
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
