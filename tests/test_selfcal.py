"""The model ladder's decisions (rgbd_calib/selfcal.py), on hand-made residuals: pure maths,
no solve. The pipeline runs are in test_board_refine (glue), test_robustness (wrong focal)
and test_distortion_pipeline (unlisted lens)."""

from types import SimpleNamespace

import numpy as np
import pytest

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.config import BundleConfig
from rgbd_calib.solve import blocks, selfcal


def _terms(rms, n=500, cam="c"):
    return selfcal.marker_terms([(cam, f"v{i}", i, rms) for i in range(n)], [], cap_px=3.0)


def test_bic_rejects_parameters_that_only_fit_noise():
    rng = np.random.default_rng(0)
    n = 2000
    base = {("c", f"v{i}", i): float(np.sum(rng.normal(0, 0.1, 8) ** 2)) for i in range(n)}
    # a correct model with k more parameters lowers SSR by about k sigma^2
    k = 32
    richer = {key: v * (1 - k / (8 * n)) for key, v in base.items()}
    ok, gain, reason = selfcal.compare(base, 8, richer, 8, k)
    assert not ok and gain < 0, reason
    # a real model error: the fit improves by far more than the parameters cost
    better = {key: v * 0.25 for key, v in base.items()}
    ok, gain, reason = selfcal.compare(base, 8, better, 8, k)
    assert ok and gain > 1000, reason


def test_more_cameras_wins_and_fewer_loses():
    a, b = _terms(0.1), _terms(0.5)
    assert selfcal.compare(a, 4, b, 8, 4)[0]  # worse fit but 4 more cameras kept
    assert not selfcal.compare(b, 8, a, 7, 4)[0]  # better fit but a camera lost


def test_compare_uses_common_markers_and_caps_outliers():
    before = selfcal.marker_terms([("c", "v", 1, 0.1)], [("c", "v", 2, 50.0)], cap_px=3.0)
    assert before[("c", "v", 2)] == pytest.approx(8 * 9.0)
    after = selfcal.marker_terms([("c", "v", 1, 0.1), ("c", "v", 3, 0.1)], [], cap_px=3.0)
    ok, gain, reason = selfcal.compare(before, 1, after, 1, 0)
    assert "1 common markers" in reason and gain == pytest.approx(0.0)


def test_candidate_groups_follow_the_config():
    auto = BundleConfig(board="auto", intrinsics="auto", time="fixed")
    groups = selfcal.candidate_groups(auto, double_sided=True, model_error=True)
    assert groups[0] == [(True, (), False)] and len(groups) == 2  # time fixed: not tried
    assert groups[1][0] == (False, ("fx", "fy", "cx", "cy"), False)
    assert groups[1][1][1] == tuple(auto.intrinsics_params)
    # no model error: the intrinsics are not tried; one-sided board: no back sheet
    assert selfcal.candidate_groups(auto, double_sided=False, model_error=False) == []
    fixed = BundleConfig(board="fixed", intrinsics="fixed", time="fixed")
    assert selfcal.candidate_groups(fixed, True, True) == []
    assert not selfcal.is_auto(fixed) and selfcal.is_auto(auto)
    # explicit refine is part of every level
    base = selfcal.base_level(BundleConfig(board="refine", intrinsics="auto"))
    assert base.board and base.intrinsics_params == () and not base.time
    level = selfcal.extend(base, (False, ("fx", "fy"), False))
    assert level.name == "board + fx fy"
    cfg = level.bundle_config(BundleConfig())
    assert cfg.board == "refine" and cfg.intrinsics == "refine" and cfg.time == "fixed"
    assert cfg.intrinsics_params == ["fx", "fy"] and not level.distortion
    assert selfcal.extend(level, (False, ("fx", "k1"), False)).distortion


def test_time_challenges_the_first_steps_and_only_with_a_model_error():
    """Time must beat every other first step (the back sheet, the lens alternatives: neither
    may absorb the other's error) to be taken first; it is tried again last on top of the
    rest. Without views that disagree (no model error: a still board, synchronised cameras)
    time is never tried."""
    auto = BundleConfig()  # board, intrinsics and time all auto
    groups = selfcal.candidate_groups(auto, double_sided=True, model_error=True)
    assert groups[0] == [(True, (), False)] and groups[-1] == [selfcal.TIME_STEP]
    assert all(not step[2] for step in groups[1])  # the lens alternatives
    challengers = selfcal.time_challengers(groups)
    assert challengers == [(True, (), False), *groups[1]]
    assert selfcal.candidate_groups(auto, True, model_error=False) == [[(True, (), False)]]
    assert selfcal.time_challengers([[(True, (), False)]]) == []
    timed = selfcal.extend(selfcal.base_level(auto), selfcal.TIME_STEP)
    assert timed.name == "time" and timed.bundle_config(auto).time == "refine"
    both = selfcal.extend(timed, groups[0][0])
    assert both.name == "time + board" and both.board and both.time
    assert selfcal.extend(both, selfcal.TIME_STEP) == both  # skipped by the ladder
    assert blocks.TimeBlock().parameters(blocks.RigShape(8, 8, 30, None)) == 2 * 8 - 1 + 6 * 30
    assert selfcal.base_level(BundleConfig(time="refine")).time


def test_better_prefers_cameras_then_bic():
    lv = selfcal.ModelLevel("x", False)
    a = selfcal.LevelFit(lv, 8, 100, 0.1, 4, 50.0)
    b = selfcal.LevelFit(lv, 8, 100, 0.1, 4, 80.0)
    c = selfcal.LevelFit(lv, 9, 100, 0.3, 4, None)
    assert selfcal.better(b, a) and not selfcal.better(a, b)
    assert selfcal.better(c, b)


