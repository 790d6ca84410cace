"""What a calibration prints after its tables: the verdict, the findings that matter most and
how many more the report holds (:func:`rgbd_calib.cli.console.verdict_lines`)."""

from __future__ import annotations

from dataclasses import replace

from rgbd_calib.cli.console import CONSOLE_FINDINGS, verdict_lines
from rgbd_calib.outputs.report.findings_base import actionable, finding


def ten_findings() -> list[dict]:
    """The findings of the real 4-webcam set (shared/data/caliscope-charuco-4cam) in the rules'
    order, shortened: three warnings, seven infos, two of them with nothing to do."""
    return [
        finding("info", "camera_model_error", ["cam_0"], "explained by the refined model.",
                "Nothing to do; rig_refined.yaml holds the refined models."),
        finding("warning", "intrinsics_unsupported", ["cam_0"], "cx k2 k3 unconstrained.",
                "Record more views at several distances."),
        finding("info", "capture_time", [], "the board moved.",
                "Nothing to do here (the time model explains it)."),
        finding("warning", "scratch_coverage", ["cam_1"], "corners reached 3% of the image.",
                "Record more views reaching every image region."),
        finding("info", "moving_board", ["cam_1"], "moved during 1 set.", "Hold it still."),
        finding("info", "board_coverage", [], "under 35% of the image.", "Cover the corners."),
        finding("info", "board_distance", ["cam_1"], "one distance only.", "Vary it."),
        finding("info", "view_model_error", [], "views disagree.", ""),
        finding("warning", "reprojection", [], "RMS 0.63 px.", "Check the intrinsics."),
        finding("info", "dropped_views", ["cam_3"], "2 views dropped.", "Bring it closer."),
    ]


def test_ten_findings_print_three_and_a_count_without_nothing_to_do():
    report = {"summary": {"verdict": "check"}, "warnings": ten_findings()}
    lines = [text for _, text in verdict_lines(report)]
    assert lines[0].startswith("verdict: CHECK")
    shown = lines[1:-1]
    assert len(shown) == CONSOLE_FINDINGS == 3
    # the warnings before every info; the one about this result (reprojection) before the
    # advice for the next recording, then in the rules' order
    assert [ln.split(":")[1].split()[0] for ln in shown] == [
        "reprojection", "intrinsics_unsupported", "scratch_coverage"]
    assert lines[-1] == "+ 7 more findings in report.html / report.json"
    assert not any("nothing to do" in ln.lower() for ln in lines)


def test_an_error_comes_first_and_infos_with_nothing_to_do_are_only_counted():
    found = ten_findings()[:3] + [finding("error", "not_calibrated", ["cam_2"],
                                          "cam_2 was not calibrated.", "Record views.")]
    lines = [text for _, text in verdict_lines({"summary": {"verdict": "poor"},
                                                "warnings": found})]
    assert lines[1].startswith("error: not_calibrated [cam_2]")
    assert lines[2].startswith("warning: intrinsics_unsupported")
    # the two infos with nothing to do are not steps: counted, not printed
    assert len(lines) == 4 and lines[-1] == "+ 2 more findings in report.html / report.json"


def test_a_fused_cloud_off_is_not_hidden_behind_lens_coverage():
    """Issue 34: findings are ranked by their effect on the result: the fused cloud off by
    centimetres outranks advice to cover the lens better, whatever the rules' order."""
    found = [finding("warning", "lens_coverage", [f"cam{k}"], "corners in 20% of the image.",
                     "Record views near the corners.") for k in range(3)]
    found.append(finding("warning", "fused_disagrees", ["cam1"], "cam1 is 12 mm off.",
                         "Calibrate cam1's depth."))
    lines = [text for _, text in verdict_lines({"summary": {"verdict": "check"},
                                                "warnings": found})]
    assert lines[1].startswith("warning: fused_disagrees [cam1]")


def test_a_good_rig_prints_the_verdict_alone():
    assert verdict_lines({"summary": {"verdict": "good"}, "warnings": []}) == [
        ("bold green", "verdict: GOOD: no warning; the extrinsics are ready to use")]


def test_advice_with_nothing_to_do_is_not_a_step():
    assert not actionable(finding("info", "a", [], "m", ""))
    assert not actionable(finding("info", "a", [], "m", "Nothing to do here (see b)."))
    assert actionable(finding("info", "a", [], "m", "Also show the board nearer."))


def test_a_change_is_a_percentage_only_of_a_prior_that_is_a_base():
    """'p1 +830.13 %' of a near-zero distortion coefficient says less than its absolute change;
    fx moved 4.8 % of 600 px stays a percentage."""
    from rgbd_calib.outputs.report.numbers import change_text, percent_of_prior

    assert change_text(600.0, 28.8, "px") == "+4.80 %"
    assert change_text(0.0011, 0.0093) == "+0.0093"  # 845 % of nearly nothing
    assert change_text(0.0004, 0.0001) == "+0.0001"  # a prior about zero
    assert change_text(0.0, -12.5, "px") == "-12.5 px"
    assert percent_of_prior(-0.33, 0.033) == 10.0
    assert percent_of_prior(None, 1.0) is None


