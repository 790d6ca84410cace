"""The settings a user tunes (issue 57): a ``user:`` section, read in a config file and shown
first in config_resolved.yaml, the expert settings by stage after it."""

from __future__ import annotations

import pytest
import yaml

from rgbd_calib.core.config import CalibrationConfig, load_config, write_config
from rgbd_calib.core.errors import ConfigError
from rgbd_calib.core.settings import USER_SETTINGS


def test_config_resolved_leads_with_the_user_settings_and_reads_back(tmp_path):
    config = load_config(None, **{"bundle.intrinsics": "fixed", "depth.fused_voxel_m": 0.01})
    path = tmp_path / "config_resolved.yaml"
    write_config(config, path)
    text = path.read_text()
    data = yaml.safe_load(text)
    assert list(data)[0] == "user" and text.startswith("# rgbd-calib settings")
    assert data["user"]["intrinsics"] == "fixed" and data["user"]["fused_voxel_m"] == 0.01
    assert set(data["user"]) == set(USER_SETTINGS)
    # the earlier keys stay where readers find them
    assert data["method"] == "bundle" and data["bundle"]["intrinsics"] == "fixed"
    assert load_config(path) == config
    assert CalibrationConfig() == load_config(None)  # defaults unchanged


def test_a_user_section_sets_the_stages_settings(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text("user:\n  intrinsics: fixed\n  time: fixed\n  corners: subpix\n")
    config = load_config(path)
    assert config.bundle.intrinsics == "fixed" and config.bundle.time == "fixed"
    assert config.detection.refinement == "subpix"


@pytest.mark.parametrize("text, says", [
    ("user:\n  intrinsic: fixed\n", "user.intrinsic: not a user setting"),
    ("user:\n  intrinsics: fixed\nbundle:\n  intrinsics: refine\n", "give it once"),
    ("user: [intrinsics]\n", "expected a mapping"),
])
def test_a_bad_user_section_is_one_line(tmp_path, text, says):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert "\n" not in str(err.value) and says in str(err.value) and str(path) in str(err.value)
