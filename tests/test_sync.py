"""Stream synchronisation: SLERP poses, reorder window, and exact drop counts on bad input."""

from __future__ import annotations

import numpy as np
import pytest
from test_monitor_scene import Scene, make_calibration, raster_run

from dm2.core.config import MonitorConfig, ProcessConfig
from dm2.core.frames import PoseInterpolator, from_euler_deg, pose_error
from dm2.core.messages import Calibration, LayerMark, Profile, RobotState
from dm2.fusion.fusion import TsdfFusion
from dm2.fusion.posebuffer import PoseBuffer
from dm2.fusion.sync import StreamSync


def test_pose_buffer_matches_slerp_and_respects_the_gap():
    rng = np.random.default_rng(4)
    stamps = np.cumsum(rng.uniform(0.002, 0.006, 40))
    poses = np.stack([from_euler_deg(rng.uniform(-500, 500, 3), rng.uniform(-170, 170, 3))
                      for _ in stamps])
    buf = PoseBuffer()
    for i in rng.permutation(len(stamps)):  # arrival order does not matter
        assert buf.add(stamps[i], poses[i])
    assert not buf.add(stamps[3], poses[3])
    q = np.concatenate([rng.uniform(stamps[0], stamps[-1], 50), stamps[[0, 7, -1]]])
    got, ok = buf.poses_at(q, max_gap_s=1.0)
    want = PoseInterpolator(stamps, poses)(q)
    assert ok.all()
    for g, w in zip(got, want, strict=True):
        dt, dr = pose_error(g, w)
        assert dt < 1e-9 and dr < 1e-9
    _, ok = buf.poses_at(np.array([stamps[0] - 0.01, stamps[-1] + 0.01,
                                   0.5 * (stamps[5] + stamps[6])]), max_gap_s=1e-4)
    assert ok.tolist() == [False, False, False]



def test_pose_buffer_in_order_appends_late_arrivals_and_pruning_keep_slerp_exact():
    """In-order poses go straight into the sorted arrays, late ones wait and are merged; queries
    in between, growth past the capacity and pruning past the horizon keep every pose."""
    rng = np.random.default_rng(9)
    stamps = np.cumsum(rng.uniform(0.002, 0.006, 700))
    poses = np.stack([from_euler_deg(rng.uniform(-500, 500, 3), rng.uniform(-170, 170, 3))
                      for _ in stamps])
    order = np.arange(len(stamps))
    for a in range(5, len(order) - 3, 37):  # every 37th pose arrives three places late
        order[a: a + 4] = order[[a + 1, a + 2, a + 3, a]]
    buf = PoseBuffer(horizon_s=0.5, capacity=64)
    interp = PoseInterpolator(stamps, poses)
    for j, i in enumerate(order):
        assert buf.add(stamps[i], poses[i])
        if j % 11 == 10:  # query the newest fully received stretch now and then
            arrived, pending = stamps[order[: j + 1]], stamps[order[j + 1:]]
            if pending.size:  # below the newest pose that has every earlier one beside it
                arrived = arrived[arrived < pending.min()]
            q = arrived.max() - 0.05 * rng.random()
            got, ok = buf.pose_at(q, max_gap_s=1.0)
            dt, dr = pose_error(got, interp(np.array([q]))[0])
            assert ok and dt < 1e-9 and dr < 1e-9
    assert not buf.add(stamps[-2], poses[-2])  # still known: a duplicate
    kept = buf.stamps_s
    assert np.all(np.diff(kept) > 0) and kept[-1] == stamps[-1]
    assert kept[0] >= stamps[-1] - 0.5 - 0.02 and len(kept) < len(stamps)
    got, ok = buf.poses_at(stamps[-100:], max_gap_s=1.0)
    assert ok.all() and np.array_equal(got, poses[-100:])


def input_drops(dropped: dict) -> dict:
    """The drops by the input's faults: without the points the pre-fusion filter takes out
    (dm2.fusion.point_filter judges surfaces, not the stream; the synthetic boxes' sharp edges
    give it a few)."""
    return {k: v for k, v in dropped.items() if not k.startswith("point_filter")}


