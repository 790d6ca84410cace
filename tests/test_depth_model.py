"""Each camera's depth model (issue 33): the pure model and its inverse, the library function
that corrects a depth image, the evidence-chosen fit from board pixels, depth_model.yaml."""

from __future__ import annotations

import numpy as np
import pytest

from rgbd_calib import correct_depth_image, load_depth_models
from rgbd_calib.core.camera import CameraIntrinsics
from rgbd_calib.core.depth_model import DepthModel, distort_depth_image, identity_model
from rgbd_calib.core.errors import RgbdCalibError
from rgbd_calib.depth.depth_model_fit import BoardSamples, fit_depth_model
from rgbd_calib.model.depth_model_file import save_depth_models

INTR = CameraIntrinsics(424, 240, 300.0, 300.0, 212.0, 120.0, (0.05, -0.02, 0.0, 0.0, 0.0))
FULL = dict(scale=1.004, d0=0.15, dx=0.04, dyy=-0.03, rx=0.1, ry=-0.2, rz=0.05, tx=1.0,
            ty=-0.5, tz=0.8)


def _plane_depth(normal, distance_m):
    u, v = np.meshgrid(np.arange(INTR.width, dtype=float), np.arange(INTR.height, dtype=float))
    rays = INTR.rays(u, v)
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    return (distance_m / (rays @ n)).reshape(INTR.height, INTR.width)


def test_measured_depth_inverts_true_depth():
    m = identity_model(INTR).with_values(FULL)
    x, y = np.meshgrid(np.linspace(-0.7, 0.7, 9), np.linspace(-0.4, 0.4, 5))
    z = np.linspace(0.3, 6.0, x.size).reshape(x.shape)
    assert np.allclose(m.true_depth(x, y, m.measured_depth(x, y, z)), z, rtol=1e-12)
    assert np.all(m.true_depth(x, y, np.zeros_like(z)) == 0.0)


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_correct_depth_image_undoes_what_the_camera_reports(dtype):
    """A tilted wall 1.5 m away seen through the full model (+-5 mm off), corrected by the
    library function: back to the wall within 0.1 mm (uint16 counts: their 1 mm rounding)."""
    m = identity_model(INTR).with_values(FULL)
    z = _plane_depth([0.2, 0.1, 1.0], 1.5)
    measured = distort_depth_image(m, z, INTR)
    assert np.median(np.abs(measured - z)) > 2e-3
    image = (np.rint(measured / INTR.depth_scale).astype(np.uint16) if dtype == np.uint16
             else measured.astype(np.float32))
    fixed = correct_depth_image(m, image, INTR)
    assert fixed.dtype == image.dtype
    metres = fixed.astype(float) * (INTR.depth_scale if dtype == np.uint16 else 1.0)
    inner = np.s_[20:-20, 20:-20]
    tol = 1.1e-3 if dtype == np.uint16 else 1e-4  # two 1 mm roundings
    assert np.max(np.abs(metres[inner] - z[inner])) < tol


def test_correct_depth_image_refuses_another_size():
    with pytest.raises(RgbdCalibError, match="aligned to colour"):
        correct_depth_image(identity_model(INTR), np.zeros((10, 10), np.uint16), INTR)


def _samples(model: DepthModel, seed: int, n_views: int = 30) -> BoardSamples:
    """Board faces at 0.7-2.8 m, tilted up to 35 deg, over the image; per pixel the D435
    noise of the true depth (subpixel 0.08 px), the depth what ``model``'s camera reports
    (no pose error: the pose is exercised on renders, tests/test_synth_depth_model.py)."""
    rng = np.random.default_rng(seed)
    parts = []
    fB = model.focal_baseline_px_m
    for v in range(n_views):
        n = np.array([*rng.uniform(-0.45, 0.45, 2), 1.0])
        n /= np.linalg.norm(n)
        d = rng.uniform(0.7, 2.8)
        us = rng.uniform(0, INTR.width - 1, 800)
        vs = rng.uniform(0, INTR.height - 1, 800)
        rays = INTR.rays(us, vs)
        z_true = d / (rays @ n)
        sigma = z_true**2 * 0.08 / fB
        zm = model.measured_depth(rays[:, 0], rays[:, 1], z_true)
        zm = zm + rng.normal(0.0, 1.0, zm.size) * sigma
        parts.append((rays, zm, np.tile(n, (800, 1)), np.full(800, d), sigma,
                      np.full(800, v), np.column_stack([us, vs])))
    cols = [np.concatenate([p[i] for p in parts]) for i in range(7)]
    return BoardSamples(cols[0], cols[1], cols[2], cols[3], cols[4], cols[5].astype(int),
                        tuple(f"{v:06d}" for v in range(n_views)), cols[6])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_clean_camera_keeps_the_identity(seed):
    fit = fit_depth_model("cam", _samples(identity_model(INTR), seed), INTR)
    assert fit.model.terms == ()
    assert fit.model.is_identity
    assert 0.8 < fit.sigma_factor < 1.2


