"""The board's motion through a synthetic rig: random poses seen by at least two cameras
(:func:`sample_board_poses`) and close-ups that fill each camera's image out to its corners
(:func:`closeup_poses`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..core.camera import OPENCV
from ..core.errors import ConfigError
from ..core.geometry import invert_transform, make_transform, rotvec_to_matrix
from ..model.board import BACK, FRONT, Board
from .params import SynthCamera, SynthRig

CLOSEUP_STREAM = 0xC105E  # rng stream of the close-up board poses (seed, stream)
# where a close-up's markers must reach, in turn (fractions of the image width and height):
# the four corners, then the middles of the four edges
CLOSEUP_TARGETS = ((0, 0), (1, 0), (1, 1), (0, 1), (0.5, 0), (1, 0.5), (0.5, 1), (0, 0.5))
CLOSEUP_REACH = 0.01  # ... and how close to it (image widths) ends the search


def marker_visibility(
    board: Board,
    cam: SynthCamera,
    T_world_board: np.ndarray,
    min_px: float = 12.0,
    max_angle_deg: float = 70.0,
) -> int:
    """How many markers a camera sees whole, facing it, and at least ``min_px`` wide."""
    T_cam_board = invert_transform(cam.T_world_cam) @ T_world_board
    return len(_visible_corners(board, cam, T_cam_board, min_px, max_angle_deg))


def sample_board_poses(
    rig: SynthRig,
    board: Board,
    n_frames: int,
    rng: np.random.Generator,
    min_cameras: int = 2,
    min_markers: int = 6,
) -> list[np.ndarray]:
    """Random board poses ``T_world_board`` seen by at least ``min_cameras`` cameras.

    The board centre is uniform in the workspace; its front normal points at a random camera
    (or away from it, showing the back), tilted by up to 35 deg and rolled by up to 25 deg, so
    distance and obliquity vary from frame to frame. Visibility is judged with the nominal
    board and the cameras' pinhole part, so a seed gives the same poses with or without the
    imperfections of :class:`SynthParams`."""
    pinholes = [
        replace(c, intrinsics=replace(c.intrinsics, distortion=(0.0,) * 5, lens=OPENCV))
        if c.intrinsics.has_distortion
        else c
        for c in rig.cameras
    ]
    centre_b = np.array(
        [
            (board.panel[0] + board.panel[1]) / 2,
            (board.panel[2] + board.panel[3]) / 2,
            -board.thickness / 2,
        ]
    )
    if board.sheets:  # a multi-face target: its markers' centre
        centre_b = board.corners.reshape(-1, 3).mean(axis=0)
    poses: list[np.ndarray] = []
    attempts = 0
    while len(poses) < n_frames:
        attempts += 1
        if attempts > 2000 * n_frames:
            raise ConfigError(
                "could not place the board in view of two cameras; the board is "
                "too large or small for this layout"
            )
        c = rng.uniform(rig.workspace_lo, rig.workspace_hi)
        cam = rig.cameras[rng.integers(len(rig.cameras))]
        to_cam = cam.T_world_cam[:3, 3] - c
        to_cam /= np.linalg.norm(to_cam)
        if rng.random() < 0.5:
            to_cam = -to_cam  # show the back face to this camera's side
        tilt_axis = np.cross(to_cam, rng.normal(size=3))
        tilt_axis /= np.linalg.norm(tilt_axis)
        z_axis = rotvec_to_matrix(tilt_axis * np.radians(rng.uniform(0, 35))) @ to_cam
        up = np.array([0.0, 0.0, 1.0])
        x_axis = np.cross(up, z_axis)
        x_axis /= np.linalg.norm(x_axis)
        y_axis = np.cross(z_axis, x_axis)
        R = np.column_stack([x_axis, y_axis, z_axis])
        R = R @ rotvec_to_matrix([0, 0, np.radians(rng.uniform(-25, 25))])
        if board.sheets:  # turn a random face (not always the first) towards to_cam
            face = board.face_labels[rng.integers(len(board.face_labels))]
            R = R @ board.T_board_face(face)[:3, :3].T
        T_world_board = make_transform(R, c - R @ centre_b)
        seen = [marker_visibility(board, k, T_world_board) for k in pinholes]
        if sum(s >= min_markers for s in seen) >= min_cameras:
            poses.append(T_world_board)
    return poses


def _visible_corners(board: Board, cam: SynthCamera, T_cam_board: np.ndarray,
                     min_px: float = 12.0, max_angle_deg: float = 70.0) -> np.ndarray:
    """Pixels ``(N,4,2)`` of the markers ``cam`` sees whole (through its true lens), facing
    it (each face from its own side only: the others hide it) and at least ``min_px`` wide;
    through a distorting lens, points beyond the widest ray of the image are never counted
    (the lens polynomial may fold them back into it)."""
    K = cam.intrinsics
    r_max = np.inf
    if K.has_distortion:
        edge_u = np.array([0.0, K.width / 2, K.width - 1.0, 0.0, K.width - 1.0, 0.0,
                           K.width / 2, K.width - 1.0])
        edge_v = np.array([0.0, 0.0, 0.0, K.height / 2, K.height / 2, K.height - 1.0,
                           K.height - 1.0, K.height - 1.0])
        r_max = np.hypot(*K.rays(edge_u, edge_v)[:, :2].T).max()
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    out = []
    for face in board.face_labels:
        pts = board.corners[board.faces == face].reshape(-1, 3) @ R.T + t
        if np.any(pts[:, 2] < 0.2):
            continue
        centre = pts.mean(axis=0)
        if -((R @ board.face_normal(face)) @ centre) / np.linalg.norm(centre) < np.cos(
                np.radians(max_angle_deg)):
            continue
        inside_fov = (np.hypot(pts[:, 0], pts[:, 1]) / pts[:, 2] <= r_max).reshape(-1, 4)
        uv = K.project(pts).reshape(-1, 4, 2)
        inside = np.all((uv[..., 0] > 2) & (uv[..., 0] < K.width - 3) & (uv[..., 1] > 2)
                        & (uv[..., 1] < K.height - 3) & inside_fov, axis=1)
        size = np.linalg.norm(uv[:, 0] - uv[:, 1], axis=1)
        out.append(uv[inside & (size >= min_px)])
    return np.concatenate(out) if out else np.zeros((0, 4, 2))


def closeup_poses(rig: SynthRig, board: Board, per_camera: int, rng: np.random.Generator,
                  min_markers: int = 6, attempts: int = 200) -> list[tuple[str, np.ndarray]]:
    """``per_camera`` board poses ``T_world_board`` close to each camera, ``(camera, pose)``
    in camera order: what a user records to calibrate a lens, the board waved near the
    camera until it has filled the image out to its corners.

    Close-up ``k`` of a camera aims at :data:`CLOSEUP_TARGETS` ``[k % 8]`` (a corner of the
    image, then the middle of an edge), through the true lens (a user sees the real image;
    unlike the regular frames these poses change with ``--distortion``). A draw: the board's
    marker corner furthest out towards the target (in the camera frame) 0.3-0.8 m from the
    camera on the ray of a pixel 3-10 px inside the target (3-30 px from a corner on each
    axis: through a barrel lens the image's corner is an acute wedge of rays that a square
    marker does not reach into), the board facing the camera (either face, tilted up to 35
    deg, rolled up to 45 deg; 10 deg for a corner, which a board corner fits only about square
    to it). Of ``attempts`` draws the first whose visible markers
    (:func:`_visible_corners`, at least ``min_markers``) come within :data:`CLOSEUP_REACH` of
    the target is kept, else the one that came closest. Other cameras may see it too."""
    out = []
    for cam in rig.cameras:
        K = cam.intrinsics
        c0 = np.array([K.cx, K.cy])
        for k in range(per_camera):
            unit = np.array(CLOSEUP_TARGETS[k % len(CLOSEUP_TARGETS)], dtype=float)
            target = unit * [K.width - 1, K.height - 1]
            inward = np.sign(0.5 - unit)  # towards the image centre, per axis (0 along an edge)
            corner = bool(np.all(inward))
            # a board corner fits an image corner only about square to it, and not right into
            # it: through a barrel lens the image's corner is an acute wedge of rays
            roll_deg, inset_px = (10.0, 30.0) if corner else (45.0, 10.0)
            best, best_gap = None, np.inf
            for _ in range(attempts):
                pixel = target + inward * rng.uniform(3, inset_px, 2)
                ray = K.rays(pixel[:1], pixel[1:])[0]
                view = K.rays(*(c0 + 0.7 * (target - c0))[:, None])[0]  # the board's middle
                to_cam = -view / np.linalg.norm(view)  # board normal towards the camera
                face = FRONT if rng.random() < 0.5 else BACK
                z_axis = to_cam * face  # the back face towards it: the normal away
                tilt_axis = np.cross(z_axis, rng.normal(size=3))
                tilt_axis /= np.linalg.norm(tilt_axis)
                z_axis = rotvec_to_matrix(tilt_axis * np.radians(rng.uniform(0, 35))) @ z_axis
                x_axis = np.cross([0.0, -1.0, 0.0], z_axis)  # image up is -y
                x_axis /= np.linalg.norm(x_axis)
                R = np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])
                R = R @ rotvec_to_matrix([0, 0, np.radians(rng.uniform(-roll_deg, roll_deg))])
                corners = board.corners[board.faces == face].reshape(-1, 3)
                anchor = corners[np.argmax(corners @ R.T @ np.append(-inward, 0.0))]
                T_cam_board = make_transform(
                    R, ray / np.linalg.norm(ray) * rng.uniform(0.3, 0.8) - R @ anchor)
                seen = _visible_corners(board, cam, T_cam_board)
                if len(seen) < min_markers:
                    continue
                gap = np.linalg.norm(seen.reshape(-1, 2) - target, axis=1).min()
                if gap < best_gap:
                    best, best_gap = cam.T_world_cam @ T_cam_board, gap
                if gap < CLOSEUP_REACH * K.width:
                    break
            if best is None:
                raise ConfigError(f"--closeups: no board pose near {cam.name} shows "
                                  f"{min_markers} markers; the board is too large for its image")
            out.append((cam.name, best))
    return out
