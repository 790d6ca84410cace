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


# ----------------------------------------------------------------------------- exit codes
def test_exit_codes_are_distinct_and_mapped():
    codes = [cli_app.EXIT_OK, cli_app.EXIT_MOVED, cli_app.EXIT_INPUT, cli_app.EXIT_POOR,
             cli_app.EXIT_UNCHECKED, cli_app.EXIT_CHECK, cli_app.EXIT_INTERRUPTED]
    assert len(set(codes)) == len(codes) and cli_app.EXIT_OK == 0
    assert cli_app.verdict_exit("good") == cli_app.verdict_exit("check") == cli_app.EXIT_OK
    assert cli_app.verdict_exit("poor") == cli_app.EXIT_POOR
    assert cli_app.verdict_exit("poor", accept_poor=True) == cli_app.EXIT_OK
    # --strict: a script can refuse CHECK too; GOOD stays 0, POOR stays 3
    assert cli_app.verdict_exit("check", strict=True) == cli_app.EXIT_CHECK
    assert cli_app.verdict_exit("good", strict=True) == cli_app.EXIT_OK
    assert cli_app.verdict_exit("poor", strict=True) == cli_app.EXIT_POOR
    assert cli_app.verdict_exit(None) == cli_app.EXIT_OK  # not judged (posegraph)
    assert cli_app.check_exit([], []) == cli_app.EXIT_OK
    assert cli_app.check_exit([], ["c1"]) == cli_app.EXIT_UNCHECKED
    assert cli_app.check_exit(["c2"], ["c1"]) == cli_app.EXIT_MOVED  # a move comes first


def test_readme_lists_every_exit_code():
    """The README's exit-code table gives each code the CLI uses, with its meaning."""
    readme = (REPO / "README.md").read_text()
    section = readme.split("## Exit codes", 1)[1].split("\n## ", 1)[0]
    rows = {int(m.group(1)): m.group(0) for m in re.finditer(r"^\| (\d+) \|.*$", section, re.M)}
    assert set(rows) == {cli_app.EXIT_OK, cli_app.EXIT_MOVED, cli_app.EXIT_INPUT,
                         cli_app.EXIT_POOR, cli_app.EXIT_UNCHECKED, cli_app.EXIT_CHECK,
                         cli_app.EXIT_INTERRUPTED}
    assert "--accept-poor" in rows[cli_app.EXIT_POOR] and "check" in rows[cli_app.EXIT_UNCHECKED]
    assert "--strict" in rows[cli_app.EXIT_CHECK]


def test_calibrate_poor_exits_3_and_every_file_says_so(poor_calibration, poor_rig):
    out, code, text = poor_calibration
    assert code == cli_app.EXIT_POOR, text
    assert "verdict: POOR" in text and "exit 3" in text and "--accept-poor" in text
    ext = load_extrinsics(out / "extrinsics.yaml", check_redundant=True)
    assert ext.verdict.grade == "poor" and UNCONNECTED not in ext.cameras
    assert ext.verdict.reason.startswith(f"not_calibrated [{UNCONNECTED}]")
    raw = yaml.safe_load((out / "extrinsics.yaml").read_text())
    assert list(raw)[0] == "verdict" and raw["verdict"]["grade"] == "poor"
    report = json.loads((out / "report.json").read_text())
    assert report["summary"]["verdict"] == "poor"
    line = f"rgbd-calib verdict: POOR: {ext.verdict.reason}"
    for name in ("camchain.yaml", "static_transforms.launch.py", "posegraph.g2o"):
        assert f"# {line}" in (out / "exports" / name).read_text().splitlines()[:2], name
    assert line.replace("--", "- -") in (out / "exports" / "cameras.urdf").read_text()
    unity = json.loads((out / "exports" / "unity_cameras.json").read_text())
    assert unity["verdict"]["grade"] == "poor"
    # --accept-poor: the old exit 0, the same verdict in the files
    code, text = cli("calibrate", poor_rig, "--out", out, "--refine", "none", "--workers", "2",
                     "--accept-poor")
    assert code == cli_app.EXIT_OK, text
    assert "verdict: POOR" in text and "exit 3" not in text
    assert load_extrinsics(out / "extrinsics.yaml").verdict.grade == "poor"


