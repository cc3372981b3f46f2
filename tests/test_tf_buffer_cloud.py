"""The tf buffer (chains of dynamic and static edges), PointCloud2 layouts drivers publish, and
de-duplication of profiles that carry no counter."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from dm2.core.frames import make_T
from dm2.core.messages import Profile, RobotState
from dm2.fusion.sync import StreamSync
from dm2.io.pointcloud import CloudError, cloud_xyz, profile_points
from dm2.io.tf_buffer import TfBuffer, TfError


def _edge(t, k):
    """A smooth dynamic edge k at stamp t."""
    R = Rotation.from_rotvec([0.2 * np.sin(t + k), 0.3 * np.cos(0.5 * t), 0.1 * k * t])
    return make_T(R.as_matrix(), [10.0 * k, 5.0 * np.sin(t), 100.0 + t])


def _chain_tree(stamps):
    tf = TfBuffer()
    frames = ["base"] + [f"l{k}" for k in range(1, 7)]
    for t in stamps:
        for k in range(6):
            tf.add(t, frames[k], frames[k + 1], _edge(t, k), static=False)
    T_6_tool = make_T(Rotation.from_euler("x", 90, degrees=True).as_matrix(), [0, 0, 50.0])
    tf.add(0.0, "l6", "tool", T_6_tool, static=True)
    tf.add(0.0, "base", "cam", make_T(None, [1, 2, 3]), static=True)
    tf.finish()
    return tf, T_6_tool


def test_lookup_composes_each_dynamic_edge_interpolated_at_the_stamp():
    stamps = np.arange(0.0, 1.0, 0.004)
    tf, T_6_tool = _chain_tree(stamps[::-1])  # any arrival order
    t = 0.4571
    expect = np.eye(4)
    for k in range(6):  # per-edge SLERP between the bracketing samples, as scipy does it
        i = np.searchsorted(stamps, t)
        t0, t1 = stamps[i - 1], stamps[i]
        E0, E1 = _edge(t0, k), _edge(t1, k)
        R = Slerp([t0, t1], Rotation.from_matrix([E0[:3, :3], E1[:3, :3]]))(t).as_matrix()
        a = (t - t0) / (t1 - t0)
        expect = expect @ make_T(R, (1 - a) * E0[:3, 3] + a * E1[:3, 3])
    expect = expect @ T_6_tool
    got = tf.lookup("base", "tool", t, max_gap_s=0.01)
    np.testing.assert_allclose(got, expect, atol=1e-9)
    # and the inverse direction, through the static sibling "cam"
    T_cam_tool = tf.lookup("cam", "tool", t, max_gap_s=0.01)
    np.testing.assert_allclose(make_T(None, [1, 2, 3]) @ T_cam_tool, expect, atol=1e-9)
    assert tf.dynamic_edges("base", "cam") == []
    assert sorted(tf.dynamic_edges("cam", "tool")) == [("base", "l1"), ("l1", "l2"), ("l2", "l3"),
                                                ("l3", "l4"), ("l4", "l5"), ("l5", "l6")]


def test_lookup_refuses_to_extrapolate_beyond_the_gap():
    stamps = np.concatenate([np.arange(0.0, 0.5, 0.004), np.arange(0.7, 1.0, 0.004)])
    tf, _ = _chain_tree(stamps)
    assert tf.lookup("base", "tool", 0.6, max_gap_s=0.05) is None  # a 0.2 s hole
    assert tf.lookup("base", "tool", 1.2, max_gap_s=0.05) is None  # after the last sample
    assert tf.lookup("base", "tool", 0.998 + 0.004, max_gap_s=0.05) is not None  # held
    assert tf.lookup("base", "tool", 0.3, max_gap_s=0.05) is not None


def test_a_fixed_transform_republished_on_tf_does_not_move():
    tf = TfBuffer()
    T = make_T(Rotation.from_euler("y", 20, degrees=True).as_matrix(), [5.0, 0.0, 1.0])
    for t in np.arange(0.0, 1.0, 0.1):
        tf.add(t, "base", "cam", T, static=False)
        tf.add(t, "base", "arm", make_T(None, [t, 0.0, 0.0]), static=False)
    tf.finish()
    assert tf.dynamic_edges("base", "cam") == [("base", "cam")]
    assert tf.dynamic_edges("arm", "cam", moving_only=True) == [("base", "arm")]
    np.testing.assert_allclose(tf.lookup("base", "cam"), T, atol=1e-12)


def test_tree_errors_name_the_frames():
    tf = TfBuffer()
    tf.add(0.0, "a", "b", np.eye(4), static=True)
    with pytest.raises(TfError, match="'b' has two parents"):
        tf.add(0.0, "c", "b", np.eye(4), static=True)
    tf.add(0.0, "x", "y", np.eye(4), static=True)
    tf.finish()
    with pytest.raises(TfError, match="'a' and 'y' are not connected"):
        tf.lookup("a", "y")
    with pytest.raises(TfError, match="'q' is not in the tf tree"):
        tf.lookup("a", "q")


def _cloud(points, fields, step, height=1, row_pad=0, big=False):
    """A PointCloud2-like object of structured ``points`` (an array already laid out)."""
    width = len(points) // height
    rows = points.tobytes()
    if row_pad:
        n = width * step
        rows = b"".join(rows[r * n:(r + 1) * n] + b"\0" * row_pad for r in range(height))
    return SimpleNamespace(fields=[SimpleNamespace(name=a, offset=b, datatype=c, count=1)
                                   for a, b, c in fields],
                           is_bigendian=big, point_step=step, height=height, width=width,
                           row_step=width * step + row_pad, data=np.frombuffer(rows, np.uint8))


def test_float64_organised_padded_cloud_with_zero_and_nan_points():
    xyz = np.array([[0.01, 0.0, 0.09], [0.0, 0.0, 0.0], [np.nan, 0.0, 0.1], [0.02, 0.0, 0.1],
                    [-0.01, 0.002, 0.08], [0.03, 0.0, 0.11]])
    dt = np.dtype({"names": ["x", "y", "z", "i"], "formats": [">f8", ">f8", ">f8", ">u2"],
                   "offsets": [0, 8, 16, 24], "itemsize": 32})
    pts = np.zeros(6, dt)
    pts["x"], pts["y"], pts["z"], pts["i"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], 65535
    msg = _cloud(pts, [("x", 0, 8), ("y", 8, 8), ("z", 16, 8), ("intensity", 24, 4)], 32,
                 height=2, row_pad=12, big=True)
    got, inten = cloud_xyz(msg)
    np.testing.assert_array_equal(np.isnan(got[:, 0]), [False, True, True, False, False, False])
    np.testing.assert_allclose(got[[0, 3, 5]], xyz[[0, 3, 5]])
    np.testing.assert_allclose(inten, 1.0)
    xz, valid, n_off = profile_points(got)
    assert n_off == 1 and valid.tolist() == [True, False, False, True, False, True]
    np.testing.assert_allclose(xz[0], [10.0, 90.0])


def test_float32_cloud_without_intensity_and_bad_layouts():
    pts = np.array([[0.01, 0.0, 0.1], [0.02, 0.0, 0.1]], "<f4")
    got, inten = cloud_xyz(_cloud(pts, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12))
    np.testing.assert_allclose(got, pts, rtol=1e-7)
    assert inten.tolist() == [0.0, 0.0]
    with pytest.raises(CloudError, match="no field 'y'"):
        cloud_xyz(_cloud(pts, [("x", 0, 7), ("z", 8, 7)], 12))
    with pytest.raises(CloudError, match="datatype 5"):
        cloud_xyz(_cloud(pts, [("x", 0, 5), ("y", 4, 7), ("z", 8, 7)], 12))


def test_profiles_without_counter_are_deduplicated_by_sensor_and_stamp():
    sync = StreamSync(["S1", "S2"], max_pose_gap_s=0.05)
    xz = np.array([[0.0, 90.0], [1.0, 91.0]])

    def prof(sid, t):
        return Profile(sid, t, None, xz, np.ones(2, bool), np.zeros(2, np.float32))

    out = []
    for t in (0.0, 0.04, 0.08):
        out += sync.push(RobotState(t, 0, np.zeros(6), np.eye(4)))
    for msg in (prof("S1", 0.05), prof("S1", 0.05), prof("S2", 0.05), prof("S1", 0.06)):
        out += sync.push(msg)
    out += sync.flush()
    assert sorted((p.profile.sensor_id, p.profile.stamp_s) for p in out) == [
        ("S1", 0.05), ("S1", 0.06), ("S2", 0.05)]
    assert dict(sync.dropped) == {"duplicate_stamp": 1}
