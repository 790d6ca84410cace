"""The synthetic renderer's real-world imperfections are rendered exactly and recorded.

Lens distortion (every pixel and sub-pixel ray from the true model), rig.yaml intrinsics that
lie, a glued-off back sheet, a thicker panel and a mis-scaled print: the images must show
exactly what ``ground_truth.yaml`` says, and the defaults must render as before.
"""

from dataclasses import replace

import cv2
import numpy as np
import pytest
import yaml
from conftest import REPO

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.errors import ConfigError
from rgbd_calib.core.geometry import (
    invert_transform,
    make_transform,
    rotvec_to_matrix,
    transform_points,
)
from rgbd_calib.model.board import BACK, FRONT, board_from_grid, thesis_board
from rgbd_calib.model.board_file import load_board
from rgbd_calib.model.rig import load_rig
from rgbd_calib.synth.render import (
    CLOSEUP_TARGETS,
    LIGHT_DIR_WORLD,
    SynthCamera,
    SynthParams,
    _BoardModel,
    board_print,
    camera_rays,
    finish_color,
    finish_depth,
    load_ground_truth,
    make_rig,
    render_background,
    render_board,
    synthesize,
)
from rgbd_calib.synth.scene import cast

# A strong barrel lens (test_camera.py's "strong-barrel"): ~40 px at the image border here.
BARREL = (-0.3, 0.1, 5e-4, 2e-4, -0.01)
# cv2.aruco with sub-pixel corner refinement on noise-free renders: measured median
# 0.23-0.24 px on pinhole renders (the detector's own error) and 0.24-0.27 px on these
# distorted ones, so the render is exact to the detector's precision.
CORNER_MEDIAN_PX = 0.3
PINHOLE_OFF_BORDER_PX = 10.0  # a pinhole projection misses border corners by more than this
PLANE_EXACT_M = 1e-9  # raw rendered depth back-projected onto its plane (round-off)
PLANE_QUANTISED_M = 1e-3  # after 1 mm depth counts, noise off
# a close-up's markers come this close to its target, in image widths: measured 0.03-0.06 for
# the 3x3-marker board at 640x360 below (six of its nine markers must be in view), 0.005-0.02
# for the thesis board on the 1280x720 ring
CLOSEUP_REACH = 0.08
NOISE_FREE = SynthParams(blur_sigma_px=0.0, color_noise_dn=0.0, depth_dropout=0.0,
                         depth_subpixel_px=0.0)  # fmt: skip


def _detector(board):
    detector = cv2.aruco.ArucoDetector(board.aruco_dict)
    params = detector.getDetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector.setDetectorParameters(params)
    return detector


def _detect(board, color):
    img = finish_color(color, NOISE_FREE, np.random.default_rng(0))
    corners, ids, _ = _detector(board).detectMarkers(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    assert ids is not None
    return {int(i): c.reshape(4, 2) for c, i in zip(corners, ids.ravel())}


def _camera(dist=(0.0,) * 5) -> SynthCamera:
    K = CameraIntrinsics(640, 480, 500.0, 498.0, 322.3, 238.6, tuple(dist))
    return SynthCamera("cam", K, np.eye(4))


def _pose(board, offset_xy, rotvec, face=FRONT, distance_m=0.5) -> np.ndarray:
    """``T_cam_board`` showing ``face`` to a camera at the origin, the board's centre at
    ``(offset_xy, distance_m)``."""
    flip = np.diag([1.0, -1.0, -1.0]) if face == FRONT else np.diag([-1.0, -1.0, 1.0])
    R = rotvec_to_matrix(rotvec) @ flip
    x0, x1, y0, y1 = board.panel
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0 if face == FRONT else -board.thickness])
    return make_transform(R, np.array([*offset_xy, distance_m]) - R @ centre)


# board centred, then pushed towards two image corners (the lens distorts most there)
POSES = [((0.0, 0.0), (0.2, -0.1, 0.05)), ((0.12, 0.08), (0.1, 0.3, 0.0)),
         ((-0.12, -0.08), (-0.2, 0.2, 0.1))]  # fmt: skip


