"""Exports: every file parses back to the extrinsics it was written from."""

from __future__ import annotations

import ast
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import assert_transforms_close

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.geometry import (
    invert_transform,
    make_transform,
    matrix_to_quaternion_xyzw,
    quaternion_xyzw_to_matrix,
    rotvec_to_matrix,
)
from rgbd_calib.model.posegraph_csv import camera_node_id, read_edges_csv, read_nodes_csv
from rgbd_calib.model.results import CameraExtrinsics, Extrinsics, PoseEdge
from rgbd_calib.model.rig import Rig
from rgbd_calib.outputs.exports import (
    EXPORT_FILES,
    g2o_information,
    g2o_text,
    kalibr_camchain_text,
    matrix_to_urdf_rpy,
    ros2_launch_text,
    urdf_rpy_to_matrix,
    urdf_text,
    write_exports,
)

EXACT_MM = 1e-9
EXACT_DEG = 1e-5  # arccos resolution of transform_error


def random_pose(rng: np.random.Generator, scale_m: float = 1.0) -> np.ndarray:
    return make_transform(rotvec_to_matrix(rng.normal(size=3)), rng.normal(size=3) * scale_m)


@pytest.fixture
def calibration(rng):
    names = ["cam7", "cam8", "cam9", "cam10"]
    T = {n: (np.eye(4) if n == "cam7" else random_pose(rng)) for n in names}
    extrinsics = Extrinsics("cam7", {n: CameraExtrinsics(n, T[n], 0.01, 0.3) for n in names})
    boards = {str(v): random_pose(rng) for v in range(23, 29)}
    edges = []
    for v, T_ref_board in boards.items():
        for c in names[: 2 + int(v) % 3]:
            cov = None
            if c == "cam9":
                A = rng.normal(size=(6, 6))
                cov = A @ A.T * 1e-6 + np.eye(6) * 1e-7
            edges.append(PoseEdge(c, v, invert_transform(T[c]) @ T_ref_board, cov))
    return extrinsics, edges, boards


def read_g2o(text: str):
    """Tiny g2o reader: vertices {id: T}, edges [(i, j, T, info 6x6)], fixed ids."""
    vertices, edges, fixed = {}, [], []
    for line in text.splitlines():
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if tok[0] == "VERTEX_SE3:QUAT":
            v = [float(x) for x in tok[2:9]]
            vertices[int(tok[1])] = make_transform(quaternion_xyzw_to_matrix(v[3:]), v[:3])
        elif tok[0] == "EDGE_SE3:QUAT":
            v = [float(x) for x in tok[3:10]]
            info = np.zeros((6, 6))
            info[np.triu_indices(6)] = [float(x) for x in tok[10:31]]
            assert len(tok) == 31
            info = info + np.triu(info, 1).T
            edges.append(
                (
                    int(tok[1]),
                    int(tok[2]),
                    make_transform(quaternion_xyzw_to_matrix(v[3:]), v[:3]),
                    info,
                )
            )
        elif tok[0] == "FIX":
            fixed.append(int(tok[1]))
    return vertices, edges, fixed


def test_g2o_parses_back_to_the_same_poses(calibration):
    extrinsics, edges, boards = calibration
    vertices, g_edges, fixed = read_g2o(g2o_text(extrinsics, edges, boards))
    cams = ["cam7", "cam8", "cam9", "cam10"]
    assert fixed == [0]
    for i, c in enumerate(cams):
        assert_transforms_close(vertices[i], extrinsics.T_ref_cam(c), EXACT_MM, EXACT_DEG)
    for i, v in enumerate(boards):
        assert_transforms_close(vertices[len(cams) + i], boards[v], EXACT_MM, EXACT_DEG)
    assert len(g_edges) == len(edges)
    for (i, j, T, info), e in zip(g_edges, edges, strict=True):
        assert i == cams.index(e.camera)
        assert_transforms_close(T, e.T_cam_board, EXACT_MM, EXACT_DEG)
        # the edge is consistent with its vertices: T_cam_board = T_ref_cam^-1 T_ref_board
        assert_transforms_close(invert_transform(vertices[i]) @ vertices[j], T, 1e-6, 1e-5)
        if e.covariance is not None:
            assert np.allclose(info, g2o_information(e.covariance), rtol=1e-9)


