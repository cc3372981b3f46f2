"""One stream per sensor: the stream guard alone, and the per-stream verdict."""

import numpy as np

from dm2.cli.outcome import EXIT_MISSED, EXIT_OK, duplicate_source_lines, stream_verdicts
from dm2.core.messages import COUNTER_MODULO, Profile, RobotState
from dm2.live.streams import COUNTER_JUMP, StreamGuard


def _p(sid, counter, t=0.0):
    return Profile(sid, t, counter % COUNTER_MODULO, np.zeros((0, 2)), np.zeros(0, bool),
                   np.zeros(0, np.float32))


def test_a_second_connection_for_a_streaming_sensor_is_dropped_the_first_kept():
    g = StreamGuard(handover_s=1.0)
    kept = [g.admit(_p("S2", k), "profiles 127.0.0.1:5000", 0.01 * k) for k in range(100)]
    forged = [g.admit(_p("S2", 3_000_000 + k), "profiles 127.0.0.1:6000", 0.5 + 0.001 * k)
              for k in range(7)]
    assert all(kept) and not any(forged)
    assert g.dropped == {"duplicate_source": 7} and g.received == {"S2": 100}
    assert g.counters == {}  # the dropped frames never touched the stream's counter
    assert g.report()["duplicate_sources"] == [
        {"sensor": "S2", "source": "profiles 127.0.0.1:6000", "frames_dropped": 7}]
    lines = duplicate_source_lines(g.report())
    assert lines == ["a second source (profiles 127.0.0.1:6000) sent 7 frames for S2, which "
                     "streams from profiles 127.0.0.1:5000: dropped (duplicate_source), the "
                     "first stream kept"]


def test_a_bridge_that_reconnects_after_its_stream_went_silent_takes_it_over():
    g = StreamGuard(handover_s=1.0)
    for k in range(10):
        assert g.admit(_p("S1", k), "profiles a:1", 0.01 * k)
    assert g.admit(_p("S1", 0), "profiles a:2", 0.09 + 1.5)  # 1.5 s silent, counter restarts
    assert not g.admit(_p("S1", 11), "profiles a:1", 0.09 + 1.6)  # the old one is now second
    assert g.report()["sources"] == {"S1": "profiles a:2"}
    assert g.counters == {} and g.dropped == {"duplicate_source": 1}


def test_counter_jumps_and_backward_steps_are_counted_not_dropped():
    g = StreamGuard()
    counters = [10, 11, 12, 12 + COUNTER_JUMP, 13 + COUNTER_JUMP + 1,  # 1 jump (+1000 is fine)
                5, 6,  # 1 backwards, then on from there
                COUNTER_MODULO - 2, 0, 1]  # far ahead is behind modulo; then the wrap
    assert all(g.admit(_p("S3", c), "x", 0.0) for c in counters)
    assert g.counters == {"counter_backwards": 2}
    g2 = StreamGuard()
    assert all(g2.admit(_p("S3", c), "x", 0.0) for c in [10, 11, 12 + COUNTER_JUMP + 1, 3_000_000])
    assert g2.counters == {"counter_jump": 2} and g2.dropped == {}


def test_robot_states_are_counted_on_their_stream():
    g = StreamGuard()
    T = np.eye(4)
    assert g.admit(RobotState(0.0, 0, np.zeros(6), T), "egm", 0.0)
    assert g.received == {"robot": 1}


def test_a_profiler_that_lost_more_than_its_share_fails_the_run_by_name():
    streams = {"robot": {"received": 9885, "kept": 9885, "lost_share": 0.0},
               "S1": {"received": 380, "kept": 380, "lost_share": 0.0},
               "S3": {"received": 1123, "kept": 783, "lost_share": round(1 - 783 / 1123, 4)}}
    code, lines = stream_verdicts(streams, 0.25)
    assert code == EXIT_MISSED
    assert lines == ["stream S3 lost 30% of its profiles (340 of 1,123; at most 25% allowed by "
                     "monitor.gates.max_lost_share): its results are not trustworthy"]
    streams["S3"] = {"received": 1123, "kept": 1100, "lost_share": round(1 - 1100 / 1123, 4)}
    assert stream_verdicts(streams, 0.25) == (EXIT_OK, [])


def test_a_bridge_whose_link_dropped_hands_its_sensors_to_its_reconnection_at_once():
    g = StreamGuard(handover_s=1.0)
    for k in range(10):
        assert g.admit(_p("S1", k), "profiles a:1", 0.001 * k)
    g.source_closed("profiles a:1")
    assert g.admit(_p("S1", 10), "profiles a:2", 0.011)  # 1 ms later, the old one closed
    assert g.dropped == {} and g.counters == {} and g.report()["sources"] == {"S1": "profiles a:2"}