def _profile(sid, stamp, counter, xz, valid=None):
    xz = np.asarray(xz, float).reshape(-1, 2)
    valid = np.ones(len(xz), bool) if valid is None else valid
    return Profile(sid, stamp, counter, xz, valid, np.zeros(len(xz), np.float32))


def test_stream_sync_counts_each_kind_of_bad_message_exactly():
    sync = StreamSync(["S1"], max_pose_gap_s=0.05, reorder_window_s=0.5)
    eye = np.eye(4)
    for k in range(101):
        sync.push(RobotState(0.01 * k, k, np.zeros(6), eye))
    sync.push(RobotState(0.5, 50, np.zeros(6), eye))  # duplicate state
    out = []
    out += sync.push(_profile("S1", 0.6, 1, [[0, 80], [np.nan, np.nan], [1, 80]]))  # 1 NaN pt
    out += sync.push(_profile("S1", 0.7, 2, np.zeros((0, 2))))  # empty
    out += sync.push(_profile("S1", 0.8, 3, [[0, 80]], valid=np.zeros(1, bool)))  # all invalid
    out += sync.push(_profile("S1", 0.9, 1, [[0, 80]]))  # duplicate counter
    out += sync.push(_profile("S2", 0.9, 9, [[0, 80]]))  # unknown sensor
    out += sync.push(_profile("S1", 0.3, 4, [[0, 80]]))  # 0.7 s behind the newest: late
    out += sync.push("not a message")
    out += sync.push(_profile("S1", 1.2, 5, [[0, 80]]))  # after the last pose: pose gap
    out += sync.flush()
    assert len(out) == 1 and out[0].xz_S.shape == (2, 2)
    assert dict(sync.dropped) == {"duplicate_state": 1, "nan_points": 1, "empty_profile": 2,
                                  "duplicate_counter": 1, "unknown_sensor": 1,
                                  "late_message": 1, "bad_message": 1, "pose_gap": 1}


def test_a_layer_mark_waits_for_every_profiler_to_pass_it():
    """Robot states (and the marks they carry) arrive over one link, profiles over others: a
    profile stamped before the mark that arrives after it still ends the old layer, as it does
    when the stream comes in stamp order; a silent profiler holds the mark for the window only."""
    eye = np.eye(4)
    sync = StreamSync(["S1", "S2"], max_pose_gap_s=0.05, reorder_window_s=0.5)
    out = []
    for k in range(21):  # poses to 0.2 s, then the mark at 0.1 s, all ahead of the profiles
        out += sync.push(RobotState(0.01 * k, k, np.zeros(6), eye))
    out += sync.push(_profile("S1", 0.05, 1, [[0, 80]]))
    out += sync.push(_profile("S2", 0.06, 1, [[0, 80]]))
    out += sync.push(LayerMark(0.1, 1))
    out += sync.push(_profile("S1", 0.08, 2, [[0, 80]]))  # before the mark, arrives after it
    out += sync.push(_profile("S1", 0.12, 3, [[0, 80]]))
    assert [type(m).__name__ for m in out] == ["SyncedProfile"] * 3  # S2 not past 0.1 s yet
    out += sync.push(_profile("S2", 0.09, 2, [[0, 80]]))
    out += sync.push(_profile("S2", 0.11, 3, [[0, 80]]))
    order = [m.layer if isinstance(m, LayerMark) else m.profile.stamp_s for m in out]
    assert order == [0.05, 0.06, 0.08, 0.09, 1, 0.11, 0.12]
    # a profiler that falls silent holds the next mark until the window has passed it
    assert sync.push(LayerMark(0.15, 2)) == []
    released_at = []
    for k in range(21, 70):
        out = sync.push(RobotState(0.01 * k, k, np.zeros(6), eye))
        if k == 30:
            out += sync.push(_profile("S1", 0.3, 4, [[0, 80]]))
        released_at += [(k, m.layer) for m in out if isinstance(m, LayerMark)]
    assert released_at == [(65, 2)]  # the newest stamp 0.65 s is the window past 0.15 s
    assert sync.dropped == {}