def test_g2o_information_weighs_errors_like_gtsam(rng):
    """chi2 of g2o's error [t, q.xyz] with our information == chi2 of GTSAM's [rot, trans]."""
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-6 + np.eye(6) * 1e-8
    info = g2o_information(cov)
    for _ in range(5):
        xi = rng.multivariate_normal(np.zeros(6), cov) * 1e-2  # small error
        delta = make_transform(rotvec_to_matrix(xi[:3]), xi[3:])
        e_g2o = np.concatenate([delta[:3, 3], matrix_to_quaternion_xyzw(delta[:3, :3])[:3]])
        chi2_gtsam = xi @ np.linalg.solve(cov, xi)
        assert e_g2o @ info @ e_g2o == pytest.approx(chi2_gtsam, rel=1e-3)


def test_g2o_radians_convention_is_what_gtsam_reads(tmp_path, calibration):
    gtsam = pytest.importorskip("gtsam")
    extrinsics, edges, boards = calibration
    path = tmp_path / "graph.g2o"
    path.write_text(g2o_text(extrinsics, edges, boards, rotation_information="radians"))
    graph, values = gtsam.readG2o(str(path), True)
    assert np.allclose(values.atPose3(1).matrix(), extrinsics.T_ref_cam("cam8"), atol=1e-12)
    with_cov = [(k, e) for k, e in enumerate(edges) if e.covariance is not None]
    for k, e in with_cov:
        R = graph.at(k).noiseModel().R()
        assert np.allclose(np.linalg.inv(R.T @ R), e.covariance, rtol=1e-6, atol=1e-14)


