"""Real-world imperfections of a synthetic rig (docs/synthetic.md): the cameras' true lens
distortion and the intrinsics ``rig.yaml`` lists instead of the truth, each camera's depth
errors (:func:`true_depth_model`), cameras knocked after the calibration (``--bump``), and
the physical board against its board file (:class:`BoardPrint`:
a back sheet glued off its place, a thicker or thinner panel, a print at the wrong scale, the
faces of a hand-built multi-face target off their poses). Each draws from its own seeded
stream, so the rig, the board motion and the noise stay those of the same seed without it."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.depth_model import PARAMETERS, TERMS, DepthModel
from ..core.errors import ConfigError
from ..core.geometry import invert_transform, make_transform, rotvec_to_matrix, transform_points
from ..model.board import BACK, Board
from .params import SynthCamera, SynthParams, check_params

IMPERFECTION_STREAM = 0x5EED1  # rng stream of the rig.yaml intrinsics errors (seed, stream)
BUMP_STREAM = 0xB0A7  # rng stream of the knocks of --bump (seed, stream, camera index)
DEPTH_MODEL_STREAM = 0xDE9E  # rng stream of the cameras' depth errors (seed, stream)
# the depth-model parameters drawn per camera, in the columns of depth_error_draws
DRAWN = tuple(p for p in PARAMETERS if p != "scale")


def camera_imperfections(
    cameras: list[SynthCamera], seed: int, params: SynthParams
) -> list[SynthCamera]:
    """True lens distortion and the intrinsics ``rig.yaml`` lists instead of the truth.

    The true distortion is ``params.distortion`` for every camera. ``rig.yaml`` lists it or
    zeros (``rig_distortion``), and focal lengths scaled by one factor ``1 + e`` (fx and fy
    together: a focal error keeps the aspect ratio), ``e`` uniform in +-F % , and ``cx``, ``cy``
    each shifted by a uniform +-PX pixels. The errors come from their own seeded stream (three
    unit draws per camera), so the rig, the board motion and the noise stay those of the same
    seed without them."""
    check_params(params)
    f_pct, px = params.intrinsics_error
    unit = np.random.default_rng([seed, IMPERFECTION_STREAM]).uniform(-1, 1, (len(cameras), 3))
    out = []
    for cam, (e_f, e_cx, e_cy) in zip(cameras, unit):
        truth = cam.intrinsics
        if params.distortion is not None:
            truth = replace(truth, distortion=tuple(float(d) for d in params.distortion),
                            lens=params.lens)
        listed = truth
        if truth.has_distortion and params.rig_distortion == "zeros":
            listed = replace(listed, distortion=(0.0,) * len(truth.distortion))
        if f_pct > 0 or px > 0:
            scale = 1.0 + e_f * f_pct / 100.0
            listed = replace(
                listed,
                fx=truth.fx * scale,
                fy=truth.fy * scale,
                cx=truth.cx + e_cx * px,
                cy=truth.cy + e_cy * px,
            )
        if truth.has_distortion:
            check_distortion(truth)
        out.append(
            replace(cam, intrinsics=truth, listed_intrinsics=None if listed is truth else listed)
        )
    return out


def depth_error_draws(seed: int, n_cameras: int) -> np.ndarray:
    """Unit draws ``(n_cameras, 12)``, uniform in +-1, of the cameras' depth errors (columns:
    :data:`DRAWN`, ``d0 .. tz``), from their own seeded stream: the rig, the board motion and
    the noise stay those of the same seed without them, and a larger setting is the same
    error scaled up."""
    return np.random.default_rng([seed, DEPTH_MODEL_STREAM]).uniform(-1, 1, (n_cameras,
                                                                          len(DRAWN)))


def true_depth_model(intr: CameraIntrinsics, scale: float, unit: np.ndarray,
                     params: SynthParams) -> DepthModel:
    """A camera's true :class:`DepthModel`: ``scale`` (its ``depth_scale_bias``), ``d0`` and
    ``dx .. dyy`` the unit draws ``unit`` (one row of :func:`depth_error_draws`) times
    ``depth_disparity_offset_px`` and ``depth_disparity_field_px``, ``rx ry rz`` (deg) and
    ``tx ty tz`` (mm) times ``depth_pose_error``; ``f B`` is the noise model's, ``fx`` times
    ``depth_baseline_m``. ``terms`` lists the terms with a non-zero parameter."""
    deg, mm = params.depth_pose_error
    half_width = {"d0": params.depth_disparity_offset_px,
                  **dict.fromkeys(("dx", "dy", "dxx", "dxy", "dyy"),
                                  params.depth_disparity_field_px),
                  **dict.fromkeys(("rx", "ry", "rz"), deg),
                  **dict.fromkeys(("tx", "ty", "tz"), mm)}
    values = {"scale": float(scale)}
    values.update({p: float(u) * half_width[p] for p, u in zip(DRAWN, unit) if half_width[p]})
    default = {p: 1.0 if p == "scale" else 0.0 for p in PARAMETERS}
    terms = tuple(t for t, names in TERMS.items()
                  if any(values.get(p, default[p]) != default[p] for p in names))
    return DepthModel(focal_baseline_px_m=float(intr.fx) * params.depth_baseline_m,
                      values=values, terms=terms)


def bump_transform(seed: int, index: int, mm: float, deg: float) -> np.ndarray:
    """The knock ``T_cam_cam'`` of camera number ``index``: a turn of ``deg`` about a seeded
    random axis through the optical centre and a shift of ``mm`` along a seeded random
    direction (camera frame), from its own stream so the rest of the seed's rig stays."""
    rng = np.random.default_rng([seed, BUMP_STREAM, index])
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction /= np.linalg.norm(direction)
    return make_transform(rotvec_to_matrix(axis * np.radians(deg)), direction * mm / 1000.0)


