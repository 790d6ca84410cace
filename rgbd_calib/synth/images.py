"""The images of one synthetic camera: the board as rectangles with its print
(:class:`_BoardModel`), the static scene (:func:`render_background`), the board rendered into
it with exact area coverage (:func:`render_board`; a moving board row by row under a rolling
shutter: :func:`render_board_moving`), then lens blur and sensor noise
(:func:`finish_color`) and the D435 depth model with the camera's depth errors
(:func:`finish_depth`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..core.camera import CameraIntrinsics
from ..core.depth_model import DepthModel, distort_depth_image
from ..core.geometry import invert_transform
from ..model.aprilgrid import corner_squares
from ..model.board import BACK, FRONT, Board, printed_markers
from .imperfections import BoardPrint
from .params import SynthCamera, SynthParams
from .scene import Rect, box, cast, pixel_rays, rect, shade_scene

LIGHT_DIR_WORLD = np.array([0.3, -0.4, 0.87]) / np.linalg.norm([0.3, -0.4, 0.87])
PAPER_WHITE, INK_BLACK, WOOD = 0.88, 0.07, 0.55
BODY_INSET_M = 1e-4  # a multi-face target's plates and body sit this far inside its sheets


def _moved(r: Rect, T: np.ndarray) -> Rect:
    """Rectangle ``r`` (given in a face frame) in the frame ``T`` maps that frame into."""
    R = T[:3, :3]
    return Rect(R @ r.origin + T[:3, 3], R @ r.u_axis, R @ r.v_axis, r.size_u, r.size_v,
                r.albedo, r.texture_seed, r.texture_cell_m)


@dataclass
class _BoardModel:
    """The board as six rectangles in the board frame plus marker look-up per face.

    ``printed`` (None: exactly the board file) is where the physical board's sheets and back
    face really are; the markers are looked up in board-file coordinates through its inverse,
    so a glued-off or scaled print stays as sharp as the nominal one."""

    board: Board
    printed: BoardPrint | None = None
    rects: list[Rect] = field(init=False)
    trees: dict[int, cKDTree] = field(init=False)
    cells: dict[int, np.ndarray] = field(init=False)
    ids: np.ndarray = field(init=False)  # the printed ArUco markers, corners and faces
    corners: np.ndarray = field(init=False)
    faces: np.ndarray = field(init=False)
    black_squares: np.ndarray | None = field(init=False)  # ChArUco, checkerboard: (rows, cols)
    ink: np.ndarray = field(init=False)  # black rectangles besides the markers (face, x0..y1)
    sheets: list[_BoardModel] = field(init=False, default_factory=list)  # multi-face: per face

    @property
    def thickness(self) -> float:
        return self.board.thickness if self.printed is None else self.printed.thickness_m

    def __post_init__(self) -> None:
        b = self.board
        if b.sheets:
            self._multiface()
            return
        x0, x1, y0, y1 = b.panel
        t = self.thickness
        w, h = x1 - x0, y1 - y0
        self.rects = [
            rect((x0, y0, 0), (w, 0, 0), (0, h, 0), (1, 1, 1), 0),  # front, normal +z
            rect((x0, y0, -t), (0, h, 0), (w, 0, 0), (1, 1, 1), 0),  # back, normal -z
            rect((x0, y0, -t), (w, 0, 0), (0, 0, t), (1, 1, 1), 0),  # bottom edge
            rect((x0, y1, -t), (0, 0, t), (w, 0, 0), (1, 1, 1), 0),  # top edge
            rect((x0, y0, -t), (0, 0, t), (0, h, 0), (1, 1, 1), 0),  # left edge
            rect((x1, y0, -t), (0, h, 0), (0, 0, t), (1, 1, 1), 0),  # right edge
        ]
        # the printed markers: the board's own, or a ChArUco board's ArUco markers (its
        # "markers" are saddle-corner quads, see board.CharucoSpec) and its black squares
        self.ids, self.corners, self.faces = printed_markers(b)
        self.black_squares = (None if b.pattern is None
                              else b.pattern.black_squares(b.dictionary))
        self.ink = corner_squares(b)
        self.trees = {
            f: cKDTree(self.corners[self.faces == f].mean(axis=1)[:, :2])
            for f in (FRONT, BACK)
            if np.any(self.faces == f)
        }
        self.cells = {int(i): b.marker_cells(int(i)) for i in self.ids}

    def _multiface(self) -> None:
        """A multi-face target: rectangle k < F is face k's sheet (its panel at the true face
        pose, its own single-face model giving the print), then each face's plate
        (``thickness`` behind its sheet) and the ``body`` box, both inset by
        :data:`BODY_INSET_M` so that no wood surface coincides with a printed one."""
        b = self.board
        poses = dict((self.printed.face_poses if self.printed is not None else None) or {})
        self.sheets = [_BoardModel(s.board) for s in b.sheets]
        sheets, plates = [], []
        e, t = BODY_INSET_M, b.thickness
        for s in b.sheets:
            T = poses.get(s.label, s.T_board_face)
            x0, x1, y0, y1 = s.board.panel
            sheets.append(_moved(rect((x0, y0, 0), (x1 - x0, 0, 0), (0, y1 - y0, 0),
                                      (1, 1, 1), 0), T))
            plates += [_moved(r, T) for r in box((x0 + e, y0 + e, -t), (x1 - e, y1 - e, -e),
                                                 (1, 1, 1), 0)]
        body = [] if b.body is None else box(np.add(b.body[0], e), np.subtract(b.body[1], e),
                                             (1, 1, 1), 0)
        self.rects = sheets + plates + body
        self.ids, self.corners, self.faces = printed_markers(b)
        self.black_squares, self.trees, self.cells = None, {}, {}
        self.ink = np.zeros((0, 5))

    def reflectance(self, hit_index: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Reflectance of board hits: ink, paper or the panel's edge."""
        out = np.full(hit_index.shape, WOOD)
        if self.sheets:  # a multi-face target: face k's print on rectangle k, wood elsewhere
            for k, sheet in enumerate(self.sheets):
                sel = np.nonzero(hit_index == k)[0]
                if sel.size:
                    out[sel] = sheet.reflectance(np.zeros(sel.size, int), a[sel], b[sel])
            return out
        x0, _, y0, _ = self.board.panel
        for rect_index, face in ((0, FRONT), (1, BACK)):
            sel = np.nonzero(hit_index == rect_index)[0]
            if sel.size == 0:
                continue
            out[sel] = PAPER_WHITE
            if face not in self.trees and self.black_squares is None:
                continue
            xy = (
                np.column_stack([x0 + a[sel], y0 + b[sel]])
                if face == FRONT
                else np.column_stack([x0 + b[sel], y0 + a[sel]])
            )
            if self.printed is not None and not self.printed.is_nominal:
                xy = self.printed.file_xy(face, xy)
            if self.black_squares is not None and face == FRONT:
                out[sel] = self._squares(xy)
            for _, u0, u1, v0, v1 in self.ink[self.ink[:, 0] == face]:
                out[sel[(xy[:, 0] >= u0) & (xy[:, 0] < u1) & (xy[:, 1] >= v0)
                        & (xy[:, 1] < v1)]] = INK_BLACK
            if face not in self.trees:
                continue
            ids = self.ids[self.faces == face]
            corners = self.corners[self.faces == face][:, :, :2]
            k = min(2, len(ids))
            _, cand = self.trees[face].query(xy, k=k)
            cand = cand.reshape(len(sel), k)
            spread = self.printed.ink_spread_m if self.printed is not None else 0.0
            grids = [self.cells[int(i)] for i in ids] if spread else []
            for j in range(k):
                c = corners[cand[:, j]]
                e1, e3 = c[:, 1] - c[:, 0], c[:, 3] - c[:, 0]
                d = xy - c[:, 0]
                u = np.einsum("ij,ij->i", d, e1) / np.einsum("ij,ij->i", e1, e1)
                v = np.einsum("ij,ij->i", d, e3) / np.einsum("ij,ij->i", e3, e3)
                if spread:
                    ink = _spread_ink(u, v, np.linalg.norm(e1, axis=1),
                                      np.linalg.norm(e3, axis=1), spread, cand[:, j],
                                      grids)
                    out[sel[ink >= 0]] = np.where(ink[ink >= 0] > 0, INK_BLACK, PAPER_WHITE)
                    continue
                inside = (u >= 0) & (u < 1) & (v >= 0) & (v < 1)
                for m in np.unique(cand[inside, j]):
                    pick = inside & (cand[:, j] == m)
                    cells = self.cells[int(ids[m])]
                    n = cells.shape[0]
                    val = cells[(v[pick] * n).astype(int), (u[pick] * n).astype(int)]
                    out[sel[pick]] = np.where(val > 127, PAPER_WHITE, INK_BLACK)
            spec = self.board.charuco
            if spec is not None and spec.inverted:  # white on black within the chessboard
                inv = sel[(xy[:, 0] >= 0) & (xy[:, 0] < spec.squares_x * spec.square_length)
                          & (xy[:, 1] >= 0) & (xy[:, 1] < spec.height)]
                out[inv] = PAPER_WHITE + INK_BLACK - out[inv]
        return out

    def _squares(self, xy: np.ndarray) -> np.ndarray:
        """Paper or ink of a ChArUco board's or checkerboard's chessboard at board-frame
        points ``(N,2)`` (m)."""
        spec = self.board.pattern
        sx, sy = spec.square_xy
        col = np.floor(xy[:, 0] / sx).astype(int)
        row = np.floor((spec.height - xy[:, 1]) / sy).astype(int)
        inside = (col >= 0) & (col < spec.squares_x) & (row >= 0) & (row < spec.squares_y)
        out = np.full(len(xy), PAPER_WHITE)
        black = np.zeros(len(xy), dtype=bool)
        black[inside] = self.black_squares[row[inside], col[inside]]
        out[black] = INK_BLACK
        return out