def test_urdf_rpy_round_trips_including_gimbal_lock(rng):
    rotations = [rotvec_to_matrix(rng.normal(size=3)) for _ in range(50)]
    rotations += [urdf_rpy_to_matrix([0.3, s * np.pi / 2, -1.1]) for s in (1, -1)]
    for R in rotations:
        assert np.allclose(urdf_rpy_to_matrix(matrix_to_urdf_rpy(R)), R, atol=1e-9)
    # convention check: pure yaw of 90 deg maps x to y (R = Rz(yaw) Ry(pitch) Rx(roll))
    assert np.allclose(urdf_rpy_to_matrix([0, 0, np.pi / 2]) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(matrix_to_urdf_rpy(urdf_rpy_to_matrix([0.1, 0.2, 0.3])), [0.1, 0.2, 0.3])


def test_urdf_joints_give_back_the_extrinsics(calibration):
    extrinsics, _, _ = calibration
    root = ET.fromstring(urdf_text(extrinsics))
    joints = root.findall("joint")
    assert len(joints) == 3
    for joint in joints:
        assert joint.find("parent").get("link") == "cam7_color_optical_frame"
        child = joint.find("child").get("link").removesuffix("_color_optical_frame")
        origin = joint.find("origin")
        xyz = [float(v) for v in origin.get("xyz").split()]
        rpy = [float(v) for v in origin.get("rpy").split()]
        T = make_transform(urdf_rpy_to_matrix(rpy), xyz)
        assert_transforms_close(T, extrinsics.T_ref_cam(child), EXACT_MM, EXACT_DEG)
    links = {link.get("name") for link in root.findall("link")}
    assert links == {f"{c}_color_optical_frame" for c in extrinsics.cameras}


def test_kalibr_chain_composes_back_to_T_ref_cam(calibration):
    extrinsics, _, _ = calibration
    rig = Rig(
        {
            "cam7": CameraIntrinsics(1280, 720, 633.47, 633.47, 643.2, 358.4),
            "cam8": CameraIntrinsics(
                1280, 720, 637.5, 637.6, 643.3, 355.4, (0.1, -0.2, 0.001, 0.002, 0.05)
            ),
        },
        "cam7",
    )
    text = kalibr_camchain_text(extrinsics, rig)
    chain = yaml.safe_load(text)
    assert list(chain) == ["cam0", "cam1", "cam2", "cam3"]
    assert "T_cn_cnm1" not in chain["cam0"]
    T_ref = np.eye(4)
    for n, name in enumerate(["cam7", "cam8", "cam9", "cam10"][1:], start=1):
        T_ref = T_ref @ invert_transform(np.asarray(chain[f"cam{n}"]["T_cn_cnm1"]))
        assert_transforms_close(T_ref, extrinsics.T_ref_cam(name), 1e-9, EXACT_DEG)
        assert chain[f"cam{n}"]["rostopic"] == f"/{name}/color/image_raw"
    assert chain["cam1"]["intrinsics"] == [637.5, 637.6, 643.3, 355.4]
    assert chain["cam1"]["distortion_coeffs"] == [0.1, -0.2, 0.001, 0.002]
    assert chain["cam1"]["resolution"] == [1280, 720]
    assert "k1 k2 p1 p2" in text and "cam8" in text.splitlines()[1]  # k3 dropped, said so
    assert "intrinsics" not in chain["cam2"]  # not in the rig


def _launch_nodes(text: str) -> list[dict[str, str]]:
    """Arguments of each Node(...) call in a launch file, as {'--x': '0.1', ...}."""
    out = []
    for call in ast.walk(ast.parse(text)):
        if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "Node":
            kw = {k.arg: k.value for k in call.keywords}
            assert ast.literal_eval(kw["package"]) == "tf2_ros"
            assert ast.literal_eval(kw["executable"]) == "static_transform_publisher"
            args = ast.literal_eval(kw["arguments"])
            out.append(dict(zip(args[::2], args[1::2], strict=True)))
    return out


@pytest.mark.parametrize("parent", [None, "world"])
def test_ros2_launch_publishes_each_camera(calibration, parent):
    extrinsics, _, _ = calibration
    nodes = _launch_nodes(ros2_launch_text(extrinsics, parent_frame=parent))
    assert len(nodes) == (3 if parent is None else 4)
    for args in nodes:
        assert args["--frame-id"] == (parent or "cam7_color_optical_frame")
        cam = args["--child-frame-id"].removesuffix("_color_optical_frame")
        q = [float(args[k]) for k in ("--qx", "--qy", "--qz", "--qw")]
        t = [float(args[k]) for k in ("--x", "--y", "--z")]
        T = make_transform(quaternion_xyzw_to_matrix(q), t)
        assert_transforms_close(T, extrinsics.T_ref_cam(cam), EXACT_MM, EXACT_DEG)


def test_write_exports_writes_everything_and_csvs_round_trip(tmp_path, calibration):
    extrinsics, edges, boards = calibration
    paths = write_exports(extrinsics, tmp_path, edges=edges, board_poses=boards)
    assert set(paths) == set(EXPORT_FILES) - {"open3d_trajectory"}  # that needs intrinsics
    for kind, path in paths.items():
        assert path == tmp_path / "exports" / EXPORT_FILES[kind] and path.stat().st_size > 0
    assert not list(Path(tmp_path / "exports").glob(".*tmp"))
    nodes = read_nodes_csv(paths["nodes_csv"])
    for cam in extrinsics.cameras:
        assert_transforms_close(
            nodes[camera_node_id(cam)], extrinsics.T_ref_cam(cam), EXACT_MM, EXACT_DEG
        )
    for view, T in boards.items():
        assert_transforms_close(nodes[view], T, EXACT_MM, EXACT_DEG)
    back = read_edges_csv(paths["edges_csv"])
    assert [(e.camera, e.view) for e in back] == [(e.camera, e.view) for e in edges]
    for a, b in zip(back, edges, strict=True):
        assert np.allclose(a.T_cam_board, b.T_cam_board, atol=1e-14)
    vertices, g_edges, _ = read_g2o(paths["g2o"].read_text())
    assert len(vertices) == 4 + len(boards) and len(g_edges) == len(edges)
    compile(paths["ros2_launch"].read_text(), "launch.py", "exec")


# ---------------------------------------------------------------------------------------------
# Exports of a calibration whose views changed after the pose graph (issue 32, item 7): the
# markers detected again with a refined lens give other views than the pose graph solved.


@pytest.fixture(scope="module")
def tiny_result(tiny_dataset):
    """The library calibration of the tiny rig (4 cameras, 640x360, 4 frames), no depth."""
    from rgbd_calib.core.config import load_config
    from rgbd_calib.model.board import thesis_board
    from rgbd_calib.model.dataset import FolderDataset
    from rgbd_calib.pipelines.calibrate import calibrate

    dataset = FolderDataset(tiny_dataset)
    config = load_config(None, workers=1, refine="none")
    return dataset, calibrate(dataset, thesis_board(), config)


def _graph_views(result) -> dict[tuple[str, str], np.ndarray]:
    """The pose graph's used views: (camera, frame) -> T_cam_board of the view it solved."""
    pg = result.posegraph
    return {(pg.edges[i].camera, pg.edges[i].view): pg.edges[i].T_cam_board
            for i in pg.used_edges}


def _assert_exports_pair_the_graphs_views(result, exports: Path) -> None:
    """Edges.csv and the g2o file hold exactly the pose graph's used edges: each row's camera,
    view and T_cam_board are those of the edge it came from."""
    graph = _graph_views(result)
    rows = read_edges_csv(exports / EXPORT_FILES["edges_csv"])
    assert len(rows) == len(graph)
    for row in rows:
        assert (row.camera, row.view) in graph, (row.camera, row.view)
        assert np.allclose(row.T_cam_board, graph[row.camera, row.view], atol=1e-12)
    used = result.posegraph.used_pose_edges
    _, g_edges, _ = read_g2o((exports / EXPORT_FILES["g2o"]).read_text())
    assert len(g_edges) == len(used)
    for (_, _, T, _), e in zip(g_edges, used, strict=True):
        assert_transforms_close(T, e.T_cam_board, 1e-6, 1e-5)  # g2o text: 9 digits


@pytest.mark.parametrize("change", ["fewer", "reordered"])
def test_exports_after_the_views_changed_pair_the_pose_graphs_edges(tiny_result, tmp_path,
                                                                    change):
    """The result's views differ from the pose graph's, as after ``_redetect``: one view fewer
    (before the fix: ``exports/ not written (IndexError)``) or the same count in another order
    with moved poses (before the fix: Edges.csv silently paired other views). The exports are
    written and pair the pose graph's own edges."""
    from dataclasses import replace

    from rgbd_calib.outputs.writer import write_outputs

    dataset, result = tiny_result
    views = list(result.observations)
    assert len(views) == len(result.posegraph.edges)
    nudge = make_transform(np.eye(3), [0.003, 0.0, 0.0])  # a redetected pose: 3 mm elsewhere
    views = (views[1:] if change == "fewer" else
             [replace(o, T_cam_board=o.T_cam_board @ nudge) for o in reversed(views)])
    changed = replace(result, observations=views)
    # the precondition: a list rebuilt from the new views does not pair like the graph's
    rebuilt = [(o.camera, o.frame) for o in views]
    assert any(i >= len(rebuilt) or rebuilt[i] != (e.camera, e.view)
               for i, e in zip(result.posegraph.used_edges, result.posegraph.used_pose_edges,
                               strict=True))
    warned: list[str] = []
    written = write_outputs(changed, dataset.rig, tmp_path / "out", warn=warned.append)
    assert not [w for w in warned if "exports" in w], warned
    assert tmp_path / "out" / "exports" / EXPORT_FILES["edges_csv"] in written
    _assert_exports_pair_the_graphs_views(changed, tmp_path / "out" / "exports")


def test_pose_graph_result_carries_the_edges_it_solved(tiny_result):
    """The edges in the result are the list the graph was given (PnP covariances, no floor),
    one per residual; a result whose edges do not match its residuals is refused."""
    from dataclasses import replace

    from rgbd_calib.core.errors import CalibrationError

    _, result = tiny_result
    pg = result.posegraph
    assert len(pg.edges) == len(pg.residuals) > 0
    for r, e, o in zip(pg.residuals, pg.edges, result.observations, strict=True):
        assert (r.camera, r.view) == (e.camera, e.view) == (o.camera, o.frame)
        assert e.T_cam_board is o.T_cam_board
    with pytest.raises(CalibrationError, match="edges"):
        replace(pg, edges=pg.edges[1:])
    with pytest.raises(CalibrationError, match="edges it was solved on"):
        _ = replace(pg, edges=()).used_pose_edges


def test_exports_after_the_markers_were_detected_again(tmp_path_factory, tmp_path):
    """End to end: a lens rig.yaml does not list (thesis-line, 640x360, 8 frames, seed 3,
    the lens of test_distortion_pipeline) makes the self-calibration refine it and detect the
    markers again; the exports are written and pair the pose graph's views."""
    from dataclasses import replace

    from conftest import shared_render

    from rgbd_calib.core.config import load_config
    from rgbd_calib.model.board import thesis_board
    from rgbd_calib.model.dataset import FolderDataset
    from rgbd_calib.outputs.writer import write_outputs
    from rgbd_calib.pipelines.calibrate import calibrate
    from rgbd_calib.synth.render import SynthParams

    lens = (0.08, -0.15, 5e-4, -5e-4, 0.03)
    params = SynthParams(resolution=(640, 360), distortion=lens, rig_distortion="truth")
    path = shared_render(tmp_path_factory, "distorted_line", "thesis-line", 8, 3,
                         params=params).path
    truth = FolderDataset(path).rig
    pinhole = Rig({c: replace(i, distortion=(0.0,) * 5) for c, i in truth.cameras.items()},
                  truth.reference)
    dataset = FolderDataset(path, pinhole)
    result = calibrate(dataset, thesis_board(), load_config(None, workers=2, refine="none"))
    assert result.self_calibration is not None and result.self_calibration.redetected
    warned: list[str] = []
    write_outputs(result, dataset.rig, tmp_path / "out", warn=warned.append)
    assert not [w for w in warned if "exports" in w], warned
    _assert_exports_pair_the_graphs_views(result, tmp_path / "out" / "exports")


# ---------------------------------------------------------------------------------------------
# The verdict in every export (issue 34 item 1): a file copied on its own says what it is worth,
# and each still reads back with its consumer.


def _rig(names: list[str]) -> Rig:
    return Rig({n: CameraIntrinsics(640, 360, 320.0, 320.0, 319.5, 179.5) for n in names},
               names[0])


def test_every_export_states_the_verdict_and_still_reads_back(tmp_path, calibration):
    from dataclasses import replace

    from rgbd_calib.model.results import Verdict

    extrinsics, edges, boards = calibration
    reason = "not_calibrated [cam11]: cam11 was not calibrated -- see --board-model <x> & \"y\""
    judged = replace(extrinsics, verdict=Verdict("poor", reason))
    rig = _rig(list(extrinsics.cameras))
    paths = write_exports(judged, tmp_path, rig=rig, edges=edges, board_poses=boards)
    plain = write_exports(extrinsics, tmp_path / "plain", rig=rig, edges=edges,
                          board_poses=boards)
    line = f"rgbd-calib verdict: POOR: {reason}"
    head = {kind: path.read_text().splitlines()[:3] for kind, path in paths.items()}
    for kind in ("kalibr", "ros2_launch", "g2o"):
        assert f"# {line}" in head[kind], (kind, head[kind])
    # XML comments may not hold "--": the URDF's says it with "- -"
    assert f"<!-- {line.replace('--', '- -')} -->" in head["urdf"]
    root = ET.parse(paths["urdf"]).getroot()
    assert root.tag == "robot" and len(root.findall("joint")) == 3
    assert yaml.safe_load(paths["kalibr"].read_text())["cam1"]["T_cn_cnm1"]
    assert len(_launch_nodes(paths["ros2_launch"].read_text())) == 3
    vertices, g_edges, _ = read_g2o(paths["g2o"].read_text())
    assert len(vertices) == 4 + len(boards) and len(g_edges) == len(edges)
    # JSON has no comments: a key, Open3D's files a namespaced one its readers skip
    import json

    unity = json.loads(paths["unity"].read_text())
    assert unity["verdict"] == {"grade": "poor", "reason": reason}
    open3d_files = [k for k in paths if k.startswith("open3d")]
    assert len(open3d_files) == 2 + len(extrinsics.cameras)
    for kind in open3d_files:
        assert json.loads(paths[kind].read_text())["rgbd_calib_verdict"]["grade"] == "poor"
    o3d = pytest.importorskip("open3d")
    assert len(o3d.io.read_pose_graph(str(paths["open3d_posegraph"])).nodes) == 4
    assert len(o3d.io.read_pinhole_camera_trajectory(
        str(paths["open3d_trajectory"])).parameters) == 4
    cam8 = o3d.io.read_pinhole_camera_parameters(str(paths["open3d_camera:cam8"]))
    assert np.allclose(cam8.extrinsic, invert_transform(extrinsics.T_ref_cam("cam8")))
    # the thesis CSVs keep their one-header-row format, byte for byte
    for kind in ("nodes_csv", "edges_csv"):
        assert paths[kind].read_bytes() == plain[kind].read_bytes()
    # unjudged extrinsics (posegraph, a hand-made Extrinsics) write no verdict at all
    assert not any("verdict" in p.read_text() for p in plain.values())
