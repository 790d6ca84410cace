"""A detector's edge offset (docs/accuracy.md, "A detector's edge offset"): on real prints the
edge fit sees every marker larger by +0.05..+0.16 px per edge, by camera, and nothing in the
bundle models it. The detections of a small still race render are shifted outward by 0.1 px
(``tools/bench_edge_offset.py``) and calibrated again: the known gap is a strict xfail, the
acceptance a model of the offset must meet (and then the marker drops)."""

from __future__ import annotations

import sys

import pytest
from conftest import REPO

from rgbd_calib.model.board import thesis_board
from rgbd_calib.synth.render import synthesize_cached

sys.path.insert(0, str(REPO / "tools"))
from bench_edge_offset import measure, shifted_outward, write_offset_cache  # noqa: E402

OFFSET_PX = 0.1  # within what issue 16 measured between cameras of one print


def test_each_marker_edge_moves_outward_by_the_offset():
    """A square marker's corners move diagonally outward, each edge by exactly the offset,
    whatever the corner order's orientation."""
    import numpy as np

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
def test_an_edge_offset_leaves_its_mark_in_the_corner_sigma(offset_runs):
    """What the tool shows today: the extrinsics move by about a millimetre and the corners'
    a-posteriori sigma grows (measured at 20 sets: 0.084 -> 1.74 mm, 0.036 -> 0.106 px)."""
    clean, shifted = offset_runs
    assert clean["worst_mm"] < 0.3, clean
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
