"""Consecutive frames of a continuous recording (rgbd_calib/solve/runs.py): the runs found from
the sets' times, and the variance factor of corner errors repeated between a run's views."""

from __future__ import annotations

import numpy as np
import pytest

from rgbd_calib.solve.runs import MIN_PAIRS, recording_runs, run_inflation, select_sets


def test_runs_are_the_stretches_a_frame_period_apart():
    set_ms = {"a": 0.0, "b": 33.3, "c": 66.7, "d": 1000.0, "e": 2000.0, "f": 2033.3}
    assert recording_runs(set_ms, set_ms, 100.0) == (("a", "b", "c"), ("e", "f"))
    assert recording_runs(set_ms, ["a", "c", "e", "f"], 40.0) == (("e", "f"),)
    assert recording_runs(set_ms, set_ms, 0.0) == ()
    assert recording_runs({}, ["a", "b"], 100.0) == ()


def _residuals(rng, rho: float, runs, cameras=("c0", "c1"), markers=12):
    """Corner residuals whose share ``rho`` of the variance repeats within a run."""
    out = {}
    for run in runs:
        for c in cameras:
            shared = rng.normal(0, np.sqrt(rho), (markers, 4, 2))
            for v in run:
                for m in range(markers):
                    out[(c, v, m)] = shared[m] + rng.normal(0, np.sqrt(1 - rho), (4, 2))
    return out


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9])
def test_the_factor_is_the_design_effect_of_the_measured_correlation(rho):
    rng = np.random.default_rng(7)
    runs = tuple(tuple(f"{r}_{k}" for k in range(3)) for r in range(40))
    corr = run_inflation(runs, _residuals(rng, rho, runs))
    for c in ("c0", "c1"):
        assert corr[c].rho == pytest.approx(rho, abs=0.05)
        assert corr[c].factor == pytest.approx(1 + 2 * corr[c].rho)  # n = 3 in every run
        assert corr[c].pairs == 40 * 3 * 12


def test_views_outside_runs_dilute_the_factor_and_few_pairs_give_none():
    rng = np.random.default_rng(8)
    runs = tuple(tuple(f"{r}_{k}" for k in range(2)) for r in range(10))
    res = _residuals(rng, 0.9, runs)
    alone = _residuals(rng, 0.0, [(f"single{i}",) for i in range(20)])
    corr = run_inflation(runs, res | alone)["c0"]
    n_eff = 20 / (1 + corr.rho) + 20  # ten runs of two, twenty single views
    assert corr.factor == pytest.approx(40 / n_eff)
    few = run_inflation(runs[:1], _residuals(rng, 0.9, runs[:1], markers=MIN_PAIRS - 1))
    assert few["c0"].factor == 1.0 and few["c0"].rho > 0.5


def _recording(n_sets: int, cameras: int = 8, seed: int = 0):
    """A continuous recording at 30 fps: the board passes the cameras in turn, one to three
    of them seeing it at a time, some sets seeing nothing."""
    rng = np.random.default_rng(seed)
    set_ms = {f"{i:05d}": i * 1000 / 30 for i in range(n_sets)}
    seen = {}
    for i, v in enumerate(set_ms):
        first = (i * cameras // n_sets)
        seen[v] = {f"cam{(first + k) % cameras}": int(rng.integers(5, 40))
                   for k in range(int(rng.integers(0, 4)))}
    return set_ms, seen


def test_a_long_recording_keeps_runs_spread_over_it_and_every_camera():
    set_ms, seen = _recording(1800)
    seen["00010"] = {"rare": 12}  # a camera that saw the board once
    sel = select_sets(set_ms, seen, 150, 3, 100.0)
    total = sum(1 for v in seen.values() if v)
    assert sel.total == total and sel.run_length == 3
    assert 150 <= len(sel.kept) <= 200  # the cameras' minimum may add a few runs
    assert list(sel.kept) == sorted(sel.kept, key=set_ms.__getitem__)
    assert all(seen[v] for v in sel.kept)
    # runs of three consecutive sets (a frame period apart, within time_link_ms)
    runs = recording_runs(set_ms, sel.kept, 100.0)
    assert sum(len(r) for r in runs) == len(sel.kept)
    assert min(len(r) for r in runs) >= 3
    # spread over the recording: no tenth of it without kept sets
    times = np.array([set_ms[v] for v in sel.kept])
    assert np.histogram(times, bins=10, range=(0, 60000))[0].min() > 0
    # every camera keeps at least max_sets / 5 views, the rare one its only view
    for c in {c for v in seen.values() for c in v}:
        mine = sum(c in seen[v] for v in seen)
        assert sum(c in seen[v] for v in sel.kept) >= min(mine, 30), c
    # the sets kept favour those that link cameras
    kept_cams = np.mean([len(seen[v]) for v in sel.kept])
    all_cams = np.mean([len(v) for v in seen.values() if v])
    assert kept_cams > all_cams


def test_short_or_separate_recordings_are_kept_whole():
    set_ms, seen = _recording(120)
    assert select_sets(set_ms, seen, 150, 3, 100.0) is None  # fewer sets than max_sets
    assert select_sets(set_ms, seen, 0, 3, 100.0) is None  # 0: keep every set
    apart = {v: 1000.0 * i for i, v in enumerate(set_ms)}  # separate poses, 1 s apart
    assert select_sets(apart, seen, 30, 3, 100.0) is None
    assert select_sets({}, seen, 30, 3, 100.0) is None  # no timestamps: no runs known
