"""Issue 33, item 2: the overlaps' median surface distances as measurements on the depth
models the board fitted (rgbd_calib.depth.overlap_models; analytic scene, D435 noise)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from analytic_scene import CAM_A, CAM_B, INTR, RECTS, look_at, scene_cloud

from rgbd_calib.core.depth_model import DepthModel, identity_model
from rgbd_calib.depth.agreement import fused_agreement
from rgbd_calib.depth.overlap_models import overlap_samples, recorrected, update_models

CAM_C = look_at([0.0, 0.8, 1.7], [1.8, 0.5, 0.3])
POSES = {"a": CAM_A, "b": CAM_B, "c": CAM_C}
PAIRS = [("a", "b"), ("a", "c"), ("b", "c")]
FB = 40.0  # focal x baseline (px m)
TRUE_A = DepthModel(FB, {"d0": 0.1}, ("scale", "offset"))  # 10 mm short at 2 m, uncorrected
PRIOR = np.diag([0.002, 0.1]) ** 2  # what a board at 1-2 m leaves of scale and offset


def _clouds(seed=3):
    rng = np.random.default_rng(seed)
    clouds = {n: scene_cloud(n, T, RECTS, rng) for n, T in POSES.items()}
    # a measures through its true depth error
    return {**clouds, "a": replace(clouds["a"], points=TRUE_A.measured_points(
        clouds["a"].points.astype(float)).astype(np.float32))}


def _board_fit(d0: float) -> DepthModel:
    return DepthModel(FB, {"d0": d0}, ("scale", "offset"), {"scale": 0.002, "d0": 0.1})


def _update(clouds, fit, extrinsics_cov=None):
    models = {"a": fit, "b": identity_model(INTR), "c": identity_model(INTR)}
    corrected = {**clouds, "a": recorrected(clouds["a"], None, fit)}
    return corrected, update_models(models, {"a": PRIOR},
                                    overlap_samples(corrected, POSES, PAIRS, models), POSES,
                                    extrinsics_cov)


def test_the_overlaps_pull_a_model_the_board_left_loose_to_the_truth():
    clouds = _clouds()
    corrected, update = _update(clouds, _board_fit(0.0))  # the board missed a's offset
    assert update is not None and set(update.models) == {"a"}
    new = update.models["a"]
    sigma = np.sqrt(np.diag(update.covariances["a"]))
    assert abs(new.value("d0") - 0.1) < 3 * sigma[1] and sigma[1] < 0.1 / 3
    assert new.sigmas["d0"] == sigma[1] and new.terms == ("scale", "offset")
    before = {(m.cam_a, m.cam_b): m for m in update.before}
    after = {(m.cam_a, m.cam_b): m for m in update.after}
    assert before["a", "b"].median_mm < -3.0 and abs(after["a", "b"].median_mm) < 0.5
    assert set(after) == {("a", "b"), ("a", "c")}  # a pair of held cameras says nothing
    # the cloud corrected by the update agrees with the others, as the report measures it
    fixed = {**corrected, "a": recorrected(corrected["a"], _board_fit(0.0), new)}
    agree = fused_agreement(fixed, POSES, PAIRS, {"a": new})
    assert not agree.off_cameras and agree.worst_bias_mm() < 1.0


def test_a_right_model_stays_within_its_sigma():
    _, update = _update(_clouds(), _board_fit(0.1))
    sigma = np.sqrt(update.covariances["a"][1, 1])
    assert abs(update.models["a"].value("d0") - 0.1) < 2 * sigma
    assert all(abs(m.median_mm) < 0.5 for m in update.after)


def test_uncertain_extrinsics_weigh_the_overlaps_down():
    """A pair whose cameras' extrinsics are known to millimetres cannot tell depth from pose
    to better than that: its median's standard error grows, and the model moves less."""
    clouds = _clouds()
    _, sure = _update(clouds, _board_fit(0.0))
    loose = {c: np.diag([np.radians(0.2)] * 3 + [0.005] * 3) ** 2 for c in "bc"}
    _, unsure = _update(clouds, _board_fit(0.0), loose)
    se = {(m.cam_a, m.cam_b): m.se_mm for m in unsure.before}
    se0 = {(m.cam_a, m.cam_b): m.se_mm for m in sure.before}
    assert se["a", "b"] > 2.5 * se0["a", "b"] and se["a", "b"] > 3.0
    assert (np.sqrt(unsure.covariances["a"][1, 1]) > 1.3 * np.sqrt(sure.covariances["a"][1, 1]))


def test_nothing_to_update_without_a_modelled_camera():
    clouds = _clouds()
    models = {c: identity_model(INTR) for c in POSES}
    assert update_models(models, {}, overlap_samples(clouds, POSES, PAIRS, models),
                         POSES) is None


def test_a_held_camera_anchors_only_as_well_as_its_board_fit_knows_its_depth():
    """A camera whose board fit kept no term is held, but its depth where the pair lies is
    known only to its every-term fit's sigma: a loose fit (few views) weighs its pairs down,
    so a biased neighbour cannot pull the updated camera towards its own error."""
    from rgbd_calib.core.depth_model import PARAMETERS
    from rgbd_calib.depth.depth_model_fit import DepthModelFit

    def fit(name, d0_sigma):
        cov = np.diag([(d0_sigma if p == "d0" else 1e-4) ** 2 for p in PARAMETERS])
        return DepthModelFit(name, identity_model(INTR), (), (), 6, 1000, 1.0,
                             law_model=identity_model(INTR), law_names=PARAMETERS, law_cov=cov)

    clouds = _clouds()
    models = {"a": _board_fit(0.0), "b": identity_model(INTR), "c": identity_model(INTR)}
    corrected = {**clouds, "a": recorrected(clouds["a"], None, models["a"])}
    samples = overlap_samples(corrected, POSES, PAIRS, models)
    exact = update_models(models, {"a": PRIOR}, samples, POSES)
    loose = update_models(models, {"a": PRIOR}, samples, POSES,
                          held={"b": fit("b", 0.2), "c": fit("c", 0.2)})
    se = {(m.cam_a, m.cam_b): m.se_mm for m in loose.before}
    se0 = {(m.cam_a, m.cam_b): m.se_mm for m in exact.before}
    assert se["a", "b"] > 3 * se0["a", "b"] and se["a", "c"] > 3 * se0["a", "c"]
    # the update then leans on a's prior: it moves a less, with a wider posterior
    assert (abs(loose.models["a"].value("d0")) < abs(exact.models["a"].value("d0"))
            and loose.covariances["a"][1, 1] > exact.covariances["a"][1, 1])