def test_a_camera_that_needs_a_model_gets_every_term():
    """``depth.model_fit.model_terms: all``: the ladder's evidence decides that the camera needs
    a model; once it does, every term is free (unbiased parameters with their own, larger
    sigmas), and the tests still say which terms the evidence alone accepted. ``evidence`` keeps
    those only. A clean camera keeps the identity either way."""
    from rgbd_calib.core.config import DepthConfig
    from rgbd_calib.core.depth_model import PARAMETERS, TERMS

    truth = identity_model(INTR).with_values({"scale": 1.005, "d0": 0.12, "dx": 0.04})
    samples = _samples(truth, 6)
    every = fit_depth_model("cam", samples, INTR, DepthConfig(model_terms="all"))
    some = fit_depth_model("cam", samples, INTR, DepthConfig(model_terms="evidence"))
    assert every.model.terms == tuple(TERMS) and set(every.model.sigmas) == set(PARAMETERS)
    assert set(some.model.terms) < set(TERMS)
    assert [t.kept for t in every.tests] == [t.kept for t in some.tests]
    for p in PARAMETERS:
        assert abs(every.model.value(p) - truth.value(p)) < 3.5 * every.model.sigmas[p], p
        if p in some.model.sigmas:
            assert every.model.sigmas[p] >= some.model.sigmas[p] * 0.99, p
    clean = fit_depth_model("cam", _samples(identity_model(INTR), 1), INTR,
                            DepthConfig(model_terms="all"))
    assert clean.model.is_identity


@pytest.mark.parametrize("n_views", [30, 15, 14, 8])
def test_auto_frees_every_term_where_the_views_can_judge_them(n_views):
    """``depth.model_fit.model_terms: auto`` (the default): a camera that needs a model gets
    every term when its views are at least the 13 parameters and 2 more (the clustered
    covariance has a view to spare), the ladder's terms with fewer (on 8 frame sets every term
    put a race's scene 20-100 mm off: docs/depth.md)."""
    from rgbd_calib.core.config import DepthConfig
    from rgbd_calib.core.depth_model import TERMS

    truth = identity_model(INTR).with_values({"scale": 1.005, "d0": 0.12, "dx": 0.04})
    samples = _samples(truth, 6, n_views)
    auto = fit_depth_model("cam", samples, INTR)
    ladder = fit_depth_model("cam", samples, INTR, DepthConfig(model_terms="evidence"))
    assert ladder.model.terms and set(ladder.model.terms) < set(TERMS)
    assert auto.model.terms == (tuple(TERMS) if n_views >= 15 else ladder.model.terms)
    assert auto.too_few_views == (n_views < 15) and not ladder.too_few_views


@pytest.mark.parametrize("n_views", [3, 4, 6, 7])
def test_no_step_is_tried_on_as_many_parameters_as_views(n_views):
    """The sandwich covariance of V views has rank V - 1 at most: a step of k >= V parameters
    is judged by the model-based covariance alone, which does not see a term the model lacks.
    Without the rule 3 views of a camera whose depth sensor sits exactly where it should (a
    disparity curvature left out) kept a depth-to-colour pose at a Wald statistic of
    3e5-1.5e7 (seeds 1, 2; an untuned ring's clouds 31 and 47 mm off: docs/depth.md, 'Few
    board views'); with it the pose's 6 parameters are not tried below 7 views."""
    from rgbd_calib.depth.depth_model_fit import step_fits_views

    truth = identity_model(INTR).with_values({"scale": 1.005, "d0": 0.12, "dx": 0.08,
                                              "dy": -0.06, "dyy": -0.05})
    for seed in (1, 2):
        fit = fit_depth_model("cam", _samples(truth, seed, n_views), INTR)
        assert "scale" in fit.model.terms
        tried = {t.term for t in fit.tests}
        assert ("pose" in tried) == (n_views >= 7) and ("pose" in fit.model.terms) <= (n_views >= 7)
    assert step_fits_views(2, 3) and not step_fits_views(3, 3) and not step_fits_views(6, 6)