@pytest.fixture(scope="module")
def distorted_views():
    """Noise-free 640x480 renders of the thesis board through a strong barrel lens, each with
    the same render through the pinhole of the same K."""
    board = thesis_board()
    model = _BoardModel(board)
    views = []
    for dist in (BARREL, (0.0,) * 5):
        cam = _camera(dist)
        bg = render_background([], cam)
        for offset, rotvec in POSES:
            T_cam_board = _pose(board, offset, rotvec)
            views.append((cam, T_cam_board, *render_board(model, cam, bg, T_cam_board)))
    return board, views[: len(POSES)], views[len(POSES) :]


def test_distorted_corners_match_the_true_lens_model(distorted_views):
    board, distorted, pinhole_renders = distorted_views
    errors, pinhole_errors, radius, baseline = [], [], [], []
    for cam, T_cam_board, color, _ in distorted:
        K = cam.intrinsics
        pinhole = replace(K, distortion=(0.0,) * 5)
        for i, c in _detect(board, color).items():
            p_cam = transform_points(T_cam_board, board.object_points([i])[0])
            errors.append(np.linalg.norm(c - K.project(p_cam), axis=1))
            pinhole_errors.append(np.linalg.norm(c - pinhole.project(p_cam), axis=1))
            radius.append(np.linalg.norm(c - [K.cx, K.cy], axis=1))
    for cam, T_cam_board, color, _ in pinhole_renders:
        for i, c in _detect(board, color).items():
            p_cam = transform_points(T_cam_board, board.object_points([i])[0])
            baseline.append(np.linalg.norm(c - cam.intrinsics.project(p_cam), axis=1))
    errors, pinhole_errors = np.concatenate(errors), np.concatenate(pinhole_errors)
    radius = np.concatenate(radius)
    assert errors.size >= 4 * 70
    assert np.median(errors) < CORNER_MEDIAN_PX, np.median(errors)
    # as exact as a pinhole render is to the same detector
    assert np.median(errors) < np.median(np.concatenate(baseline)) + 0.05
    border = radius > 250  # px from the principal point; the image corner is at ~400
    assert border.sum() > 20
    assert np.min(pinhole_errors[border]) > PINHOLE_OFF_BORDER_PX, np.min(pinhole_errors[border])


def test_distorted_edges_are_area_averaged(distorted_views):
    """Anti-aliasing under distortion: a patch of board edges against a brute-force render
    of every pixel with 16x16 rays from the lens model."""
    board, distorted, _ = distorted_views
    cam, T_cam_board, color, _ = distorted[1]  # board towards the bottom-right corner
    model = _BoardModel(board)
    K = cam.intrinsics
    v0, u0, n = 380, 560, 40  # near the image corner (a marker row lies here)
    s = 16
    offs = (np.arange(s) + 0.5) / s - 0.5
    vv, uu = np.mgrid[v0 : v0 + n, u0 : u0 + n].astype(float)
    us = (uu.reshape(-1, 1) + np.tile(offs, s)[None]).ravel()
    vs = (vv.reshape(-1, 1) + np.repeat(offs, s)[None]).ravel()
    hits = cast(model.rects, T_cam_board, camera_rays(K, us, vs))
    light = T_cam_board[:3, :3].T @ (invert_transform(cam.T_world_cam)[:3, :3] @ LIGHT_DIR_WORLD)
    shade = np.array([0.55 + 0.45 * abs(r.normal @ light) for r in model.rects])
    value = np.where(hits.index >= 0, model.reflectance(hits.index, hits.a, hits.b)
                     * shade[np.maximum(hits.index, 0)], 0.0)  # fmt: skip
    reference = value.reshape(n * n, s * s).mean(axis=1).reshape(n, n)
    patch = color[v0 : v0 + n, u0 : u0 + n, 0]
    edge = (reference > 0.1 * shade[0]) & (reference < 0.8 * shade[0])
    assert edge.sum() > 40  # the patch holds ink/paper edges
    assert np.max(np.abs(patch - reference)) < 0.06, np.max(np.abs(patch - reference))
    assert np.mean(np.abs(patch - reference)[edge]) < 0.015


