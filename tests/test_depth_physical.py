"""Issue 56, item 3: a depth model stays physical whatever its fitted terms.

For every pixel and measured depth in a D435's range (0.2-10 m) the corrected depth is finite,
positive and increasing in the measured depth; what the bound holds is named and dropped from
the clouds; the voxel grids take any cloud; extreme models and far scenes go through the depth
paths (overlap update, agreement, image correction) without an exception."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from analytic_scene import CAM_A, CAM_B, INTR, RECTS, look_at, scene_cloud

from rgbd_calib.core.depth_model import (
    PARAMETERS,
    RATIO_MAX,
    RATIO_MIN,
    DepthModel,
    correct_depth_image,
    identity_model,
)
from rgbd_calib.depth.agreement import fused_agreement
from rgbd_calib.depth.clouds import voxel_keys, voxel_mean, voxel_pick
from rgbd_calib.depth.depth_model_fit import (
    STEP,
    BoardSamples,
    predicted_depth_jacobian,
    predicted_depth_m,
)
from rgbd_calib.depth.overlap_models import overlap_samples, recorrected, update_models

FB = 40.0  # focal x baseline (px m)
Z = np.linspace(0.2, 10.0, 200)  # the sensor's range (m)


def _extreme_models(seed: int, n: int = 40) -> list[DepthModel]:
    """Models a fit extrapolated past its data could return: offsets of tens of pixels,
    gradients and curvatures that reach them at the image's corners, scales far from 1."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        values = {"scale": float(rng.uniform(0.5, 2.0)), "d0": float(rng.normal(0, 20)),
                  "dx": float(rng.normal(0, 50)), "dy": float(rng.normal(0, 50)),
                  "dxx": float(rng.normal(0, 200)), "dxy": float(rng.normal(0, 200)),
                  "dyy": float(rng.normal(0, 200)), "rx": float(rng.normal(0, 2)),
                  "tz": float(rng.normal(0, 20))}
        out.append(DepthModel(FB, values, ("scale", "offset", "gradient", "curvature", "pose")))
    return out


def _rays(n: int = 15) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.meshgrid(np.linspace(-0.9, 0.9, n), np.linspace(-0.6, 0.6, n))
    return x.ravel(), y.ravel()


@pytest.mark.parametrize("seed", [0, 1])
def test_corrected_depth_is_finite_positive_and_increasing_for_any_model(seed):
    x, y = _rays()
    for model in _extreme_models(seed):
        zz = np.broadcast_to(Z[:, None], (len(Z), len(x)))
        z = model.true_depth(np.broadcast_to(x, zz.shape), np.broadcast_to(y, zz.shape), zz)
        assert np.all(np.isfinite(z)) and np.all(z > 0)
        assert np.all(np.diff(z, axis=0) > 0), "not increasing in the measured depth"
        ratio = zz / z
        assert np.all(ratio >= RATIO_MIN - 1e-12) and np.all(ratio <= RATIO_MAX + 1e-12)
        # the inverse (rendering) undoes it, bound included
        back = model.measured_depth(np.broadcast_to(x, zz.shape), np.broadcast_to(y, zz.shape), z)
        np.testing.assert_allclose(back, zz, rtol=1e-9)


def test_a_mild_model_is_untouched_by_the_bound_and_the_bound_is_named():
    x, y = _rays()
    mild = DepthModel(FB, {"scale": 1.004, "d0": 0.2, "dxx": -1.5}, ("scale", "offset"))
    zz = np.full_like(x, 4.0)
    assert not np.any(mild.beyond_bounds(x, y, zz))
    expect = zz / (1.004 - zz * mild.disparity_offset_px(x, y) / FB)
    np.testing.assert_allclose(mild.true_depth(x, y, zz), expect, rtol=1e-12)
    wild = DepthModel(FB, {"d0": 30.0}, ("offset",))  # 1 - z d0 / fB < 0 beyond 1.3 m
    held = wild.beyond_bounds(x, y, np.full_like(x, 3.0))
    assert np.all(held)
    rays = np.column_stack([x, y, np.ones_like(x)])
    pts = wild.correct_points(rays, np.full_like(x, 3.0), drop_beyond_bounds=True)
    assert np.all(np.isnan(pts))
    assert np.all(np.isfinite(wild.correct_points(rays, np.full_like(x, 3.0))))


def test_nothing_measured_stays_nothing():
    model = _extreme_models(3, 1)[0]
    z = model.true_depth(np.zeros(4), np.zeros(4), np.array([0.0, -1.0, np.nan, np.inf]))
    assert np.all(z == 0.0)


def test_voxel_grids_take_a_cloud_of_any_extent():
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(0, 1, (500, 3)), [[1e5, -3e4, 7e3]]])
    keys = voxel_keys(pts, 0.005)  # 2e7 voxels across: more than 21 bits
    again = voxel_keys(pts + 0.0, 0.005)
    assert np.array_equal(keys, again)
    twin = np.concatenate([pts, pts[:3]])
    k2 = voxel_keys(twin, 0.005)
    assert np.array_equal(k2[-3:], k2[:3])  # the same voxel, the same key
    assert len(np.unique(k2)) == len(np.unique(np.floor(twin / 0.005), axis=0))
    means, _, counts = voxel_mean(pts, 0.005)
    assert counts.sum() == len(pts) and len(voxel_pick(pts, 0.005)) == len(means)
    assert len(voxel_keys(np.zeros((0, 3)), 0.005)) == 0


