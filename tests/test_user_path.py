"""The user's path end to end: a real ``calibrate`` run whose every output is read back by the
tool that consumes it, and whose console (not a terminal) shows progress, the verdict, the
warnings and the report's path."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml
from conftest import assert_transforms_close
from test_exports import _launch_nodes
from typer.testing import CliRunner

from rgbd_calib.cli.commands import app
from rgbd_calib.core.geometry import invert_transform, make_transform, quaternion_xyzw_to_matrix
from rgbd_calib.model.results import load_extrinsics
from rgbd_calib.outputs.exports import urdf_rpy_to_matrix

EXACT_MM, EXACT_DEG = 1e-6, 1e-5  # the same numbers written in another format
# the thesis pose graph re-solved from the exported CSVs: another method on the same views
POSEGRAPH_MM, POSEGRAPH_DEG = 5.0, 0.3


def test_every_export_reads_back_with_its_consumer(tiny_calibration, tmp_path):
    _, out, _ = tiny_calibration
    ext = load_extrinsics(out / "extrinsics.yaml", check_redundant=True)
    names = list(ext.cameras)
    assert len(names) == 4 and ext.T_ref_cam(ext.reference).tolist() == np.eye(4).tolist()
    exports = out / "exports"

    # Kalibr: composing T_cn_cnm1 along the chain gives back T_ref_cam
    chain = yaml.safe_load((exports / "camchain.yaml").read_text())
    T_ref = np.eye(4)
    for n, name in enumerate([ext.reference] + [c for c in names if c != ext.reference]):
        if n:
            T_ref = T_ref @ invert_transform(np.asarray(chain[f"cam{n}"]["T_cn_cnm1"]))
        assert_transforms_close(T_ref, ext.T_ref_cam(name), EXACT_MM, EXACT_DEG)
        assert chain[f"cam{n}"]["resolution"] == [640, 360]

    # ROS 2 launch file and URDF: one transform per non-reference camera
    launch = (exports / "static_transforms.launch.py").read_text()
    compile(launch, "static_transforms.launch.py", "exec")
    nodes = _launch_nodes(launch)
    assert len(nodes) == 3
    for args in nodes:
        cam = args["--child-frame-id"].removesuffix("_color_optical_frame")
        T = make_transform(quaternion_xyzw_to_matrix([float(args[k]) for k in
                                                      ("--qx", "--qy", "--qz", "--qw")]),
                           [float(args[k]) for k in ("--x", "--y", "--z")])
        assert_transforms_close(T, ext.T_ref_cam(cam), EXACT_MM, EXACT_DEG)
    joints = ET.parse(exports / "cameras.urdf").getroot().findall("joint")
    assert len(joints) == 3
    for joint in joints:
        cam = joint.find("child").get("link").removesuffix("_color_optical_frame")
        origin = joint.find("origin")
        T = make_transform(urdf_rpy_to_matrix(origin.get("rpy").split()),
                           [float(v) for v in origin.get("xyz").split()])
        assert_transforms_close(T, ext.T_ref_cam(cam), EXACT_MM, EXACT_DEG)

    # the thesis CSVs: rgbd-calib's own posegraph command accepts them and agrees
    edge_rows = (exports / "Edges.csv").read_text().strip().splitlines()[1:]
    assert len(edge_rows) >= 8
    result = CliRunner().invoke(app, ["posegraph", str(exports / "Nodes.csv"),
                                      str(exports / "Edges.csv"), "--out", str(tmp_path / "pg")])
    assert result.exit_code == 0, result.output
    again = load_extrinsics(tmp_path / "pg" / "extrinsics.yaml")
    assert set(again.cameras) == set(names)
    for name in names:
        assert_transforms_close(again.T_ref_cam(name), ext.T_ref_cam(name), POSEGRAPH_MM,
                                POSEGRAPH_DEG)

    # g2o: GTSAM's reader finds every camera vertex and one edge per Edges.csv row
    gtsam = pytest.importorskip("gtsam")
    graph, values = gtsam.readG2o(str(exports / "posegraph.g2o"), True)
    assert graph.size() == len(edge_rows)
    for i, name in enumerate([ext.reference] + [c for c in names if c != ext.reference]):
        assert np.allclose(values.atPose3(i).matrix(), ext.T_ref_cam(name), atol=1e-9)

    # the other outputs: config, fused cloud, report.json rebuilt by `rgbd-calib report`
    from rgbd_calib.core.config import load_config
    from rgbd_calib.core.ply import read_ply

    assert load_config(out / "config_resolved.yaml").method == "bundle"
    points, _, _, cloud_names = read_ply(out / "fused.ply")
    assert len(points) > 1000 and set(cloud_names) == set(names)
    report = (out / "report.json").read_text()
    result = CliRunner().invoke(app, ["report", str(out)])
    assert result.exit_code == 0, result.output
    assert (out / "report.json").read_text() == report


def test_console_off_a_terminal_shows_progress_verdict_warnings_and_report(tiny_calibration):
    _, out, text = tiny_calibration
    lines = text.splitlines()
    # progress as plain lines: each stage's start and end, with counts
    for stage in ("detecting markers", "registering pairs", "checking depth pairs"):
        assert any(re.match(rf"{stage}.*: \d+/\d+ done in [\d.]+ s$", ln) for ln in lines), stage
    verdict = [i for i, ln in enumerate(lines) if ln.startswith("verdict: ")]
    assert len(verdict) == 1
    import json

    report = json.loads((out / "report.json").read_text())
    assert report["summary"]["verdict"].upper() in lines[verdict[0]]
    found = report["warnings"]
    shown = [ln for ln in lines[verdict[0] + 1:] if ln.split(":")[0] in ("error", "warning",
                                                                          "info")]
    # issue 34: at most three findings that ask for action, one line each, worst first; the
    # count of the rest (all of them in report.json / report.html)
    assert 1 <= len(shown) <= min(3, len(found))
    ranks = [("error", "warning", "info").index(ln.split(":")[0]) for ln in shown]
    assert ranks == sorted(ranks)  # worst first
    if len(found) > len(shown):
        assert f"+ {len(found) - len(shown)} more finding" in text
    assert lines[-1] == f"report: {out / 'report.html'}"  # the last line
    results = lines[verdict[0] - 1]
    assert results.startswith(f"results in {out}/") and "fused.ply" in results


def test_plain_progress_lines_have_rate_and_eta():
    from rgbd_calib.cli.console import PROGRESS_LINE, PlainProgress

    now = [0.0]
    lines: list[str] = []
    progress = PlainProgress(lines.append, interval_s=10.0, clock=lambda: now[0])
    tick = progress("detecting markers", 100, 20)
    for _ in range(8):
        now[0] += 5.0
        tick(10)
    assert lines == [
        "detecting markers: 20/100 started",
        "detecting markers: 40/100 (40%), 2.0/s, ETA 30 s",
        "detecting markers: 60/100 (60%), 2.0/s, ETA 20 s",
        "detecting markers: 80/100 (80%), 2.0/s, ETA 10 s",
        "detecting markers: 100/100 done in 40.0 s",
    ]
    unknown = PlainProgress(lines.append, clock=lambda: now[0])("rendering", None)
    now[0] += 20
    unknown(4)
    assert lines[-2:] == ["rendering: started", "rendering: 4 done, 0.2/s, 20 s"]
    # a log reader (and the one-line-error tests) can tell progress from everything else
    assert all(PROGRESS_LINE.match(ln) for ln in lines)
    for other in ("error: ds/rig.yaml: missing; write one", "verdict: GOOD: no warning",
                  "report: out/report.html", "results in out/ (extrinsics.yaml)"):
        assert not PROGRESS_LINE.match(other), other


def test_readme_library_example_runs_as_written(tiny_dataset, tmp_path):
    """The README's ``## Library use`` snippet, run as a script from a clone's root (its
    configs/ linked in), calibrates and writes the outputs. Its dataset is the session's
    :func:`tiny_dataset`, rendered with the snippet's own ``synthesize`` arguments, so the
    snippet skips that step here."""
    import os
    import shutil
    import subprocess
    import sys

    from conftest import CONFIGS, REPO

    readme = (REPO / "README.md").read_text()
    section = readme.split("## Library use", 1)[1]
    snippet = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    (tmp_path / "configs").symlink_to(CONFIGS)
    (tmp_path / "example.py").write_text(snippet)
    assert 'synthesize(data, "thesis-line", 4, 0, thesis_board(), SynthParams(resolution=(640, ' \
        '360)))' in snippet  # what tiny_dataset renders
    shutil.copytree(tiny_dataset, tmp_path / "example_dataset")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), *sys.path])}
    run = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr
    assert [ln.split(":")[0] for ln in run.stdout.splitlines()] == ["cam7", "cam8", "cam9",
                                                                    "cam10"]
    assert load_extrinsics(tmp_path / "example_out" / "extrinsics.yaml").reference == "cam7"


def test_script_without_main_guard_fails_with_one_line(tmp_path):
    """A script that calls the library at import time is refused before any worker starts,
    with one line naming the script and the fix (instead of a BrokenProcessPool traceback)."""
    import os
    import subprocess
    import sys

    from conftest import REPO

    script = tmp_path / "noguard.py"
    script.write_text("from rgbd_calib.core.parallel import process_context\n"
                      "from rgbd_calib import RgbdCalibError\n"
                      "try:\n    process_context()\n"
                      "except RgbdCalibError as exc:\n    print(exc)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), *sys.path])}
    run = subprocess.run([sys.executable, str(script)], env=env, capture_output=True,
                         text=True, timeout=60, check=False)
    assert run.returncode == 0, run.stderr
    assert len(run.stdout.splitlines()) == 1
    assert str(script) in run.stdout and 'if __name__ == "__main__":' in run.stdout


def test_public_api_names_load_on_use():
    import importlib

    import rgbd_calib
    from rgbd_calib import CalibrationConfig, FolderDataset, calibrate, load_board, write_outputs

    module = importlib.import_module("rgbd_calib.pipelines.calibrate")
    assert calibrate is module.calibrate and callable(calibrate)
    assert FolderDataset.__module__ == "rgbd_calib.model.dataset"
    assert load_board.__name__ == "load_board" and write_outputs.__name__ == "write_outputs"
    assert CalibrationConfig().method == "bundle"
    assert set(rgbd_calib.__all__) >= {"calibrate", "FolderDataset", "load_board",
                                       "CalibrationConfig", "write_outputs"}
    for name in rgbd_calib.__all__:
        assert getattr(rgbd_calib, name) is not None, name


def _anchors(markdown: str) -> set[str]:
    """GitHub's anchors of a markdown file's headings."""
    out = set()
    for line in markdown.splitlines():
        if line.startswith("#"):
            title = line.lstrip("#").strip().lower()
            out.add("#" + re.sub(r"[^a-z0-9 _-]", "", title).replace(" ", "-"))
    return out


def test_errors_about_a_format_link_its_section_of_docs_formats_md(tmp_path):
    from conftest import REPO

    from rgbd_calib.core.errors import RgbdCalibError
    from rgbd_calib.model.board_file import load_board
    from rgbd_calib.model.dataset import FolderDataset
    from rgbd_calib.model.posegraph_csv import read_edges_csv
    from rgbd_calib.model.rig import load_rig

    anchors = _anchors((REPO / "docs" / "formats.md").read_text())
    (tmp_path / "rig.yaml").write_text("cameras: []\n")
    (tmp_path / "board.yaml").write_text("dictionary: DICT_4X4_100\nthickness: 0.005\n")
    (tmp_path / "extrinsics.yaml").write_text("cameras: {}\n")
    (tmp_path / "Edges.csv").write_text("Cam,Node ID,tx,ty,tz,qx,qy,qz,qw\n")
    (tmp_path / "ds").mkdir()
    cases = {
        "#rigyaml": lambda: load_rig(tmp_path / "rig.yaml"),
        "#board-file-added": lambda: load_board(tmp_path / "board.yaml"),
        "#calibration-output": lambda: load_extrinsics(tmp_path / "extrinsics.yaml"),
        "#thesis-pose-graph-csvs": lambda: read_edges_csv(tmp_path / "Edges.csv"),
        "#recorded-rgb-d-set-folder-form": lambda: FolderDataset(tmp_path / "nowhere"),
    }
    for section, fail in cases.items():
        assert section in anchors, section
        with pytest.raises(RgbdCalibError) as err:
            fail()
        assert str(err.value).count("docs/formats.md") == 1, str(err.value)
        assert f"docs/formats.md{section}" in str(err.value), str(err.value)


def test_help_shows_plain_types_not_python_annotations():
    runner = CliRunner()
    for cmd in ("calibrate", "board", "synth", "demo", "posegraph", "record", "refine"):
        result = runner.invoke(app, [cmd, "--help"], env={"COLUMNS": "200"})
        assert result.exit_code == 0, result.output
        for raw in ("<bool>", "<list[", "<path>", "<str>", "<int>"):
            assert raw not in result.output, (cmd, raw)
    text = runner.invoke(app, ["calibrate", "--help"], env={"COLUMNS": "200"}).output
    assert "PATH..." in text and "INT" in text


def test_side_view_labels_of_close_cameras_are_stacked():
    from rgbd_calib.outputs.report.figures import label_row

    placed: list[tuple[float, float]] = []
    rows = []
    for anchor in [(0.0, 1.0), (0.01, 1.0), (0.02, 1.01), (2.0, 1.0)]:  # 3 close, 1 far
        rows.append(label_row(anchor, placed, size=3.0))
        placed.append(anchor)
    assert rows == [0, 1, 2, 0]


def test_unity_and_open3d_exports_read_back(tiny_calibration):
    """Open3D's own readers take the Open3D files; the Unity poses convert back exactly."""
    import json

    from rgbd_calib.model.rig import load_rig
    from rgbd_calib.outputs.exports import UNITY_FROM_OPENCV

    dataset, out, _ = tiny_calibration
    ext = load_extrinsics(out / "extrinsics.yaml")
    rig = load_rig(dataset / "rig.yaml")
    names = [ext.reference] + [c for c in ext.cameras if c != ext.reference]
    S = UNITY_FROM_OPENCV

    unity = json.loads((out / "exports" / "unity_cameras.json").read_text())
    for name in names:
        cam = unity["cameras"][name]
        R_unity = quaternion_xyzw_to_matrix(cam["rotation_xyzw"])
        T = make_transform(S @ R_unity @ S, S @ np.asarray(cam["position"]))
        assert_transforms_close(T, ext.T_ref_cam(name), EXACT_MM, EXACT_DEG)
        # a point 1 m in front of the camera is 1 m along the Unity camera's forward (+z)
        ahead = ext.T_ref_cam(name) @ [0, 0, 1, 1]
        assert np.allclose(S @ ahead[:3], cam["position"] + R_unity @ [0, 0, 1], atol=1e-9)
    assert np.allclose(unity["cameras"][ext.reference]["rotation_xyzw"], [0, 0, 0, 1])

    o3d = pytest.importorskip("open3d")
    for name in names:
        params = o3d.io.read_pinhole_camera_parameters(
            str(out / "exports" / "open3d" / f"{name}.json"))
        np.testing.assert_allclose(params.extrinsic, invert_transform(ext.T_ref_cam(name)),
                                   atol=1e-12)
        np.testing.assert_allclose(params.intrinsic.intrinsic_matrix, rig.cameras[name].K)
        assert (params.intrinsic.width, params.intrinsic.height) == (640, 360)
    trajectory = o3d.io.read_pinhole_camera_trajectory(
        str(out / "exports" / "open3d" / "cameras.json"))
    assert len(trajectory.parameters) == len(names)
    graph = o3d.io.read_pose_graph(str(out / "exports" / "open3d" / "posegraph.json"))
    assert len(graph.nodes) == len(names) and len(graph.edges) == len(names) - 1
    for i, name in enumerate(names):
        np.testing.assert_allclose(graph.nodes[i].pose, ext.T_ref_cam(name), atol=1e-12)
    for edge in graph.edges:  # source -> target (the reference) is the source's pose
        np.testing.assert_allclose(edge.transformation, graph.nodes[edge.source_node_id].pose,
                                   atol=1e-12)
        assert edge.target_node_id == 0 and np.all(np.linalg.eigvalsh(edge.information) > 0)