def test_distorted_depth_back_projects_onto_the_board(distorted_views):
    board, distorted, _ = distorted_views
    x0, x1, y0, y1 = board.panel
    for cam, T_cam_board, _, depth in distorted:
        K = cam.intrinsics
        T_board_cam = invert_transform(T_cam_board)
        v, u = np.nonzero(np.isfinite(depth))
        assert v.size > 20000
        exact = transform_points(T_board_cam, K.rays(u, v) * depth[v, u][:, None])
        front = (exact[:, 0] > x0 + 0.005) & (exact[:, 0] < x1 - 0.005)
        front &= (exact[:, 1] > y0 + 0.005) & (exact[:, 1] < y1 - 0.005)
        assert front.mean() > 0.9  # the rest: the 5 mm band at the panel edge
        assert np.max(np.abs(exact[front, 2])) < PLANE_EXACT_M
        counts = finish_depth(depth, cam, NOISE_FREE, np.random.default_rng(0))
        z = counts[v, u] * K.depth_scale
        quantised = transform_points(T_board_cam, K.rays(u, v) * z[:, None])
        assert np.max(np.abs(quantised[front, 2])) < PLANE_QUANTISED_M
        # the pinhole back-projection of the same depth is off the tilted plane
        pinhole = replace(K, distortion=(0.0,) * 5)
        wrong = transform_points(T_board_cam, pinhole.rays(u, v) * depth[v, u][:, None])
        assert np.max(np.abs(wrong[front, 2])) > 3 * PLANE_QUANTISED_M  # measured 3.9-12 mm


# --------------------------------------------------------------------------- the board print
@pytest.fixture(scope="module")
def board_views():
    """The thesis board's front and back through a pinhole, nominal and imperfect."""
    board = thesis_board()
    cam = _camera()
    bg = render_background([], cam)
    front = _pose(board, (0.02, -0.01), (0.15, -0.1, 0.05), FRONT)
    back = _pose(board, (0.02, -0.01), (-0.1, 0.15, 0.05), BACK)
    return board, cam, bg, front, back


def _render(board, cam, bg, T_cam_board, params):
    return render_board(_BoardModel(board, board_print(board, params)), cam, bg, T_cam_board)


def _marker_errors(board, cam, T_cam_board, detected, corners_board, face):
    err = []
    for i, c in detected.items():
        k = board.index_of[i]
        if board.faces[k] != face:
            continue
        truth = cam.intrinsics.project(transform_points(T_cam_board, corners_board[k]))
        err.append(np.linalg.norm(c - truth, axis=1))
    assert len(err) >= 20  # most of the face's 28 markers
    return np.concatenate(err)


def test_glued_back_sheet_renders_where_T_front_back_puts_it(board_views):
    board, cam, bg, front, back = board_views
    params = SynthParams(glue=(4.0, -3.0, 1.5), thickness_error_mm=1.0)
    printed = board_print(board, params)
    T = printed.T_front_back
    np.testing.assert_allclose(T[:3, :3], rotvec_to_matrix([0, 0, np.radians(1.5)]), atol=1e-15)
    # the rotation is about the back grid's centre (here x = 0.2 m, y = 0.11 m)
    np.testing.assert_allclose(transform_points(T, [[0.2, 0.11, 0.0]]), [[0.204, 0.107, -1e-3]],
                               atol=1e-12)  # fmt: skip
    assert printed.thickness_m == pytest.approx(board.thickness + 1e-3)
    color, _ = _render(board, cam, bg, back, params)
    detected = _detect(board, color)
    true_err = _marker_errors(board, cam, back, detected, printed.corners(board), BACK)
    nominal_err = _marker_errors(board, cam, back, detected, board.corners, BACK)
    assert np.median(true_err) < CORNER_MEDIAN_PX, np.median(true_err)
    assert np.median(nominal_err) > 4.0, np.median(nominal_err)  # ~5 mm at 0.5 m