def bump_cameras(cameras: list[SynthCamera], seed: int,
                 bump: tuple[tuple[str, float, float], ...]) -> list[SynthCamera]:
    """Cameras moved after the calibration (``--bump NAME MM DEG``): the same rig as the seed's
    without it, but the named cameras' poses knocked by :func:`bump_transform`."""
    names = [c.name for c in cameras]
    knocks = {}
    for name, mm, deg in bump:
        if name not in names:
            raise ConfigError(f"--bump {name}: no such camera; this layout has "
                              f"{', '.join(names)}")
        knocks[name] = bump_transform(seed, names.index(name), mm, deg)
    return [replace(c, T_world_cam=c.T_world_cam @ knocks[c.name]) if c.name in knocks else c
            for c in cameras]


def check_distortion(K: CameraIntrinsics, step_px: int = 8) -> None:
    """The lens model must map the image one-to-one (no fold inside it), or the per-pixel
    rays are not the truth: every pixel's ray projects back onto it and the model's Jacobian
    keeps its orientation."""
    u = np.append(np.arange(-0.5, K.width - 0.5, step_px), K.width - 0.5)
    v = np.append(np.arange(-0.5, K.height - 0.5, step_px), K.height - 0.5)
    uu, vv = (a.ravel() for a in np.meshgrid(u, v))
    rays = K.rays(uu, vv)
    uv, J = K.project_jacobian(rays)
    round_trip_px = np.max(np.abs(uv - np.column_stack([uu, vv])))
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    if not (round_trip_px < 1e-6 and np.all(det > 0)):
        raise ConfigError(
            f"--distortion {list(K.distortion)}: the lens model folds over inside the "
            f"{K.width}x{K.height} image; give smaller coefficients"
        )


@dataclass(frozen=True)
class BoardPrint:
    """The physical board against its board file (which stays nominal).

    In the board frame (metres): a front-face corner ``p`` of the board file is really at
    ``diag(S, S, 1) p`` and a back-face corner at ``T_front_back diag(S, S, 1) p``, with ``S``
    the print scale. ``T_front_back`` maps the (scaled) board-file position of a back-sheet
    point to where the back sheet really is: a rotation by ``rot`` about the board normal
    (+z, counter-clockwise seen from the front) through the centre of the printed back-marker
    grid, then the in-plane shift ``(dx, dy)`` and ``-(thickness_m - board.thickness)`` along
    z. The panel is ``thickness_m`` thick (its back face at ``z = -thickness_m``)."""

    thickness_m: float
    print_scale: float = 1.0
    T_front_back: np.ndarray = field(default_factory=lambda: np.eye(4))
    # a multi-face target: the true pose T_board_face of each face (label -> 4x4, metres);
    # empty: every face where the board file puts it
    face_poses: dict[int, np.ndarray] = field(default_factory=dict)
    # how far the ink spreads beyond the file's black edges (m, on the board; the markers'
    # corners stay where :meth:`corners` puts them: the print, not the geometry, is off)
    ink_spread_m: float = 0.0

    @property
    def is_nominal(self) -> bool:
        return self.print_scale == 1.0 and bool(np.all(self.T_front_back == np.eye(4)))

    def corners(self, board: Board) -> np.ndarray:
        """True board-frame corners ``(M,4,3)`` (metres) of the board file's markers."""
        if board.sheets:
            out = board.corners.copy()
            for f, T_true in self.face_poses.items():
                sel = board.faces == f
                T = T_true @ invert_transform(board.T_board_face(f))
                out[sel] = transform_points(T, out[sel].reshape(-1, 3)).reshape(-1, 4, 3)
            return out
        scaled = board.corners * np.array([self.print_scale, self.print_scale, 1.0])
        back = board.faces == BACK
        scaled[back] = transform_points(self.T_front_back, scaled[back].reshape(-1, 3)).reshape(
            -1, 4, 3
        )
        return scaled

    def file_xy(self, face: int, xy: np.ndarray) -> np.ndarray:
        """Board-file coordinates ``(N,2)`` of points ``xy`` (board frame, metres) on the true
        ``face``: the inverse of :meth:`corners`, for the texture look-up."""
        if face == BACK:
            T_back_front = invert_transform(self.T_front_back)
            xy = xy @ T_back_front[:2, :2].T + T_back_front[:2, 3]
        return xy / self.print_scale


