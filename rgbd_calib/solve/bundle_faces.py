"""The board self-calibration's models: the back sheet's pose (:class:`BoardModel`) and a
multi-face target's faces (:class:`FaceModel`), which of them the bundle adjustment can
estimate (or why each is held) and their priors; which cameras, views and faces the graph
connects to the reference. Used by :mod:`rgbd_calib.solve.bundle`."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from ..core.config import BundleConfig
from ..core.geometry import invert_transform, matrix_to_rotvec, skew, transform_points


@dataclass(frozen=True)
class BoardModel:
    """The back sheet's pose relative to the front sheet as the bundle adjustment estimated it.

    ``T_front_back`` (4x4, metres, board frame) maps a back-face point of the board file to
    where the back sheet really is (the convention of ``ground_truth.yaml``, docs/synthetic.md);
    ``covariance`` is its 6x6 marginal ``[rot rad, trans m]`` for the right perturbation
    ``T_front_back @ Exp(xi)``; ``centre`` the board-file centre of the back-marker grid (m),
    about which the offset is reported. ``held`` names why it was not estimated (identity then).
    """

    T_front_back: np.ndarray
    covariance: np.ndarray
    centre: np.ndarray
    thickness_m: float  # the board file's
    held: str = ""

    @property
    def offset_mm(self) -> np.ndarray:
        """Shift (dx, dy, dz) mm of the back-grid centre: ``T_front_back c - c``."""
        c = self.centre
        return (self.T_front_back[:3, :3] @ c + self.T_front_back[:3, 3] - c) * 1000.0

    @property
    def rotation_deg(self) -> float:
        """Rotation of the back sheet about the board normal (+z, counter-clockwise seen from
        the front), degrees."""
        R = self.T_front_back[:3, :3]
        return float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))

    @property
    def thickness_mm(self) -> float:
        """The estimated thickness: the board file's minus the back sheet's z shift."""
        return (self.thickness_m - float(self.offset_mm[2]) / 1000.0) * 1000.0

    @property
    def sigmas(self) -> dict[str, float]:
        """Marginal 1-sigmas: offset x, y and thickness (mm) at the centre, rotation (deg).

        d(T c) = R [-[c]x, I] xi for the right perturbation xi = [w, v]."""
        R = self.T_front_back[:3, :3]
        c = self.centre
        J = np.zeros((4, 6))
        J[:3, :3] = -R @ skew(c)
        J[:3, 3:] = R
        J[3, 2] = 1.0  # rotation about z (small tilts held)
        s = np.sqrt(np.maximum(np.diag(J @ self.covariance @ J.T), 0.0))
        return {"offset_x_mm": float(s[0] * 1000), "offset_y_mm": float(s[1] * 1000),
                "thickness_mm": float(s[2] * 1000), "rotation_deg": float(np.degrees(s[3]))}


@dataclass(frozen=True)
class FaceModel:
    """A multi-face target's face as the bundle adjustment estimated it (board
    self-calibration): the face's true pose is ``T_board_face = T_nominal @ Delta``, ``Delta``
    (4x4, metres, in the nominal face frame: x, y in the sheet, z its outward normal) the
    correction, ``covariance`` its 6x6 marginal ``[rot rad, trans m]`` for the right
    perturbation ``Delta @ Exp(xi)`` (face frame), ``centre`` the face-frame centre of its
    markers, about which the shift is reported. ``held`` names why it was not estimated."""

    label: int
    T_nominal: np.ndarray
    Delta: np.ndarray
    covariance: np.ndarray
    centre: np.ndarray
    held: str = ""

    @property
    def T_board_face(self) -> np.ndarray:
        return self.T_nominal @ self.Delta

    @property
    def offset_mm(self) -> np.ndarray:
        """Shift (x, y along the sheet, z along the normal; mm) of the markers' centre."""
        c = self.centre
        return (self.Delta[:3, :3] @ c + self.Delta[:3, 3] - c) * 1000.0

    @property
    def rotation_deg(self) -> np.ndarray:
        """Turn as a rotation vector (degrees; x, y tilts, z about the normal)."""
        return np.degrees(matrix_to_rotvec(self.Delta[:3, :3]))

    @property
    def sigmas(self) -> dict[str, list[float]]:
        """Marginal 1-sigmas of the centre's shift (mm, face x, y, z) and of the turn (deg,
        about face x, y, z): d(Delta c) = R [-[c]x, I] xi."""
        R, c = self.Delta[:3, :3], self.centre
        J = np.zeros((6, 6))
        J[:3, :3] = -R @ skew(c)
        J[:3, 3:] = R
        J[3:, :3] = np.eye(3)
        s = np.sqrt(np.maximum(np.diag(J @ self.covariance @ J.T), 0.0))
        return {"offset_mm": (s[:3] * 1000).tolist(), "rotation_deg": np.degrees(s[3:]).tolist()}

    def to_dict(self) -> dict[str, Any]:
        held = bool(self.held)
        return {"face": int(self.label), "held": self.held or None,
                "offset_mm": None if held else self.offset_mm.tolist(),
                "rotation_deg": None if held else self.rotation_deg.tolist(),
                "sigmas": None if held else self.sigmas,
                "T_board_face": self.T_board_face.tolist()}


BOARD_TILT_SIGMA_RAD = 1e-6  # a sheet glued flat on the panel does not tilt: held


