"""report.html in a real headless browser: it renders offline, with no console error, every
figure decoded and the 3D view drawn.

Method: ``chromium --headless --dump-dom`` with console logging on stderr and every host name
resolving to nothing (so any network fetch would fail and be logged). The page itself
records script errors in ``<html data-js-errors>`` and, once every ``<img>`` has decoded and
the 3D canvas has drawn, sets ``<body data-report-ready="yes" data-images=N
data-broken-images=0>``; the test reads those attributes from the dumped DOM.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from rgbd_calib.core.config import CalibrationConfig
from rgbd_calib.model.board import thesis_board
from rgbd_calib.model.dataset import FolderDataset
from rgbd_calib.outputs.report import (
    dump_report,
    error_map,
    finalize_report,
    pair_entry,
    rebuild_report,
)
from rgbd_calib.outputs.writer import write_outputs
from rgbd_calib.pipelines.calibrate import calibrate
from rgbd_calib.synth.render import SynthParams, synthesize

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
BROWSER = next((shutil.which(b) for b in BROWSERS if shutil.which(b)), None)
pytestmark = pytest.mark.skipif(
    BROWSER is None, reason="no chromium on PATH (Debian: apt-get install -y chromium)"
)
EXPECTED_FIGURES = 9  # rig, cloud, histograms, edges, co-visibility, coverage x2, markers, maps


def _write_ply(path: Path, points: np.ndarray, cams: np.ndarray, names: list[str]) -> None:
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
    data["green"], data["camera"] = 180, cams
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


@pytest.fixture(scope="module")
def report_dirs(tmp_path_factory):
    """A calibration folder with the preview cloud, and a copy with a fused.ply and depth
    pairs (so that every kind of figure is on the page)."""
    base = tmp_path_factory.mktemp("browser")
    board = thesis_board()
    ds = synthesize(base / "dataset", "race", 6, 3, board, SynthParams(), workers=2)
    dataset = FolderDataset(ds.path)
    result = calibrate(dataset, board, CalibrationConfig(refine="none"))
    plain = base / "plain"
    write_outputs(result, dataset.rig, plain)

    full = base / "full"
    shutil.copytree(plain, full)
    report = json.loads((full / "report.json").read_text())
    names = list(report["cameras"])
    rng = np.random.default_rng(0)
    _write_ply(
        full / "fused.ply", rng.uniform(-2, 2, (3000, 3)), rng.integers(0, len(names), 3000), names
    )
    w, h = (report["cameras"][names[0]]["intrinsics"][k] for k in ("width", "height"))
    uv = np.column_stack([rng.integers(0, w, 2000), rng.integers(0, h, 2000)])
    em = error_map(uv, rng.normal(0, 0.002, 2000), w, h)
    report["pairs"] = [
        pair_entry(
            {
                "cam_a": names[0],
                "cam_b": names[1],
                "fitness": 0.7,
                "rmse_before_mm": 3.0,
                "rmse_after_mm": 1.2,
                "error_map": em,
            }
        )
    ]
    (full / "report.json").write_text(dump_report(finalize_report(report)))
    rebuild_report(full)
    return plain, full


def _open(page: Path, tmp_path: Path) -> tuple[str, str]:
    """(dumped DOM, browser stderr) of ``page`` after its scripts ran."""
    cmd = [
        BROWSER,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}",
        "--host-resolver-rules=MAP * ~NOTFOUND",
        "--enable-logging=stderr",
        "--v=0",
        "--window-size=1280,2000",
        "--virtual-time-budget=15000",
        "--dump-dom",
        page.resolve().as_uri(),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout, done.stderr


def _attr(dom: str, tag: str, name: str) -> str | None:
    m = re.search(rf"<{tag}\b[^>]*\b{name}=\"([^\"]*)\"", dom)
    return m.group(1) if m else None


@pytest.mark.parametrize("which", ["plain", "full"])
def test_report_renders_in_a_browser(report_dirs, tmp_path, which):
    folder = report_dirs[0] if which == "plain" else report_dirs[1]
    page = folder / "report.html"
    dom, log = _open(page, tmp_path)
    console = [line for line in log.splitlines() if ":CONSOLE" in line or "Uncaught" in line]
    assert not console, "console output:\n" + "\n".join(console)
    assert "Failed to load resource" not in log
    assert _attr(dom, "html", "data-js-errors") is None, _attr(dom, "html", "data-js-errors")
    n_img = len(re.findall(r"<img\b", page.read_text()))
    assert _attr(dom, "body", "data-report-ready") == "yes", dom[-1500:]
    assert _attr(dom, "body", "data-images") == str(n_img)
    assert _attr(dom, "body", "data-broken-images") == "0"
    assert _attr(dom, "canvas", "data-ready") == "yes"
    drawn = int(_attr(dom, "canvas", "data-points-drawn") or 0)
    if which == "full":
        assert n_img == EXPECTED_FIGURES
        assert drawn > 1000  # most of the 3000 fused.ply points are in view
    else:
        assert n_img == EXPECTED_FIGURES - 1  # no depth pairs: no error-map figure
        assert drawn > 1000  # the preview cloud from the dataset's depth frames
