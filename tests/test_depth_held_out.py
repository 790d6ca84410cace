"""A depth model is kept only where it predicts board views it was not fitted to better than
the raw depth (issue 56 item 1: held-out prediction decides, for the depth model's terms too)."""

from __future__ import annotations

import numpy as np
import pytest

from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.depth_model import PARAMETERS, DepthModel
from rgbd_calib.depth.depth_model_fit import (
    BoardSamples,
    _solve,
    fit_depth_model,
    held_out_cost,
)

FB = 30.0
HUBER = 1.345


def _samples(truth: DepthModel, views: int, seed: int, per_view: int = 300) -> BoardSamples:
    """Board views at 0.8-2 m, tilted at random, the depth ``truth`` measured with D435-like
    noise (1 mm at 1 m, growing with the square of the distance)."""
    rng = np.random.default_rng(seed)
    parts = []
    for v in range(views):
        n = np.array([rng.normal(0, 0.3), rng.normal(0, 0.3), 1.0])
        n /= np.linalg.norm(n)
        d = rng.uniform(0.8, 2.0)
        rays = np.column_stack([rng.uniform(-0.5, 0.5, per_view), rng.uniform(-0.3, 0.3, per_view),
                                np.ones(per_view)])
        z = d / (rays @ n)
        sigma = 1e-3 * z * z
        zm = truth.measured_depth(rays[:, 0], rays[:, 1], z) + rng.normal(0, 1, per_view) * sigma
        parts.append((rays, zm, np.tile(n, (per_view, 1)), np.full(per_view, d), sigma,
                      np.full(per_view, v)))
    c = [np.concatenate([p[i] for p in parts]) for i in range(6)]
    return BoardSamples(c[0], c[1], c[2], c[3], c[4], c[5].astype(int),
                        tuple(f"f{v}" for v in range(views)), np.zeros((len(c[0]), 2)))


@pytest.mark.parametrize("views", [4, 6, 15])
def test_every_term_on_a_clean_camera_predicts_held_out_views_no_better(views):
    s = _samples(DepthModel(FB), views, seed=views)
    held = held_out_cost(_solve(DepthModel(FB), s, PARAMETERS, HUBER), DepthModel(FB), s, HUBER)
    assert held is not None and held.model >= held.identity


@pytest.mark.parametrize("views", [4, 15])
def test_a_real_depth_error_is_predicted_far_better_than_the_raw_depth(views):
    truth = DepthModel(FB, {"scale": 1.006, "d0": 0.3})
    s = _samples(truth, views, seed=10 + views)
    held = held_out_cost(_solve(DepthModel(FB), s, PARAMETERS, HUBER), DepthModel(FB), s, HUBER)
    assert held is not None and held.model < 0.2 * held.identity


def test_the_fit_reports_held_out_prediction_and_keeps_a_needed_model():
    intr = CameraIntrinsics(fx=FB / 0.05, fy=FB / 0.05, cx=424, cy=240, width=848, height=480)
    fit = fit_depth_model("c", _samples(DepthModel(FB, {"scale": 1.006, "d0": 0.3}), 16, 3),
                          intr)
    assert fit.model.terms and fit.held_out is not None and not fit.held_out.rejected
    assert fit.to_dict()["held_out"]["model"] < fit.to_dict()["held_out"]["identity"]


def test_a_model_that_predicts_no_better_leaves_the_raw_depth(monkeypatch):
    """Where held-out views are predicted no better (forced here), the camera keeps the
    identity, and the report says why."""
    import rgbd_calib.depth.depth_model_fit as dmf

    def no_better(solve, base, s, k):
        return dmf.HeldOut(0.6, 0.5, len(s.frames))

    monkeypatch.setattr(dmf, "held_out_cost", no_better)
    intr = CameraIntrinsics(fx=FB / 0.05, fy=FB / 0.05, cx=424, cy=240, width=848, height=480)
    fit = fit_depth_model("c", _samples(DepthModel(FB, {"scale": 1.006, "d0": 0.3}), 16, 3),
                          intr)
    assert fit.model.is_identity and fit.model.terms == () and fit.held_out.rejected
    assert fit.to_dict()["held_out"]["rejected"] is True


def test_the_overlaps_update_is_judged_on_pairs_left_out():
    """Each pair's median predicted by the update made from the others: pairs that agree on
    one camera reading long are predicted far better than by the board's models; pairs that
    contradict each other (noise about a zero truth) are not, and the update is refused."""
    from rgbd_calib.depth.overlap_models import PairMedian, held_out_pairs

    rng = np.random.default_rng(0)
    cams = ["a", "b", "c", "d"]
    index = {c: k for k, c in enumerate(cams)}
    prior = np.eye(4) / 1e-3**2  # each camera's depth offset known to 1 mm from the board
    pairs = [(x, y) for i, x in enumerate(cams) for y in cams[i + 1:]]
    jac = {}
    for x, y in pairs:
        J = np.zeros(4)
        J[index[x]], J[index[y]] = 1.0, -1.0  # the pair's median moves with a's and b's depth
        jac[x, y] = J
    offset = {"a": 3.0, "b": 0.0, "c": 0.0, "d": 0.0}  # mm: camera a reads 3 mm long
    agree = [PairMedian(x, y, offset[x] - offset[y] + rng.normal(0, 0.2), 0.2, 1000)
             for x, y in pairs]
    held = held_out_pairs(prior, agree, jac)
    assert held is not None and held.update < 0.2 * held.board
    rng = np.random.default_rng(0)
    noise = [PairMedian(x, y, rng.normal(0, 0.2), 0.2, 1000) for x, y in pairs]
    held = held_out_pairs(prior, noise, jac)
    assert held is not None and held.update > held.board  # calibrate then keeps the board's
