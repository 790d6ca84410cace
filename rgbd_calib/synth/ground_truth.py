"""``ground_truth.yaml`` of a synthetic set: written beside the dataset folder by
:func:`write_ground_truth`, read back by :func:`load_ground_truth` (never by the calibration
itself)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.geometry import invert_transform
from ..core.yamlio import write_yaml
from ..model.board import Board
from .imperfections import BoardPrint
from .params import SynthParams, SynthRig


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
) -> None:
    """``ground_truth.yaml`` of a render: the true rig, board poses (``T_ref_board`` per frame
    set, close-ups after the ``n_frames`` regular ones), depth biases, the physical board
    (``printed``) beside the nominal board file, the true intrinsics and the settings."""
    T_world_ref = rig.cameras[rig.reference_index].T_world_cam
    T_ref_world = invert_transform(T_world_ref)
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
                **({"T_board_face": {s.label: printed.face_poses.get(s.label,
                                                                     s.T_board_face)
                                     for s in board.sheets}} if board.sheets else {}),
            },
            "intrinsics": {c.name: c.intrinsics.to_dict() for c in rig.cameras},
            "params": {
                k: _plain(v) for k, v in params.__dict__.items()
            },
            "bumped": {name: {"mm": mm, "deg": deg} for name, mm, deg in params.bump},
            "closeups": {f"{n_frames + i:06d}": name
                         for i, (name, _) in enumerate(closeups)},
        },
    )


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
    the camera each close-up frame set was posed for (``--closeups``; empty without)."""

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

    def board_print(self, board: Board) -> BoardPrint:
        """The physical board of this set, for the board file ``board`` it was rendered with."""
        thickness = board.thickness if self.thickness_m is None else self.thickness_m
        return BoardPrint(thickness, self.print_scale, self.T_front_back,
                          dict(self.T_board_face))


def load_ground_truth(path: Path) -> GroundTruth:
    from ..core.yamlio import matrix4, read_yaml_mapping
    from ..model.rig import parse_camera

    path = Path(path)
    if path.is_dir():
        path = path / "ground_truth.yaml"
    data = read_yaml_mapping(path, "ground truth")
    board = data.get("board") or {}
    thickness = board.get("thickness_m")
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
    )
