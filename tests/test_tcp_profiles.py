"""TCP profile protocol: round trip, stream parser drop counts, fuzz, server reconnects."""

import socket
import struct
import time

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from dm2.core.messages import COUNTER_MODULO, Profile
from dm2.live.inbox import Inbox
from dm2.live.tcp_frames import FrameParser, decode_body, encode_frame
from dm2.live.tcp_profiles import ProfileClient, ProfileServer


def profile(k: int, n: int = 50, sensor: str = "S1") -> Profile:
    rng = np.random.default_rng(k)
    xz = np.column_stack([np.linspace(-20, 20, n), 90 + rng.normal(0, 0.5, n)])
    valid = np.ones(n, bool)
    valid[::7] = False
    xz[~valid] = np.nan
    return Profile(sensor, 10.0 + 0.1 * k, k % COUNTER_MODULO, xz, valid,
                   rng.uniform(0, 1, n).astype(np.float32))


def test_round_trip_to_float32_precision():
    p = profile(3, sensor="S3")
    q = decode_body(encode_frame(p)[4:-4])
    assert (q.sensor_id, q.counter, q.stamp_s) == ("S3", 3, p.stamp_s)
    np.testing.assert_array_equal(q.valid, p.valid)
    np.testing.assert_allclose(q.xz_S[q.valid], p.xz_S[p.valid], atol=1e-5)
    np.testing.assert_allclose(q.intensity, p.intensity, atol=1 / 65535)


def test_any_chunking_gives_all_profiles():
    frames = [encode_frame(profile(k)) for k in range(6)]
    stream = b"".join(frames)
    rng = np.random.default_rng(0)
    cuts = np.sort(rng.choice(len(stream), 40, replace=False))
    parser = FrameParser()
    got = []
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(stream)], strict=True):
        got += parser.feed(stream[a:b])
    assert [p.counter for p in got] == list(range(6)) and parser.dropped == {}


def test_each_bad_frame_class_counted_exactly():
    f = [encode_frame(profile(k)) for k in range(8)]
    cut = f[1][: len(f[1]) // 2]  # truncated: the next frame follows
    flipped = bytearray(f[3])
    flipped[40] ^= 0xFF  # CRC mismatch
    oversized = struct.pack("<I", 10_000_000) + f[4][4:]
    bad_counter = bytearray(f[5])
    body = bytearray(bad_counter[4:-4])
    body[8:12] = struct.pack("<I", COUNTER_MODULO + 5)
    import zlib
    bad_counter = bytes(bad_counter[:4]) + bytes(body) + struct.pack("<I", zlib.crc32(body))
    stream = f[0] + cut + f[2] + bytes(flipped) + oversized + bad_counter + f[6] + f[7][:30]
    parser = FrameParser(max_frame_bytes=4096)
    got = parser.feed(stream)
    parser.close()
    assert [p.counter for p in got] == [0, 2, 6]
    assert parser.dropped == {"truncated_frame": 2, "corrupt_frame": 1, "oversized_frame": 1,
                              "bad_frame_field": 1}


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2000))
def test_fuzz_random_bytes_never_raise(data):
    parser = FrameParser(max_frame_bytes=2048)
    out = parser.feed(data)
    parser.close()
    assert all(isinstance(p, Profile) for p in out)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 1500), st.integers(0, 255)), max_size=6),
       st.integers(1, 700))