@pytest.fixture(scope="module")
def run():
    cal = make_calibration()
    scene = Scene(boxes=[((50, 50, 0), (66, 66, 6))])
    msgs, _ = raster_run(scene, cal, [((40, 58, 0), (80, 58, 0))], step_mm=1.0, seed=5)
    return cal, msgs


def _fused(cal, msgs, cfg=MonitorConfig()):
    mon = TsdfFusion(cal, cfg, ProcessConfig())
    mon.feed_all(msgs)
    mon.finish()
    return mon


def test_bad_stream_never_crashes_and_counts_exactly(run):
    cal, msgs = run
    profiles = [m for m in msgs if isinstance(m, Profile)]
    rng = np.random.default_rng(6)
    bad = list(msgs)
    # poses missing for a stretch: remove robot states in [1.0, 1.6) s
    bad = [m for m in bad if not (isinstance(m, RobotState) and 1.0 <= m.stamp_s < 1.6)]
    kept = np.array([m.stamp_s for m in bad if isinstance(m, RobotState)])
    s_a, s_b = kept[kept < 1.0].max(), kept[kept >= 1.6].min()
    in_gap = sum(1 for p in profiles if s_a < p.stamp_s < s_b)
    assert in_gap > 10
    # NaN points flagged valid in three profiles (7 points each)
    nan_ids = [id(p) for p in profiles[2:5]]
    for i, m in enumerate(bad):
        if id(m) in nan_ids:
            xz = m.xz_S.copy()
            xz[rng.choice(np.flatnonzero(m.valid), 7, replace=False)] = np.nan
            bad[i] = Profile(m.sensor_id, m.stamp_s, m.counter, xz, m.valid, m.intensity)
    # duplicated messages: four profiles and five robot states sent twice
    dup_p = [profiles[k] for k in (10, 20, 30, 40)]
    dup_s = [m for m in bad if isinstance(m, RobotState)][100:105]
    for m in dup_p + dup_s:
        bad.insert(bad.index(m) + 1, m)
    # two empty profiles with fresh counters
    bad.insert(50, _profile("S2", bad[50].stamp_s, 77777, np.zeros((0, 2))))
    bad.insert(90, _profile("S3", bad[90].stamp_s, 77778, [[1, 90]], np.zeros(1, bool)))
    mon = _fused(cal, bad)
    nan_profile_in_gap = sum(1 for p in profiles[2:5] if s_a < p.stamp_s < s_b)
    assert nan_profile_in_gap == 0
    assert input_drops(mon.dropped) == {"nan_points": 21, "duplicate_counter": 4,
                                        "duplicate_state": 5, "empty_profile": 2,
                                        "pose_gap": in_gap}
    assert mon.profiles_fused == len(profiles) - in_gap
    assert mon.layer_done[0].surface.n_faces > 1000


def test_late_messages_within_the_window_are_reordered(run):
    cal, msgs = run
    ordered = _fused(cal, msgs)
    rng = np.random.default_rng(7)
    jitter = np.array([m.stamp_s for m in msgs]) + rng.uniform(0, 0.3, len(msgs))
    shuffled = [msgs[i] for i in np.argsort(jitter, kind="stable")]
    assert shuffled != msgs
    mon = _fused(cal, shuffled)
    assert input_drops(mon.dropped) == {} and mon.points_fused == ordered.points_fused
    a, b = ordered.surface(0), mon.surface(0)
    assert abs(a.n_vertices - b.n_vertices) <= 0.01 * a.n_vertices
    np.testing.assert_allclose(np.sort(a.vertices_O[:, 2]).mean(),
                               np.sort(b.vertices_O[:, 2]).mean(), atol=0.01)
    # the same jitter beyond the window drops messages as late instead
    late = [msgs[i] for i in np.argsort(np.array([m.stamp_s for m in msgs]) +
                                        rng.uniform(0, 2.0, len(msgs)), kind="stable")]
    mon_late = _fused(cal, late, MonitorConfig(reorder_window_s=0.2))
    assert mon_late.dropped.get("late_message", 0) > 0


def test_monitor_rejects_an_empty_calibration():
    with pytest.raises(ValueError, match="T_B_S"):
        TsdfFusion(Calibration({}, np.eye(4), np.eye(4)), MonitorConfig(), ProcessConfig())
