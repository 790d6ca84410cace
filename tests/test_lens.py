"""The lens interface (issue 57): OpenCV's k1 k2 p1 p2 k3 and the equidistant fisheye
(cv2.fisheye, Kalibr's pinhole-equi) behind one camera model, through PnP, the bundle
adjustment's parameter names, rig.yaml and the exports."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from rgbd_calib.cli.commands import app
from rgbd_calib.core.camera import FISHEYE, CameraIntrinsics
from rgbd_calib.core.errors import ConfigError
from rgbd_calib.model.results import CameraExtrinsics, Extrinsics
from rgbd_calib.model.rig import Rig, parse_camera
from rgbd_calib.outputs.exports import kalibr_camchain, ros_distortion
from rgbd_calib.solve.bundle_factors import lens_names, with_parameters
from rgbd_calib.solve.pose import _solve, pose_jacobian, pose_jacobian_numeric, project_points

FISH = CameraIntrinsics(1280, 720, 500.0, 502.0, 640.0, 360.0, (0.05, -0.01, 0.003, -0.0005),
                        lens=FISHEYE)


def _points(n=300, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.2, 1.2, n),
                            rng.uniform(0.5, 3.0, n)])


def test_the_fisheye_projects_as_cv2_fisheye_and_undistorts_back():
    P = _points()
    uv = FISH.project(P)
    cv_uv, _ = cv2.fisheye.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                         FISH.K, FISH.dist)
    assert np.abs(uv - cv_uv.reshape(-1, 2)).max() < 1e-9
    rays = FISH.rays(uv[:, 0], uv[:, 1])
    assert np.abs(rays[:, :2] - P[:, :2] / P[:, 2:]).max() < 1e-10
    assert np.abs(FISH.project(P[:1] * 0 + [0.0, 0.0, 1.0]) - [640.0, 360.0]).max() < 1e-12


def test_the_fisheyes_derivatives_are_its_projections():
    P = _points(50, 1)
    uv0, J = FISH.project_jacobian(P)
    eps = 1e-6
    for i in range(3):
        step = np.zeros(3)
        step[i] = eps
        numeric = (FISH.project(P + step) - FISH.project(P - step)) / (2 * eps)
        assert np.abs(numeric - J[:, :, i]).max() < 1e-4
    Ji = FISH.intrinsics_jacobian(P)
    assert FISH.parameter_names == ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    for j, name in enumerate(FISH.parameter_names):
        plus, minus = (with_parameters(FISH, (name,), np.array([FISH.parameters[name] + s]))
                       for s in (eps, -eps))
        numeric = (plus.project(P) - minus.project(P)) / (2 * eps)
        assert np.abs(numeric - Ji[:, :, j]).max() < 1e-4, name


def test_the_bundles_lens_names_are_the_fisheyes_own():
    opencv = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    assert lens_names(FISH, opencv) == ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    assert lens_names(FISH, ("fx", "fy")) == ("fx", "fy")
    plain = replace(FISH, lens="opencv", distortion=(0.0,) * 5)
    assert lens_names(plain, opencv) == opencv
    moved = with_parameters(FISH, opencv, np.arange(1.0, 9.0))
    assert moved.lens == FISHEYE and moved.distortion == (5.0, 6.0, 7.0, 8.0)


def test_pnp_through_a_fisheye_finds_the_pose_its_pixels_were_made_with():
    rng = np.random.default_rng(3)
    board = np.column_stack([rng.uniform(0, 0.6, 40), rng.uniform(0, 0.4, 40), np.zeros(40)])
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.3, -0.5, 0.2]))[0]
    T[:3, 3] = [0.4, -0.1, 1.2]
    px = project_points(T, board, FISH)
    found, _, _ = _solve(board, px, FISH, planar=True)
    assert np.abs(found - T).max() < 1e-6
    assert np.abs(pose_jacobian(T, board, FISH) - pose_jacobian_numeric(T, board, FISH)).max() \
        < 1e-3


def test_rig_yaml_names_the_lens_model_and_refuses_a_fisheye_of_five():
    raw = {"width": 1280, "height": 720, "fx": 500, "fy": 500, "cx": 640, "cy": 360,
           "model": "fisheye", "distortion": [0.05, -0.01, 0.003, -0.0005]}
    cam = parse_camera(raw, "rig.yaml: cameras.c")
    assert cam.lens == FISHEYE and cam.to_dict()["model"] == "fisheye"
    assert "model" not in replace(cam, lens="opencv", distortion=(0.0,) * 5).to_dict()
    for bad, says in (({**raw, "distortion": [0.05, -0.01, 0.003, -0.0005, 0.0]}, "4 finite"),
                      ({**raw, "model": "kannala"}, "not a lens model"),
                      ({"width": 1280, "height": 720, "model": "fisheye"}, "from scratch")):
        with pytest.raises(ConfigError) as err:
            parse_camera(bad, "rig.yaml: cameras.c")
        assert "\n" not in str(err.value) and says in str(err.value)


def test_calibrate_with_a_fisheye_of_five_coefficients_exits_2_and_writes_nothing(tmp_path):
    dataset = tmp_path / "ds"
    (dataset / "c" / "color").mkdir(parents=True)
    (dataset / "rig.yaml").write_text(
        "cameras:\n  c: {width: 1280, height: 720, fx: 500, fy: 500, cx: 640, cy: 360, "
        "model: fisheye, distortion: [0.05, -0.01, 0.003, -0.0005, 0]}\n")
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["calibrate", str(dataset), "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert "4 finite coefficients" in result.output and not out.exists()


def test_the_exports_carry_the_lens_model():
    rig = Rig({"a": FISH, "b": replace(FISH, lens="opencv", distortion=(0.1, 0.0, 0.0, 0.0,
                                                                             0.0))}, "a")
    ex = Extrinsics("a", {c: CameraExtrinsics(c, np.eye(4)) for c in ("a", "b")})
    chain, _ = kalibr_camchain(ex, rig)
    assert chain["cam0"]["distortion_model"] == "equidistant"
    assert chain["cam0"]["distortion_coeffs"] == list(FISH.distortion)
    assert chain["cam1"]["distortion_model"] == "radtan"
    assert ros_distortion(FISH) == ("equidistant", list(FISH.distortion))
    assert ros_distortion(rig.cameras["b"])[0] == "plumb_bob"


def test_a_fisheye_with_zero_coefficients_is_equidistant_not_a_pinhole():
    """rig.yaml's "unknown lens" of a fisheye is its zeros: theta_d = theta, not r."""
    zero = replace(FISH, distortion=(0.0,) * 4)
    assert zero.has_distortion
    P = np.array([[1.0, 0.5, 1.0]])
    r = np.hypot(1.0, 0.5)
    expected = np.array([640.0, 360.0]) + np.array([500.0, 502.0]) * P[0, :2] * np.arctan(r) / r
    assert np.abs(zero.project(P)[0] - expected).max() < 1e-9
    assert np.abs(project_points(np.eye(4), P, zero)[0] - expected).max() < 1e-9


