"""Read every datagram already queued on a UDP socket in one call, without giving up the GIL.

A Python socket read releases the interpreter lock around the system call, so a reader thread
competing with a busy thread gets the lock back only after a switch interval (5 ms): one
datagram per 5 ms, while the robot controller sends one every 4 ms (every 0.4 ms in a 10x
rehearsal). :class:`DatagramBatch` calls Linux ``recvmmsg`` with ``MSG_DONTWAIT`` through
``ctypes.PyDLL`` (which keeps the lock: the call never blocks), so after one blocking read the
thread takes everything queued since at once. Where ``recvmmsg`` is missing (not Linux) it
falls back to ``recvfrom_into`` calls, one per datagram that ``select`` says is there.
"""

from __future__ import annotations

import ctypes
import select
import socket

MSG_DONTWAIT = 0x40
MSG_TRUNC = 0x20
_ADDR_BYTES = 128  # sockaddr_storage


class _IoVec(ctypes.Structure):
    _fields_ = [("iov_base", ctypes.c_void_p), ("iov_len", ctypes.c_size_t)]


class _MsgHdr(ctypes.Structure):
    _fields_ = [("msg_name", ctypes.c_void_p), ("msg_namelen", ctypes.c_uint32),
                ("msg_iov", ctypes.POINTER(_IoVec)), ("msg_iovlen", ctypes.c_size_t),
                ("msg_control", ctypes.c_void_p), ("msg_controllen", ctypes.c_size_t),
                ("msg_flags", ctypes.c_int)]


class _MMsgHdr(ctypes.Structure):
    _fields_ = [("msg_hdr", _MsgHdr), ("msg_len", ctypes.c_uint)]


def _recvmmsg():
    try:
        fn = ctypes.PyDLL(None).recvmmsg  # PyDLL: the GIL stays held (the call never blocks)
    except (AttributeError, OSError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.POINTER(_MMsgHdr), ctypes.c_uint, ctypes.c_int,
                   ctypes.c_void_p]
    fn.restype = ctypes.c_int
    return fn


_RECVMMSG = _recvmmsg()


class DatagramBatch:
    """Buffers for up to ``capacity`` datagrams of up to ``size`` bytes each (larger ones come
    back cut to ``size`` bytes, so a caller that allows ``size - 1`` bytes sees them as too
    large).

    Parameters
    ----------
    sock : an IPv4 UDP socket
    size : int, bytes kept per datagram
    capacity : int, datagrams taken per call at most
    """

    def __init__(self, sock: socket.socket, size: int, capacity: int = 64):
        self.sock = sock
        self.size = int(size)
        self.capacity = int(capacity)
        self._bufs = ctypes.create_string_buffer(self.size * self.capacity)
        self._names = ctypes.create_string_buffer(_ADDR_BYTES * self.capacity)
        self._iov = (_IoVec * self.capacity)()
        self._msgs = (_MMsgHdr * self.capacity)()
        base = ctypes.addressof(self._bufs)
        names = ctypes.addressof(self._names)
        for i in range(self.capacity):
            self._iov[i].iov_base = base + i * self.size
            self._iov[i].iov_len = self.size
            hdr = self._msgs[i].msg_hdr
            hdr.msg_name = names + i * _ADDR_BYTES
            hdr.msg_iov = ctypes.pointer(self._iov[i])
            hdr.msg_iovlen = 1
        self._fallback = bytearray(self.size)

    def take_queued(self) -> list[tuple[bytes, str]]:
        """``(data, sender ip)`` of the datagrams queued now (at most ``capacity``), without
        waiting; an empty list when none is."""
        if _RECVMMSG is None:
            return self._take_one_by_one()
        for i in range(self.capacity):
            self._msgs[i].msg_hdr.msg_namelen = _ADDR_BYTES
        n = _RECVMMSG(self.sock.fileno(), self._msgs, self.capacity, MSG_DONTWAIT, None)
        out = []
        base, names = ctypes.addressof(self._bufs), ctypes.addressof(self._names)
        for i in range(max(n, 0)):
            length = min(self._msgs[i].msg_len, self.size)
            ip = socket.inet_ntoa(ctypes.string_at(names + i * _ADDR_BYTES + 4, 4))
            out.append((ctypes.string_at(base + i * self.size, length), ip))
        return out

    def _take_one_by_one(self) -> list[tuple[bytes, str]]:
        out = []
        while len(out) < self.capacity and select.select([self.sock], [], [], 0)[0]:
            try:
                n, addr = self.sock.recvfrom_into(self._fallback, self.size)
            except (BlockingIOError, InterruptedError, TimeoutError):
                break
            out.append((bytes(self._fallback[:n]), addr[0]))
        return out
