"""synth renders time (issue 32, item 5): a board that moves during each frame set, cameras
whose clocks are offset, a rolling-shutter colour sensor.

The images must show the board where the shared convention (rgbd_calib.synth.timing) puts it
at each camera's and each row's own time, ``ground_truth.yaml`` must say so, and a render with
the time settings off (or a still board) must be what it was before they existed.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from rgbd_calib.cli.commands import app
from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.errors import ConfigError
from rgbd_calib.core.geometry import (
    invert_transform,
    make_transform,
    pose_after_twist,
    rotvec_to_matrix,
    transform_points,
)
from rgbd_calib.detect.markers import detect_markers
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.synth.render import (
    SynthCamera,
    SynthParams,
    _BoardModel,
    load_ground_truth,
    make_rig,
    render_background,
    render_board,
    render_board_moving,
    synthesize,
)
from rgbd_calib.synth.timing import draw_timing

LAYOUT, SEED, FRAMES, RESOLUTION = "thesis-line", 5, 2, (640, 360)
# the board waved fast so that the rolling shutter's shear is several pixels wide
MOVING = dict(motion=(1.0, 30.0), rolling_shutter_ms=40.0, sync_offset_ms=16.0)
OFFSETS_ONLY = dict(motion=(1.0, 30.0), sync_offset_ms=16.0)
# detected corners (edge fit, blur 0.6 px, noise 2 DN) against their exact projection at the
# per-row time: measured 0.02-0.07 px median and 0.18 px max per view on this render, as on a
# still one. Markers under MIN_MARKER_PX wide are left out: the edge fit often fails on them
# and the detector's corners are then off by up to 1 px, on still renders too.
CORNER_MEDIAN_PX = 0.15
CORNER_MAX_PX = 0.5
MIN_MARKER_PX = 11.0
ROW_EXACT_PX = 1e-9  # the implicit row equation solved to this


def _render(tmp_path_factory, name: str, **time) -> FolderDataset:
    out = tmp_path_factory.mktemp(name) / "set"
    synthesize(out, LAYOUT, FRAMES, SEED, thesis_board(),
               SynthParams(resolution=RESOLUTION, **time), workers=1)
    return out


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    return _render(tmp_path_factory, "moving", **MOVING)


@pytest.fixture(scope="module")
def offsets_only(tmp_path_factory):
    return _render(tmp_path_factory, "offsets", **OFFSETS_ONLY)


def _project_per_row(gt, camera: str, frame: str, K: CameraIntrinsics, points_board):
    """Pixels of board points in ``camera``'s colour image of ``frame``, each at the time of
    its own row: ``v = project_v(T(tau(v)))`` solved by fixed-point iteration to
    :data:`ROW_EXACT_PX` (the board moves a small fraction of a row per row)."""
    T_cam_ref = invert_transform(gt.T_ref_cam[camera])
    v = np.full(len(points_board), (K.height - 1) / 2)
    for _ in range(100):
        taus = gt.exposure_tau_s(camera, v, K.height)
        uv = np.array([K.project(transform_points(T_cam_ref @ gt.T_ref_board_at(frame, tau),
                                                  p[None]))[0]
                       for tau, p in zip(taus, points_board)])
        step = np.max(np.abs(uv[:, 1] - v))
        v = uv[:, 1]
        if step < ROW_EXACT_PX:
            return uv
    raise AssertionError(f"row equation did not converge ({step} px)")


def _project_at(gt, camera, frame, K, points_board, tau_s):
    T_cam_board = invert_transform(gt.T_ref_cam[camera]) @ gt.T_ref_board_at(frame, tau_s)
    return K.project(transform_points(T_cam_board, points_board))


def _views(folder):
    """``(camera, frame, intrinsics, detections)`` of every view with markers."""
    ds, board = FolderDataset(folder), thesis_board()
    gt = load_ground_truth(folder)
    for camera in ds.cameras:
        for frame in sorted(gt.T_ref_board):
            path = ds.color_path(camera, frame)
            if path is None:
                continue
            det = detect_markers(cv2.imread(str(path)), board)
            det = det.subset(np.linalg.norm(det.corners_px[:, 0] - det.corners_px[:, 1],
                                            axis=1) >= MIN_MARKER_PX)
            if len(det):
                yield camera, frame, ds.rig.cameras[camera], det


def test_the_time_truth_is_written_and_read_back(moving, tmp_path):
    gt = load_ground_truth(moving)
    params = SynthParams(resolution=RESOLUTION, **MOVING)
    rig = make_rig(LAYOUT, SEED, params)
    timing = draw_timing(rig, FRAMES, SEED, params)
    for cam, offset_s, readout_s in zip(rig.cameras, timing.offset_s, timing.readout_s):
        assert gt.offset_ms[cam.name] == pytest.approx(1000 * offset_s, abs=1e-12)
        assert gt.readout_ms[cam.name] == pytest.approx(1000 * readout_s, abs=1e-12)
        assert gt.readout_ms[cam.name] == MOVING["rolling_shutter_ms"]
        assert abs(gt.offset_ms[cam.name]) <= MOVING["sync_offset_ms"]
    assert gt.offset_ms[gt.reference] == 0.0
    assert sum(abs(v) > 1.0 for v in gt.offset_ms.values()) >= 2  # the offsets were drawn
    speed_mps, rate_dps = MOVING["motion"]
    for i in range(FRAMES):
        frame = f"{i:06d}"
        np.testing.assert_allclose(gt.board_v_mps[frame], timing.v_mps[i], atol=1e-15)
        np.testing.assert_allclose(gt.board_w_radps[frame], timing.w_radps[i], atol=1e-15)
        assert np.linalg.norm(gt.board_v_mps[frame]) == pytest.approx(speed_mps)
        assert np.degrees(np.linalg.norm(gt.board_w_radps[frame])) == pytest.approx(rate_dps)
    # the convention: [Exp(w tau) R | p + v tau] in the reference frame; tau 0 is T_ref_board
    frame, tau = "000001", 0.012
    T = gt.T_ref_board_at(frame, tau)
    T0 = gt.T_ref_board[frame]
    np.testing.assert_allclose(T[:3, 3], T0[:3, 3] + gt.board_v_mps[frame] * tau, atol=1e-15)
    np.testing.assert_allclose(T[:3, :3] @ T0[:3, :3].T,
                               rotvec_to_matrix(gt.board_w_radps[frame] * tau), atol=1e-15)
    assert gt.T_ref_board_at(frame, 0.0) is T0
    raw = yaml.safe_load((moving / "ground_truth.yaml").read_text())
    assert raw["params"]["motion"] == list(MOVING["motion"])
    assert set(raw["time"]) == {"offset_ms", "readout_ms", "board_twist"}
    # an older (or still) set reads as all zeros
    del raw["time"]
    (tmp_path / "ground_truth.yaml").write_text(yaml.safe_dump(raw))
    old = load_ground_truth(tmp_path)
    assert set(old.offset_ms.values()) == {0.0} and set(old.readout_ms) == set(gt.readout_ms)
    assert not any(np.any(v) for v in old.board_v_mps.values())
    np.testing.assert_array_equal(old.T_ref_board_at(frame, tau), T0)


def test_rolling_shutter_rows_see_the_board_at_their_own_time(moving):
    gt, board = load_ground_truth(moving), thesis_board()
    medians, sheared = [], 0
    for camera, frame, K, det in _views(moving):
        points = board.object_points(det.ids).reshape(-1, 3)
        corners = det.corners_px.reshape(-1, 2)
        per_row = _project_per_row(gt, camera, frame, K, points)
        timeless = _project_at(gt, camera, frame, K, points, 0.0)
        error = np.linalg.norm(corners - per_row, axis=1)
        medians.append(np.median(error))
        assert np.median(error) < CORNER_MEDIAN_PX, (camera, frame, np.median(error))
        assert error.max() < CORNER_MAX_PX, (camera, frame, error.max())
        shift = np.linalg.norm(per_row - timeless, axis=1)
        if np.median(shift) > 2 * CORNER_MAX_PX:  # the timeless projection misses them
            sheared += 1
            assert np.median(np.linalg.norm(corners - timeless, axis=1)) > CORNER_MAX_PX
    assert len(medians) >= 5
    assert sheared >= 3, sheared  # the bound is met where the shear is many times wider


def test_each_camera_sees_the_board_at_its_own_offset(offsets_only):
    gt, board = load_ground_truth(offsets_only), thesis_board()
    offset_views = 0
    for camera, frame, K, det in _views(offsets_only):
        points = board.object_points(det.ids).reshape(-1, 3)
        corners = det.corners_px.reshape(-1, 2)
        at_offset = _project_at(gt, camera, frame, K, points, gt.offset_ms[camera] / 1000.0)
        error = np.linalg.norm(corners - at_offset, axis=1)
        assert np.median(error) < CORNER_MEDIAN_PX, (camera, frame, np.median(error))
        assert error.max() < CORNER_MAX_PX, (camera, frame, error.max())
        at_nominal = _project_at(gt, camera, frame, K, points, 0.0)
        apart = np.median(np.linalg.norm(at_offset - at_nominal, axis=1))
        if camera == gt.reference:
            assert apart == 0.0
        elif apart > 2 * CORNER_MAX_PX:
            offset_views += 1
            assert np.median(np.linalg.norm(corners - at_nominal, axis=1)) > CORNER_MAX_PX
    assert offset_views >= 3, offset_views


def _still_camera(distortion=(0.0,) * 5) -> SynthCamera:
    return SynthCamera("cam", CameraIntrinsics(320, 240, 260.0, 259.0, 161.3, 118.6,
                                               tuple(distortion)), np.eye(4))


def _facing(distance_m: float = 0.6) -> np.ndarray:
    """``T_cam_board``: the thesis board's front towards a camera at the origin."""
    board = thesis_board()
    x0, x1, y0, y1 = board.panel
    R = rotvec_to_matrix([0.2, -0.15, 0.05]) @ np.diag([1.0, -1.0, -1.0])
    return make_transform(R, [0.02, -0.01, distance_m] - R @ [(x0 + x1) / 2, (y0 + y1) / 2, 0])


