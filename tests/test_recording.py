"""Recordings: MCAP written by dm2 reads back identical through dm2 and through mcap_ros2."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from mcap.reader import make_reader

from dm2.core.calibration_io import calibration_to_toml
from dm2.core.frames import from_euler_deg, from_quat_abb
from dm2.core.messages import Calibration, LayerMark, MessageError, Profile, RobotState
from dm2.io.recording import read_recording
from dm2.io.recording_writer import RecordingWriter

N_POINTS = 640
DURATION_S = 4.0
ROBOT_HZ = 250.0


def _calibration() -> Calibration:
    return Calibration(
        T_B_S={sid: from_euler_deg([1200.0 + 10 * k, -50.0 * k, 980.5], [30.0 * k, 55.0, 5.0])
               for k, sid in enumerate(("S1", "S2", "S3"))},
        T_F_O=from_euler_deg([-60.0, -60.0, 150.0], [0.0, 0.0, 0.0]),
        T_B_N=from_quat_abb([1300.0, 0.0, 900.0], [0.0, 1.0, 0.0, 0.0]))


def _stream(seed: int = 3):
    """Profiles (3 x 10 Hz, cascaded), robot states at 250 Hz and two layer marks."""
    rng = np.random.default_rng(seed)
    msgs = []
    for k in range(int(DURATION_S * 10)):
        for j, sid in enumerate(("S1", "S2", "S3")):
            x = np.linspace(-25.0, 25.0, N_POINTS) + rng.normal(0, 0.01, N_POINTS)
            z = 95.0 + rng.normal(0, 3.0, N_POINTS)
            valid = rng.random(N_POINTS) > 0.1
            xz = np.column_stack([x, z])
            xz[~valid] = np.nan
            counter = (16_777_200 + 7 * k + j) % (1 << 24)  # wraps the 24-bit counter
            msgs.append(Profile(sid, 0.1 * k + 0.02 * j + 1e-9 * k, counter, xz, valid,
                                rng.random(N_POINTS).astype(np.float32)))
    for i in range(int(DURATION_S * ROBOT_HZ)):
        T = from_euler_deg(rng.normal([1250.0, 30.0, 700.0], 40.0), rng.normal(0, 40.0, 3))
        msgs.append(RobotState(i / ROBOT_HZ, 4_000_000_000 + i, rng.normal(0, 1.0, 6), T))
    msgs += [LayerMark(0.0, 0), LayerMark(2.004, 1)]
    msgs.sort(key=lambda m: m.stamp_s)
    return msgs


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    msgs = _stream()
    cal = _calibration()
    attachments = {"scenario.toml": b'name = "demo"\nseed = 7\n', "notes.bin": bytes(range(256))}
    with RecordingWriter(path, attachments=attachments) as w:
        w.write_static_tf(cal)
        for m in msgs:
            w.write(m)
    return path, msgs, cal, attachments


def _key(m):
    return (type(m).__name__, getattr(m, "sensor_id", ""), round(m.stamp_s * 1e9))


def test_round_trip_through_dm2_reader(recorded):
    path, msgs, _, _ = recorded
    assert not path.with_name(path.name + ".part").exists()
    rec = read_recording(path)
    back = list(rec.messages())
    assert rec.skipped == {}
    assert len(back) == len(msgs)
    stamps = [m.stamp_s for m in back]
    assert stamps == sorted(stamps)
    originals = {_key(m): m for m in msgs}
    for b in back:
        m = originals[_key(b)]
        assert abs(b.stamp_s - m.stamp_s) < 1e-9  # 1 ns
        if isinstance(m, Profile):
            assert b.counter == m.counter
            assert np.array_equal(b.valid, m.valid)
            assert np.all(np.isnan(b.xz_S[~b.valid]))
            # float32 metres -> float64 mm: relative error of float32 rounding
            np.testing.assert_allclose(b.xz_S[b.valid], m.xz_S[m.valid], rtol=1.2e-7, atol=0)
            np.testing.assert_array_equal(b.intensity, m.intensity)
        elif isinstance(m, RobotState):
            assert b.seq == m.seq
            np.testing.assert_array_equal(b.joints_rad, m.joints_rad)
            np.testing.assert_allclose(b.T_B_F, m.T_B_F, rtol=0, atol=1e-9)
        else:
            assert b.layer == m.layer


def test_independent_ros2_reader_sees_frames_and_metres(recorded):
    with warnings.catch_warnings():  # the module warns about itself on import
        warnings.simplefilter("ignore", DeprecationWarning)
        from mcap_ros2.reader import read_ros2_messages
    path, msgs, cal, _ = recorded
    profiles = {(m.sensor_id, round(m.stamp_s * 1e9)): m for m in msgs if isinstance(m, Profile)}
    states = {round(m.stamp_s * 1e9): m for m in msgs if isinstance(m, RobotState)}
    seen = {"scan": 0, "joints": 0, "tf": 0, "static": 0, "layer": 0}
    for rm in read_ros2_messages(str(path)):
        msg, topic = rm.ros_msg, rm.channel.topic
        if topic.startswith("/scan/"):
            sid = topic.split("/")[-1]
            assert rm.schema.name == "sensor_msgs/msg/PointCloud2"
            assert msg.header.frame_id == sid
            ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            assert ns == rm.log_time_ns
            p = profiles[(sid, ns)]
            assert rm.sequence_count == p.counter
            assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity"]
            assert all(f.datatype == 7 and f.count == 1 for f in msg.fields)
            assert (msg.height, msg.width, msg.point_step) == (1, N_POINTS, 16)
            assert not msg.is_bigendian and not msg.is_dense
            pts = np.frombuffer(bytes(msg.data), dtype="<f4").reshape(-1, 4)
            ok = np.isfinite(pts[:, 0])
            assert np.array_equal(ok, p.valid)
            assert np.all(pts[ok, 1] == 0.0)  # the laser plane y_S = 0
            np.testing.assert_allclose(pts[ok][:, [0, 2]], p.xz_S[p.valid] / 1000.0, rtol=1e-7)
            assert 0.090 < np.median(pts[ok, 2]) < 0.100  # ~95 mm range, in metres
            seen["scan"] += 1
        elif topic == "/joint_states":
            ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            s = states[ns]
            assert list(msg.name) == [f"joint_{i}" for i in range(1, 7)]
            np.testing.assert_array_equal(msg.position, s.joints_rad)
            assert rm.sequence_count == s.seq
            seen["joints"] += 1
        elif topic == "/tf":
            (tf,) = msg.transforms
            assert (tf.header.frame_id, tf.child_frame_id) == ("B", "F")
            ns = tf.header.stamp.sec * 1_000_000_000 + tf.header.stamp.nanosec
            t = tf.transform.translation
            np.testing.assert_allclose([t.x, t.y, t.z], states[ns].T_B_F[:3, 3] / 1000.0,
                                       rtol=1e-12)
            seen["tf"] += 1
        elif topic == "/tf_static":
            pairs = {(tf.header.frame_id, tf.child_frame_id): tf for tf in msg.transforms}
            assert set(pairs) == {("B", "N"), ("B", "S1"), ("B", "S2"), ("B", "S3"), ("F", "O")}
            t, q = pairs[("B", "N")].transform.translation, pairs[("B", "N")].transform.rotation
            np.testing.assert_allclose([t.x, t.y, t.z], [1.3, 0.0, 0.9], atol=1e-12)
            np.testing.assert_allclose(abs(q.x), 1.0, atol=1e-12)  # 180 deg about x
            seen["static"] += 1
        elif topic == "/dm2/layer":
            assert msg.layer in (0, 1)
            seen["layer"] += 1
    n_prof = sum(isinstance(m, Profile) for m in msgs)
    assert seen == {"scan": n_prof, "joints": len(states), "tf": len(states), "static": 1,
                    "layer": 2}


def test_attachments_and_calibration_round_trip(recorded):
    path, _, cal, attachments = recorded
    rec = read_recording(path)
    assert rec.attachments["notes.bin"] == attachments["notes.bin"]
    assert rec.scenario_toml == attachments["scenario.toml"].decode()
    assert rec.attachments["calibration.toml"].decode() == calibration_to_toml(cal)
    for got in (rec.calibration, rec.static_calibration()):
        for sid in ("S1", "S2", "S3"):
            np.testing.assert_allclose(got.T_B_S[sid], cal.T_B_S[sid], atol=1e-9)
        np.testing.assert_allclose(got.T_B_N, cal.T_B_N, atol=1e-9)
        np.testing.assert_allclose(got.T_F_O, cal.T_F_O, atol=1e-9)
    assert rec.toolpath is None


def test_chunks_hold_about_one_second(recorded):
    path, *_ = recorded
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    spans = [(c.message_end_time - c.message_start_time) / 1e9 for c in chunks]
    assert len(chunks) >= DURATION_S - 1
    assert max(spans) < 1.0
    assert np.median(spans) > 0.9


def test_truncated_recording_loses_only_the_tail(recorded, tmp_path):
    path, msgs, *_ = recorded
    data = path.read_bytes()
    cut = tmp_path / "crashed.mcap.part"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    rec = read_recording(cut)
    assert not rec.complete
    assert rec.scenario_toml is not None  # attachments are written first
    back = list(rec.messages())
    # ~60 % of a 4 s file survives; at most about a chunk (1 s) beyond the cut is lost
    assert 0.3 * len(msgs) < len(back) < 0.65 * len(msgs)
    originals = {_key(m): m for m in msgs}
    assert all(_key(b) in originals for b in back)


def test_bad_input_errors(tmp_path):
    with pytest.raises(MessageError, match="stamp"):
        with RecordingWriter(tmp_path / "neg.mcap") as w:
            w.write_layer_mark(LayerMark(-1.0, 0))
    assert not (tmp_path / "neg.mcap").exists()
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(ValueError, match="junk.mcap"):
        read_recording(junk)
    with pytest.raises(FileNotFoundError, match="missing.mcap"):
        read_recording(tmp_path / "missing.mcap")