def test_the_ladder_names_a_fisheye_rigs_lens_by_its_own_coefficients():
    from rgbd_calib.core.config import BundleConfig
    from rgbd_calib.solve.ladder import _in_the_rigs_lens_names

    config = BundleConfig()
    fish = _in_the_rigs_lens_names(config, Rig({"a": FISH, "b": FISH}, "a"))
    assert fish.intrinsics_params == ["fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"]
    mixed = Rig({"a": FISH, "b": replace(FISH, lens="opencv", distortion=(0.0,) * 5)}, "a")
    assert _in_the_rigs_lens_names(config, mixed) is config


def test_a_fisheyes_back_projection_moves_with_its_coefficients_as_its_rays_do():
    """The depth pairs' lens uncertainty (rig_refined.yaml's sigmas): d point / d k of a point
    back-projected from a fixed pixel at fixed depth, for a fisheye's k1..k4 (before: a
    KeyError 'k4' failed every pair of a self-calibrated fisheye rig)."""
    from rgbd_calib.depth.information import back_projection_jacobian

    P = _points(40, 2)
    names = ["fx", "cx", "k1", "k2", "k3", "k4"]
    J = back_projection_jacobian(P, FISH, names)
    uv = FISH.project(P)
    eps = 1e-7
    for k, name in enumerate(names[2:], start=2):
        moved = with_parameters(FISH, (name,), np.array([FISH.parameters[name] + eps]))
        rays = moved.rays(uv[:, 0], uv[:, 1])
        numeric = (rays * P[:, 2:] - P) / eps
        assert np.abs(numeric - J[:, :, k]).max() < 1e-4 * np.abs(J[:, :, k]).max() + 1e-6
