"""The live recorder thread: everything queued reaches the file, bad stamps are refused at once,
a full queue drops and counts instead of blocking; the clock aligner's Theil-Sen kernel."""

import numpy as np
import pytest

from dm2.core.messages import MessageError, Profile, RobotState
from dm2.io.recording import read_recording
from dm2.live.clock import _theil_sen_at
from dm2.live.recorder import LiveRecorder, RecorderThread


def _state(k: int) -> RobotState:
    T = np.eye(4)
    T[:3, 3] = (k, 2.0 * k, 3.0)
    return RobotState(0.004 * k, k, np.full(6, 0.01 * k), T)


def test_recorder_thread_writes_every_message_in_order(tmp_path):
    rec = RecorderThread(LiveRecorder(tmp_path / "r.mcap", chunk_s=0.2), max_wait_s=0.01)
    for k in range(500):
        rec.write(_state(k))
    xz = np.column_stack([np.linspace(-5, 5, 7), np.full(7, 30.0)])
    rec.write(Profile("S2", 1.0, 77, xz, np.ones(7, bool), np.full(7, 0.5)))
    with pytest.raises(MessageError, match="stamps >= 0"):
        rec.write(RobotState(-1.0, 1, np.zeros(6), np.eye(4)))
    assert rec.close() == tmp_path / "r.mcap"
    msgs = list(read_recording(tmp_path / "r.mcap").messages())
    states = [m for m in msgs if isinstance(m, RobotState)]
    assert [s.seq for s in states] == list(range(500))
    np.testing.assert_allclose(states[123].T_B_F[:3, 3], (123, 246, 3))
    (p,) = [m for m in msgs if isinstance(m, Profile)]
    assert (p.sensor_id, p.counter) == ("S2", 77)
    np.testing.assert_allclose(p.xz_S, xz, atol=1e-5)
    assert rec.written == 501 and rec.dropped == {}


def test_recorder_thread_full_queue_drops_and_counts(tmp_path):
    rec = RecorderThread(LiveRecorder(tmp_path / "q.mcap"), maxsize=10, max_wait_s=5.0)
    for k in range(25):  # the thread sleeps for up to 5 s: the queue fills
        rec.write(_state(k))
    assert rec.dropped == {"recording_queue_full": 15}
    rec.close()
    assert len([m for m in read_recording(tmp_path / "q.mcap").messages()
                if isinstance(m, RobotState)]) == 10


def test_theil_sen_recovers_a_drifting_skew_despite_outliers():
    t = np.linspace(0.0, 1.4, 15)
    k = 0.25 + 2e-3 * t
    k[[3, 9]] += (0.4, -0.3)  # two late arrivals
    assert _theil_sen_at(t, k, 2.0) == pytest.approx(0.25 + 2e-3 * 2.0, abs=1e-12)
    assert _theil_sen_at(np.zeros(3), np.array([0.1, 0.2, 0.3]), 5.0) == pytest.approx(0.2)


def _aligned(clock, stamp_s, skew_s=0.0):
    """One profile of S1 arriving at ``stamp_s`` (host clock = robot clock), stamped with
    ``skew_s`` added; the stamps released."""
    p = Profile("S1", stamp_s + skew_s, 1, np.zeros((2, 2)), np.ones(2, bool), np.ones(2))
    return [q.stamp_s for q in clock.profile(p, stamp_s)]


def test_clock_releases_in_band_profiles_at_once_and_waits_out_of_band():
    from dm2.live.clock import ClockAligner

    clock = ClockAligner(tolerance_s=0.05, min_samples=3)
    for k in range(100):
        clock.pose(0.004 * k, 0.004 * k)
    # a synchronised sensor: the first profile is released unchanged, not held for 3 samples
    assert _aligned(clock, 0.1) == [0.1]
    assert _aligned(clock, 0.2) == [0.2]
    assert "S1" not in clock.engaged
    # a sensor 3 s ahead waits for min_samples, then all are released corrected
    clock = ClockAligner(tolerance_s=0.05, min_samples=3)
    for k in range(100):
        clock.pose(0.004 * k, 0.004 * k)
    assert _aligned(clock, 0.1, 3.0) == []
    assert _aligned(clock, 0.2, 3.0) == []
    assert _aligned(clock, 0.3, 3.0) == pytest.approx([0.1, 0.2, 0.3])
    assert clock.engaged == {"S1"}