def test_a_gauss_newton_step_that_leaves_the_models_domain_is_halved(monkeypatch):
    """A fit barely held by its views (every term on 3 views of a real camera: condition
    number 2e21) took a first step of 0.5 in scale and 840 mm in the depth sensor's position,
    after which every predicted depth was negative and the next solve raised an SVD error
    out of calibrate. A step is now taken only where it lowers the Huber cost, halved until
    it does: here the first step made 1e4 times too long comes back to the same solution."""
    import rgbd_calib.depth.depth_model_fit as dmf
    from rgbd_calib.core.depth_model import PARAMETERS

    truth = identity_model(INTR).with_values({"scale": 1.005, "d0": 0.12, "dx": 0.04})
    samples = _samples(truth, 6, 20)
    names = ("scale", "d0", "dx", "dy")
    plain = dmf._solve(identity_model(INTR), samples, names, 1.5)
    lstsq, calls = np.linalg.lstsq, []

    def overshooting(a, b, rcond=None):
        x = lstsq(a, b, rcond=rcond)
        calls.append(1)
        return (x[0] * (1e4 if len(calls) == 1 else 1.0), *x[1:])

    monkeypatch.setattr(dmf.np.linalg, "lstsq", overshooting)
    pushed = dmf._solve(identity_model(INTR), samples, names, 1.5)
    assert np.isfinite(pushed.chi2) and pushed.chi2 == pytest.approx(plain.chi2, rel=1e-6)
    for p in names:
        assert pushed.model.value(p) == pytest.approx(plain.model.value(p), abs=1e-3), p
    assert set(names) <= set(PARAMETERS)


def test_the_report_says_how_many_views_a_model_was_fitted_on():
    """report.json ``depth_models.<camera>.n_views`` (1.17): why a camera kept the ladder's
    terms under ``auto`` is read there, as on the console."""
    from rgbd_calib.outputs.report.build import _depth_model_entry

    truth = identity_model(INTR).with_values({"scale": 1.005, "d0": 0.12})
    entry = _depth_model_entry(fit_depth_model("cam", _samples(truth, 4, 12), INTR))
    assert entry["n_views"] == 12 and entry["terms"] and len(entry["terms"]) < 5


@pytest.mark.parametrize("seed", [4, 5])
def test_scale_and_disparity_offset_are_found_within_their_sigmas(seed):
    truth = identity_model(INTR).with_values({"scale": 1.005, "d0": 0.12})
    fit = fit_depth_model("cam", _samples(truth, seed), INTR)
    assert set(fit.model.terms) >= {"scale", "offset"}, fit.tests
    for p in ("scale", "d0"):
        assert abs(fit.model.value(p) - truth.value(p)) < 3 * fit.model.sigmas[p], (p, fit)
    # per distance band the corrected median is within 3 standard errors of a median (of the
    # noise there) of the plane; before, the far bands were tens of them off
    for z0, z1, n, _before, after, _, _, noise in fit.bands:
        se = 1.2533 * noise / np.sqrt(n)
        assert abs(after) < 3 * se + 0.1, (z0, z1, after, se)
    assert max(abs(b[3]) / (1.2533 * b[7] / np.sqrt(b[2])) for b in fit.bands) > 20


def test_depth_model_yaml_round_trips_through_the_library_function(tmp_path):
    m = identity_model(INTR).with_values(FULL, terms=("scale", "offset", "pose"),
                                         sigmas={"scale": 1e-4})
    save_depth_models({"cam": m}, tmp_path / "depth_model.yaml")
    back = load_depth_models(tmp_path)["cam"]
    assert np.array_equal(back.vector(), m.vector())
    assert (back.terms, back.sigmas, back.focal_baseline_px_m) == (
        m.terms, m.sigmas, m.focal_baseline_px_m)
    z = distort_depth_image(m, _plane_depth([0.0, 0.3, 1.0], 2.0), INTR)
    assert np.array_equal(correct_depth_image(back, z, INTR), correct_depth_image(m, z, INTR))


