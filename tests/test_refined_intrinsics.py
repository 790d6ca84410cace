"""refine and check back-project depth with the intrinsics the calibration refined
(``rig_refined.yaml`` beside its extrinsics, with the sigmas of its report.json), and the
clouds carry those sigmas (docs/depth.md, 'Refined intrinsics')."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from rgbd_calib.core.config import DepthConfig
from rgbd_calib.core.errors import DatasetError
from rgbd_calib.depth.clouds import static_cloud
from rgbd_calib.model.calib_folder import with_refined_intrinsics
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.model.rig import Rig, load_rig, save_rig


def _calibration(folder, rig: Rig, shift_fx: float, sigma: float | None, width=None):
    folder.mkdir(parents=True, exist_ok=True)
    first = next(iter(rig.cameras))
    intr = rig.cameras[first]
    refined = replace(intr, fx=intr.fx + shift_fx, width=width or intr.width)
    save_rig(Rig({**rig.cameras, first: refined}, rig.reference), folder / "rig_refined.yaml")
    cams = {first: {"intrinsics_refined": {"fx": {"refined": refined.fx, "sigma": sigma}}}}
    if sigma is not None:
        (folder / "report.json").write_text(json.dumps({"cameras": cams}))
    return first, refined


def test_refined_intrinsics_replace_rig_yaml_with_their_sigmas(tiny_dataset, tmp_path):
    rig = load_rig(tiny_dataset / "rig.yaml")
    first, refined = _calibration(tmp_path / "calib", rig, 1.5, 0.2)
    out, changed = with_refined_intrinsics(rig, tmp_path / "calib")
    assert changed == [first]
    assert out.cameras[first] == refined
    assert out.sigmas == {first: {"fx": 0.2}}
    assert all(out.cameras[c] == rig.cameras[c] for c in rig.cameras if c != first)
    # no rig_refined.yaml: rig.yaml as it is
    same, none = with_refined_intrinsics(rig, tmp_path / "elsewhere")
    assert same is rig and none == []


def test_refined_intrinsics_of_another_resolution_are_refused(tiny_dataset, tmp_path):
    rig = load_rig(tiny_dataset / "rig.yaml")
    _calibration(tmp_path / "calib", rig, 0.0, 0.2, width=1280)
    with pytest.raises(DatasetError, match="rig_refined.yaml: camera .* is 1280x"):
        with_refined_intrinsics(rig, tmp_path / "calib")


def test_a_cloud_carries_the_variance_of_estimated_intrinsics(tiny_dataset):
    ds = FolderDataset(tiny_dataset)
    cam = ds.cameras[0]
    config = DepthConfig(max_frames=2)
    exact = static_cloud(ds, cam, {}, np.eye(4), None, config)
    assert exact.intrinsics_variance == {}
    ds.rig = replace(ds.rig, sigmas={cam: {"fx": 0.3, "cx": 0.5}})
    cloud = static_cloud(ds, cam, {}, np.eye(4), None, config)
    f2 = config.uncertainty.lens_sigma_factor ** 2
    assert cloud.intrinsics_variance == pytest.approx({"fx": f2 * 0.09, "cx": f2 * 0.25})