@pytest.mark.parametrize("distortion", [(0.0,) * 5, (-0.2, 0.05, 1e-3, -5e-4, 0.0)])
@pytest.mark.parametrize("band_rows", [1, 7])
def test_row_by_row_rendering_of_a_still_board_is_the_global_render(distortion, band_rows):
    """The rolling-shutter path, given a board that does not move, paints exactly the pixels
    (bit for bit) the global-shutter path paints: bands, their box and margins lose nothing."""
    model, cam = _BoardModel(thesis_board()), _still_camera(distortion)
    bg = render_background([], cam)
    T = _facing()
    color, depth = render_board(model, cam, bg, T)
    color_rs, depth_rs = render_board_moving(model, cam, bg, lambda tau: T, 0.004, 0.030,
                                             band_rows=band_rows)
    assert np.isfinite(depth).sum() > 5000  # the board is in view
    np.testing.assert_array_equal(color_rs, color)
    np.testing.assert_array_equal(depth_rs, depth)


def test_a_board_that_leaves_the_view_during_the_readout():
    """The board rushes towards the camera and passes behind it while the rows are read out:
    early rows show it, the rows exposed once it is behind the camera show the scene only, and
    depth (a global shutter at tau = 0) is the global render of the board at that time."""
    model, cam = _BoardModel(thesis_board()), _still_camera()
    bg = render_background([], cam)
    bg.color[:] = 0.3  # a scene that is not the board's grey
    T0 = _facing(0.5)
    v_mps = np.array([0.0, 0.0, -40.0])  # in the camera frame: through the camera
    readout_s = 0.040  # rows -20 ms .. +20 ms: z from 1.3 m down to -0.3 m
    pose_at = lambda tau: pose_after_twist(T0, v_mps, np.zeros(3), tau)  # noqa: E731
    color, depth = render_board_moving(model, cam, bg, pose_at, 0.0, readout_s)
    x0, x1, y0, y1 = model.board.panel
    panel = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1)
                      for z in (0.0, -model.thickness)])
    behind = [y for y in range(cam.intrinsics.height)
              if transform_points(pose_at(readout_s * (y / (cam.intrinsics.height - 1) - 0.5)),
                                  panel)[:, 2].max() < 0]
    assert len(behind) > 30
    np.testing.assert_array_equal(color[behind], bg.color[behind])
    assert np.any(color[: behind[0] - 5] != 0.3)  # earlier rows show the board
    _, depth_global = render_board(model, cam, bg, T0)
    np.testing.assert_array_equal(depth, depth_global)


