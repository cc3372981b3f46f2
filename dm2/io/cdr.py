"""CDR (XCDR1, little endian) primitives for the ROS 2 messages of dm2 recordings.

:class:`CdrWriter` appends and :class:`CdrReader` reads the fields of one payload with CDR's
alignment (relative to the payload start, after the 4-byte encapsulation header); the message
layouts built from them are in :mod:`dm2.io.ros_messages`.
"""

from __future__ import annotations

import struct

import numpy as np

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little endian


class CdrError(ValueError):
    """A CDR payload does not match the expected layout."""


class CdrWriter:
    """Append-only little-endian CDR buffer (alignment relative to the payload start)."""

    __slots__ = ("buf",)

    def __init__(self):
        self.buf = bytearray(ENCAPSULATION)

    def align(self, n: int) -> None:
        pad = (-(len(self.buf) - 4)) % n
        if pad:
            self.buf += b"\x00" * pad

    def u32(self, v: int) -> None:
        self.align(4)
        self.buf += struct.pack("<I", v)

    def i32(self, v: int) -> None:
        self.align(4)
        self.buf += struct.pack("<i", v)

    def u8(self, v: int) -> None:
        self.buf.append(v)

    def string(self, s: str) -> None:
        b = s.encode()
        self.u32(len(b) + 1)
        self.buf += b + b"\x00"

    def f64s(self, values) -> None:
        self.align(8)
        self.buf += struct.pack(f"<{len(values)}d", *values)

    def time(self, stamp_ns: int) -> None:
        self.align(4)
        self.buf += struct.pack("<iI", *split_ns(stamp_ns))

    def header(self, stamp_ns: int, frame_id: str) -> None:
        self.time(stamp_ns)
        self.string(frame_id)


class CdrReader:
    """Sequential little-endian CDR reader (alignment relative to the payload start); a
    payload that ends early raises :class:`CdrError`."""

    __slots__ = ("data", "pos")

    def __init__(self, data: bytes):
        if len(data) < 4 or data[1] != 1:
            raise CdrError("not a little-endian CDR payload")
        self.data = memoryview(data)
        self.pos = 4

    def align(self, n: int) -> None:
        self.pos += (-(self.pos - 4)) % n

    def _take(self, n: int) -> memoryview:
        if self.pos + n > len(self.data):
            raise CdrError("payload ends early")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def u32(self) -> int:
        self.align(4)
        return struct.unpack("<I", self._take(4))[0]

    def i32(self) -> int:
        self.align(4)
        return struct.unpack("<i", self._take(4))[0]

    def u8(self) -> int:
        return self._take(1)[0]

    def string(self) -> str:
        n = self.u32()
        return bytes(self._take(n)[:-1]).decode() if n else ""

    def f64s(self, n: int) -> np.ndarray:
        if n == 0:
            return np.zeros(0)
        self.align(8)
        return np.frombuffer(self._take(8 * n), dtype="<f8").astype(np.float64)

    def time_ns(self) -> int:
        self.align(4)
        sec, nsec = struct.unpack("<iI", self._take(8))
        return sec * 1_000_000_000 + nsec


def split_ns(stamp_ns: int) -> tuple[int, int]:
    """ROS ``builtin_interfaces/Time`` (sec, nanosec) of a nanosecond stamp."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    if not -(1 << 31) <= sec < (1 << 31):
        raise ValueError(f"stamp {stamp_ns} ns does not fit ROS Time")
    return sec, nsec