def test_a_second_render_with_the_same_options_is_reused(tmp_path, monkeypatch):
    """The demo's render is cached like the detections: same options and renderer, no
    render (the renderer is replaced by a stub that records its calls)."""
    import rgbd_calib.synth.render as synth
    from rgbd_calib.model.board import thesis_board

    renders = []

    def fake_synthesize(out, layout, n_frames, seed, board, params, workers, progress):
        renders.append(seed)
        out.mkdir(parents=True)
        (out / "ground_truth.yaml").write_text(f"seed: {seed}\n")

    monkeypatch.setattr(synth, "synthesize", fake_synthesize)
    params = synth.SynthParams(depth_bias=0.004)
    out = tmp_path / "dataset"
    for seed, reused in ((0, False), (0, True), (1, False), (1, True)):
        path, was = synth.synthesize_cached(out, "race", 16, seed, thesis_board(), params)
        assert path == out and was == reused, seed
    assert renders == [0, 1] and (out / "ground_truth.yaml").read_text() == "seed: 1\n"
    other = synth.SynthParams(depth_bias=0.005)
    assert synth.render_key("race", 16, 1, thesis_board(), other) != synth.render_key(
        "race", 16, 1, thesis_board(), params)


def test_script_calling_at_import_time_despite_a_guard_word_gets_one_clear_error(tmp_path):
    """A script whose text mentions __main__ but still starts the pool at import time: the
    re-imported copies in the workers stop quietly and the parent gets one clear error."""
    import os
    import subprocess
    import sys

    from conftest import REPO

    script = tmp_path / "halfguard.py"
    script.write_text("# __main__ is mentioned, yet the pool starts at import time\n"
                      "from rgbd_calib import RgbdCalibError\n"
                      "from rgbd_calib.core.parallel import WorkerPool\n"
                      "try:\n"
                      "    with WorkerPool(2) as pool:\n"
                      "        print(list(pool.map(abs, [1, -2, 3, -4])))\n"
                      "except RgbdCalibError as exc:\n"
                      "    print('ERROR', exc)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), *sys.path])}
    run = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("ERROR a worker process stopped") and GUARD_TEXT in run.stdout
    assert "Traceback" not in run.stderr, run.stderr


GUARD_TEXT = 'if __name__ == "__main__":'


def test_a_failing_figure_or_export_never_loses_the_calibration(tiny_dataset, tmp_path,
                                                                  monkeypatch):
    """A figure of report.html and an export that raise: calibrate still writes
    extrinsics.yaml and report.json, says what was left out in one warning each, exits 0, and
    leaves no half-written exports/ (issue 16: a finished calibration is never lost)."""
    from typer.testing import CliRunner

    from rgbd_calib.cli.commands import app
    from rgbd_calib.outputs import exports
    from rgbd_calib.outputs.report import figures

    def boom(*_args, **_kwargs):
        raise RuntimeError("broken on purpose")

    out = tmp_path / "out"
    (out / "exports").mkdir(parents=True)
    (out / "exports" / "stale.txt").write_text("an older run's export")
    monkeypatch.setattr(figures, "fig_rig", boom)
    monkeypatch.setattr(exports, "urdf_text", boom)
    res = CliRunner().invoke(app, ["calibrate", str(tiny_dataset), "--out", str(out),
                                   "--refine", "none", "--workers", "1"])
    assert res.exit_code == 0, res.output
    assert "report.html not written (RuntimeError: broken on purpose)" in res.output
    assert "exports/ not written (RuntimeError: broken on purpose)" in res.output
    assert (out / "extrinsics.yaml").is_file() and (out / "report.json").is_file()
    assert not (out / "report.html").exists() and not (out / "exports").exists()
    assert load_extrinsics(out / "extrinsics.yaml").reference == "cam7"