def test_refine_from_a_poor_calibration_says_so_and_exits_3(poor_calibration, tiny_dataset,
                                                            tmp_path):
    """The --init calibration's POOR verdict is named before the run; the refined result,
    still without cam10, is POOR too: exit 3, the verdict in its extrinsics.yaml."""
    calib, _, _ = poor_calibration
    out = tmp_path / "refined"
    code, text = cli("refine", tiny_dataset, "--init", calib / "extrinsics.yaml", "--out", out)
    flat = " ".join(text.split())
    assert code == cli_app.EXIT_POOR, text
    assert "its verdict is POOR" in flat and "verdict: POOR: not_calibrated" in flat
    assert load_extrinsics(out / "extrinsics.yaml").verdict.grade == "poor"
    assert json.loads((out / "report.json").read_text())["summary"]["verdict"] == "poor"


@pytest.mark.parametrize("statuses, expected", [
    ({"cam7": "in_place", "cam8": "in_place", "cam9": "in_place"}, cli_app.EXIT_OK),
    ({"cam7": "in_place", "cam8": "in_place", "cam9": "unknown"}, cli_app.EXIT_UNCHECKED),
    ({"cam7": "in_place", "cam8": "moved", "cam9": "unknown"}, cli_app.EXIT_MOVED),
], ids=["all-in-place", "unknown", "moved-and-unknown"])
def test_check_exit_code_never_says_in_place_for_an_unchecked_camera(
        poor_calibration, tiny_dataset, tmp_path, monkeypatch, statuses, expected):
    from rgbd_calib.cli import commands_depth
    from rgbd_calib.pipelines.check import CheckResult, CheckRun
    from rgbd_calib.solve.moved import CameraCheck, Tolerance

    calib, _, _ = poor_calibration
    cams = {c: (CameraCheck(c, s, reason="no overlapping depth") if s == "unknown" else
                CameraCheck(c, s, 0.1 if s == "in_place" else 30.0, 0.01, 0.5, 0.02, 1.0, 2))
            for c, s in statuses.items()}
    run = CheckRun(CheckResult(cams, [], Tolerance()), {}, [], {c: "given" for c in cams})
    monkeypatch.setattr(commands_depth, "_run_check", lambda *args, **kwargs: run)
    code, text = cli("check", tiny_dataset, "--calib", calib, "--out", tmp_path / "c")
    assert code == expected, text
    report = json.loads((tmp_path / "c" / "check.json").read_text())
    assert report["unknown"] == [c for c, s in statuses.items() if s == "unknown"]
    if expected == cli_app.EXIT_UNCHECKED:
        assert "not checked: cam9" in text and f"exit {cli_app.EXIT_UNCHECKED}" in text
    if "unknown" in statuses.values():  # how to make them checkable, with or without a move
        assert "not checked: cam9" in text and "board held still" in text
    if expected == cli_app.EXIT_OK:
        assert "in place: every camera within" in text


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


# ----------------------------------------------------------------------------- videos folder
def _videos(folder: Path, n: int = 2) -> list[Path]:
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in range(n):
        path = folder / f"cam_{k}.mp4"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30, (64, 48))
        for i in range(3):
            writer.write(np.full((48, 64, 3), 40 * i, np.uint8))
        writer.release()
        paths.append(path)
    return paths


