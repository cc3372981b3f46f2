"""ABB EGM decoding: round trip, tm wrap, layer marks, bad datagrams counted exactly, fuzz."""

import socket
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dm2.core.frames import from_euler_deg
from dm2.core.messages import LayerMark, RobotState
from dm2.live import egm_pb2
from dm2.live.egm_source import (
    EgmDecodeError,
    EgmDecoder,
    EgmSource,
    TmUnwrapper,
    encode_egm_robot,
)
from dm2.live.inbox import Inbox

JOINTS = np.radians([10.0, -20.0, 30.0, 5.0, -64.0, 170.0])
T = from_euler_deg([1712.5, -33.25, 1021.0], [12.0, -40.0, 175.0])


def test_round_trip_recovers_pose_joints_and_stamp():
    data = encode_egm_robot(7, 123456, JOINTS, T, stamp_s=12.345678, layer=3)
    mark, state = EgmDecoder().decode(data)
    assert isinstance(mark, LayerMark) and mark.layer == 3 and mark.stamp_s == state.stamp_s
    assert isinstance(state, RobotState) and state.seq == 7
    assert state.stamp_s == pytest.approx(12.345678, abs=1e-9)
    np.testing.assert_allclose(state.joints_rad, JOINTS, atol=1e-12)
    np.testing.assert_allclose(state.T_B_F, T, atol=1e-9)


def test_layer_mark_only_on_change():
    dec = EgmDecoder()
    kinds = []
    for i, layer in enumerate([0, 0, 1, 1, 1, 2]):
        kinds.append([type(m).__name__ for m in dec.decode(
            encode_egm_robot(i, i * 4, JOINTS, T, stamp_s=i * 0.004, layer=layer))])
    assert [k.count("LayerMark") for k in kinds] == [1, 0, 1, 0, 0, 1]


def test_tm_wrap_keeps_stamps_increasing_without_feedback_time():
    dec = EgmDecoder()
    tm0 = (1 << 32) - 8  # 8 ms before the uint32 millisecond counter wraps
    stamps = [dec.decode(encode_egm_robot(i, tm0 + 4 * i, JOINTS, T))[-1].stamp_s
              for i in range(6)]
    np.testing.assert_allclose(np.diff(stamps), 0.004, atol=1e-9)
    assert stamps[0] == pytest.approx(tm0 / 1000.0)


def test_tm_unwrapper_places_late_datagram_before_the_wrap():
    u = TmUnwrapper()
    m = 1 << 32
    assert u(m - 4) == pytest.approx((m - 4) / 1000)
    assert u(4) == pytest.approx((m + 4) / 1000)  # wrapped
    assert u(m - 8) == pytest.approx((m - 8) / 1000)  # late, from before the wrap
    assert u(8) == pytest.approx((m + 8) / 1000)


@pytest.mark.parametrize("data", [
    b"\xff\xff\xff",  # not protobuf
    egm_pb2.EgmRobot().SerializeToString(),  # no header
])
def test_malformed_raises_decode_error(data):
    with pytest.raises(EgmDecodeError):
        EgmDecoder().decode(data)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_joint_is_malformed(bad):
    joints = JOINTS.copy()
    joints[4] = bad
    with pytest.raises(EgmDecodeError, match="joints: non-finite"):
        EgmDecoder().decode(encode_egm_robot(1, 4, joints, T))


def test_decoded_state_equals_a_validated_one():
    state = EgmDecoder().decode(encode_egm_robot(9, 36, JOINTS, T, stamp_s=2.5))[-1]
    ref = RobotState(state.stamp_s, state.seq, state.joints_rad.copy(), state.T_B_F.copy())
    assert type(state.stamp_s) is float and type(state.seq) is int and state.seq == 9
    for name in ("joints_rad", "T_B_F"):
        a, b = getattr(state, name), getattr(ref, name)
        assert a.dtype == b.dtype and a.shape == b.shape and a.flags.c_contiguous
        assert not a.flags.writeable
        np.testing.assert_array_equal(a, b)


def test_non_unit_quaternion_is_malformed():
    msg = egm_pb2.EgmRobot()
    msg.ParseFromString(encode_egm_robot(1, 4, JOINTS, T))
    o = msg.feedBack.cartesian.orient
    o.u0, o.u1, o.u2, o.u3 = 1.5 * o.u0, 1.5 * o.u1, 1.5 * o.u2, 1.5 * o.u3
    with pytest.raises(EgmDecodeError, match="unit quaternion"):
        EgmDecoder().decode(msg.SerializeToString())


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_fuzz_decoder_only_raises_decode_error(data):
    try:
        out = EgmDecoder().decode(data)
    except EgmDecodeError:
        return
    assert isinstance(out[-1], RobotState)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 300), st.integers(0, 255))
def test_fuzz_mutated_valid_datagram(pos, value):
    data = bytearray(encode_egm_robot(3, 12, JOINTS, T, stamp_s=1.0, layer=1))
    data[pos % len(data)] = value
    try:
        EgmDecoder().decode(bytes(data))
    except EgmDecodeError:
        pass


def test_source_counts_each_bad_datagram_class_exactly():
    inbox = Inbox(100)
    src = EgmSource(inbox, "127.0.0.1", 0, controllers=("127.0.0.1",), max_datagram_bytes=512)
    try:
        good = encode_egm_robot(1, 4, JOINTS, T, stamp_s=0.004)
        src.handle_datagram(good, "127.0.0.1")
        src.handle_datagram(b"\x08\x96\x01garbage", "127.0.0.1")
        src.handle_datagram(b"x" * 513, "127.0.0.1")
        src.handle_datagram(good, "10.0.0.9")
        src.handle_datagram(good, "10.0.0.9")
    finally:
        src.close()
    assert inbox.dropped == {"malformed_egm": 1, "oversized_datagram": 1, "foreign_sender": 2}
    assert inbox.accepted == 1


def test_udp_loopback_filters_foreign_sender_and_oversize():
    inbox = Inbox(100)
    with EgmSource(inbox, "127.0.0.1", 0, controllers=("127.0.0.1",),
                   max_datagram_bytes=600) as src:
        ok = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        foreign = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        foreign.bind(("127.0.0.2", 0))
        try:
            for i in range(5):
                ok.sendto(encode_egm_robot(i, 4 * i, JOINTS, T, stamp_s=0.004 * i), src.address)
            foreign.sendto(encode_egm_robot(9, 40, JOINTS, T), src.address)
            ok.sendto(b"\x00" * 1000, src.address)
            deadline = time.monotonic() + 5.0
            while inbox.accepted + sum(inbox.dropped.values()) < 7 and \
                    time.monotonic() < deadline:
                time.sleep(0.01)
        finally:
            ok.close()
            foreign.close()
    assert inbox.accepted == 5
    assert inbox.dropped == {"foreign_sender": 1, "oversized_datagram": 1}
    seqs = [inbox.get(0)[0].seq for _ in range(5)]
    assert seqs == [0, 1, 2, 3, 4]
