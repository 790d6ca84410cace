"""Issue 14, item 3: refine knows its depth scales or does not move along what they confound."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
from analytic_scene import CAM_A, CAM_B, RECTS, scene_cloud

from rgbd_calib.depth import registration as D
from rgbd_calib.depth import stage as S
from rgbd_calib.model import calib_folder as CF
from rgbd_calib.model.results import CameraExtrinsics, Extrinsics
from rgbd_calib.pipelines import refine as R

SCALE_ERROR = 1.01  # camera a's depth reads 1 % long


def test_unknown_depth_scale_does_not_count_a_move_it_explains():
    """a's depth 1 % long, both cameras at their true poses: ICP shifts a to absorb the scale.
    Told the scale is known, that shift looks like a significant correction; with a's scale
    free the pair's information leaves that direction out (the verdict says so, below)."""
    rng = np.random.default_rng(9)
    a = scene_cloud("a", CAM_A, RECTS, rng)
    a = replace(a, points=a.points * np.float32(SCALE_ERROR))
    b = scene_cloud("b", CAM_B, RECTS, rng)
    known = D.register_pair(a, b, CAM_A, CAM_B, "colored-icp")
    free = D.register_pair(a, b, CAM_A, CAM_B, "colored-icp", free_scale=(True, False))
    assert known.correction_mm > 5.0  # the scale error moved it (2-3 m away: 20-30 mm)
    assert known.accepted and known.improvement_chi2 > 12.59
    # measured: 54434 -> 165; what is left is the part of a scale error no rigid move explains
    assert free.improvement_chi2 < 0.01 * known.improvement_chi2


def test_depth_scales_read_from_the_calibration_report(tmp_path):
    report = tmp_path / "report.json"
    assert CF.load_depth_scales(report) == {}
    report.write_text(json.dumps({"cameras": {
        "left0": {"depth_scale_factor": 1.004}, "left1": {"depth_scale_factor": None}}}))
    assert CF.load_depth_scales(report) == {"left0": 1.004}


def test_depth_models_beside_the_calibration_take_over_its_factors(tmp_path):
    """check and refine correct each camera's depth as its calibration did: the model of its
    depth_model.yaml (an identity one too: the evidence chose no term), else its factor."""
    from rgbd_calib.core.depth_model import DepthModel
    from rgbd_calib.model.depth_model_file import save_depth_models

    assert CF.load_depth_corrections(tmp_path) == {}
    (tmp_path / "report.json").write_text(json.dumps({"cameras": {
        "left0": {"depth_scale_factor": 1.004}, "left1": {"depth_scale_factor": 0.998}}}))
    assert CF.load_depth_corrections(tmp_path) == {"left0": 1.004, "left1": 0.998}
    scaled = DepthModel(50.0, {"scale": 1.003}, terms=("scale",), sigmas={"scale": 0.0005})
    save_depth_models({"left0": scaled, "left1": DepthModel(50.0)},
                      tmp_path / "depth_model.yaml")
    got = CF.load_depth_corrections(tmp_path)
    assert set(got) == {"left0", "left1"}
    assert got["left0"].value("scale") == 1.003 and got["left1"].is_identity


def test_initial_sigmas_become_priors_and_the_verdict_names_the_outcome():
    T1 = np.eye(4)
    T1[0, 3] = 1.0
    init = Extrinsics("ref", {
        "ref": CameraExtrinsics("ref", np.eye(4), 0.0, 0.0),
        "good": CameraExtrinsics("good", T1, 0.003, 0.05),
        "hand": CameraExtrinsics("hand", T1),  # hand-measured: no sigma, no prior
    })
    priors = R.initial_pose_priors(init, {c: e.T_ref_cam for c, e in init.cameras.items()})
    assert [(p.cam_a, p.cam_b) for p in priors] == [("good", "ref")]
    np.testing.assert_allclose(1.0 / np.sqrt(np.diag(priors[0].information))[3:], 5e-5)
    depth = S.DepthRefinement("colored-icp", {}, {}, [], [], {}, fallback="no pair overlaps",
                              scale_source={"good": "unknown"})
    verdict = R.refine_verdict(init, init, depth)
    assert verdict["verdict"] == "unchanged" and "no pair overlaps" in verdict["message"]
    assert "depth scale unknown for good" in verdict["message"]
    moved = T1.copy()
    moved[0, 3] += 0.001  # 1 mm: 20 of its 0.05 mm sigmas
    result = Extrinsics("ref", {**init.cameras, "good": CameraExtrinsics("good", moved)})
    fitted = replace(D.failed_registration("good", "ref", "colored-icp", np.eye(4), "-"),
                     accepted=True, reason=None, rejected_by=())
    depth = replace(depth, fallback=None, pairs=[D.DepthPair(fitted)])
    verdict = R.refine_verdict(init, result, depth)
    assert verdict["verdict"] == "check" and "good moved by more than 3" in verdict["message"]
