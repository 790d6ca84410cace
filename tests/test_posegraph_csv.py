"""Thesis pose-graph CSV readers and writers (docs/formats.md, thesis Figs 4.9/4.10)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import SHARED_DATA, assert_transforms_close, shared_data_missing

from rgbd_calib.core.errors import ConfigError
from rgbd_calib.core.geometry import (
    invert_transform,
    make_transform,
    quaternion_xyzw_to_matrix,
    rotvec_to_matrix,
)
from rgbd_calib.model.posegraph_csv import (
    camera_name,
    camera_node_id,
    node_ids,
    read_edges_csv,
    read_nodes_csv,
    read_optimised_camera_poses,
    write_edges_csv,
    write_nodes_csv,
    write_optimised_camera_poses,
)
from rgbd_calib.model.results import PoseEdge, load_extrinsics
from rgbd_calib.outputs.writer import write_posegraph_outputs
from rgbd_calib.pipelines.posegraph import run_posegraph

THESIS = SHARED_DATA / "thesis-posegraph"

# Thesis Figure 4.10 rows (tab-separated, "Node ID" splits into two header words)
EDGES_TAB = """Cam\tNode ID\ttx\tty\ttz\tqx\tqy\tqz\tqw
7\t23\t-0.334\t0.239252\t0.829421\t-0.03693\t0.008331\t0.997229\t-0.06404
8\t23\t0.067101\t0.239014\t0.832156\t-0.03917\t0.007246\t0.997285\t-0.06193
"""
EDGES_COMMA = """\ufeffCam,Node ID,tx,ty,tz,qx,qy,qz,qw\r
7,23,-0.334,0.239252,0.829421,-0.03693,0.008331,0.997229,-0.06404\r
\r
8,23,0.067101,0.239014,0.832156,-0.03917,0.007246,0.997285,-0.06193\r
"""
NODES = """Node ID,tx,ty,tz,qx,qy,qz,qw
7,0,0,0,0,0,0,1
10,-0.6,0,0.1,0,0.4,0,0.9
11,,,,,,,
23,-0.334003,0.239252,0.829421,-0.036934,0.00833136,0.997229,-0.0640365
"""


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    return path


def test_thesis_files_parse(tmp_path):
    if not (THESIS / "Edges.csv").is_file():
        pytest.skip(shared_data_missing("thesis-posegraph"))
    edges = read_edges_csv(THESIS / "Edges.csv")
    nodes = read_nodes_csv(THESIS / "Nodes.csv")
    cams = read_optimised_camera_poses(THESIS / "optimised_camera_poses.csv")
    assert len(edges) == 1524
    assert {e.camera for e in edges} == {"cam7", "cam8", "cam9", "cam10"}
    assert len({e.view for e in edges}) == 390
    assert len(nodes) == 4 + 390 and "11" not in nodes  # rows 11-22 are empty
    first = edges[0]
    assert (first.camera, first.view) == ("cam7", "23")
    assert np.allclose(first.T_cam_board[:3, 3], [-0.3340030, 0.2392520, 0.8294210])
    q = [-0.0369340, 0.0083314, 0.9972290, -0.0640365]
    assert np.allclose(first.T_cam_board[:3, :3], quaternion_xyzw_to_matrix(q))
    # optimised_camera_poses.csv has w FIRST: cam10 of Table 4.3 is a ~30 deg turn about y
    q10_xyzw = [-0.0230178120157993, 0.257479439244382, 0.00393738594580626, 0.966001560914017]
    assert np.allclose(cams["cam10"][:3, :3], quaternion_xyzw_to_matrix(q10_xyzw), atol=1e-12)
    assert np.allclose(
        cams["cam10"][:3, 3], [-1.05335318591724, -0.0244326108708615, 0.171729533437121]
    )
    assert np.allclose(cams["cam7"], np.eye(4))


def test_separators_bom_crlf_and_blank_lines_read_the_same(tmp_path):
    a = read_edges_csv(write(tmp_path, "tab.csv", EDGES_TAB))
    b = read_edges_csv(write(tmp_path, "comma.csv", EDGES_COMMA))
    assert len(a) == len(b) == 2
    for ea, eb in zip(a, b, strict=True):
        assert (ea.camera, ea.view) == (eb.camera, eb.view)
        assert np.array_equal(ea.T_cam_board, eb.T_cam_board)
        assert ea.covariance is None
    assert [e.camera for e in a] == ["cam7", "cam8"]


def test_nodes_skip_unused_rows_and_normalise_quaternions(tmp_path):
    nodes = read_nodes_csv(write(tmp_path, "Nodes.csv", NODES))
    assert list(nodes) == ["7", "10", "23"]
    assert np.allclose(nodes["7"], np.eye(4))
    R10 = nodes["10"][:3, :3]  # the thesis guess (0, 0.4, 0, 0.9) is not unit length
    assert np.allclose(R10 @ R10.T, np.eye(3), atol=1e-12)
    assert np.allclose(
        R10, quaternion_xyzw_to_matrix(np.array([0, 0.4, 0, 0.9]) / np.hypot(0.4, 0.9))
    )


def test_header_names_decide_the_quaternion_order(tmp_path):
    text = "Cam,Node ID,tx,ty,tz,qw,qx,qy,qz\n7,1,0.1,0.2,0.3,0.9,0.1,0.2,0.3\n"
    (edge,) = read_edges_csv(write(tmp_path, "e.csv", text))
    assert np.allclose(edge.T_cam_board[:3, :3], quaternion_xyzw_to_matrix([0.1, 0.2, 0.3, 0.9]))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("Cam,Node ID,tx,ty,tz,qx,qy,qz,qw\n7,23,1,2,3,0,0,0\n", "row 2: expected 9 values"),
        (
            "Cam,Node ID,tx,ty,tz,qx,qy,qz,qw\n7,23,1,2,3,0,0,0,1\n7,24,1,x,3,0,0,0,1\n",
            "row 3: column ty is not a number",
        ),
        ("Cam,Node ID,tx,ty,tz,qx,qy,qz,qw\n7,23,1,2,3,0,0,0,0\n", "row 2: quaternion"),
        ("Cam,Node ID,tx,ty,tz,qx,qy,qz,qw\n7,23,1,2,nan,0,0,0,1\n", "row 2: column tz is nan"),
        ("Cam,Node ID,tx,ty,tz,qx,qy,qz,qw\n7,23,,,,,,,\n", "row 2: column tx is not a number"),
        ("Cam,Node ID,tx,ty,tz,qx,qy,qz,qw\n", "no pose rows"),
    ],
)
def test_edge_errors_name_file_row_and_fix(tmp_path, text, message):
    path = write(tmp_path, "Edges.csv", text)
    with pytest.raises(ConfigError) as info:
        read_edges_csv(path)
    assert str(path) in str(info.value) and message in str(info.value)
    assert "\n" not in str(info.value)


def test_nodes_errors(tmp_path):
    dup = write(
        tmp_path, "Nodes.csv", "Node ID,tx,ty,tz,qx,qy,qz,qw\n7,0,0,0,0,0,0,1\n7,0,0,0,0,0,0,1\n"
    )
    with pytest.raises(ConfigError, match="row 3: node 7 appears twice"):
        read_nodes_csv(dup)
    with pytest.raises(ConfigError, match="not found"):
        read_nodes_csv(tmp_path / "missing.csv")
    partial = write(tmp_path, "N2.csv", "Node ID,tx,ty,tz,qx,qy,qz,qw\n8,1,2,,,,,\n")
    with pytest.raises(ConfigError, match="row 2: column tz is not a number"):
        read_nodes_csv(partial)


def test_camera_names():
    assert camera_name("7") == "cam7" and camera_node_id("cam7") == "7"
    assert camera_name("left0") == "left0" and camera_node_id("left0") == "left0"
    assert camera_node_id("camera") == "camera"


def test_writers_round_trip_through_the_readers(tmp_path, rng):
    def random_pose():
        return make_transform(rotvec_to_matrix(rng.normal(size=3)), rng.normal(size=3))

    T_ref_cam = {"cam7": np.eye(4), "cam8": random_pose(), "left0": random_pose()}
    T_ref_board = {"23": random_pose(), "24": random_pose()}
    edges = [PoseEdge(c, v, random_pose()) for c in T_ref_cam for v in T_ref_board]
    write_nodes_csv(tmp_path / "Nodes.csv", T_ref_cam, T_ref_board)
    write_edges_csv(tmp_path / "Edges.csv", edges)
    write_optimised_camera_poses(tmp_path / "cams.csv", T_ref_cam)
    nodes = read_nodes_csv(tmp_path / "Nodes.csv")
    assert list(nodes) == ["7", "8", "left0", "23", "24"]
    for name, T in {**T_ref_cam, **T_ref_board}.items():
        assert_transforms_close(nodes[camera_node_id(name)], T, atol_mm=1e-9, atol_deg=1e-5)
    back = read_edges_csv(tmp_path / "Edges.csv")
    assert [(e.camera, e.view) for e in back] == [(e.camera, e.view) for e in edges]
    for a, b in zip(back, edges, strict=True):
        assert np.allclose(a.T_cam_board, b.T_cam_board, atol=1e-14)
    cams = read_optimised_camera_poses(tmp_path / "cams.csv")
    for name, T in T_ref_cam.items():
        assert np.allclose(cams[name], T, atol=1e-14)


def test_cameras_named_like_views_round_trip(tmp_path):
    """cam0..cam2 with views 0..2 (a camera named like a frame): the cameras keep their names
    as node ids, Nodes.csv and Edges.csv agree, and reading them back gives the same poses."""
    rng = np.random.default_rng(3)

    def pose():
        return make_transform(rotvec_to_matrix(rng.normal(size=3) * 0.3), rng.normal(size=3))

    T_ref_cam = {f"cam{i}": pose() for i in range(3)}
    boards = {str(v): pose() for v in range(3)}
    edges = [PoseEdge(c, v, np.linalg.inv(T_ref_cam[c]) @ boards[v], np.eye(6))
             for c in T_ref_cam for v in boards]
    write_nodes_csv(tmp_path / "Nodes.csv", T_ref_cam, boards)
    write_edges_csv(tmp_path / "Edges.csv", edges)
    nodes = read_nodes_csv(tmp_path / "Nodes.csv")
    assert set(nodes) == {"cam0", "cam1", "cam2", "0", "1", "2"}
    for name, T in {**T_ref_cam, **boards}.items():
        assert np.allclose(nodes[name], T, atol=1e-14)
    read = read_edges_csv(tmp_path / "Edges.csv")
    assert {(e.camera, e.view) for e in read} == {(e.camera, e.view) for e in edges}
    # a camera literally named like a view: the view is renamed, consistently in both files
    cams, views = node_ids(["7", "cam8"], ["7", "8", "view7"])
    assert cams == {"7": "7", "cam8": "cam8"}
    assert views == {"7": "view7", "8": "8", "view7": "viewview7"}
    assert len(set(cams.values()) | set(views.values())) == 5


# ---------------------------------------------------------------------------------------------
# The library entry point: run_posegraph / write_posegraph_outputs


def test_run_posegraph_takes_the_identity_node_as_reference(tmp_path, rng):
    def random_pose():
        return make_transform(rotvec_to_matrix(rng.normal(size=3) * 0.5), rng.normal(size=3))

    T_ref_cam = {"cam3": random_pose(), "cam5": np.eye(4), "cam9": random_pose()}
    boards = {str(100 + v): random_pose() for v in range(12)}
    edges = [
        PoseEdge(c, v, invert_transform(T_ref_cam[c]) @ T)
        for v, T in boards.items()
        for c in T_ref_cam
    ]
    # Nodes.csv lists cam3 first with a rough guess; cam5's node is the identity
    guesses = {"cam3": random_pose(), "cam5": np.eye(4), "cam9": random_pose()}
    write_nodes_csv(tmp_path / "Nodes.csv", guesses, boards)
    write_edges_csv(tmp_path / "Edges.csv", edges)
    run = run_posegraph(tmp_path / "Nodes.csv", tmp_path / "Edges.csv")
    assert run.extrinsics.reference == "cam5"
    for cam, T in T_ref_cam.items():
        assert_transforms_close(run.extrinsics.T_ref_cam(cam), T, atol_mm=1e-6, atol_deg=1e-5)
    paths = write_posegraph_outputs(run, tmp_path / "out")
    back = load_extrinsics(paths["extrinsics"])
    assert back.reference == "cam5" and set(back.cameras) == set(T_ref_cam)
    assert (tmp_path / "out" / "exports" / "posegraph.g2o").is_file()


def test_run_posegraph_on_the_thesis_data(tmp_path):
    if not (THESIS / "Edges.csv").is_file():
        pytest.skip(shared_data_missing("thesis-posegraph"))
    run = run_posegraph(THESIS / "Nodes.csv", THESIS / "Edges.csv")
    assert run.extrinsics.reference == "cam7"
    assert set(run.extrinsics.cameras) == {"cam7", "cam8", "cam9", "cam10"}
    assert sum(1 for i in run.stale_edges if run.edges[i].camera == "cam7") == 54
    assert not set(run.stale_edges) & set(run.outlier_edges)
    paths = write_posegraph_outputs(run, tmp_path)
    report = json.loads(paths["report"].read_text(), parse_constant=pytest.fail)
    assert len(report["stale_edges"]) == len(run.stale_edges)
    assert report["stale_edges"][0]["csv_row"] == report["stale_edges"][0]["index"] + 2
    assert report["stats"]["edges_used"] == len(run.result.used_edges)
    assert 0 < report["stats"]["median_edge_residual_used_mm"] < 5
    extrinsics = load_extrinsics(paths["extrinsics"])
    assert np.allclose(extrinsics.T_ref_cam("cam8"), run.extrinsics.T_ref_cam("cam8"))
    # the exported thesis-style edges are the ones the solution used
    assert len(read_edges_csv(paths["edges_csv"])) == len(run.result.used_edges)


def test_posegraph_writes_a_verdict_as_calibrate_does():
    """issue 58 item 6: an unlinked camera is POOR, a model-error camera or many outlier
    edges CHECK, else GOOD (written into extrinsics.yaml; the exit codes follow it)."""
    from types import SimpleNamespace

    from rgbd_calib.pipelines.posegraph import posegraph_verdict

    ext = SimpleNamespace(unconnected={})
    clean = SimpleNamespace(model_error={}, outlier_edges=(1,))
    assert posegraph_verdict(ext, clean, 100).grade == "good"
    assert posegraph_verdict(ext, SimpleNamespace(model_error={}, outlier_edges=tuple(
        range(11))), 100).grade == "check"
    assert posegraph_verdict(ext, SimpleNamespace(model_error={"cam9": 1}, outlier_edges=()),
                             100).reason.startswith("camera_model_error [cam9]")
    poor = posegraph_verdict(SimpleNamespace(unconnected={"cam10": "no edge"}), clean, 100)
    assert poor.grade == "poor" and "cam10" in poor.reason