def test_glue_leaves_the_front_face_alone(board_views):
    board, cam, bg, front, _ = board_views
    nominal = _render(board, cam, bg, front, SynthParams())
    glued = _render(board, cam, bg, front, SynthParams(glue=(4.0, -3.0, 1.5)))
    np.testing.assert_array_equal(glued[0], nominal[0])
    np.testing.assert_array_equal(glued[1], nominal[1])
    assert any(board_views[0].faces[board.index_of[i]] == FRONT
               for i in _detect(board, nominal[0]))  # fmt: skip


@pytest.mark.parametrize("face", [FRONT, BACK])
def test_print_scale_scales_both_faces(board_views, face):
    board, cam, bg, front, back = board_views
    T_cam_board = front if face == FRONT else back
    scale = 1.03
    params = SynthParams(print_scale=scale)
    printed = board_print(board, params)
    nominal = _detect(board, _render(board, cam, bg, T_cam_board, SynthParams())[0])
    scaled = _detect(board, _render(board, cam, bg, T_cam_board, params)[0])
    ratios = [
        np.linalg.norm(np.diff(scaled[i][[0, 1, 2, 3, 0]], axis=0), axis=1).sum()
        / np.linalg.norm(np.diff(nominal[i][[0, 1, 2, 3, 0]], axis=0), axis=1).sum()
        for i in set(nominal) & set(scaled)
        if board.faces[board.index_of[i]] == face
    ]
    assert len(ratios) >= 20
    assert np.median(ratios) == pytest.approx(scale, abs=0.004)
    err = _marker_errors(board, cam, T_cam_board, scaled, printed.corners(board), face)
    assert np.median(err) < CORNER_MEDIAN_PX


def test_board_print_conventions():
    board = thesis_board()
    printed = board_print(board, SynthParams(print_scale=0.99, glue=(1.0, 2.0, -0.5)))
    corners = printed.corners(board)
    front = board.faces == FRONT
    np.testing.assert_allclose(corners[front], board.corners[front] * [0.99, 0.99, 1.0])
    back = corners[board.faces == BACK].reshape(-1, 3)
    nominal_back = board.corners[board.faces == BACK].reshape(-1, 3) * [0.99, 0.99, 1.0]
    np.testing.assert_allclose(transform_points(printed.T_front_back, nominal_back), back)
    # file_xy is the texture look-up's inverse of corners()
    np.testing.assert_allclose(printed.file_xy(BACK, back[:, :2]),
                               board.corners[board.faces == BACK].reshape(-1, 3)[:, :2],
                               atol=1e-15)  # fmt: skip
    assert board_print(board, SynthParams()).is_nominal


# --------------------------------------------------------------------------- synthesize
GRID_BOARD = dict(dictionary="DICT_4X4_50", rows=3, cols=3, marker_length=0.09, separation=0.02,
                  thickness=0.006, front_first_id=0, back_first_id=9)  # fmt: skip
INK_MM = 0.5  # --ink-spread of the "ink" set
IMPERFECT = dict(distortion=(0.1, -0.2, 1e-3, -1e-3, 0.05), intrinsics_error=(2.0, 3.0),
                 glue=(3.0, -2.0, 1.0), thickness_error_mm=0.5, print_scale=0.995)  # fmt: skip


def _synth(path, **options):
    """A tiny ring (2 facing cameras, 640x360, 2 frames) of a 3x3-marker board."""
    params = SynthParams(resolution=(640, 360), cameras=2, **options)
    board = board_from_grid(**GRID_BOARD)
    return synthesize(path, "ring", 2, 11, board, params, workers=1)


def _pngs(path):
    return {p.relative_to(path): p.read_bytes() for p in sorted(path.glob("*/*/*.png"))}