def test_prior_tension_and_loosening():
    nominal = CameraIntrinsics(640, 480, 500.0, 500.0, 320.0, 240.0)
    refined = CameraIntrinsics(640, 480, 525.0, 500.0, 320.5, 240.0)
    bundle = SimpleNamespace(intrinsics={"c": refined},
                             intrinsics_prior_sigma={"c": {"fx": 5.0, "fy": 5.0, "cx": 10.0,
                                                           "cy": 10.0}})
    rig = SimpleNamespace(cameras={"c": nominal})
    z, cam, name = selfcal.prior_tension(bundle, rig)
    assert (cam, name) == ("c", "fx") and z == pytest.approx(5.0)
    loose = selfcal.loosened(BundleConfig())
    assert loose.intrinsics_prior.intrinsics_prior_focal_pct == pytest.approx(10.0)
    assert loose.intrinsics_prior.intrinsics_prior_center_px == pytest.approx(100.0)


def test_lens_refined_from_thin_coverage_is_named():
    """Warning ``lens_coverage``: distortion refined from views covering < 35 % of the image,
    or never reaching one of its corners (the polynomial is extrapolated towards them);
    focal/centre only, or good coverage (an edge region missed is not a corner), raise
    nothing."""
    from rgbd_calib.outputs.report.findings import lens_coverage

    entry = {"prior": 0.0, "prior_sigma": 0.1, "refined": 0.08, "sigma": 0.001,
             "change": 0.08, "change_pct": None}
    report = {"cameras": {
        "thin": {"intrinsics_refined": {"fx": entry, "k1": entry},
                 "coverage": {"image_fraction": 0.13}},
        "wide": {"intrinsics_refined": {"k1": entry},
                 "coverage": {"image_fraction": 0.6, "missing_regions": ["right"]}},
        "cornerless": {"intrinsics_refined": {"k1": entry},
                       "coverage": {"image_fraction": 0.4, "missing_regions": ["bottom-right"]}},
        "focal": {"intrinsics_refined": {"fx": entry}, "coverage": {"image_fraction": 0.1}},
        "fixed": {"coverage": {"image_fraction": 0.1}},
    }}
    found = lens_coverage(report, [])
    assert len(found) == 1
    f = found[0]
    as_dict = f if isinstance(f, dict) else f.to_dict()
    assert as_dict["code"] == "lens_coverage" and as_dict["cameras"] == ["thin", "cornerless"]
    assert "thin 13%" in as_dict["message"]
    assert "cornerless 40%, never the bottom-right corner" in as_dict["message"]


def test_cli_time_option_refuses_a_bad_value(tmp_path):
    """``calibrate --time`` takes auto, fixed or refine; anything else is one line naming the
    setting, exit 2, before the dataset is read."""
    from typer.testing import CliRunner

    from rgbd_calib.cli.commands import app

    bad = CliRunner().invoke(app, ["calibrate", str(tmp_path / "no_such_set"), "--out",
                                   str(tmp_path / "x"), "--time", "sometimes"])
    assert bad.exit_code == 2 and "bundle.time" in bad.output, bad.output
    assert "Traceback" not in bad.output and not (tmp_path / "x").exists()


def test_each_model_block_owns_its_count_its_held_test_and_its_settings():
    """The ladder asks the blocks (rgbd_calib.solve.blocks, issue 57 item 1): what each adds
    over the level below, why a freed one was held, and which settings switch it on."""
    from types import SimpleNamespace

    flat = SimpleNamespace(sheets=())
    cube = SimpleNamespace(sheets=(1, 2, 3, 4, 5, 6))
    rig = blocks.RigShape(cameras=6, free_cameras=5, views=40, board=flat)
    assert blocks.BoardBlock().parameters(rig) == 4
    assert blocks.BoardBlock().parameters(blocks.RigShape(6, 5, 40, cube)) == 30
    lens = blocks.IntrinsicsBlock(("fx", "fy", "cx", "cy", "k1", "k2"))
    pinhole = blocks.IntrinsicsBlock(("fx", "fy", "cx", "cy"))
    assert blocks.added((pinhole,), (pinhole, lens), rig) == 0 + 2 * 5  # k1 k2 on 5 cameras
    assert blocks.added((), (blocks.TimeBlock(), blocks.BoardBlock()), rig) == 11 + 240 + 4
    held = SimpleNamespace(board=SimpleNamespace(held="no view shows both faces"), faces=[])
    free = SimpleNamespace(board=SimpleNamespace(held=None), faces=[])
    assert blocks.newly_held((), (blocks.BoardBlock(),), held) == "no view shows both faces"
    assert blocks.newly_held((blocks.BoardBlock(),), (blocks.BoardBlock(),), held) is None
    assert blocks.newly_held((), (blocks.BoardBlock(),), free) is None
    level = selfcal.ModelLevel("time + board + fx fy cx cy", True, pinhole.params, True)
    assert [b.label for b in level.blocks] == ["time", "board", "fx fy cx cy"]
    cfg = level.bundle_config(BundleConfig())
    assert (cfg.time, cfg.board, cfg.intrinsics, tuple(cfg.intrinsics_params)) == (
        "refine", "refine", "refine", pinhole.params)
    nominal = selfcal.ModelLevel("nominal", False).bundle_config(BundleConfig())
    assert (nominal.time, nominal.board, nominal.intrinsics) == ("fixed", "fixed", "fixed")
