"""ROS 2 messages of recordings: the hand-written PointCloud2 encoder gives rosbags' own bytes,
and every message decodes back to the values encoded (units, frames, invalid points)."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.core.frames import from_euler_deg
from dm2.io import ros_messages as ros
from dm2.io.cdr import CdrError, serialize

STAMP_NS = 1_712_345_678_123_456_789


@pytest.mark.parametrize("frame_id", ["", "S1", "S12", "abc", "profiler_left"])
@pytest.mark.parametrize("n", [0, 1, 3, 1280])
def test_cloud_template_is_rosbags_serialization(frame_id, n):
    rng = np.random.default_rng(n)
    xz = np.column_stack([rng.uniform(-40, 40, n), rng.uniform(80, 160, n)])
    valid = rng.random(n) > 0.2
    inten = rng.uniform(0, 1, n).astype(np.float32)
    data = ros.encode_cloud(STAMP_NS, frame_id, xz, valid, inten)
    pts = ros._cloud_points(xz, valid, inten)
    assert data == serialize(ros.cloud_msg(STAMP_NS, frame_id, pts), ros.POINTCLOUD2)
    ns, fid, xz_back, valid_back, inten_back = ros.decode_cloud(data)
    assert (ns, fid) == (STAMP_NS, frame_id)
    np.testing.assert_array_equal(valid_back, valid)
    np.testing.assert_allclose(xz_back[valid], xz[valid], atol=1e-4)  # float32 metres
    assert np.isnan(xz_back[~valid]).all()
    np.testing.assert_array_equal(inten_back, inten)


@pytest.mark.parametrize("seed", range(5))
def test_joint_state_template_is_rosbags_serialization(seed):
    rng = np.random.default_rng(seed)
    stamp = int(rng.integers(0, 2**31 * 10**9))
    joints = rng.uniform(-3.2, 3.2, 6)
    data = ros.encode_joint_state(stamp, joints)
    assert data == serialize(ros._joint_state_msg(stamp, joints), ros.JOINTSTATE)
    ns, names, pos = ros.decode_joint_state(data)
    assert ns == stamp and names == list(ros.JOINT_NAMES)
    np.testing.assert_array_equal(pos, joints)


def test_cloud_point_in_metres_in_the_laser_plane():
    data = ros.encode_cloud(0, "S1", np.array([[12.5, 140.0]]), np.array([True]),
                            np.array([0.25], np.float32))
    np.testing.assert_array_equal(np.frombuffer(data[-17:-1], "<f4"),
                                  np.array([0.0125, 0.0, 0.14, 0.25], np.float32))


def test_joint_tf_and_layer_mark_decode_to_what_was_encoded():
    joints = np.array([0.1, -0.2, 0.3, -0.4, 0.5, -0.6])
    ns, names, pos = ros.decode_joint_state(ros.encode_joint_state(STAMP_NS, joints))
    assert ns == STAMP_NS
    assert names == list(ros.JOINT_NAMES)
    np.testing.assert_array_equal(pos, joints)
    T = from_euler_deg([1300.0, -20.0, 900.0], [10.0, 170.0, -35.0])
    ((ns, parent, child, T_back),) = ros.decode_tf(ros.encode_tf([(STAMP_NS, "B", "F", T)]))
    assert (ns, parent, child) == (STAMP_NS, "B", "F")
    np.testing.assert_allclose(T_back, T, atol=1e-9)
    assert ros.decode_layer_mark(ros.encode_layer_mark(STAMP_NS, 7)) == (STAMP_NS, 7)


def test_truncated_cloud_raises_cdr_error():
    data = ros.encode_cloud(0, "S1", np.zeros((3, 2)), np.ones(3, bool), np.zeros(3, np.float32))
    with pytest.raises(CdrError, match="PointCloud2"):
        ros.decode_cloud(data[:-20])
