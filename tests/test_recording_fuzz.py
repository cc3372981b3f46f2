"""Damaged recordings never crash the reader and never return changed data.

200 seeded copies of a small recording, each with one kind of damage (a flipped bit, a run of
random bytes, a truncation), are decoded. Each must either read exactly the original messages
and attachments, or stop at the damage, say so (``input_summary()['complete']`` False) and
return only an unchanged prefix of the original messages. ``dm2 recover`` of each copy never
crashes, never leaves its ``.recovering`` file, and keeps an unchanged prefix.
"""

from __future__ import annotations

import numpy as np
import pytest

from dm2.core.calibration_io import calibration_to_toml
from dm2.core.frames import from_euler_deg
from dm2.core.messages import Calibration, LayerMark, Profile, RobotState
from dm2.io.recording import read_recording
from dm2.io.recording_writer import RecordingWriter
from dm2.live.recover import recover_recording

N_COPIES = 200


def _stream(seed: int = 11):
    rng = np.random.default_rng(seed)
    msgs = []
    for k in range(30):  # 3 s: 10 Hz profiles, 50 Hz robot states
        xz = np.column_stack([np.linspace(-5, 5, 16), 95 + rng.normal(0, 1, 16)])
        msgs.append(Profile("S1", 0.1 * k + 0.01, k + 1, xz, np.ones(16, bool),
                            rng.random(16).astype(np.float32)))
    for i in range(150):
        T = from_euler_deg(rng.normal([1250.0, 30.0, 700.0], 10.0), rng.normal(0, 5.0, 3))
        msgs.append(RobotState(i / 50, i + 1, rng.normal(0, 1.0, 6), T))
    msgs += [LayerMark(0.0, 0), LayerMark(1.5, 1)]
    msgs.sort(key=lambda m: m.stamp_s)
    return msgs


def _key(m):
    """Everything a message carries, as comparable bytes."""
    if isinstance(m, Profile):
        return ("P", m.sensor_id, m.stamp_s, m.counter, np.nan_to_num(m.xz_S, nan=-1).tobytes(),
                m.valid.tobytes(), np.asarray(m.intensity).tobytes())
    if isinstance(m, RobotState):
        return ("R", m.stamp_s, m.seq, m.joints_rad.tobytes(), m.T_B_F.tobytes())
    return ("L", m.stamp_s, m.layer)


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    path = tmp_path_factory.mktemp("fuzz") / "small.mcap"
    cal = Calibration(T_B_S={"S1": from_euler_deg([1200.0, 0.0, 980.0], [0.0, 55.0, 5.0])},
                      T_F_O=np.eye(4), T_B_N=from_euler_deg([1300.0, 0.0, 900.0], [180, 0, 0]))
    msgs = _stream()
    with RecordingWriter(path, attachments={"scenario.toml": b'name = "f"\n'},
                         chunk_s=0.25) as w:
        w.write_static_tf(cal)
        for m in msgs:
            w.write(m)
    rec = read_recording(path)
    keys = [_key(m) for m in rec.messages()]
    # the undamaged file's decode is the reference (poses pass through a quaternion)
    assert len(keys) == len(msgs) and rec.input_summary()["complete"]
    assert rec.attachments["calibration.toml"].decode() == calibration_to_toml(cal)
    return path.read_bytes(), keys, dict(rec.attachments)


def _damage(data: bytes, rng) -> tuple[str, bytes]:
    buf = bytearray(data)
    kind = ("bit", "run", "cut")[int(rng.integers(3))]
    if kind == "bit":
        i = int(rng.integers(len(buf)))
        buf[i] ^= 1 << int(rng.integers(8))
    elif kind == "run":
        i = int(rng.integers(len(buf) - 1))
        n = int(rng.integers(1, 200))
        run = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        buf[i:i + n] = run[: len(buf) - i]
    else:
        del buf[int(rng.integers(8, len(buf))):]
    return kind, bytes(buf)


def _recover_keeps_a_prefix(path, keys, n, kind):
    """`dm2 recover` of a damaged copy: a file whose messages are an unchanged prefix, or a
    ValueError naming the file; never a crash, never a ``.recovering`` file left."""
    out = path.with_name(path.stem + ".fixed.mcap")
    try:
        res = recover_recording(path, out)
    except ValueError as exc:
        assert str(path) in str(exc) and not out.exists(), (n, kind)
        return
    finally:
        assert not out.with_name(out.name + ".recovering").exists(), (n, kind)
    rec = read_recording(out)
    got = [_key(m) for m in rec.messages()]
    assert got == keys[: len(got)], (n, kind, "recovered, but changed")
    assert rec.recovered["intact"] and rec.recovered["complete"] == str(res.complete).lower()
    out.unlink()


def test_damaged_copies_read_exactly_or_stop_at_the_damage(original, tmp_path):
    data, keys, attachments = original
    rng = np.random.default_rng(2026)
    outcomes = {"exact": 0, "stopped": 0, "refused": 0}
    for n in range(N_COPIES):
        kind, bad = _damage(data, rng)
        if bad == data:  # a run of the same bytes: no damage
            continue
        path = tmp_path / f"copy{n}.mcap"
        path.write_bytes(bad)
        try:
            rec = read_recording(path)
        except ValueError as exc:  # only a file that no longer starts as MCAP is refused
            assert "not an MCAP file" in str(exc) and str(path) in str(exc)
            outcomes["refused"] += 1
            continue
        got = [_key(m) for m in rec.messages()]
        info = rec.input_summary()
        for name, blob in rec.attachments.items():  # never a changed attachment
            assert attachments.get(name) == blob, (n, kind, name)
        if info["complete"]:
            assert got == keys, (n, kind, "complete but changed")
            assert rec.attachments == attachments, (n, kind)
            outcomes["exact"] += 1
        else:
            assert got == keys[: len(got)], (n, kind, "stopped, but what it read changed")
            outcomes["stopped"] += 1
        _recover_keeps_a_prefix(path, keys, n, kind)
        path.unlink()
    # the damage mostly falls in the chunks, which must be caught, not read as good
    assert outcomes["stopped"] > outcomes["exact"] > 0, outcomes
