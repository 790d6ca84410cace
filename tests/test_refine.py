"""Depth refinement (issue 4): scale bias, pair registration in the joint graph, refine CLI.

Ground truth from the synthetic renders (D435 noise model, s = 0.08 px, B = 50 mm; colour
blur 0.6 px, noise 2 DN)."""

import json
from dataclasses import replace

import gtsam
import numpy as np
import pytest
from typer.testing import CliRunner

from rgbd_calib.cli.commands import app
from rgbd_calib.core.config import CalibrationConfig, DepthConfig
from rgbd_calib.core.geometry import make_transform, rotvec_to_matrix, transform_error
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.model.depth_model_file import load_depth_models
from rgbd_calib.model.results import CameraExtrinsics, Extrinsics, load_extrinsics, write_extrinsics
from rgbd_calib.pipelines.calibrate import calibrate
from rgbd_calib.synth.render import SynthParams, load_ground_truth, synthesize

SCALE_TOL = 0.001  # issue 4: depth-scale factor within 0.1 % (absolute)
WEAK_GAIN = 0.30  # issue 4: refinement lowers the mean camera error by >= 30 % on weak data
# ... with depth sensors whose poses are known to a real camera's 0.1 deg / 1 mm (the default;
# measured -25 %)
WEAK_GAIN_SENSOR_POSE = 0.10
STRONG_RATIO, STRONG_MM = 0.10, 0.1  # ... and never worsens a camera by > 10 % (or 0.1 mm)


def errors(ext, gt):
    return {c: transform_error(e.T_ref_cam, gt.T_ref_cam[c]) for c, e in ext.cameras.items()}


@pytest.fixture(scope="module")
def biased_race(tmp_path_factory):
    """Race rig, 8 frames, depth-scale bias up to +-0.6 % per camera."""
    out = tmp_path_factory.mktemp("refine") / "race"
    return synthesize(out, "race", 8, 5, thesis_board(), SynthParams(depth_bias=0.006),
                      workers=2)


@pytest.fixture(scope="module")
def refined_small_race(biased_race):
    result = calibrate(FolderDataset(biased_race.path), thesis_board(), CalibrationConfig())
    return biased_race, result


def test_depth_scale_bias_recovered(refined_small_race):
    synth, result = refined_small_race
    gt = load_ground_truth(synth.path)
    assert result.depth is not None and result.depth.depth_scales
    for cam, est in result.depth.depth_scales.items():
        assert abs(est.factor - gt.depth_scale_bias[cam]) < SCALE_TOL, cam
        assert est.sigma > 0


def test_pairs_are_reported_and_joined(refined_small_race):
    _, result = refined_small_race
    pairs = result.depth.pairs
    assert pairs and any(p.accepted for p in pairs)
    for p in pairs:
        assert p.accepted or p.reason
        if p.accepted:
            assert p.finished and np.isfinite(p.rmse_final_mm) and p.rmse_final_mm < 20
    # the joint graph used the accepted pairs (one relative-pose factor each), weighed by
    # their variance factor against the board (never trusted beyond their information)
    assert len(result.depth.relative_poses) == sum(p.accepted for p in pairs)
    assert result.depth.pair_variance_factor >= 1.0
    assert result.depth.status_dict()["pair_variance_factor"] == result.depth.pair_variance_factor