def _spread_ink(u: np.ndarray, v: np.ndarray, side_u: np.ndarray, side_v: np.ndarray,
                spread: float, marker: np.ndarray, cells: list[np.ndarray]) -> np.ndarray:
    """Per board point at ``(u, v)`` in its candidate ``marker``'s unit square (sides
    ``side_u`` / ``side_v`` m): 1 where the ink spread ``spread`` (m; negative: thinner) makes
    it ink, 0 paper, -1 not within the spread marker. Ink within ``|spread|`` of a black cell
    (a disc's reach, sampled on 8 directions); the marker's outline is black, so its outside
    within ``spread`` of the square is ink."""
    du, dv = abs(spread) / side_u, abs(spread) / side_v
    out = np.full(len(u), -1)
    near = (u >= -du) & (u < 1 + du) & (v >= -dv) & (v < 1 + dv)
    gap = np.hypot(np.maximum(np.maximum(-u, u - 1), 0) * side_u,
                   np.maximum(np.maximum(-v, v - 1), 0) * side_v)
    diag = np.sqrt(0.5)
    offsets = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1),
               (diag, diag), (diag, -diag), (-diag, diag), (-diag, -diag)]
    for m in np.unique(marker[near]):
        pick = np.nonzero(near & (marker == m))[0]
        grid = cells[int(m)]
        n = grid.shape[0]
        black = []
        for ou, ov in offsets:
            uu = np.clip(u[pick] + ou * du[pick], 0, 1 - 1e-9)
            vv = np.clip(v[pick] + ov * dv[pick], 0, 1 - 1e-9)
            black.append(grid[(vv * n).astype(int), (uu * n).astype(int)] <= 127)
        black = np.array(black)
        inside = gap[pick] == 0
        if spread > 0:  # ink where any sample within reach is black; outside: the outline's
            ink = np.where(inside, black.any(axis=0), gap[pick] <= spread)
        else:  # paper eats into the ink: black only where every sample within reach is,
            #   the outline's edge included
            inner = ((u[pick] >= du[pick]) & (u[pick] < 1 - du[pick])
                     & (v[pick] >= dv[pick]) & (v[pick] < 1 - dv[pick]))
            ink = inner & black.all(axis=0)
        keep = inside | (spread > 0)
        out[pick[keep]] = ink[keep].astype(int)
    return out