def test_extreme_models_and_far_scenes_pass_every_depth_path():
    """A cloud corrected by a model that left physics, pushed 10x further out: the overlap
    update, the agreement and the image correction finish and say what they could."""
    rng = np.random.default_rng(7)
    cam_c = look_at([0.0, 0.8, 1.7], [1.8, 0.5, 0.3])
    poses = {"a": CAM_A, "b": CAM_B, "c": cam_c}
    pairs = [("a", "b"), ("a", "c"), ("b", "c")]
    clouds = {n: scene_cloud(n, T, RECTS, rng) for n, T in poses.items()}
    far = replace(clouds["b"], points=(clouds["b"].points * 10.0).astype(np.float32))
    clouds = {**clouds, "b": far}
    for model in _extreme_models(5, 4):
        models = {"a": model, "b": identity_model(INTR), "c": identity_model(INTR)}
        corrected = {**clouds, "a": recorrected(clouds["a"], None, model)}
        assert np.all(np.isfinite(corrected["a"].points))
        update = update_models(models, {"a": np.diag([0.002, 0.1]) ** 2},
                               overlap_samples(corrected, poses, pairs, models), poses, None)
        used = {**models, **(update.models if update is not None else {})}
        for m in used.values():
            z = m.true_depth(np.zeros_like(Z), np.zeros_like(Z), Z)
            assert np.all(np.isfinite(z)) and np.all(z > 0)
        agree = fused_agreement(corrected, poses, pairs, used)
        assert agree is not None
        depth = np.full((INTR.height, INTR.width), 9.5)
        img = correct_depth_image(model, depth, INTR)
        assert np.all(np.isfinite(img)) and np.all(img >= 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_fits_closed_form_jacobian_equals_central_differences(seed):
    """The depth-model fit's Jacobian (closed form, issue 59) is the derivative of the
    prediction it fits: equal to central differences at the fit's steps for any model, with
    every term free and each view's plane moved by an inverse-depth offset."""
    rng = np.random.default_rng(seed)
    n = 2000
    rays = np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.4, 0.4, n), np.ones(n)])
    normal = np.tile(np.array([-0.1, 0.2, 1.0]) / np.linalg.norm([-0.1, 0.2, 1.0]), (n, 1))
    samples = BoardSamples(rays, np.ones(n), normal, np.full(n, rng.uniform(0.8, 3.0)),
                           np.full(n, 1e-3), np.zeros(n, int), ("f0",), np.zeros((n, 2)))
    values = {p: (1.0 + rng.normal(0, 0.01)) if p == "scale" else rng.normal(0, 0.3)
              for p in PARAMETERS}
    model = DepthModel(40.0, values)
    offset = rng.normal(0, 0.01, n)
    J, d_inv = predicted_depth_jacobian(model, samples, PARAMETERS, offset)
    for j, p in enumerate(PARAMETERS):
        h = STEP[p]
        fd = (predicted_depth_m(model.with_values({p: model.value(p) + h}), samples, offset)
              - predicted_depth_m(model.with_values({p: model.value(p) - h}), samples, offset)
              ) / (2 * h)
        assert np.max(np.abs(fd - J[:, j])) <= 1e-6 * np.max(np.abs(fd)), p
    fd = (predicted_depth_m(model, samples, offset + 1e-5)
          - predicted_depth_m(model, samples, offset - 1e-5)) / 2e-5
    assert np.max(np.abs(fd - d_inv)) <= 1e-6 * np.max(np.abs(fd))


def test_normals_moved_through_a_depth_correction_equal_normals_estimated_again():
    """A camera's normals are estimated once (NormalGrid) and moved with each change of its
    depth correction: they must be the normals of the corrected cloud, and undoing the move
    must give the grid back (issue 59, surfaces built once)."""
    from scipy.spatial import cKDTree

    from rgbd_calib.depth.agreement import NormalGrid

    rng = np.random.default_rng(5)
    u, w = rng.uniform(-1, 1, 150_000), rng.uniform(0, 1, 150_000)
    floor = np.column_stack([1.5 * u, np.full_like(u, 0.8), 1 + 3 * w])
    wall = np.column_stack([-1.2 + 0.3 * w, 0.6 * u, 1 + 3 * w])
    measured = np.vstack([floor, wall])
    model = DepthModel(35.0, {"scale": 1.004, "d0": 0.4, "dx": 0.3, "dy": -0.2, "dxx": 0.3,
                              "rx": 0.2, "ry": -0.1, "tz": 3.0})
    z = measured[:, 2]
    corrected = model.correct_points(measured / z[:, None], z)
    grid = NormalGrid.of(measured)
    moved, again = grid.moved(None, model), NormalGrid.of(corrected)
    nearest = cKDTree(again.centres).query(moved.centres)[1]
    cos = np.abs(np.sum(again.normals[nearest] * moved.normals, axis=1))
    assert np.percentile(np.degrees(np.arccos(np.clip(cos, 0, 1))), 99) < 0.1
    assert np.all(np.sum(moved.normals * moved.centres, axis=1) < 0)  # facing the camera
    back = moved.moved(model, None)
    assert np.allclose(back.centres, grid.centres, atol=1e-9)
    assert np.allclose(back.normals, grid.normals, atol=1e-9)
