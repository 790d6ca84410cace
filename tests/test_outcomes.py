"""Outcomes a machine can read (issue 34, "a bad result never looks like a good one"): the exit
code of every command, the verdict inside extrinsics.yaml and the exports, what a folder of
videos or recordings says, the library's check / refine / convert and its path arguments, and
tools/run.sh run from the user's folder.

The POOR result is the tiny rig (4 cameras, 640x360, 4 frames) with cam10's frames cut to the
one no other camera sees: cam10 cannot be connected, the error ``not_calibrated`` makes the
verdict POOR (about 15 s to calibrate)."""

from __future__ import annotations

import importlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import CONFIGS, REPO
from typer.testing import CliRunner

import rgbd_calib
from rgbd_calib.cli.commands import app
from rgbd_calib.core.errors import ConfigError, DatasetError, RgbdCalibError, UnknownCameraError
from rgbd_calib.model.results import (
    CameraExtrinsics,
    Extrinsics,
    Verdict,
    load_extrinsics,
    write_extrinsics,
)

cli_app = importlib.import_module("rgbd_calib.cli.app")  # the package's `app` is the Typer
runner = CliRunner()
UNCONNECTED = "cam10"  # the camera the POOR rig cannot connect


class PathLike:
    """An ``os.PathLike`` that is neither ``str`` nor ``Path``."""

    def __init__(self, path) -> None:
        self.path = str(path)

    def __fspath__(self) -> str:
        return self.path


def cli(*args) -> tuple[int, str]:
    result = runner.invoke(app, [str(a) for a in args])
    if result.exception and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.output


@pytest.fixture(scope="module")
def poor_rig(tiny_dataset, tmp_path_factory) -> Path:
    """The tiny rig with cam10 left only frame 000000, which no other camera sees."""
    data = tmp_path_factory.mktemp("poor") / "dataset"
    shutil.copytree(tiny_dataset, data)
    for kind in ("color", "depth"):
        for p in (data / UNCONNECTED / kind).iterdir():
            if p.stem != "000000":
                p.unlink()
    return data


@pytest.fixture(scope="module")
def poor_calibration(poor_rig, tmp_path_factory) -> tuple[Path, int, str]:
    """``calibrate`` of :func:`poor_rig` through the command line: (out, exit code, output)."""
    out = tmp_path_factory.mktemp("poor_calibration") / "out"
    code, text = cli("calibrate", poor_rig, "--out", out, "--refine", "none", "--workers", "2")
    return out, code, text


# ----------------------------------------------------------------------------- extrinsics.yaml
def _extrinsics(verdict: Verdict | None = None) -> Extrinsics:
    T = np.eye(4)
    T[0, 3] = 0.4
    return Extrinsics("a", {"a": CameraExtrinsics("a", np.eye(4), 0.0, 0.0),
                            "b": CameraExtrinsics("b", T, 0.01, 0.2)}, verdict=verdict)


def test_extrinsics_yaml_keeps_its_verdict_and_rejects_a_malformed_one(tmp_path):
    path = tmp_path / "extrinsics.yaml"
    write_extrinsics(_extrinsics(Verdict("check", "few_views [a]: a has only 2 views.")), path)
    back = load_extrinsics(path, check_redundant=True)
    assert back.verdict == Verdict("check", "few_views [a]: a has only 2 views.")
    write_extrinsics(_extrinsics(), path)  # not judged: no key, as before the verdict existed
    assert "verdict" not in yaml.safe_load(path.read_text()) and load_extrinsics(path).verdict \
        is None
    for bad in ({"grade": "bad", "reason": "x"}, {"grade": "poor"}, "poor"):
        data = yaml.safe_load(path.read_text())
        path.write_text(yaml.safe_dump({"verdict": bad, **data}))
        with pytest.raises(ConfigError, match="verdict must be"):
            load_extrinsics(path)
    with pytest.raises(ConfigError, match="verdict grade"):
        Verdict("excellent", "x")


def test_report_verdict_reason_is_the_worst_finding_in_one_line():
    from rgbd_calib.outputs.report import report_verdict

    def w(severity, code, cams, message):
        return {"severity": severity, "code": code, "cameras": cams, "message": message,
                "advice": ""}

    found = [w("error", "not_calibrated", ["c3"], "c3 was not\ncalibrated."),
             w("error", "board_scale", [], "the board is 2% larger."),
             w("warning", "few_views", ["c1"], "c1 has 2 views.")]
    poor = report_verdict({"summary": {"verdict": "poor"}, "warnings": found})
    assert poor == Verdict("poor", "not_calibrated [c3]: c3 was not calibrated. (and 1 more "
                                   "error(s) in report.json)")
    check = report_verdict({"summary": {"verdict": "check"}, "warnings": found[2:]})
    assert check.reason == "few_views [c1]: c1 has 2 views."
    good = report_verdict({"summary": {"verdict": "good"}, "warnings": []})
    assert good.grade == "good" and "\n" not in good.reason
    long = report_verdict({"summary": {"verdict": "check"},
                           "warnings": [w("warning", "x", [], "y " * 400)]})
    assert len(long.reason) <= 300 and long.reason.endswith("...")


def test_an_unknown_camera_names_the_cameras():
    ext = _extrinsics()
    for lookup in (lambda: ext.T_ref_cam("cam99"), lambda: ext.cameras["cam99"]):
        with pytest.raises(UnknownCameraError) as caught:
            lookup()
        assert isinstance(caught.value, KeyError) and isinstance(caught.value, RgbdCalibError)
        assert str(caught.value) == "camera 'cam99' is not in this calibration; its cameras: a, b"
    assert ext.cameras.get("cam99") is None and "b" in ext.cameras