@dataclass
class _Background:
    color: np.ndarray  # HxWx3 float BGR [0,1]
    depth: np.ndarray  # HxW metres (inf: no surface)
    rays: np.ndarray | None = None  # HxWx3 pixel-centre rays of a distorted lens (z = 1)


def camera_rays(K: CameraIntrinsics, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """Camera-frame rays ``(N,3)`` with z = 1 through pixels ``(us, vs)`` of the true camera:
    the lens model's converged undistortion (:meth:`CameraIntrinsics.rays`), or the pinhole
    formula of earlier renders when the lens has no distortion (bit-identical images)."""
    return K.rays(us, vs) if K.has_distortion else pixel_rays(K.K, us, vs)


def _grid(K: CameraIntrinsics, shape: tuple[int, int]) -> tuple[int, int] | None:
    """:func:`cast`'s row/column culling needs rays whose x varies along columns only and y
    along rows only: true of a pinhole's pixel grid, not of a distorted one."""
    return None if K.has_distortion else shape


def render_background(scene: list[Rect], cam: SynthCamera, samples: int = 2) -> _Background:
    """Static scene seen by a camera: colour box-filtered over ``samples^2`` rays per pixel,
    depth (camera z of the hit, as an aligned D435 depth image stores it) at pixel centres."""
    K = cam.intrinsics
    T_cam_world = invert_transform(cam.T_world_cam)
    light = T_cam_world[:3, :3] @ LIGHT_DIR_WORLD
    vs, us = np.mgrid[0 : K.height, 0 : K.width].astype(float)
    grid = _grid(K, us.shape)
    color = np.zeros((K.height, K.width, 3))
    for i in range(samples):
        for j in range(samples):
            du, dv = (i + 0.5) / samples - 0.5, (j + 0.5) / samples - 0.5
            rays = camera_rays(K, (us + du).ravel(), (vs + dv).ravel())
            hits = cast(scene, T_cam_world, rays, grid=grid)
            color += shade_scene(scene, hits, light, T_cam_world).reshape(color.shape)
    rays = camera_rays(K, us.ravel(), vs.ravel())
    depth = cast(scene, T_cam_world, rays, grid=grid).depth.reshape(K.height, K.width)
    centre_rays = rays.reshape(K.height, K.width, 3) if K.has_distortion else None
    return _Background(color / samples**2, depth, centre_rays)


def _board_bbox(model: _BoardModel, K: CameraIntrinsics, T_cam_board: np.ndarray, rays=None,
                first_row: int = 0):
    """Pixel box ``(u0, u1, v0, v1)`` that holds the board's image, or None.

    Pinhole: the box of the projected panel corners. Distorted lens (its pixel-centre
    ``rays``, HxWx3): straight edges image as curves, so it is the box of the pixels whose
    ray falls in the ray-space box of the corners, 2 pixels wider (pixel corners and sub-pixel
    samples reach half a pixel beyond a centre); ``rays`` may be the image's rows from
    ``first_row`` on only."""
    x0, x1, y0, y1 = model.board.panel
    t = model.thickness
    pts = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (0.0, -t)])
    if model.sheets:  # a multi-face target: the corners of every rectangle
        pts = np.array([r.origin + i * r.size_u * r.u_axis + j * r.size_v * r.v_axis
                        for r in model.rects for i in (0, 1) for j in (0, 1)])
    pc = pts @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    if np.all(pc[:, 2] <= 0.01):
        return None
    if np.any(pc[:, 2] <= 0.01):
        return 0, K.width - 1, 0, K.height - 1
    if rays is not None:
        xy = pc[:, :2] / pc[:, 2:]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        inside = (
            (rays[..., 0] >= lo[0])
            & (rays[..., 0] <= hi[0])
            & (rays[..., 1] >= lo[1])
            & (rays[..., 1] <= hi[1])
        )
        rows, cols = np.nonzero(np.any(inside, axis=1))[0], np.nonzero(np.any(inside, axis=0))[0]
        rows = rows + first_row
        if rows.size == 0:
            return None
        return (
            max(cols[0] - 2, 0),
            min(cols[-1] + 2, K.width - 1),
            max(rows[0] - 2, 0),
            min(rows[-1] + 2, K.height - 1),
        )
    uv = K.project(pc)
    u0 = max(int(np.floor(uv[:, 0].min())) - 1, 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + 1, K.width - 1)
    v0 = max(int(np.floor(uv[:, 1].min())) - 1, 0)
    v1 = min(int(np.ceil(uv[:, 1].max())) + 1, K.height - 1)
    if u0 > u1 or v0 > v1:
        return None
    return u0, u1, v0, v1


