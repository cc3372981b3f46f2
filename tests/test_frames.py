"""SE(3) algebra properties of dm2.core.frames (hypothesis-driven)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dm2.core import frames

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite)
quat = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4).filter(
    lambda q: np.linalg.norm(q) > 0.1)


def pose(q, t):
    return frames.from_quat_abb(t, q)


@settings(max_examples=60, deadline=None)
@given(quat, vec3)
def test_inverse_is_two_sided(q, t):
    T = pose(q, t)
    assert np.allclose(T @ frames.invert(T), np.eye(4), atol=1e-9)
    assert np.allclose(frames.invert(T) @ T, np.eye(4), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(quat, vec3, quat, vec3, quat, vec3)
def test_composition_is_associative_and_names_cancel(q1, t1, q2, t2, q3, t3):
    T_a_b, T_b_c, T_c_d = pose(q1, t1), pose(q2, t2), pose(q3, t3)
    left = frames.compose(frames.compose(T_a_b, T_b_c), T_c_d)
    right = frames.compose(T_a_b, frames.compose(T_b_c, T_c_d))
    assert np.allclose(left, right, atol=1e-7)
    p_d = np.array([[1.0, -2.0, 3.0], [10.0, 0.5, -7.0]])
    p_a = frames.apply(T_a_b, frames.apply(T_b_c, frames.apply(T_c_d, p_d)))
    assert np.allclose(p_a, frames.apply(left, p_d), atol=1e-7)


@settings(max_examples=60, deadline=None)
@given(quat, vec3, quat, vec3, st.floats(0.0, 1.0))
def test_interpolation_endpoints_and_midpoint(q0, t0, q1, t1, alpha):
    T0, T1 = pose(q0, t0), pose(q1, t1)
    assert np.allclose(frames.interpolate_pose(T0, T1, 0.0), T0, atol=1e-9)
    assert np.allclose(frames.interpolate_pose(T0, T1, 1.0), T1, atol=1e-9)
    Tm = frames.interpolate_pose(T0, T1, alpha)
    # translation is linear
    assert np.allclose(Tm[:3, 3], (1 - alpha) * T0[:3, 3] + alpha * T1[:3, 3], atol=1e-7)
    # rotation lies on the geodesic: angles from both ends add up to the whole angle
    _, a0 = frames.pose_error(T0, Tm)
    _, a1 = frames.pose_error(Tm, T1)
    _, total = frames.pose_error(T0, T1)
    assert a0 + a1 == pytest.approx(total, abs=1e-6)
    assert a0 == pytest.approx(alpha * total, abs=1e-6)


def test_abb_quaternion_order_and_sign():
    # 90 degrees about z: ABB order (qw, qx, qy, qz) = (cos45, 0, 0, sin45)
    T = frames.make_T(Rotation.from_euler("z", 90, degrees=True), [1, 2, 3])
    t, q = frames.to_quat_abb(T)
    assert np.allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)])
    assert np.allclose(t, [1, 2, 3])
    assert np.allclose(frames.from_quat_abb(t, -q), T)  # q and -q are the same rotation


def test_euler_round_trip_and_point_mapping():
    T = frames.from_euler_deg([100, 0, 50], [90, 0, 0])  # ZYX: yaw 90 degrees
    assert np.allclose(frames.apply(T, np.array([[1.0, 0, 0]])), [[100, 1, 50]])
    t, e = frames.to_euler_deg(T)
    assert np.allclose(e, [90, 0, 0]) and np.allclose(t, [100, 0, 50])


def test_pose_interpolator_rejects_out_of_range_and_bad_stamps():
    T = np.stack([np.eye(4), np.eye(4)])
    interp = frames.PoseInterpolator(np.array([0.0, 1.0]), T)
    with pytest.raises(ValueError, match="outside"):
        interp(np.array([1.5]))
    with pytest.raises(ValueError, match="increasing"):
        frames.PoseInterpolator(np.array([1.0, 1.0]), T)


def test_look_at_points_z_at_target():
    T = frames.look_at([0, 0, 100], [30, 40, 0])
    z = T[:3, 2]
    d = np.array([30, 40, -100.0])
    assert np.allclose(z, d / np.linalg.norm(d))
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3))


def test_rotation_between_maps_a_onto_b_including_antiparallel():
    for a, b in [([0, 0, 1], [0, 1, 0]), ([0, 0, 1], [0, 0, -1]), ([1, 2, 3], [1, 2, 3])]:
        R = frames.rotation_between(a, b)
        bn = np.asarray(b, float) / np.linalg.norm(b)
        assert np.allclose(R.apply(np.asarray(a, float) / np.linalg.norm(a)), bn, atol=1e-9)
