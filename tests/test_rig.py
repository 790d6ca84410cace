"""rig.yaml loading (formats.md) and its error messages."""

import pytest
import yaml
from conftest import CONFIGS, SHARED_DATA

from rgbd_calib.core.errors import ConfigError
from rgbd_calib.model.rig import load_rig, save_rig

GOOD = {"reference": "cam8", "cameras": {
    "cam7": {"width": 1280, "height": 720, "fx": 633.47, "fy": 633.47, "cx": 643.2, "cy": 358.4},
    "cam8": {"width": 1280, "height": 720, "fx": 637.5, "fy": 637.5, "cx": 643.3, "cy": 355.3,
             "distortion": [0.01, 0, 0, 0, 0], "depth_scale": 0.0001}}}


def write(tmp_path, data):
    p = tmp_path / "rig.yaml"
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


def test_load_and_defaults(tmp_path):
    rig = load_rig(write(tmp_path, GOOD))
    assert rig.reference == "cam8" and rig.names == ["cam7", "cam8"]
    assert rig.cameras["cam7"].distortion == (0.0,) * 5
    assert rig.cameras["cam7"].depth_scale == 0.001
    assert rig.cameras["cam8"].depth_scale == 0.0001
    save_rig(rig, tmp_path / "again.yaml")
    assert load_rig(tmp_path / "again.yaml") == rig


def test_depth_noise_model_per_camera(tmp_path):
    """``depth_noise`` (default d435) survives a save and load; a D435 camera's entry is
    written without it, so existing rig files do not change."""
    import copy

    data = copy.deepcopy(GOOD)
    data["cameras"]["cam8"]["depth_noise"] = "kinect-v1"
    rig = load_rig(write(tmp_path, data))
    assert rig.cameras["cam7"].depth_noise == "d435"
    assert rig.cameras["cam8"].depth_noise == "kinect-v1"
    assert "depth_noise" not in rig.cameras["cam7"].to_dict()
    save_rig(rig, tmp_path / "again.yaml")
    assert load_rig(tmp_path / "again.yaml") == rig


def test_reference_defaults_to_first_camera(tmp_path):
    data = {"cameras": GOOD["cameras"]}
    assert load_rig(write(tmp_path, data)).reference == "cam7"


def test_thesis_rig_matches_table_4_1_and_camera_info():
    rig = load_rig(CONFIGS / "rig_thesis.yaml")
    table_4_1 = {"cam7": (633.470275878906, 643.229064941406, 358.437103271484),
                 "cam8": (637.565185546875, 643.337707519531, 355.360290527343),
                 "cam9": (640.793884277343, 645.108825683593, 356.419738769531),
                 "cam10": (642.689758300781, 645.234985351562, 355.756347656250)}
    for name, (f, cx, cy) in table_4_1.items():
        c = rig.cameras[name]
        assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx((f, f, cx, cy), abs=1e-8)
        assert (c.width, c.height) == (1280, 720)
    info = SHARED_DATA / "thesis-posegraph" / "camera_info.yaml"
    if info.exists():
        rows = yaml.safe_load(info.read_text())["intrinsic"]
        full = load_rig(CONFIGS / "rig_thesis16.yaml")
        assert len(full.cameras) == 16
        for i in range(7, 23):
            assert full.cameras[f"cam{i}"].fx == pytest.approx(rows[i][0])


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d["cameras"]["cam7"].update(fx=0), "fx: must be a positive"),
    (lambda d: d["cameras"]["cam7"].update(fy=float("nan")), "fy: must be a positive"),
    (lambda d: d["cameras"]["cam7"].update(cx=-3), "cx: must be a positive"),
    (lambda d: d["cameras"]["cam7"].update(cx=2000), "principal point"),
    (lambda d: d["cameras"]["cam7"].update(focal=600), "unknown key"),
    (lambda d: d["cameras"]["cam7"].pop("width"), "missing required key"),
    (lambda d: d["cameras"]["cam7"].update(distortion=[1, 2, 3]), "distortion"),
    (lambda d: d.update(reference="camX"), "reference camera 'camX'"),
    (lambda d: d["cameras"].update({"bad name": d["cameras"]["cam7"]}), "may only use"),
    (lambda d: d.update(cameras={}), "non-empty mapping"),
    (lambda d: d["cameras"]["cam7"].update(depth_noise="kinect"), "not a depth noise model"),
])
def test_bad_rigs_fail_with_one_line(tmp_path, mutate, message):
    import copy

    data = copy.deepcopy(GOOD)
    mutate(data)
    with pytest.raises(ConfigError, match=message) as err:
        load_rig(write(tmp_path, data))
    assert "\n" not in str(err.value) and "rig.yaml" in str(err.value)


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_rig(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_rig(write(tmp_path, "cameras: [1, 2"))