def test_a_still_board_renders_as_without_time(tmp_path):
    """Offsets and a readout of a still board change no pixel and no other draw: the same
    images, poses and rig as the same seed without them (the defaults render byte-identical
    to before the time settings existed: docs/synthetic.md, "Time")."""
    kw = dict(resolution=(424, 240), depth_dropout=0.2)
    a = synthesize(tmp_path / "a", LAYOUT, 1, SEED, thesis_board(), SynthParams(**kw),
                   workers=1)
    b = synthesize(tmp_path / "b", LAYOUT, 1, SEED, thesis_board(),
                   SynthParams(**kw, sync_offset_ms=20.0, rolling_shutter_ms=30.0), workers=1)
    files = sorted(p.relative_to(a.path) for p in a.path.rglob("*.png"))
    assert len(files) >= 4
    for f in files:
        assert (a.path / f).read_bytes() == (b.path / f).read_bytes(), f
    ga, gb = load_ground_truth(a.path), load_ground_truth(b.path)
    for k in ga.T_ref_board:
        np.testing.assert_array_equal(ga.T_ref_board[k], gb.T_ref_board[k])
    assert any(v != 0 for v in gb.offset_ms.values())
    raw = yaml.safe_load((a.path / "ground_truth.yaml").read_text())
    assert "time" not in raw and "motion" not in raw["params"]  # the file as before


