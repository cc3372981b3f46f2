"""Bad input survived: each class injected into a twin stream; the run goes on and counts it.

Every test feeds the live runner's processing path (clock alignment, recording, monitoring
session) and compares with the clean stream's result: the exact extra drops by reason.
"""

import dataclasses

import numpy as np
import pytest

from dm2.core.messages import COUNTER_MODULO, Profile, RobotState
from dm2.live.config import load_cell_file
from dm2.live.runner import LiveRunner

DURATION_S = 5.0


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    from dm2.core.config import load_scenario
    from scenarios import resolve_scenario
    from twin.stream.serve import write_cell_files
    from twin.stream.simulate import Simulation

    sc = load_scenario(resolve_scenario("pad")).model_copy(update={"duration_s": DURATION_S})
    sim = Simulation(sc)
    msgs = list(sim.messages())
    cell_path = write_cell_files(sim, tmp_path_factory.mktemp("cell"))
    return load_cell_file(cell_path), msgs


def run(cell, msgs, tmp_path, arrivals=None, record=False):
    runner = LiveRunner(cell, tmp_path / "out", record=record)
    for k, m in enumerate(msgs):
        runner.process(m, "test", m.stamp_s if arrivals is None else arrivals[k])
    runner.finish()
    return runner


@pytest.fixture(scope="module")
def baseline(twin, tmp_path_factory):
    cell, msgs = twin
    r = run(cell, msgs, tmp_path_factory.mktemp("base"))
    return r.analysis.dropped, r.analysis.fusion.profiles_fused, len(r.analysis.tracks)


def fused_profiles(msgs, t0=1.5, t1=DURATION_S - 0.5, min_valid=100):
    """Profiles well inside the stream that the clean run fuses (many valid points)."""
    return [i for i, m in enumerate(msgs) if isinstance(m, Profile) and t0 < m.stamp_s < t1
            and m.valid.sum() >= min_valid]


def extra(dropped, base):
    return {k: v - base.get(k, 0) for k, v in dropped.items() if v != base.get(k, 0)}


def test_nan_and_out_of_range_points(twin, baseline, tmp_path):
    cell, msgs = twin
    msgs = list(msgs)
    idx = fused_profiles(msgs)[:6]
    for i in idx[:3]:  # 10 points flagged valid but NaN
        p = msgs[i]
        xz = p.xz_S.copy()
        on = np.flatnonzero(p.valid)[:10]
        xz[on] = np.nan
        msgs[i] = dataclasses.replace(p, xz_S=xz)
    for i in idx[3:]:  # 7 points 100 m down the laser line
        p = msgs[i]
        xz = p.xz_S.copy()
        xz[np.flatnonzero(p.valid)[:7], 1] = 1e5
        msgs[i] = dataclasses.replace(p, xz_S=xz)
    r = run(cell, msgs, tmp_path)
    assert extra(r.analysis.dropped, baseline[0]) == {"nan_points": 30, "out_of_range": 21}
    assert r.analysis.fusion.profiles_fused == baseline[1]


def test_empty_profiles_duplicates_late_messages(twin, baseline, tmp_path):
    cell, msgs = twin
    msgs = list(msgs)
    idx = fused_profiles(msgs)
    out = []
    for k, m in enumerate(msgs):
        out.append(m)
        if k in idx[:4]:  # an empty profile with a fresh counter right after
            out.append(Profile(m.sensor_id, m.stamp_s + 0.001, (m.counter + 500) % COUNTER_MODULO,
                               np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0, np.float32)))
        if k in idx[10:16]:  # the same profile twice
            out.append(m)
        if k in idx[20:23]:  # a message 2 s older than the stream
            out.append(dataclasses.replace(m, stamp_s=m.stamp_s - 2.0,
                                           counter=(m.counter + 900) % COUNTER_MODULO))
    r = run(cell, out, tmp_path)
    assert extra(r.analysis.dropped, baseline[0]) == {"empty_profile": 4,
                                                      "duplicate_counter": 6, "late_message": 3}
    assert r.analysis.fusion.profiles_fused == baseline[1]


def test_out_of_order_within_window_loses_nothing(twin, baseline, tmp_path):
    cell, msgs = twin
    rng = np.random.default_rng(5)
    order = np.argsort([m.stamp_s + rng.uniform(0, 0.15) for m in msgs], kind="stable")
    shuffled = [msgs[i] for i in order]
    assert shuffled != list(msgs)
    r = run(cell, shuffled, tmp_path)
    assert r.analysis.dropped == baseline[0]
    assert r.analysis.fusion.profiles_fused == baseline[1]