@pytest.mark.parametrize("command", ["calibrate", "check", "refine"])
def test_a_folder_of_videos_or_recordings_says_to_convert_it(tmp_path, command):
    """calibrate reads a dataset folder or recordings; given a folder of videos (or of bags),
    it says so in one line naming the folder, with the convert command to run; nothing is
    written. check and refine read their dataset the same way."""
    videos = _videos(tmp_path / "vids")
    bags = tmp_path / "bags"
    bags.mkdir()
    for name in ("left.bag", "right.bag"):
        (bags / name).write_bytes(b"")
    calib = tmp_path / "calib" / "extrinsics.yaml"
    calib.parent.mkdir()
    write_extrinsics(_extrinsics(), calib)
    extra = {"calibrate": [], "check": ["--calib", calib], "refine": ["--init", calib]}[command]
    cases = [
        ([tmp_path / "vids"], f"{tmp_path / 'vids'}: holds videos (cam_0.mp4, cam_1.mp4), not "
         f"a dataset folder; convert them first with `rgbd-calib convert "
         f"{tmp_path / 'vids'}/*.mp4 --out DATASET`, then give DATASET"),
        (videos, f"{videos[0]}: a video; calibrate, check and refine read a dataset folder or "
         f"RealSense/ROS recordings: convert the videos first with `rgbd-calib convert "
         f"{videos[0]} {videos[1]} --out DATASET`"),
        ([bags], f"{bags}: holds recordings (left.bag, right.bag), not a dataset folder; "
         f"convert them first with `rgbd-calib convert {bags}/*.bag --out DATASET`"),
    ]
    for sources, says in cases:
        out = tmp_path / f"out_{command}"
        code, text = cli(command, *sources, *extra, "--out", out)
        assert code == cli_app.EXIT_INPUT, text
        assert len(text.strip().splitlines()) == 1 and says in " ".join(text.split()), text
        assert not out.exists()


def test_the_library_refuses_a_videos_folder_the_same_way(tmp_path):
    _videos(tmp_path / "vids")
    with pytest.raises(DatasetError, match=r"holds videos .*`rgbd-calib convert .*/vids/\*.mp4"):
        rgbd_calib.calibrate(str(tmp_path / "vids"), CONFIGS / "board_thesis.yaml")


# ----------------------------------------------------------------------------- library API
def test_library_convert_takes_str_and_pathlike(tmp_path):
    videos = _videos(tmp_path / "vids")
    out = tmp_path / "dataset"
    report = rgbd_calib.convert([str(videos[0]), PathLike(videos[1])], str(out))
    assert report.cameras == ["cam_0", "cam_1"] and report.frames_written == 3
    rig = rgbd_calib.load_rig(PathLike(out / "rig.yaml"))
    assert set(rig.cameras) == {"cam_0", "cam_1"}
    assert rgbd_calib.FolderDataset(PathLike(out)).frames == ["000000", "000001", "000002"]
    with pytest.raises(ConfigError, match="either video files or recordings"):
        rgbd_calib.convert([videos[0], tmp_path / "x.bag"], tmp_path / "mixed")


def test_library_calibrate_check_refine_take_paths(poor_calibration, tiny_dataset, tmp_path):
    """calibrate(cache_dir="...") used to be a TypeError; check and refine are library calls
    too, on a calibration folder's path, as the commands take it."""
    from rgbd_calib import CalibrationConfig

    cache = tmp_path / "cache"
    result = rgbd_calib.calibrate(str(tiny_dataset), str(CONFIGS / "board_thesis.yaml"),
                                  CalibrationConfig(refine="none", workers=2),
                                  cache_dir=str(cache))
    assert (cache / "detections.json").is_file()
    assert set(result.extrinsics.cameras) == {"cam7", "cam8", "cam9", "cam10"}
    paths = rgbd_calib.write_outputs(result, rgbd_calib.FolderDataset(tiny_dataset).rig,
                                     PathLike(tmp_path / "out"))
    assert tmp_path / "out" / "extrinsics.yaml" in paths
    ext = rgbd_calib.load_extrinsics(PathLike(tmp_path / "out" / "extrinsics.yaml"))
    assert ext.verdict.grade in ("good", "check")
    assert rgbd_calib.load_config(PathLike(tmp_path / "out" / "config_resolved.yaml"))
    assert rgbd_calib.load_board(PathLike(CONFIGS / "board_thesis.yaml")).name
    assert rgbd_calib.load_ground_truth(PathLike(tiny_dataset)).reference == "cam7"
    exported = rgbd_calib.write_exports(ext, PathLike(tmp_path / "again"))
    assert all(p.is_file() for p in exported.values())

    calib, _, _ = poor_calibration
    run = rgbd_calib.check(PathLike(tiny_dataset), str(calib))
    assert set(run.result.cameras) == {"cam7", "cam8", "cam9"}  # cam10 was not calibrated
    assert set(run.moved) | set(run.unknown) <= set(run.result.cameras)
    assert {"moved", "unknown", "cameras"} <= set(run.result.to_dict())

    refined = rgbd_calib.refine(str(tiny_dataset), PathLike(calib))
    assert refined.init_path == calib / "extrinsics.yaml"
    assert refined.outcome["verdict"] in ("refined", "unchanged", "check")
    written = rgbd_calib.write_refine(refined, str(tmp_path / "refined"))
    assert tmp_path / "refined" / "extrinsics.yaml" in written
    back = rgbd_calib.load_extrinsics(tmp_path / "refined" / "extrinsics.yaml")
    assert back.verdict.grade == "poor"  # cam10 is still not calibrated


