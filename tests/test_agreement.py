"""Issue 33, item 4: the fused cloud's agreement in the overlaps, in mm, before and after the
depth models, and the camera it points to (analytic scene, D435 noise)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from analytic_scene import CAM_A, CAM_B, RECTS, look_at, scene_cloud

from rgbd_calib.core.depth_model import DepthModel
from rgbd_calib.depth.agreement import fused_agreement

CAM_C = look_at([0.0, 0.8, 1.7], [1.8, 0.5, 0.3])
LONG = DepthModel(40.0, {"scale": 0.99}, terms=("scale",))  # true = measured / 0.99: reads short


def _clouds(seed=3):
    rng = np.random.default_rng(seed)
    return {n: scene_cloud(n, T, RECTS, rng) for n, T in (("a", CAM_A), ("b", CAM_B),
                                                          ("c", CAM_C))}


POSES = {"a": CAM_A, "b": CAM_B, "c": CAM_C}
PAIRS = [("a", "b"), ("a", "c"), ("b", "c")]


def test_true_depth_agrees_within_the_noise():
    agree = fused_agreement(_clouds(), POSES, PAIRS, {})
    assert len(agree.pairs) == 3 and not agree.off_cameras and not agree.ambiguous
    for p in agree.pairs:
        assert p.before is None and not p.off
        assert abs(p.after.median_mm) < max(0.5, 3 * p.after.median_se_mm)
        assert p.after.n > 1000
        # the p90 of two independent noisy surfaces, as the noise model predicts (+-30 %)
        assert 0.7 < p.after.p90_mm / p.noise_p90_mm < 1.3


def test_a_camera_off_is_named_and_its_model_measured_before_and_after():
    clouds = _clouds()
    # a's depth reads 1 % short and nothing corrects it: a's surfaces lie in front of b's, c's
    short = {**clouds, "a": replace(clouds["a"], points=(LONG.measured_points(
        clouds["a"].points.astype(float))).astype(np.float32))}
    agree = fused_agreement(short, POSES, PAIRS, {})
    by = {(p.cam_a, p.cam_b): p for p in agree.pairs}
    assert by["a", "b"].off and by["a", "c"].off and not by["b", "c"].off
    assert by["a", "b"].after.median_mm < -5.0  # 1 % of 1.5-3 m, along the normals
    assert agree.off_cameras == ["a"] and agree.ambiguous == []
    assert agree.camera_bias_mm["a"] < -5.0 and abs(agree.camera_bias_mm["b"]) < 1.0
    # the same error, corrected by a's model: after agrees, before shows what it corrected
    fixed = fused_agreement(clouds, POSES, PAIRS, {"a": LONG})
    by = {(p.cam_a, p.cam_b): p for p in fixed.pairs}
    assert not fixed.off_cameras and not any(p.off for p in fixed.pairs)
    assert by["a", "b"].before is not None and by["b", "c"].before is None
    assert by["a", "b"].before.median_mm < -5.0 and abs(by["a", "b"].after.median_mm) < 1.0
    assert fixed.worst_bias_mm(before=True) > 5.0 > 1.0 > fixed.worst_bias_mm()


def test_one_off_pair_between_two_cameras_is_ambiguous():
    clouds = _clouds()
    short = {**clouds, "a": replace(clouds["a"], points=(LONG.measured_points(
        clouds["a"].points.astype(float))).astype(np.float32))}
    agree = fused_agreement({k: short[k] for k in "ab"}, POSES, [("a", "b")], {})
    assert agree.off_cameras == [] and agree.ambiguous == [("a", "b")]


def test_calibrate_reports_the_fused_cloud_agreement(tiny_calibration):
    """A clean rig (true depth): every overlapping pair within the noise, identity models, the
    figures in report.json and report.html and one console line."""
    import json

    _, out, console = tiny_calibration
    report = json.loads((out / "report.json").read_text())
    agree = report["fused_agreement"]
    assert agree["pairs"] and agree["off_cameras"] == [] and agree["ambiguous"] == []
    assert agree["worst_bias_mm"] < 1.0
    assert all(p["before"] is None for p in agree["pairs"])  # identity models: nothing undone
    assert "fused_disagrees" not in {w["code"] for w in report["warnings"]}
    assert "fused cloud: cameras agree within" in console
    page = (out / "report.html").read_text()
    assert "Fused cloud (depth models)" in page and "beyond the noise" in page


def test_a_failing_measurement_never_ends_the_run(monkeypatch):
    """The agreement measures the result; if it fails the calibration stands, with a warning."""
    import pytest

    from rgbd_calib.depth import stage

    def broken(*args, **kwargs):
        raise ValueError("no normals")

    clouds = _clouds()
    depth = stage.DepthRefinement("colored-icp", {}, clouds, [], [], dict(POSES))
    monkeypatch.setattr(stage, "fused_agreement", broken)
    with pytest.warns(RuntimeWarning, match="could not be measured.*no normals"):
        out = stage.measure_agreement(depth, POSES)
    assert out is depth and out.agreement is None
