"""Signed distances of points to the true surfaces of a synthetic scene (synth/surfaces.py)."""

from __future__ import annotations

import numpy as np
import pytest

from rgbd_calib.synth.scene import box, rect
from rgbd_calib.synth.surfaces import surface_distances

EXACT_M = 1e-12
GREY = (0.5, 0.5, 0.5)


def _floor_and_wall():
    """A 1 m x 1 m floor (z = 0, normal +z) and a 1 m x 1 m wall (x = 0, normal +x) meeting
    along the y axis, and a far floor tile 5 m away in the floor's plane."""
    floor = rect((0, 0, 0), (1, 0, 0), (0, 1, 0), GREY, 1)
    wall = rect((0, 0, 0), (0, 1, 0), (0, 0, 1), GREY, 2)
    far_tile = rect((5, 0, 0), (1, 0, 0), (0, 1, 0), GREY, 3)
    return [floor, wall, far_tile]


def test_sign_says_beyond_or_in_front_from_either_side():
    floor = [rect((0, 0, 0), (1, 0, 0), (0, 1, 0), GREY, 1)]
    points = np.array([[0.3, 0.4, -0.01], [0.3, 0.4, 0.02]])
    above = surface_distances(floor, points, np.array([0.5, 0.5, 2.0]))
    np.testing.assert_allclose(above.signed_m, [0.01, -0.02], atol=EXACT_M)
    below = surface_distances(floor, points, np.array([0.5, 0.5, -2.0]))
    np.testing.assert_allclose(below.signed_m, [-0.01, 0.02], atol=EXACT_M)
    np.testing.assert_array_equal(above.rect_index, [0, 0])


def test_the_sign_does_not_depend_on_the_rectangles_orientation():
    """The same floor with u and v swapped has its normal along -z: same signed distances."""
    up = [rect((0, 0, 0), (1, 0, 0), (0, 1, 0), GREY, 1)]
    down = [rect((0, 0, 0), (0, 1, 0), (1, 0, 0), GREY, 1)]
    points = np.array([[0.3, 0.4, -0.01], [0.7, 0.2, 0.03]])
    eye = np.array([0.5, 0.5, 2.0])
    np.testing.assert_allclose(surface_distances(up, points, eye).signed_m,
                               surface_distances(down, points, eye).signed_m, atol=EXACT_M)


def test_edges_count_the_distance_to_the_bounded_rectangle():
    floor = [rect((0, 0, 0), (1, 0, 0), (0, 1, 0), GREY, 1)]
    eye = np.array([0.5, 0.5, 2.0])
    points = np.array([
        [1.03, 0.5, 0.0],    # 3 cm past the edge, in the plane: matched, on the surface
        [1.03, 1.039, 0.0],  # past a corner: 4.9 cm away, matched
        [1.03, 0.5, -0.039],  # past the edge and below: 4.9 cm away, matched
        [1.06, 0.5, 0.0],    # 6 cm past the edge: unmatched
        [0.5, 0.5, 0.051],   # above the middle, beyond 5 cm: unmatched
    ])
    d = surface_distances(floor, points, eye)
    np.testing.assert_allclose(d.gap_m[:3], [0.03, np.hypot(0.03, 0.039), np.hypot(0.03, 0.039)],
                               atol=1e-12)
    np.testing.assert_allclose(d.signed_m[:3], [0.0, 0.0, 0.039], atol=EXACT_M)
    np.testing.assert_array_equal(d.rect_index, [0, 0, 0, -1, -1])
    assert np.all(np.isnan(d.signed_m[3:])) and np.all(np.isinf(d.gap_m[3:]))
    assert d.matched.tolist() == [True, True, True, False, False]


def test_the_nearest_bounded_rectangle_is_chosen():
    rects = _floor_and_wall()
    eye = np.array([2.0, 0.5, 1.5])  # in front of the wall, above the floor
    points = np.array([
        [0.01, 0.5, 0.3],    # 1 cm in front of the wall, 30 cm above the floor
        [0.03, 0.5, 0.01],   # 1 cm over the floor, 3 cm from the wall: the floor
        [-0.02, 0.5, 0.4],   # 2 cm behind the wall
        [0.5, 0.5, 0.02],    # over the floor; the far tile's plane has the same height
        [5.5, 0.5, -0.01],   # below the far tile
    ])
    d = surface_distances(rects, points, eye)
    np.testing.assert_array_equal(d.rect_index, [1, 0, 1, 0, 2])
    np.testing.assert_allclose(d.signed_m, [-0.01, -0.01, 0.02, -0.02, 0.01], atol=EXACT_M)


def test_a_box_seen_from_outside_is_signed_per_face():
    """An axis-aligned box (outward normals): a camera outside sees each face from outside,
    so points inside the box lie beyond the face they are nearest to."""
    faces = box((0, 0, 0), (1, 1, 1), GREY, 10)
    eye = np.array([3.0, 2.5, 2.0])
    points = np.array([[0.98, 0.5, 0.5], [0.5, 1.01, 0.5], [0.5, 0.5, 0.97]])
    d = surface_distances(faces, points, eye)
    np.testing.assert_allclose(d.signed_m, [0.02, -0.01, 0.03], atol=EXACT_M)
    normals = np.array([faces[k].normal for k in d.rect_index])
    np.testing.assert_allclose(normals, np.eye(3), atol=EXACT_M)


@pytest.mark.parametrize("chunk", [1, 7, 1000])
def test_blocks_give_the_same_answer_as_one_pass_and_a_per_point_reference(rng, chunk):
    rects = _floor_and_wall() + box((0.3, 0.3, 0.0), (0.6, 0.7, 0.4), GREY, 20)
    eye = np.array([2.0, 1.5, 1.8])
    points = rng.uniform([-0.1, -0.1, -0.1], [1.1, 1.1, 0.6], (300, 3))
    blocks = surface_distances(rects, points, eye, chunk=chunk)
    whole = surface_distances(rects, points, eye, chunk=10**6)
    np.testing.assert_array_equal(blocks.rect_index, whole.rect_index)
    np.testing.assert_array_equal(blocks.signed_m, whole.signed_m)
    assert 0 < np.count_nonzero(whole.matched) < len(points)
    for p, k, s in zip(points, whole.rect_index, whole.signed_m):
        gaps = [_bounded_gap(r, p) for r in rects]
        if min(gaps) > 0.05:
            assert k == -1
            continue
        assert gaps[k] == pytest.approx(min(gaps), abs=1e-12)
        r = rects[k]
        side = np.sign((eye - r.origin) @ r.normal)
        assert s == pytest.approx(-side * (p - r.origin) @ r.normal, abs=EXACT_M)


def test_no_points_and_no_rectangles():
    floor = [rect((0, 0, 0), (1, 0, 0), (0, 1, 0), GREY, 1)]
    assert surface_distances(floor, np.zeros((0, 3)), np.zeros(3)).signed_m.shape == (0,)
    d = surface_distances([], np.ones((2, 3)), np.zeros(3))
    assert d.rect_index.tolist() == [-1, -1]


def _bounded_gap(r, p) -> float:
    """Distance from ``p`` to the rectangle ``r``, one point at a time (the reference)."""
    d = p - r.origin
    a, b = d @ r.u_axis, d @ r.v_axis
    q = r.origin + np.clip(a, 0, r.size_u) * r.u_axis + np.clip(b, 0, r.size_v) * r.v_axis
    return float(np.linalg.norm(p - q))
