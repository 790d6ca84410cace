"""Depth-only refinement on real RGB-D data (issue 4): two frames of a TUM RGB-D sequence
(Kinect v1, motion-capture ground truth) as two cameras, started 2 cm / 2 deg off the truth,
must land within 1 cm and 1.5 deg.

The real sample lives in ``tests/data/tum_fr1_xyz_pair`` and is made from a TUM sequence by
``tools/make_real_rgbd_sample.py``; until it is committed the real-data tests skip. The
converter itself is tested here on a TUM-layout sequence rendered from a known trajectory
(association, mocap interpolation, quaternion order, T_a_b direction, 5000 counts/m)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from rgbd_calib.camera import CameraIntrinsics
from rgbd_calib.dataset import FolderDataset
from rgbd_calib.geometry import (
    look_at,
    make_transform,
    matrix_to_quaternion_xyzw,
    rotvec_to_matrix,
    transform_error,
)
from rgbd_calib.refine import refine_extrinsics
from rgbd_calib.results import load_extrinsics
from rgbd_calib.scene import box, rect
from rgbd_calib.synth import SynthCamera, load_ground_truth, render_background

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "tests" / "data" / "tum_fr1_xyz_pair"
MAX_MM, MAX_DEG = 10.0, 1.5  # issue 4: within 1 cm and 1.5 deg of the mocap truth


def _tool():
    """tools/make_real_rgbd_sample.py as a module (tools/ is not a package)."""
    name = "make_real_rgbd_sample"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod  # dataclasses look their module up while it executes
        spec.loader.exec_module(mod)
    return sys.modules[name]


def _refine(path: Path, method: str):
    gt = load_ground_truth(path)
    init = load_extrinsics(path / "init_extrinsics.yaml")
    before = transform_error(init.T_ref_cam("b"), gt.T_ref_cam["b"])
    ext, depth = refine_extrinsics(FolderDataset(path), init, method)
    after = transform_error(ext.T_ref_cam("b"), gt.T_ref_cam["b"])
    return before, after, depth


# --------------------------------------------------------------------------- real data
real = pytest.mark.skipif(not (SAMPLE / "rig.yaml").is_file(),
                          reason=f"real TUM sample not present ({SAMPLE.relative_to(REPO)}); "
                          "make it with tools/make_real_rgbd_sample.py")


@real
@pytest.mark.parametrize("method", ["colored-icp", "geometric"])
def test_refine_on_real_tum_pair(method):
    (deg0, mm0), (deg1, mm1), depth = _refine(SAMPLE, method)
    print(f"\n{method}: b error {mm0:.1f} mm / {deg0:.2f} deg -> {mm1:.1f} mm / {deg1:.3f} deg; "
          f"pairs {[(p['accepted'], p.get('reason')) for p in depth.pairs]}")
    assert 15.0 <= mm0 <= 25.0 and 1.5 <= deg0 <= 2.5  # the start really is 2 cm / 2 deg off
    assert mm1 <= MAX_MM and deg1 <= MAX_DEG, (method, mm1, deg1)


# --------------------------------------------------------------------------- converter
K_ROS = CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5, depth_scale=0.0002)
T_A_B = make_transform(rotvec_to_matrix(np.array([0.2, 1.0, 0.1]) / math.sqrt(1.05)
                                        * math.radians(8.0)), [0.12, -0.03, 0.08])


def _corner_scene():
    """A room corner (two walls and the floor, z up) with three boxes: textured, and
    geometrically well conditioned for ICP."""
    s = [
        rect((0, 0, 0), (4, 0, 0), (0, 4, 0), (0.55, 0.6, 0.62), 11, 0.08),  # floor
        rect((0, 0, 0), (0, 4, 0), (0, 0, 3), (0.7, 0.72, 0.6), 21, 0.1),  # wall x = 0
        rect((0, 0, 0), (4, 0, 0), (0, 0, 3), (0.75, 0.65, 0.6), 41, 0.1),  # wall y = 0
    ]
    s += box((0.4, 0.9, 0.0), (0.8, 1.3, 0.5), (0.3, 0.5, 0.8), 100, 0.04)
    s += box((1.0, 0.3, 0.0), (1.3, 0.6, 0.8), (0.8, 0.4, 0.3), 110, 0.04)
    s += box((0.2, 0.2, 0.9), (0.5, 0.45, 1.2), (0.4, 0.75, 0.4), 120, 0.04)
    return s


def _write_tum_sequence(root: Path) -> None:
    """Two still phases (at pose A, t in [1.0, 1.2]; at pose B, t in [2.0, 2.2]) joined by
    a move; mocap at 100 Hz (offset 3 ms), colour at 1.05 / 2.05 / 2.60 s (the last has no
    depth), depth 12 ms after colour, Kinect-like depth noise 1.4e-3 z^2."""
    T_w_a = look_at([1.8, 1.8, 1.3], [0.3, 0.3, 0.6])
    T_w_b = T_w_a @ T_A_B
    tool = _tool()
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    qa, qb = matrix_to_quaternion_xyzw(T_w_a[:3, :3]), matrix_to_quaternion_xyzw(T_w_b[:3, :3])
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for t in np.arange(0.903, 2.4, 0.01):
        s = float(np.clip(t - 1.2, 0.0, 0.8) / 0.8)
        p = (1 - s) * T_w_a[:3, 3] + s * T_w_b[:3, 3]
        q = tool.slerp(qa, qb, s)
        gt.append(f"{t:.4f} " + " ".join(f"{x:.6f}" for x in (*p, *q)))
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    scene = _corner_scene()
    rng = np.random.default_rng(5)
    rgb, dep = ["# color images"], ["# depth maps"]
    for t, T in ((1.05, T_w_a), (2.05, T_w_b)):
        bg = render_background(scene, SynthCamera("k", K_ROS, T), samples=1)
        z = np.where(np.isfinite(bg.depth), bg.depth, 0.0)
        z = z + rng.normal(0.0, 1.0, z.shape) * 1.4e-3 * z**2
        counts = np.where((z > 0.5) & (z < 4.5), np.rint(z * 5000.0), 0).astype(np.uint16)
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"),
                    np.clip(np.rint(bg.color * 255), 0, 255).astype(np.uint8))
        cv2.imwrite(str(root / "depth" / f"{t + 0.012:.6f}.png"), counts)
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        dep.append(f"{t + 0.012:.6f} depth/{t + 0.012:.6f}.png")
    rgb.append("2.600000 rgb/2.600000.png")  # no depth near it: dropped by the association
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(dep) + "\n")


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    root = tmp_path_factory.mktemp("tum")
    seq = root / "rgbd_dataset_rendered"
    _write_tum_sequence(seq)
    out = root / "sample"
    assert _tool().main([str(seq), "--out", str(out), "--max-rgb-depth-dt", "0.02"]) == 0
    return seq, out


def test_converter_writes_the_folder_form(converted):
    seq, out = converted
    ds = FolderDataset(out)
    assert ds.cameras == ["a", "b"] and ds.rig.reference == "a"
    for c in ("a", "b"):
        intr = ds.rig.cameras[c]
        assert (intr.fx, intr.fy, intr.cx, intr.cy) == (525.0, 525.0, 319.5, 239.5)
        assert intr.depth_scale == pytest.approx(1 / 5000)
    # PNGs copied byte for byte, in time order
    assert (out / "a" / "color" / "000000.png").read_bytes() == \
        (seq / "rgb" / "1.050000.png").read_bytes()
    assert (out / "b" / "depth" / "000000.png").read_bytes() == \
        (seq / "depth" / "2.062000.png").read_bytes()
    readme = (out / "README.md").read_text()
    assert "CC BY 4.0" in readme and "Sturm" in readme


def test_converter_ground_truth_and_start(converted):
    _, out = converted
    gt = load_ground_truth(out)
    deg, mm = transform_error(gt.T_ref_cam["b"], T_A_B)
    assert mm < 0.01 and deg < 1e-4  # T_a_b = inv(T_world_a) @ T_world_b, quaternions xyzw
    init = load_extrinsics(out / "init_extrinsics.yaml")
    deg0, mm0 = transform_error(init.T_ref_cam("b"), T_A_B)
    assert mm0 == pytest.approx(20.0, abs=0.01) and deg0 == pytest.approx(2.0, abs=1e-3)
    np.testing.assert_allclose(init.T_ref_cam("a"), np.eye(4))


@pytest.mark.parametrize("method", ["colored-icp", "geometric"])
def test_refine_on_converted_rendered_pair(converted, method):
    _, out = converted
    (deg0, mm0), (deg1, mm1), _ = _refine(out, method)
    assert mm1 <= MAX_MM / 2 and deg1 <= MAX_DEG / 2, (method, mm0, deg0, mm1, deg1)