def render_board(
    model: _BoardModel,
    cam: SynthCamera,
    bg: _Background,
    T_cam_board: np.ndarray,
    supersample: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free colour (HxWx3 float, BGR [0,1]) and depth (HxW metres) with the board.

    Exact area coverage: pixels whose four corners hit the same surface with the same
    reflectance are uniform; the rest are averaged over ``supersample^2`` rays. Every ray
    (pixel corner, centre or sub-pixel sample) comes from the true camera model
    (:func:`camera_rays`), so a distorted lens is rendered exactly, anti-aliasing included."""
    color = bg.color.copy()
    depth = bg.depth.copy()
    _paint_board(model, cam, bg, T_cam_board, supersample, color, depth)
    return color, depth


def render_board_moving(
    model: _BoardModel,
    cam: SynthCamera,
    bg: _Background,
    pose_at: Callable[[float], np.ndarray],
    offset_s: float,
    readout_s: float,
    supersample: int = 8,
    band_rows: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`render_board` of a board that moves: ``pose_at(tau)`` is ``T_cam_board`` at
    ``tau`` seconds after the frame set's nominal time (:mod:`.timing`).

    Depth is exposed as a whole at ``offset_s``. With a rolling shutter (``readout_s`` > 0)
    colour is rendered, not warped, band by band of ``band_rows`` rows (1: every row at its
    own time, the exact convention), each band with the board where it was at the time of its
    middle row, ``offset_s + readout_s / (H - 1) * (y - (H - 1) / 2)``; every ray of a row
    (pixel corners, centre, sub-pixel samples) sees that one board pose. The static scene does
    not move. A board that leaves the image (or passes behind the camera) during the readout is
    handled band by band as :func:`render_board` handles any view."""
    color = bg.color.copy()
    depth = bg.depth.copy()
    rolling = readout_s > 0
    _paint_board(model, cam, bg, pose_at(offset_s), supersample,
                 None if rolling else color, depth)
    if not rolling:
        return color, depth
    height = cam.intrinsics.height
    line_delay_s = readout_s / (height - 1)
    for r0 in range(0, height, band_rows):
        r1 = min(r0 + band_rows, height) - 1
        tau_s = offset_s + line_delay_s * ((r0 + r1) / 2 - (height - 1) / 2)
        _paint_board(model, cam, bg, pose_at(tau_s), supersample, color, None, rows=(r0, r1))
    return color, depth


def _band_bbox(model: _BoardModel, K: CameraIntrinsics, T_cam_board: np.ndarray, rays,
               rows: tuple[int, int] | None):
    """:func:`_board_bbox` within the image rows ``rows`` (inclusive; None: all). A distorted
    lens's ray box is searched only in those rows and two on each side (the box's margin)."""
    if rows is None:
        return _board_bbox(model, K, T_cam_board, rays)
    r0, r1 = rows
    first = 0
    if rays is not None:
        first = max(r0 - 2, 0)
        rays = rays[first : min(r1 + 2, K.height - 1) + 1]
    box_ = _board_bbox(model, K, T_cam_board, rays, first)
    if box_ is None:
        return None
    u0, u1, v0, v1 = box_
    v0, v1 = max(v0, r0), min(v1, r1)
    return None if v0 > v1 else (u0, u1, v0, v1)


def _paint_board(
    model: _BoardModel,
    cam: SynthCamera,
    bg: _Background,
    T_cam_board: np.ndarray,
    supersample: int,
    color: np.ndarray | None,
    depth: np.ndarray | None,
    rows: tuple[int, int] | None = None,
) -> None:
    """The board at ``T_cam_board`` painted over the static scene ``bg`` into ``color`` and
    ``depth`` (either None: not painted), in image rows ``rows`` only (inclusive; None: all)."""
    K = cam.intrinsics
    if K.has_distortion and bg.rays is None:
        raise ValueError("render_board: a distorted camera needs render_background's rays")
    box_ = _band_bbox(model, K, T_cam_board, bg.rays, rows)
    if box_ is None:
        return
    u0, u1, v0, v1 = box_
    region_depth_bg = bg.depth[v0 : v1 + 1, u0 : u1 + 1]
    # pixel-centre depth decides occlusion between the board and the static scene
    cvv, cuu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1].astype(float)
    centre_rays = None if bg.rays is None else bg.rays[v0 : v1 + 1, u0 : u1 + 1].reshape(-1, 3)
    if centre_rays is None:
        centre_rays = camera_rays(K, cuu.ravel(), cvv.ravel())
    hits_p = cast(model.rects, T_cam_board, centre_rays, grid=_grid(K, cuu.shape))
    z_board = hits_p.depth.reshape(cvv.shape)
    board_front = z_board < region_depth_bg
    if depth is not None:
        depth[v0 : v1 + 1, u0 : u1 + 1] = np.where(board_front, z_board, region_depth_bg)
    if color is not None:
        color[v0 : v1 + 1, u0 : u1 + 1] = _board_colors(
            model, cam, bg, T_cam_board, supersample, (u0, u1, v0, v1), board_front)