# ----------------------------------------------------------------------------- tools/run.sh
def _venv_ready() -> str | None:
    """Why tools/run.sh would set an environment up (slow) instead of running, or None."""
    import hashlib

    stamp = Path(sys.prefix) / ".rgbd-calib-stamp"
    want = hashlib.sha256((REPO / "pyproject.toml").read_bytes()
                          + (REPO / "requirements.lock").read_bytes()).hexdigest()
    if not stamp.is_file() or stamp.read_text().strip() != want:
        return f"{sys.prefix} is not tools/run.sh's environment of this checkout (stamp)"
    if not (Path(sys.prefix) / "bin" / "rgbd-calib").is_file():
        return "no rgbd-calib entry point in this environment"
    # as tools/run.sh: ldconfig from the PATH, else /sbin's (a PATH without sbin is common)
    found = shutil.which("ldconfig") or ("/sbin/ldconfig" if Path("/sbin/ldconfig").is_file()
                                         else None)
    if found is None:
        return "no ldconfig to look for libusb-1.0-0 with"
    ldconfig = subprocess.run([found, "-p"], capture_output=True, text=True, check=False)
    if "libusb-1.0.so.0" not in ldconfig.stdout:
        return "libusb-1.0-0 missing (tools/run.sh would install it)"
    return None


