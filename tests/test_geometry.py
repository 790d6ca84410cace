"""Property tests of the rigid-body helpers (group axioms, round trips)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from rgbd_calib.core.geometry import (
    adjoint,
    invert_transform,
    is_rigid,
    look_at,
    make_transform,
    matrix_to_quaternion_xyzw,
    matrix_to_rotvec,
    quaternion_xyzw_to_matrix,
    rotvec_to_matrix,
    skew,
    transform_error,
    transform_points,
)

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
angle = st.floats(0, np.pi - 1e-6)
unit = st.tuples(finite, finite, finite).filter(lambda v: np.linalg.norm(v) > 1e-3).map(
    lambda v: np.asarray(v) / np.linalg.norm(v))


@st.composite
def transforms(draw):
    return make_transform(rotvec_to_matrix(draw(unit) * draw(angle)), draw(vec3))


@given(transforms())
def test_inverse_composes_to_identity(T_a_b):
    assert is_rigid(T_a_b)
    np.testing.assert_allclose(T_a_b @ invert_transform(T_a_b), np.eye(4), atol=1e-9)


@given(transforms(), transforms(), vec3)
def test_composition_cancels_inner_names(T_a_b, T_b_c, p_c):
    p_a = transform_points(T_a_b @ T_b_c, p_c[None])[0]
    np.testing.assert_allclose(p_a, transform_points(T_a_b, transform_points(T_b_c, p_c[None]))[0],
                               atol=1e-9)


@given(unit, angle)
def test_rotvec_round_trip(axis, theta):
    R = rotvec_to_matrix(axis * theta)
    np.testing.assert_allclose(rotvec_to_matrix(matrix_to_rotvec(R)), R, atol=1e-7)
    assert abs(transform_error(make_transform(R, [0, 0, 0]), np.eye(4))[0]
               - np.degrees(theta)) < 1e-5


@settings(max_examples=200)
@given(transforms())
def test_quaternion_round_trip_and_sign(T):
    q = matrix_to_quaternion_xyzw(T[:3, :3])
    assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    np.testing.assert_allclose(quaternion_xyzw_to_matrix(q), T[:3, :3], atol=1e-9)


def test_look_at_is_opencv_optical_frame():
    T_world_cam = look_at([0, 0, 1], [0, 5, 1])  # looking along +y, z up
    R = T_world_cam[:3, :3]
    np.testing.assert_allclose(R[:, 2], [0, 1, 0], atol=1e-12)  # z forward
    np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-12)  # y down
    np.testing.assert_allclose(R[:, 0], [1, 0, 0], atol=1e-12)  # x right


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """``Exp([omega, v])`` by the matrix exponential of the twist (GTSAM's order)."""
    twist = np.zeros((4, 4))
    twist[:3, :3] = skew(xi[:3])
    twist[:3, 3] = xi[3:]
    return expm(twist)


@settings(deadline=None)
@given(transforms(), st.tuples(*[st.floats(-1, 1)] * 6).map(np.array))
def test_adjoint_moves_a_right_perturbation_to_the_left(T_a_b, xi):
    """T Exp(xi) = Exp(Ad(T) xi) T, the defining property of GTSAM's Pose3::AdjointMap."""
    np.testing.assert_allclose(T_a_b @ exp_se3(xi), exp_se3(adjoint(T_a_b) @ xi) @ T_a_b,
                               atol=1e-9)


@given(transforms())
def test_adjoint_is_gtsams(T_a_b):
    gtsam = pytest.importorskip("gtsam")
    np.testing.assert_allclose(adjoint(T_a_b), gtsam.Pose3(T_a_b).AdjointMap(), atol=1e-12)
