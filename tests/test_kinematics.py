"""Forward / inverse kinematics of the arm: known poses, round trips, reach failures."""

import numpy as np
import pytest

from dm2.core import frames
from twin.cell import kinematics as kin


def test_fk_calibration_pose_and_axis_one():
    T = kin.fk(np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [kin.A1 + kin.D4 + kin.D6, 0.0, kin.D1 + kin.A2 + kin.A3])
    np.testing.assert_allclose(T[:3, 2], [1.0, 0.0, 0.0], atol=1e-15)  # flange z along the forearm
    np.testing.assert_allclose(T[:3, 0], [0.0, 0.0, -1.0], atol=1e-15)
    T90 = kin.fk(np.deg2rad([90, 0, 0, 0, 0, 0]))
    np.testing.assert_allclose(T90[:3, 3], [0.0, 1270.0, 1570.0], atol=1e-9)
    # Axis 2 forward by 90 deg lays the upper arm along +x: wrist drops by a2, moves out by a2.
    T2 = kin.fk(np.deg2rad([0, 90, 0, 0, 0, 0]))
    np.testing.assert_allclose(T2[:3, 3], [kin.A1 + kin.A2 + kin.A3, 0.0,
                                           kin.D1 - kin.D4 - kin.D6], atol=1e-9)


def test_ik_round_trip_recovers_joints_and_pose():
    rng = np.random.default_rng(3)
    lo, hi = kin.JOINT_LIMITS_RAD[:, 0], kin.JOINT_LIMITS_RAD[:, 1]
    n = 0
    while n < 300:
        q = rng.uniform(lo, hi)
        q[3], q[5] = rng.uniform(-3.0, 3.0, 2)
        if abs(np.sin(q[4])) < 0.2 or abs(q[2] - (np.arctan2(kin.A3, kin.D4) - np.pi / 2)) < 0.2:
            continue  # keep away from wrist and elbow singularities where branches meet
        n += 1
        T = kin.fk(q)
        q_ik = kin.ik(T, q + rng.normal(0.0, 0.02, 6))
        np.testing.assert_allclose(q_ik, q, atol=1e-8)
        dt, dr = frames.pose_error(kin.fk(q_ik), T)
        assert dt < 1e-8 and dr < 1e-10


def test_ik_picks_branch_nearest_seed_and_unwraps_wrist():
    q = np.deg2rad([10.0, 30.0, -20.0, 40.0, -60.0, 30.0])
    T = kin.fk(q)
    q_flip = kin.ik(T, np.deg2rad([10.0, 30.0, -20.0, 40.0 - 180.0, 60.0, 30.0 - 180.0]))
    assert q_flip[4] > 0  # the wrist-flipped branch, same pose
    assert frames.pose_error(kin.fk(q_flip), T)[0] < 1e-8
    q_turn = kin.ik(T, q + np.array([0, 0, 0, 2 * np.pi, 0, -2 * np.pi]))
    np.testing.assert_allclose(q_turn[[3, 5]], q[[3, 5]] + [2 * np.pi, -2 * np.pi], atol=1e-9)


def test_ik_out_of_reach_and_singularity_raise():
    T = kin.fk(np.deg2rad([0, 30, 0, 0, -60, 0]))
    T_far = T.copy()
    T_far[:3, 3] = [4000.0, 0.0, 500.0]
    with pytest.raises(kin.ReachError, match="out of reach"):
        kin.ik(T_far, np.zeros(6))
    T_sing = kin.fk(np.deg2rad([0, 30, 0, 0, 1.0, 0]))
    with pytest.raises(kin.ReachError, match="singularity"):
        kin.ik(T_sing, np.deg2rad([0, 30, 0, 0, 1.0, 0]))


def test_ik_track_follows_a_stream_and_reports_failing_sample():
    q0 = np.deg2rad([0.0, 24.0, 1.0, 0.0, -64.0, 0.0])
    qs = q0 + np.linspace(0.0, 1.0, 200)[:, None] * np.deg2rad([20, 10, -10, 90, 30, -120])
    Q, code, k = kin.ik_track(kin.fk(qs), q0, dt_s=0.004)
    assert code == kin.OK and k == -1
    np.testing.assert_allclose(Q, qs, atol=1e-8)
    T = kin.fk(qs)
    T[150:, 0, 3] += 5000.0
    _, code, k = kin.ik_track(T, q0)
    assert code == kin.OUT_OF_REACH and k == 150
    # Too fast: 200 samples 1 ms apart sweeping axis 6 by 120 deg is 600 deg/s > 360 deg/s.
    _, code, k = kin.ik_track(kin.fk(qs), q0, dt_s=0.001)
    assert code == kin.JOINT_SPEED and k == 1