def test_run_sh_runs_a_command_in_the_callers_folder(tmp_path):
    """Relative paths are the caller's, and so is where the outputs land (not the
    repository)."""
    why = _venv_ready()
    if why:
        pytest.skip(why)
    shutil.copy(CONFIGS / "board_thesis.yaml", tmp_path / "my_board.yaml")
    env = {**os.environ, "RGBD_CALIB_VENV": sys.prefix,
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run(["bash", str(REPO / "tools" / "run.sh"), "board", "my_board.yaml",
                          "--out", "printed", "--dpi", "20"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "printed" / "board.pdf").is_file()
    assert not (REPO / "printed").exists()


def test_run_sh_finds_an_installed_libusb_every_time():
    """tools/run.sh's libusb check under ``set -euo pipefail``, 300 times in a row: never a
    false 'missing' (``ldconfig -p | grep -q`` said so in ~1.5 % of calls: grep stopped at the
    first match, ldconfig died of SIGPIPE and pipefail failed the pipe)."""
    found = shutil.which("ldconfig") or ("/sbin/ldconfig" if Path("/sbin/ldconfig").is_file()
                                         else None)
    if found is None or "libusb-1.0.so.0" not in subprocess.run(
            [found, "-p"], capture_output=True, text=True, check=False).stdout:
        pytest.skip("libusb-1.0-0 is not installed here")
    text = (REPO / "tools" / "run.sh").read_text()
    start = text.index("need_libusb() {")
    body = text[start:text.index("\n}\n", start) + 3]
    script = (f"set -euo pipefail\nLDCONFIG={found}\n{body}\nn=0\n"
              "for i in $(seq 1 300); do if need_libusb; then n=$((n+1)); fi; done\necho $n\n")
    run = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=120,
                         check=False)
    assert run.returncode == 0 and run.stdout.strip() == "0", (run.stdout, run.stderr)


def test_out_in_the_dataset_or_the_calibration_read_is_refused(tiny_dataset, poor_calibration,
                                                                tmp_path):
    """``--out`` the dataset or inside it, or the calibration refine reads: one line, exit 2,
    nothing written there (the results would mix with the recording or overwrite the
    calibration being refined)."""
    data = tmp_path / "dataset"
    shutil.copytree(tiny_dataset, data)
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    for out in (data, data / "results"):
        code, text = cli("calibrate", data, "--out", out, "--refine", "none")
        assert code == cli_app.EXIT_INPUT, text
        line = [ln for ln in text.splitlines() if ln.startswith("error:")]
        assert len(line) == 1 and "dataset" in line[0] and "outside it" in line[0], text
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before
    calib, _, _ = poor_calibration
    stamp = (calib / "extrinsics.yaml").stat().st_mtime_ns
    code, text = cli("refine", data, "--init", calib / "extrinsics.yaml", "--out", calib)
    assert code == cli_app.EXIT_INPUT and "calibration" in text, text
    code, text = cli("check", data, "--calib", calib, "--out", data / "check")
    assert code == cli_app.EXIT_INPUT and "dataset" in text, text
    assert (calib / "extrinsics.yaml").stat().st_mtime_ns == stamp


def test_check_and_refine_name_cameras_that_match_none_of_the_calibration(
        tiny_dataset, poor_calibration, tmp_path):
    """A recording whose camera names differ from the calibration's: one line naming both
    lists, exit 2 (it ran on and called every camera 'unknown' for want of a depth cloud,
    then 'in place' with none checked)."""
    data = tmp_path / "renamed"
    shutil.copytree(tiny_dataset, data)
    rig = yaml.safe_load((data / "rig.yaml").read_text())
    names = list(rig["cameras"])
    rig["cameras"] = {f"x_{n}": v for n, v in rig["cameras"].items()}
    if "reference" in rig:
        rig["reference"] = f"x_{rig['reference']}"
    (data / "rig.yaml").write_text(yaml.safe_dump(rig))
    for n in names:
        (data / n).rename(data / f"x_{n}")
    calib, _, _ = poor_calibration
    for command in (["check", data, "--calib", calib],
                    ["refine", data, "--init", calib / "extrinsics.yaml"]):
        code, text = cli(*command, "--out", tmp_path / command[0])
        assert code == cli_app.EXIT_INPUT, text
        errors = [ln for ln in text.splitlines() if ln.startswith("error:")]
        assert len(errors) == 1 and "match none of the calibration's" in errors[0], text
        assert f"x_{names[0]}" in text and names[0] in text
        assert not (tmp_path / command[0] / "check.json").exists()


def test_a_board_file_in_millimetres_is_named_before_anything_runs(tiny_dataset, tmp_path):
    """A board file written in millimetres (marker 40 instead of 0.04): one line, exit 2,
    nothing written (it ran 1-2 minutes, then put cameras 800 m apart or raised a
    TypeError)."""
    text = (CONFIGS / "board_thesis.yaml").read_text()
    for old, new in (("marker_length: 0.04", "marker_length: 40"),
                     ("separation: 0.02", "separation: 20"),
                     ("thickness: 0.0066", "thickness: 6.6")):
        assert old in text
        text = text.replace(old, new)
    text = "\n".join(ln for ln in text.splitlines() if not ln.startswith("panel:"))
    (tmp_path / "board_mm.yaml").write_text(text)
    out = tmp_path / "out"
    code, said = cli("calibrate", tiny_dataset, "--board", tmp_path / "board_mm.yaml", "--out",
                     out)
    assert code == cli_app.EXIT_INPUT, said
    errors = [ln for ln in said.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "cannot be metres" in errors[0] and "1000" in errors[0], said
    assert not out.exists()


def test_a_charuco_recording_without_its_board_file_is_named_not_blamed_on_intrinsics(
        charuco_line, tmp_path):
    """A ChArUco recording whose rig.yaml gives only the image sizes, calibrated without
    --board (so with the thesis marker board): one line saying the images show a ChArUco
    board and which board file to give, exit 2 (it blamed the cameras' missing intrinsics:
    'no fx/fy/cx/cy ... only 0 board view(s)')."""
    data = tmp_path / "charuco"
    shutil.copytree(charuco_line, data)
    (data / "board.yaml").unlink(missing_ok=True)
    rig = yaml.safe_load((data / "rig.yaml").read_text())
    for cam in rig["cameras"].values():
        for key in ("fx", "fy", "cx", "cy", "distortion"):
            cam.pop(key, None)
    (data / "rig.yaml").write_text(yaml.safe_dump(rig))
    out = tmp_path / "out"
    code, text = cli("calibrate", data, "--out", out, "--refine", "none")
    assert code == cli_app.EXIT_INPUT, text
    errors = [ln for ln in text.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "ChArUco" in errors[0] and "--board" in errors[0], text
    assert "fx/fy" not in text
    assert not out.exists()  # nothing written, not even the detection cache
    # a folder that was there keeps what it held, and gets no cache
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    code, text = cli("calibrate", data, "--out", out, "--refine", "none")
    assert code == cli_app.EXIT_INPUT, text
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_an_extrinsics_file_of_yours_is_not_overwritten_and_stale_exports_go(
        tiny_dataset, tmp_path):
    """--out holding an extrinsics.yaml rgbd-calib did not write: refused with one line
    (exit 2, the file untouched) unless --force; --out holding another rig's result: its
    exports that this run does not write (another rig's cameras) are gone afterwards."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "extrinsics.yaml").write_text("cameras: {mine: 1}\n")
    code, text = cli("calibrate", tiny_dataset, "--out", out, "--refine", "none")
    assert code == cli_app.EXIT_INPUT and "--force" in text and "not written by" in text, text
    assert (out / "extrinsics.yaml").read_text() == "cameras: {mine: 1}\n"
    stale = out / "exports" / "open3d" / "cam_of_another_rig.json"
    stale.parent.mkdir(parents=True)
    stale.write_text("{}")
    code, text = cli("calibrate", tiny_dataset, "--out", out, "--refine", "none", "--force")
    assert code in (cli_app.EXIT_OK, cli_app.EXIT_POOR), text
    assert (out / "extrinsics.yaml").read_text().startswith("# rgbd-calib")
    assert not stale.exists() and any((out / "exports").iterdir())


def test_the_readme_is_short_plain_and_its_links_resolve():
    """The README is the user's document (issue 58): at most 2,500 words, no line over 300
    characters outside code blocks, no commit hashes, and every relative link (and its
    #anchor) points at a file and heading that exist."""
    text = (REPO / "README.md").read_text()
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    assert len(text.split()) <= 2500
    assert max(len(ln) for ln in prose.splitlines()) <= 300
    assert not re.search(r"\b(at|commit) [0-9a-f]{7,40}\b", prose)
    _links_resolve(REPO / "README.md")


def _links_resolve(doc: Path) -> None:
    """Every relative link of ``doc`` (and its #anchor, or an anchor of ``doc`` itself)
    points at a file and heading that exist."""
    text = doc.read_text()
    for target in re.findall(r"\]\(([^)#:]*?\.(?:md|png))?(#[^)]+)?\)", text):
        if not target[0] and not target[1]:
            continue
        path, anchor = (doc.parent / target[0]) if target[0] else doc, target[1]
        assert path.is_file(), (doc.name, target)
        if anchor:
            heads = [re.sub(r"[^\w\- ]", "", h.strip("# ").lower()).replace(" ", "-")
                     for h in path.read_text().splitlines() if h.startswith("#")]
            assert anchor[1:] in heads, (doc.name, target)


def test_the_user_guide_is_plain_and_its_links_resolve():
    """docs/guide.md is the user's guide (issue 58 item 2): short, no line over 300 characters
    outside code blocks, no commit hashes, its links resolve; the reference and the lab notes
    hold the detail."""
    guide = REPO / "docs" / "guide.md"
    text = guide.read_text()
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    assert len(text.split()) <= 2500
    assert max(len(ln) for ln in prose.splitlines()) <= 300
    assert not re.search(r"\b(at|commit) [0-9a-f]{7,40}\b", prose)
    _links_resolve(guide)
