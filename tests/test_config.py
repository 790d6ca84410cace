"""The config module: per-stage validation, YAML + overrides -> CalibrationConfig with one-line
errors, and the resolved config written beside a result reading back unchanged."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from rgbd_calib.config import (
    CalibrationConfig,
    DepthConfig,
    DetectionConfig,
    PoseConfig,
    PoseGraphConfig,
    load_config,
    write_config,
)
from rgbd_calib.errors import ConfigError


def test_detection_config_rejects_unknown_and_inconsistent_fields():
    with pytest.raises(ValueError):
        DetectionConfig(refinement="apriltag")
    with pytest.raises(ValueError):
        DetectionConfig(edge_span=(0.8, 0.2))
    with pytest.raises(ValueError):
        DetectionConfig(unknown_option=1)


def test_pose_graph_config_rejects_unknown_keys():
    with pytest.raises(ValueError):
        PoseGraphConfig(kernal="huber")
    with pytest.raises(ValueError):
        PoseGraphConfig(kernel="welsch")


def test_depth_config_rejects_unknown_keys_and_inconsistent_schedules():
    with pytest.raises(ValidationError):
        DepthConfig(max_frame=3)
    with pytest.raises(ValidationError):
        DepthConfig(voxel_schedule_m=[0.04, 0.02], iterations=[50, 30, 14])
    with pytest.raises(ValidationError):
        DepthConfig(voxel_schedule_m=[0.01, 0.02], iterations=[10, 10])
    with pytest.raises(ValidationError):
        DepthConfig(min_range_m=3.0, max_range_m=2.0)


def test_load_config_applies_the_yaml_then_the_overrides(tmp_path):
    path = tmp_path / "calib.yaml"
    path.write_text("method: posegraph\npose:\n  min_markers: 3\ngraph:\n  kernel: huber\n")
    cfg = load_config(path, method="bundle", workers=None, **{"graph.kernel": "tukey"})
    assert cfg.method == "bundle"  # an override beats the file
    assert cfg.graph.kernel == "tukey"  # dotted override into a stage
    assert cfg.pose.min_markers == 3  # the file beats the default
    assert cfg.workers is None  # None leaves the setting alone
    assert cfg.detection == DetectionConfig()
    assert load_config(None) == CalibrationConfig()


@pytest.mark.parametrize(
    "text, setting",
    [
        ("pose:\n  min_marker: 3\n", "pose.min_marker"),
        ("pose:\n  min_markers: 0\n", "pose.min_markers"),
    ],
)
def test_load_config_errors_name_the_file_the_setting_and_the_fix(tmp_path, text, setting):
    path = tmp_path / "calib.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    message = str(exc.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: {setting}: ")
    assert "fix this setting" in message
    with pytest.raises(ConfigError, match=r"^options: workers: "):
        load_config(None, workers=0)


def test_written_config_reads_back_unchanged(tmp_path):
    cfg = CalibrationConfig(
        method="posegraph",
        workers=3,
        detection=DetectionConfig(refinement="subpix", edge_span=(0.2, 0.8)),
        pose=PoseConfig(min_markers=2, pixel_sigma_px=0.3),
        graph=PoseGraphConfig(kernel="huber"),
        depth=DepthConfig(voxel_schedule_m=[0.05, 0.01], iterations=[20, 10]),
    )
    path = tmp_path / "config_resolved.yaml"
    write_config(cfg, path)
    assert load_config(path) == cfg
    assert path.read_text().startswith("detection:\n")  # field order, as in the model
