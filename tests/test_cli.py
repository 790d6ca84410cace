"""End-to-end through the command line: outputs per formats.md, caching, bad input."""

import json
import math
import shutil

import numpy as np
import pytest
import yaml
from conftest import CONFIGS, SHARED_DATA, shared_data_missing
from typer.testing import CliRunner

from rgbd_calib import __version__
from rgbd_calib.cli.commands import app
from rgbd_calib.core.geometry import quaternion_xyzw_to_matrix, transform_error
from rgbd_calib.model.board_file import load_board
from rgbd_calib.synth.render import load_ground_truth

runner = CliRunner()
# noisy synthetic data (blur 0.6 px, 2 DN), only 6 frames: loose end-to-end bounds; the
# acceptance bounds on 40-frame rigs are in test_accuracy.py
E2E_MM, E2E_DEG = 1.0, 0.05


def run(*args):
    result = runner.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


def test_version_and_help():
    code, out = run("--version")
    assert code == 0 and __version__ in out
    for cmd in ("board", "synth", "calibrate", "posegraph", "demo", "convert", "record"):
        code, out = run(cmd, "--help")
        assert code == 0 and "Usage" in out, cmd


@pytest.fixture(scope="module")
def calibrated(small_line, tmp_path_factory):
    out = tmp_path_factory.mktemp("calib") / "out"
    code, text = run("calibrate", small_line.path, "--board", CONFIGS / "board_thesis.yaml",
                     "--out", out)
    assert code == 0, text
    return small_line, out


def test_extrinsics_yaml_follows_the_contract(calibrated):
    synth, out = calibrated
    data = yaml.safe_load((out / "extrinsics.yaml").read_text())
    gt = load_ground_truth(synth.path)
    assert data["reference"] == gt.reference == "cam7"
    assert set(data["cameras"]) == set(gt.T_ref_cam)
    for name, cam in data["cameras"].items():
        T = np.asarray(cam["T_ref_cam"])
        np.testing.assert_allclose(cam["translation_m"], T[:3, 3])
        np.testing.assert_allclose(quaternion_xyzw_to_matrix(cam["quaternion_xyzw"]), T[:3, :3],
                                   atol=1e-9)
        deg, mm = transform_error(T, gt.T_ref_cam[name])
        assert mm < E2E_MM and deg < E2E_DEG, (name, mm, deg)
        if name == "cam7":
            np.testing.assert_allclose(T, np.eye(4), atol=1e-9)
        else:
            assert 0 < cam["sigma_translation_mm"] < 1 and 0 < cam["sigma_rotation_deg"] < 0.1
    report = json.loads((out / "report.json").read_text())
    assert report["cameras"]["cam8"]["views_used"] > 0
    for name in ("camchain.yaml", "static_transforms.launch.py", "cameras.urdf", "Nodes.csv",
                 "Edges.csv", "posegraph.g2o"):
        assert (out / "exports" / name).stat().st_size > 0
    assert yaml.safe_load((out / "config_resolved.yaml").read_text())["method"] == "bundle"


def test_rerun_uses_the_detection_cache(calibrated):
    from rgbd_calib.core.config import DetectionConfig
    from rgbd_calib.detect.run import detect_dataset
    from rgbd_calib.model.board import thesis_board
    from rgbd_calib.model.dataset import FolderDataset

    synth, out = calibrated
    ds = FolderDataset(synth.path)
    counts = []
    dets = detect_dataset(ds, thesis_board(), DetectionConfig(), out / "cache" / "detections.json",
                          workers=1, progress=counts.append)
    n_images = sum(len(fs.color) for fs in ds.frame_sets())
    assert counts == [n_images] and len(dets) == n_images  # all from the cache, none detected
    code, text = run("calibrate", synth.path, "--out", out, "--method", "posegraph")
    assert code == 0, text
    assert yaml.safe_load((out / "config_resolved.yaml").read_text())["method"] == "posegraph"


