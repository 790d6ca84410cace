"""``ground_truth.yaml`` of a synthetic set: written beside the dataset folder by
:func:`write_ground_truth`, read back by :func:`load_ground_truth` (never by the calibration
itself)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.depth_model import DepthModel, identity_model
from ..core.geometry import invert_transform, pose_after_twist
from ..core.yamlio import write_yaml
from ..model.board import Board
from .imperfections import BoardPrint
from .params import SynthCamera, SynthParams, SynthRig
from .timing import SynthTiming, row_time_s

# listed only when a time setting is on
TIME_PARAMS = ("motion", "sync_offset_ms", "rolling_shutter_ms", "timestamp_jitter_ms", "burst",
               "acceleration", "frame_rate")
# listed only when a depth error beyond depth_bias is on
DEPTH_ERROR_PARAMS = ("depth_disparity_offset_px", "depth_disparity_field_px",
                      "depth_pose_error")


def write_ground_truth(
    path: Path,
    rig: SynthRig,
    poses: list[np.ndarray],
    layout: str,
    seed: int,
    board: Board,
    printed: BoardPrint,
    params: SynthParams,
    closeups: list[tuple[str, np.ndarray]],
    n_frames: int,
    timing: SynthTiming | None = None,
) -> None:
    """``ground_truth.yaml`` of a render: the true rig, board poses (``T_ref_board`` per frame
    set, close-ups after the ``n_frames`` regular ones), depth biases, the physical board
    (``printed``) beside the nominal board file, the true intrinsics and the settings; with
    ``timing`` (any time setting on) its ``time:`` section, and only then are the time
    settings listed under ``params`` (a still render's file is as before they existed).
    ``depth_model`` (each camera's true :class:`DepthModel`) is written when a camera's is
    not the identity, the depth-error settings only when one of them is on."""
    T_world_ref = rig.cameras[rig.reference_index].T_world_cam
    T_ref_world = invert_transform(T_world_ref)
    burst = 1 if timing is None else timing.burst
    write_yaml(
        path,
        {
            "reference": rig.reference,
            "T_ref_cam": {c.name: rig.T_ref_cam(c) for c in rig.cameras},
            "T_ref_board": {f"{i:06d}": T_ref_world @ T for i, T in enumerate(poses)},
            "depth_scale_bias": {c.name: c.depth_scale_bias for c in rig.cameras},
            "layout": layout,
            "seed": seed,
            "board": {
                **board.to_dict(),  # the board file, nominal
                "T_front_back": printed.T_front_back,
                "print_scale": printed.print_scale,
                "thickness_m": printed.thickness_m,
                **({"ink_spread_mm": printed.ink_spread_m * 1000.0}
                   if printed.ink_spread_m else {}),
                **({"T_board_face": {s.label: printed.face_poses.get(s.label,
                                                                     s.T_board_face)
                                     for s in board.sheets}} if board.sheets else {}),
            },
            "intrinsics": {c.name: c.intrinsics.to_dict() for c in rig.cameras},
            "params": {
                k: _plain(v) for k, v in params.__dict__.items()
                if (timing is not None or k not in TIME_PARAMS)
                and (params.depth_errors or k not in DEPTH_ERROR_PARAMS)
            },
            "bumped": {name: {"mm": mm, "deg": deg} for name, mm, deg in params.bump},
            "closeups": {f"{(n_frames + i) * burst + k:06d}": name
                         for i, (name, _) in enumerate(closeups) for k in range(burst)},
            **({} if timing is None else {"time": _time_section(rig, timing)}),
            **_depth_model_section(rig),
        },
    )


def _depth_model_section(rig: SynthRig) -> dict:
    """``depth_model:`` per camera its true :class:`DepthModel` (``to_dict``), or nothing when
    every camera's is the identity (the file of a render made before it was recorded)."""
    models = {c.name: _true_model(c) for c in rig.cameras}
    if all(m.is_identity for m in models.values()):
        return {}
    return {"depth_model": {name: m.to_dict() for name, m in models.items()}}


def _true_model(cam: SynthCamera) -> DepthModel:
    """A camera's true depth model; one without ``depth_model`` has its scale alone."""
    if cam.depth_model is not None:
        return cam.depth_model
    return identity_model(cam.intrinsics).with_values({"scale": cam.depth_scale_bias})


def _time_section(rig: SynthRig, timing: SynthTiming) -> dict:
    """``time:``: per camera its clock offset and colour readout (ms), per frame set the
    board's twist in the reference frame (m/s, rad/s), with its accelerations (m/s^2, rad/s^2)
    when it accelerates and its nominal time ``t_ms``; the convention is :mod:`.timing`'s."""

    def motion(i: int) -> dict:
        out = {"v_mps": [float(x) for x in timing.v_mps[i]],
               "w_radps": [float(x) for x in timing.w_radps[i]]}
        if np.any(timing.a_mps2[i]) or np.any(timing.alpha_radps2[i]):
            out |= {"a_mps2": [float(x) for x in timing.a_mps2[i]],
                    "alpha_radps2": [float(x) for x in timing.alpha_radps2[i]]}
        return out | {"t_ms": float(timing.t_ms[i])}

    return {
        "offset_ms": {c.name: 1000.0 * t for c, t in zip(rig.cameras, timing.offset_s)},
        "readout_ms": {c.name: 1000.0 * t for c, t in zip(rig.cameras, timing.readout_s)},
        "board_twist": {f"{i:06d}": motion(i) for i in range(len(timing.v_mps))},
    }


def _plain(value):
    """Tuples (nested too) as lists, for YAML."""
    return [_plain(v) for v in value] if isinstance(value, (tuple, list)) else value


@dataclass(frozen=True)
class GroundTruth:
    """``ground_truth.yaml`` of a synthetic set (never read by the calibration itself).

    ``intrinsics`` are the true camera models the images were rendered with (empty for a set
    written before they were recorded: its ``rig.yaml`` is then exact). ``T_front_back``,
    ``print_scale`` and ``thickness_m`` (None: the board file's) describe the physical board
    (:class:`BoardPrint`); absent, the board is exactly its board file. ``closeups`` names
    the camera each close-up frame set was posed for (``--closeups``; empty without).

    Time (``--motion``, ``--sync-offset-ms``, ``--rolling-shutter-ms``; 0 for every camera and
    frame set when the file has no ``time:`` section): ``offset_ms`` and ``readout_ms`` per
    camera, the board's twist per frame set in the reference frame, ``board_v_mps`` and
    ``board_w_radps`` (3-vectors), under the convention of :mod:`rgbd_calib.synth.timing`
    (:meth:`T_ref_board_at`, :meth:`exposure_tau_s`).

    ``depth_model`` holds each camera's true :class:`DepthModel`, the measured -> true depth
    correction a calibration estimates (its ``true_depth`` inverts what the camera reported);
    empty when the file has none: every camera's depth error is its ``depth_scale_bias``
    alone."""

    reference: str
    T_ref_cam: dict[str, np.ndarray]
    T_ref_board: dict[str, np.ndarray]
    depth_scale_bias: dict[str, float]
    intrinsics: dict[str, CameraIntrinsics] = field(default_factory=dict)
    T_front_back: np.ndarray = field(default_factory=lambda: np.eye(4))
    print_scale: float = 1.0
    thickness_m: float | None = None
    closeups: dict[str, str] = field(default_factory=dict)  # frame -> camera (--closeups)
    T_board_face: dict[int, np.ndarray] = field(default_factory=dict)  # multi-face: true poses
    offset_ms: dict[str, float] = field(default_factory=dict)  # camera -> clock offset
    readout_ms: dict[str, float] = field(default_factory=dict)  # camera -> colour readout
    board_v_mps: dict[str, np.ndarray] = field(default_factory=dict)  # frame -> v (ref frame)
    board_w_radps: dict[str, np.ndarray] = field(default_factory=dict)  # frame -> w (ref)
    board_a_mps2: dict[str, np.ndarray] = field(default_factory=dict)  # frame -> a (ref)
    board_alpha_radps2: dict[str, np.ndarray] = field(default_factory=dict)  # frame -> alpha
    depth_model: dict[str, DepthModel] = field(default_factory=dict)  # camera -> true model
    ink_spread_mm: float = 0.0  # --ink-spread: the print's ink beyond the file's edges

    def T_ref_board_at(self, frame: str, tau_s: float) -> np.ndarray:
        """The board pose (4x4, metres, reference frame) ``tau_s`` seconds after frame set
        ``frame``'s nominal time: ``[Exp_SO3(w tau + alpha tau^2 / 2) R | p + v tau +
        a tau^2 / 2]``."""
        zero = np.zeros(3)
        return pose_after_twist(self.T_ref_board[frame], self.board_v_mps.get(frame, zero),
                                self.board_w_radps.get(frame, zero), tau_s,
                                self.board_a_mps2.get(frame, zero),
                                self.board_alpha_radps2.get(frame, zero))

    def exposure_tau_s(self, camera: str, v_px: float | np.ndarray, height: int):
        """When ``camera``'s colour pixel row ``v_px`` (0 = top) of an image ``height`` rows
        high is exposed, seconds after the frame set's nominal time."""
        return row_time_s(v_px, height, self.offset_ms.get(camera, 0.0) / 1000.0,
                          self.readout_ms.get(camera, 0.0) / 1000.0)

    def board_print(self, board: Board) -> BoardPrint:
        """The physical board of this set, for the board file ``board`` it was rendered with."""
        thickness = board.thickness if self.thickness_m is None else self.thickness_m
        return BoardPrint(thickness, self.print_scale, self.T_front_back,
                          dict(self.T_board_face), self.ink_spread_mm / 1000.0)


def load_ground_truth(path: Path) -> GroundTruth:
    from ..core.yamlio import matrix4, read_yaml_mapping
    from ..model.rig import parse_camera

    path = Path(path)
    if path.is_dir():
        path = path / "ground_truth.yaml"
    data = read_yaml_mapping(path, "ground truth")
    board = data.get("board") or {}
    thickness = board.get("thickness_m")
    time = data.get("time") or {}
    twist = time.get("board_twist") or {}
    cameras, frames = [str(k) for k in data["T_ref_cam"]], [str(k) for k in data["T_ref_board"]]

    def per_camera(key: str) -> dict[str, float]:
        values = {str(k): float(v) for k, v in (time.get(key) or {}).items()}
        return {c: values.get(c, 0.0) for c in cameras}

    def per_frame(key: str) -> dict[str, np.ndarray]:
        values = {str(k): _vector3(v.get(key), f"{path}: time.board_twist.{k}.{key}")
                  for k, v in twist.items() if key in v or key in ("v_mps", "w_radps")}
        return {f: values.get(f, np.zeros(3)) for f in frames}

    return GroundTruth(
        str(data["reference"]),
        {k: matrix4(v, f"{path}: T_ref_cam.{k}") for k, v in data["T_ref_cam"].items()},
        {str(k): matrix4(v, f"{path}: T_ref_board.{k}") for k, v in data["T_ref_board"].items()},
        {k: float(v) for k, v in data.get("depth_scale_bias", {}).items()},
        {
            str(k): parse_camera(v, f"{path}: intrinsics.{k}")
            for k, v in (data.get("intrinsics") or {}).items()
        },
        matrix4(board["T_front_back"], f"{path}: board.T_front_back")
        if "T_front_back" in board
        else np.eye(4),
        float(board.get("print_scale", 1.0)),
        None if thickness is None else float(thickness),
        {str(k): str(v) for k, v in (data.get("closeups") or {}).items()},
        {int(k): matrix4(v, f"{path}: board.T_board_face.{k}")
         for k, v in (board.get("T_board_face") or {}).items()},
        per_camera("offset_ms"),
        per_camera("readout_ms"),
        per_frame("v_mps"),
        per_frame("w_radps"),
        per_frame("a_mps2"),
        per_frame("alpha_radps2"),
        {str(k): DepthModel.from_dict(v, f"{path}: depth_model.{k}")
         for k, v in (data.get("depth_model") or {}).items()},
        float(board.get("ink_spread_mm", 0.0)),
    )


def _vector3(value, where: str) -> np.ndarray:
    from ..core.errors import ConfigError

    out = np.asarray(value if value is not None else [], dtype=float).reshape(-1)
    if out.shape != (3,):
        raise ConfigError(f"{where}: expected 3 numbers [x, y, z]; write the render again")
    return out