def test_counter_wrap_is_not_a_duplicate(twin, baseline, tmp_path):
    cell, msgs = twin
    start = {"S1": COUNTER_MODULO - 7, "S2": COUNTER_MODULO - 3, "S3": COUNTER_MODULO - 11}
    out = []
    for m in msgs:
        if isinstance(m, Profile):
            m = dataclasses.replace(m, counter=(start[m.sensor_id] + m.counter) % COUNTER_MODULO)
        out.append(m)
    r = run(cell, out, tmp_path)
    assert r.analysis.dropped == baseline[0]
    assert r.analysis.fusion.profiles_fused == baseline[1]


def test_clock_skew_and_drift_are_aligned(twin, baseline, tmp_path):
    cell, msgs = twin
    out, arrivals = [], []
    for m in msgs:
        arrivals.append(m.stamp_s)  # host clock = robot clock here
        if isinstance(m, Profile):  # profiler clock 3 s ahead, running 200 ppm fast
            m = dataclasses.replace(m, stamp_s=3.0 + m.stamp_s * (1 + 200e-6))
        out.append(m)
    r = run(cell, out, tmp_path, arrivals)
    assert r.analysis.dropped == baseline[0]
    assert r.analysis.fusion.profiles_fused == baseline[1]
    assert set(r.aligner.engaged) == {"S1", "S2", "S3"}
    assert r.aligner.correction_s["S1"] == pytest.approx(3.0 + 200e-6 * DURATION_S, abs=0.02)


def test_sensor_and_pose_dropout(twin, baseline, tmp_path):
    cell, msgs = twin
    gap = (2.0, 2.3)  # robot states missing: profiles inside cannot be posed
    silent = (2.5, 4.2)  # S2 silent for longer than max_sensor_gap_s (1 s)
    kept_states = [m.stamp_s for m in msgs if isinstance(m, RobotState)
                   and not gap[0] <= m.stamp_s < gap[1]]
    before = max(t for t in kept_states if t < gap[0])
    after = min(t for t in kept_states if t >= gap[1])
    fused = set(fused_profiles(msgs, 0.0, DURATION_S, 1))
    out, expect_gap = [], 0
    for k, m in enumerate(msgs):
        if isinstance(m, RobotState) and gap[0] <= m.stamp_s < gap[1]:
            continue
        if isinstance(m, Profile) and m.sensor_id == "S2" and silent[0] <= m.stamp_s < silent[1]:
            continue
        if isinstance(m, Profile) and k in fused and before < m.stamp_s < after:
            expect_gap += 1
        out.append(m)
    assert expect_gap > 3
    r = run(cell, out, tmp_path)
    assert extra(r.analysis.dropped, baseline[0]) == {"pose_gap": expect_gap}
    assert r.analysis.events == {"sensor_dropout": 1}
    assert r.analysis.fusion.profiles_fused > 0


def test_the_run_freezes_the_heap_out_of_the_collector_and_thaws_it(twin, tmp_path):
    """During a live run the objects that existed at its start are out of the cyclic
    collector's view (a full collection over them stalls every thread); afterwards they are
    back in it."""
    import gc

    cell, msgs = twin
    runner = LiveRunner(cell, tmp_path / "out", record=False)
    seen = []
    get = runner.inbox.get

    def spy(timeout_s):
        seen.append(gc.get_freeze_count())
        if len(seen) == 3:  # the stream of a few messages, then quiet: the run ends
            for m in msgs[:50]:
                runner.inbox.put(m, "test", m.stamp_s)
        return get(timeout_s=timeout_s)

    runner.inbox.get = spy
    before = gc.get_freeze_count()
    runner.run(idle_stop_s=0.2, max_duration_s=5.0)
    assert min(seen) > before + 10_000  # frozen for the whole loop
    assert gc.get_freeze_count() == before
    assert runner.messages_in == 50


def _robot_indices(msgs, t0=1.5, t1=DURATION_S - 0.5):
    return [i for i, m in enumerate(msgs) if isinstance(m, RobotState) and t0 < m.stamp_s < t1]