@pytest.fixture(scope="module")
def ring_sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("imperfect")
    return {
        name: _synth(root / name, **options)
        for name, options in {
            "default": {},
            "neutral": dict(distortion=(0.0,) * 5, rig_distortion="truth",
                            intrinsics_error=(0.0, 0.0), glue=(0.0, 0.0, 0.0), print_scale=1.0),
            "lying": dict(intrinsics_error=(2.0, 3.0)),
            "imperfect": IMPERFECT,
            "imperfect-truth": dict(IMPERFECT, rig_distortion="truth"),
            "imperfect-closeups": dict(IMPERFECT, closeups=2),
            "ink": dict(ink_spread_mm=INK_MM),
        }.items()
    }  # fmt: skip


def test_neutral_options_render_the_defaults(ring_sets):
    default, neutral = ring_sets["default"].path, ring_sets["neutral"].path
    assert _pngs(neutral) == _pngs(default) and len(_pngs(default)) == 8
    assert (neutral / "rig.yaml").read_bytes() == (default / "rig.yaml").read_bytes()
    gt = load_ground_truth(default)
    assert gt.print_scale == 1.0 and np.array_equal(gt.T_front_back, np.eye(4))
    assert gt.intrinsics == load_rig(default / "rig.yaml").cameras


def test_intrinsics_error_only_changes_rig_yaml(ring_sets):
    default, lying = ring_sets["default"].path, ring_sets["lying"].path
    assert _pngs(lying) == _pngs(default)
    truth = load_ground_truth(lying).intrinsics
    listed = load_rig(lying / "rig.yaml").cameras
    assert truth == load_rig(default / "rig.yaml").cameras
    for name, K in listed.items():
        T = truth[name]
        scale = K.fx / T.fx
        assert K.fy / T.fy == pytest.approx(scale, abs=1e-12)  # one focal factor
        assert 0 < abs(scale - 1) <= 0.02
        assert 0 < abs(K.cx - T.cx) <= 3.0 and 0 < abs(K.cy - T.cy) <= 3.0
        assert K.distortion == T.distortion == (0.0,) * 5


def test_imperfect_set_records_its_truth(ring_sets):
    path = ring_sets["imperfect"].path
    gt = load_ground_truth(path)
    raw = yaml.safe_load((path / "ground_truth.yaml").read_text())
    board = board_from_grid(**GRID_BOARD)
    assert raw["board"]["thickness"] == board.thickness  # the board file stays nominal
    assert gt.thickness_m == pytest.approx(board.thickness + 0.5e-3)
    assert gt.print_scale == 0.995
    np.testing.assert_allclose(gt.T_front_back, board_print(board, SynthParams(**IMPERFECT))
                               .T_front_back, atol=1e-15)  # fmt: skip
    listed = load_rig(path / "rig.yaml").cameras
    for name, K in gt.intrinsics.items():
        assert K.distortion == IMPERFECT["distortion"]
        assert listed[name].distortion == (0.0,) * 5  # as a D435 reports
    truth_listed = load_rig(ring_sets["imperfect-truth"].path / "rig.yaml").cameras
    assert all(truth_listed[n].distortion == IMPERFECT["distortion"] for n in truth_listed)
    assert _pngs(ring_sets["imperfect-truth"].path) == _pngs(path)
    # the images show the board where the ground truth says: every detected corner
    detector = _detector(board)
    corners_true = gt.board_print(board).corners(board)
    errors = []
    for frame, T_ref_board in gt.T_ref_board.items():
        for name, K in gt.intrinsics.items():
            img = cv2.imread(str(path / name / "color" / f"{frame}.png"), cv2.IMREAD_GRAYSCALE)
            corners, ids, _ = detector.detectMarkers(img)
            T_cam_board = invert_transform(gt.T_ref_cam[name]) @ T_ref_board
            for c, i in zip(corners, [] if ids is None else ids.ravel()):
                truth = K.project(transform_points(T_cam_board, corners_true[board.index_of[i]]))
                errors.append(np.linalg.norm(c.reshape(4, 2) - truth, axis=1))
    errors = np.concatenate(errors)
    assert errors.size >= 4 * 12
    assert np.median(errors) < 0.5, np.median(errors)  # 14-20 px markers, blur and noise on