@pytest.mark.parametrize(
    "args, option",
    [(["--motion", "5", "0"], "--motion"), (["--motion", "0.3", "-1"], "--motion"),
     (["--sync-offset-ms", "-2"], "--sync-offset-ms"),
     (["--rolling-shutter-ms", "250"], "--rolling-shutter-ms"),
     (["--frame-rate", "0"], "--frame-rate")],
)
def test_cli_time_options_are_checked(tmp_path, args, option):
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "s"), "--frames", "1", *args])
    assert result.exit_code != 0
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and option in lines[0], result.output
    assert not (tmp_path / "s").exists()


def test_time_params_are_validated():
    with pytest.raises(ConfigError, match="--motion"):
        make_rig(LAYOUT, 0, SynthParams(motion=(0.3, 400.0)))
    with pytest.raises(ConfigError, match="--rolling-shutter-ms"):
        make_rig(LAYOUT, 0, SynthParams(rolling_shutter_ms=-1.0))
    assert replace(SynthParams(), sync_offset_ms=1.0).timed and not SynthParams().timed


# timestamps.csv of a timed render: tiny renders, the board still (offsets only: one global
# render per image), many frame sets so the offsets' estimate has a few samples per camera
STAMP_RESOLUTION, STAMP_FRAMES, STAMP_JITTER_MS = (424, 240), 8, 2.0


def _stamped(out, frames=STAMP_FRAMES, **params):
    synthesize(out, LAYOUT, frames, SEED, thesis_board(),
               SynthParams(resolution=STAMP_RESOLUTION, supersample=1, **params), workers=1)
    return FolderDataset(out), load_ground_truth(out)


def test_a_timed_render_stamps_each_colour_frame(tmp_path):
    """``t_ms = f * 1000 + offset_c + jitter`` per camera and frame set (a board position a
    second, close-ups continue the count, dropped frames have no row); the stamps' mean
    difference to the reference camera's recovers the true offsets; the jitter is a stream
    of its own (another sigma changes no image and no truth, only the stamps)."""
    kw = dict(sync_offset_ms=16.0, drop_rate=0.15, closeups=1)
    ds, gt = _stamped(tmp_path / "a", timestamp_jitter_ms=STAMP_JITTER_MS, **kw)
    period_ms = 1000.0  # one position per second, no burst
    residuals, dropped = [], 0
    for camera in ds.cameras:
        stamps = ds.timestamps_ms(camera)
        colour = [f for f in ds.frames if ds.color_path(camera, f) is not None]
        assert stamps is not None and sorted(stamps) == colour  # a row per colour frame
        dropped += len(ds.frames) - len(colour)
        rows = (tmp_path / "a" / camera / "timestamps.csv").read_text().splitlines()
        assert rows[0] == "frame,t_ms" and len(rows) == len(colour) + 1
        for frame, t_ms in stamps.items():
            residuals.append(t_ms - (int(frame) * period_ms + gt.offset_ms[camera]))
    assert len(ds.frames) == STAMP_FRAMES + len(ds.cameras) and dropped > 0
    residuals = np.array(residuals)
    assert np.max(np.abs(residuals)) < 5 * STAMP_JITTER_MS
    assert 0.5 * STAMP_JITTER_MS < np.std(residuals) < 1.5 * STAMP_JITTER_MS  # jitter applied
    ref = ds.timestamps_ms(gt.reference)
    for camera in ds.cameras:
        stamps = ds.timestamps_ms(camera)
        common = sorted(set(stamps) & set(ref))
        mean = np.mean([stamps[f] - ref[f] for f in common])
        # the mean of n differences of two stamps has sigma sqrt(2) jitter / sqrt(n): 2.8 of it
        assert abs(mean - gt.offset_ms[camera]) < 4 * STAMP_JITTER_MS / np.sqrt(len(common)), (
            camera, mean, gt.offset_ms[camera])
    assert sum(abs(v) > 4.0 for v in gt.offset_ms.values()) >= 2  # offsets worth recovering
    raw = yaml.safe_load((tmp_path / "a" / "ground_truth.yaml").read_text())
    assert raw["params"]["timestamp_jitter_ms"] == STAMP_JITTER_MS

    ds_b, gt_b = _stamped(tmp_path / "b", timestamp_jitter_ms=0.0, **kw)
    for f in sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*.png")):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    assert gt_b.offset_ms == gt.offset_ms
    for camera in ds.cameras:  # without jitter the stamps are the truth
        stamps = ds_b.timestamps_ms(camera)
        assert sorted(stamps) == sorted(ds.timestamps_ms(camera))
        for frame, t_ms in stamps.items():
            assert t_ms == pytest.approx(int(frame) * period_ms + gt.offset_ms[camera],
                                         abs=1e-9)