def test_a_broken_depth_model_yaml_is_one_line_naming_the_file(tmp_path):
    bad = tmp_path / "depth_model.yaml"
    bad.write_text("format_version: 1\ncameras:\n  cam: {parameters: {zoom: 2}}\n")
    with pytest.raises(RgbdCalibError, match="depth_model.yaml.*cam") as info:
        load_depth_models(bad)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("setting", ["auto", "none"])
def test_depth_model_none_leaves_the_clouds_to_the_depth_scale_factor(tiny_dataset, setting):
    """``depth.model: none`` fits no model: each static cloud is divided by its camera's
    depth-scale factor, as before the model; ``auto`` fits one per camera with board views."""
    from rgbd_calib.core.config import DepthConfig
    from rgbd_calib.core.geometry import invert_transform
    from rgbd_calib.depth.stage import measure_depth
    from rgbd_calib.model.board import thesis_board
    from rgbd_calib.model.dataset import FolderDataset
    from rgbd_calib.synth.ground_truth import load_ground_truth

    ds, gt = FolderDataset(tiny_dataset), load_ground_truth(tiny_dataset)
    views = {c: {f: invert_transform(T) @ B for f, B in gt.T_ref_board.items()}
             for c, T in gt.T_ref_cam.items()}
    depth = measure_depth(ds, thesis_board(), gt.T_ref_cam, views, gt.T_ref_board, "none",
                          DepthConfig(model=setting), workers=1)
    assert depth.depth_scales and set(depth.clouds) == set(ds.cameras)
    if setting == "none":
        assert depth.depth_models == {}
        for c, cloud in depth.clouds.items():
            assert cloud.depth_scale_factor == depth.depth_scales[c].factor
    else:
        assert set(depth.depth_models) == set(depth.depth_scales)


def _moved(xi: np.ndarray) -> np.ndarray:
    """``p -> R p + t`` for a small twist ``xi = [rotation vector, t]`` (first order: Exp)."""
    from rgbd_calib.core.geometry import make_transform, rotvec_to_matrix

    return make_transform(rotvec_to_matrix(xi[:3]), xi[3:])


def test_a_planes_covariance_is_its_inverse_depth_error_under_its_pose_error():
    """:func:`plane_covariance`: a board pose moved by a small ``xi`` (left perturbation in the
    camera frame) moves its face plane's inverse depth along every ray by ``u . ray``; the
    covariance of ``u`` for ``xi``'s covariance ``xi xi^T`` is ``u u^T`` (to first order)."""
    from rgbd_calib.depth.depth_model_fit import plane_covariance

    rng = np.random.default_rng(7)
    n = np.array([0.3, -0.2, 1.0])
    n /= np.linalg.norm(n)
    d = 1.4
    rays = INTR.rays(np.array([10.0, 400.0, 200.0, 50.0]), np.array([5.0, 30.0, 230.0, 120.0]))
    for _ in range(3):
        xi = np.concatenate([rng.normal(0, 1e-4, 3), rng.normal(0, 1e-4, 3)])
        T = _moved(xi)
        n2 = T[:3, :3] @ n
        d2 = d + n2 @ T[:3, 3]
        change = rays @ n2 / d2 - rays @ n / d
        u = np.linalg.lstsq(rays, change, rcond=None)[0]
        assert np.allclose(rays @ u, change, rtol=0, atol=1e-9)
        assert np.allclose(plane_covariance(n, d, np.outer(xi, xi)), np.outer(u, u),
                           rtol=0.02, atol=1e-12)


def _posed_samples(model: DepthModel, seed: int, n_views: int, rot_deg: float,
                   trans_mm: float) -> tuple[BoardSamples, dict[str, np.ndarray]]:
    """:func:`_samples` whose planes are where a board pose with errors of ``rot_deg`` /
    ``trans_mm`` (1 sigma per axis, camera frame) put them, not where the board was; with the
    poses' covariance per frame."""
    s = _samples(model, seed, n_views)
    rng = np.random.default_rng(seed + 1000)
    C = np.diag([np.radians(rot_deg) ** 2] * 3 + [(trans_mm * 1e-3) ** 2] * 3)
    normal, distance = s.normal.copy(), s.distance_m.copy()
    for v in range(n_views):
        m = s.view == v
        T = _moved(rng.multivariate_normal(np.zeros(6), C))
        n2 = normal[m][0] @ T[:3, :3].T
        normal[m] = n2
        distance[m] = distance[m][0] + n2 @ T[:3, 3]
    posed = BoardSamples(s.rays, s.z_measured, normal, distance, s.sigma_z, s.view, s.frames,
                         s.pixels)
    return posed, {f: C for f in s.frames}