def test_imperfection_settings_are_checked():
    for bad in (dict(distortion=(0.1, 0.2)), dict(rig_distortion="factory"),
                dict(intrinsics_error=(-1.0, 0.0)), dict(print_scale=0.0),
                dict(distortion=(-2.0, 0.0, 0.0, 0.0, 0.0)),
                dict(board_volume=0.0), dict(closeups=-1), dict(ink_spread_mm=0.8)):  # fmt: skip
        with pytest.raises(ConfigError):
            make_rig("ring", 0, SynthParams(resolution=(640, 360), cameras=2, **bad))
    with pytest.raises(ConfigError, match="thickness"):
        board_print(thesis_board(), SynthParams(thickness_error_mm=-7.0))
    charuco = load_board(REPO / "configs" / "board_charuco_a3.yaml")
    with pytest.raises(ConfigError, match="ink-spread"):
        board_print(charuco, SynthParams(ink_spread_mm=0.1))


def test_ink_spread_moves_each_ink_edge_by_its_reach():
    """The print's reflectance: a marker's outline lies ``w`` outside the board file's edge
    (inside for a thin print), a white bit's edge ``w`` inside it, the geometry unchanged."""
    board = board_from_grid(**GRID_BOARD)
    x0, _, y0, _ = board.panel
    c = board.corners[board.faces == FRONT][0][:, :2]
    left, y_mid = c[:, 0].min(), c[:, 1].mean()
    xs = np.linspace(left - 2e-3, left + 2e-3, 4001)

    def outline(w):
        printed = replace(board_print(board, SynthParams()), ink_spread_m=w)
        refl = _BoardModel(board, printed).reflectance(np.zeros(len(xs), int), xs - x0,
                                                       np.full(len(xs), y_mid - y0))
        return xs[np.argmax(refl < refl.max())]

    for w in (0.0, 3e-4, -3e-4):
        assert outline(w) == pytest.approx(left - w, abs=2e-6), w
    # a white bit: the fraction of paper over the marker's inside shrinks with the spread
    u = np.linspace(0, 1, 301)
    uu, vv = np.meshgrid(left + u * (c[:, 0].max() - left), c[:, 1].min() + u * (c[:, 1].max()
                         - c[:, 1].min()))  # fmt: skip
    paper = []
    for w in (0.0, 1e-3):
        printed = replace(board_print(board, SynthParams()), ink_spread_m=w)
        refl = _BoardModel(board, printed).reflectance(np.zeros(uu.size, int), uu.ravel() - x0,
                                                       vv.ravel() - y0)
        paper.append(np.mean(refl == refl.max()))
    assert 0 < paper[1] < paper[0], paper


def test_an_ink_spread_print_looks_larger_by_the_spread_and_records_it(ring_sets):
    """The detected markers of the ``ink`` set lie outside those of the default set by 0.4-1.0
    of the spread's projection (the edge fit sees 0.55-0.63 on the race, docs/synthetic.md),
    and ground_truth.yaml holds the spread."""
    from rgbd_calib.detect.markers import detect_markers
    from rgbd_calib.solve.edge_offset import outward_bisectors

    ink, plain = ring_sets["ink"].path, ring_sets["default"].path
    gt = load_ground_truth(ink)
    assert gt.ink_spread_mm == INK_MM and load_ground_truth(plain).ink_spread_mm == 0.0
    board = board_from_grid(**GRID_BOARD)
    ratios = []
    for frame, T_ref_board in gt.T_ref_board.items():
        for name, K in gt.intrinsics.items():
            a, b = (detect_markers(cv2.imread(str(p / name / "color" / f"{frame}.png")), board)
                    for p in (plain, ink))
            T = invert_transform(gt.T_ref_cam[name]) @ T_ref_board
            for k, i in enumerate(b.ids):
                if int(i) not in a.ids:
                    continue
                ca = a.corners_px[list(a.ids).index(int(i))]
                P = board.object_points(np.array([i]))[0]
                out = P + INK_MM * 1e-3 * np.sign(P - P.mean(axis=0)) * [1, 1, 0]
                pa, pt = (K.project(transform_points(T, X)) for X in (P, out))
                bis = outward_bisectors(pa[None])[0]
                ratios.append(np.sum((b.corners_px[k] - ca) * bis) / np.sum((pt - pa) * bis))
    assert len(ratios) >= 12 and 0.4 < np.median(ratios) < 1.0, (len(ratios), np.median(ratios))