def _board_colors(model: _BoardModel, cam: SynthCamera, bg: _Background,
                  T_cam_board: np.ndarray, supersample: int, box_: tuple[int, int, int, int],
                  board_front: np.ndarray) -> np.ndarray:
    """Colour of the pixel box ``box_`` (``u0, u1, v0, v1``, inclusive) with the board in front
    of the static scene where ``board_front``: uniform pixels from their corner rays, the rest
    averaged over ``supersample^2`` rays."""
    K = cam.intrinsics
    u0, u1, v0, v1 = box_
    light = T_cam_board[:3, :3].T @ (invert_transform(cam.T_world_cam)[:3, :3] @ LIGHT_DIR_WORLD)
    face_shade = np.array([0.55 + 0.45 * abs(r.normal @ light) for r in model.rects])

    def trace(us: np.ndarray, vs: np.ndarray, grid=None):
        hits = cast(model.rects, T_cam_board, camera_rays(K, us, vs),
                    grid=None if grid is None else _grid(K, grid))
        refl = model.reflectance(hits.index, hits.a, hits.b)
        value = np.where(hits.index >= 0, refl * face_shade[np.maximum(hits.index, 0)], np.nan)
        return hits, value

    cv_, cu_ = np.mgrid[v0 : v1 + 2, u0 : u1 + 2].astype(float) - 0.5
    hits_c, val_c = trace(cu_.ravel(), cv_.ravel(), grid=cu_.shape)
    key = np.where(hits_c.index >= 0, hits_c.index * 10 + (val_c * 8).round(), -1)
    key = key.reshape(cv_.shape)
    val_c = val_c.reshape(cv_.shape)
    same = (
        (key[:-1, :-1] == key[1:, :-1])
        & (key[:-1, :-1] == key[:-1, 1:])
        & (key[:-1, :-1] == key[1:, 1:])
    )
    region_bg = bg.color[v0 : v1 + 1, u0 : u1 + 1]
    region_depth_bg = bg.depth[v0 : v1 + 1, u0 : u1 + 1]
    uniform_board = same & (key[:-1, :-1] >= 0) & board_front
    out = region_bg.copy()
    out[uniform_board] = val_c[:-1, :-1][uniform_board][:, None]
    mixed = ~same
    if np.any(mixed):
        mv, mu = np.nonzero(mixed)
        s = supersample
        offs = (np.arange(s) + 0.5) / s - 0.5
        ov, ou = np.meshgrid(offs, offs, indexing="ij")
        us = (mu[:, None] + u0 + ou.ravel()[None]).ravel()
        vs = (mv[:, None] + v0 + ov.ravel()[None]).ravel()
        hits_s, val_s = trace(us, vs)
        zbg = np.repeat(region_depth_bg[mv, mu], s * s)
        vis = (hits_s.index >= 0) & (hits_s.depth < zbg)
        bgc = np.repeat(region_bg[mv, mu], s * s, axis=0)
        samp = np.where(vis[:, None], val_s[:, None], bgc)
        out[mv, mu] = samp.reshape(-1, s * s, 3).mean(axis=1)
    return out