def test_fuzz_mutations_keep_untouched_frames(mutations, chunk):
    frames = [encode_frame(profile(k, n=20)) for k in range(5)]
    stream = bytearray(b"".join(frames))
    hit = set()
    for pos, val in mutations:
        pos %= len(stream)
        if stream[pos] != val:
            stream[pos] = val
            hit.add(pos // len(frames[0]))
    parser = FrameParser(max_frame_bytes=4096)
    got = []
    for a in range(0, len(stream), chunk):
        got += parser.feed(bytes(stream[a:a + chunk]))
    parser.close()
    intact = {k for k in range(5) if k not in hit}
    assert intact <= {p.counter for p in got}


def _wait(cond, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.01)


def test_server_survives_dropped_connection_and_reconnect_and_foreign_peer():
    inbox = Inbox(1000)
    with ProfileServer(inbox, "127.0.0.1", 0, bridges=("127.0.0.1",)) as server:
        host, port = server.address
        client = ProfileClient(host, port)
        for k in range(3):
            client.send(profile(k))
        client.send_bytes(encode_frame(profile(3))[:25])  # cut off by the dropped link
        client.drop_connection()
        for k in range(4, 7):
            client.send(profile(k))  # reconnects
        foreign = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        foreign.bind(("127.0.0.2", 0))
        foreign.connect((host, port))
        foreign.sendall(encode_frame(profile(9)))
        _wait(lambda: inbox.accepted >= 6 and "foreign_sender" in inbox.dropped)
        client.close()
        foreign.close()
        _wait(lambda: server.disconnects >= 2)
    got = sorted(inbox.get(0)[0].counter for _ in range(inbox.qsize()))
    assert got == [0, 1, 2, 4, 5, 6]
    assert inbox.dropped == {"truncated_frame": 1, "foreign_sender": 1}
    assert server.connections == 2


def test_full_queue_counts_queue_full():
    inbox = Inbox(2)
    parser_out = [profile(k) for k in range(5)]
    for p in parser_out:
        inbox.put(p, "profiles", 0.0)
    assert inbox.accepted == 2 and inbox.dropped == {"queue_full": 3}


def test_eight_idle_connections_do_not_block_the_bridge(monkeypatch):
    """Eight local connections that never send a frame hold every slot; the real bridge that
    connects next replaces the one idle the longest and all its profiles arrive."""
    import dm2.live.tcp_profiles as tp

    monkeypatch.setattr(tp, "EVICT_IDLE_S", 0.2)
    inbox = Inbox(1000)
    with ProfileServer(inbox, "127.0.0.1", 0, max_connections=8, idle_timeout_s=0) as server:
        host, port = server.address
        idle = [socket.create_connection((host, port)) for _ in range(8)]
        _wait(lambda: server.connections == 8)
        time.sleep(0.3)
        bridge = ProfileClient(host, port)
        for k in range(5):
            bridge.send(profile(k))
        _wait(lambda: inbox.accepted >= 5)
        assert inbox.accepted == 5
        assert inbox.dropped == {"idle_connection": 1}
        bridge.close()
        for c in idle:
            c.close()
    got = sorted(inbox.get(0)[0].counter for _ in range(inbox.qsize()))
    assert got == [0, 1, 2, 3, 4]


def test_busy_connections_keep_their_slot_and_idle_ones_time_out():
    inbox = Inbox(1000)
    with ProfileServer(inbox, "127.0.0.1", 0, max_connections=1, idle_timeout_s=0.3) as server:
        host, port = server.address
        busy = ProfileClient(host, port)
        busy.send(profile(0))
        _wait(lambda: inbox.accepted == 1)
        late = socket.create_connection((host, port))  # the busy one keeps the only slot
        _wait(lambda: "connection_limit" in inbox.dropped)
        late.close()
        _wait(lambda: server.disconnects >= 1, timeout=3.0)  # 0.3 s without a frame
        assert inbox.dropped == {"connection_limit": 1, "idle_connection": 1}
        busy.close()


def test_frame_drops_are_reported_while_the_connection_is_open():
    inbox = Inbox(1000)
    with ProfileServer(inbox, "127.0.0.1", 0) as server:
        host, port = server.address
        client = ProfileClient(host, port)
        bad = bytearray(encode_frame(profile(1)))
        bad[-1] ^= 0xFF  # CRC mismatch
        client.send_bytes(bytes(bad))
        client.send(profile(2))
        _wait(lambda: inbox.accepted == 1 and inbox.dropped)
        assert server.disconnects == 0
        assert sum(inbox.dropped.values()) == 1 and inbox.accepted == 1
        client.close()


def test_a_bridge_closed_for_idling_reconnects_without_losing_its_next_frame():
    inbox = Inbox(1000)
    with ProfileServer(inbox, "127.0.0.1", 0, idle_timeout_s=0.3) as server:
        client = ProfileClient(*server.address)
        client.connect()
        _wait(lambda: server.disconnects >= 1, timeout=3.0)  # closed: no frame for 0.3 s
        time.sleep(1.1)
        for k in range(3):
            client.send(profile(k))
        _wait(lambda: inbox.accepted >= 3)
        client.close()
    assert inbox.accepted == 3 and inbox.dropped == {"idle_connection": 1}
    assert server.connections == 2