def test_refine_command_recovers_a_perturbed_calibration(biased_race, tmp_path):
    small_race = biased_race
    gt = load_ground_truth(small_race.path)
    rng = np.random.default_rng(3)
    cams = {}
    for c, T in gt.T_ref_cam.items():
        if c != gt.reference:  # 2 cm / 2 deg off the truth
            axis = rng.normal(size=3)
            d = rng.normal(size=3)
            T = T @ make_transform(rotvec_to_matrix(axis / np.linalg.norm(axis)
                                                    * np.radians(2.0)),
                                   d / np.linalg.norm(d) * 0.02)
        cams[c] = CameraExtrinsics(c, T)
    init = tmp_path / "init.yaml"
    write_extrinsics(Extrinsics(gt.reference, cams), init)
    result = CliRunner().invoke(app, ["refine", str(small_race.path), "--init", str(init),
                                      "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    out = load_extrinsics(tmp_path / "out" / "extrinsics.yaml")
    before = errors(load_extrinsics(init), gt)
    after = errors(out, gt)
    # the reference row (left0..3) shares floor, rails and walls: those cameras come back;
    # measured (seed 5): 20 mm -> 1.7, 15.1, 5.2 mm. The facing row is only linked to it by
    # floor-only overlaps, which are rejected, so it keeps its start (see docs/depth.md).
    row = [c for c in after if c.startswith("left") and c != gt.reference]
    assert np.median([after[c][1] for c in row]) < 0.5 * np.median([before[c][1] for c in row])
    assert all(after[c][0] < before[c][0] for c in row)
    report = json.loads((tmp_path / "out" / "refine_report.json").read_text())
    for p in report["pairs"]:
        if p["accepted"]:
            assert p["rmse_final_mm"] <= p["rmse_before_mm"] + 0.5


@pytest.mark.slow
def test_refinement_helps_weak_board_data_and_never_hurts_strong(tmp_path_factory):
    board = thesis_board()
    root = tmp_path_factory.mktemp("refine")
    weak = synthesize(root / "weak", "race", 6, 5, board, SynthParams(depth_bias=0.006))
    strong = synthesize(root / "strong", "race", 40, 1, board, SynthParams(depth_bias=0.006))
    for synth, check in ((weak, "weak"), (strong, "strong")):
        gt = load_ground_truth(synth.path)
        ds = FolderDataset(synth.path)
        refined = calibrate(ds, board, CalibrationConfig(), cache_dir=root / check)
        plain = calibrate(ds, board, CalibrationConfig(refine="none"), cache_dir=root / check)
        e_ref, e_none = errors(refined.extrinsics, gt), errors(plain.extrinsics, gt)
        cams = [c for c in e_ref if c != gt.reference]
        for cam, est in refined.depth.depth_scales.items():
            assert abs(est.factor - gt.depth_scale_bias[cam]) < SCALE_TOL
        if check == "weak":
            # the render's depth sensors sit exactly where their colour cameras say (its only
            # depth error is a scale): with their poses taken as exact, as before 2026-11-30,
            # measured (2026-11-24): 0.801 -> 0.290 mm (-64 %); with the board-estimated depth
            # scales taken as exact in the pairs it was -15 % (docs/depth.md, "Weak board data");
            # with the pairs registering depth-model-corrected clouds (ea91206 .. 5bf18b5)
            # 0.92 -> 2.17 mm, since registered with the scale alone 0.92 -> 0.34-0.44 mm
            exact = calibrate(ds, board, CalibrationConfig(depth=DepthConfig(
                sensor_pose_sigma_deg=0.0, sensor_pose_sigma_mm=0.0)), cache_dir=root / check)
            mean_none = np.mean([e_none[c][1] for c in cams])
            e_exact = errors(exact.extrinsics, gt)
            mean_exact = np.mean([e_exact[c][1] for c in cams])
            assert mean_exact <= (1 - WEAK_GAIN) * mean_none, (mean_exact, mean_none)
            # by default the pairs carry a real camera's depth-to-colour pose (0.1 deg / 1 mm
            # per axis): they help less, and never hurt (0.92 -> 0.69 mm, docs/depth.md, "The
            # depth sensor's pose in the pairs")
            mean_ref = np.mean([e_ref[c][1] for c in cams])
            assert mean_ref <= (1 - WEAK_GAIN_SENSOR_POSE) * mean_none, (mean_ref, mean_none)
        else:
            for c in cams:
                allowed = max(STRONG_RATIO * e_none[c][1], STRONG_MM)
                assert e_ref[c][1] <= e_none[c][1] + allowed, (c, e_ref[c], e_none[c])


# ----------------------------------------------------------------------------- refine's report
def test_refine_writes_the_calibration_report_with_a_verdict(tiny_calibration, tmp_path):
    """Issue 14, item 3: refine writes report.json (the calibrate schema, method ``depth``,
    board sections empty) and report.html, with refine_report.json's verdict."""
    from rgbd_calib.outputs.report import rebuild_report, validate_report

    data, calib, _ = tiny_calibration
    out = tmp_path / "refined"
    res = CliRunner().invoke(app, ["refine", str(data), "--init", str(calib / "extrinsics.yaml"),
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "report.json").read_text())
    assert validate_report(report) == []
    legacy = json.loads((out / "refine_report.json").read_text())
    assert report["method"] == "depth" and report["refine"]["fix_others"] is False
    assert report["refine"]["outcome"] == legacy["verdict"]
    assert report["refine"]["message"] == legacy["message"]
    assert report["refine"]["init"] == str((calib / "extrinsics.yaml").resolve())
    # the summary verdict follows the outcome: refined and nothing else found -> good
    codes = {w["code"] for w in report["warnings"] if w["severity"] != "info"}
    assert (report["summary"]["verdict"] == "good") == (legacy["verdict"] == "refined"
                                                        and not codes)
    # depth: every pair with its reason, the depth scales and where they came from
    assert report["pairs"] and [p["cam_a"] for p in report["pairs"]] == [
        p["cam_a"] for p in legacy["pairs"]]
    assert all(p["accepted"] or p["reason"] for p in report["pairs"])
    # each camera's depth corrected as its calibration did: the depth model of its
    # depth_model.yaml (carried into the refined folder, so a later check applies it too),
    # else the report's factor
    start = json.loads((calib / "report.json").read_text())
    models = load_depth_models(calib) if (calib / "depth_model.yaml").exists() else {}
    assert models, "calibrate writes depth_model.yaml"
    assert load_depth_models(out) == models
    for cam, entry in report["cameras"].items():
        want = (models[cam].value("scale") if cam in models
                else start["cameras"][cam]["depth_scale_factor"])
        assert entry["depth_scale_factor"] == want
        assert report["refine"]["cameras"][cam]["depth_scale_source"] == "given"
    assert report["depth"]["status"] == legacy["depth"]["status"]
    # the cameras as extrinsics.yaml has them; no board section filled
    ext = load_extrinsics(out / "extrinsics.yaml")
    for cam, e in ext.cameras.items():
        np.testing.assert_allclose(report["cameras"][cam]["T_ref_cam"], e.T_ref_cam, atol=1e-9)
        assert report["cameras"][cam]["sigma_translation_mm"] == pytest.approx(
            e.sigma_translation_mm)
    assert report["views"] == report["board_views"] == report["markers"] == []
    assert report["summary"]["reprojection_rms_px"] is None
    page = (out / "report.html").read_text()
    assert "Depth-only refinement report" in page and report["refine"]["init"] in page
    assert "Reprojection error per camera" not in page and "Camera pairs (depth)" in page
    # and `rgbd-calib report DIR` rebuilds it byte for byte
    before = (out / "report.json").read_bytes(), (out / "report.html").read_bytes()
    rebuild_report(out)
    assert ((out / "report.json").read_bytes(), (out / "report.html").read_bytes()) == before


def test_a_failing_figure_costs_the_page_not_the_refined_extrinsics(tiny_calibration, tmp_path,
                                                                     monkeypatch):
    from rgbd_calib.outputs.report import figures

    def boom(*_):
        raise RuntimeError("no display")

    monkeypatch.setattr(figures, "fig_rig", boom)
    data, calib, _ = tiny_calibration
    out = tmp_path / "refined"
    res = CliRunner().invoke(app, ["refine", str(data), "--init", str(calib / "extrinsics.yaml"),
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "report.html not written (RuntimeError: no display)" in res.output
    assert not (out / "report.html").exists()
    assert (out / "extrinsics.yaml").is_file() and (out / "report.json").is_file()


def test_refine_and_check_take_the_depth_settings_of_a_config_file(tiny_calibration, tmp_path):
    """`--config` gives refine and check calibrate's depth settings (its `depth:` section):
    a minimum fitness no pair reaches leaves refine nothing to use; a bad key stops both with
    one line naming the file, before anything is read or written."""
    data, calib, _ = tiny_calibration
    strict = tmp_path / "strict.yaml"
    strict.write_text("depth:\n  min_fitness: 0.999\n")
    out = tmp_path / "refined"
    res = CliRunner().invoke(app, ["refine", str(data), "--init", str(calib / "extrinsics.yaml"),
                                   "--out", str(out), "--config", str(strict)])
    assert res.exit_code == 0, res.output
    legacy = json.loads((out / "refine_report.json").read_text())
    assert legacy["verdict"] == "unchanged"
    assert legacy["pairs"] and all(not p["accepted"] and "fitness" in p["reason"]
                                   for p in legacy["pairs"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("depth:\n  min_fitnes: 0.5\n")
    for cmd in (["refine", str(data), "--init", str(calib / "extrinsics.yaml")],
                ["check", str(data), "--calib", str(calib)]):
        out = tmp_path / f"bad_{cmd[0]}"
        res = CliRunner().invoke(app, [*cmd, "--out", str(out), "--config", str(bad)])
        assert res.exit_code == 2, res.output
        assert str(bad) in res.output and "min_fitnes" in res.output
        assert "Traceback" not in res.output and not out.exists()


def _noisy(T: np.ndarray, sigma_rad: float, sigma_m: float, rng) -> np.ndarray:
    """``T @ Exp(xi)`` (to first order) with xi ~ N(0, diag(sigma_rad^2 x3, sigma_m^2 x3))."""
    return T @ make_transform(rotvec_to_matrix(rng.normal(scale=sigma_rad, size=3)),
                              rng.normal(scale=sigma_m, size=3))


def _pose_graph_case(rng, pair_noise_factor: float):
    """A reference and 7 cameras on a 2 m circle; each camera held to its (noisy) start by a
    prior of 0.1 mm / 0.005 deg at that noise, and a pair between every two cameras claiming
    0.2 mm / 0.01 deg but drawn ``pair_noise_factor`` times wider."""
    from rgbd_calib.solve.bundle import RelativePose

    names = ["ref"] + [f"c{i}" for i in range(7)]
    angle = {c: 2 * np.pi * i / len(names) for i, c in enumerate(names)}
    T_true = {c: make_transform(rotvec_to_matrix([0, a, 0]), [2 * np.sin(a), 0, 2 - 2 * np.cos(a)])
              for c, a in angle.items()}
    prior_rad, prior_m = np.radians(0.005), 1e-4
    pair_rad, pair_m = np.radians(0.01), 2e-4
    T_init = {c: T if c == "ref" else _noisy(T, prior_rad, prior_m, rng)
              for c, T in T_true.items()}
    priors = [RelativePose(c, "ref", T_init[c],
                           np.diag([prior_rad**-2] * 3 + [prior_m**-2] * 3)) for c in names[1:]]
    k = pair_noise_factor
    pairs = [RelativePose(a, b, _noisy(np.linalg.inv(T_true[b]) @ T_true[a], k * pair_rad,
                                       k * pair_m, rng),
                          np.diag([pair_rad**-2] * 3 + [pair_m**-2] * 3))
             for i, a in enumerate(names) for b in names[i + 1:]]
    return T_true, T_init, priors, pairs


def _hat_redundancy(reference: str, T_ref_cam: dict[str, np.ndarray],
                    relative_poses: list,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The reference the bundle's ``relative_pose_fit`` is checked against, computed
    independently from the graph's hat matrix. Per relative pose of a pose graph with
    ``reference`` held, linearised at ``T_ref_cam``
    (camera -> 4x4, m): its whitened chi-square ``e^T W e`` and its redundancy number
    ``r = 6 - tr(A_f (A^T A)^+ A_f^T)`` (``A`` the whitened Jacobian of the graph without the
    reference's columns, ``A_f`` the rows of that factor; Foerstner 1979), the share of the
    graph's redundancy its residual carries. A pose with a camera not in ``T_ref_cam`` (cut
    off from the reference: not in the solve) gets 0 for both. Arrays follow
    ``relative_poses``."""
    used = [i for i, r in enumerate(relative_poses)
            if r.cam_a in T_ref_cam and r.cam_b in T_ref_cam]
    chi2_f, redundancy = np.zeros(len(relative_poses)), np.zeros(len(relative_poses))
    if not used:
        return chi2_f, redundancy
    cams = sorted({reference} | {c for i in used for c in (relative_poses[i].cam_a,
                                                          relative_poses[i].cam_b)})
    key = {c: gtsam.symbol("c", i) for i, c in enumerate(cams)}
    graph = gtsam.NonlinearFactorGraph()
    for i in used:
        graph.add(relative_poses[i].factor(key))
    values = gtsam.Values()
    ordering = gtsam.Ordering()
    for c in cams:
        values.insert(key[c], gtsam.Pose3(T_ref_cam[c]))
        ordering.push_back(key[c])
    A, b = graph.linearize(values).jacobian(ordering)
    k = cams.index(reference)  # held: its columns go
    A = np.delete(A, np.s_[6 * k:6 * k + 6], axis=1)
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    U = U[:, s > s.max() * 1e-12] if s.size else U  # rank-revealing: a free direction adds 0
    h = np.sum(U**2, axis=1)  # the hat matrix's diagonal
    chi2_f[used] = np.sum(np.reshape(b, (len(used), 6)) ** 2, axis=1)
    redundancy[used] = 6.0 - np.sum(np.reshape(h, (len(used), 6)), axis=1)
    return chi2_f, redundancy


def test_relative_pose_redundancy_sums_to_the_graph_redundancy():
    """Redundancy numbers (Foerstner) of the bundle's relative poses: over all factors they
    sum to observations minus unknowns, and two priors on one camera split its 6 by their
    weights (r_1 = tr(W_2 (W_1 + W_2)^-1), 6 x 1/5 for a prior 4x tighter in information)."""
    from rgbd_calib.core.config import BundleConfig
    from rgbd_calib.solve.bundle import BundleProblem, RelativePose, bundle_adjust

    def fit(T_init, poses):
        K = {c: np.eye(3) for c in T_init}
        res = bundle_adjust(BundleProblem([], K, "ref", T_init, {}, BundleConfig(),
                                          relative_poses=poses))
        return np.array(res.relative_pose_fit)

    rng = np.random.default_rng(2)
    T_true, T_init, priors, pairs = _pose_graph_case(rng, 1.0)
    f = fit(T_init, priors + pairs)
    assert f[:, 1].sum() == pytest.approx(6 * (len(priors) + len(pairs)) - 6 * 7, abs=1e-3)
    assert np.all(f[:, 1] > 0) and np.all(f[:, 0] > 0)
    T = T_true["c0"]
    W = np.eye(6) * 1e8
    f2 = fit({"ref": np.eye(4), "c0": T}, [RelativePose("c0", "ref", T, W),
                                           RelativePose("c0", "ref", T, 4 * W)])
    np.testing.assert_allclose(f2[:, 1], [6 * 4 / 5, 6 * 1 / 5], atol=1e-3)


def test_the_bundle_gives_each_relative_pose_its_chi2_and_redundancy():
    """``BundleResult.relative_pose_fit`` (from the whole graph's marginals, what calibrate's
    joint solve weighs its depth pairs by) equals the pose graph's own redundancy numbers
    (``_hat_redundancy``, from the hat matrix) on a graph of relative poses alone, and its held
    factors (``variance_components.updated_factor``) recover pairs drawn 2x wider than they
    claim: a factor of ~4."""
    from rgbd_calib.core.config import BundleConfig
    from rgbd_calib.solve.bundle import BundleProblem, bundle_adjust
    from rgbd_calib.solve.variance_components import updated_factor

    rng = np.random.default_rng(5)
    T_true, T_init, priors, pairs = _pose_graph_case(rng, 2.0)
    K = {c: np.eye(3) for c in T_init}
    res = bundle_adjust(BundleProblem([], K, "ref", T_init, {}, BundleConfig(),
                                      relative_poses=priors + pairs))
    fit = np.array(res.relative_pose_fit)
    chi2_f, r = _hat_redundancy("ref", res.T_ref_cam, priors + pairs)
    np.testing.assert_allclose(fit[:, 1], r, atol=1e-3)
    np.testing.assert_allclose(fit[:, 0], chi2_f, rtol=1e-3)
    assert fit[:, 1].sum() == pytest.approx(6 * (len(priors) + len(pairs)) - 6 * 7, abs=1e-3)
    # the pairs' factor, the priors held at their (honest) model: iterate as calibrate does
    factor = 1.0
    for _ in range(20):
        scaled = [replace(p, information=p.information / factor) for p in pairs]
        res = bundle_adjust(BundleProblem([], K, "ref", T_init, {}, BundleConfig(),
                                          relative_poses=priors + scaled))
        part = np.array(res.relative_pose_fit)[len(priors):]
        new = updated_factor(factor, part[:, 0], part[:, 1])
        if abs(new / factor - 1) < 0.01:
            break
        factor = new
    assert 0.6 * 4 <= factor <= 1.5 * 4, factor
    assert updated_factor(2.0, np.array([0.1]), np.array([0.5])) == 2.0  # too little redundancy
    assert updated_factor(2.0, np.array([1.0]), np.array([6.0])) == 1.0  # never below 1


@pytest.mark.parametrize("k", [1.0, 2.0])
def test_variance_components_recover_the_pairs_noise(k):
    """Pairs drawn k times wider than their information claims: the estimated pair factor is
    ~k^2 (the priors', drawn at their model, stays ~1), and the result is closer to the truth
    than the plain solve when the pairs overclaim (k = 2)."""
    from rgbd_calib.solve.variance_components import solve_variance_components

    rng = np.random.default_rng(11)
    T_true, T_init, priors, pairs = _pose_graph_case(rng, k)
    K = {c: np.eye(3) for c in T_init}
    groups = {"initial": priors, "pairs": pairs}
    res, factors = solve_variance_components(K, "ref", T_init, groups)
    plain, ones = solve_variance_components(K, "ref", T_init, groups, max_iterations=1)
    assert ones == {"initial": 1.0, "pairs": 1.0}
    # 126 pair rows of redundancy ~100: the factor's relative sigma is ~sqrt(2 / 100) = 0.14
    assert 0.6 * k**2 <= factors["pairs"] <= 1.5 * k**2, factors
    assert 1.0 <= factors["initial"] <= 1.6, factors

    def mean_mm(T):
        return np.mean([transform_error(T[c], T_true[c])[1] for c in T_true if c != "ref"])

    if k > 1:
        assert mean_mm(res.T_ref_cam) < mean_mm(plain.T_ref_cam)
        # the marginals carry the factor: the pairs no longer claim their model sigmas
        assert all(res.sigma_translation_mm[c] > plain.sigma_translation_mm[c]
                   for c in T_true if c != "ref")
