"""report.json for large rigs (issue 17, item 4): above a view-count threshold the per-view
detail goes to report_views.ndjson.gz with a ``views_file`` pointer; up to it report.json is
written exactly as before. Both paths, the rebuild and the HTML, on the tiny rig with a
threshold of 3 views standing in for 2000."""

from __future__ import annotations

import gzip
import json
import shutil

import pytest

from rgbd_calib.core.config import CalibrationConfig
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.outputs.report import (
    VIEWS_FILE,
    ReportError,
    dump_report,
    load_report,
    rebuild_report,
    validate_report,
)
from rgbd_calib.outputs.report.storage import join_views, split_report
from rgbd_calib.outputs.writer import write_outputs
from rgbd_calib.pipelines.calibrate import calibrate

SMALL = 3  # views kept inline in these tests (2000 in use)


@pytest.fixture(scope="module")
def written(tiny_dataset, tmp_path_factory):
    """The tiny rig calibrated once (board only), written inline and with the side file."""
    base = tmp_path_factory.mktemp("storage")
    ds = FolderDataset(tiny_dataset)
    result = calibrate(ds, thesis_board(), CalibrationConfig(refine="none"),
                       cache_dir=base / "cache")
    write_outputs(result, ds.rig, base / "inline")
    write_outputs(result, ds.rig, base / "side", views_inline_max=SMALL)
    return result, ds.rig, base / "inline", base / "side"


def test_above_the_threshold_views_move_to_the_side_file(written):
    _, _, inline, side = written
    full = json.loads((inline / "report.json").read_text())
    assert len(full["views"]) > SMALL and not (inline / VIEWS_FILE).exists()
    stored = json.loads((side / "report.json").read_text())
    assert "views" not in stored
    # the pointer sits where views was; every other key is as inline
    assert list(stored) == [("views_file" if k == "views" else k) for k in full]
    assert stored["views_file"]["count"] == len(full["views"])
    assert {k: v for k, v in stored.items() if k != "views_file"} == {
        k: v for k, v in full.items() if k != "views"}
    lines = gzip.decompress((side / VIEWS_FILE).read_bytes()).decode().splitlines()
    assert [json.loads(line) for line in lines] == full["views"]
    assert load_report(side / "report.json") == full
    assert validate_report(stored) == [] and validate_report(full) == []
    assert validate_report({**full, "views_file": stored["views_file"]})  # both: refused
    # the HTML is drawn from the same report either way
    assert (side / "report.html").read_bytes() == (inline / "report.html").read_bytes()


def test_rebuild_keeps_the_side_file_and_reproduces_both(written, tmp_path):
    _, _, _, side = written
    copy = tmp_path / "side"
    shutil.copytree(side, copy)
    before = {p: (copy / p).read_bytes() for p in ("report.json", VIEWS_FILE, "report.html")}
    (copy / "report.html").unlink()
    rebuild_report(copy)
    assert {p: (copy / p).read_bytes() for p in before} == before
    (copy / VIEWS_FILE).unlink()
    with pytest.raises(ReportError, match=f"{VIEWS_FILE}: missing"):
        rebuild_report(copy)


def test_a_side_file_of_another_run_is_refused(written, tmp_path):
    _, _, _, side = written
    stored = json.loads((side / "report.json").read_text())
    text = gzip.decompress((side / VIEWS_FILE).read_bytes()).decode()
    other = gzip.compress(text.replace('"camera"', '"camera" ', 1).encode())
    with pytest.raises(ReportError, match="does not match the report.json"):
        join_views(stored, other, side / VIEWS_FILE)


def test_a_smaller_run_writes_inline_again_and_removes_the_old_side_file(written, tmp_path):
    result, rig, inline, side = written
    out = tmp_path / "out"
    shutil.copytree(side, out)
    write_outputs(result, rig, out)  # default threshold: inline
    assert not (out / VIEWS_FILE).exists()
    assert (out / "report.json").read_bytes() == (inline / "report.json").read_bytes()


def test_at_or_below_the_threshold_nothing_changes():
    report = {"schema_version": "1.3", "views": [{"camera": "a"}] * SMALL, "x": 1}
    stored, side = split_report(report, SMALL)
    assert stored is report and side is None
    stored, side = split_report(report, SMALL - 1)
    assert side is not None and "views" not in stored
    assert dump_report(join_views(stored, side, VIEWS_FILE)) == dump_report(report)