def test_one_datagram_or_frame_stamped_1000_s_ahead_costs_that_message(twin, baseline, tmp_path):
    cell, msgs = twin
    out = list(msgs)
    i_state = _robot_indices(out)[100]
    i_prof = fused_profiles(out)[5]
    out[i_state] = dataclasses.replace(out[i_state], stamp_s=out[i_state].stamp_s + 1000.0)
    out[i_prof] = dataclasses.replace(out[i_prof], stamp_s=out[i_prof].stamp_s + 1000.0)
    r = run(cell, out, tmp_path, [m.stamp_s for m in msgs])  # arriving on time
    assert extra(r.analysis.dropped, baseline[0]) == {"implausible_stamp": 2}
    assert r.analysis.fusion.profiles_fused == baseline[1] - 1
    assert r.gates.steps == []


def test_a_first_stamp_far_off_does_not_seed_the_band(twin, baseline, tmp_path):
    cell, msgs = twin
    out = list(msgs)
    first = next(i for i, m in enumerate(out) if isinstance(m, RobotState))
    out[first] = dataclasses.replace(out[first], stamp_s=out[first].stamp_s + 1000.0)
    r = run(cell, out, tmp_path, [m.stamp_s for m in msgs])
    # the first state only: the stream's first profile, which only it bracketed, cannot be
    # posed without it (pose_gap); everything after is untouched
    assert extra(r.analysis.dropped, baseline[0]) == {"implausible_stamp": 1, "pose_gap": 1}
    assert r.analysis.fusion.profiles_fused == baseline[1] - 1


def test_absurd_but_finite_poses_are_dropped_and_counted(twin, baseline, tmp_path):
    cell, msgs = twin
    out = list(msgs)
    idx = _robot_indices(out)
    far = out[idx[50]].T_B_F.copy()
    far[:3, 3] = (1e12, 0.0, 0.0)  # 1e12 mm out
    out[idx[50]] = dataclasses.replace(out[idx[50]], T_B_F=far)
    wild = out[idx[300]].joints_rad.copy()
    wild[2] = np.radians(1e300)  # joints at 1e300 degrees
    out[idx[300]] = dataclasses.replace(out[idx[300]], joints_rad=wild)
    jump = out[idx[500]].T_B_F.copy()
    jump[:3, 3] += (400.0, 0.0, 0.0)  # inside the workspace, but 400 mm in 4 ms: 100 m/s
    out[idx[500]] = dataclasses.replace(out[idx[500]], T_B_F=jump)
    r = run(cell, out, tmp_path)
    assert extra(r.analysis.dropped, baseline[0]) == {"implausible_pose": 3}
    assert r.analysis.fusion.profiles_fused == baseline[1]
    assert len(r.analysis.tracks) == baseline[2]


@pytest.mark.parametrize("step", [-5.0, 5.0])
def test_a_lasting_clock_step_is_resynced_within_a_second(twin, baseline, tmp_path, step):
    """The controller's clock steps 5 s back (or ahead) at 2.5 s while host time runs on:
    re-synced after one second of process time, at most that second lost, no track created."""
    cell, msgs = twin
    t_step = 2.5
    out, arrivals = [], []
    for m in msgs:
        arrivals.append(m.stamp_s)
        if not isinstance(m, Profile) and m.stamp_s >= t_step:
            m = dataclasses.replace(m, stamp_s=m.stamp_s + step)
        out.append(m)
    r = run(cell, out, tmp_path, arrivals)
    (s,) = r.gates.steps
    assert s["source"] == "robot" and s["step_s"] == pytest.approx(step, abs=0.01)
    assert r.analysis.dropped.get("implausible_stamp", 0) == 0  # the held second came back
    lost = baseline[1] - r.analysis.fusion.profiles_fused
    per_s = baseline[1] / DURATION_S
    assert 0 <= lost <= 1.2 * per_s  # at most about the second before the re-sync
    assert len(r.analysis.tracks) == baseline[2]


def test_a_datagram_stamped_1e12_s_ahead_leaves_the_recording_whole(twin, baseline, tmp_path):
    """A stamp that does not fit a ROS Time is one implausible message: the recording holds
    every other state and the run goes on."""
    from dm2.io.recording import read_recording

    cell, msgs = twin
    out = list(msgs)
    i = _robot_indices(out)[200]
    out[i] = dataclasses.replace(out[i], stamp_s=out[i].stamp_s + 1e12)
    r = run(cell, out, tmp_path, [m.stamp_s for m in msgs], record=True)
    assert extra(r.analysis.dropped, baseline[0]) == {"implausible_stamp": 1}
    assert r.analysis.fusion.profiles_fused == baseline[1]
    recorded = [m for m in read_recording(r.recording_path).messages()
                if isinstance(m, RobotState)]
    assert len(recorded) == sum(isinstance(m, RobotState) for m in msgs) - 1
