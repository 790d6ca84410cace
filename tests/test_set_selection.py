"""A long continuous recording is thinned to ``bundle.max_sets`` frame sets
(rgbd_calib/solve/runs.py select_sets, rgbd_calib/pipelines/calibrate.py): runs of
consecutive sets spread over it, every camera kept, the selection in the result, the report
and on the console. A still burst render (race, 10 poses x 6 consecutive sets, seed 52):
about a minute on 2 cores (slow); the README's tiny rig stamped as a recording (default)."""

from __future__ import annotations

import json

import pytest

from rgbd_calib import CalibrationConfig, FolderDataset, calibrate
from rgbd_calib.core.geometry import transform_error
from rgbd_calib.model.board import thesis_board
from rgbd_calib.outputs.writer import write_outputs
from rgbd_calib.solve.runs import recording_runs
from rgbd_calib.synth.render import SynthParams, load_ground_truth, synthesize


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("burst") / "race"
    synthesize(out, "race", 10, 52, thesis_board(), SynthParams(burst=6))
    return out


def _config(max_sets: int) -> CalibrationConfig:
    return CalibrationConfig.model_validate(
        {"refine": "none", "bundle": {"max_sets": max_sets, "set_run_length": 3}})


@pytest.mark.slow
def test_the_recording_is_thinned_to_runs_and_every_camera_calibrated(recording, tmp_path):
    result = calibrate(FolderDataset(recording), thesis_board(), _config(30))
    sel = result.set_selection
    assert sel is not None and sel.total == 60 and sel.run_length == 3
    assert 30 <= len(sel.kept) < 60
    frames = {o.frame for o in result.observations}
    assert frames <= set(sel.kept)
    # runs of three consecutive sets of the bursts (33 ms apart)
    set_ms = {f: 1000.0 * (int(f) // 6) + 1000 / 30 * (int(f) % 6) for f in sel.kept}
    assert all(len(r) >= 3 for r in recording_runs(set_ms, sel.kept, 100.0))
    gt = load_ground_truth(recording)
    assert set(result.extrinsics.cameras) == set(gt.T_ref_cam)  # none dropped by thinning
    for c, cam in result.extrinsics.cameras.items():
        deg, mm = transform_error(cam.T_ref_cam, gt.T_ref_cam[c])
        assert mm < 1.0 and deg < 0.1, (c, mm, deg)
    write_outputs(result, FolderDataset(recording).rig, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["frame_selection"] == {"kept": len(sel.kept), "total": 60, "run_length": 3}
    assert {v["frame"] for v in report["views"]} <= set(sel.kept)


@pytest.mark.slow
def test_every_set_kept_with_max_sets_0(recording):
    result = calibrate(FolderDataset(recording), thesis_board(), _config(0))
    assert result.set_selection is None
    assert len({o.frame for o in result.observations}) == 60


def test_a_stamped_recording_longer_than_max_sets_is_thinned(tiny_dataset, tmp_path):
    """Default tier: the README's tiny rig (4 still frame sets) stamped as one continuous
    recording, max_sets 3: one run of 3 consecutive sets kept, every camera calibrated."""
    import shutil

    data = tmp_path / "tiny"
    shutil.copytree(tiny_dataset, data)
    for cam in (p for p in data.iterdir() if p.is_dir() and (p / "color").is_dir()):
        frames = sorted(f.stem for f in (cam / "color").iterdir())
        (cam / "timestamps.csv").write_text("frame,t_ms\n" + "".join(
            f"{f},{1000 + 33.3 * int(f)}\n" for f in frames))
    result = calibrate(FolderDataset(data), thesis_board(), _config(3))
    sel = result.set_selection
    assert sel is not None and sel.total == 4 and len(sel.kept) == 3
    assert recording_runs({f: 33.3 * int(f) for f in sel.kept}, sel.kept, 100.0) == (
        sel.kept,)
    assert {o.frame for o in result.observations} <= set(sel.kept)
    assert set(result.extrinsics.cameras) == set(FolderDataset(data).rig.names)
