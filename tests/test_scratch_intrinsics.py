"""Intrinsics from scratch (rig.yaml with only width/height) and colour-only video input.

Measured on :func:`charuco_line` (ChArUco A3, thesis-line, 6 frames, 5-6 views per camera,
corners reaching 4-7 % of each image) with rig.yaml stripped to the sizes: the single-camera
first estimates are 0.1-0.5 % off in fx/fy, the bundle's 0.02-0.2 % (cam9 the worst, 1.3 px of
632), cx/cy within 1.7 px; extrinsics 0.8-3.9 mm / 0.05-0.09 deg off (claimed sigmas 0.9-1.3
mm: cam9's 3.9 mm is 3 sigmas, its 0.2 % focal error times its ~1.9 m board distance; 6 views
a camera do not pin the focal length against the distance). Bounds below with a margin.
"""

from __future__ import annotations

import csv
import json
import shutil

import cv2
import numpy as np
import pytest
import yaml
from conftest import CONFIGS, SHARED_DATA, shared_data_missing
from typer.testing import CliRunner

from rgbd_calib.cli.commands import app
from rgbd_calib.core.errors import ConfigError
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.detect.markers import detect_markers
from rgbd_calib.model.board_file import load_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.model.rig import load_rig, save_rig
from rgbd_calib.sources.video import frames_of

A3 = CONFIGS / "board_charuco_a3.yaml"
CALISCOPE = CONFIGS / "board_charuco_caliscope.yaml"
CALISCOPE_DATA = SHARED_DATA / "caliscope-charuco-4cam"
FOCAL_PCT = 0.5  # bundle fx, fy vs the render's truth (measured <= 0.2 %)
CENTRE_PX = 4.0  # cx, cy (measured <= 1.6 px)
EXTRINSICS_MM, EXTRINSICS_DEG = 8.0, 0.2  # measured <= 3.9 mm / 0.09 deg


def size_only(src, dst, frames=None):
    """``src`` (a dataset folder) as ``dst`` with rig.yaml reduced to the image sizes; the
    images are symlinked (only the stems in ``frames`` when given)."""
    dst.mkdir()
    rig = yaml.safe_load((src / "rig.yaml").read_text())
    rig["cameras"] = {n: {"width": c["width"], "height": c["height"]}
                      for n, c in rig["cameras"].items()}
    (dst / "rig.yaml").write_text(yaml.safe_dump(rig))
    for cam in rig["cameras"]:
        (dst / cam / "color").mkdir(parents=True)
        for img in sorted((src / cam / "color").iterdir()):
            if frames is None or img.stem in frames:
                (dst / cam / "color" / img.name).symlink_to(img)
    return dst