def test_camera_that_never_shares_a_view_is_named(small_line, tmp_path):
    data = tmp_path / "ds"
    shutil.copytree(small_line.path, data)
    for kind in ("color", "depth"):  # cam10's frames get stems no other camera has
        for p in sorted((data / "cam10" / kind).iterdir()):
            p.rename(p.with_name("9" + p.name[1:]))
    code, text = run("calibrate", data, "--out", tmp_path / "out")
    assert code == 3, text  # written, but POOR (a camera not calibrated): not a success
    assert "cam10" in text and "not calibrated" in text and "exit 3" in text
    data = yaml.safe_load((tmp_path / "out" / "extrinsics.yaml").read_text())
    assert set(data["cameras"]) == {"cam7", "cam8", "cam9"}
    assert data["verdict"]["grade"] == "poor" and "cam10" in data["verdict"]["reason"]


def test_wrong_board_fails_cleanly_and_keeps_earlier_result(calibrated, tmp_path):
    synth, out = calibrated
    keep = tmp_path / "out"
    shutil.copytree(out, keep)
    before = (keep / "extrinsics.yaml").read_bytes()
    board = tmp_path / "other.yaml"
    board.write_text("dictionary: DICT_5X5_100\nthickness: 0.005\ngrid: {rows: 2, cols: 2, "
                     "marker_length: 0.05, separation: 0.01, front_first_id: 0}\n")
    code, text = run("calibrate", synth.path, "--board", board, "--out", keep)
    assert code == 2 and "no usable board view" in text and "Traceback" not in text
    assert (keep / "extrinsics.yaml").read_bytes() == before
    assert not any(p.name.startswith(".staging") for p in keep.iterdir())


@pytest.mark.parametrize("setup, message", [
    (lambda p: None, "dataset folder not found"),
    (lambda p: p.mkdir(), "rig.yaml: missing"),
    (lambda p: (p.mkdir(), shutil.copy(CONFIGS / "rig_thesis.yaml", p / "rig.yaml")),
     "have no <camera>/color folder"),
])
def test_bad_datasets_fail_with_one_line(tmp_path, setup, message):
    data = tmp_path / "ds"
    setup(data)
    code, text = run("calibrate", data, "--out", tmp_path / "out")
    assert code == 2 and message in text and "Traceback" not in text
    assert len(text.strip().splitlines()) == 1
    assert not (tmp_path / "out" / "extrinsics.yaml").exists()


def test_posegraph_command_on_thesis_data(tmp_path):
    data = SHARED_DATA / "thesis-posegraph"
    if not data.exists():
        pytest.skip(shared_data_missing("thesis-posegraph"))
    code, text = run("posegraph", data / "Nodes.csv", data / "Edges.csv", "--out", tmp_path)
    assert code == 0, text
    cams = yaml.safe_load((tmp_path / "extrinsics.yaml").read_text())["cameras"]
    assert list(cams) == ["cam7", "cam8", "cam9", "cam10"]
    # cam8 sits about 0.4 m along -x of cam7 (thesis Table 4.3)
    assert cams["cam8"]["translation_m"][0] == pytest.approx(-0.40, abs=0.03)