def finish_color(color: np.ndarray, params: SynthParams, rng: np.random.Generator) -> np.ndarray:
    """Lens blur, sensor noise and 8-bit quantisation."""
    img = color * 255.0
    if params.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), params.blur_sigma_px)
    if params.color_noise_dn > 0:
        img = img + rng.normal(0.0, params.color_noise_dn, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def finish_depth(
    depth_m: np.ndarray, cam: SynthCamera, params: SynthParams, rng: np.random.Generator
) -> np.ndarray:
    """D435 depth of the true depth image ``depth_m`` (m, HxW; inf: no surface): the camera's
    depth errors, noise, range limits, dropout and 16-bit counts.

    The camera's :attr:`SynthCamera.depth_model` but its scale moves the true depth ``z`` to
    ``z'`` (:func:`_depth_errors`); the noise ``sigma_z = z^2 s / (f B)`` of the true ``z`` of
    the surface each pixel sees is added and the sum scaled by the model's scale
    (``depth_scale_bias``), so a pixel reports ``measured_depth(z) + scale sigma_z n`` (the RMS
    error of Intel's D400 "Tuning depth cameras for best performance" white paper; the errors:
    :mod:`rgbd_calib.core.depth_model`). Without depth errors beyond the scale the image is the
    one of before they existed, bit for bit."""
    K = cam.intrinsics
    z = np.where(np.isfinite(depth_m), depth_m, 0.0)
    z, z_seen = _depth_errors(z, cam)
    sigma = z_seen**2 * params.depth_subpixel_px / (K.fx * params.depth_baseline_m)
    z = (z + rng.normal(0.0, 1.0, z.shape) * sigma) * cam.depth_scale_bias
    valid = (z >= params.depth_min_m) & (z <= params.depth_max_m)
    valid &= rng.random(z.shape) >= params.depth_dropout
    counts = np.where(valid, np.rint(z / K.depth_scale), 0)
    return np.clip(counts, 0, 65535).astype(np.uint16)


POSE_PARAMETERS = ("rx", "ry", "rz", "tx", "ty", "tz")


def _depth_errors(z_m: np.ndarray, cam: SynthCamera) -> tuple[np.ndarray, np.ndarray]:
    """``(z', z_seen)``: what the camera reports for the true depth image ``z_m`` (m, 0: no
    surface) by its depth model without the scale (:func:`distort_depth_image`), and the true
    depth of the surface each pixel sees (``z_m`` moved by the pose error alone, which the
    noise follows). A camera without depth errors beyond the scale: ``(z_m, z_m)``, untouched.
    """
    model = cam.depth_model
    if model is None or model.with_values({"scale": 1.0}).is_identity:
        return z_m, z_m
    values = {p: model.value(p) for p in model.values if p != "scale"}
    pose = {p: v for p, v in values.items() if p in POSE_PARAMETERS}
    disparity = {p: v for p, v in values.items() if p not in POSE_PARAMETERS}
    bare = DepthModel(focal_baseline_px_m=model.focal_baseline_px_m)
    K = cam.intrinsics
    # the two calls compose exactly to distort_depth_image(model without scale): warp, then
    # measured_depth of the warped image
    z_seen = distort_depth_image(bare.with_values(pose), z_m, K) if pose else z_m
    z = distort_depth_image(bare.with_values(disparity), z_seen, K) if disparity else z_seen
    return z, np.where(z > 0, z_seen, 0.0)  # no depth reported: no noise either