# ----------------------------------------------------------------------------- rig.yaml
def test_rig_with_sizes_only_loads_and_writes_back(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"cameras": {
        "a": {"width": 640, "height": 480},
        "b": {"width": 640, "height": 480, "fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0}}}))
    rig = load_rig(path)
    assert rig.unknown_intrinsics == {"a"}
    assert rig.cameras["a"].width == 640 and not rig.cameras["a"].has_distortion
    save_rig(rig, tmp_path / "again.yaml")
    again = yaml.safe_load((tmp_path / "again.yaml").read_text())
    assert again["cameras"]["a"] == {"width": 640, "height": 480}  # no invented intrinsics
    assert again["cameras"]["b"]["fx"] == 500.0
    known = rig.with_intrinsics({"a": rig.cameras["b"]})
    assert known.unknown_intrinsics == set() and known.cameras["a"].fx == 500.0


def test_rig_with_part_of_the_pinhole_is_rejected(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"cameras": {"a": {"width": 640, "height": 480, "fx": 500}}}))
    with pytest.raises(ConfigError, match=r"missing required key\(s\) fy, cx, cy"):
        load_rig(path)


# ----------------------------------------------------------------------------- calibration
def test_intrinsics_from_scratch_recover_the_render(charuco_line, tmp_path):
    """Every camera of the render calibrated from scratch through the command line: the
    refined intrinsics (rig_refined.yaml, with sigmas in report.json) and the extrinsics
    against the truth, and the coverage warning (the board reached < 10 % of each image)."""
    from rgbd_calib.synth.render import load_ground_truth

    ds = size_only(charuco_line, tmp_path / "ds")
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["calibrate", str(ds), "--board", str(A3), "--out",
                                      str(out), "--workers", "1"])
    assert result.exit_code == 0, result.output
    truth = yaml.safe_load((charuco_line / "ground_truth.yaml").read_text())["intrinsics"]
    refined = load_rig(out / "rig_refined.yaml")
    assert refined.unknown_intrinsics == set()
    report = json.loads((out / "report.json").read_text())
    for cam, t in truth.items():
        r = refined.cameras[cam]
        for p in ("fx", "fy"):
            assert abs(getattr(r, p) / t[p] - 1) * 100 < FOCAL_PCT, (cam, p, getattr(r, p), t[p])
        for p in ("cx", "cy"):
            assert abs(getattr(r, p) - t[p]) < CENTRE_PX, (cam, p, getattr(r, p), t[p])
        entry = report["cameras"][cam]
        assert entry["intrinsics_initial"]["views"] >= 4
        assert entry["intrinsics_refined"]["fx"]["sigma"] > 0
        assert entry["intrinsics_refined"]["fx"]["prior"] == entry["intrinsics_initial"]["fx"]
    gt = load_ground_truth(charuco_line)
    data = yaml.safe_load((out / "extrinsics.yaml").read_text())
    assert set(data["cameras"]) == set(gt.T_ref_cam)
    for name, cam in data["cameras"].items():
        deg, mm = transform_error(np.asarray(cam["T_ref_cam"]), gt.T_ref_cam[name])
        assert mm < EXTRINSICS_MM and deg < EXTRINSICS_DEG, (name, mm, deg)
    codes = {w["code"]: w for w in report["warnings"]}
    assert set(codes["scratch_coverage"]["cameras"]) == set(truth)
    assert "scratch_coverage" in result.output  # on the console too


def test_pose_graph_only_writes_the_first_estimates(charuco_line, tmp_path):
    """--method posegraph has no bundle adjustment: rig_refined.yaml holds the single-camera
    first estimates (measured 0.1-0.5 % off in fx/fy on this render)."""
    ds = size_only(charuco_line, tmp_path / "ds")
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["calibrate", str(ds), "--board", str(A3), "--out",
                                      str(out), "--method", "posegraph", "--workers", "1"])
    assert result.exit_code == 0, result.output
    truth = yaml.safe_load((charuco_line / "ground_truth.yaml").read_text())["intrinsics"]
    first = load_rig(out / "rig_refined.yaml")
    for cam, t in truth.items():
        assert abs(first.cameras[cam].fx / t["fx"] - 1) * 100 < 2 * FOCAL_PCT, cam