def test_few_views_whose_board_poses_are_off_keep_the_identity_when_their_planes_are_uncertain():
    """A clean camera of 8 views whose board planes are off by their poses' errors (0.05 deg,
    0.8 mm: the board a camera did not detect, placed through its extrinsics and the time
    model; race seed 382) gets terms it does not need when the planes count as exact; with
    each plane's error a random effect of its view (its pose's covariance,
    :func:`board_samples`' ``pose_covariance``) it keeps the identity. (At 6 views the
    exact planes' spurious term, the 6-parameter pose, is no longer tried at all:
    test_no_term_is_tried_on_as_many_parameters_as_views.)"""
    from dataclasses import replace

    from rgbd_calib.depth.depth_model_fit import plane_covariance

    exact, uncertain = [], []
    for seed in range(8):
        s, cov = _posed_samples(identity_model(INTR), seed, 8, 0.05, 0.8)
        exact.append(fit_depth_model("cam", s, INTR).model.terms)
        planes = np.array([plane_covariance(s.normal[s.view == v][0],
                                            s.distance_m[s.view == v][0], cov[f])
                           for v, f in enumerate(s.frames)])
        uncertain.append(fit_depth_model("cam", replace(s, plane_cov=planes), INTR).model.terms)
    # the exact planes' spurious term (the pose): 3 of 8 before held-out board views judged the
    # model (2026-12-07), 1 of 8 since (tests/test_depth_held_out.py)
    assert sum(bool(t) for t in exact) >= 1, exact
    assert all(t == () for t in uncertain), uncertain


def test_a_real_depth_error_is_still_found_on_uncertain_planes():
    """The same random effects on 30 views of a camera with a 0.5 % scale and a 0.12 px
    disparity offset: both found, within 3 sigma, with sigmas that grew by the planes'
    uncertainty."""
    from dataclasses import replace

    from rgbd_calib.depth.depth_model_fit import plane_covariance

    truth = identity_model(INTR).with_values({"scale": 1.005, "d0": 0.12})
    s, cov = _posed_samples(truth, 5, 30, 0.05, 0.8)
    planes = np.array([plane_covariance(s.normal[s.view == v][0], s.distance_m[s.view == v][0],
                                        cov[f]) for v, f in enumerate(s.frames)])
    fit = fit_depth_model("cam", replace(s, plane_cov=planes), INTR)
    exact = fit_depth_model("cam", s, INTR)
    assert set(fit.model.terms) >= {"scale", "offset"}, fit.tests
    for p in ("scale", "d0"):
        assert abs(fit.model.value(p) - truth.value(p)) < 3 * fit.model.sigmas[p], (p, fit)
        assert fit.model.sigmas[p] > exact.model.sigmas[p], p


def test_a_view_whose_pose_covariance_is_not_finite_keeps_its_plane_exact():
    """A PnP covariance of inf or NaN (a degenerate view) must not break the fit: that view's
    plane counts as exact, as with no covariance."""
    from dataclasses import replace

    from rgbd_calib.depth.depth_model_fit import plane_covariance

    s, cov = _posed_samples(identity_model(INTR), 3, 8, 0.05, 0.8)
    planes = np.array([plane_covariance(s.normal[s.view == v][0], s.distance_m[s.view == v][0],
                                        cov[f]) for v, f in enumerate(s.frames)])
    held = planes.copy()
    held[0] = 0.0
    expected = fit_depth_model("cam", replace(s, plane_cov=held), INTR)
    for bad in (np.inf, np.nan):
        broken = planes.copy()
        broken[0] = bad
        fit = fit_depth_model("cam", replace(s, plane_cov=broken), INTR)
        assert fit.model.terms == expected.model.terms
        assert [t.wald for t in fit.tests] == pytest.approx([t.wald for t in expected.tests])
