"""report.json schema, byte-identical rebuilds, and the warnings on a rig with known faults.

One small synthetic race rig (10 frame sets) is calibrated twice: as rendered, and from a
copy with two deliberate faults, a weak camera (all colour frames but one deleted) and a
camera whose rig.yaml fx is 5 % too large.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml

from rgbd_calib.core.config import CalibrationConfig
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.outputs.report import (
    REPORT_SCHEMA_VERSION,
    ReportError,
    dump_report,
    error_map,
    finalize_report,
    load_cloud,
    pair_entry,
    rebuild_report,
    render_html,
    schema_blocks,
    schema_paths,
    validate_report,
)
from rgbd_calib.outputs.writer import write_outputs
from rgbd_calib.pipelines.calibrate import calibrate
from rgbd_calib.synth.render import SynthParams, synthesize

DOC = Path(__file__).resolve().parents[1] / "docs" / "report_schema.md"
FX_ERROR = 1.05  # the wrong camera's fx in rig.yaml, relative to the true one
FLAG_CODES = {"error", "warning"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """(clean report folder, faulty report folder, weak camera, wrong-intrinsics camera)."""
    base = tmp_path_factory.mktemp("report")
    board = thesis_board()
    ds_path = synthesize(base / "dataset", "race", 10, 3, board, SynthParams(), workers=2).path
    ds = FolderDataset(ds_path)
    clean = calibrate(ds, board, CalibrationConfig(refine="none"))  # depth: test_refine.py
    write_outputs(clean, ds.rig, base / "clean")

    views = Counter(o.camera for o in clean.observations)
    ref = clean.extrinsics.reference
    order = sorted(views, key=lambda c: (-views[c], c))
    wrong = next(c for c in order if c != ref)
    weak = next(c for c in order if c not in (ref, wrong) and views[c] >= 3)
    used = {(r.camera, r.view) for r in clean.posegraph.residuals if r.used}
    frames = [f for c, f in used if c == weak]
    keep = max(frames, key=lambda f: (sum(1 for _, v in used if v == f), f))

    faulty_ds = base / "faulty_dataset"
    shutil.copytree(ds_path, faulty_ds)
    for p in (faulty_ds / weak / "color").iterdir():
        if p.stem != keep:
            p.unlink()
    rig = yaml.safe_load((faulty_ds / "rig.yaml").read_text())
    rig["cameras"][wrong]["fx"] *= FX_ERROR
    (faulty_ds / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    ds2 = FolderDataset(faulty_ds)
    # posegraph: the bundle stage can fail outright on a camera with wrong intrinsics (a board
    # view left with only that camera's rejected markers); the report is what is tested here
    faulty = calibrate(ds2, board, CalibrationConfig(method="posegraph", refine="none"))
    write_outputs(faulty, ds2.rig, base / "faulty")
    return base / "clean", base / "faulty", weak, wrong


def _load(folder: Path) -> dict:
    return json.loads((folder / "report.json").read_text())


def _flagged(report: dict, codes: set[str]) -> dict[str, set[str]]:
    """camera -> codes of error/warning findings naming it."""
    out: dict[str, set[str]] = {}
    for w in report["warnings"]:
        if w["severity"] in FLAG_CODES and w["code"] in codes:
            for c in w["cameras"]:
                out.setdefault(c, set()).add(w["code"])
    return out


# ----------------------------------------------------------------------------- schema
def test_reports_validate_against_the_schema(runs):
    clean, faulty, *_ = runs
    for folder in (clean, faulty):
        report = _load(folder)
        assert validate_report(report) == []
        assert report["schema_version"] == REPORT_SCHEMA_VERSION
        assert report["pairs"] == []
        assert all(c["depth_scale_factor"] is None for c in report["cameras"].values())
    assert "bundle" in _load(clean) and "bundle" not in _load(faulty)


def test_validator_rejects_broken_reports(runs):
    report = _load(runs[0])
    cam = next(iter(report["cameras"]))
    broken = json.loads(json.dumps(report))
    del broken["summary"]["verdict"]
    broken["cameras"][cam]["views_used"] = "many"
    broken["views"][0]["edge_status"] = "maybe"
    broken["board_views"][0]["T_ref_board"] = [[1, 0, 0]]
    broken["surprise"] = 1
    errors = "\n".join(validate_report(broken))
    assert "summary.verdict: missing" in errors
    assert f"cameras.{cam}.views_used: expected integer" in errors
    assert "views[0].edge_status: 'maybe' not one of" in errors
    assert "board_views[0].T_ref_board: expected matrix4" in errors
    assert ".surprise: not in schema" in errors


def _documented() -> tuple[dict[str, str], str]:
    text = DOC.read_text()
    rows = re.findall(r"^\| `([^`]+)` \| (.+?) \| [^|]* \| .* \|$", text, flags=re.M)
    unescape = {"\\|": "|", "&lt;": "<", "&gt;": ">"}
    types = {}
    for key, typ in rows:
        for a, b in unescape.items():
            typ = typ.replace(a, b)
        types[key] = typ.strip()
    return types, text


def test_schema_doc_matches_the_code():
    documented, text = _documented()
    code = schema_paths()
    keys = {k: v for k, v in documented.items() if k not in schema_blocks()}
    assert set(keys) == set(code), (
        f"undocumented: {sorted(set(code) - set(keys))}; "
        f"not in the schema: {sorted(set(keys) - set(code))}"
    )
    wrong = {k: (keys[k], code[k]) for k in code if keys[k] != code[k]}
    assert not wrong, f"documented type differs from the code: {wrong}"
    for block, fields in schema_blocks().items():
        row = re.search(rf"^\| `{block}` \| (.*)$", text, flags=re.M)
        assert row and all(f"`{f}`" in row.group(1) for f in fields), block
    assert f"**Schema version: {REPORT_SCHEMA_VERSION}**" in text


def test_every_warning_code_raised_is_documented(runs):
    text = DOC.read_text()
    codes = {w["code"] for f in runs[:2] for w in _load(f)["warnings"]}
    assert codes, "the faulty rig raised no warning at all"
    for code in codes:
        assert f"| `{code}` |" in text, f"warning code {code} is not documented"


# ----------------------------------------------------------------------------- rebuild
def test_rebuild_reproduces_report_json_and_html(runs, tmp_path):
    for folder in runs[:2]:
        copy = tmp_path / folder.name
        shutil.copytree(folder, copy)
        json_before = (copy / "report.json").read_bytes()
        html_before = (copy / "report.html").read_bytes()
        (copy / "report.html").unlink()
        assert rebuild_report(copy) == copy / "report.html"
        assert (copy / "report.json").read_bytes() == json_before
        assert (copy / "report.html").read_bytes() == html_before
        report = json.loads(json_before)
        assert finalize_report(json.loads(json_before)) == report
        assert dump_report(report).encode() == json_before


def test_rebuild_refuses_mismatched_or_missing_results(runs, tmp_path):
    copy = tmp_path / "mismatch"
    shutil.copytree(runs[0], copy)
    ext = yaml.safe_load((copy / "extrinsics.yaml").read_text())
    cam = next(c for c in ext["cameras"] if c != ext["reference"])
    ext["cameras"][cam]["T_ref_cam"][0][3] += 0.01
    (copy / "extrinsics.yaml").write_text(yaml.safe_dump(ext))
    with pytest.raises(ReportError, match=f"camera {cam} differs"):
        rebuild_report(copy)
    with pytest.raises(ReportError, match="report.json: missing"):
        rebuild_report(tmp_path / "nothing")


def test_html_is_self_contained(runs):
    page = (runs[0] / "report.html").read_text()
    sources = re.findall(r"""\b(?:src|href)\s*=\s*["']([^"']*)""", page)
    assert sources and all(s.startswith("data:image/png;base64,") for s in sources), sources
    assert not re.search(r"https?://", page)
    assert "<script src" not in page and "@import" not in page


# ----------------------------------------------------------------------------- warnings
def test_clean_rig_is_not_flagged(runs):
    report = _load(runs[0])
    assert report["summary"]["verdict"] != "poor"
    assert report["summary"]["n_calibrated"] == report["summary"]["n_cameras"]
    assert not _flagged(report, {"inconsistent_camera", "weak_camera", "not_calibrated"})
    covis = np.asarray(report["covisibility"]["views"])
    assert (covis == covis.T).all()
    assert list(np.diag(covis)) == [
        sum(1 for v in report["views"] if v["camera"] == c and v["edge_status"] == "used")
        for c in report["covisibility"]["cameras"]
    ]


def test_faulty_rig_names_the_weak_and_the_wrong_camera(runs):
    _, faulty, weak, wrong = runs
    report = _load(faulty)
    flagged = _flagged(report, {"inconsistent_camera", "weak_camera", "not_calibrated"})
    assert "weak_camera" in flagged.get(weak, set()), report["warnings"]
    assert "inconsistent_camera" in flagged.get(wrong, set()), report["warnings"]
    assert set(flagged) == {weak, wrong}, f"others flagged too: {flagged}"
    assert report["summary"]["verdict"] == "poor"
    intrinsics = next(
        w
        for w in report["warnings"]
        if w["code"] == "inconsistent_camera" and wrong in w["cameras"]
    )
    assert "intrinsics" in intrinsics["advice"] and wrong in intrinsics["advice"]
    # the wrong camera's corners miss by far more than the rest of the rig's
    cams = report["cameras"]
    others = [
        c["reprojection_all_px"]["p50"]
        for n, c in cams.items()
        if n != wrong and c["reprojection_all_px"]
    ]
    if cams[wrong]["reprojection_all_px"]:
        assert cams[wrong]["reprojection_all_px"]["p50"] > 5 * max(others)
    assert cams[weak]["views_used"] == 1
    assert report["next_steps"], "a faulty rig must come with next steps"
    page = (faulty / "report.html").read_text()
    assert f"{weak} is weakly constrained" in page and "POOR" in page


# ----------------------------------------------------------------------------- depth inputs
def _write_ply(path: Path, points: np.ndarray, cams: np.ndarray, names: list[str]) -> None:
    """A fused.ply as docs/formats.md and the depth stage write it."""
    dtype = np.dtype(
        [
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
            ("camera", "u1"),
        ]
    )
    data = np.zeros(len(points), dtype)
    data["x"], data["y"], data["z"] = points.T
    data["red"], data["camera"] = 200, cams
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment camera {k} {n}" for k, n in enumerate(names)]
    header += [
        f"element vertex {len(points)}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "property uchar camera",
        "end_header",
    ]
    path.write_bytes(("\n".join(header) + "\n").encode() + data.tobytes())


def test_fused_ply_replaces_the_preview_cloud(runs, tmp_path, rng):
    copy = tmp_path / "with_ply"
    shutil.copytree(runs[0], copy)
    report = _load(copy)
    names = list(report["cameras"])[::-1]  # camera order of the PLY differs from the rig's
    points = rng.uniform(-1, 1, (500, 3))
    cams = rng.integers(0, len(names), 500)
    _write_ply(copy / "fused.ply", points, cams, names)
    cloud, why = load_cloud(report, copy)
    assert cloud is not None and why == "" and cloud.source.startswith("fused.ply")
    np.testing.assert_allclose(cloud.points, points.astype(np.float32), atol=1e-6)
    rig_order = list(report["cameras"])
    assert [rig_order[i] for i in cloud.camera] == [names[i] for i in cams]
    rebuild_report(copy)
    page = (copy / "report.html").read_text()
    data = json.loads(re.search(r"id='viewer-data'>(.*?)</script>", page, re.S).group(1))
    assert data["cloud"]["n"] == 500


def test_no_depth_is_reported_gracefully(runs, tmp_path):
    report = _load(runs[0])
    report["dataset"]["path"] = str(tmp_path / "moved_away")
    cloud, why = load_cloud(report, tmp_path)
    assert cloud is None and "not available" in why
    page = render_html(report, cloud, why)
    assert "No depth" in page and "moved_away" in page


def test_depth_pairs_show_error_maps_and_warnings(runs):
    report = _load(runs[0])
    a, b = list(report["cameras"])[:2]
    uv = np.array([[5, 5], [6, 7], [40, 5], [40, 40]])
    d_m = np.array([0.001, 0.003, -0.002, np.nan])
    em = error_map(uv, d_m, 64, 48, cell_px=16)
    assert (em["cols"], em["rows"]) == (4, 3)
    assert em["values_mm"][0] == pytest.approx(2.0)  # median of 1 and 3 mm
    assert em["values_mm"][2] == pytest.approx(-2.0)
    assert em["values_mm"][2 * 4 + 2] is None  # NaN distance: no partner
    report["pairs"] = [
        pair_entry(
            {
                "cam_a": a,
                "cam_b": b,
                "fitness": 0.8,
                "rmse_before_mm": 19.0,
                "rmse_after_mm": 17.5,  # above PAIR_RMSE_MAX_MM: the depth itself is off
                "rmse_final_mm": 20.0,  # > after + PAIR_FINAL_EXCESS_MM: disagrees
                "accepted": True,
                "overlap_fraction": 0.4,
                "error_map": em,
                "T_b_a": [[1.0]],
                "time_s": 1.0,
            }
        )
    ]
    report["cameras"][a]["depth_scale_factor"] = 1.006
    report["cameras"][a]["depth_scale_sigma"] = 0.001
    report.pop("depth_models", None)  # a report from before depth models: the factor decides
    report = finalize_report(report)
    assert validate_report(report) == []
    codes = {w["code"]: w for w in report["warnings"]}
    assert a in codes["pair_rmse"]["cameras"] and b in codes["pair_rmse"]["cameras"]
    assert codes["pair_disagrees"]["cameras"] == [a, b]
    assert codes["depth_scale"]["cameras"] == [a]
    page = render_html(report, None, "no cloud in this test")
    assert 'alt="overlap error maps"' in page and "17.50" in page


def test_depth_scale_advice_only_when_significant(runs):
    """Issue 33: a clean rig's scale estimates scatter within their sigmas (0.9958-0.9996 at
    0.4-0.9 %): no advice. With depth models the model's choice decides (the scale term kept
    by the evidence) when more than 3 sigmas from 1, without them the factor likewise."""
    report = _load(runs[0])
    a, b = list(report["cameras"])[:2]
    report.pop("depth_models", None)
    report["cameras"][a].update(depth_scale_factor=0.9969, depth_scale_sigma=0.004)
    report["cameras"][b].update(depth_scale_factor=0.9950, depth_scale_sigma=0.0005)
    codes = {w["code"]: w for w in finalize_report(report)["warnings"]}
    assert codes["depth_scale"]["cameras"] == [b]
    model = {"terms": [], "parameters": {}, "sigmas": {}, "bands": []}
    report["depth_models"] = {a: model, b: model}
    assert "depth_scale" not in {w["code"] for w in finalize_report(report)["warnings"]}
    report["depth_models"][a] = {**model, "terms": ["scale"], "parameters": {"scale": 1.005},
                                 "sigmas": {"scale": 0.0004}}
    codes = {w["code"]: w for w in finalize_report(report)["warnings"]}
    assert codes["depth_scale"]["cameras"] == [a]
    assert "depth_model.yaml" in codes["depth_scale"]["advice"] and "1.0050" in codes[
        "depth_scale"]["advice"]
    # every term free (depth.model_fit.model_terms: all): the scale is there whether needed or
    # not, and only one more than 3 sigmas from 1 is advice
    report["depth_models"][a] = {**model, "terms": ["scale", "offset"],
                                 "parameters": {"scale": 1.005, "d0": 0.1},
                                 "sigmas": {"scale": 0.003, "d0": 0.02}}
    assert "depth_scale" not in {w["code"] for w in finalize_report(report)["warnings"]}
    # 1.17: the views the model was fitted on
    report["depth_models"][a]["n_views"] = 12
    assert validate_report(finalize_report(report)) == []


def test_rebuild_reads_a_report_from_before_rmse_final(runs, tmp_path):
    """A 1.0 report's depth pairs have no ``rmse_final_mm`` (added in 1.1): the rebuild
    fills it with null instead of refusing the report."""
    copy = tmp_path / "old"
    shutil.copytree(runs[0], copy)
    report = _load(copy)
    a, b = list(report["cameras"])[:2]
    pair = pair_entry(
        {
            "cam_a": a,
            "cam_b": b,
            "fitness": 0.8,
            "rmse_before_mm": 6.0,
            "rmse_after_mm": 5.0,
            "accepted": True,
            "overlap_fraction": 0.4,
            "T_b_a": [[1.0]],
            "time_s": 1.0,
        }
    )
    pair.pop("rmse_final_mm", None)
    report["pairs"], report["schema_version"] = [pair], "1.0"
    (copy / "report.json").write_text(json.dumps(report))
    rebuild_report(copy)
    rebuilt = _load(copy)
    assert rebuilt["schema_version"] == REPORT_SCHEMA_VERSION
    assert rebuilt["pairs"][0]["rmse_final_mm"] is None
    assert validate_report(rebuilt) == []


def test_depth_that_confirms_the_board_result_is_an_info_not_a_warning(runs, tmp_path):
    """No pair used because ICP moved each by less than its own uncertainty: the depth agrees
    with the board result (info ``depth_agrees``, the verdict unchanged by it); pairs that
    failed to register, or one that contradicts the board, keep the warning ``depth_unused``.
    A report written before schema 1.9 gets ``agrees`` from its pairs' reasons."""
    report = _load(runs[0])
    assert report["summary"]["verdict"] == "good"
    a, b, c = list(report["cameras"])[:3]
    agree = ("no significant improvement on the current extrinsics: ICP moved 0.30 mm / 0.010 "
             "deg, chi2 1.2 < 12.59 (6 dof) under its own uncertainty")
    beyond = ("ICP moved 4.00 mm / 0.100 deg from the board's extrinsics, beyond their "
              "uncertainty and the pair's (chi2 90 > 16.81, 6 dof): a wrong local minimum")

    def pair(x, y, reason, fitness=0.7):
        return pair_entry({"cam_a": x, "cam_b": y, "fitness": fitness, "accepted": False,
                           "reason": reason, "correction_mm": 0.3, "correction_deg": 0.01})

    def findings_of(pairs):
        report["pairs"] = pairs
        report["timings_s"]["depth"] = 1.0
        report["depth"] = {"status": "fallback", "weak_cameras": {},
                           "reason": f"all {len(pairs)} camera pairs were rejected"}
        out = finalize_report(report)
        assert validate_report(out) == []
        return {w["code"]: w for w in out["warnings"]}, out["summary"]["verdict"]

    confirmed = [pair(a, b, agree), pair(a, c, "fitness 0.20 < 0.3", 0.2)]
    assert [p["agrees"] for p in confirmed] == [True, False]  # from the reason (pre-1.9)
    codes, verdict = findings_of(confirmed)
    assert "depth_unused" not in codes and verdict == "good"
    assert codes["depth_agrees"]["severity"] == "info"
    assert codes["depth_agrees"]["cameras"] == sorted([a, b])
    assert "1 of 2 camera pairs" in codes["depth_agrees"]["message"]
    for pairs in ([pair(a, c, "fitness 0.20 < 0.3", 0.2)], confirmed + [pair(b, c, beyond)]):
        codes, verdict = findings_of(pairs)
        assert "depth_unused" in codes and "depth_agrees" not in codes and verdict == "check"

    copy = tmp_path / "old"  # the rebuild fills a 1.8 report's agrees
    shutil.copytree(runs[0], copy)
    old = _load(copy)
    old["pairs"], old["schema_version"] = [pair(a, b, agree)], "1.8"
    del old["pairs"][0]["agrees"]
    (copy / "report.json").write_text(json.dumps(old))
    rebuild_report(copy)
    assert _load(copy)["pairs"][0]["agrees"] is True


def test_depth_unused_sums_up_alike_pairs_and_names_the_depth_models_beyond_the_scale():
    """Rejected pairs that differ only in their numbers read once with their count and the
    moves' range (an 8-camera ring gave 16 such sentences), and calibrate's warning says why
    the pairs could not help when depth models found errors beyond the scale: they register
    the depth divided by the scale alone (docs/depth.md, 'Weak board data'); a depth-only
    refinement (it registers model-corrected clouds) does not say so."""
    from rgbd_calib.outputs.report.findings_depth import depth_unused

    def moved(a, b, mm):
        return {"cam_a": a, "cam_b": b, "accepted": False, "correction_mm": mm,
                "rejected_by": ["beyond_extrinsics"],
                "reason": f"ICP moved {mm:.2f} mm / 0.100 deg from the board's extrinsics, "
                          f"beyond their uncertainty and the pair's (chi2 {10 * mm:.0f} > "
                          "22.46, 6 dof): a wrong local minimum or a depth error"}

    pairs = [moved("c0", "c1", 5.2), moved("c1", "c2", 44.3), moved("c0", "c2", 9.0),
             {"cam_a": "c2", "cam_b": "c3", "accepted": False, "correction_mm": 0.1,
              "rejected_by": ["fitness"], "reason": "fitness 0.20 < 0.3"}]
    report = {"depth": {"status": "fallback"}, "timings_s": {"depth": 1.0}, "pairs": pairs,
              "depth_models": {"c0": {"terms": ["scale"]}, "c1": {"terms": ["scale", "offset"]},
                               "c2": {"terms": ["scale", "offset", "pose"]}, "c3": {}}}
    (f,) = depth_unused(report, [])
    assert f["severity"] == "warning" and f["code"] == "depth_unused"
    assert ("3 pairs: ICP moved 5.2-44.3 mm from the board's extrinsics, beyond their "
            "uncertainty and the pair's: a wrong local minimum or a depth error; fitness 0.20 "
            "< 0.3)") in f["message"]
    assert "depth models of c1, c2 found errors beyond the scale" in f["message"]
    assert "hold the board where the cameras' views overlap" in f["advice"]
    report["depth_models"] = {"c0": {"terms": ["scale"]}}
    (f,) = depth_unused(report, [])
    assert "depth models" not in f["message"] and "hold the board" not in f["advice"]


def test_pairs_name_the_kind_of_each_rejection_and_older_reports_get_it_from_their_reasons():
    """``pairs[].rejected_by`` (schema 1.18): the findings read the kind, not the wording; a
    report written before it gets the kinds from its reasons' clauses, one per clause."""
    from rgbd_calib.depth.registration import REJECTION_KINDS
    from rgbd_calib.outputs.report.build import kinds_from_reason, pair_entry
    from rgbd_calib.outputs.report.findings_depth import confirming_pairs

    older = {
        "fitness 0.20 < 0.3; point-to-plane RMSE 9.1 mm > 5.0 mm": ["fitness", "rmse"],
        "12 correspondences < 300; 3 surface patches of 0.2 m < 8: too few to estimate the "
        "pair's uncertainty": ["correspondences", "patches"],
        "poorly conditioned overlap (0.0012 < 0.01): the common surfaces leave a direction "
        "unconstrained (e.g. a single plane)": ["conditioning"],
        "no significant improvement on the current extrinsics: ICP moved 0.10 mm / 0.002 deg, "
        "chi2 1.2 < 12.6 (6 dof) under its own uncertainty": ["not_significant"],
        "ICP moved 5.20 mm / 0.100 deg from the board's extrinsics, beyond their uncertainty "
        "and the pair's (chi2 52 > 22.46, 6 dof): a wrong local minimum or a depth error":
            ["beyond_extrinsics"],
        "moved 612 mm / 4.0 deg from the check's estimate (a fix's limit: 100 mm / 10 deg): "
        "another minimum": ["fix_reach"],
        "not used: the joint solve failed (x; y)": ["not_used"],
        "registration process died (MemoryError)": ["failed"],
    }
    for reason, kinds in older.items():
        assert kinds_from_reason({"reason": reason}) == kinds
        assert set(kinds) <= set(REJECTION_KINDS)
    assert kinds_from_reason({"reason": None}) == []
    # a pair of this version keeps its own kinds; one of before 1.18 gets them
    entry = pair_entry({"cam_a": "a", "cam_b": "b", "accepted": False,
                        "reason": "fitness 0.20 < 0.3", "rejected_by": ("fitness",)})
    assert entry["rejected_by"] == ["fitness"]
    entry = pair_entry({"cam_a": "a", "cam_b": "b", "accepted": False,
                        "reason": next(iter(older))})
    assert entry["rejected_by"] == ["fitness", "rmse"]
    # a pair that contradicts the extrinsics is read by its kind, whatever its wording
    agree = {"cam_a": "a", "cam_b": "b", "accepted": False, "agrees": True,
             "reason": "no significant improvement", "rejected_by": ["not_significant"]}
    against = {"cam_a": "b", "cam_b": "c", "accepted": False, "agrees": False,
               "reason": "reworded", "rejected_by": ["beyond_extrinsics"]}
    assert confirming_pairs([agree]) == [agree]
    assert confirming_pairs([agree, against]) == []


def test_edge_figure_draws_a_rig_without_edge_residuals():
    """Only the reference calibrated (no edge residual anywhere): the log-scaled residual
    panels say "no data" instead of raising (it stopped report.html being written)."""
    from rgbd_calib.outputs.report.figures import fig_edges

    report = {"reference": "a", "cameras": {"a": {}, "b": {}}}
    empty = {"camera": "a", "edge_status": "used", "edge_translation_mm": None,
             "edge_rotation_deg": None, "final_reprojection_rms_px": None}
    for views in ([], [empty]):
        png = base64.b64decode(fig_edges({**report, "views": views}))
        assert png.startswith(b"\x89PNG")


@pytest.mark.parametrize("rms_px, excluded, flagged", [
    (0.05, 0, False),  # the bundle used them and they fit: an info
    (0.05, 28, False),  # left out, but they fit the final calibration: an info
    (0.40, 0, True),  # used, but they fit 8x worse than the rig's typical view (out of sync)
    (0.40, 28, True),  # left out and far off: outliers
])
def test_outlier_views_that_fit_the_final_calibration_are_not_an_inconsistent_camera(
    rms_px, excluded, flagged
):
    """Measured on a ring with a misglued back sheet (seed 41): the pose graph, judging under
    the board file's model, flagged 5 of cam0's 15 views and 8 of cam3's 21 as outliers;
    the bundle adjustment with the self-calibrated back sheet used every marker of them at
    0.03-0.06 px and the cameras came out 0.05-0.12 mm off the truth, yet the verdict was
    POOR with two inconsistent_camera errors. And a clean 8-camera ring (seed 105, blur 1 px)
    was CHECK for 4 views rejected at 4.6-5.4 whitened sigmas that fit at 0.03-0.07 px
    (typical 0.044). Views the final calibration fits are an info; views it does not fit
    still count."""
    from rgbd_calib.outputs.report.findings import (
        fitting_outlier_views,
        inconsistent_camera,
        outlier_views,
    )

    def view(frame, status, rms, excl):
        return {"camera": "cam3", "frame": frame, "edge_status": status, "markers": 28,
                "excluded_markers": excl, "final_reprojection_rms_px": rms,
                "edge_translation_mm": 2.3 if status == "outlier" else 0.1}

    views = ([view(f"{i:06d}", "used", 0.04 + 0.002 * i, 0) for i in range(8)]
             + [view(f"{i:06d}", "outlier", rms_px, excluded) for i in range(8, 12)])
    report = {
        "views": views,
        "cameras": {"cam3": {"calibrated": True, "reprojection_all_px": {"p50": 0.04},
                             "edge_outliers": 4, "dropped_reasons": {}, "views_used": 12,
                             "views_dropped": 0}},
        "pose_graph": {"model_error": [], "outliers": [
            {"camera": "cam3", "view": v["frame"]} for v in views[8:]]},
    }
    found = inconsistent_camera(report, [])
    assert bool(found) == flagged, found
    if flagged:
        assert "4 of its 12 board views disagree" in found[0]["message"]
    later = outlier_views(report, found) + fitting_outlier_views(report, found)
    assert [f["code"] for f in later] == ([] if flagged else ["fitting_outlier_views"])
    if not flagged:
        assert later[0]["severity"] == "info"
        kind = "used by the bundle adjustment" if excluded == 0 else "left out (cam3 4)"
        assert kind in later[0]["message"], later[0]["message"]


@pytest.mark.parametrize("views, median, warned", [
    (2, 4, True),  # below the absolute minimum
    (10, 40, True),  # a quarter of the rig's median
    (29, 370, True),
    (123, 370, False),  # race16 x 1000 sets: a third of the median, but plenty of views
    (40, 40, False),
])
def test_few_views_is_relative_to_the_rig_but_capped(views, median, warned):
    """`few_views` flags a camera far below the rig's median number of used views, but not
    one with 30 or more: on a long recording that is plenty (its precision is weak_camera's
    test)."""
    from rgbd_calib.outputs.report.findings import few_views

    cams = {"ref": {"views_used": median, "calibrated": True},
            "other": {"views_used": median, "calibrated": True},
            "cam": {"views_used": views, "calibrated": True}}
    found = few_views({"cameras": cams}, "cam", cams["cam"])
    assert (found is not None) == warned


def test_cameras_the_refined_model_explains_share_one_info():
    """Every lens off (the usual factory-intrinsics case): the whole rig's views disagreed
    under rig.yaml, the refined model explains each camera. One info naming them, not one
    identical line per camera; a camera beyond its prior keeps its own warning."""
    from rgbd_calib.outputs.report.findings import camera_model_error

    def entry(name, n):
        return {"camera": name, "outliers_before": n, "edges": 12, "translation_mm": 4.0,
                "rotation_deg": 0.2, "sigma_factor": 1.0}

    far = {"fx": {"prior": 600.0, "prior_sigma": 2.0, "refined": 640.0, "sigma": 0.3,
                  "change": 40.0, "change_pct": 6.67}}
    report = {"pose_graph": {"model_error": [entry("cam1", 9), entry("cam2", 11),
                                             entry("cam3", 10)]},
              "cameras": {"cam1": {}, "cam2": {}, "cam3": {"intrinsics_refined": far}}}
    found = camera_model_error(report, [])
    assert [(f["severity"], f["cameras"]) for f in found] == [
        ("info", ["cam1", "cam2"]), ("warning", ["cam3"])]
    assert "cam1 9 of 12, cam2 11 of 12 beyond" in found[0]["message"]


@pytest.mark.parametrize(
    "sigma_factor, fx_change, severity",
    [(2.5, 0.0, "warning"),  # kept with an inflated sigma
     (1.0, 3.0, "info"),  # explained by refined intrinsics within 3 prior sigmas (sigma 2 px)
     (1.0, 40.0, "warning")],  # explained, but rig.yaml's fx was off 20 prior sigmas
)
def test_camera_model_error_is_an_info_when_the_refined_model_explains_it(
    sigma_factor, fx_change, severity
):
    """A model error the self-calibrated intrinsics absorb within their prior is what the
    prior is for (factory intrinsics a fraction of a percent off): it must not turn the
    verdict to CHECK. One they absorb far beyond it means rig.yaml is wrong: a warning that
    names the parameter."""
    from rgbd_calib.outputs.report.findings import camera_model_error

    fx = {"prior": 600.0, "prior_sigma": 2.0, "refined": 600.0 + fx_change, "sigma": 0.3,
          "change": fx_change, "change_pct": fx_change / 6.0}
    report = {
        "pose_graph": {"model_error": [{"camera": "cam3", "outliers_before": 9, "edges": 12,
                                        "translation_mm": 4.0, "rotation_deg": 0.2,
                                        "sigma_factor": sigma_factor}]},
        "cameras": {"cam3": {"intrinsics_refined": {"fx": fx}}},
    }
    (found,) = camera_model_error(report, [])
    assert (found["code"], found["cameras"], found["severity"]) == (
        "camera_model_error", ["cam3"], severity)
    if fx_change > 10:
        assert "fx +6.67 % (20 sigma)" in found["message"]
        assert "rig_refined.yaml" in found["advice"]
    # the self-calibration loosened the priors 10x for this camera: the reported prior sigma
    # is 10x the configured one, and a change within 3 of those is still beyond the rig.yaml's
    if sigma_factor <= 1.0:
        fx["prior_sigma"] *= 10
        report["bundle"] = {"self_calibration": {"chosen": "fx", "levels": [
            {"level": "fx", "reason": "fits better; fx of cam3 came 4.6 prior sigmas from "
             "rig.yaml: priors loosened 10x"}]}}
        (found,) = camera_model_error(report, [])
        assert found["severity"] == severity


def test_an_estimated_view_floor_is_an_info_that_says_its_size():
    """``pose.model_error_px: auto`` set a floor (real cameras): one info with its size and how
    far the typical view was off; none when it stayed 0, was fixed, or the report predates it."""
    from rgbd_calib.outputs.report.findings import view_model_error

    def report(floor):
        pg = {"model_error": []}
        if floor != "absent":
            pg["view_floor"] = floor
        return {"pose_graph": pg}

    (found,) = view_model_error(report({"model_error_px": 0.29, "misfit_ratio": 70.75,
                                        "edges": 64}), [])
    assert (found["code"], found["severity"]) == ("view_model_error", "info")
    assert "0.29 px" in found["message"] and "8.4x" in found["message"]
    for quiet in ({"model_error_px": 0.0, "misfit_ratio": 0.57, "edges": 40}, None, "absent"):
        assert view_model_error(report(quiet), []) == []


def test_a_board_whose_printed_size_is_not_stated_is_named_with_what_a_print_error_costs():
    """The info ``board_size``: the board file states no print_scale_sigma, so every
    translation rests on its lengths being exact; it names the farthest camera and what a
    0.1 % print error moves it by. A stated sigma (0 included: a render's exact board) or an
    older report without the key says nothing."""
    from rgbd_calib.outputs.report.findings import board_size

    def report(sigma="absent"):
        board = {"markers_seen": 10} if sigma == "absent" else {"print_scale_sigma": sigma}
        return {"board": board, "cameras": {
            "ref": {"calibrated": True, "translation_m": [0.0, 0.0, 0.0]},
            "near": {"calibrated": True, "translation_m": [0.9, 0.0, 0.1]},
            "far": {"calibrated": True, "translation_m": [1.5, 0.3, 2.4]},
            "lost": {"calibrated": False, "translation_m": None}}}

    found = board_size(report(None), [])
    assert [(f["code"], f["severity"], f["cameras"]) for f in found] == [
        ("board_size", "info", ["far"])]
    assert "puts far 2.8 mm off (2.85 m from the reference)" in found[0]["message"]
    assert "print_scale_sigma" in found[0]["advice"]
    assert board_size(report(0.0), []) == board_size(report(0.0005), []) == []
    assert board_size(report(), []) == []


def test_the_report_leads_with_the_verdict_and_at_most_three_actions_the_rest_folded():
    """Issue 58: report.html opens with the verdict in plain words and the actions that matter
    most (what to do, then why), as the console lists them; every finding is folded below."""
    from rgbd_calib.outputs.report.html import REPORT_ACTIONS, _verdict_section

    found = [{"severity": s, "code": f"code{k}", "cameras": ["cam1"], "message": f"why {k}",
              "advice": f"do {k}"} for k, s in enumerate(["info", "warning", "error", "info",
                                                          "warning"])]
    html = "".join(_verdict_section({"summary": {"verdict": "poor"}, "warnings": found,
                                     "next_steps": []}))
    head, _, folded = html.partition("<details>")
    assert "Do not use these extrinsics" in head and head.count("<li>") == REPORT_ACTIONS == 3
    assert head.index("do 2") < head.index("do 1") < head.index("do 4")  # errors first
    assert "Every finding (5)" in folded and all(f"why {k}" in folded for k in range(5))