def test_distortion_keeps_the_board_poses(ring_sets):
    default, imperfect = ring_sets["default"], ring_sets["imperfect"]
    for a, b in zip(default.board_poses, imperfect.board_poses, strict=True):
        np.testing.assert_array_equal(a, b)
    rig = make_rig("ring", 11, SynthParams(resolution=(640, 360), cameras=2))
    assert [c.T_world_cam.tolist() for c in rig.cameras] == [
        c.T_world_cam.tolist() for c in imperfect.rig.cameras
    ]


def test_board_volume_scales_the_box_about_its_centre():
    """--board-volume S: the box the board centre is drawn from, S times the layout's about
    its centre; the cameras stay where the seed puts them."""
    small = SynthParams(resolution=(640, 360), cameras=4)
    base, wide = make_rig("ring", 3, small), make_rig("ring", 3, replace(small, board_volume=2.5))
    np.testing.assert_allclose((wide.workspace_lo + wide.workspace_hi) / 2,
                               (base.workspace_lo + base.workspace_hi) / 2)
    np.testing.assert_allclose(wide.workspace_hi - wide.workspace_lo,
                               2.5 * (base.workspace_hi - base.workspace_lo))
    assert [c.T_world_cam.tolist() for c in wide.cameras] == [
        c.T_world_cam.tolist() for c in base.cameras]


def test_closeups_fill_each_camera_image_out_to_its_corners(ring_sets):
    """--closeups N: N frame sets per camera after the regular ones (which render as without
    them), the board near that camera; close-up k aims at CLOSEUP_TARGETS[k], here the top
    left and top right image corners. Its markers are detected where the truth says, out to
    within CLOSEUP_REACH of them."""
    plain, path = ring_sets["imperfect"].path, ring_sets["imperfect-closeups"].path
    gt = load_ground_truth(path)
    assert gt.closeups == {"000002": "cam0", "000003": "cam0", "000004": "cam1",
                           "000005": "cam1"}
    assert sorted(gt.T_ref_board) == [f"{i:06d}" for i in range(6)]
    regular = {k: v for k, v in _pngs(path).items() if k.stem in ("000000", "000001")}
    assert regular == _pngs(plain)
    board = board_from_grid(**GRID_BOARD)
    detector, corners_true = _detector(board), gt.board_print(board).corners(board)
    for k, (frame, name) in enumerate(sorted(gt.closeups.items())):
        K = gt.intrinsics[name]
        img = cv2.imread(str(path / name / "color" / f"{frame}.png"), cv2.IMREAD_GRAYSCALE)
        corners, ids, _ = detector.detectMarkers(img)
        assert ids is not None and len(ids) >= 4, (frame, name)
        T_cam_board = invert_transform(gt.T_ref_cam[name]) @ gt.T_ref_board[frame]
        seen = []
        for c, i in zip(corners, ids.ravel()):
            truth = K.project(transform_points(T_cam_board, corners_true[board.index_of[i]]))
            assert np.median(np.linalg.norm(c.reshape(4, 2) - truth, axis=1)) < 0.5
            seen.append(truth)
        target = np.array(CLOSEUP_TARGETS[k % 2]) * [K.width - 1, K.height - 1]
        gap = np.linalg.norm(np.concatenate(seen) - target, axis=1).min()
        assert gap < CLOSEUP_REACH * K.width, (frame, name, gap)
