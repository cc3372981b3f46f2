"""The plausibility gates alone: seeding, one outlier, lasting steps, pose limits."""

import numpy as np
import pytest

from dm2.core.config import InputGateConfig
from dm2.core.messages import LayerMark, RobotState
from dm2.fusion.gates import InputGates

DT = 0.004


def _state(t, x_mm=1200.0, q=0.1, seq=0):
    T = np.eye(4)
    T[:3, 3] = (x_mm, 0.0, 900.0)
    return RobotState(t, seq, np.full(6, q), T)


def _feed(gates, stamps, arrivals=None):
    out = []
    for k, t in enumerate(stamps):
        arr = None if arrivals is None else arrivals[k]
        out += [m.stamp_s for m, _ in gates.admit(_state(t, seq=k), arr)]
    return out + [m.stamp_s for m, _ in gates.flush()]


def test_a_bad_first_stamp_does_not_seed_the_band():
    stamps = [5000.0] + [10.0 + DT * k for k in range(100)]
    g = InputGates()
    assert _feed(g, stamps) == pytest.approx(stamps[1:])
    assert g.dropped == {"implausible_stamp": 1}


def test_one_outlier_costs_one_message_either_way():
    stamps = [10.0 + DT * k for k in range(500)]
    stamps[200] += 1000.0
    stamps[300] -= 1000.0
    g = InputGates()
    got = _feed(g, stamps)
    assert len(got) == 498 and g.dropped == {"implausible_stamp": 2} and g.steps == []


@pytest.mark.parametrize("step", [-5.0, 5.0])
def test_a_replayed_lasting_step_is_resynced_after_a_second_of_its_stamps(step):
    """No host time in a replay: a step back continues the stamps where they were; a step
    forward may be a pause of the recording and is taken as it is. Nothing is lost."""
    n = 1000
    stamps = [10.0 + DT * k + (step if k >= 400 else 0.0) for k in range(n)]
    g = InputGates()
    got = _feed(g, stamps)
    assert len(got) == n and not g.dropped.get("implausible_stamp")
    (s,) = g.steps
    assert s["step_s"] == pytest.approx(step, abs=1e-9) and s["held"] == 251
    if step < 0:
        assert np.all(np.diff(got) > 0)  # continuous: every stamp after the last
        assert got[-1] == pytest.approx(10.0 + DT * (n - 1), abs=1e-9)
    else:
        assert got == pytest.approx(stamps)


def test_live_arrival_times_let_a_pause_through_but_not_a_jump():
    stamps = [10.0 + DT * k for k in range(50)] + [40.0 + DT * k for k in range(50)]
    arrivals = list(stamps)  # a 30 s pause in host time as well: no step
    g = InputGates()
    assert len(_feed(g, stamps, arrivals)) == 100 and g.steps == []
    arrivals = [0.001 * k for k in range(100)]  # host time runs on: the 30 s are a jump
    g = InputGates()
    assert len(_feed(g, stamps, arrivals)) == 50
    assert g.dropped == {"implausible_stamp": 50} and g.steps == []  # 0.2 s: not confirmed


def test_poses_outside_the_workspace_limits_or_speed_are_dropped():
    g = InputGates(InputGateConfig())
    t = [10.0 + DT * k for k in range(20)]
    msgs = [_state(tk, x_mm=1200.0 + 0.1 * k, seq=k) for k, tk in enumerate(t)]
    msgs[5] = _state(t[5], x_mm=1e12)  # out of the workspace
    msgs[8] = _state(t[8], q=np.radians(1e300))  # beyond every joint limit
    msgs[12] = _state(t[12], x_mm=1600.0)  # 400 mm in 4 ms
    kept = [m for msg in msgs for m, _ in g.admit(msg)] + [m for m, _ in g.flush()]
    assert [m.seq for m in kept] == [k for k in range(20) if k not in (5, 8, 12)]
    assert g.dropped == {"implausible_pose": 3}


def test_layer_marks_ride_on_the_robot_clock():
    g = InputGates()
    for k in range(10):
        g.admit(_state(10.0 + DT * k, seq=k))
    assert [m for m, _ in g.admit(LayerMark(10.02, 1))] == [LayerMark(10.02, 1)]
    assert g.admit(LayerMark(9000.0, 2)) == [] and g.dropped == {"implausible_stamp": 1}


def test_a_burst_of_forged_stamps_is_no_clock_step():
    """Three stamps 1e9, 1e9+0.5 and 1e9+1.0 s arriving within 2 ms of host time span a
    second of stamps: live, the host clock disagrees, so they stay dropped and the source's
    clock is never re-synced to them; the stream goes on untouched."""
    stamps = [10.0 + DT * k for k in range(300)]
    arrivals = list(stamps)
    forged = [1e9, 1e9 + 0.5, 1e9 + 1.0]
    stamps[150:150] = forged
    arrivals[150:150] = [arrivals[149] + 0.001 * i for i in range(3)]
    g = InputGates()
    got = _feed(g, stamps, arrivals)
    assert got == pytest.approx([10.0 + DT * k for k in range(300)])
    assert g.dropped == {"implausible_stamp": 3} and g.steps == []


def test_a_live_step_the_host_clock_agrees_with_is_resynced():
    """The same second of stepped stamps arriving over a second of host time is a step."""
    n = 600
    stamps = [10.0 + DT * k + (1e6 if k >= 300 else 0.0) for k in range(n)]
    arrivals = [10.0 + DT * k for k in range(n)]
    g = InputGates()
    got = _feed(g, stamps, arrivals)
    (s,) = g.steps
    assert s["step_s"] == pytest.approx(1e6, abs=1e-6) and s["held"] == 251
    assert len(got) == n  # the held second came back: nothing lost


def test_forged_stamps_trickled_slower_than_the_host_clock_are_no_step():
    """A second of stamps spread over 5 s of host time (stamp_rate_max 2: at most 2.5 s of
    stamps in it) disagrees with the host clock: all dropped, no re-sync."""
    g = InputGates()
    arrivals = [10.0 + DT * k for k in range(10)]
    _feed(g, [10.0 + DT * k for k in range(10)], arrivals)
    forged = [1e9 + 0.1 * k for k in range(11)]
    got = _feed(g, forged, [20.0 + 0.5 * k for k in range(11)])
    assert got == [] and g.steps == [] and g.dropped == {"implausible_stamp": 11}