def test_too_few_views_for_scratch_intrinsics_is_one_line(charuco_line, tmp_path):
    ds = size_only(charuco_line, tmp_path / "ds", frames={"000000", "000001"})
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["calibrate", str(ds), "--board", str(A3), "--out",
                                      str(out), "--workers", "1"])
    assert result.exit_code != 0
    lines = [ln for ln in result.output.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, result.output
    assert "has no fx/fy/cx/cy in rig.yaml" in lines[0] and "record more views" in lines[0]
    assert "camera 'cam" in lines[0]
    assert not (out / "extrinsics.yaml").exists()


# ----------------------------------------------------------------------------- video input
def write_video(path, frames, fps=6.0):
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(f)
    writer.release()


def test_convert_videos_writes_a_colour_only_dataset(charuco_line, tmp_path):
    """Two cameras' renders as videos (each frame shown 3 times, so the board is still in the
    middle copy): without a board every 2nd set; with it only sets where the board is seen
    and still, never a frame next to a jump of the board."""
    frames = {}
    for cam in ("cam7", "cam8"):
        imgs = [cv2.imread(str(p)) for p in sorted((charuco_line / cam / "color").iterdir())]
        frames[cam] = [im for im in imgs for _ in range(3)]
        write_video(tmp_path / f"{cam}.avi", frames[cam])
    videos = [str(tmp_path / f"{c}.avi") for c in frames]
    plain = CliRunner().invoke(app, ["convert", *videos, "--out", str(tmp_path / "plain"),
                                     "--step", "2"])
    assert plain.exit_code == 0, plain.output
    ds = FolderDataset(tmp_path / "plain")
    assert ds.rig.unknown_intrinsics == {"cam7", "cam8"}
    assert [fs.frame for fs in ds.frame_sets()] == [f"{k:06d}" for k in range(0, 18, 2)]
    assert not any(ds.has_depth(c) for c in ds.rig.names)
    written = cv2.imread(str(tmp_path / "plain" / "cam7" / "color" / "000004.png"))
    assert written.shape == frames["cam7"][4].shape

    still = CliRunner().invoke(app, ["convert", *videos, "--out", str(tmp_path / "still"),
                                     "--board", str(A3)])
    assert still.exit_code == 0, still.output
    kept = {fs.frame: set(fs.color) for fs in FolderDataset(tmp_path / "still").frame_sets()}
    assert kept, still.output
    # the middle copy of every pose with the board is still (no motion either side); views
    # next to a jump of the board are dropped, so fewer views are kept than show the board
    board = load_board(A3)
    decoded = {c: list(frames_of(tmp_path / f"{c}.avi")) for c in frames}
    seen = {c: [len(detect_markers(f, board)) > 0 for f in decoded[c]] for c in frames}
    for c in frames:
        middles = {f"{f:06d}" for f in range(1, 18, 3) if seen[c][f]}
        assert middles <= {f for f, cams in kept.items() if c in cams}, (c, sorted(kept))
        assert all(seen[c][int(f)] for f, cams in kept.items() if c in cams)
    assert sum(map(len, kept.values())) < sum(map(sum, seen.values()))
    # the board goes with the dataset: calibrate reads it when --board is not given
    assert load_board(tmp_path / "still" / "board.yaml").to_dict() == board.to_dict()
    assert not (tmp_path / "plain" / "board.yaml").exists()


@pytest.mark.skipif(not CALISCOPE_DATA.is_dir(),
                    reason=shared_data_missing("caliscope-charuco-4cam"))
def test_convert_real_webcam_clips_with_timestamps(tmp_path):
    """Real data: frames 68-79 of cam_0 and cam_2 of the Caliscope session, cut into clips,
    converted with the session's timestamps (rows cut to match) and the board: the sets keep
    their sync index, and every kept view has the board."""
    first, n = 68, 12
    rows = list(csv.DictReader(open(CALISCOPE_DATA / "timestamps.csv")))
    cut = []
    for cam in (0, 2):
        cap = cv2.VideoCapture(str(CALISCOPE_DATA / f"cam_{cam}.mp4"))
        imgs = [cap.read()[1] for _ in range(first + n)][first:]
        cap.release()
        write_video(tmp_path / f"cam_{cam}.avi", imgs)
        mine = sorted((r for r in rows if int(r["cam_id"]) == cam),
                      key=lambda r: int(r["frame_index"]))
        cut += mine[first:first + n]
    with open(tmp_path / "ts.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(cut)
    out = tmp_path / "ds"
    result = CliRunner().invoke(app, ["convert", str(tmp_path / "cam_0.avi"),
                                      str(tmp_path / "cam_2.avi"), "--timestamps",
                                      str(tmp_path / "ts.csv"), "--board", str(CALISCOPE),
                                      "--out", str(out)])
    assert result.exit_code == 0, result.output
    ds = FolderDataset(out)
    assert (ds.rig.cameras["cam_0"].width, ds.rig.cameras["cam_0"].height) == (1280, 720)
    sync = {int(r["sync_index"]) for r in cut}
    board = load_board(CALISCOPE)
    views = 0
    for fs in ds.frame_sets():
        assert int(fs.frame) in sync
        for cam, path in fs.color.items():
            assert len(detect_markers(cv2.imread(str(path)), board)) > 0, (cam, fs.frame)
            views += 1
    assert views >= 4, result.output
    shutil.rmtree(out)


@pytest.mark.skipif(not CALISCOPE_DATA.is_dir(),
                    reason=shared_data_missing("caliscope-charuco-4cam"))
def test_real_webcams_get_an_estimated_view_floor_instead_of_outlier_views(tmp_path):
    """Real data: the 4 Caliscope webcams, intrinsics from scratch. Their board views disagree
    with the rig far beyond their corner noise (intrinsics fitted on a few percent of each
    image, an edge bias, unsynchronised rolling shutters; renders give a misfit ratio of ~0.5),
    so ``pose.model_error_px: auto`` estimates a floor of a few tenths of a pixel, and the pose
    graph rejects a handful of views where without it (``0``) it rejects a quarter of them;
    every camera is kept either way."""
    from dataclasses import replace

    from rgbd_calib.core.config import CalibrationConfig
    from rgbd_calib.pipelines.calibrate import calibrate
    from rgbd_calib.solve.pose import pose_edges
    from rgbd_calib.solve.posegraph import calibrate_pose_graph

    ds = tmp_path / "ds"
    videos = [str(CALISCOPE_DATA / f"cam_{c}.mp4") for c in range(4)]
    result = CliRunner().invoke(app, ["convert", *videos, "--timestamps",
                                      str(CALISCOPE_DATA / "timestamps.csv"), "--board",
                                      str(CALISCOPE), "--out", str(ds)])
    assert result.exit_code == 0, result.output
    config = CalibrationConfig(workers=1, refine="none")
    auto = calibrate(FolderDataset(ds), load_board(CALISCOPE), config)
    assert sorted(auto.extrinsics.cameras) == ["cam_0", "cam_1", "cam_2", "cam_3"]
    floor = auto.posegraph.stats["view_floor"]
    assert floor["misfit_ratio"] > 10 and 0.1 < floor["model_error_px"] < 1.0, floor
    assert len(auto.posegraph.outlier_edges) < 0.05 * floor["edges"]

    # the same views without the floor (pose.model_error_px: 0)
    edges = [replace(e, model_error_unit=None) for e in pose_edges(auto.observations, config)]
    zero = calibrate_pose_graph(edges, auto.extrinsics.reference, config.graph)
    assert "view_floor" not in zero.stats
    assert len(zero.outlier_edges) > 0.15 * floor["edges"]
    assert sorted(zero.cameras) == ["cam_0", "cam_1", "cam_2", "cam_3"]


def test_board_motion_is_the_largest_corner_move_to_either_neighbour():
    from rgbd_calib.sources.video import board_motion

    c = np.zeros((4, 2))
    frames = [{1: c}, {1: c + [3.0, 0.0]}, {1: c + [3.0, 0.5], 2: c}, {}, {2: c}]
    motion = board_motion(frames)
    np.testing.assert_allclose(motion[:3], [3.0, 3.0, 0.5])
    assert np.isnan(motion[3])  # no board
    assert motion[4] == np.inf  # no neighbour with a common marker: cannot tell


def test_timestamps_csv_without_its_columns_is_one_line(tmp_path):
    from rgbd_calib.core.errors import DatasetError
    from rgbd_calib.sources.video import read_timestamps

    path = tmp_path / "ts.csv"
    path.write_text("frame,time\n0,0.1\n")
    with pytest.raises(DatasetError, match="sync_index,cam_id,frame_index,frame_time"):
        read_timestamps(path)
