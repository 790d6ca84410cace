"""The config module: per-stage validation, YAML + overrides -> CalibrationConfig with one-line
errors, and the resolved config written beside a result reading back unchanged."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from rgbd_calib.core.config import (
    CalibrationConfig,
    DepthConfig,
    DetectionConfig,
    PoseConfig,
    PoseGraphConfig,
    load_config,
    write_config,
)
from rgbd_calib.core.errors import ConfigError


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


def test_grouped_settings_read_at_their_group_or_where_they_were_before(tmp_path):
    """A depth setting in its group or, as config files gave it before the groups, directly
    under ``depth:``: the same config; both at once and different: one line naming it."""
    grouped, flat, both = (tmp_path / n for n in ("grouped.yaml", "flat.yaml", "both.yaml"))
    grouped.write_text("depth:\n  clouds: {max_frames: 8}\n  acceptance: {min_fitness: 0.4}\n")
    flat.write_text("depth:\n  max_frames: 8\n  min_fitness: 0.4\n")
    both.write_text("depth:\n  max_frames: 9\n  clouds: {max_frames: 8}\n")
    cfg = load_config(grouped)
    assert cfg == load_config(flat) != CalibrationConfig()
    assert cfg.depth.clouds.max_frames == 8 and cfg.depth.acceptance.min_fitness == 0.4
    assert load_config(None, **{"depth.max_frames": 8, "depth.min_fitness": 0.4}) == cfg
    with pytest.raises(ConfigError, match="max_frames is given twice") as err:
        load_config(both)
    assert "\n" not in str(err.value) and str(both) in str(err.value)
    # the resolved file lists the groups and reads back unchanged
    write_config(cfg, tmp_path / "resolved.yaml")
    assert "  clouds:\n    max_frames: 8" in (tmp_path / "resolved.yaml").read_text()
    assert load_config(tmp_path / "resolved.yaml") == cfg


def test_a_group_refuses_a_setting_it_does_not_hold_in_model_copy_and_replaced():
    """pydantic's model_copy takes any key without a check: a setting left at its place
    before the groups would be silently unused. The groups refuse it; ``replaced`` finds each
    setting's group itself."""
    depth = DepthConfig()
    with pytest.raises(TypeError, match="max_frames"):
        depth.model_copy(update={"max_frames": 3})
    assert depth.replaced(max_frames=3, model="none").clouds.max_frames == 3
    assert depth.replaced(model="none").model == "none"
    with pytest.raises(TypeError, match="max_frame"):
        depth.replaced(max_frame=3)
    with pytest.raises(ValidationError):
        depth.replaced(min_range_m=5.0)  # beyond max_range_m: validated as a file is


def test_a_grouped_stage_dumps_flat_as_before_the_groups():
    """The detection cache's fingerprint hashes the settings flat (sorted keys), so caches
    written before the groups stay valid: every setting once, no group left."""
    flat = DetectionConfig(edge_passes=3, subpix_win_size_px=7).flat_dump()
    assert flat["edge_passes"] == 3 and flat["subpix_win_size_px"] == 7
    assert not {"edges", "aruco"} & set(flat) and len(flat) == 27
    assert DetectionConfig(**flat) == DetectionConfig(edge_passes=3, subpix_win_size_px=7)


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
        ("pose:\n  model_error_px: autox\n", "pose.model_error_px"),
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


def test_model_error_floor_is_a_number_or_auto(tmp_path):
    """``pose.model_error_px``: ``auto`` (the default: estimated by the pose graph), a number of
    pixels, or one error line that names both forms."""
    path = tmp_path / "calib.yaml"
    assert CalibrationConfig().pose.model_error_px == "auto"
    for text, value in (("auto", "auto"), ("0.5", 0.5), ("'0.25'", 0.25), ("0", 0.0)):
        path.write_text(f"pose:\n  model_error_px: {text}\n")
        assert load_config(path).pose.model_error_px == value
    path.write_text("pose:\n  model_error_px: automatic\n")
    with pytest.raises(ConfigError, match="a number of pixels .* or 'auto', got 'automatic'"):
        load_config(path)


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
    # the user section first (issue 57), then every setting in field order, as in the model
    text = path.read_text()
    assert "\nuser:\n" in text and text.index("\nuser:\n") < text.index("\ndetection:\n")


# The child process of the test below: validate a config from YAML + overrides, then do what a
# pool worker of calibrate.detect_dataset does (import the initializer and job it is given by
# reference, run them on one image); print the marker ids found and the heavy modules loaded.
_CHILD = """
import importlib, json, sys
from pathlib import Path

from rgbd_calib.core.config import load_config

config_path, image, width, height, *functions = sys.argv[1:]
cfg = load_config(Path(config_path), method="posegraph", **{"detection.refinement": "subpix"})
assert cfg.pose.min_markers == 2 and cfg.detection.refinement == "subpix", cfg

from rgbd_calib.model.board import thesis_board

init, job = (getattr(importlib.import_module(f.split(":")[0]), f.split(":")[1]) for f in functions)
init(thesis_board(), cfg.detection)
_, _, det = job(("cam0", "000000", image, int(width), int(height)))
heavy = sorted(m for m in ("open3d", "kiss_icp", "gtsam") if m in sys.modules)
print(json.dumps({"ids": det["ids"], "heavy": heavy}))
"""


def test_config_and_a_detection_worker_load_no_open3d_kiss_icp_or_gtsam(tmp_path):
    """Validating a config and starting a detection worker must stay light: a worker imports
    the module of the function the pool runs, so that module must not pull in graph/depth."""
    import json
    import os
    import subprocess
    import sys

    import cv2
    import numpy as np

    from rgbd_calib.detect import run as detect_run
    from rgbd_calib.model.board import aruco_dictionary, thesis_board

    board = thesis_board()
    marker_id = int(board.ids[5])
    image = np.full((360, 640), 255, np.uint8)
    marker = cv2.aruco.generateImageMarker(aruco_dictionary(board.dictionary), marker_id, 120)
    image[100:220, 250:370] = marker
    image_path = tmp_path / "000000.png"
    cv2.imwrite(str(image_path), cv2.GaussianBlur(image, (0, 0), 0.7))
    config_path = tmp_path / "calib.yaml"
    config_path.write_text("pose:\n  min_markers: 2\ndetection:\n  refinement: edges\n")
    pool_functions = [detect_run.init_detector, detect_run.detect_job]  # detect_dataset's pool
    refs = [f"{f.__module__}:{f.__qualname__}" for f in pool_functions]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(config_path), str(image_path), "640", "360", *refs],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["ids"] == [marker_id]  # the job really ran
    assert result["heavy"] == []