def face_perturbation(label: int, mm: float, deg: float) -> np.ndarray:
    """The error ``Delta`` (4x4, face frame) of face ``label`` of a hand-built target: a shift
    of ``mm`` and a turn of ``deg`` about axes drawn from a stream seeded by the label (the true
    face pose is ``T_board_face @ Delta``)."""
    rng = np.random.default_rng([16, int(label) % 2**31])
    axis_t, axis_r = rng.normal(size=3), rng.normal(size=3)
    t = axis_t / np.linalg.norm(axis_t) * mm / 1000.0
    w = axis_r / np.linalg.norm(axis_r) * np.radians(deg)
    return make_transform(rotvec_to_matrix(w), t)


def board_print(board: Board, params: SynthParams) -> BoardPrint:
    """The :class:`BoardPrint` of ``params.glue``, ``thickness_error_mm``, ``print_scale`` and
    ``ink_spread_mm`` (a double-sided board), or of ``params.face_error`` (a multi-face
    target)."""
    printed = _board_print(board, params)
    if params.ink_spread_mm == 0:
        return printed
    if board.sheets or board.pattern is not None:
        raise ConfigError("--ink-spread renders an ArUco board's markers; this board is "
                          f"{board.board_type}: leave --ink-spread out")
    return replace(printed, ink_spread_m=params.ink_spread_mm / 1000.0)


def _board_print(board: Board, params: SynthParams) -> BoardPrint:
    if board.sheets:
        if (tuple(params.glue) != (0, 0, 0) or params.thickness_error_mm != 0
                or params.print_scale != 1.0):
            raise ConfigError("--glue, --thickness-error and --print-scale describe a "
                              "double-sided board; for a multi-face target use --face-error")
        mm, deg = params.face_error
        if (mm, deg) == (0, 0):
            return BoardPrint(board.thickness)
        return BoardPrint(board.thickness, face_poses={
            s.label: s.T_board_face @ face_perturbation(s.label, mm, deg)
            for s in board.sheets if s.label != board.reference_face})
    if tuple(params.face_error) != (0, 0):
        raise ConfigError("--face-error moves the faces of a multi-face target; for a "
                          "double-sided board use --glue / --thickness-error")
    scale = float(params.print_scale)
    dx_mm, dy_mm, rot_deg = params.glue
    thickness_m = board.thickness + params.thickness_error_mm / 1000.0
    if not thickness_m > 0:
        raise ConfigError(
            f"--thickness-error {params.thickness_error_mm}: the board would be "
            f"{thickness_m * 1000:g} mm thick; give a smaller error"
        )
    if (dx_mm, dy_mm, rot_deg, params.thickness_error_mm) == (0, 0, 0, 0):
        return BoardPrint(thickness_m, scale)
    back = board.corners[board.faces == BACK].reshape(-1, 3)
    if len(back):
        centre_xy = scale * (back[:, :2].min(axis=0) + back[:, :2].max(axis=0)) / 2
    else:
        x0, x1, y0, y1 = board.panel
        centre_xy = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    R = rotvec_to_matrix([0.0, 0.0, np.radians(rot_deg)])
    centre = np.array([centre_xy[0], centre_xy[1], 0.0])
    shift = np.array([dx_mm / 1000.0, dy_mm / 1000.0, board.thickness - thickness_m])
    return BoardPrint(thickness_m, scale, make_transform(R, centre - R @ centre + shift))
