"""A depth pair carries the disparity offset its clouds keep (depth/information.py
``disparity_covariance``): calibrate registers clouds divided by their depth-scale factor alone,
so a D435's disparity offset stays in them and moves every point of a cloud together."""

from __future__ import annotations

import numpy as np

from rgbd_calib.depth.clouds import DisparityMoment
from rgbd_calib.depth.information import (
    Matches,
    disparity_covariance,
    noise_model_information,
    whitened_rows,
)

FB = 20.0  # f B (px m) of a D435 at 848x480


def _scene(rng: np.random.Generator, n: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Points of three walls at 1-3 m in camera a's frame (= b's: T_b_a is the identity),
    with their normals: a scene that holds every direction of a pose."""
    normals = np.array([[0.0, 0.0, -1.0], [0.7, 0.0, -0.7], [0.0, 0.7, -0.7]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    k = rng.integers(0, 3, n)
    p = np.c_[rng.uniform(-0.8, 0.8, (n, 2)), rng.uniform(1.0, 3.0, n)]
    return p, normals[k]


def _matches(src: np.ndarray, tgt: np.ndarray, normals: np.ndarray) -> Matches:
    residual = np.einsum("ij,ij->i", normals, src - tgt)
    n = len(src)
    return Matches(src, tgt, normals, residual, np.full(n, 0.002), np.abs(residual),
                   np.arange(n), np.arange(n))


def _with_offset(p: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``p`` moved along its rays by the relative depth error ``z delta(x, y) / (f B)``."""
    z = p[:, 2]
    x, y = p[:, 0] / z, p[:, 1] / z
    d = delta @ np.stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    return p * (1.0 + z * d / FB)[:, None]


def test_a_disparity_offset_moves_the_pose_as_its_covariance_says():
    """Cloud a keeps an offset of 0.2 px (and a gradient): the least-squares pose from the
    matches moves by ``s``; with the offset as the moment's estimate (no covariance) the
    covariance the pair gains is ``s s^T``, to first order."""
    rng = np.random.default_rng(3)
    p, normals = _scene(rng)
    delta = np.array([0.2, 0.05, -0.03, 0.0, 0.0, 0.0])
    moment = DisparityMoment(FB, np.outer(delta, delta))
    rows = whitened_rows(_matches(p, p, normals), np.eye(4), 0.1,
                         disparity=(moment, None))
    C = disparity_covariance(rows)
    # the move the offset makes: Gauss-Newton step of the residuals it adds
    moved = whitened_rows(_matches(_with_offset(p, delta), p, normals), np.eye(4), 0.1)
    s = -np.linalg.lstsq(moved.J, moved.r, rcond=None)[0][:6]
    assert C is not None and C.shape == (6, 6)
    assert np.allclose(np.sqrt(np.diag(C)), np.abs(s), rtol=0.05, atol=1e-6), (np.diag(C), s)
    assert np.linalg.norm(1e3 * s[3:]) > 5.0  # millimetres of the pose: why it matters


def test_no_offset_adds_nothing_and_the_gates_keep_their_information():
    rng = np.random.default_rng(4)
    p, normals = _scene(rng)
    plain = whitened_rows(_matches(p, p, normals), np.eye(4), 0.1)
    assert disparity_covariance(plain) is None
    cov = np.diag([0.02, 0.01, 0.01, 0.005, 0.005, 0.005]) ** 2
    both = whitened_rows(_matches(p, p, normals), np.eye(4), 0.1,
                         disparity=(DisparityMoment(FB, cov), DisparityMoment(FB, 4 * cov)))
    assert both.n_disparity == 12 and np.array_equal(both.J, plain.J)
    # the gates' information is the pair's own noise, offsets or not
    assert np.array_equal(noise_model_information(both), noise_model_information(plain))
    C = disparity_covariance(both)
    one = disparity_covariance(whitened_rows(_matches(p, p, normals), np.eye(4), 0.1,
                                             disparity=(DisparityMoment(FB, cov), None)))
    assert np.all(np.diag(C) > np.diag(one))  # b's offset adds its own