def board_prior_sigmas(config: BundleConfig) -> np.ndarray:
    """Prior sigmas of ``T_front_back`` in GTSAM's order ``[rx, ry, rz, tx, ty, tz]``."""
    prior = config.board_prior
    return np.array([BOARD_TILT_SIGMA_RAD, BOARD_TILT_SIGMA_RAD,
                     np.radians(prior.board_prior_rotation_deg),
                     prior.board_prior_offset_mm / 1000.0, prior.board_prior_offset_mm / 1000.0,
                     prior.board_prior_thickness_mm / 1000.0])


def face_prior_sigmas(config: BundleConfig) -> np.ndarray:
    """Prior sigmas of a multi-face target's face correction ``Delta`` (face frame, GTSAM's
    order ``[rx, ry, rz, tx, ty, tz]``)."""
    r = np.radians(config.board_prior.board_prior_face_rotation_deg)
    t = config.board_prior.board_prior_face_offset_mm / 1000.0
    return np.array([r, r, r, t, t, t])


def union_find():
    """``(find, union)`` of a disjoint-set forest over hashable items (path halving): the
    connected parts of a graph given edge by edge."""
    parent: dict = {}

    def find(x):
        parent.setdefault(x, x)
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    def union(a, b) -> None:
        parent[find(a)] = find(b)

    return find, union


def reference_component(active: list, values: gtsam.Values,
                        cam_key: dict, view_key: dict, fixed: set[str],
                        relative_poses, reference: str, intr_key: dict | None = None):
    """Keep the measurements and values connected to the reference camera (a camera or view
    cut off from it has no determined pose: its marginals would be singular); ``intr_key``
    (camera -> intrinsics vector key) keeps the intrinsics of the kept cameras."""
    find, union = union_find()
    for camera, view in dict.fromkeys((m.camera, m.view) for m in active):
        union("c:" + camera, "v:" + view)
    for r in relative_poses:
        union("c:" + r.cam_a, "c:" + r.cam_b)
    for c in fixed:  # fixed cameras are tied to the reference frame by their priors
        union("c:" + c, "c:" + reference)
    root = find("c:" + reference)
    cameras = {c for c in cam_key if find("c:" + c) == root}
    kept = [m for m in active if m.camera in cameras]
    sub = gtsam.Values()
    for c, k in cam_key.items():
        if values.exists(k) and find("c:" + c) == root:
            sub.insert(k, values.atPose3(k))
    for v, k in view_key.items():
        if values.exists(k) and find("v:" + v) == root:
            sub.insert(k, values.atPose3(k))
    for c, k in (intr_key or {}).items():
        if values.exists(k) and find("c:" + c) == root:
            sub.insert(k, values.atVector(k))
    return kept, sub


def face_models_setup(measurements: list, config: BundleConfig,
                       face_frames: dict[int, np.ndarray] | None) -> tuple[FaceModel, ...]:
    """The faces of a multi-face target to estimate (``held`` empty) or why each is held;
    empty for a double-sided board or with ``config.board`` fixed. A face's pose is
    observable when it is tied to the reference face (the one not in ``face_frames``)
    through views that see two faces at once."""
    if config.board != "refine" or not face_frames:
        return ()
    find, union = union_find()
    faces_of: dict[str, set[int]] = defaultdict(set)
    points: dict[int, list[np.ndarray]] = defaultdict(list)
    for m in measurements:
        faces_of[m.view].add(m.face)
        points[m.face].append(m.object_points)
    for seen in faces_of.values():
        first, *rest = sorted(seen)
        for f in rest:
            union(f, first)
    reference = [f for f in {m.face for m in measurements} if f not in face_frames]
    ref_root = find(reference[0]) if reference else None
    out = []
    for label, T in sorted(face_frames.items()):
        centre = np.zeros(3)
        if points[label]:
            P = transform_points(invert_transform(T), np.concatenate(points[label]).reshape(-1, 3))
            centre = np.r_[(P[:, :2].min(axis=0) + P[:, :2].max(axis=0)) / 2, 0.0]
        held = ""
        if not points[label]:
            held = f"face {label} was never seen: its pose is held at the board file"
        elif ref_root is None or find(label) != ref_root:
            held = (f"no view sees face {label} together with a face tied to the reference "
                    "face: its pose is unobservable, held at the board file")
        out.append(FaceModel(label, np.asarray(T, float), np.eye(4), np.zeros((6, 6)), centre,
                             held))
    return tuple(out)


def board_model_setup(measurements: list, config: BundleConfig,
                       back_centre: np.ndarray | None) -> BoardModel | None:
    """The back-sheet model to estimate (``held`` empty) or the reason it is held; None when
    ``config.board`` is fixed."""
    if config.board != "refine":
        return None
    back = [m.object_points for m in measurements if m.face < 0]
    if not back:
        return BoardModel(np.eye(4), np.zeros((6, 6)), np.zeros(3), 0.0,
                          "the back face was never seen: the back sheet's pose is "
                          "unobservable, held at the board file")
    P = np.concatenate(back).reshape(-1, 3)
    thickness_m = float(-np.mean(P[:, 2]))
    if back_centre is None:
        back_centre = np.r_[(P[:, :2].min(axis=0) + P[:, :2].max(axis=0)) / 2, -thickness_m]
    faces_of: dict[str, set[int]] = defaultdict(set)
    for m in measurements:
        faces_of[m.view].add(m.face)
    held = ""
    if not any(len(f) == 2 for f in faces_of.values()):
        held = ("no board view has both faces seen at once (by different cameras): the back "
                "sheet's pose is unobservable, held at the board file")
    return BoardModel(np.eye(4), np.zeros((6, 6)), np.asarray(back_centre, float),
                      thickness_m, held)
