"""Batched UDP reads: every queued datagram comes back once, in order, with its sender's
address; datagrams longer than the buffer come back cut to it (so the caller sees them as too
large); the portable one-by-one path gives the same answer."""

import socket
import time

import pytest

from dm2.live import udp_batch
from dm2.live.udp_batch import DatagramBatch


@pytest.fixture
def sockets():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.1)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    foreign = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    foreign.bind(("127.0.0.2", 0))
    yield rx, tx, foreign
    for s in (rx, tx, foreign):
        s.close()


def _send_burst(rx, tx, foreign):
    for i in range(10):
        tx.sendto(bytes([i]) * (i + 3), rx.getsockname())
    foreign.sendto(b"from elsewhere", rx.getsockname())
    time.sleep(0.05)  # loopback delivers at once; leave it time all the same


@pytest.mark.parametrize("portable", [False, True])
def test_takes_every_queued_datagram_once_in_order(sockets, monkeypatch, portable):
    rx, tx, foreign = sockets
    if portable:
        monkeypatch.setattr(udp_batch, "_RECVMMSG", None)
    batch = DatagramBatch(rx, size=9, capacity=4)
    assert batch.take_queued() == []
    _send_burst(rx, tx, foreign)
    got = []
    while chunk := batch.take_queued():
        assert len(chunk) <= 4
        got += chunk
    expect = [(bytes([i]) * min(i + 3, 9), "127.0.0.1") for i in range(10)]
    assert got == expect + [(b"from else", "127.0.0.2")]
    assert batch.take_queued() == []