def test_synth_and_board_commands(tmp_path):
    code, text = run("synth", tmp_path / "s", "--layout", "moon")
    assert code == 2 and "unknown layout" in text
    code, text = run("synth", tmp_path / "s", "--resolution", "big")
    assert code != 0 and "WIDTHxHEIGHT" in text
    code, text = run("synth", tmp_path / "s", "--ink-spread", "0.8")
    assert code == 2 and "--ink-spread 0.8" in text and len(text.strip().splitlines()) == 1
    code, text = run("synth", tmp_path / "s", "--ink-spread", "0.1", "--board",
                     CONFIGS / "board_charuco_a3.yaml")
    assert code == 2 and "leave --ink-spread out" in text
    assert not (tmp_path / "s").exists()
    code, text = run("board", CONFIGS / "board_thesis.yaml", "--out", tmp_path / "b",
                     "--dpi", "50")
    assert code == 0 and (tmp_path / "b" / "board.pdf").exists()
    assert "should span 400.0 mm across and 220.0 mm down" in " ".join(text.split())
    # the print measured: the board file rescaled to it, with the measurement's sigma
    code, text = run("board", CONFIGS / "board_thesis.yaml", "--out", tmp_path / "m",
                     "--measured", "400.8", "220.44")
    assert code == 0 and "1.00200 x the file's size" in text
    measured = load_board(tmp_path / "m" / "board.yaml")
    assert measured.marker_length == pytest.approx(0.04 * 1.002)
    assert measured.print_scale_sigma == pytest.approx(0.3 / math.hypot(400.0, 220.0))
    assert not (tmp_path / "m" / "board.pdf").exists()
    code, text = run("board", CONFIGS / "board_thesis.yaml", "--out", tmp_path / "cm",
                     "--measured", "40.08", "22.04")
    assert code == 2 and "more than 5% off" in text and len(text.strip().splitlines()) == 1
    assert not (tmp_path / "cm").exists()
    before = (tmp_path / "m" / "board.yaml").read_text()  # never rescaled in place
    code, text = run("board", tmp_path / "m" / "board.yaml", "--out", tmp_path / "m",
                     "--measured", "401.6", "220.88")
    assert code == 2 and "in place" in text
    assert (tmp_path / "m" / "board.yaml").read_text() == before


def test_python_m_runs_a_command_with_worker_processes(tmp_path):
    """``python -m rgbd_calib.cli`` (tools/bench_caliscope.py calls it so) runs a command whose
    pool workers re-import the main module: the module must not run the app on re-import."""
    import subprocess
    import sys

    out = tmp_path / "rig"
    run = subprocess.run([sys.executable, "-m", "rgbd_calib.cli", "synth", str(out), "--layout",
                          "thesis-line", "--frames", "1", "--seed", "3", "--resolution",
                          "640x360", "--workers", "2"], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stdout + run.stderr
    assert load_ground_truth(out).T_ref_cam and (out / "rig.yaml").exists()


def test_calibrate_without_board_reads_the_datasets_board_yaml(small_line, tmp_path):
    """Issue 34: the board goes with the dataset (synth and convert --board write board.yaml);
    without --board calibrate reads it and says so, and says when it falls back to the thesis
    board, never silently."""
    own = load_board(small_line.path / "board.yaml").to_dict()
    assert own.pop("print_scale_sigma") == 0.0  # rendered at the file's size: exact
    assert own == load_board(CONFIGS / "board_thesis.yaml").to_dict()
    code, text = run("calibrate", small_line.path, "--out", tmp_path / "own", "--refine",
                     "none")
    assert code == 0, text
    assert f"board: {small_line.path / 'board.yaml'} (the dataset's" in " ".join(text.split())
    bare = tmp_path / "bare"
    shutil.copytree(small_line.path, bare)
    (bare / "board.yaml").unlink()
    code, text = run("calibrate", bare, "--out", tmp_path / "thesis", "--refine", "none")
    assert code == 0, text
    assert "board: the thesis board (no --board" in " ".join(text.split())


def test_the_command_line_runs_numpy_blas_on_one_thread_unless_told_otherwise():
    """OpenBLAS's threads on the pipeline's small products slow a loaded machine down
    (issue 59): the command line sets OPENBLAS_NUM_THREADS=1 before numpy loads, and keeps a
    user's own setting."""
    import os
    import subprocess
    import sys

    code = ("import os, rgbd_calib.cli, numpy; "
            "print(os.environ.get('OPENBLAS_NUM_THREADS'))")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout.strip()
    assert out == "1"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OPENBLAS_NUM_THREADS": "2"},
                         capture_output=True, text=True, check=True).stdout.strip()
    assert out == "2"