def test_a_burst_renders_consecutive_frames_on_one_trajectory(tmp_path):
    """``--burst 3 --acceleration``: each position becomes 3 frame sets 1000/30 ms apart
    (positions 1 s apart), the truth of each set lies on its position's trajectory (the next
    set's pose is this one's moved by the set's twist and acceleration over a frame period),
    the twist changes by the acceleration times the period, and close-ups are named per set."""
    ds, gt = _stamped(tmp_path / "b", frames=2, motion=(0.3, 30.0), acceleration=(1.0, 100.0),
                      burst=3, closeups=1, timestamp_jitter_ms=0.0)
    n_sets = (2 + len(ds.cameras)) * 3
    assert len(ds.frames) == n_sets and len(gt.T_ref_board) == n_sets
    assert sorted(gt.closeups) == [f"{f:06d}" for f in range(6, n_sets)]
    ref = ds.timestamps_ms(gt.reference)
    period = 1000.0 / 30.0
    for f in range(n_sets - 1):
        name, nxt = f"{f:06d}", f"{f + 1:06d}"
        if f % 3 == 2:  # the next position, a second after this burst's first set
            assert ref[nxt] - ref[f"{f - 2:06d}"] == pytest.approx(1000.0)
            continue
        assert ref[nxt] - ref[name] == pytest.approx(period)
        moved = gt.T_ref_board_at(name, period / 1000.0)
        assert np.allclose(moved, gt.T_ref_board[nxt], atol=1e-9)
        a = gt.board_a_mps2[name]
        assert np.linalg.norm(a) == pytest.approx(1.0)
        assert np.allclose(gt.board_v_mps[nxt] - gt.board_v_mps[name], a * period / 1000.0)
        assert np.degrees(np.linalg.norm(gt.board_alpha_radps2[name])) == pytest.approx(100.0)
    assert np.linalg.norm(gt.board_v_mps["000001"]) == pytest.approx(0.3)  # the middle's speed


def test_a_still_render_has_no_timestamps(tmp_path):
    ds, _ = _stamped(tmp_path / "s", frames=1, timestamp_jitter_ms=STAMP_JITTER_MS)
    assert not list((tmp_path / "s").rglob("timestamps.csv"))
    assert all(ds.timestamps_ms(c) is None for c in ds.cameras)
    raw = yaml.safe_load((tmp_path / "s" / "ground_truth.yaml").read_text())
    assert "timestamp_jitter_ms" not in raw["params"]  # the file as before


@pytest.mark.parametrize("value", ["-0.1", "60", "nan"])
def test_the_timestamp_jitter_option_is_checked(tmp_path, value):
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "s"), "--frames", "1",
                                      "--sync-offset-ms", "5", "--timestamp-jitter-ms", value])
    assert result.exit_code != 0
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "--timestamp-jitter-ms" in lines[0], result.output
    assert not (tmp_path / "s").exists()
    with pytest.raises(ConfigError, match="--timestamp-jitter-ms"):
        make_rig(LAYOUT, 0, SynthParams(timestamp_jitter_ms=float(value)))


def test_the_frame_rate_spaces_a_burst():
    """``--frame-rate 6``: a burst's sets 1000/6 ms apart on one trajectory (the twist
    changes by the acceleration over that period), positions still 1 s apart; the option is
    checked and the render counts as timed."""
    params = SynthParams(motion=(0.3, 30.0), acceleration=(1.0, 100.0), burst=3,
                         frame_rate=6.0)
    timing = draw_timing(make_rig(LAYOUT, SEED, params), 2, SEED, params)
    assert np.allclose(timing.t_ms, [0.0, 1000 / 6, 2000 / 6, 1000.0, 1000 + 1000 / 6,
                                     1000 + 2000 / 6])
    assert timing.frame_period_ms == pytest.approx(1000 / 6)
    assert np.allclose(timing.v_mps[1] - timing.v_mps[0], timing.a_mps2[0] / 6.0)
    assert timing.burst_s(0) == pytest.approx(-1 / 6)
    assert replace(SynthParams(), frame_rate=10.0).timed
    with pytest.raises(ConfigError, match="--frame-rate"):
        make_rig(LAYOUT, SEED, SynthParams(frame_rate=0.5))