def _replay(clock, events):
    """Feed ``(arrival, kind, stamp, skew)`` events in arrival order (poses first on ties);
    ``(arrival, released stamps)`` of the profiles."""
    out = []
    for arrival, kind, stamp, skew in sorted(events, key=lambda e: (e[0], e[1] != "pose")):
        if kind == "pose":
            clock.pose(stamp, arrival)
        else:
            out.append((arrival, _aligned_at(clock, stamp, arrival, skew)))
    return out


def _aligned_at(clock, stamp_s, arrival_s, skew_s):
    p = Profile("S1", stamp_s + skew_s, 1, np.zeros((2, 2)), np.ones(2, bool), np.ones(2))
    return [q.stamp_s for q in clock.profile(p, arrival_s)]


def test_clock_ignores_a_stalled_pose_socket_but_follows_a_lasting_offset():
    from dm2.live.clock import ClockAligner

    # a 10x rehearsal: host time = robot time / 10; the pose socket is not read for 150 ms
    # (host; all states stamped 3.0-4.5 s arrive at once at 0.45 s): the pose clock looks up to
    # 1.5 s behind, the estimate leaves the 0.5 s band, but the profiler's clock is fine
    poses = [(k * 0.0004, "pose", k * 0.004, 0.0) for k in range(2500)]
    poses = [(0.45 if 3.0 <= s < 4.5 else a, kind, s, k) for a, kind, s, k in poses]
    profiles = [(k * 0.01, "profile", k * 0.1, 0.0) for k in range(1, 100)]
    released = _replay(ClockAligner(tolerance_s=0.5), poses + profiles)
    assert [s for _, r in released for s in r] == [k * 0.1 for k in range(1, 100)]
    eager = ClockAligner(tolerance_s=0.5, confirm_s=0.0)  # without the confirmation it engages
    _replay(eager, poses + profiles)
    assert eager.engaged == {"S1"}

    # real time; the profiler's clock jumps 2 s ahead at 5 s and stays there: passed through
    # unchanged for at least confirm_s (1 s; counted from when the running estimate leaves the
    # band, a few samples after the jump), corrected from then on
    clock = ClockAligner(tolerance_s=0.05)
    poses = [(k * 0.004, "pose", k * 0.004, 0.0) for k in range(2500)]
    profiles = [(k * 0.1, "profile", k * 0.1, 2.0 if k >= 50 else 0.0) for k in range(1, 95)]
    for arrival, stamps in _replay(clock, poses + profiles):
        if arrival < 5.0:
            assert stamps == [pytest.approx(arrival)]
        elif arrival < 6.0:
            assert stamps == [pytest.approx(arrival + 2.0)]
        elif arrival > 7.5:
            assert stamps == [pytest.approx(arrival, abs=1e-6)]
    assert clock.engaged == {"S1"}
    assert clock.correction_s["S1"] == pytest.approx(2.0)


def test_recorder_survives_a_stamp_beyond_ros_time_and_one_it_cannot_encode(tmp_path):
    class Picky(LiveRecorder):  # the writer fails on one message after the queue took it
        def write(self, msg):
            if isinstance(msg, RobotState) and msg.seq == 7:
                raise ValueError("stamp does not fit ROS Time")
            super().write(msg)

    rec = RecorderThread(Picky(tmp_path / "h.mcap", chunk_s=0.2), max_wait_s=0.01)
    with pytest.raises(MessageError, match="does not fit a ROS Time"):
        rec.write(RobotState(1e12, 99, np.zeros(6), np.eye(4)))
    for k in range(20):
        rec.write(_state(k))
    rec.close()
    states = [m for m in read_recording(tmp_path / "h.mcap").messages()
              if isinstance(m, RobotState)]
    assert [s.seq for s in states] == [k for k in range(20) if k != 7]
    assert rec.dropped == {"unrecordable_message": 1} and rec.written == 19