def test_the_depth_model_line_names_a_camera_with_too_few_views_for_every_term():
    """``depth.model_fit.model_terms: auto``: every term from 15 board views; a camera with
    fewer that kept the ladder's terms says how many views it had, one with enough does not."""
    from types import SimpleNamespace

    from rgbd_calib.cli.console import depth_model_line
    from rgbd_calib.core.depth_model import TERMS

    def fit(terms, views, few=False, rejected=None):
        return SimpleNamespace(model=SimpleNamespace(terms=tuple(terms)), n_views=views,
                               too_few_views=few,
                               held_out=(None if rejected is None
                                         else SimpleNamespace(rejected=rejected)),
                               bands=[(1.0, 1.5, 900, 4.0, 0.2, 6.0, 2.1, 1.5)])

    line = depth_model_line({"a": fit(TERMS, 30), "b": fit(("scale", "offset"), 13, True),
                             "c": fit(("scale", "offset"), 20), "d": fit((), 30),
                             "e": fit(("scale", "offset"), 13), "f": fit((), 16, rejected=True)})
    assert line.startswith("depth model: every term for a, b scale+offset (13 board views, "
                           "15 free every term), c scale+offset, e scale+offset, 1 identity, "
                           "raw depth for f (its model predicted held-out board views no "
                           "better);"), line


def test_the_depth_registration_line_says_what_the_pairs_did_and_how_they_were_weighed():
    """calibrate's console line on the depth pairs: used with their variance factor (the
    pairs' covariance x the factor: at least depth.uncertainty.pair_variance_floor), not used
    and why (markup in the reason escaped), not needed, or nothing."""
    import numpy as np

    from rgbd_calib.cli.console import depth_registration_line
    from rgbd_calib.depth.registration import DepthPair, failed_registration
    from rgbd_calib.depth.stage import DepthRefinement
    from rgbd_calib.solve.bundle import RelativePose

    rejected = failed_registration("a", "b", "colored-icp", np.eye(4), "no correspondences")
    pair = DepthPair(replace(rejected, accepted=True, reason=None, rejected_by=()))
    rel = RelativePose("a", "b", np.eye(4), np.eye(6))
    used = DepthRefinement("colored-icp", {}, {}, [pair, DepthPair(rejected)], [rel],
                           {}, pair_variance_factor=4.37)
    line = depth_registration_line(used)
    assert line.startswith("depth registration: 1 of 2 camera pairs used") and "x4.37" in line
    biased = depth_registration_line(replace(used, pair_bias_sigma=(0.3, 0.007)))
    assert "x4.37" in biased and "plus a 0.3 mm / 0.007 deg bias" in biased
    assert used.status_dict()["pair_variance_factor"] == 4.37
    assert replace(used, pair_bias_sigma=(0.3, 0.007)).status_dict()["pair_bias_sigma_mm"] == 0.3
    fallback = DepthRefinement("colored-icp", {}, {}, [], [], {},
                               fallback="[red] in a reason is not markup")
    assert "\\[red] in a reason" in depth_registration_line(fallback)
    assert depth_registration_line(DepthRefinement("colored-icp", {}, {}, [], [], {},
                                                   note="the board constrains every camera"))
    assert depth_registration_line(DepthRefinement("colored-icp", {}, {}, [], [], {})) is None


def test_the_edge_offset_line_names_only_the_modelled_cameras():
    from rgbd_calib.cli.console import edge_offset_line
    from rgbd_calib.solve.edge_offset import EdgeOffset

    offsets = {"b": EdgeOffset(0.101, 0.001, 300, 0.1), "a": EdgeOffset(0.052, 0.001, 200, 0.05),
               "clean": EdgeOffset(0.002, 0.001, 300)}
    line = edge_offset_line(offsets)
    assert line is not None and "a, b read +0.052..+0.101 px per edge" in line, line
    assert "clean" not in line and "taken out of their corners" in line
    assert edge_offset_line({"clean": offsets["clean"]}) is None and edge_offset_line({}) is None


def test_the_extrinsics_table_keeps_its_numbers_in_a_file_or_pipe(monkeypatch):
    """Off a terminal rich lays out 80 columns, which cut the demo's table to '0.53…'; the
    table gets 100 unless COLUMNS says otherwise."""
    from rgbd_calib.cli import console as con

    monkeypatch.delenv("COLUMNS", raising=False)
    assert con._table_console().width == con.CONSOLE_WIDTH == 100
    monkeypatch.setenv("COLUMNS", "132")
    assert con._table_console().width == 132
