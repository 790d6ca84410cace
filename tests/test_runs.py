"""Consecutive frames of a continuous recording (rgbd_calib/solve/runs.py): the runs found from
the sets' times, and the variance factor of corner errors repeated between a run's views."""

from __future__ import annotations

import numpy as np
import pytest

from rgbd_calib.solve.runs import MIN_PAIRS, recording_runs, run_inflation


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
