"""A detector's edge offset (docs/accuracy.md, "A detector's edge offset"): on real prints the
edge fit sees every marker larger by +0.05..+0.16 px per edge, by camera, and nothing in the
bundle models it; the bundle's residuals read it (``bundle.edge_offset``) and the report names
it (finding ``edge_offset``). The detections of a small still race render are shifted outward
by 0.1 px (``tools/bench_edge_offset.py``) and calibrated again: the known gap is a strict
xfail, the acceptance a model of the offset must meet (and then the marker drops)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from conftest import REPO

from rgbd_calib.model.board import thesis_board
from rgbd_calib.synth.render import synthesize_cached

sys.path.insert(0, str(REPO / "tools"))
from bench_edge_offset import measure, shifted_outward, write_offset_cache  # noqa: E402

OFFSET_PX = 0.1  # within what issue 16 measured between cameras of one print


def _quads(rng, n):
    """``n`` perspective-ish marker quads of 10-20 px, corners in either order."""
    out = []
    for _ in range(n):
        c, s, a = rng.uniform(50, 500, 2), rng.uniform(10, 20), rng.uniform(0, np.pi)
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        q = (np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * s / 2) @ R.T + c
        out.append(q if rng.uniform() < 0.5 else q[::-1])
    return np.array(out)


def test_the_residuals_read_the_edge_offset_with_an_honest_sigma():
    """``edge_offsets`` recovers an offset put into the measured corners from the residuals
    (``predicted - measured``), within 3 of its standard errors over seeds, leaves an outlier
    marker out, and gives nothing for a camera with one marker."""
    from rgbd_calib.solve.edge_offset import edge_offsets, marker_outward_px

    z = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        true = _quads(rng, 300)
        measured = shifted_outward(true, 0.08) + rng.normal(0, 0.03, true.shape)
        measured[0] = shifted_outward(true[:1], 1.0)[0]  # a marker far off: not an offset
        got = edge_offsets(["a"] * 299 + ["b"], marker_outward_px(measured, true - measured))
        assert set(got) == {"a"} and got["a"].markers == 298
        z.append((got["a"].offset_px - 0.08) / got["a"].sigma_px)
    assert np.sqrt(np.mean(np.square(z))) < 1.6, z
    assert max(np.abs(z)) < 3.5, z


def test_the_report_names_a_camera_whose_markers_read_off_by_an_edge_offset():
    from rgbd_calib.outputs.report.findings import edge_offset

    report = {"bundle": {"edge_offset": {
        "big": {"offset_px": 0.10, "sigma_px": 0.001, "markers": 400},
        "small": {"offset_px": 0.003, "sigma_px": 0.0005, "markers": 400},  # 0.05 mm
        "noisy": {"offset_px": -0.05, "sigma_px": 0.02, "markers": 9},  # 2.5 sigma
        "inside": {"offset_px": -0.04, "sigma_px": 0.002, "markers": 200}}}}
    found = edge_offset(report, [])
    assert len(found) == 1 and found[0]["cameras"] == ["big", "inside"], found
    assert found[0]["severity"] == "warning" and "+0.100 px" in found[0]["message"]
    assert edge_offset({"bundle": {}}, []) == [] and edge_offset({}, []) == []


def test_each_marker_edge_moves_outward_by_the_offset():
    """A square marker's corners move diagonally outward, each edge by exactly the offset,
    whatever the corner order's orientation."""
    quad = np.array([[[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]]])
    for q in (quad, quad[:, ::-1]):
        out = shifted_outward(q, 0.5)
        lo, hi = out[0].min(axis=0), out[0].max(axis=0)
        np.testing.assert_allclose(lo, [9.5, 9.5])
        np.testing.assert_allclose(hi, [20.5, 20.5])


@pytest.fixture(scope="module")
def offset_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("edge_offset")
    render, _ = synthesize_cached(root / "race", "race", 12, 382, thesis_board())
    clean = measure(render, root / "cache")
    write_offset_cache(root / "cache", root / "offset", OFFSET_PX)
    return clean, measure(render, root / "offset")


@pytest.mark.slow
def test_an_edge_offset_is_read_and_named_but_moves_the_extrinsics(offset_runs):
    """What the tool does today: the residuals read the offset (0.094-0.099 px for 0.1 at 20
    sets, below 0.004 on the clean render), but the extrinsics move by about a millimetre and
    the corners' a-posteriori sigma grows (20 sets: 0.084 -> 1.74 mm, 0.036 -> 0.106 px)."""
    clean, shifted = offset_runs
    assert clean["worst_mm"] < 0.3, clean
    assert max(abs(v) for v in clean["edge_offsets"]) < 0.01, clean
    assert all(0.085 < v < 0.105 for v in shifted["edge_offsets"]), shifted
    assert shifted["worst_mm"] > 3 * clean["worst_mm"], (clean, shifted)
    assert shifted["corner_sigma_px"] > 2 * clean["corner_sigma_px"], (clean, shifted)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="no per-camera edge offset in the bundle: a 0.1 px offset "
                   "moves the race's extrinsics ~1.7 mm at sigmas 5-6x too small; see "
                   "docs/accuracy.md, 'A detector's edge offset'")
def test_an_edge_offset_is_estimated_and_does_not_move_the_extrinsics(offset_runs):
    clean, shifted = offset_runs
    assert shifted["worst_mm"] < 2 * clean["worst_mm"] + 0.1, (clean, shifted)
    assert shifted["chi2_over_6"] < 3.0, shifted
